"""Centre votes step by step: the shipped z-buffer's labels, the net's instances alone, then with
the smoothing, the superpixel vote and the split, against K-Means and Felzenszwalb.

`inseggan centres` makes the model (the model with the net, `centre_votes: on`); this script
shows which of the shipped steps after the labels help them (docs/experiments.md, 2026-11-28,
night: the vote does not, the smoothing and the split do).

    python scripts/experiments/centre_votes.py runs/dense/cyl_cli/model.pt data/cylinder --split val
"""
import argparse
from dataclasses import replace

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a model with centre votes (inseggan centres' model.pt)")
    ap.add_argument("data", help="a simulated data set with labels")
    ap.add_argument("--split", default="val")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    from inseggan_ros.baselines import BASELINES
    from inseggan_ros.centres import centre_labels
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter
    from inseggan_ros.smoothing import smooth_labels
    from inseggan_ros.superpixels import split_labels, vote_labels

    torch.set_num_threads(args.threads)
    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    cfg = replace(seg.inference, centre_votes="off")
    n = seg.model_cfg.n_instances
    data = load_sim_split(args.data, args.split, seg.prep_cfg, limit=args.frames)
    x, fg, gt = data["x"], data["fg"], data["labels"]
    xt = torch.from_numpy(x)

    def batched(fn):
        return np.concatenate([fn(i) for i in range(0, len(x), 50)])

    rows = {"z-buffer as shipped": batched(lambda i: seg.segment_batch(
        x[i:i + 50], fg[i:i + 50], settings=cfg)["labels"].numpy())}
    raw = torch.from_numpy(batched(lambda i: centre_labels(
        seg.centre_net, x[i:i + 50], fg[i:i + 50], n).numpy()))
    rows["centre votes"] = raw
    smooth = smooth_labels(raw, xt, n, cfg.smooth)
    rows["+ smoothing"] = smooth
    voted = vote_labels(smooth, xt, n, cfg.superpixel_scale)
    rows[f"+ vote ({cfg.superpixel_scale})"] = voted
    rows["+ vote + split"] = split_labels(voted, xt, n, cfg.split_scale)[0]
    rows["+ split, no vote (shipped)"] = split_labels(smooth, xt, n, cfg.split_scale)[0]
    heights = (x[:, 0] + 1) / 2
    for m in ("kmeans", "felzenszwalb"):
        rows[m] = np.stack([BASELINES[m](heights[i], fg[i], n, seed=i) for i in range(len(x))])
    scores = {k: miou_batch(np.asarray(v), gt) for k, v in rows.items()}
    hard = {"all": np.ones(len(x), bool), "K-Means hard": scores["kmeans"] < 0.6,
            "Felzenszwalb hard": scores["felzenszwalb"] < 0.8}
    print(f"{args.data} ({args.split}), {len(x)} frames; " + ", ".join(
        f"{k} {v.sum()}" for k, v in hard.items() if k != "all"))
    for k, v in scores.items():
        print(f"  {k:28s} " + " / ".join(f"{v[m].mean():.3f}" if m.any() else "-"
                                         for m in hard.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
