"""Ship a finished loop's model: RUN/model (model.pt, card.json, pictures) into models/NAME with
the card renamed and its README written again, and the run's resolved recipe (RUN/recipe.yaml)
into config/recipes/NAME.yaml, each written atomically (a temporary folder or file beside the
target, then renamed), an existing one replaced only when asked.

    inseggan ship runs/my_part --name my_part                  # models/my_part, config/recipes
"""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
RECIPE_HEADER = ("The recipe of models/{name}: the `inseggan loop` run that made it, every option "
                 "after defaults,\nwritten by `inseggan ship` from the run's recipe.yaml. "
                 "`inseggan loop --recipe {name}` runs it\nagain (flags given beside --recipe "
                 "override its values).")


def default_recipes(into) -> Path:
    """Where the recipes go by default: config/recipes beside the models folder `into`."""
    return Path(into).resolve().parent / "config" / "recipes"


def _run_parts(run_dir: Path, with_recipe: bool) -> tuple[Path, dict, dict | None]:
    """(RUN/model, its card, the run's recipe or None), each refused by name where missing."""
    from inseggan_ros.core import recipe as recipe_file

    model_dir = run_dir / "model"
    for f in ("model.pt", "card.json"):
        if not (model_dir / f).is_file():
            raise FileNotFoundError(f"{model_dir / f}: missing; valid: a finished `inseggan "
                                    "loop` output folder (its model/ with model.pt and card.json)")
    card = json.loads((model_dir / "card.json").read_text())
    if not with_recipe:
        return model_dir, card, None
    if not (run_dir / "recipe.yaml").is_file():
        raise FileNotFoundError(f"{run_dir / 'recipe.yaml'}: missing (a loop run writes it); "
                                "valid: a loop output folder with its recipe, or --no-recipe to "
                                "ship the model alone")
    recipe = recipe_file.read(run_dir / "recipe.yaml")
    if recipe.get("command", "loop") != "loop" or "steps" in recipe:
        raise ValueError(f"{run_dir / 'recipe.yaml'}: not a loop run's recipe (command "
                         f"{recipe.get('command')!r}); valid: the recipe.yaml `inseggan loop` "
                         "writes")
    return model_dir, card, recipe


def ship(run_dir, name: str, into="models", recipes=None, force: bool = False,
         with_recipe: bool = True, ship_failing: bool = False) -> dict:
    """RUN/model into `into`/NAME (model.pt, the pictures, card.json named NAME, README.md from
    it) and RUN/recipe.yaml into `recipes`/NAME.yaml (default: `default_recipes(into)`), its
    `name` NAME -> {"model": folder, "recipe": file or None, "card": the card}. Refuses an
    existing folder or recipe without `force`, and a model whose card's verdict
    (`evaluation.verdict`) failed without `ship_failing`, before writing either."""
    from inseggan_ros.core import recipe as recipe_file
    from inseggan_ros.evaluation.modelcard import markdown, write_folder

    if not NAME.fullmatch(name or ""):
        raise ValueError(f"--name {name!r} invalid; valid: letters, digits, _ . - (a folder "
                         "name, e.g. my_part)")
    run_dir = Path(run_dir)
    model_dir, card, recipe = _run_parts(run_dir, with_recipe)
    target = Path(into) / name
    recipe_target = Path(recipes or default_recipes(into)) / f"{name}.yaml"
    judged = card.get("verdict") or {"ok": True}
    if not judged["ok"] and not ship_failing:
        raise ValueError(f"{model_dir / 'card.json'}: the loop judged this model not to explain "
                         "its frames (" + "; ".join(judged["problems"]) + "); valid: a model "
                         "whose card's verdict is ok, or --ship-failing to ship it anyway")
    for path in (target, recipe_target if recipe is not None else None):
        if path is not None and path.exists() and not force:
            raise FileExistsError(f"{path} exists; valid: another --name, or --force to "
                                  "replace it")
    card["name"] = name
    if recipe is not None:
        recipe = {**recipe, "name": name}
        card.setdefault("recipe", {k: v for k, v in recipe.items()
                                   if k not in recipe_file.META})
        card.setdefault("commit", recipe.get("commit", "unknown"))
        card["recipe"]["name"] = name

    def write(tmp: Path) -> None:
        for f in sorted(model_dir.iterdir()):
            if f.is_file() and (f.name == "model.pt" or f.suffix == ".png"):
                shutil.copy2(f, tmp / f.name)
        (tmp / "card.json").write_text(json.dumps(card, indent=2))
        (tmp / "README.md").write_text(markdown(card))

    write_folder(target, write)
    if recipe is not None:
        recipe_file.write(recipe_target, recipe, RECIPE_HEADER.format(name=name))
    return {"model": target, "recipe": recipe_target if recipe is not None else None,
            "card": card}
