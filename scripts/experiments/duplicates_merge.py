"""Experiment: two renders on one part. Where two instances' rendered masks (render >= tau) of
the chosen start overlap by IoU > thr, the less visible one's labels go to the other before the
smoothing, the superpixel vote and the split (which can then give the freed id to a part the
model missed; `label_rules`). Prints all / K-Means-hard / Felzenszwalb-hard mIoU per threshold.

    python scripts/experiments/duplicates_merge.py --data data/pin_connector
        --model models/pin_connector/model.pt   (one line)
"""
import numpy as np
import torch
from label_rules import arguments, load

from inseggan_ros.segment import labels_from_renders


def merge(lab, renders, tau, thr):
    out, merged = lab.copy(), 0
    n = renders.shape[1]
    for b in range(len(lab)):
        m = renders[b] >= tau
        vis = np.array([(out[b] == k + 1).sum() for k in range(n)])
        for i in range(n):
            for j in range(i + 1, n):
                union = (m[i] | m[j]).sum()
                if union and (m[i] & m[j]).sum() / union > thr and vis[i] and vis[j]:
                    lo, hi = (i, j) if vis[i] < vis[j] else (j, i)
                    out[b][out[b] == lo + 1] = hi + 1
                    vis[hi] += vis[lo]
                    vis[lo] = 0
                    merged += 1
    return out, merged


def main():
    ap = arguments(__doc__)
    ap.add_argument("--thr", type=float, nargs="+", default=[0.3, 0.5, 0.7])
    a = ap.parse_args()
    bench = load(a.model, a.data, a.split)
    pose, loss = bench.starts()
    with torch.no_grad():
        renders = bench.seg.G.render_poses(pose[np.arange(len(pose)), loss.argmin(1)])
        lab = labels_from_renders(renders, bench.seg.tau, bench.fg).numpy()
    s0 = bench.finish(lab)
    print("shipped", bench.row(s0))
    for thr in a.thr:
        merged_lab, merged = merge(lab, renders.numpy(), bench.seg.tau, thr)
        s1 = bench.finish(merged_lab)
        print(f"thr {thr}: {merged} merges;", bench.row(s1),
              f"frames changed {(np.abs(s1 - s0) > 1e-9).sum()}")
    bench.print_baselines()


if __name__ == "__main__":
    main()
