"""Experiment: centre votes averaged over views. The net also reads the frame mirrored and
transposed, and its heatmaps and offsets, mapped back onto the frame, are averaged before
decoding (test-time augmentation, as Panoptic-DeepLab's flips); the rest of the pipeline as the
model ships it. Prints all / K-Means-hard / Felzenszwalb-hard mIoU against one view, with the
classical methods on the same frames (docs/experiments.md, 2026-11-29, day: not shipped, the
gains are within the spread between single views).

    python scripts/experiments/centre_views.py --model models/bolt/model.pt --data data/bolt \
        --views 1 2 8
"""
import time

import torch
from label_rules import arguments, load

from inseggan_ros import centres, segment
from inseggan_ros.symmetry import SYMMETRIES, transform_image


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
    ap = arguments(__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, nargs="+", default=[1, 2, 8],
                    help="how many of the 8 symmetries of the square (the identity first)")
    args = ap.parse_args(argv)
    views = [1]

    def averaged_labels(net, x, fg, n):
        inp = centres.net_input(x, fg)
        syms = SYMMETRIES[:views[0]]
        out = net(torch.cat([transform_image(inp, s) for s in syms]))
        pred = torch.stack([untransform(p, s) for p, s in zip(out.chunk(len(syms)), syms)])
        return centres.decode(pred.mean(0), fg, n)

    segment.centre_labels = averaged_labels  # the segmenter's votes, over the views
    bench = load(args.model, args.data, args.split)
    if bench.seg.inference.centre_votes != "on":
        ap.error(f"{args.model}: its settings do not use centre votes")
    bench.print_baselines()
    for k in args.views:
        views[0] = k
        t0 = time.perf_counter()
        scores = bench.scores()
        ms = (time.perf_counter() - t0) / len(scores) * 1e3
        print(f"{k} view(s), {ms:.1f} ms a frame", bench.row(scores))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
