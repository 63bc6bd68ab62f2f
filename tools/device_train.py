"""Train on a GPU machine that has PyTorch but not the simulator, ROS or the full data set.

A simulated data set is thousands of 224 x 224 frames in npz shards; what training reads is the
preprocessed 64 x 64 model input. `pack` writes that input (and the validation labels) into one
compressed file small enough to copy to such a machine; `train` runs `learning.train.train`
on it, exactly as `inseggan train --data` would, and writes a slim copy of the best checkpoint
(generator, encoder, configs, tau: what `inseggan export` and `inseggan eval` read; no optimiser
or discriminator state; with --half its weights in float16) so that it can be copied back.

    python tools/device_train.py pack --data data/cone --out packed/cone.npz
    python tools/device_train.py pack --bag bags/tilted --instances 5 --out packed/tilted.npz
    python tools/device_train.py train --packed packed/cone.npz --config paper \
        --minutes 7 --out runs/cone_paper_gpu --device cuda

The loop's encoder stage, too: `pack --with-labels` on the simulated piles of a learned part
(`inseggan loop`'s sim/ folder), then `distill` from the shape stage's checkpoint with the
loop's settings (labels, ownership 0.2, cosine learning rate), any number of iterations.
And `shape-fit` (`inseggan_ros.learning.shapefit`) from a rod model on the packed training frames.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inseggan_ros.core import checkpoint  # noqa: E402
from inseggan_ros.runtime.preprocess import PreprocessConfig  # noqa: E402
from inseggan_ros.learning.train import get_config, train  # noqa: E402

SLIM_KEYS = ("format", "model_config", "train_config", "preprocess_config", "data", "tau",
             "iteration", "elapsed_seconds", "best", "history", "resets", "generator", "encoder")


def pack(args) -> int:
    if (args.data is None) == (args.bag is None):
        raise SystemExit("pack: give --data (a simulated data set) or --bag (a recording)")
    if args.bag is not None:
        if args.instances is None or args.with_labels or args.train_frames is not None:
            raise SystemExit("pack --bag: needs --instances N, and takes every frame before the "
                             "held-out fifth (no --train-frames); the frames have no labels to "
                             "pack (no --with-labels)")
        tr, val, prep, info = recording(args.bag, args.instances, args.topic)
    else:
        from inseggan_ros.data.datasets import load_sim_training

        tr, val, prep, info = load_sim_training(args.data, args.train_frames, progress=True)
    write_packed(args.out, tr, val, prep, info, with_labels=args.with_labels)
    return 0


def write_packed(out: Path, tr: dict, val: dict, prep, info: dict,
                 with_labels: bool = False) -> None:
    """Training frames `tr` (with their labels if `with_labels`) and validation frames `val` as
    one compressed file that `unpack` reads back, written atomically; frames in float16."""
    tmp = out.with_suffix(".tmp.npz")
    out.parent.mkdir(parents=True, exist_ok=True)
    extra = {"train_labels": tr["labels"]} if with_labels else {}
    if val.get("labels") is not None:
        extra["val_labels"] = val["labels"]
    np.savez_compressed(
        tmp, **extra, train_x=tr["x"].astype(np.float16), val_x=val["x"].astype(np.float16),
        val_fg=val["fg"], val_roi=val["roi"],
        val_floor_depth=val["floor_depth"],
        meta=np.frombuffer(json.dumps({"prep": prep.to_dict(), "info": info}).encode(), np.uint8))
    tmp.replace(out)
    print(f"{out}: {len(tr['x'])} training and {len(val['x'])} validation frames, "
          f"{out.stat().st_size / 2**20:.1f} MiB")


def recording(bag: Path, instances: int, topic: str | None):
    """A recording's frames as `inseggan loop --bag` learns the shape from them
    (`loop.bag_shape_frames`; no labels read), its data record saying how many parts a bin
    holds, as a data set's does."""
    from inseggan_ros.learning.loop import BagFrames, bag_shape_frames

    tr, val, prep, info = bag_shape_frames(BagFrames(bag, instances, topic))
    return tr, val, prep, {**info, "instances": instances}


def unpack(path: Path) -> tuple[dict, dict, dict, dict]:
    z = np.load(path)
    meta = json.loads(z["meta"].tobytes().decode())
    prep = PreprocessConfig.from_dict(meta["prep"])
    tr = {"x": z["train_x"].astype(np.float32), "config": prep,
          "labels": z["train_labels"] if "train_labels" in z else None}
    val = {"x": z["val_x"].astype(np.float32), "fg": z["val_fg"],
           "labels": z["val_labels"] if "val_labels" in z else None,  # none from a recording
           "roi": z["val_roi"], "floor_depth": z["val_floor_depth"], "config": prep}
    return tr, val, meta["prep"], meta["info"]


def run(args) -> int:
    tr, val, prep, info = unpack(args.packed)
    n = args.instances or info.get("instances")  # the parts per bin, as `inseggan train` takes
    if n is None:
        print(f"note: {args.packed} does not say how many parts a bin holds (packed before it "
              "did) and no --instances given: the config's n", file=sys.stderr)
    overrides = {"max_minutes": args.minutes, "seed": args.seed, "batch_size": args.batch_size,
                 "nf": args.nf, "spheres": args.spheres, "eval_every": args.eval_every,
                 "checkpoint_every": args.eval_every, "n_instances": n}
    cfg = get_config(args.config, **overrides)
    rod = f" ({cfg.model.spheres} spheres)" if cfg.model.renderer == "spheres" else ""
    print(f"{args.config}: n {cfg.model.n_instances}, nf {cfg.model.nf}, "
          f"{cfg.model.renderer} renderer{rod}, "
          f"batch {cfg.batch_size}, {len(tr['x'])} frames, "
          f"{args.minutes} min on {args.device}", flush=True)
    t0 = time.perf_counter()
    summary = train(cfg, tr, val, args.out, prep, info, device=args.device,
                    progress=not args.quiet)
    print(f"{args.config}: {summary['iterations']} iterations in "
          f"{time.perf_counter() - t0:.0f} s, best validation score {summary['best_score']:.4f}",
          flush=True)
    state = checkpoint.load(args.out / "best.pt", map_location="cpu")
    slim = {k: state[k] for k in SLIM_KEYS if k in state}
    if args.half:  # weights in float16 (`checkpoint.build_models` reads them back as float32)
        for k in ("generator", "encoder"):
            slim[k] = {n: t.half() if t.is_floating_point() else t for n, t in slim[k].items()}
    checkpoint.save(args.out / "slim.pt", slim)
    return 0


def distill(args) -> int:
    from inseggan_ros.learning.distill import DistillConfig, distill as run_distill

    tr, val, _, _ = unpack(args.packed)
    if tr["labels"] is None:
        raise SystemExit(f"{args.packed}: no training labels (pack it with --with-labels)")
    if args.frames is not None:  # the first N piles only
        if not 1 <= args.frames <= len(tr["x"]):
            raise SystemExit(f"--frames {args.frames} invalid; valid: 1..{len(tr['x'])}")
        tr = {**tr, "x": tr["x"][:args.frames], "labels": tr["labels"][:args.frames]}
    iterations = args.iterations
    if args.minutes:  # as many iterations as fit: timed on a short probe run first
        probe = DistillConfig(frames=len(tr["x"]), iterations=100, lambda_pose=0.0,
                              lambda_label=1.0, batch_size=args.batch_size, eval_every=100)
        t0 = time.perf_counter()
        run_distill(args.checkpoint, tr["x"], None, args.out / "probe", probe, progress=False,
                    train_labels=tr["labels"], device=args.device)
        iterations = int(100 / (time.perf_counter() - t0) * args.minutes * 60 * 0.9)
        print(f"probe: {iterations} iterations fit in {args.minutes} min", flush=True)
    cfg = DistillConfig(frames=len(tr["x"]), iterations=iterations, lr=args.lr,
                        lr_schedule="cosine", eval_every=args.eval_every, lambda_pose=0.0,
                        lambda_label=1.0, lambda_ownership=args.ownership_weight,
                        batch_size=args.batch_size, seed=args.seed, eval_frames=len(val["x"]))
    s = run_distill(args.checkpoint, tr["x"], val, args.out, cfg, progress=not args.quiet,
                    train_labels=tr["labels"], device=args.device)
    print(f"distilled {s['iterations']} iterations in {s['seconds']:.0f} s, best validation "
          f"mIoU {s['best_score']:.4f}", flush=True)
    return 0


def shape_fit(args) -> int:
    from inseggan_ros.learning.shapefit import ShapeFitConfig, fit_shape

    tr, val, _, _ = unpack(args.packed)
    cfg = ShapeFitConfig(pieces=args.pieces, walls=args.walls, iterations=args.iterations,
                         frames=len(tr["x"]), batch_size=args.batch_size,
                         template_lr=args.template_lr, thickness=args.thickness,
                         eval_every=args.eval_every, seed=args.seed)
    t0 = time.perf_counter()
    s = fit_shape(args.model, tr["x"], args.out, cfg, val_x=val["x"], progress=not args.quiet,
                  device=args.device)
    print(f"shape fit {args.out}: {s['iterations']} iterations in "
          f"{time.perf_counter() - t0:.0f} s, validation L1 {s['first']['recon_l1']:.4f} -> "
          f"{s['last']['recon_l1']:.4f}", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(required=True)
    p = sub.add_parser("pack")
    p.add_argument("--data", type=Path, help="a simulated data set")
    p.add_argument("--bag", type=Path, help="or a recording (depth and CameraInfo)")
    p.add_argument("--instances", type=int, help="with --bag: the parts in the bin")
    p.add_argument("--topic", help="with --bag: the depth topic (default: the only one)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--train-frames", type=int, help="with --data: the first N training frames")
    p.add_argument("--with-labels", action="store_true", help="also the training labels")
    p.set_defaults(func=pack)
    p = sub.add_parser("train")
    p.add_argument("--packed", type=Path, required=True)
    p.add_argument("--config", required=True)
    p.add_argument("--minutes", type=float, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--device", default="auto")
    p.add_argument("--seed", type=int)
    p.add_argument("--batch-size", type=int)
    p.add_argument("--nf", type=int)
    p.add_argument("--spheres", type=int, help="the rod's spheres (renderer 'spheres')")
    p.add_argument("--instances", type=int, help="n (default: the packed data set's)")
    p.add_argument("--eval-every", type=int)
    p.add_argument("--half", action="store_true", help="slim checkpoint's weights in float16")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)
    p = sub.add_parser("distill")
    p.add_argument("--packed", type=Path, required=True)
    p.add_argument("--checkpoint", type=Path, required=True, help="the shape stage's best.pt")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--iterations", type=int, default=3000)
    p.add_argument("--minutes", type=float, help="instead of --iterations: what fits in this")
    p.add_argument("--frames", type=int, help="the first N packed piles (default: all)")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--ownership-weight", type=float, default=0.2)
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--device", default="auto")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=distill)
    p = sub.add_parser("shape-fit")
    p.add_argument("--packed", type=Path, required=True)
    p.add_argument("--model", type=Path, required=True, help="a rod model")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--iterations", type=int, default=1500)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--template-lr", type=float, default=3e-3)
    p.add_argument("--pieces", type=int, default=1)
    p.add_argument("--walls", type=int, default=4)
    p.add_argument("--thickness", default="data")
    p.add_argument("--eval-every", type=int, default=250)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=shape_fit)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
