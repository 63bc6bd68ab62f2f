"""Recipe files: how a model was made, as YAML that `inseggan loop --recipe FILE` runs again.

A recipe names each option as the command line does, with underscores for dashes (the
project's one name per setting): `--pile-lengths 0.1,0.3` is `pile_lengths: [0.1, 0.3]`,
`--match-piles` is `match_piles: true`. A recipe of one command is a mapping of its options,
with `command` (the `inseggan` subcommand) and, where the file was written by a run, `commit`
(the git commit of the code that ran it, or "unknown"):

    command: loop
    commit: 0123abc...
    bag: runs/tilt/bag41
    instances: 5
    ...

A recipe of several commands (the shipped models': config/recipes/<name>.yaml) lists them as
`steps`, each such a mapping, in the order they ran; a step that is not an `inseggan` command
(copying a file) is `shell: <the command>`, for the reader. No torch or argparse here.
"""
from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

# the keys of a step that are not options of its command
META = ("command", "commit")


def code_commit() -> str:
    """The git commit of this package's code (`git rev-parse HEAD` in its folder), or
    "unknown" where it is not in a git checkout (or git is not installed)."""
    try:
        p = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse",
                            "HEAD"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    commit = p.stdout.strip()
    return commit if p.returncode == 0 and commit else "unknown"


def plain(value):
    """`value` as YAML and JSON write it: paths as text, tuples as lists, in dicts and lists."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def dump(recipe: dict, header: str = "") -> str:
    """The recipe as YAML text (keys in their order, lists on one line), after `header`'s lines
    as comments."""
    import yaml

    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    return comments + yaml.safe_dump(plain(recipe), sort_keys=False, default_flow_style=None,
                                     width=100)


def write(path, recipe: dict, header: str = "") -> Path:
    """`dump(recipe, header)` into `path` atomically: a temporary file beside it, then renamed
    over it, so that a reader finds the old file or the new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(dump(recipe, header))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read(path) -> dict:
    """A recipe file's mapping. Raises ValueError naming the file where it is not one."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"recipe {path}: not a readable YAML file ({e})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"recipe {path}: not a mapping of options (`name: value` lines) or "
                         "of `steps:`")
    return doc


def steps(doc: dict, where) -> list[dict]:
    """The steps of a recipe's mapping: its `steps` list, or the mapping itself (one step)."""
    if "steps" not in doc:
        return [doc]
    if set(doc) - {"steps"} or not isinstance(doc["steps"], list) \
            or not all(isinstance(s, dict) for s in doc["steps"]):
        raise ValueError(f"recipe {where}: `steps:` is a list of mappings (each a command's "
                         "options, with `command:`, or `shell:`), and the file has nothing "
                         "beside it")
    return doc["steps"]


def command_step(doc: dict, command: str, where) -> dict:
    """The options of the one step of `command` in a recipe's mapping (`command` and `commit`
    left out). A single-step recipe without `command:` is taken as `command`'s. Raises
    ValueError where the file has no such step, or several."""
    found = [s for s in steps(doc, where) if s.get("command", command if "steps" not in doc
                                                   else None) == command]
    if len(found) != 1:
        named = [s.get("command") or ("shell" if "shell" in s else "?")
                 for s in steps(doc, where)]
        raise ValueError(f"recipe {where}: {len(found)} `{command}` steps (its steps: "
                         f"{', '.join(map(str, named)) or 'none'}); valid: a recipe of one "
                         f"`{command}` step (copy the step into a file of its own)")
    return {k: v for k, v in found[0].items() if k not in META}
