"""Where a model's mIoU is lost: whole parts (missed, merged, read twice) or their outlines.

    python scripts/experiments/error_kinds.py MODEL DATA [--split val] [--frames N]

For every ground-truth instance of every frame, its best IoU over the predicted instances (the
paper's mIoU averages these). An instance below 0.5 is a *gross* error: no prediction covers most
of it. Prints the mIoU, the share of ground-truth instances with a gross error, and what the mIoU
would be if every gross error scored the frame's median outline IoU instead, for the model at
its shipped settings and for Felzenszwalb on the same frames; and the ceiling of the vote
within depth superpixels: each superpixel of the model's scale given its true plurality label.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from inseggan_ros.metrics import instance_ious


def gross_kind(pred: np.ndarray, gt: np.ndarray, g: int) -> str:
    """Why ground-truth instance g has no prediction covering most of it."""
    gm = gt == g
    ids, counts = np.unique(np.where(gt > 0, pred, 0)[gm], return_counts=True)
    share = dict(zip(ids.tolist(), (counts / gm.sum()).tolist()))
    if share.get(0, 0) > 0.5:
        return "background"
    top = max((i for i in share if i != 0), key=share.get)
    others = [h for h in np.unique(gt[(pred == top) & (gt > 0)]) if h != g]
    owner = max(others, key=lambda h: ((pred == top) & (gt == h)).sum(), default=None)
    if owner is not None and ((pred == top) & (gt == owner)).sum() > ((pred == top) & gm).sum():
        return "merged"  # its main prediction belongs mostly to another part
    if share[top] < 0.6:
        return "split"
    return "oversized"  # one prediction covers it but spills far beyond


def report(name: str, labels: np.ndarray, gt: np.ndarray) -> None:
    per_frame, gross, fixed = [], 0, []
    kinds = {}
    total = 0
    for p, g in zip(labels, gt):
        ious = instance_ious(p, g)  # in the order of np.unique(g[g > 0])
        if ious.size == 0:
            continue
        for gi, iou in zip(np.unique(g[g > 0]), ious):
            if iou < 0.5:
                k = gross_kind(p, g, gi)
                kinds[k] = kinds.get(k, 0) + 1
        total += ious.size
        per_frame.append(ious.mean())
        bad = ious < 0.5
        gross += bad.sum()
        good = ious[~bad]
        med = np.median(good) if good.size else 0.0
        fixed.append(np.where(bad, med, ious).mean())
    print(f"{name:14s} mIoU {np.mean(per_frame):.4f}  gross {gross}/{total} "
          f"({gross / total:.3f})  with gross errors at the outline median {np.mean(fixed):.4f}"
          f"  kinds {kinds}")


def superpixel_oracle(x: np.ndarray, gt: np.ndarray, scale: int) -> np.ndarray:
    from inseggan_ros.superpixels import depth_superpixels

    fg = x > -1 + 1e-4
    sp = depth_superpixels(x, fg, scale=scale)
    out = np.zeros_like(gt)
    for s in np.unique(sp[fg]):
        m = (sp == s) & fg
        out[m] = np.bincount(gt[m].ravel()).argmax()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model")
    ap.add_argument("data")
    ap.add_argument("--split", default="val")
    ap.add_argument("--frames", type=int, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    from inseggan_ros import data as data_mod, evaluate
    from inseggan_ros.metrics import mean_miou, miou_batch
    from inseggan_ros.paths import resolve_model
    from inseggan_ros.segment import Segmenter

    seg = Segmenter.from_checkpoint(resolve_model(args.model), device="cpu")
    d = data_mod.load_sim_split(args.data, args.split, seg.prep_cfg, limit=args.frames)
    res = evaluate.run_methods(d, seg.model_cfg.n_instances, seg, ["felzenszwalb"],
                               progress=False)
    for name in ("inseggan", "felzenszwalb"):
        report(name, res[name]["labels"], d["labels"])
    scale = seg.inference.superpixel_scale or 50
    oracle = [superpixel_oracle(x[0], gt, scale) for x, gt in zip(d["x"], d["labels"])]
    print(f"superpixels at scale {scale}, each given its true plurality label: mIoU "
          f"{mean_miou(miou_batch(oracle, d['labels'])):.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
