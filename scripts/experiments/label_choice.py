"""Experiment: a model's two label sources, its centre votes and its z-buffer (each followed by the
model's own smoothing, vote and split), and what choosing between them frame by frame could give:
the better of the two in each frame (an oracle: it reads the true labels), and label-free rules
that keep the z-buffer's labels where the centre votes break more of the frame's height
structure (pixels of one label across a height step, or two labels meeting on level ground).
Prints all / K-Means-hard / Felzenszwalb-hard mIoU with the classical methods on the same frames
(docs/experiments.md, 2026-11-29, day).

    python scripts/experiments/label_choice.py --model models/pin_connector/model.pt \
        --data data/pin_connector
"""
from dataclasses import replace

import numpy as np
from label_rules import arguments, load

from inseggan_ros.metrics import miou_batch


def height_breaks(labels: np.ndarray, x: np.ndarray, step: float) -> tuple[np.ndarray, ...]:
    """(N, H, W) labels and heights -> per frame, the 4-neighbour pairs of one label across a
    height step above `step`, and of two labels on level ground (steps below it)."""
    across, level = 0, 0
    for a, b, ha, hb in ((labels[:, 1:], labels[:, :-1], x[:, 1:], x[:, :-1]),
                         (labels[:, :, 1:], labels[:, :, :-1], x[:, :, 1:], x[:, :, :-1])):
        both, steep = (a > 0) & (b > 0), np.abs(ha - hb) > step
        across = across + ((a == b) & both & steep).sum((1, 2))
        level = level + ((a != b) & both & ~steep).sum((1, 2))
    return across, level


def main(argv=None) -> int:
    args = arguments(__doc__.split("\n")[0]).parse_args(argv)
    bench = load(args.model, args.data, args.split)
    bench.print_baselines()
    seg, x = bench.seg, bench.x[:, 0].numpy()
    votes = bench.labels(replace(seg.inference, centre_votes="on"))
    zbuf = bench.labels(replace(seg.inference, centre_votes="off"))
    s_votes, s_zbuf = miou_batch(votes, bench.gt), miou_batch(zbuf, bench.gt)
    print("centre votes", bench.row(s_votes))
    print("z-buffer", bench.row(s_zbuf))
    print("oracle: the better in each frame", bench.row(np.maximum(s_votes, s_zbuf)))
    for step in (0.05, 0.1, 0.2, 0.3):  # the model input's units: [-1, 1] over max_height
        v, z = height_breaks(votes, x, step), height_breaks(zbuf, x, step)
        for name, bv, bz in (("across", v[0], z[0]), ("level", v[1], z[1]),
                             ("both", v[0] + v[1], z[0] + z[1])):
            for margin in (0, 10):
                pick = bz + margin < bv
                print(f"z-buffer where fewer {name} (step {step}, +{margin}; {pick.sum()} "
                      "frames)", bench.row(np.where(pick, s_zbuf, s_votes)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
