"""Experiment: two centre-vote networks of different origin averaged. The shipped model's net
(taught on piles of its learned part) and another model's (e.g. taught on the model's own labels
of its training frames, `inseggan centres --self-labels`) read the same frame; their heatmaps and
offsets are averaged before decoding, and the rest of the shipped pipeline follows. Prints all /
K-Means-hard / Felzenszwalb-hard mIoU of each net alone and of the pair, with the classical
methods on the same frames (docs/experiments.md, 2026-11-29, day).

    python scripts/experiments/centre_ensemble.py models/bolt/model.pt \
        runs/dense/bolt_self_votes/model.pt data/bolt --split val
"""
import argparse

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="the model whose encoder, renders and settings are used")
    ap.add_argument("other", help="a model whose centre-vote net is averaged with the first's")
    ap.add_argument("data", help="a simulated data set with labels")
    ap.add_argument("--split", default="val")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    from inseggan_ros import centres, segment
    from inseggan_ros.baselines import BASELINES
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(args.threads)
    seg = Segmenter.from_checkpoint(args.model, device="cpu")
    other = Segmenter.from_checkpoint(args.other, device="cpu").centre_net
    if seg.centre_net is None or other is None:
        ap.error("both models need a centre-vote network")
    nets = {"the first's net": [seg.centre_net], "the other's net": [other],
            "both averaged": [seg.centre_net, other]}
    use = []

    def averaged_labels(net, x, fg, n):
        inp = centres.net_input(x, fg)
        return centres.decode(torch.stack([m(inp) for m in use]).mean(0), fg, n)

    segment.centre_labels = averaged_labels  # the segmenter's votes, from the nets in `use`
    data = load_sim_split(args.data, args.split, seg.prep_cfg)
    x, fg, gt = data["x"], data["fg"], data["labels"]
    n, heights = seg.model_cfg.n_instances, (x[:, 0] + 1) / 2
    rows = {m: np.array([miou_batch(BASELINES[m](heights[i], fg[i], n, seed=i)[None],
                                    gt[i:i + 1])[0] for i in range(len(x))])
            for m in ("kmeans", "felzenszwalb", "spectral")}
    for name, chosen in nets.items():
        use[:] = chosen
        labels = np.concatenate([seg.segment_batch(x[i:i + 50], fg[i:i + 50])["labels"].numpy()
                                 for i in range(0, len(x), 50)])
        rows[name] = miou_batch(labels, gt)
    hard = {"all": np.ones(len(x), bool), "K-Means hard": rows["kmeans"] < 0.6,
            "Felzenszwalb hard": rows["felzenszwalb"] < 0.8}
    print(f"{args.data} ({args.split}), {len(x)} frames; " + ", ".join(
        f"{k} {v.sum()}" for k, v in hard.items() if k != "all"))
    for k, v in rows.items():
        print(f"  {k:20s} " + " / ".join(f"{v[m].mean():.3f}" if m.any() else "-"
                                         for m in hard.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
