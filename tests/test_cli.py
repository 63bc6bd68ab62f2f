"""The `inseggan` command as a user reads it: the help lists the user's path first and the
research commands apart; `loop --help` shows the user's options, `--help-advanced` the rest;
a loop's options from a recipe file (`--recipe`), the flags over the file's; `ship` puts a
finished run's model and recipe in place; every shipped model has a recipe whose steps are
commands the CLI takes."""
import argparse
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import REPO, refused, run_cli

from inseggan_ros.cli.app import build_parser, main

USER = ["loop", "check", "eval", "simulate", "bag-info", "ship"]
RESEARCH = ["train", "distill", "shape-fit", "self-fit", "head", "centres"]
DATE = re.compile(r"20\d\d-\d\d-\d\d")
# every option `inseggan loop` took before its research options moved behind --help-advanced
LOOP_OPTIONS = [
    "--bag", "--centre-iterations", "--centre-teacher", "--coarse-piles", "--config",
    "--convex-iterations", "--convex-pieces", "--convex-walls", "--data", "--eval-every",
    "--export-settings", "--fine-piles", "--head-iterations", "--held-out", "--instances",
    "--iterations", "--labels-topic", "--lr", "--match-pieces", "--match-piles", "--match-seed",
    "--match-walls", "--model", "--name", "--noise", "--out", "--pile-holes", "--pile-lengths",
    "--pile-offsets", "--pile-radii", "--pile-shafts", "--pile-stretches", "--pile-tapers",
    "--quiet", "--scenes", "--seed", "--self-frames", "--self-iterations", "--self-settings",
    "--size-by-thickness", "--size-keep-length", "--size-rounds", "--spheres", "--topic",
    "--train-iterations", "--train-minutes", "--train-seed", "--user-weight", "--val-scenes",
    "--vote-scales", "--workers"]
ADVANCED = ["--data", "--model", "--scenes", "--iterations", "--centre-iterations",
            "--match-piles", "--pile-lengths", "--convex-pieces", "--size-rounds",
            "--vote-scales", "--labels-topic", "--held-out"]


def _commands() -> dict:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _sections(text: str) -> dict:
    """{section title: [the command names listed under it]} of `inseggan --help`."""
    sections, title = {}, None
    for line in text.splitlines():
        if line and not line.startswith(" ") and line.endswith(":"):
            title = line[:-1]
            sections[title] = []
        elif title and re.match(r"  [a-z-]+ ", line):
            sections[title].append(line.split()[0])
    return sections


def test_the_help_lists_the_users_path_first_and_the_research_commands_apart():
    p = run_cli("--help", check=True, timeout=60)  # the installed entry point
    sections = _sections(p.stdout)
    titles = list(sections)
    assert sections[titles[0]] == USER, sections  # the user's path, in the order of use
    research = [t for t in titles if t.startswith("research commands")]
    assert len(research) == 1 and sections[research[0]] == RESEARCH, sections
    assert not set(RESEARCH) & set(sections[titles[0]])
    listed = [name for names in sections.values() for name in names]
    assert sorted(listed) == sorted(_commands()), "every command listed once"
    assert "bench-sim" not in listed  # tools/bench_sim.py, not the package's
    # no notebook dates in any help text
    for name, sub in _commands().items():
        assert not DATE.search(sub.format_help()), name
    assert not DATE.search(p.stdout)


def test_loop_help_shows_the_users_options_and_the_advanced_help_the_research_ones():
    plain = run_cli("loop", "--help", check=True, timeout=60).stdout
    advanced = run_cli("loop", "--help-advanced", check=True, timeout=60).stdout
    for flag in ("--bag", "--instances", "--out", "--recipe", "--print-recipe",
                 "--help-advanced"):
        assert flag in plain, flag
    for flag in ADVANCED:  # an option's own line (other options' help texts may name it)
        assert not re.search(rf"^  {flag}\b", plain, re.M), flag
        assert re.search(rf"^  {flag}\b", advanced, re.M), flag
    assert "\nadvanced (research) options:\n" in advanced  # the group's title
    assert "\nadvanced (research) options:\n" not in plain
    assert not DATE.search(advanced)
    # every option the loop took keeps its name
    loop = _commands()["loop"]
    names = {s for a in loop._actions for s in a.option_strings}
    assert set(LOOP_OPTIONS) <= names, set(LOOP_OPTIONS) - names


def _print_recipe(*args) -> dict:
    p = run_cli("loop", *args, "--print-recipe", timeout=120)
    assert p.returncode == 0, p.stderr
    return yaml.safe_load(p.stdout)


def _config(recipe: dict) -> dict:
    """A recipe without the commit of the code that resolved it."""
    return {k: v for k, v in recipe.items() if k != "commit"}


def test_a_printed_recipe_read_back_resolves_the_same_and_flags_override_it(tmp):
    first = _print_recipe("--bag", tmp / "bag", "--instances", "4", "--noise", "realsense",
                          "--out", tmp / "run", "--scenes", "16", "--iterations", "0",
                          "--centre-iterations", "20", "--match-piles", "--pile-lengths",
                          "0.1,0.17", "--pile-tapers", "1", "--match-pieces", "1",
                          "--vote-scales", "none", "--size-by-thickness", "off",
                          "--lr", "5e-4")
    assert first["command"] == "loop"
    assert re.fullmatch(r"[0-9a-f]{40}|unknown", first["commit"])
    assert (first["scenes"], first["pile_lengths"], first["vote_scales"],
            first["size_by_thickness"], first["lr"]) == (16, [0.1, 0.17], [], "off", 0.0005)
    assert first["val_scenes"] == 200 and first["data"] is None  # every option, defaults too
    assert first["family_edges"] is False  # the edges' W1 recorded, scored when asked
    assert _print_recipe("--bag", tmp / "bag", "--instances", "4", "--out", tmp / "run",
                         "--family-edges")["family_edges"] is True
    recipe = tmp / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(first))
    assert _config(_print_recipe("--recipe", recipe)) == _config(first)
    # the flags given beside --recipe win
    over = _print_recipe("--recipe", recipe, "--scenes", "40", "--pile-lengths", "0.3,0.5",
                         "--bag", tmp / "bag2", "--out", tmp / "other")
    assert over["scenes"] == 40 and over["out"] == str(tmp / "other")
    assert over["pile_lengths"] == [0.3, 0.5] and over["bag"] == str(tmp / "bag2")
    changed = ("scenes", "out", "pile_lengths", "bag", "commit")
    assert {k: v for k, v in over.items() if k not in changed} \
        == {k: v for k, v in first.items() if k not in changed}
    # a flag turned off over the file's (--no-match-piles), its grid still set: refused, by name
    p = refused("loop", "--recipe", recipe, "--no-match-piles", "--print-recipe")
    assert p.returncode == 2 and "valid: with --match-piles" in p.stderr, p.stderr


@pytest.mark.parametrize("text, message", [
    ("bag: b\ninstances: 4\nout: o\nscenez: 10\n",
     "unknown option scenez; valid: bag, data, instances"),
    ("bag: b\ninstances: four\nout: o\n", "instances 'four' invalid; valid: a whole number"),
    ("bag: b\ninstances: 4\nout: o\ncentre_teacher: teachers\n",
     "centre_teacher 'teachers' invalid; valid: piles, self-labels"),
    ("bag: b\ninstances: 4\nout: o\nmatch_piles: yes please\n",
     "match_piles 'yes please' invalid; valid: true or false"),
    ("bag: b\ninstances: 4\nout: o\nscenes: null\n", "scenes: null invalid; valid: a value"),
    ("bag: b\ninstances: 4\n", "no run directory: give --out DIR"),
    ("command: simulate\ncount: 3\n", "0 `loop` steps (its steps: simulate)"),
    ("steps:\n  - {command: loop, out: a}\n  - {command: loop, out: b}\n", "2 `loop` steps"),
    ("- a list\n", "not a mapping of options"),
])
def test_a_recipe_with_an_unknown_or_bad_option_is_refused_by_name(tmp, text, message):
    recipe = tmp / "bad.yaml"
    recipe.write_text(text)
    p = refused("loop", "--recipe", recipe, "--print-recipe")
    assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert str(recipe) in p.stderr or "--out" in p.stderr


def _run_folder(tmp: Path) -> Path:
    """A finished loop's folder as `ship` takes it: a shipped model as its model/ (a label-free
    card: a recording's), and a recipe the loop resolves."""
    run = tmp / "run"
    shutil.copytree(REPO / "models" / "cylinder_tilted", run / "model")
    recipe = _print_recipe("--bag", tmp / "bag", "--instances", "5", "--out", run,
                           "--name", "cylinder_tilted")
    (run / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    return run


def test_ship_puts_a_runs_model_and_recipe_in_place_whole_and_only_once(tmp):
    from inseggan_ros.evaluation.modelcard import markdown

    run = _run_folder(tmp)
    into, recipes = tmp / "models", tmp / "config" / "recipes"
    p = run_cli("ship", run, "--name", "my_part", "--into", into, timeout=120)
    assert p.returncode == 0, p.stderr
    folder = into / "my_part"
    shipped = sorted(f.name for f in folder.iterdir())
    assert shipped == ["README.md", "card.json", "model.pt", "qualitative.png", "shape.png"]
    assert (folder / "model.pt").read_bytes() == (run / "model" / "model.pt").read_bytes()
    card = json.loads((folder / "card.json").read_text())
    assert card["name"] == "my_part" and (folder / "README.md").read_text() == markdown(card)
    assert "# Model card: my_part" in (folder / "README.md").read_text()
    # the recipe beside the models folder (config/recipes), named for the model; the card
    # stores the same configuration and the code's commit
    written = yaml.safe_load((recipes / "my_part.yaml").read_text())
    source = yaml.safe_load((run / "recipe.yaml").read_text())
    assert written == {**source, "name": "my_part"}
    assert card["recipe"] == {k: v for k, v in written.items() if k not in ("command", "commit")}
    assert card["commit"] == source["commit"]
    assert "**Recipe:**" in (folder / "README.md").read_text()
    # the shipped recipe runs the loop again as it was resolved
    assert _config(_print_recipe("--recipe", recipes / "my_part.yaml")) == _config(written)
    # not twice without --force; nothing left half-written beside it
    stamp = (folder / "card.json").stat().st_mtime_ns
    p = refused("ship", run, "--name", "my_part", "--into", into)
    assert p.returncode == 2 and "exists; valid: another --name, or --force" in p.stderr
    assert (folder / "card.json").stat().st_mtime_ns == stamp
    p = run_cli("ship", run, "--name", "my_part", "--into", into, "--force", timeout=120)
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in into.iterdir()) == ["my_part"]
    assert sorted(f.name for f in recipes.iterdir()) == ["my_part.yaml"]


def test_ship_refuses_a_folder_without_a_model_or_a_recipe_and_a_bad_name(tmp):
    run = _run_folder(tmp)
    p = refused("ship", run, "--name", "../up", "--into", tmp / "models")
    assert p.returncode == 2 and "--name '../up' invalid; valid: letters" in p.stderr
    (run / "recipe.yaml").unlink()
    p = refused("ship", run, "--name", "x", "--into", tmp / "models")
    assert p.returncode == 2 and "recipe.yaml: missing" in p.stderr and "--no-recipe" in p.stderr
    assert not (tmp / "models" / "x").exists()
    p = run_cli("ship", run, "--name", "x", "--into", tmp / "models", "--no-recipe", timeout=120)
    assert p.returncode == 0 and (tmp / "models" / "x" / "model.pt").is_file(), p.stderr
    assert not (tmp / "config").exists()
    p = refused("ship", tmp, "--name", "y", "--into", tmp / "models")
    assert p.returncode == 2 and "model.pt: missing" in p.stderr


def test_every_shipped_model_has_a_recipe_of_commands_the_cli_takes(tmp, capsys):
    """config/recipes/<name>.yaml for each models/<name>: its steps in order, each an
    `inseggan` command whose options parse as its flags (the loop's resolved as `--recipe`
    resolves them), or a `shell:` step."""
    from inseggan_ros.cli.recipes import step_argv
    from inseggan_ros.core import recipe as recipe_file

    parser, commands = build_parser(), _commands()
    models = sorted(p.parent.name for p in (REPO / "models").glob("*/card.json"))
    recipes = sorted(p.stem for p in (REPO / "config" / "recipes").glob("*.yaml"))
    assert recipes == models and len(models) == 14
    for name in models:
        path = REPO / "config" / "recipes" / f"{name}.yaml"
        steps = recipe_file.steps(recipe_file.read(path), path)
        assert "not say enough to rebuild" in path.read_text() or name.endswith("_tilted") \
            and "Exactness" in path.read_text(), name
        shipping = ("loop", "export", "self-fit", "centres", "card-settings")
        assert any(s.get("command") in shipping for s in steps), name
        for k, step in enumerate(steps):
            if "shell" in step:
                assert set(step) == {"shell"} and isinstance(step["shell"], str)
                continue
            command = step["command"]
            assert command in commands, (name, k, command)
            if command == "loop":
                one = tmp / f"{name}_{k}.yaml"
                one.write_text(yaml.safe_dump(step))
                assert main(["loop", "--recipe", str(one), "--print-recipe"]) == 0, (name, k)
                capsys.readouterr()
                continue
            try:
                parser.parse_args([command, *step_argv(commands[command], step, path)])
            except SystemExit:
                pytest.fail(f"{path} step {k} ({command}): {capsys.readouterr().err}")
        assert any(s.get("name") == name for s in steps), name  # the steps ship this model
