"""Experiment: a model's two label sources, its centre votes and its z-buffer (each followed by the
model's own smoothing, vote and split), and what choosing between them frame by frame could give:
the best of the two per frame (an oracle: it reads the true labels), and label-free rules that
keep the z-buffer's labels where the centre votes' break more of the frame's height structure
(pixels of one label across a height step, or two labels meeting on level ground). Prints all /
K-Means-hard / Felzenszwalb-hard mIoU with spectral clustering's on the same frames
(docs/experiments.md, 2026-11-29, day).

    python scripts/experiments/label_choice.py models/pin_connector/model.pt data/pin_connector
"""
import argparse
from dataclasses import replace

import numpy as np
import torch


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
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a model with centre votes")
    ap.add_argument("data", help="a simulated data set with labels")
    ap.add_argument("--split", default="val")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    from inseggan_ros.baselines import BASELINES
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(args.threads)
    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    data = load_sim_split(args.data, args.split, seg.prep_cfg)
    x, fg, gt = data["x"], data["fg"], data["labels"]
    n, heights = seg.model_cfg.n_instances, (x[:, 0] + 1) / 2

    def labels(cfg):
        return np.concatenate([seg.segment_batch(x[i:i + 50], fg[i:i + 50], settings=cfg)
                               ["labels"].numpy() for i in range(0, len(x), 50)])

    votes = labels(replace(seg.inference, centre_votes="on"))
    zbuf = labels(replace(seg.inference, centre_votes="off"))
    base = {m: np.array([miou_batch(BASELINES[m](heights[i], fg[i], n, seed=i)[None],
                                    gt[i:i + 1])[0] for i in range(len(x))])
            for m in ("kmeans", "felzenszwalb", "spectral")}
    s_votes, s_zbuf = miou_batch(votes, gt), miou_batch(zbuf, gt)
    rows = {"spectral clustering": base["spectral"], "centre votes": s_votes,
            "z-buffer": s_zbuf, "oracle: the better per frame": np.maximum(s_votes, s_zbuf)}
    for step in (0.05, 0.1, 0.2, 0.3):  # the model input's units: [-1, 1] over max_height
        v, z = height_breaks(votes, x[:, 0], step), height_breaks(zbuf, x[:, 0], step)
        for name, bv, bz in (("across", v[0], z[0]), ("level", v[1], z[1]),
                             ("both", v[0] + v[1], z[0] + z[1])):
            for margin in (0, 10):
                pick = bz + margin < bv
                rows[f"z-buffer where fewer {name} (step {step}, +{margin}): "
                     f"{pick.sum()}"] = np.where(pick, s_zbuf, s_votes)
    hard = {"all": np.ones(len(x), bool), "K-Means hard": base["kmeans"] < 0.6,
            "Felzenszwalb hard": base["felzenszwalb"] < 0.8}
    print(f"{args.data} ({args.split}), {len(x)} frames; " + ", ".join(
        f"{k} {v.sum()}" for k, v in hard.items() if k != "all"))
    for k, v in rows.items():
        print(f"  {k:52s} " + " / ".join(f"{v[m].mean():.3f}" if m.any() else "-"
                                         for m in hard.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
