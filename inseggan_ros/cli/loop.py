"""`inseggan loop`: a recording (or a data set) to a shipped model, in one command; its options
from the command line, a recipe file (`--recipe`), or both (the flags over the file's).

    inseggan loop --bag my_recording --instances 5 --noise realsense --out runs/mine
    inseggan loop --recipe bolt_tilted --bag my_bolts --out runs/my_bolts

`inseggan loop --help` lists the options a user gives; the stages' own (the research
options) are listed by `inseggan loop --help-advanced`.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from inseggan_ros.cli import common, recipes
from inseggan_ros.evaluation.vote_scale import SCALES as VOTE_SCALES
from inseggan_ros.learning.budget import DEFAULT_MINUTES
from inseggan_ros.learning.family import DEFAULT_FAMILIES, FAMILIES, FamilyConfig

SUMMARY = "a recording to a model: learn the part's shape from the unlabelled frames, finish " \
          "the model on labelled simulated piles of it, ship it with a label-free card"
ADVANCED = "advanced (research) options"
# the options that are not the configuration: never read from, nor written to, a recipe
NOT_RECIPE = ("recipe", "print_recipe", "quiet")
# the user's frames: a recipe's --bag and --data are dropped where the command line gives either
FRAMES = (("bag", "data"),)


class _AdvancedHelp(argparse.Action):
    """--help-advanced: the help with the research options shown, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, group=None, help=None):
        super().__init__(option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                         nargs=0, help=help)
        # the group's description and each option's help, hidden from the plain --help
        self.group, self.description = group, group.description
        self.hidden = [(a, a.help) for a in group._group_actions]
        group.description = None
        for action, _ in self.hidden:
            action.help = argparse.SUPPRESS

    def __call__(self, parser, namespace, values, option_string=None):
        self.group.description = self.description
        for action, text in self.hidden:
            action.help = text
        parser.print_help()
        parser.exit()


def _user_options(p) -> None:
    """What a user gives: the recording, the parts in the bin, where the run goes."""
    common.frames_args(p, required=False)
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="run directory (required): a killed run started again with the same "
                        "--out resumes where it stopped, stage by stage")
    p.add_argument("--name", default="model", help="the exported model's name (model)")
    p.add_argument("--minutes", type=float, default=DEFAULT_MINUTES, metavar="MIN",
                   help="the whole run's time budget: the shape stage, the template family's "
                        "candidates and the centre votes get their shares of it, and the card "
                        f"says what it cut ({DEFAULT_MINUTES:g}; 0: none)")
    p.add_argument("--train-minutes", type=float, metavar="MIN",
                   help="the shape stage's budget in minutes (without --model; 600 iterations "
                        "when neither this nor --train-iterations is given)")
    p.add_argument("--workers", type=int, default=common.default_workers(), metavar="N",
                   help="simulation and self-labelling processes (this machine's cores, "
                        f"{common.default_workers()}; the piles do not depend on it)")
    p.add_argument("--recipe", metavar="FILE",
                   help="the options from a recipe file (YAML, the flags' names with "
                        "underscores; a run's OUT/recipe.yaml, or a shipped model's name: "
                        "config/recipes/NAME.yaml); flags given beside it override its values")
    p.add_argument("--print-recipe", action="store_true",
                   help="print the resolved configuration (every option, after the recipe "
                        "and the flags) as a recipe, and exit")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _shape_options(g) -> None:
    """The model the loop starts from, or the shape stage that learns it."""
    g.add_argument("--model", type=Path,
                   help="a trained model: checkpoint (best.pt) or model folder; without it the "
                        "loop learns the shape first (`inseggan train` on the user's unlabelled "
                        "frames, into OUT/shape)")
    g.add_argument("--config", default="cpu_spheres",
                   help="without --model: the training config (cpu_spheres)")
    g.add_argument("--spheres", type=int, help="without --model: the rod's sphere count")
    g.add_argument("--train-iterations", type=int,
                   help="without --model: the shape stage's iteration budget (600 unless "
                        "--train-minutes is given)")
    g.add_argument("--train-seed", type=int, default=1, help="of the shape stage (1)")
    g.add_argument("--eval-every", type=int, default=100,
                   help="without --model: validate and checkpoint every N iterations (100)")


def _stage_options(g) -> None:
    """The piles, the encoder and the stages after it."""
    g.add_argument("--scenes", type=int, default=3000, help="simulated training scenes (3000)")
    g.add_argument("--val-scenes", type=int, default=200, help="and validation scenes (200)")
    g.add_argument("--min-instances", type=int, metavar="M",
                   help="each simulated scene holds M..--instances parts, drawn per scene (0: "
                        "empty bins among them), so that the centre votes find as many parts "
                        "as there are; default: every scene holds --instances")
    g.add_argument("--iterations", type=int, default=0,
                   help="encoder iterations (0, the default: no encoder stage, the model's own "
                        "encoder, with --centre-iterations or --head-iterations)")
    g.add_argument("--lr", type=float, default=3e-4, help="their learning rate (3e-4, cosine)")
    g.add_argument("--seed", type=int, default=11, help="of the simulated scenes (11)")
    g.add_argument("--user-weight", type=float, default=0.0,
                   help="the encoder also reconstructs the user's own training frames (not "
                        "their labels), with this weight (0: off)")
    g.add_argument("--head-iterations", type=int, default=0,
                   help="also train a label head on the same piles for this many iterations "
                        "and ship the model with it on (0: none; measured: "
                        "docs/experiments.md, a label head)")
    g.add_argument("--centre-iterations", type=int, default=3000,
                   help="train centre votes (`inseggan centres`) on the same piles for this "
                        "many iterations and ship the model with them on (3000; 0: none)")
    g.add_argument("--centre-teacher", choices=("piles", "self-labels", "pasted"),
                   default="piles",
                   help="what teaches the centre votes: the same piles' labels (piles, the "
                        "default), the user's training frames labelled by the model itself "
                        "(self-labels; no label read; better where the learned shape is not "
                        "the real part's), or piles pasted from the parts seen whole in the "
                        "user's frames (pasted; no template, no label; better where no "
                        "template family has the part's outline)")
    g.add_argument("--self-frames", type=int, default=0,
                   help="then fit the encoder further to the model's own labels (at "
                        "--self-settings) of this many of the user's training frames, no label "
                        "read (0: no such stage); run again on a finished loop's OUT, it adds "
                        "only this")
    g.add_argument("--self-iterations", type=int, default=1500,
                   help="with --self-frames: encoder iterations (1500; the last is kept)")
    g.add_argument("--self-settings", default="quality",
                   help="with --self-frames: the settings that label the frames (quality)")
    g.add_argument("--export-settings", default="realtime",
                   help="the exported model's own settings, as the node and its card use "
                        "them (realtime)")
    g.add_argument("--vote-scales", type=common.vote_scales, default=VOTE_SCALES,
                   help="at export, the superpixel vote's scale chosen among these on the "
                        "simulated piles' validation split, whose labels are the loop's own "
                        "(default: " + ",".join(map(str, VOTE_SCALES)) + "; none: the export "
                        "settings' own scale)")


def _sizing_options(g) -> None:
    """The rod resized to the user's frames."""
    g.add_argument("--size-by-thickness", nargs="?", const="on", default="auto",
                   choices=("auto", "on", "off"),
                   help="before the first simulation, resize the rod to the thickness of the "
                        "parts in the user's frames (no label read). auto, the default: only "
                        "a rod the loop learns itself (no --model) that came out elongated; "
                        "on (the option alone): any rod; off")
    g.add_argument("--size-keep-length", action=argparse.BooleanOptionalAction, default=False,
                   help="the thickness rule thins the rod's spheres and keeps its length (more "
                        "spheres where they need them to overlap): for a long, thin part whose "
                        "rod came out thick, such as a bolt")
    g.add_argument("--size-rounds", type=int, default=None,
                   help="after the encoder, up to N rounds of: the rod's scale chosen by how "
                        "well it explains the user's frames, and where it is not 1, the "
                        "simulation and the encoder again at that scale (default: 2 for a rod "
                        "the loop learns itself, 0 with --model)")


def _template_options(g) -> None:
    """The piles made of another template than the rod: discs sized by piles, a convex fit."""
    g.add_argument("--match-piles", action=argparse.BooleanOptionalAction, default=False,
                   help="with a rod: the piles are of a disc template cut from it, its widest "
                        "disc sized (and the whole stretched) by how each variant's piles look "
                        "against the user's frames (pilematch; OUT/match; no size stage then)")
    common.pile_grid_args(g)
    g.add_argument("--match-pieces", type=int, default=2,
                   help="--match-piles: the template's discs (2: a head on a shaft; 3: a flange; "
                        "1 with --match-walls 12 and --pile-holes: a hexagonal nut)")
    g.add_argument("--match-walls", type=int, default=8,
                   help="--match-piles: side planes of each disc (8)")
    g.add_argument("--match-seed", type=int, default=0,
                   help="--match-piles: of the variants' piles (0)")
    g.add_argument("--convex-pieces", type=int, default=0,
                   help="with a rod: the rod becomes a convex template of this many pieces (a "
                        "box, a prism: flat faces, sharp edges), fitted to the user's frames by "
                        "reconstruction as `shape-fit` fits it (OUT/convex), and the piles are "
                        "of it; no size stage then (0: the rod's own piles)")
    g.add_argument("--convex-walls", type=int, default=4,
                   help="--convex-pieces: side planes of each piece (4: a box)")
    g.add_argument("--convex-iterations", type=int, default=1500,
                   help="--convex-pieces: iterations of the fit (1500)")
    g.add_argument("--families", type=_families, default=DEFAULT_FAMILIES,
                   help="the template families the loop chooses among, by how their piles "
                        "and renders match the user's frames (comma-separated; default: "
                        f"{','.join(DEFAULT_FAMILIES)}; also: bar, best with "
                        "--family-flat-refine 1; rod alone: no choice, the rod's own piles). "
                        "Not with --convex-pieces, --match-piles or an encoder stage, which "
                        "name the template or come before it")

    g.add_argument("--family-piles", type=int, default=FamilyConfig.piles,
                   help="--families: simulated piles of each candidate at each scale "
                        f"({FamilyConfig.piles})")
    g.add_argument("--family-iterations", type=int, default=FamilyConfig.fit_iterations,
                   help="--families: iterations of the fitted candidates, box and bars "
                        f"({FamilyConfig.fit_iterations})")
    g.add_argument("--family-edges", action=argparse.BooleanOptionalAction,
                   default=FamilyConfig.edges,
                   help="--families: the piles' edge distances' W1 joins each candidate's "
                        "score (recorded either way)")
    g.add_argument("--family-refine", type=int, default=FamilyConfig.refine,
                   help="--families: rounds of halving the scale step about each candidate's "
                        "best scale (one round for every candidate, the rest for the "
                        f"{FamilyConfig.leaders} leaders; {FamilyConfig.refine}: none)")
    g.add_argument("--family-widths", type=int, default=FamilyConfig.widths,
                   help="--families: steps of the bars' width search (the lone bar, T, L and "
                        f"U; {FamilyConfig.widths}; 0: none)")
    g.add_argument("--family-flat-refine", type=int, default=FamilyConfig.flat_refine,
                   help="--families: rounds of halving the scale step about each bars "
                        "candidate's best scale, before its width search "
                        f"({FamilyConfig.flat_refine}; 0: none)")


def _families(text: str) -> tuple[str, ...]:
    names = tuple(t.strip() for t in str(text).split(",") if t.strip())
    bad = [n for n in names if n not in FAMILIES]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"families {text!r} invalid; valid: a comma-separated "
                                         f"list of {', '.join(FAMILIES)}")
    return names


def add_parser(sub) -> argparse.ArgumentParser:
    """The `loop` command: the user's options shown, the research ones behind --help-advanced;
    every default deferred (`recipes.defer_defaults`), so that a recipe fills what the command
    line leaves."""
    p = sub.add_parser("loop", help=SUMMARY,
                       epilog="The stages' own options (the shape stage, the piles, the "
                              "encoder, centre votes, sizing, disc and convex templates): "
                              "`inseggan loop --help-advanced`.")
    _user_options(p)
    adv = p.add_argument_group(ADVANCED, "each stage's own settings, as the research runs and "
                                         "the shipped models' recipes (config/recipes) use them")
    moved = [a for a in p._optionals._group_actions
             if a.dest in ("data", "labels_topic", "held_out")]
    for action in moved:  # the user's frames' research options, listed with the others
        p._optionals._group_actions.remove(action)
        adv._group_actions.append(action)
    _shape_options(adv)
    _stage_options(adv)
    _sizing_options(adv)
    _template_options(adv)
    p.add_argument("--help-advanced", action=_AdvancedHelp, group=adv,
                   help="show the advanced (research) options too, and exit")
    p.set_defaults(func=cmd_loop, loop_parser=p,
                   loop_defaults=recipes.defer_defaults(p, keep=NOT_RECIPE))
    return p


def resolve(args) -> dict:
    """The loop's options: the command line's flags over the recipe file's (--recipe) over the
    defaults -> {name: value}, every option but --recipe, --print-recipe and --quiet."""
    from inseggan_ros.core import recipe as recipe_file

    defaults = {k: v for k, v in args.loop_defaults.items() if k not in NOT_RECIPE}
    given = {}
    if args.recipe is not None:
        path = recipes.shipped_recipe(str(args.recipe))
        step = recipe_file.command_step(recipe_file.read(path), "loop", path)
        given = recipes.read_options(args.loop_parser, step, path, defaults,
                                     exclude=NOT_RECIPE)
    opts = recipes.merge(args, defaults, given, together=FRAMES)
    if opts["out"] is None:
        raise ValueError("no run directory: give --out DIR (or `out:` in the recipe)")
    # the defaults that depend on other options, written out so that the recipe is whole
    if opts["bag"] is not None and opts["noise"] is None:
        opts["noise"] = "auto"
    if opts["model"] is None and opts["train_minutes"] is None and \
            opts["train_iterations"] is None:
        from inseggan_ros.learning.loop import SHAPE_ITERATIONS

        opts["train_iterations"] = SHAPE_ITERATIONS
    return opts


def loop_config(opts: dict):
    """The `LoopConfig` of the resolved options; the grid's and the templates' flags refused
    where their stage is not asked for."""
    from dataclasses import replace

    from inseggan_ros.learning.loop import LoopConfig

    names = ("scenes", "val_scenes", "min_instances", "iterations", "lr", "seed", "workers", "name",
             "user_weight", "head_iterations", "centre_iterations", "centre_teacher",
             "self_frames", "self_iterations", "self_settings", "export_settings",
             "size_by_thickness", "size_rounds", "size_keep_length", "vote_scales",
             "match_pieces", "match_walls", "minutes")
    cfg = LoopConfig(**{k: opts[k] for k in names})
    grid = common.pile_grid(argparse.Namespace(**opts))
    if opts["match_piles"]:
        from inseggan_ros.learning.pilematch import PileMatchConfig

        cfg = replace(cfg, match_piles=PileMatchConfig(seed=opts["match_seed"],
                                                       workers=opts["workers"], **grid))
    elif opts["match_pieces"] != 2 or opts["match_walls"] != 8 or opts["match_seed"] != 0:
        raise ValueError("--match-pieces, --match-walls and --match-seed shape --match-piles' "
                         "discs; valid: with --match-piles")
    if opts["convex_pieces"]:
        from inseggan_ros.learning.shapefit import ShapeFitConfig

        cfg = replace(cfg, convex=ShapeFitConfig(pieces=opts["convex_pieces"],
                                                 walls=opts["convex_walls"],
                                                 iterations=opts["convex_iterations"],
                                                 seed=opts["seed"]))
    elif opts["convex_walls"] != 4 or opts["convex_iterations"] != 1500:
        raise ValueError("--convex-walls and --convex-iterations shape --convex-pieces' "
                         "template; valid: with --convex-pieces")
    return _with_family(cfg, opts)


def _with_family(cfg, opts: dict):
    """`cfg` with the family choice (`family.FamilyConfig`) where the options leave the
    template to the loop: more than the rod among --families, no encoder stage, neither
    --convex-pieces nor --match-piles. Families named beside those refused."""
    from dataclasses import replace

    families = tuple(opts["families"])
    if families == ("rod",):
        return cfg
    named = cfg.convex is not None or cfg.match_piles is not None or cfg.iterations
    if named and families != DEFAULT_FAMILIES:
        raise ValueError("--families chooses the template; valid: without --convex-pieces, "
                         "--match-piles and --iterations, or --families rod")
    if named:
        return cfg
    return replace(cfg, family=FamilyConfig(families=families, piles=opts["family_piles"],
                                            fit_iterations=opts["family_iterations"],
                                            refine=opts["family_refine"],
                                            widths=opts["family_widths"],
                                            flat_refine=opts["family_flat_refine"],
                                            edges=opts["family_edges"],
                                            workers=opts["workers"], seed=opts["seed"]))


def train_config(opts: dict):
    """The shape stage's `TrainConfig` (None with --model)."""
    if opts["model"] is None:
        from inseggan_ros.learning.train import get_config

        from inseggan_ros.learning.loop import SHAPE_ITERATIONS

        iterations = opts["train_iterations"]
        if iterations is None and opts["train_minutes"] is None:
            iterations = SHAPE_ITERATIONS
        return get_config(opts["config"], spheres=opts["spheres"], seed=opts["train_seed"],
                          max_minutes=opts["train_minutes"], max_iterations=iterations,
                          eval_every=opts["eval_every"], checkpoint_every=opts["eval_every"])
    if opts["train_minutes"] is not None or opts["train_iterations"] is not None:
        raise ValueError("--train-minutes/--train-iterations learn the shape first: without "
                         "--model only")
    return None


def cmd_loop(args) -> int:
    from inseggan_ros.core import recipe as recipe_file
    from inseggan_ros.learning.loop import RECIPE_HEADER, run

    opts = resolve(args)
    cfg, train_cfg = loop_config(opts), train_config(opts)
    frames = common.bag_or_data(argparse.Namespace(**opts))
    resolved = {"command": "loop", "commit": recipe_file.code_commit(), **opts}
    if args.print_recipe:
        print(recipe_file.dump(resolved, RECIPE_HEADER), end="")
        return 0
    t0 = time.perf_counter()
    summary = run(opts["model"], frames, opts["out"], cfg, progress=not args.quiet,
                  train_cfg=train_cfg, recipe=resolved)
    report(summary, opts["out"], time.perf_counter() - t0)
    return 0


def report(summary: dict, out: Path, seconds: float) -> None:
    """What a finished loop prints: its stages' times, the encoder's validation, the model and
    its card, and what the template and sizing stages chose."""
    enc = summary["encoder"]
    print(f"loop done in {seconds / 60:.1f} min ("
          + common.stage_minutes(summary["seconds"]) + "); "
          + (f"encoder validation mIoU on the simulated scenes {enc['val'][0]['miou']:.3f} -> "
             f"{enc['best_score']:.3f}" if enc else "no encoder stage (--iterations 0)")
          + f"; model: {out}/model (tau {summary['tau']:.2f}), card {summary['card']}; "
          f"recipe: {out}/recipe.yaml")
    if "match" in summary:
        best = summary["match"]["best"]
        print(f"piles of a disc template matched by {summary['match']['variants']} variants: "
              f"head length x{best['length']:g}, radius x{best['radius']:g}, shaft "
              f"x{best['shaft']:g}, stretched x{best['stretch']:g}"
              + (f", a nut with a hole x{best['hole']:g} as wide" if best.get("hole") else "")
              + (f", tapering to x{best['taper']:g}" if best.get("taper", 1) != 1 else "")
              + f" (heights' W1 {best['distance']:.4f}); {summary['match']['part']}")
    if summary.get("template_family"):
        fam = summary["template_family"]
        print(f"template family: {fam['kept']} kept (piles at x{fam['scale']:g}) of "
              + ", ".join(f"{r['family']} {r['score']:.2f}" if "score" in r
                          else f"{r['family']} (not made)" for r in fam["candidates"])
              + " (each scored measure over the best, summed: piles' heights W1, "
              + ("their edges' W1, " if fam.get("edges") else "") + "reconstruction; "
              f"{fam['seconds'] / 60:.1f} min); {out}/family/family.png")
    if "not_by_thickness" in summary["sizing"]:
        print(f"rod not resized to the frames' thickness: "
              f"{summary['sizing']['not_by_thickness']}")
    if "size" in summary and summary["size"].get("left_as_is"):
        print(f"rod not resized to the frames' thickness: {summary['size']['left_as_is']}")
    elif "size" in summary:
        size = summary["size"]
        print("rod sized to the frames' thickness, {:.1f} mm: {} -> {} mm".format(
            size["thickness_mm"], " x ".join(f"{v:.1f}" for v in size["dimensions_mm_before"]),
            " x ".join(f"{v:.1f}" for v in size["dimensions_mm_after"])))
    if summary.get("size_rounds"):
        print("template scales chosen by the frames' reconstruction, round by round: "
              + ", ".join(f"{r['scale']:g}" for r in summary["size_rounds"]))
    v = summary.get("verdict") or {"ok": True}
    if not v["ok"]:
        print("WARNING: this model does not explain its frames (label-free verdict, on its "
              "card; `inseggan ship` refuses it without --ship-failing):\n  "
              + "\n  ".join(v["problems"]))
    b = summary.get("budget")
    if b and b["minutes"]:
        print(f"time budget {b['minutes']:g} min: {b['used_minutes']:g} used"
              + (" (over it)" if b["over"] else "")
              + ("; cut: " + "; ".join(b["cut"]) if b["cut"] else "; nothing cut"))
    if summary.get("vote_scale"):
        from inseggan_ros.evaluation.vote_scale import describe

        print(f"superpixel vote: {describe(summary['vote_scale'])}")
