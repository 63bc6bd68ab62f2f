"""The research commands: each stage of `inseggan loop` on its own (`train`, `distill`,
`shape-fit`, `self-fit`, `head`, `centres`), for experiments and the shipped models' recipes."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from inseggan_ros.cli import common


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


def cmd_self_fit(args) -> int:
    from inseggan_ros.learning.loop import LoopConfig, run_self_fit

    cfg = LoopConfig(self_frames=args.frames, self_iterations=args.iterations,
                     self_settings=args.settings, workers=args.workers, name=args.name,
                     seed=args.seed, export_settings=args.export_settings)
    t0 = time.perf_counter()
    s = run_self_fit(args.model, common.bag_or_data(args), args.out, cfg, progress=not args.quiet)
    print(f"self-fit done in {(time.perf_counter() - t0) / 60:.1f} min ("
          + common.stage_minutes(s["seconds"])
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
    grid = common.pile_grid(args)
    if args.match_piles and args.start != "discs":
        raise ValueError("--match-piles sizes the head of a disc template; valid: with "
                         "--start discs")
    file = _model_file(args.model)
    frames = common.bag_or_data(args)
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


def add_train(sub) -> argparse.ArgumentParser:
    """The `train` command's options."""
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
    return p


def add_distill(sub) -> argparse.ArgumentParser:
    """The `distill` command's options."""
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
    return p


def add_shape_fit(sub) -> argparse.ArgumentParser:
    """The `shape-fit` command's options."""
    p = sub.add_parser("shape-fit", help="fit a convex template (a box, a prism) to the "
                                         "user's unlabelled frames, starting from a rod model")
    p.add_argument("--model", type=Path, required=True,
                   help="a rod model: a model folder or training checkpoint")
    common.frames_args(p)
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
    common.pile_grid_args(p)
    p.add_argument("--workers", type=int, default=1,
                   help="simulation processes of --match-piles (1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_shape_fit)
    return p


def add_self_fit(sub) -> argparse.ArgumentParser:
    """The `self-fit` command's options."""
    p = sub.add_parser("self-fit", help="fit a model's encoder further to its own labels (at "
                                        "the quality settings) of the user's unlabelled frames, "
                                        "and ship it with a label-free card")
    p.add_argument("--model", type=Path, required=True,
                   help="a model folder or checkpoint (the loop's OUT/encoder/best.pt keeps "
                        "the card's account of the loop)")
    common.frames_args(p)
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
    return p


def add_head(sub) -> argparse.ArgumentParser:
    """The `head` command's options."""
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
    return p


def add_centres(sub) -> argparse.ArgumentParser:
    """The `centres` command's options."""
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
    return p
