"""A recipe file's options read as a command's flags (`core.recipe`): each value converted and
checked by the flag's own type and choices, unknown names refused with the valid ones, and the
command line's flags over the file's."""
from __future__ import annotations

import argparse
from pathlib import Path


class _Unset:
    """The default of an option while its command is parsed: not given on the command line."""

    def __repr__(self) -> str:
        return "unset"


UNSET = _Unset()


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """{name: action} of a command's options and positional arguments (not its help)."""
    return {a.dest: a for a in parser._actions
            if a.dest != argparse.SUPPRESS and a.default != argparse.SUPPRESS}


def defer_defaults(parser: argparse.ArgumentParser, keep=()) -> dict:
    """Every option's default (but those named in `keep`) replaced by UNSET, so that a parse
    tells the flags given from the defaults -> {name: its default}."""
    defaults = {}
    for name, action in options(parser).items():
        if name not in keep:
            defaults[name], action.default = action.default, UNSET
    return defaults


def _text(value) -> str:
    """A YAML value as the command line writes it: a list comma-separated, an empty one none."""
    if isinstance(value, (list, tuple)):
        return ",".join(map(str, value)) if value else "none"
    return str(value)


def convert(action: argparse.Action, name: str, value, where, default=None):
    """A recipe's `name: value` as the flag of `action` reads it. Raises ValueError naming the
    file, the option and what is valid."""
    flag = f"recipe {where}: {name}"
    if value is None:
        if default is None:
            return None
        raise ValueError(f"{flag}: null invalid; valid: a value (default {default!r})")
    if action.nargs == 0:  # a flag alone: --match-piles
        if not isinstance(value, bool):
            raise ValueError(f"{flag} {value!r} invalid; valid: true or false")
        return value
    if isinstance(action, argparse._AppendAction):  # repeatable: a list of values
        return [convert_one(action, name, v, where)
                for v in (value if isinstance(value, list) else [value])]
    return convert_one(action, name, value, where)


def convert_one(action: argparse.Action, name: str, value, where):
    """One value of a recipe's option through the flag's type and choices."""
    flag = f"recipe {where}: {name}"
    if isinstance(value, dict):
        raise ValueError(f"{flag}: a mapping invalid; valid: a value or a list of numbers")
    choices = action.choices
    if isinstance(value, bool) and choices is not None and "on" in choices:
        value = "on" if value else "off"  # YAML reads a bare on / off as true / false
    kinds = {int: "a whole number", float: "a number"}
    try:
        out = action.type(_text(value)) if action.type else _text(value)
    except (argparse.ArgumentTypeError, TypeError, ValueError) as e:
        if action.type in kinds:
            raise ValueError(f"{flag} {value!r} invalid; valid: {kinds[action.type]}") from None
        raise ValueError(f"{flag}: {e}") from None
    if choices is not None and out not in choices:
        raise ValueError(f"{flag} {out!r} invalid; valid: {', '.join(map(str, choices))}")
    return out


def read_options(parser: argparse.ArgumentParser, step: dict, where, defaults: dict | None = None,
                 exclude=()) -> dict:
    """A recipe step's {name: value}, each converted as its flag is (`convert`). Names that are
    not the command's options (or are among `exclude`) are refused with the valid ones.
    `defaults`: the command's defaults where the parser's are deferred (`defer_defaults`)."""
    actions = {k: a for k, a in options(parser).items() if k not in exclude}
    unknown = sorted(set(step) - set(actions))
    if unknown:
        raise ValueError(f"recipe {where}: unknown option{'s' * (len(unknown) > 1)} "
                         f"{', '.join(unknown)}; valid: {', '.join(actions)}")
    defaults = defaults if defaults is not None else {k: a.default for k, a in actions.items()}
    return {k: convert(actions[k], k, v, where, defaults.get(k)) for k, v in step.items()}


def merge(args: argparse.Namespace, defaults: dict, recipe: dict, together=()) -> dict:
    """The resolved options: each the command line's where given there, else the recipe's,
    else its default, in the command's order. `together`: groups of names that go together
    (--bag and --data: the user's frames): where the command line gives one of a group, the
    recipe's values of the whole group are dropped."""
    given = {k: getattr(args, k) for k in defaults if getattr(args, k, UNSET) is not UNSET}
    recipe = dict(recipe)
    for group in together:
        if any(k in given for k in group):
            for k in group:
                recipe.pop(k, None)
    return {k: given[k] if k in given else recipe.get(k, default)
            for k, default in defaults.items()}


def step_argv(parser: argparse.ArgumentParser, step: dict, where) -> list[str]:
    """A recipe step's options (`command` and `commit` left out) as its command's arguments:
    the positional ones in the command's order, then `--flag=value` each (a list
    comma-separated, a repeatable flag repeated, `true` the flag alone, `false` its `--no-`
    form where it has one, null left out). Unknown names are refused with the valid ones."""
    from inseggan_ros.core.recipe import META

    actions = options(parser)
    step = {k: v for k, v in step.items() if k not in META}
    unknown = sorted(set(step) - set(actions))
    if unknown:
        raise ValueError(f"recipe {where}: unknown option{'s' * (len(unknown) > 1)} "
                         f"{', '.join(unknown)}; valid: {', '.join(actions)}")
    positional, flags = [], []
    for name, action in actions.items():
        value = step.get(name)
        if name not in step or value is None:
            continue
        if not action.option_strings:
            positional += [_text(v) for v in value] if isinstance(value, list) else [_text(value)]
        elif action.nargs == 0:
            if not isinstance(value, bool):
                raise ValueError(f"recipe {where}: {name} {value!r} invalid; valid: true or false")
            off = [s for s in action.option_strings if s.startswith("--no-")]
            flags += [action.option_strings[0]] if value is True else off
        elif isinstance(action, argparse._AppendAction):
            flags += [f"{action.option_strings[0]}={_text(v)}"
                      for v in (value if isinstance(value, list) else [value])]
        else:
            flags.append(f"{action.option_strings[0]}={_text(value)}")
    return positional + flags


def shipped_recipe(name: str) -> Path:
    """A recipe path, or the name of a shipped one (config/recipes/<name>.yaml)."""
    from inseggan_ros.core.paths import NotFoundError, shipped_dir

    p = Path(name).expanduser()
    if p.is_file() or "/" in name or name.endswith((".yaml", ".yml")):
        return p
    config = shipped_dir("config")
    folder = config / "recipes" if config else None
    if folder and (folder / f"{name}.yaml").is_file():
        return folder / f"{name}.yaml"
    names = sorted(f.stem for f in folder.glob("*.yaml")) if folder and folder.is_dir() else []
    raise NotFoundError(f"recipe {name!r}: no such file or shipped recipe; shipped: "
                        f"{', '.join(names) or 'none'}")
