"""Experiment: the labels of several starting points voted together, against the best-fitting
start alone (realtime.yaml's choice). Each start's z-buffer labels are matched to the best
start's instances (Hungarian on overlap), then every pixel takes the label most starts give it
(weighted by exp(-(loss - best loss) / T); T 0: equally). The rest of the pipeline as the model
ships it (`label_rules`). Prints all / K-Means-hard / Felzenszwalb-hard mIoU.

    python scripts/experiments/consensus.py --model models/cylinder/model.pt --data data/cylinder
"""
import numpy as np
import torch
from label_rules import arguments, load
from scipy.optimize import linear_sum_assignment

from inseggan_ros.segment import labels_from_renders


def consensus(lab, loss, T, top):
    """Labels (B, H, s, s) uint8 of each start, fit losses (B, H) -> voted labels (B, s, s)."""
    n = int(lab.max())
    out = np.zeros(lab.shape[:1] + lab.shape[2:], np.uint8)
    for b in range(len(lab)):
        order = np.argsort(loss[b])[:top]
        ref = lab[b, order[0]]
        votes = np.zeros((n + 1,) + ref.shape, np.float64)
        for h in order:
            w = np.exp(-(loss[b, h] - loss[b, order[0]]) / T) if T > 0 else 1.0
            lh = lab[b, h]
            if h != order[0]:
                ov = np.array([[np.sum((ref == i + 1) & (lh == j + 1)) for j in range(n)]
                               for i in range(n)])
                r, c = linear_sum_assignment(-ov)
                m = np.zeros(n + 1, np.int64)
                m[c + 1] = r + 1
                lh = m[lh]
            for k in range(n + 1):
                votes[k] += w * (lh == k)
        out[b] = np.where(ref > 0, votes[1:].argmax(0) + 1, 0)
    return out


def main():
    ap = arguments(__doc__)
    ap.add_argument("--T", type=float, nargs="+", default=[0.0])
    ap.add_argument("--top", type=int, nargs="+", default=[8])
    a = ap.parse_args()
    bench = load(a.model, a.data, a.split)
    pose, loss = bench.starts()
    B, H, n = pose.shape[:3]
    with torch.no_grad():
        renders = bench.seg.G.render_poses(pose.reshape(B * H, n, 6))
        lab = labels_from_renders(renders, bench.seg.tau, bench.fg.repeat_interleave(H, 0))
    lab = lab.reshape(B, H, *lab.shape[1:]).numpy()
    print("best start", bench.row(bench.finish(lab[np.arange(B), loss.argmin(1)])))
    for T in a.T:
        for top in a.top:
            print(f"T {T} top {top}", bench.row(bench.finish(consensus(lab, loss, T, top))))
    bench.print_baselines()


if __name__ == "__main__":
    main()
