"""`inseggan eval`: a model against the classical baselines on labelled frames."""
from __future__ import annotations

import argparse
from pathlib import Path

from inseggan_ros.core import settings


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


def add_eval(sub) -> argparse.ArgumentParser:
    """The `eval` command's options."""
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
    return p
