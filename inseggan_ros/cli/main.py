"""`inseggan`: one command, several subcommands.

    inseggan simulate --object cylinder --count 1000 --out data/cylinder [--bags]
    inseggan simulate-bag --object hex_nut --count 20 --out bags/hex_nut_sim
    inseggan bench-sim [--scenes 100 --workers 2]
    inseggan contact-sheet --out sheet.png
    inseggan bag-info bags/cylinder_sim

Expected errors (bad arguments, a bag that cannot be read, an existing output) print one line
`inseggan <command>: error: ...` and exit with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from inseggan_ros.core import settings
from inseggan_ros.io.bags import BagError
from inseggan_ros.core.checkpoint import CheckpointError
from inseggan_ros.evaluation.vote_scale import SCALES as VOTE_SCALES


def _floats(text: str) -> tuple[float, ...] | None:
    """Comma-separated numbers, or None where one is not a number."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        return None


def _fractions(text: str) -> tuple[float, float, float]:
    parts = _floats(text)
    if parts is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not three numbers like 0.8,0.1,0.1")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: need three fractions train,val,test")
    return parts


def _vote_scales(text: str) -> tuple[int, ...]:
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


def _numbers(text: str) -> tuple[float, ...]:
    parts = _floats(text)
    if parts is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not numbers like 0.4,0.7,1")
    return parts


def _offset(text: str) -> tuple[float, float]:
    parts = _floats(text) or ()
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not two numbers like -0.15,0.08 "
                                         "(fractions of the image width,height)")
    return parts


def _scene_config(args):
    from dataclasses import replace

    from inseggan_ros.sim.camera import get_camera
    from inseggan_ros.sim.noise import get_noise
    from inseggan_ros.sim.scene import SceneConfig

    camera = get_camera(args.camera, args.width, args.height)
    pose = {k: v for k, v in (("tilt", args.tilt), ("roll", args.roll),
                              ("bin_offset", args.bin_offset)) if v is not None}
    return SceneConfig(object=args.object, instances=args.instances,
                       camera=replace(camera, **pose) if pose else camera,
                       noise=get_noise(args.noise))


def _object(name: str) -> str:
    """--object: a library part's name, or a model whose learned template is simulated."""
    from inseggan_ros.sim.learned import is_model_path
    from inseggan_ros.sim.objects import OBJECTS

    if name in OBJECTS or is_model_path(name):
        return name
    raise argparse.ArgumentTypeError(
        f"{name!r} is neither a part ({', '.join(OBJECTS)}) nor a model folder or .pt checkpoint")


def _add_scene_args(p: argparse.ArgumentParser) -> None:
    from inseggan_ros.sim.camera import PRESETS
    from inseggan_ros.sim.noise import NOISE_PRESETS
    from inseggan_ros.sim.objects import OBJECTS

    p.add_argument("--object", default="cylinder", type=_object,
                   help=f"a part of the library ({', '.join(OBJECTS)}; default cylinder), or a "
                        "model folder or .pt checkpoint: the shape it learned")
    p.add_argument("--instances", type=int, default=5, help="objects per bin (default 5)")
    p.add_argument("--camera", default="default", choices=list(PRESETS),
                   help="camera preset: default = 224x224, realsense_d435 = 848x480, "
                        "realsense_d435_tilted = the same tilted 3 degrees, bin off-centre")
    p.add_argument("--width", type=int, help="override the preset's image width")
    p.add_argument("--height", type=int, help="override the preset's image height")
    p.add_argument("--noise", default="none", choices=list(NOISE_PRESETS),
                   help="sensor noise model (default none)")
    p.add_argument("--tilt", type=float, help="override the preset's camera tilt, degrees")
    p.add_argument("--roll", type=float, help="override the preset's camera roll, degrees")
    p.add_argument("--bin-offset", type=_offset,
                   help="override where the bin's centre appears: fractions of the image "
                        "width,height from the principal point, e.g. -0.15,0.08")


# ----------------------------------------------------------------------------- commands
def _camera_from_bag(args):
    """--camera-from: (camera, bin inner size, one line saying so) estimated from a bag's
    depth frames and their camera info (sim.user_camera)."""
    from inseggan_ros.sim.user_camera import camera_from_bag

    cam, est, line = camera_from_bag(args.camera_from, args.topic)
    return cam, est["bin_inner_size"], line


def cmd_simulate(args) -> int:
    from dataclasses import replace

    from inseggan_ros.sim.dataset import DatasetSpec, generate

    if args.camera_from is not None and args.camera is not None:
        raise ValueError("--camera-from and --camera are mutually exclusive; valid: one of them")
    args.camera = args.camera or "default"
    scene = _scene_config(args)
    if args.camera_from is not None:
        cam, size, line = _camera_from_bag(args)
        print(line)
        if args.width is not None or args.height is not None:
            cam = cam.resized(args.width or cam.width, args.height or cam.height)
        pose = {k: v for k, v in (("tilt", args.tilt), ("roll", args.roll),
                                  ("bin_offset", args.bin_offset)) if v is not None}
        scene = replace(scene, camera=replace(cam, **pose),
                        bin=replace(scene.bin, inner_size=tuple(size)))
    spec = DatasetSpec.from_fractions(scene, args.count, args.split,
                                      seed=args.seed, shard_size=args.shard_size)
    t0 = time.perf_counter()
    meta = generate(spec, args.out, workers=args.workers, bags=args.bags,
                    bag_encoding=args.bag_encoding, overwrite=args.overwrite,
                    progress=not args.quiet)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"simulated {sum(meta['counts'].values())} scenes of {args.instances} x {args.object} "
          f"({', '.join(f'{k} {v}' for k, v in meta['counts'].items())}) into {args.out}")
    print(f"  {meta['scenes_per_second']:.1f} scenes/s with {args.workers} worker(s), "
          f"{time.perf_counter() - t0:.1f} s in all, {size / 1e6:.1f} MB on disk"
          + (f", bags: {', '.join(meta['bags'].values())}" if meta["bags"] else ""))
    if meta["repiled_scenes"]:
        print(f"  {meta['repiled_scenes']} scene(s) piled again: a part bounced out of the bin "
              "in every drop of the seed's own pile")
    return 0


def cmd_simulate_bag(args) -> int:
    from inseggan_ros.io.bags import BagWriter, CameraInfo
    from inseggan_ros.sim.dataset import BAG_PERIOD_NS, BAG_START_NS, scene_seed
    from inseggan_ros.sim.scene import BinSimulator
    from tqdm import tqdm

    cfg = _scene_config(args)
    if args.count < 1:
        raise ValueError(f"count must be >= 1, got {args.count}")
    period = int(1e9 / args.rate) if args.rate > 0 else BAG_PERIOD_NS
    info = CameraInfo.from_camera(cfg.camera)
    with BinSimulator(cfg) as sim, BagWriter(args.out, encoding=args.encoding,
                                             storage=args.storage,
                                             compression=args.compression) as w:
        for k in tqdm(range(args.count), desc="simulating", unit="frame", disable=args.quiet):
            s = sim.render(scene_seed(args.seed, "test", k))
            w.write(BAG_START_NS + k * period, s.depth, s.labels, info)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"wrote {args.out}: {args.count} frames of {args.instances} x {args.object}, "
          f"{cfg.camera.width}x{cfg.camera.height} {args.encoding}, {args.storage} "
          f"({w.compression}), "
          f"{size / 1e6:.1f} MB")
    return 0


def _load_training_data(args):
    """(train, val, preprocess config, description) from a simulated data set or a bag."""
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.runtime.preprocess import PreprocessConfig

    if args.data:
        train, val, prep, info = data_mod.load_sim_training(
            args.data, args.train_frames, args.val_frames, progress=not args.quiet)
    else:
        roi = tuple(int(v) for v in args.roi.split(",")) if args.roi else None
        prep = PreprocessConfig(roi=roi, min_height=args.min_height, max_height=args.max_height)
        frames = data_mod.load_bag(args.bag, prep, depth_topic=args.topic,
                                   progress=not args.quiet)
        k = max(1, len(frames["x"]) // 10)
        if len(frames["x"]) < 2 * k:
            raise ValueError(f"{args.bag}: {len(frames['x'])} frames are too few to train on")

        def split(sl):
            return {key: (v[sl] if isinstance(v, np.ndarray) else v) for key, v in frames.items()}

        train, val = split(slice(None, -k)), split(slice(-k, None))
        info = {"source": "bag", "path": str(args.bag), "topic": args.topic,
                "train_frames": len(train["x"]), "val_frames": len(val["x"]),
                "view": data_mod.bag_view(train)}  # with a camera: the template in metres
        try:
            from dataclasses import asdict

            from inseggan_ros.sim.user_camera import camera_from_bag

            info["camera"] = asdict(camera_from_bag(args.bag, args.topic)[0])
        except ValueError as e:  # no CameraInfo, no floor found: the template's size unknown
            print(f"note: no camera for the template's size in metres ({e})", file=sys.stderr)
    return train, val, prep, info


def _instances(args) -> int | None:
    """The n of `inseggan train`: --instances, else a simulated data set's parts per bin (a
    model of 5 instances fitted to bins of 4 renders a part too many in every frame), else the
    config's own (a bag does not say how many parts its bin holds)."""
    if args.instances is not None or not args.data:
        return args.instances
    from inseggan_ros.data.datasets import parts_per_bin

    return parts_per_bin(args.data)


def cmd_train(args) -> int:
    from inseggan_ros.learning.train import get_config, torchrun_env, train

    cfg = get_config(args.config, nf=args.nf, composite=args.composite,
                     n_instances=_instances(args), batch_size=args.batch_size,
                     lambda_real=args.lambda_real, matching=args.matching, seed=args.seed,
                     max_iterations=args.iterations, max_minutes=args.minutes,
                     eval_every=args.eval_every, checkpoint_every=args.eval_every,
                     rotate=args.rotate or None,
                     real_trains_generator=args.real_trains_generator or None,
                     r1_gamma=args.r1_gamma, spectral_norm=args.spectral_norm or None,
                     renderer=args.renderer, lr_template=args.lr_template,
                     compactness=args.compactness, coord_conv=args.coord_conv or None,
                     recon_levels=args.recon_levels, background_weight=args.background_weight,
                     real_trains_template=False if args.template_from_gan else None,
                     floor_contact=args.floor_contact or None, spheres=args.spheres)
    train_data, val_data, prep, info = _load_training_data(args)
    if val_data.get("labels") is None:
        print("no labels in the validation frames: validation uses the reconstruction error")
    t0 = time.perf_counter()
    summary = train(cfg, train_data, val_data, args.out, prep.to_dict(), info,
                    device=args.device, resume=args.resume, progress=not args.quiet)
    if torchrun_env()[1] != 0:  # under torchrun, rank 0 reports for all
        return 0
    print(f"trained {summary['iterations']} iterations in {summary['seconds'] / 60:.1f} min "
          f"({summary['images_per_s_this_process']:.0f} images/s on {summary['device']}); "
          f"best validation score {summary['best_score']:.4f} at tau {summary['tau']:.2f}; "
          f"{summary['resets']} divergence resets; wall time {time.perf_counter() - t0:.0f} s")
    print(f"checkpoints: {args.out}/best.pt, {args.out}/last.pt; curves: {args.out}/curves.png")
    return 0


def cmd_distill(args) -> int:
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.learning.distill import DistillConfig, distill

    cfg = DistillConfig(frames=args.frames, refine_steps=args.refine_steps,
                        hypotheses=args.hypotheses, iterations=args.iterations,
                        eval_every=args.eval_every, lr=args.lr, seed=args.seed,
                        encoder_nf=args.encoder_nf, lr_schedule=args.lr_schedule,
                        lambda_pose=args.pose_weight, lambda_label=args.label_weight,
                        lambda_ownership=args.ownership_weight, lambda_user=args.user_weight)
    if (args.user_data is None) != (cfg.lambda_user == 0):
        raise ValueError("--user-data and --user-weight go together: the user's frames and the "
                         "weight of their reconstruction (> 0)")
    train = data_mod.load_sim_split(args.data, "train", limit=cfg.frames, progress=not args.quiet)
    val = data_mod.load_sim_split(args.data, "val", limit=cfg.eval_frames)
    user = (data_mod.load_sim_split(args.user_data, "train", limit=args.user_frames,
                                    progress=not args.quiet)["x"]
            if args.user_data is not None else None)
    t0 = time.perf_counter()
    summary = distill(args.checkpoint, train["x"], val, args.out, cfg, resume=args.resume,
                      progress=not args.quiet,
                      train_labels=train["labels"] if cfg.lambda_label > 0 else None,
                      user_x=user)
    vals = summary["val"]
    key = "miou" if vals and "miou" in vals[0] else "recon_l1"
    kind = "pseudo-labelled" if cfg.lambda_pose > 0 else "labelled"
    print(f"distilled {summary['iterations']} iterations on {summary['pseudo_label_frames']} "
          f"{kind} frames in {(time.perf_counter() - t0) / 60:.1f} min; validation "
          f"{key} without refinement: {vals[0][key]:.4f} -> best {summary['best_score']:.4f}"
          if vals else f"distilled {summary['iterations']} iterations")
    print(f"checkpoints: {args.out}/best.pt, {args.out}/last.pt; curves: {args.out}/curves.png")
    return 0


def _bag_or_data(args):
    """--bag (with --instances and its options) or --data, as `loop` and `self-fit` take them."""
    from inseggan_ros.learning.piles import BagFrames

    if args.bag is not None:
        if args.instances is None:
            raise ValueError("--bag needs --instances N (the parts in the bin: the piles are "
                             "simulated with that many)")
        return BagFrames(args.bag, args.instances, args.topic, args.labels_topic,
                         args.noise or "none", args.held_out)
    only_bag = ("instances", "topic", "labels_topic", "noise")
    given = [f"--{k.replace('_', '-')}" for k in only_bag if getattr(args, k, None) is not None]
    if given:
        raise ValueError(f"{', '.join(given)} go with --bag; a data set names its own")
    return args.data


def _frames_args(p) -> None:
    """The user's frames: --data, or --bag and its options (`loop`, `self-fit`)."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path,
                     help="the user's data set (its camera, noise and bin are simulated; its "
                          "val and test frames make the card, without their labels)")
    src.add_argument("--bag", type=Path,
                     help="the user's recording (depth and CameraInfo, no labels): its camera "
                          "and bin are estimated and simulated; its last frames (--held-out) "
                          "make the card")
    p.add_argument("--instances", type=int,
                   help="with --bag (required): the parts in the bin")
    p.add_argument("--topic", help="with --bag: the depth topic (default: the only one)")
    p.add_argument("--labels-topic", help="with --bag: a label image topic, for the card's "
                                          "mIoU rows only (never trained on)")
    p.add_argument("--noise", help="with --bag: the simulator's noise preset for the piles "
                                   "(none)")
    p.add_argument("--held-out", type=float, default=0.2,
                   help="with --bag: the last fraction of its frames, kept for the card (0.2)")


def _stage_minutes(seconds: dict) -> str:
    """A run summary's stage times, as `loop` and `self-fit` print them."""
    return ", ".join(f"{k} {v / 60:.1f} min" for k, v in seconds.items())


def cmd_self_fit(args) -> int:
    from inseggan_ros.learning.loop import LoopConfig, run_self_fit

    cfg = LoopConfig(self_frames=args.frames, self_iterations=args.iterations,
                     self_settings=args.settings, workers=args.workers, name=args.name,
                     seed=args.seed, export_settings=args.export_settings)
    t0 = time.perf_counter()
    s = run_self_fit(args.model, _bag_or_data(args), args.out, cfg, progress=not args.quiet)
    print(f"self-fit done in {(time.perf_counter() - t0) / 60:.1f} min ("
          + _stage_minutes(s["seconds"])
          + f"); {s['encoder']['pseudo_label_frames']} frames labelled at {args.settings} "
          f"settings, {s['encoder']['iterations']} iterations; checkpoint {args.out}/last.pt; "
          f"model: {args.out}/model (tau {s['tau']:.2f}), card {s['card']}")
    return 0


def cmd_shape_fit(args) -> int:
    from dataclasses import replace

    from inseggan_ros.core import checkpoint
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.learning.piles import BagFrames, _model_file, _same_view
    from inseggan_ros.runtime.preprocess import PreprocessConfig
    from inseggan_ros.learning.shapefit import ShapeFitConfig, fit_shape, hold_out

    cfg = ShapeFitConfig(pieces=args.pieces, walls=args.walls, iterations=args.iterations,
                         frames=args.frames, eval_every=args.eval_every, seed=args.seed,
                         thickness=args.thickness, start=args.start)
    grid = _pile_grid(args)
    if args.match_piles and args.start != "discs":
        raise ValueError("--match-piles sizes the head of a disc template; valid: with "
                         "--start discs")
    file = _model_file(args.model)
    frames = _bag_or_data(args)
    report = None
    if isinstance(frames, BagFrames):
        prep = PreprocessConfig.from_dict(checkpoint.load(file)["preprocess_config"])
        train_x, val_x = hold_out(frames.frames(prep)[0]["x"], cfg)
    else:
        _same_view(file, frames)
        train_x = data_mod.load_sim_split(frames, "train", limit=cfg.frames,
                                          progress=not args.quiet)["x"]
        val_x = data_mod.load_sim_split(frames, "val", limit=cfg.val_frames)["x"]
        report = _shape_report(file, frames)
    t0 = time.perf_counter()
    discs, hole, taper = None, 0.0, 1.0
    if args.match_piles:
        from inseggan_ros.learning.pilematch import PileMatchConfig, search

        m = search(file, cfg, frames, train_x, args.out / "match",
                   PileMatchConfig(seed=args.seed, workers=args.workers, **grid),
                   progress=not args.quiet, report=report)
        discs, best, hole, taper = m["discs"], m["best"], m.get("hole", 0.0), m.get("taper", 1.0)
        print(f"head matched by {len(m['coarse']) + len(m['fine'])} variants' piles: length x"
              f"{best['length']:g}, radius x{best['radius']:g}"
              + (f", shaft x{best['shaft']:g}" if best.get("shaft", 1) != 1 else "")
              + (f", offset {best['offset']:g}" if best.get("offset") else "")
              + (f", stretched x{best['stretch']:g}" if best.get("stretch", 1) != 1 else "")
              + (f", a hole x{hole:g} as wide" if hole else "")
              + (f", tapering to x{taper:g}" if taper != 1 else "")
              + f" (heights' W1 {best['distance']:.4f}"
              + (f"; IoU with the true part {best['iou']:.3f}" if "iou" in best else "")
              + f"); {args.out / 'match' / 'match.png'}")
        if m.get("skipped"):  # the grid's variants no template of these discs can be
            print(f"{len(m['skipped'])} variants of the grid skipped, e.g. "
                  f"{m['skipped'][0]['why']}")
    s = fit_shape(file, train_x, args.out, replace(cfg, hole=hole, taper=taper), val_x=val_x,
                  progress=not args.quiet, report=report, discs=discs)
    first, last = s["first"] or {}, s["best"] or s["last"] or {}
    line = (f"shape fitted in {(time.perf_counter() - t0) / 60:.1f} min, {s['iterations']} "
            f"iterations on {s['frames']} frames")
    if "recon_l1" in last:
        line += (f"; validation reconstruction L1 {first['recon_l1']:.4f} -> best "
                 f"{last['recon_l1']:.4f} (iteration {last['iteration']}, kept)")
    if "shape_iou" in last:
        line += (f"; IoU with the true part {first['shape_iou']:.3f} -> {last['shape_iou']:.3f}, "
                 f"{' x '.join(f'{v:.1f}' for v in last['dims_mm'])} mm (true "
                 f"{' x '.join(f'{v:.1f}' for v in last['true_dims_mm'])})")
    print(line + f"; model {s['model']}")
    return 0


def _pile_grid_args(p) -> None:
    """--match-piles' grid (`pilematch.PileMatchConfig`), as `shape-fit` and `loop` take it."""
    p.add_argument("--pile-lengths", type=_numbers,
                   help="--match-piles: the widest disc's length factors (0.4,0.55,0.7,0.85,1)")
    p.add_argument("--pile-radii", type=_numbers,
                   help="--match-piles: its radius factors (0.9,1,1.1,1.2,1.3)")
    p.add_argument("--pile-shafts", type=_numbers,
                   help="--match-piles: the other discs' radius factors (1; a flange made on a "
                        "uniform rod: e.g. 0.5,0.65,0.8,1)")
    p.add_argument("--pile-offsets", type=_numbers,
                   help="--match-piles: the middle disc moved along the axis, fractions of the "
                        "template's length (0)")
    p.add_argument("--pile-stretches", type=_numbers,
                   help="--match-piles: the whole template's length factors, radii kept (1; a "
                        "rod learned too short: e.g. 1,1.25,1.5)")
    p.add_argument("--pile-holes", type=_numbers,
                   help="--match-piles: one disc (--match-pieces 1, --match-walls 12) as a "
                        "hexagonal nut whose hole is these fractions of its width (0: a solid "
                        "disc; e.g. 0,0.5,0.65)")
    p.add_argument("--pile-tapers", type=_numbers,
                   help="--match-piles: one disc (--match-pieces 1) as a frustum whose far "
                        "end's radius is these fractions of its radius (1: a straight disc; "
                        "a cone, a stopper: e.g. 0.1,0.4,0.7,1)")
    p.add_argument("--coarse-piles", type=int,
                   help="--match-piles: piles of each variant of the coarse grid (200)")
    p.add_argument("--fine-piles", type=int,
                   help="--match-piles: piles of each variant of the fine grid about the coarse "
                        "best (600; 0: no fine grid)")


def _pile_grid(args) -> dict:
    """The grid flags given (`_pile_grid_args`) -> PileMatchConfig keywords; refused without
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


def _shape_report(model_file, data):
    """For a simulated data set of a library part: the template's fidelity against it (the
    report `shape-fit` logs; None when the part is not the library's)."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.evaluation import shape
    from inseggan_ros.sim.camera import CameraConfig
    from inseggan_ros.sim.dataset import load_meta
    from inseggan_ros.sim.objects import OBJECTS

    scene = load_meta(data)["scene"]
    if scene["object"] not in OBJECTS:
        return None
    state = checkpoint.load(model_file)
    scale = shape.metres_per_unit(state["preprocess_config"], CameraConfig(**scene["camera"]),
                                  float(state["model_config"].get("height_gain", 1.8)))
    voxel = shape.part_voxel(scene["object"])  # as the cards measure it (`modelcard.add_shape`)
    return lambda G: shape.evaluate_generator(G, scene["object"], scale, voxel=voxel)


def cmd_loop(args) -> int:
    from inseggan_ros.learning.loop import LoopConfig, run

    cfg = LoopConfig(scenes=args.scenes, val_scenes=args.val_scenes, iterations=args.iterations,
                     lr=args.lr, seed=args.seed, workers=args.workers, name=args.name,
                     user_weight=args.user_weight, head_iterations=args.head_iterations,
                     centre_iterations=args.centre_iterations,
                     centre_teacher=args.centre_teacher,
                     self_frames=args.self_frames, self_iterations=args.self_iterations,
                     self_settings=args.self_settings, export_settings=args.export_settings,
                     size_by_thickness=args.size_by_thickness, size_rounds=args.size_rounds,
                     size_keep_length=args.size_keep_length, vote_scales=args.vote_scales,
                     match_pieces=args.match_pieces, match_walls=args.match_walls)
    grid = _pile_grid(args)
    if args.match_piles:
        from dataclasses import replace

        from inseggan_ros.learning.pilematch import PileMatchConfig

        cfg = replace(cfg, match_piles=PileMatchConfig(seed=args.match_seed,
                                                       workers=args.workers, **grid))
    elif args.match_pieces != 2 or args.match_walls != 8 or args.match_seed != 0:
        raise ValueError("--match-pieces, --match-walls and --match-seed shape --match-piles' "
                         "discs; valid: with --match-piles")
    if args.convex_pieces:
        from dataclasses import replace

        from inseggan_ros.learning.shapefit import ShapeFitConfig

        cfg = replace(cfg, convex=ShapeFitConfig(pieces=args.convex_pieces,
                                                 walls=args.convex_walls,
                                                 iterations=args.convex_iterations,
                                                 seed=args.seed))
    elif args.convex_walls != 4 or args.convex_iterations != 1500:
        raise ValueError("--convex-walls and --convex-iterations shape --convex-pieces' "
                         "template; valid: with --convex-pieces")
    train_cfg = None
    if args.model is None:
        from inseggan_ros.learning.train import get_config

        train_cfg = get_config(args.config, spheres=args.spheres, seed=args.train_seed,
                               max_minutes=args.train_minutes,
                               max_iterations=args.train_iterations,
                               eval_every=args.eval_every, checkpoint_every=args.eval_every)
    elif args.train_minutes is not None or args.train_iterations is not None:
        raise ValueError("--train-minutes/--train-iterations learn the shape first: without "
                         "--model only")
    frames = _bag_or_data(args)
    t0 = time.perf_counter()
    summary = run(args.model, frames, args.out, cfg, progress=not args.quiet,
                  train_cfg=train_cfg)
    enc = summary["encoder"]
    print(f"loop done in {(time.perf_counter() - t0) / 60:.1f} min ("
          + _stage_minutes(summary["seconds"]) + "); "
          + (f"encoder validation mIoU on the simulated scenes {enc['val'][0]['miou']:.3f} -> "
             f"{enc['best_score']:.3f}" if enc else "no encoder stage (--iterations 0)")
          + f"; model: {args.out}/model (tau {summary['tau']:.2f}), card {summary['card']}")
    if "match" in summary:
        best = summary["match"]["best"]
        print(f"piles of a disc template matched by {summary['match']['variants']} variants: "
              f"head length x{best['length']:g}, radius x{best['radius']:g}, shaft "
              f"x{best['shaft']:g}, stretched x{best['stretch']:g}"
              + (f", a nut with a hole x{best['hole']:g} as wide" if best.get("hole") else "")
              + (f", tapering to x{best['taper']:g}" if best.get("taper", 1) != 1 else "")
              + f" (heights' W1 {best['distance']:.4f}); {summary['match']['part']}")
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
    if summary.get("vote_scale"):
        from inseggan_ros.evaluation.vote_scale import describe

        print(f"superpixel vote: {describe(summary['vote_scale'])}")
    return 0


def cmd_head(args) -> int:
    from inseggan_ros.learning.label_head import HeadConfig, fit
    from inseggan_ros.core.paths import resolve_model

    import torch

    torch.set_num_threads(args.threads)
    cfg = HeadConfig(width=args.width, iterations=args.iterations, lr=args.lr, seed=args.seed,
                     batch=args.batch,
                     scale_jitter=args.scale_jitter, shift_jitter=args.shift_jitter,
                     eval_every=min(250, args.iterations))
    summary = fit(resolve_model(str(args.model)), args.sim, args.out, cfg, frames=args.frames,
                  progress=not args.quiet)
    first = summary["history"][0]["val_miou_zbuffer"]
    print(f"label head in {summary['seconds'] / 60:.1f} min: validation mIoU on the simulated "
          f"scenes {first:.3f} (z-buffer) -> {summary['best_val_miou']:.3f} (head); model with "
          f"the head: {summary['model']} (tau {summary['tau']:.2f}); ship it with `inseggan "
          "export --checkpoint` it and `--label-head on`")
    return 0


def _model_and_piles(p) -> None:
    """--model and --sim of the commands that teach a network on the loop's piles."""
    p.add_argument("--model", type=Path, required=True,
                   help="a checkpoint (the loop's OUT/encoder/best.pt) or model.pt")
    p.add_argument("--sim", type=Path, required=True,
                   help="a simulated data set of the model's learned part (train, val)")


def cmd_centres(args) -> int:
    from inseggan_ros.learning.centres import CentreConfig, fit
    from inseggan_ros.core.paths import resolve_model

    import torch

    if args.threads < 1:
        raise ValueError(f"--threads {args.threads} invalid; valid: >= 1")
    if args.as_bag and args.self_labels:
        raise ValueError("--as-bag cuts simulated piles as a recording's frames; --self-labels "
                         "frames are cut as the model cuts them already; valid: one of them")
    torch.set_num_threads(args.threads)
    cfg = CentreConfig(width=args.width, iterations=args.iterations, batch=args.batch,
                       lr=args.lr, seed=args.seed, eval_every=min(500, args.iterations))
    summary = fit(resolve_model(str(args.model)), args.sim, args.out, cfg, frames=args.frames,
                  progress=not args.quiet, self_labels=args.self_labels,
                  as_given=args.as_bag, held_out=args.held_out, workers=args.threads,
                  teacher_votes=args.teacher_centre_votes,
                  teacher_settings=args.teacher_settings)
    chosen = ("held-out self-labelled frames" if args.self_labels else "simulated scenes")
    print(f"centre votes in {summary['seconds'] / 60:.1f} min: validation mIoU on the "
          f"{chosen} {summary['best_val_miou']:.3f}; model with them: "
          f"{summary['model']} (centre_votes: on); ship it with `inseggan export --checkpoint` "
          "it, or measure it with `inseggan eval --model` it")
    return 0


def cmd_eval(args) -> int:
    from inseggan_ros.data import datasets as data_mod
    from inseggan_ros.evaluation import evaluate
    from inseggan_ros.core.paths import resolve_model
    from inseggan_ros.runtime.segment import Segmenter

    import torch

    if args.threads < 1:
        raise ValueError(f"--threads {args.threads} invalid; valid: >= 1")
    torch.set_num_threads(args.threads)
    seg = Segmenter.from_checkpoint(resolve_model(str(args.model)), device=args.device)
    seg.inference = settings.resolve(seg.inference, args, seg.stored_settings)
    n = seg.model_cfg.n_instances
    if args.data:
        d = data_mod.load_sim_split(args.data, args.split, seg.prep_cfg, limit=args.frames)
        source = f"{args.data} ({args.split})"
    else:
        d = data_mod.load_bag(args.bag, seg.prep_cfg, depth_topic=args.topic, limit=args.frames)
        source = str(args.bag)
    if d.get("labels") is None:
        raise ValueError(f"{source}: no ground-truth labels to evaluate against")
    methods = args.methods.split(",") if args.methods else None
    results = evaluate.run_methods(d, n, seg, methods, progress=not args.quiet)
    summary = evaluate.summarise(results, len(d["x"]))
    summary.update({"model": str(args.model), "data": source, "tau": seg.tau,
                    **seg.inference.to_dict(), "smooth_iters": seg.inference.smooth.iters})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    evaluate.write_json(out / "results.json", summary)
    evaluate.qualitative_png(out / "qualitative.png", d, results)
    print(f"{source}: {summary['frames']} frames, {summary['hard_frames']} hard "
          f"({summary['hard_rule']}); model {args.model}, tau {seg.tau:.2f}, "
          f"{seg.inference.refine_steps} refinement steps x "
          f"{seg.inference.refine_hypotheses} starts"
          + (f" (best {seg.inference.refine_keep} refined)" if seg.inference.refine_keep else "")
          + (f", {seg.inference.refine_swaps} swaps" if seg.inference.refine_swaps else "")
          + f", {seg.inference.smooth.iters} smoothing iterations")
    print(evaluate.format_table(summary))
    print(f"wrote {out / 'results.json'} and {out / 'qualitative.png'}")
    return 0


def cmd_card_run(args) -> int:
    from inseggan_ros.evaluation.modelcard import add_training_run

    r = add_training_run(args.model, args.checkpoint, args.eval, args.label, args.hardware)
    print(f"{args.model}: run {r['label']!r} ({r['iterations']} iterations, "
          f"{r['wall_minutes']} min on {r['hardware']}): test mIoU {r['miou_all']:.3f}; "
          "card and README written")
    return 0


def _also_profiles(args, base) -> dict:
    """{file stem: InferenceConfig} of each --also-profile FILE, applied to `base` (the settings
    the model ships with) as the segmenter node applies a parameters file to the model's own:
    what the file leaves out stays the model's (a part's own superpixel scale, say), so that
    each row of the card is what the node does with that file."""
    return {Path(f).stem: settings.apply(base, settings.read_params_file(f))
            for f in args.also_profile or []}


def cmd_card_settings(args) -> int:
    from inseggan_ros.evaluation.modelcard import apply_settings
    from inseggan_ros.runtime.segment import Segmenter

    t0 = time.perf_counter()
    seg = Segmenter.from_checkpoint(Path(args.model) / "model.pt", device="cpu")
    inference = settings.resolve(seg.inference, args, seg.stored_settings)
    also = _also_profiles(args, inference)
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
    also = _also_profiles(args, inference)
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


def cmd_check(args) -> int:
    """Segment a few frames of a bag: a PNG sheet and the label-free measures."""
    import torch

    from inseggan_ros.evaluation import selfcheck
    from inseggan_ros.core.paths import resolve_bag, resolve_model
    from inseggan_ros.runtime.segment import Segmenter

    if args.frames < 1:
        raise ValueError(f"--frames {args.frames} invalid; valid: >= 1")
    torch.set_num_threads(1)  # as the node runs by default
    model = resolve_model(str(args.model), "--model")
    seg = Segmenter.from_checkpoint(model, device="cpu")
    seg.inference = settings.resolve(seg.inference, args, seg.stored_settings)
    bag = resolve_bag(str(args.bag), "--bag")
    frames = selfcheck.load_bag_frames(bag, seg.prep_cfg, args.topic, count=args.frames)
    out = selfcheck.segment_frames(seg, frames["x"], frames["fg"])
    m = selfcheck.measure(seg, frames["x"], frames["fg"], out)
    selfcheck.sheet_png(args.out, frames["x"], out, frames=range(len(frames["x"])))
    print(f"{model} on {bag} (frames {', '.join(map(str, frames['index']))}):")
    print(selfcheck.format_measures(m))
    print(f"wrote {args.out}: input | reconstruction | labels | each instance rendered alone")
    return 0


def cmd_bench_sim(args) -> int:
    from tools import bench_sim as benchmark

    r = benchmark.run(_scene_config(args), scenes=args.scenes, workers=args.workers)
    print(f"simulator benchmark: {r['instances']} x {r['object']} at {r['resolution']}, "
          f"{r['scenes']} scenes")
    print(f"  one core : {r['one_core_scenes_per_s']:7.1f} scenes/s  "
          f"({r['ms_per_scene']:.1f} ms/scene:"
          f" physics {r['ms_physics']:.1f} ms, render {r['ms_render']:.1f} ms)")
    if "workers" in r:
        print(f"  {r['workers']} workers: {r['parallel_scenes_per_s']:7.1f} scenes/s  "
              f"(x{r['parallel_scaling']:.2f} of one core)")
    print(f"  vs the paper's PhysX pipeline (~2 s/scene): x{r['speedup_vs_paper_physx']:.0f}")
    if (r["resolution"], r["instances"]) == ("224x224", 5):
        met = "met" if r["one_core_scenes_per_s"] >= 25 else "NOT met"
        print(f"  target >= 25 scenes/s per core (224x224, 5 objects): {met}")
    if args.json:
        from inseggan_ros.evaluation.evaluate import write_json

        write_json(args.json, r)  # atomic
    return 0


def cmd_contact_sheet(args) -> int:
    from inseggan_ros.core import viz
    from inseggan_ros.sim.objects import OBJECTS
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    base = _scene_config(args)
    rows, titles = [[], [], []], []
    for name in OBJECTS:
        cfg = SceneConfig(**{**base.__dict__, "object": name})
        with BinSimulator(cfg) as sim:
            for k in range(args.per_object):
                s = sim.render(args.seed + k)
                rows[0].append(viz.colorize_depth(s.depth))
                rows[1].append(viz.colorize_labels(s.labels))
                rows[2].append(viz.overlay(s.depth, s.labels))
                titles.append(name)
    viz.save_sheet(args.out, rows, col_titles=titles,
                   row_titles=["depth", "ground-truth labels", "overlay"])
    print(f"wrote {args.out}: {len(OBJECTS)} objects x {args.per_object} scene(s)")
    return 0


def cmd_bag_info(args) -> int:
    from inseggan_ros.io.bags import list_topics, read_frames

    topics = list_topics(args.bag)
    print(f"{args.bag}:")
    for t, (typ, n) in sorted(topics.items()):
        print(f"  {t}  [{typ}]  {n} messages")
    frames = list(read_frames(args.bag, depth_topic=args.topic, limit=1))
    if frames:
        f = frames[0]
        print(f"  depth: {f.depth.shape[1]}x{f.depth.shape[0]} {f.encoding}, frame_id "
              f"{f.frame_id!r}, labels {'yes' if f.labels is not None else 'no'}, camera_info "
              f"{'yes' if f.camera_info is not None else 'no'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="inseggan", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate a data set of bins (npz shards, optional bags)")
    _add_scene_args(p)
    p.add_argument("--count", type=int, default=1000, help="scenes in all (default 1000)")
    p.add_argument("--split", type=_fractions, default=(0.8, 0.1, 0.1),
                   help="train,val,test fractions (default 0.8,0.1,0.1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--shard-size", type=int, default=128)
    p.add_argument("--bags", action="store_true", help="also write a rosbag2 (MCAP) per split")
    p.add_argument("--bag-encoding", default="16UC1", choices=["16UC1", "32FC1"])
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--camera-from", type=Path, metavar="BAG",
                   help="the camera (and bin inner size) estimated from up to 30 depth frames "
                        "of a bag with a sensor_msgs/CameraInfo beside them, instead of "
                        "--camera PRESET (--tilt, --roll, --bin-offset, --width, --height "
                        "still override)")
    p.add_argument("--topic", help="with --camera-from: the depth topic (default: auto)")
    p.set_defaults(func=cmd_simulate, camera=None)  # None: not given (default preset)

    p = sub.add_parser("simulate-bag", help="simulate bins straight into a rosbag2 bag")
    _add_scene_args(p)
    p.add_argument("--count", type=int, default=20, help="frames (default 20)")
    p.add_argument("--seed", type=int, default=0,
                   help="frame k is scene_seed(seed, 'test', k), as bin_replay publishes")
    p.add_argument("--rate", type=float, default=10.0, help="recorded frame rate, Hz")
    p.add_argument("--encoding", default="16UC1", choices=["16UC1", "32FC1"])
    p.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"])
    p.add_argument("--compression", choices=["zstd", "none"],
                   help="MCAP chunk compression (default zstd for mcap, none for sqlite3)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, type=Path, help="bag directory to create")
    p.set_defaults(func=cmd_simulate_bag)

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

    p = sub.add_parser("card-run", help="record another training run of the part (another "
                                        "config, a GPU) on a model card, with its test scores")
    p.add_argument("model", type=Path, help="a model folder (models/<name>)")
    p.add_argument("--checkpoint", type=Path, required=True, help="the run's checkpoint")
    p.add_argument("--eval", type=Path, required=True,
                   help="its `inseggan eval` results.json on the card's test split")
    p.add_argument("--label", required=True, help="the run's name on the card")
    p.add_argument("--hardware", required=True, help="what it trained on, e.g. 'NVIDIA H200'")
    p.set_defaults(func=cmd_card_run)

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

    p = sub.add_parser("check", help="segment a few frames of a bag: PNG sheet and label-free "
                                     "measures")
    p.add_argument("--model", required=True,
                   help="model folder, model.pt or a shipped model's name")
    p.add_argument("--bag", required=True, help="bag path or a shipped bag's name")
    p.add_argument("--topic", help="depth topic (default: auto)")
    p.add_argument("--frames", type=int, default=6, help="frames spread over the bag (6)")
    settings.add_flags(p, "(default: the model's)")
    p.add_argument("--out", type=Path, default=Path("check.png"), help="PNG sheet (check.png)")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("bench-sim", help="simulator throughput (scenes/s)")
    _add_scene_args(p)
    p.add_argument("--scenes", type=int, default=100)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.set_defaults(func=cmd_bench_sim)

    p = sub.add_parser("contact-sheet", help="PNG of a simulated bin of every object")
    _add_scene_args(p)
    p.add_argument("--per-object", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="contact_sheet.png")
    p.set_defaults(func=cmd_contact_sheet)

    p = sub.add_parser("train", help="train InSeGAN on a simulated data set or a bag")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="simulated data set (inseggan simulate)")
    src.add_argument("--bag", type=Path, help="rosbag2 bag of depth frames (unlabelled)")
    p.add_argument("--topic", help="depth topic in the bag (default: auto)")
    p.add_argument("--roi", help="bin region x0,y0,x1,y1 in pixels for bags (default: found)")
    p.add_argument("--min-height", type=float, default=0.006, help="metres above the floor")
    p.add_argument("--max-height", type=float, default=0.05, help="metres mapped to +1")
    p.add_argument("--config", default="cpu_spheres",
                   help="named config: cpu_spheres (default), cpu_convex, cpu, paper_cpu, paper")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--minutes", type=float, help="wall-clock budget")
    p.add_argument("--iterations", type=int, help="iteration budget")
    p.add_argument("--batch-size", type=int)
    p.add_argument("--nf", type=int)
    p.add_argument("--instances", type=int,
                   help="n, the parts per bin (default: the simulated data set's; with --bag, 5)")
    p.add_argument("--composite", choices=["average", "zbuffer"])
    p.add_argument("--lambda-real", type=float)
    p.add_argument("--matching", choices=["hungarian", "ot", "greedy"])
    p.add_argument("--rotate", action="store_true", help="augment with +-20 degree rotations")
    p.add_argument("--r1-gamma", type=float, help="R1 penalty weight on real frames")
    p.add_argument("--spectral-norm", action="store_true", help="in the discriminator")
    p.add_argument("--renderer", choices=["learned", "spheres", "convex"])
    p.add_argument("--lr-template", type=float, help="learning rate of an explicit template")
    p.add_argument("--compactness", type=float, help="weight of the template compactness prior")
    p.add_argument("--spheres", type=int,
                   help="spheres on the rod template (6): a rod of K spheres is at most about "
                        "K / 2 times as long as it is thick (long thin parts: more)")
    p.add_argument("--coord-conv", action="store_true", help="encoder sees pixel coordinates")
    p.add_argument("--recon-levels", type=int, help="pyramid levels of the re-render losses")
    p.add_argument("--floor-contact", action="store_true",
                   help="sphere rods: an instance reaching below the floor is lifted onto it")
    p.add_argument("--template-from-gan", action="store_true",
                   help="the real-frame loss trains the poses, not the explicit template")
    p.add_argument("--background-weight", type=float,
                   help="real-frame loss: weight of floor pixels (> 1: precision first)")
    p.add_argument("--real-trains-generator", action="store_true",
                   help="the real-frame reconstruction loss also trains the generator")
    p.add_argument("--eval-every", type=int)
    p.add_argument("--train-frames", type=int, help="use at most this many training frames")
    p.add_argument("--val-frames", type=int, default=200)
    p.add_argument("--seed", type=int)
    p.add_argument("--device", default="auto", help="auto, cpu, cuda")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("distill", help="fine-tune a model's encoder on its own refined poses")
    p.add_argument("--checkpoint", type=Path, required=True, help="training checkpoint (best.pt)")
    p.add_argument("--data", type=Path, required=True, help="its simulated data set")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--frames", type=int, default=4000, help="pseudo-labelled frames (4000)")
    p.add_argument("--refine-steps", type=int, default=24,
                   help="pseudo-labels: refinement iterations (24) ...")
    p.add_argument("--hypotheses", type=int, default=8, help="... from this many starts (8)")
    p.add_argument("--iterations", type=int, default=6000, help="encoder iterations (6000)")
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lr-schedule", choices=("constant", "cosine"), default="constant",
                   help="constant (default) or cosine: down to 0 at the last iteration")
    p.add_argument("--encoder-nf", type=int, default=0,
                   help="0: fine-tune the checkpoint's encoder (default); N: an encoder of width "
                        "N (a multiple of 8; narrower is faster), pruned from the checkpoint's "
                        "or, wider, widened from it")
    p.add_argument("--pose-weight", type=float, default=1.0,
                   help="weight of the loss on the refined poses (1; 0: no pseudo-labels)")
    p.add_argument("--label-weight", type=float, default=0.0,
                   help="weight of the loss on the data set's ground-truth labels (0): for "
                        "simulated scenes of the part (`inseggan simulate --object model.pt`)")
    p.add_argument("--ownership-weight", type=float, default=0.0,
                   help="with the labels: weight of the cross-entropy of each pixel's true "
                        "instance under the soft z-buffer (0; 0.2 with --label-weight 1 was the "
                        "best measured)")
    p.add_argument("--user-data", type=Path, default=None,
                   help="the user's own data set: its training frames (not their labels) are "
                        "reconstructed too, a second batch each iteration (with --user-weight)")
    p.add_argument("--user-weight", type=float, default=0.0,
                   help="weight of that reconstruction loss (0: off)")
    p.add_argument("--user-frames", type=int, default=3000,
                   help="at most this many of the user's frames (3000)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_distill)

    p = sub.add_parser("shape-fit", help="fit a convex template (a box, a prism) to the "
                                         "user's unlabelled frames, starting from a rod model")
    p.add_argument("--model", type=Path, required=True,
                   help="a rod model: a model folder or training checkpoint")
    _frames_args(p)
    p.add_argument("--out", type=Path, required=True,
                   help="run directory (resumable): best.pt (the model), last.pt, log.jsonl, "
                        "curves.png")
    p.add_argument("--pieces", type=int, default=1, help="convex pieces (1)")
    p.add_argument("--walls", type=int, default=4, help="side planes of each piece (4: a box)")
    p.add_argument("--iterations", type=int, default=1500,
                   help="(1500; 0: the starting template, measured on the frames, not fitted)")
    p.add_argument("--frames", type=int, default=1000,
                   help="the user's training frames fitted to (1000)")
    p.add_argument("--eval-every", type=int, default=250, help="(250)")
    p.add_argument("--thickness", choices=("data", "rod"), default="data",
                   help="the starting box's height: the frames' flat-lying parts' (data) or the "
                        "rod's diameter (rod)")
    p.add_argument("--start", choices=("box", "discs"), default="box",
                   help="the starting template: a box, every piece a copy (box), or the rod's "
                        "radius profile as a stack of PIECES flat-ended discs (discs: a head on a "
                        "shaft, a flange)")
    p.add_argument("--match-piles", action="store_true",
                   help="with --start discs: the widest disc's length and radius chosen by "
                        "simulating piles of variants in the user's bin and keeping the one "
                        "whose heights look most like the frames' (pilematch; OUT/match)")
    _pile_grid_args(p)
    p.add_argument("--workers", type=int, default=1,
                   help="simulation processes of --match-piles (1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_shape_fit)

    p = sub.add_parser("loop", help="finish a model on labelled simulated piles of the shape "
                                    "it learned, and ship it with a label-free card")
    p.add_argument("--model", type=Path,
                   help="a trained model: checkpoint (best.pt) or model folder; without it the "
                        "loop learns the shape first (`inseggan train` on the data set's "
                        "unlabelled frames, into OUT/shape)")
    p.add_argument("--config", default="cpu_spheres",
                   help="without --model: the training config (cpu_spheres)")
    p.add_argument("--spheres", type=int, help="without --model: the rod's sphere count")
    p.add_argument("--train-minutes", type=float,
                   help="without --model: the shape's training budget in minutes (the config's "
                        "when neither this nor --train-iterations is given)")
    p.add_argument("--train-iterations", type=int)
    p.add_argument("--train-seed", type=int, default=1)
    p.add_argument("--eval-every", type=int, default=100,
                   help="without --model: validate and checkpoint every N iterations (100)")
    _frames_args(p)
    p.add_argument("--out", type=Path, required=True, help="run directory (resumable)")
    p.add_argument("--scenes", type=int, default=3000, help="simulated training scenes (3000)")
    p.add_argument("--val-scenes", type=int, default=200)
    p.add_argument("--iterations", type=int, default=3000,
                   help="encoder iterations (3000; 0: no encoder stage, the model's own "
                        "encoder, with --centre-iterations or --head-iterations)")
    p.add_argument("--lr", type=float, default=3e-4, help="their learning rate (3e-4, cosine)")
    p.add_argument("--seed", type=int, default=11, help="of the simulated scenes (11)")
    p.add_argument("--workers", type=int, default=1,
                   help="simulation and self-labelling processes (1)")
    p.add_argument("--user-weight", type=float, default=0.0,
                   help="the encoder also reconstructs the data set's own training frames "
                        "(not their labels), with this weight (0: off)")
    p.add_argument("--head-iterations", type=int, default=0,
                   help="also train a label head on the same piles for this many iterations "
                        "and ship the model with it on (0, the default: none; measured: "
                        "docs/experiments.md, 2026-11-25, a label head)")
    p.add_argument("--centre-iterations", type=int, default=0,
                   help="also train centre votes (`inseggan centres`) on the same piles for "
                        "this many iterations and ship the model with them on (0, the "
                        "default: none)")
    p.add_argument("--centre-teacher", choices=("piles", "self-labels"), default="piles",
                   help="what teaches the centre votes: the same piles' labels (piles, the "
                        "default), or the user's training frames labelled by the model itself "
                        "(self-labels; no label read; better where the learned shape is not "
                        "the real part's: docs/experiments.md, 2026-11-29)")
    p.add_argument("--self-frames", type=int, default=0,
                   help="then fit the encoder further to the model's own labels (at "
                        "--self-settings) of this many of the user's training frames, no label "
                        "read (0, the default: no such stage; measured: docs/experiments.md, "
                        "2026-11-26); run again on a finished loop's OUT, it adds only this")
    p.add_argument("--self-iterations", type=int, default=1500,
                   help="with --self-frames: encoder iterations (1500; the last is kept)")
    p.add_argument("--self-settings", default="quality",
                   help="with --self-frames: the settings that label the frames (quality)")
    p.add_argument("--export-settings", default="realtime",
                   help="the exported model's own settings, as the node and its card use "
                        "them (realtime)")
    p.add_argument("--size-by-thickness", nargs="?", const="on", default="auto",
                   choices=("auto", "on", "off"),
                   help="before the first simulation, resize the rod to the thickness of the "
                        "parts in the user's frames (no label read). auto, the default: only "
                        "a rod the loop learns itself (no --model) that came out elongated; "
                        "on (the option alone): any rod; off (measured: docs/experiments.md, "
                        "2026-11-27)")
    p.add_argument("--size-keep-length", action="store_true",
                   help="the thickness rule thins the rod's spheres and keeps its length (more "
                        "spheres where they need them to overlap): for a long, thin part whose "
                        "rod came out thick, such as a bolt (docs/experiments.md, 2026-11-28)")
    p.add_argument("--size-rounds", type=int, default=None,
                   help="after the encoder, up to N rounds of: the rod's scale chosen by how "
                        "well it explains the user's frames, and where it is not 1, the "
                        "simulation and the encoder again at that scale (default: 2 for a rod "
                        "the loop learns itself, 0 with --model)")
    p.add_argument("--vote-scales", type=_vote_scales, default=VOTE_SCALES,
                   help="at export, the superpixel vote's scale chosen among these on the "
                        "simulated piles' validation split, whose labels are the loop's own "
                        "(default: " + ",".join(map(str, VOTE_SCALES)) + "; none: the export "
                        "settings' own scale; measured: docs/experiments.md, 2026-11-28, "
                        "evening)")
    p.add_argument("--match-piles", action="store_true",
                   help="with a rod: the piles are of a disc template cut from it, its widest "
                        "disc sized (and the whole stretched) by how each variant's piles look "
                        "against the user's frames (pilematch; OUT/match; no size stage then). "
                        "Tilted bolts: docs/experiments.md, 2026-12-02")
    _pile_grid_args(p)
    p.add_argument("--match-pieces", type=int, default=2,
                   help="--match-piles: the template's discs (2: a head on a shaft; 3: a flange; "
                        "1 with --match-walls 12 and --pile-holes: a hexagonal nut)")
    p.add_argument("--match-walls", type=int, default=8,
                   help="--match-piles: side planes of each disc (8)")
    p.add_argument("--match-seed", type=int, default=0,
                   help="--match-piles: of the variants' piles (0)")
    p.add_argument("--convex-pieces", type=int, default=0,
                   help="with a rod: the rod becomes a convex template of this many pieces (a "
                        "box, a prism: flat faces, sharp edges), fitted to the user's frames by "
                        "reconstruction as `shape-fit` fits it (OUT/convex), and the piles are "
                        "of it; no size stage then (0, the default: the rod's own piles). "
                        "Tilted wooden blocks: docs/experiments.md, 2026-12-04")
    p.add_argument("--convex-walls", type=int, default=4,
                   help="--convex-pieces: side planes of each piece (4: a box)")
    p.add_argument("--convex-iterations", type=int, default=1500,
                   help="--convex-pieces: iterations of the fit (1500)")
    p.add_argument("--name", default="model", help="the exported model's name")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_loop)

    p = sub.add_parser("self-fit", help="fit a model's encoder further to its own labels (at "
                                        "the quality settings) of the user's unlabelled frames, "
                                        "and ship it with a label-free card")
    p.add_argument("--model", type=Path, required=True,
                   help="a model folder or checkpoint (the loop's OUT/encoder/best.pt keeps "
                        "the card's account of the loop)")
    _frames_args(p)
    p.add_argument("--out", type=Path, required=True,
                   help="run directory (resumable): last.pt, labels.npz, model/")
    p.add_argument("--frames", type=int, default=1500,
                   help="the user's training frames labelled and fitted to (1500)")
    p.add_argument("--iterations", type=int, default=1500, help="encoder iterations (1500)")
    p.add_argument("--settings", default="quality",
                   help="the settings that label the frames: a parameters file or a shipped "
                        "one's name (quality)")
    p.add_argument("--workers", type=int, default=2, help="labelling processes (2)")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--export-settings", default="realtime",
                   help="the exported model's own settings, as the node and its card use "
                        "them (realtime)")
    p.add_argument("--name", default="model", help="the exported model's name")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_self_fit)

    p = sub.add_parser("head", help="train a label head for a model on labelled simulated "
                                    "scenes (the loop's OUT/sim)")
    _model_and_piles(p)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--iterations", type=int, default=1000, help="(1000)")
    p.add_argument("--width", type=int, default=8, help="channels at 64 x 64 (8)")
    p.add_argument("--batch", type=int, default=32, help="scenes per iteration (32)")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--scale-jitter", type=float, default=0.0,
                   help="the template's length and thickness scaled at random by up to 1 + "
                        "this while training (0: off; 0.3 was worse on the cone)")
    p.add_argument("--shift-jitter", type=float, default=0.0,
                   help="instances moved at random by up to this many pixels (0: off)")
    p.add_argument("--frames", type=int, help="scenes per split at most (default: all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_head)

    p = sub.add_parser("centres", help="train centre votes for a model on labelled simulated "
                                       "scenes (the loop's OUT/sim), or on the user's own "
                                       "frames labelled by the model (--self-labels)")
    _model_and_piles(p)
    p.add_argument("--out", type=Path, required=True,
                   help="output folder; a killed run started again resumes from its last.pt")
    p.add_argument("--iterations", type=int, default=3000, help="(3000)")
    p.add_argument("--width", type=int, default=16, help="channels at 64 x 64 (16)")
    p.add_argument("--batch", type=int, default=32, help="scenes per iteration (32)")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--frames", type=int, help="scenes per split at most (default: all)")
    p.add_argument("--self-labels", action="store_true",
                   help="--sim is the user's own data set (its training frames) or recording "
                        "(a bag: all its frames), labelled by the model itself (no true label "
                        "read), to teach the net, for a part whose learned shape is not the "
                        "real one")
    p.add_argument("--held-out", type=int, default=200,
                   help="with --self-labels: the last training frames kept out to choose the "
                        "iteration by (200)")
    p.add_argument("--as-bag", action="store_true",
                   help="--sim's scenes cut as a recording's frames are (the bin and floor "
                        "found in every frame, not the data set's known ones): for a model "
                        "learned from a bag, taught on piles seen through its camera "
                        "(`simulate --camera-from`), as the loop cuts them")
    p.add_argument("--teacher-centre-votes", action="store_true",
                   help="with --self-labels: the model labels with its own centre votes on "
                        "(the model as it ships; it must have them), not the z-buffer's "
                        "labels: a second round, or a net taught on piles as the teacher")
    p.add_argument("--teacher-settings", default="own",
                   help="with --self-labels: the settings the model labels with, a parameters "
                        "file or a shipped one's name (e.g. quality), or own: its stored "
                        "settings (own)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2,
                   help="threads to train with, and with --self-labels processes to label "
                        "with (2)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_centres)

    p = sub.add_parser("eval", help="InSeGAN vs classical baselines (mIoU table, PNG)")
    p.add_argument("--model", type=Path, required=True)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="simulated data set")
    src.add_argument("--bag", type=Path, help="bag with ground-truth labels")
    p.add_argument("--split", default="test", choices=["train", "val", "test"])
    p.add_argument("--topic")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--methods", help="comma-separated baselines (default: all)")
    settings.add_flags(p, "(default: the model's)")
    p.add_argument("--device", default="auto")
    p.add_argument("--threads", type=int, default=1,
                   help="CPU threads for inference (default 1, as the model cards and the node; "
                        "the pick among refinement starts can tip with another count's rounding)")
    p.add_argument("--out", type=Path, default=Path("eval_out"))
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("bag-info", help="topics and depth format of a rosbag2 bag")
    p.add_argument("bag")
    p.add_argument("--topic", help="depth topic (default: auto)")
    p.set_defaults(func=cmd_bag_info)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (BagError, CheckpointError, ValueError, FileExistsError, FileNotFoundError) as e:
        print(f"inseggan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"inseggan {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
