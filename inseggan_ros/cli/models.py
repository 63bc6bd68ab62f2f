"""Shipping a model: `ship` (a finished loop's model into models/NAME with its recipe),
`export` (a checkpoint with its card) and the `card-*` commands that add to a card."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from inseggan_ros.cli import common
from inseggan_ros.core import settings


def cmd_card_run(args) -> int:
    from inseggan_ros.evaluation.modelcard import add_training_run

    r = add_training_run(args.model, args.checkpoint, args.eval, args.label, args.hardware)
    print(f"{args.model}: run {r['label']!r} ({r['iterations']} iterations, "
          f"{r['wall_minutes']} min on {r['hardware']}): test mIoU {r['miou_all']:.3f}; "
          "card and README written")
    return 0


def cmd_card_settings(args) -> int:
    from inseggan_ros.evaluation.modelcard import apply_settings
    from inseggan_ros.runtime.segment import Segmenter

    t0 = time.perf_counter()
    seg = Segmenter.from_checkpoint(Path(args.model) / "model.pt", device="cpu")
    inference = settings.resolve(seg.inference, args, seg.stored_settings)
    also = common.also_profiles(args, inference)
    card = apply_settings(args.model, args.data, inference, also=also)
    t = card["test"]
    print(f"{args.model}: now ships {card['inference']}; test mIoU "
          + ", ".join(f"{m} {t['methods'][m]['miou_all']:.3f}" for m in t["methods"])
          + f" ({time.perf_counter() - t0:.0f} s); model, card and README written")
    return 0


def cmd_card_shape(args) -> int:
    from inseggan_ros.evaluation.modelcard import add_shape

    t0 = time.perf_counter()
    f = add_shape(args.model, args.object, voxels=args.voxels,
                  piles_template=args.piles_template)
    print(f"{args.model}: learned template vs the true {f['object']}: volumetric IoU "
          f"{f['iou']:.3f}, dimensions {f['dims_template_mm']} mm vs {f['dims_true_mm']} mm "
          f"({time.perf_counter() - t0:.0f} s); card, README and shape.png written")
    return 0


def cmd_export(args) -> int:
    from inseggan_ros.evaluation.evaluate import format_table
    from inseggan_ros.evaluation.modelcard import export_model
    from inseggan_ros.runtime.segment import InferenceConfig

    if args.bag or args.label_free:
        return _export_label_free(args)
    for flag in ("topic", "labels_topic"):
        if getattr(args, flag):
            raise ValueError(f"--{flag.replace('_', '-')} goes with --bag, not --data")
    inference = settings.resolve(InferenceConfig(), args, stored=False)
    also = common.also_profiles(args, inference)
    card = export_model(args.checkpoint, args.data, args.name,
                        args.out or Path("models") / args.name,
                        inference=inference, half=not args.no_half, frames=args.frames,
                        notes=args.config_name or "", sample_bag=args.sample_bag, also=also)
    print(f"exported {args.name}: tau {card['tau']:.3f}, {card['precision']}, refine steps "
          f"{card['refine_steps']} x {card['hypotheses']} hypotheses; test split:")
    print(format_table(card["test"]))
    return 0


def _export_label_free(args) -> int:
    """`inseggan export --bag` (or --data --label-free): tau and the card without labels."""
    from inseggan_ros.core.checkpoint import load
    from inseggan_ros.evaluation.evaluate import format_table
    from inseggan_ros.evaluation.modelcard import export_from_bag, export_from_dataset
    from inseggan_ros.runtime.segment import InferenceConfig
    from inseggan_ros.evaluation.selfcheck import format_measures

    if args.also_profile:
        raise ValueError("--also-profile needs --data (labelled), not a label-free export")
    if args.frames < 1:
        raise ValueError(f"--frames {args.frames} invalid; valid: >= 1")
    # the checkpoint's own settings (an exported model.pt has them), then the flags
    stored = load(args.checkpoint).get("inference")
    inference = settings.resolve(InferenceConfig.from_dict(stored or {}), args,
                                 stored is not None)
    out = args.out or Path("models") / args.name
    if args.bag:
        card = export_from_bag(args.checkpoint, args.bag, args.name, out, args.topic,
                               args.labels_topic, args.held_out, args.frames, inference,
                               sample_bag=args.sample_bag)
    else:
        if args.topic or args.labels_topic:
            raise ValueError("--topic and --labels-topic go with --bag, not --data")
        card = export_from_dataset(args.checkpoint, args.data, args.name, out, args.frames,
                                   inference, sample_bag=args.sample_bag)
    print(f"exported {args.name} to {out}: tau {card['tau']:.3f} (from the frames, no labels); "
          f"on {card['source']['held_out_rule']}:")
    print(format_measures(card["measures"]))
    if card["labelled"]:
        print(format_table(card["labelled"]))
    return 0


def add_card_shape(sub) -> argparse.ArgumentParser:
    """The `card-shape` command's options."""
    p = sub.add_parser("card-shape", help="add the learned template vs the simulator's true "
                                          "part (IoU, dimensions, three views) to a model card")
    p.add_argument("model", type=Path, help="a model folder (models/<name>)")
    p.add_argument("--object", help="the true part (default: the card's object)")
    p.add_argument("--voxels", type=int, default=30,
                   help="voxels along the part's largest extent (30)")
    p.add_argument("--piles-template", type=Path,
                   help="the learned template the centre votes' piles were of, where it is not "
                        "the model's own (shape-fit --start discs): measured and drawn too")
    p.set_defaults(func=cmd_card_shape)
    return p


def add_card_settings(sub) -> argparse.ArgumentParser:
    """The `card-settings` command's options."""
    p = sub.add_parser("card-settings", help="ship a model with other test-time settings: "
                                             "stored in its model.pt, its card measured anew")
    p.add_argument("model", type=Path, help="a model folder (models/<name>)")
    p.add_argument("--data", type=Path, required=True,
                   help="the card's data set (its val and test splits are read)")
    p.add_argument("--also-profile", action="append", type=Path, metavar="FILE",
                   help="other settings measured on the test split too, each file applied "
                        "to the settings shipped, as the node applies it (repeatable)")
    settings.add_flags(p, "(default: the model's own)")
    p.set_defaults(func=cmd_card_settings)
    return p


def add_card_run(sub) -> argparse.ArgumentParser:
    """The `card-run` command's options."""
    p = sub.add_parser("card-run", help="record another training run of the part (another "
                                        "config, a GPU) on a model card, with its test scores")
    p.add_argument("model", type=Path, help="a model folder (models/<name>)")
    p.add_argument("--checkpoint", type=Path, required=True, help="the run's checkpoint")
    p.add_argument("--eval", type=Path, required=True,
                   help="its `inseggan eval` results.json on the card's test split")
    p.add_argument("--label", required=True, help="the run's name on the card")
    p.add_argument("--hardware", required=True, help="what it trained on, e.g. 'NVIDIA H200'")
    p.set_defaults(func=cmd_card_run)
    return p


def add_export(sub) -> argparse.ArgumentParser:
    """The `export` command's options."""
    p = sub.add_parser("export", help="ship a trained model: models/<name>/ with a model card")
    p.add_argument("--checkpoint", type=Path, required=True,
                   help="training checkpoint (best.pt) or an exported model.pt")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="its simulated data set (val, test)")
    src.add_argument("--bag", help="a recording of the part, no labels needed: tau from its "
                                   "frames, label-free measures on its last 20 %% (a path or a "
                                   "shipped bag's name)")
    p.add_argument("--label-free", action="store_true",
                   help="with --data: calibrate tau without the labels (val split) and report "
                        "the label-free measures on the test split")
    p.add_argument("--topic", help="with --bag: depth topic (default: auto)")
    p.add_argument("--labels-topic", help="with --bag: a label Image topic in the bag (e.g. "
                                          "/camera/depth/instance_labels): the card adds mIoU")
    p.add_argument("--held-out", type=float, default=0.2,
                   help="with --bag: the fraction of last frames held out (default 0.2)")
    p.add_argument("--name", required=True)
    p.add_argument("--out", type=Path, help="default: models/<name>")
    settings.add_flags(p, "(default: none)")
    p.add_argument("--also-profile", type=Path, action="append",
                   help="parameters file of other settings to measure on the test split too, "
                        "applied to the settings exported, as the node applies it (a row "
                        "inseggan_<file stem>; repeatable)")
    p.add_argument("--no-half", action="store_true", help="keep float32 weights")
    p.add_argument("--frames", type=int, default=200,
                   help="frames per split at most (with --bag: calibration and held-out)")
    p.add_argument("--config-name", help="the named training config, for the card")
    p.add_argument("--sample-bag", help="name of a shipped bag of this object with labels: "
                                        "scored on the card, and again by the tests")
    p.set_defaults(func=cmd_export)
    return p


SHIP = "ship a finished loop's model: models/NAME (model.pt, card, README, pictures) and " \
       "config/recipes/NAME.yaml (the run's recipe)"


def cmd_ship(args) -> int:
    from inseggan_ros.evaluation.ship import ship

    done = ship(args.run, args.name, args.into, args.recipes, force=args.force,
                with_recipe=not args.no_recipe, ship_failing=args.ship_failing)
    card = done["card"]
    print(f"shipped {args.name}: {done['model']} (tau {card['tau']:.3f}; card and README)"
          + (f", recipe {done['recipe']}" if done["recipe"] else ", no recipe (--no-recipe)"))
    print(f"use it: ros2 run inseggan_ros segmenter --ros-args -p model_path:={done['model']}")
    return 0


def add_ship(sub) -> argparse.ArgumentParser:
    """The `ship` command's options."""
    p = sub.add_parser("ship", help=SHIP, description=SHIP + ". Each is written whole (a "
                       "temporary folder, then renamed); an existing one is kept unless --force.")
    p.add_argument("run", type=Path, metavar="RUN_DIR",
                   help="a finished `inseggan loop` output folder (its model/ and recipe.yaml)")
    p.add_argument("--name", required=True, help="the model's name: its folder and recipe")
    p.add_argument("--into", type=Path, default=Path("models"),
                   help="the models folder (models)")
    p.add_argument("--recipes", type=Path,
                   help="where the recipe goes (default: config/recipes beside --into)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing model folder and recipe of that name")
    p.add_argument("--ship-failing", action="store_true",
                   help="ship a model whose card says it does not explain its frames (the "
                        "loop's label-free verdict)")
    p.add_argument("--no-recipe", action="store_true",
                   help="ship the model alone, from a run that wrote no recipe.yaml")
    p.set_defaults(func=cmd_ship)
    return p
