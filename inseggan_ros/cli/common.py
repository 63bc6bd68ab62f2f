"""What several commands share: argument types, the simulated scene's flags, the user's frames
(`--data` or `--bag` and its options), --match-piles' grid and the parameters files measured
beside a model's own settings."""
from __future__ import annotations

import argparse
from pathlib import Path

from inseggan_ros.core import settings


def floats(text: str) -> tuple[float, ...] | None:
    """Comma-separated numbers, or None where one is not a number."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        return None


def fractions(text: str) -> tuple[float, float, float]:
    """--split: three numbers train,val,test (fractions, or counts of scenes)."""
    parts = floats(text)
    if parts is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not three numbers like 0.8,0.1,0.1")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: need three fractions train,val,test")
    return parts


def vote_scales(text: str) -> tuple[int, ...]:
    """--vote-scales: integers >= 1, or none."""
    if text.strip().lower() == "none":
        return ()
    try:
        scales = tuple(int(x) for x in text.split(","))
    except ValueError:
        scales = ()
    if not scales or min(scales) < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not scales like 50,160,250 (integers "
                                         ">= 1) or none")
    return scales


def numbers(text: str) -> tuple[float, ...]:
    """A grid's factors: comma-separated numbers."""
    parts = floats(text)
    if parts is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not numbers like 0.4,0.7,1")
    return parts


def offset(text: str) -> tuple[float, float]:
    """--bin-offset: two fractions of the image width,height."""
    parts = floats(text) or ()
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not two numbers like -0.15,0.08 "
                                         "(fractions of the image width,height)")
    return parts


def bin_size(text: str) -> tuple[float, float]:
    """--bin-size: the bin's inner width and length, metres."""
    parts = floats(text) or ()
    if len(parts) != 2 or not all(p > 0 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r} is not two lengths like 0.09,0.09 (the "
                                         "bin's inner width,length in metres)")
    return parts


def scene_config(args):
    """The `SceneConfig` of the scene flags (`add_scene_args`)."""
    from inseggan_ros.sim.camera import get_camera
    from inseggan_ros.sim.noise import get_noise
    from inseggan_ros.sim.scene import BinConfig, SceneConfig

    camera = get_camera(args.camera, args.width, args.height)
    return SceneConfig(object=args.object, instances=args.instances,
                       min_instances=args.min_instances, noise=get_noise(args.noise),
                       **cell(args, camera, BinConfig()))


def cell(args, camera, bin_cfg) -> dict:
    """The camera and the bin with the scene flags' overrides of their pose and size (--tilt,
    --roll, --bin-offset, --mount-height, --bin-size): `SceneConfig` fields."""
    from dataclasses import replace

    pose = {k: v for k, v in (("tilt", args.tilt), ("roll", args.roll),
                              ("bin_offset", args.bin_offset),
                              ("mount_height", args.mount_height)) if v is not None}
    return {"camera": replace(camera, **pose),
            "bin": bin_cfg if args.bin_size is None else replace(bin_cfg, inner_size=args.bin_size)}


def part(name: str) -> str:
    """--object: a library part's name, or a model whose learned template is simulated."""
    from inseggan_ros.sim.learned import is_model_path
    from inseggan_ros.sim.objects import OBJECTS

    if name in OBJECTS or is_model_path(name):
        return name
    raise argparse.ArgumentTypeError(
        f"{name!r} is neither a part ({', '.join(OBJECTS)}) nor a model folder or .pt checkpoint")


def add_scene_args(p: argparse.ArgumentParser) -> None:
    """The simulated scene: the part, how many, the camera, its pose and the sensor noise."""
    from inseggan_ros.sim.camera import PRESETS
    from inseggan_ros.sim.noise import NOISE_PRESETS
    from inseggan_ros.sim.objects import OBJECTS

    p.add_argument("--object", default="cylinder", type=part,
                   help=f"a part of the library ({', '.join(OBJECTS)}; default cylinder), or a "
                        "model folder or .pt checkpoint: the shape it learned")
    p.add_argument("--instances", type=int, default=5, help="objects per bin (default 5)")
    p.add_argument("--min-instances", type=int, metavar="M",
                   help="each scene draws its own count, uniformly in M..--instances, from its "
                        "seed (a bin a robot empties; 0: empty bins among them); default: "
                        "every scene holds --instances")
    p.add_argument("--camera", default="default", choices=list(PRESETS),
                   help="camera preset: default = 224x224, realsense_d435 = 848x480, "
                        "realsense_d435_tilted = the same tilted 3 degrees, bin off-centre")
    p.add_argument("--width", type=int, help="override the preset's image width")
    p.add_argument("--height", type=int, help="override the preset's image height")
    p.add_argument("--noise", default="none", choices=list(NOISE_PRESETS),
                   help="sensor noise model (default none)")
    p.add_argument("--tilt", type=float, help="override the preset's camera tilt, degrees")
    p.add_argument("--roll", type=float, help="override the preset's camera roll, degrees")
    p.add_argument("--bin-offset", type=offset,
                   help="override where the bin's centre appears: fractions of the image "
                        "width,height from the principal point, e.g. -0.15,0.08")
    p.add_argument("--mount-height", type=float, metavar="M",
                   help="override the preset's camera height above the bin floor, metres "
                        "(another cell: a camera mounted higher or lower)")
    p.add_argument("--bin-size", type=bin_size, metavar="X,Y",
                   help="the bin's inner width,length in metres (default 0.09,0.09)")


def frames_args(p, required: bool = True) -> None:
    """The user's frames: --data, or --bag and its options (`loop`, `self-fit`, `shape-fit`).
    `required`: one of --data and --bag on the command line (the loop's may come from a recipe
    file instead)."""
    src = p.add_mutually_exclusive_group(required=required)
    src.add_argument("--bag", type=Path,
                     help="the user's recording (depth and CameraInfo, no labels): its camera "
                          "and bin are estimated and simulated; its last frames (--held-out) "
                          "make the card")
    src.add_argument("--data", type=Path,
                     help="the user's data set (its camera, noise and bin are simulated; its "
                          "val and test frames make the card, without their labels)")
    p.add_argument("--instances", type=int, metavar="N",
                   help="with --bag (required): the parts in the bin")
    p.add_argument("--topic", help="with --bag: the depth topic (default: the only one)")
    p.add_argument("--noise", help="with --bag: the piles' sensor noise (auto, the default: "
                                   "measured on the bag's own frames; or a preset: none, "
                                   "realsense)")
    p.add_argument("--labels-topic", help="with --bag: a label image topic, for the card's "
                                          "mIoU rows only (never trained on)")
    p.add_argument("--held-out", type=float, default=0.2,
                   help="with --bag: the last fraction of its frames, kept for the card (0.2)")


def bag_or_data(args):
    """--bag (with --instances and its options) or --data, as `loop`, `self-fit` and
    `shape-fit` take them: a `BagFrames` or the data set's folder."""
    from inseggan_ros.learning.piles import BagFrames

    if (args.bag is None) == (args.data is None):
        raise ValueError("the user's frames: give --bag (a recording) or --data (a simulated "
                         "data set), one of them")
    if args.bag is not None:
        if args.instances is None:
            raise ValueError("--bag needs --instances N (the parts in the bin: the piles are "
                             "simulated with that many)")
        return BagFrames(args.bag, args.instances, args.topic, args.labels_topic,
                         args.noise or "auto", args.held_out)
    only_bag = ("instances", "topic", "labels_topic", "noise")
    given = [f"--{k.replace('_', '-')}" for k in only_bag if getattr(args, k, None) is not None]
    if given:
        raise ValueError(f"{', '.join(given)} go with --bag; a data set names its own")
    return args.data


def stage_minutes(seconds: dict) -> str:
    """A run summary's stage times, as `loop` and `self-fit` print them."""
    return ", ".join(f"{k} {v / 60:.1f} min" for k, v in seconds.items())


def pile_grid_args(p) -> None:
    """--match-piles' grid (`pilematch.PileMatchConfig`), as `shape-fit` and `loop` take it."""
    for flag, text in (
            ("--pile-lengths", "the widest disc's length factors (0.4,0.55,0.7,0.85,1)"),
            ("--pile-radii", "its radius factors (0.9,1,1.1,1.2,1.3)"),
            ("--pile-shafts", "the other discs' radius factors (1; a flange made on a uniform "
                              "rod: e.g. 0.5,0.65,0.8,1)"),
            ("--pile-offsets", "the middle disc moved along the axis, fractions of the "
                               "template's length (0)"),
            ("--pile-stretches", "the whole template's length factors, radii kept (1; a rod "
                                 "learned too short: e.g. 1,1.25,1.5)"),
            ("--pile-holes", "one disc (--match-pieces 1, --match-walls 12) as a hexagonal nut "
                             "whose hole is these fractions of its width (0: a solid disc; e.g. "
                             "0,0.5,0.65)"),
            ("--pile-tapers", "one disc (--match-pieces 1) as a frustum whose far end's radius "
                              "is these fractions of its radius (1: a straight disc; a cone, a "
                              "stopper: e.g. 0.1,0.4,0.7,1)")):
        p.add_argument(flag, type=numbers, help="--match-piles: " + text)
    p.add_argument("--coarse-piles", type=int,
                   help="--match-piles: piles of each variant of the coarse grid (200)")
    p.add_argument("--fine-piles", type=int,
                   help="--match-piles: piles of each variant of the fine grid about the "
                        "coarse best (600; 0: no fine grid)")


def pile_grid(args) -> dict:
    """The grid flags given (`pile_grid_args`) -> PileMatchConfig keywords; refused without
    --match-piles."""
    grid = {"lengths": args.pile_lengths, "radii": args.pile_radii, "shafts": args.pile_shafts,
            "offsets": args.pile_offsets, "stretches": args.pile_stretches,
            "holes": args.pile_holes, "tapers": args.pile_tapers,
            "piles": args.coarse_piles, "fine_piles": args.fine_piles}
    grid = {k: v for k, v in grid.items() if v is not None}
    if grid and not args.match_piles:
        raise ValueError("--pile-lengths, --pile-radii, --pile-shafts, --pile-offsets, "
                         "--pile-stretches, --pile-holes, --pile-tapers, --coarse-piles and "
                         "--fine-piles are "
                         "--match-piles' grid; valid: with --match-piles")
    return grid


def also_profiles(args, base) -> dict:
    """{file stem: InferenceConfig} of each --also-profile FILE, applied to `base` (the settings
    the model ships with) as the segmenter node applies a parameters file to the model's own:
    what the file leaves out stays the model's (a part's own superpixel scale, say), so that
    each row of the card is what the node does with that file."""
    return {Path(f).stem: settings.apply(base, settings.read_params_file(f))
            for f in args.also_profile or []}


def default_workers() -> int:
    """Simulation processes by default: one per core this process may run on (at most 8).
    Every pile is drawn from its own seed (`sim.dataset.scene_seed`), so the piles are the
    same whatever the count; only the time differs."""
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(8, cores or 1))
