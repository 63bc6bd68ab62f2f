"""The centre-vote net in float32 and in bfloat16 (its last layer float32) on one split of a
labelled data set, with the model's own settings: mIoU on all frames and on both hard subsets,
and how many frames change (docs/experiments.md, 2026-12-02, day).

    python scripts/experiments/centre_precision.py models/bolt/model.pt data/bolt val
"""
import sys

import numpy as np
import torch


def main(argv=None) -> int:
    from inseggan_ros.baselines import BASELINES
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter

    model, data, split = (argv or sys.argv[1:])[:3]
    torch.set_num_threads(2)
    seg = Segmenter.from_checkpoint(model, device="cpu")
    d = load_sim_split(data, split, seg.prep_cfg)
    x, fg, gt = d["x"], d["fg"], d["labels"]
    n = seg.model_cfg.n_instances
    heights = (x[:, 0] + 1) / 2
    base = {m: miou_batch(np.stack([BASELINES[m](heights[i], fg[i], n, seed=i)
                                    for i in range(len(x))]), gt)
            for m in ("kmeans", "felzenszwalb")}
    hard = {"K-Means hard": base["kmeans"] < 0.6, "Felzenszwalb hard": base["felzenszwalb"] < 0.8}
    scores = {}
    for precision in ("float32", "bfloat16"):
        labels = []
        for i in range(0, len(x), 50):
            votes = seg.centre_votes(x[i:i + 50], fg[i:i + 50], n, precision)
            labels.append(seg.segment_batch(x[i:i + 50], fg[i:i + 50], centres=votes)
                          ["labels"].numpy())
        s = scores[precision] = miou_batch(np.concatenate(labels), gt)
        cols = " / ".join(f"{s[m].mean():.4f} ({m.sum()})" if m.any() else "-"
                          for m in hard.values())
        print(f"{precision}: all {s.mean():.4f}, hard {cols}")
    diff = scores["bfloat16"] - scores["float32"]
    print(f"frames changed: {int((np.abs(diff) > 1e-6).sum())} of {len(x)}, "
          f"most lost {diff.min():+.4f}, most gained {diff.max():+.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
