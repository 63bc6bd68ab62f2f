"""Centre votes averaged over views: the net also reads the frame mirrored and transposed, and its
heatmaps and offsets, mapped back onto the frame, are averaged before decoding (test-time
augmentation, as Panoptic-DeepLab's flips). Measured against one view with each model's own
settings, and the classical baselines on the same frames (docs/experiments.md, 2026-11-29, day:
not shipped, the gains are within the spread between single views).

    python scripts/experiments/centre_views.py models/bolt/model.pt data/bolt --split val \
        --views 1 2 8
"""
import argparse
import time

import numpy as np
import torch


def untransform(pred: torch.Tensor, sym) -> torch.Tensor:
    """(B, 3, H, W) net output on `transform_image(input, sym)` -> the same for the input: the
    heatmap as an image, the offsets as images and as vectors (a mirror negates a component, a
    transposition swaps them)."""
    fx, fy, tr = sym
    pred = pred.transpose(-1, -2) if tr else pred  # the transform's steps undone in reverse
    pred = torch.flip(pred, [d for d, f in ((-1, fx), (-2, fy)) if f]) if fx or fy else pred
    heat, dy, dx = pred.unbind(1)
    if tr:
        dy, dx = dx, dy
    return torch.stack([heat, -dy if fy else dy, -dx if fx else dx], 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a model with centre votes")
    ap.add_argument("data", help="a simulated data set with labels")
    ap.add_argument("--split", default="val")
    ap.add_argument("--views", type=int, nargs="+", default=[1, 2, 8],
                    help="how many of the 8 symmetries of the square (identity first)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    from inseggan_ros import centres, segment
    from inseggan_ros.baselines import BASELINES
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter
    from inseggan_ros.symmetry import SYMMETRIES, transform_image

    torch.set_num_threads(args.threads)
    views = [1]

    def averaged_labels(net, x, fg, n):
        inp = centres.net_input(x, fg)
        syms = SYMMETRIES[:views[0]]
        out = net(torch.cat([transform_image(inp, s) for s in syms]))
        pred = torch.stack([untransform(p, s) for p, s in zip(out.chunk(len(syms)), syms)])
        return centres.decode(pred.mean(0), fg, n)

    segment.centre_labels = averaged_labels  # the segmenter's votes, over the views
    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    if seg.inference.centre_votes != "on":
        ap.error(f"{args.model}: its settings do not use centre votes")
    data = load_sim_split(args.data, args.split, seg.prep_cfg)
    x, fg, gt = data["x"], data["fg"], data["labels"]
    n, heights = seg.model_cfg.n_instances, (x[:, 0] + 1) / 2
    rows = {m: np.array([miou_batch(BASELINES[m](heights[i], fg[i], n, seed=i)[None],
                                    gt[i:i + 1])[0] for i in range(len(x))])
            for m in ("kmeans", "felzenszwalb", "spectral")}
    for k in args.views:
        views[0] = k
        t0 = time.perf_counter()
        labels = np.concatenate([seg.segment_batch(x[i:i + 50], fg[i:i + 50])["labels"].numpy()
                                 for i in range(0, len(x), 50)])
        ms = (time.perf_counter() - t0) / len(x) * 1e3
        rows[f"{k} view(s), {ms:.1f} ms"] = miou_batch(labels, gt)
    hard = {"all": np.ones(len(x), bool), "K-Means hard": rows["kmeans"] < 0.6,
            "Felzenszwalb hard": rows["felzenszwalb"] < 0.8}
    print(f"{args.data} ({args.split}), {len(x)} frames; " + ", ".join(
        f"{k} {v.sum()}" for k, v in hard.items() if k != "all"))
    for k, v in rows.items():
        print(f"  {k:24s} " + " / ".join(f"{v[m].mean():.3f}" if m.any() else "-"
                                         for m in hard.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
