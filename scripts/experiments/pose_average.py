"""Experiment: the instances of the 8 starting points averaged pose by pose. The best-fitting
start's instances are matched to each other start's (Hungarian assignment on the distance of
their centres), and each instance's axis (sign-aligned) and translation are averaged over the
starts whose match lies within `--radius` image half-widths; the averaged poses are rendered
and the labels made from them, then smoothing, vote and split as the model ships them. If the
encoder's readings scatter about the true pose, their mean is closer. Prints all / K-Means-hard
/ Felzenszwalb-hard mIoU on a split, the best start alone first (`label_rules`).

    python scripts/experiments/pose_average.py --model models/cylinder/model.pt --data data/cylinder
"""
import numpy as np
import torch
from label_rules import arguments, load
from scipy.optimize import linear_sum_assignment

from inseggan_ros.model import pose_from_axis, rodrigues
from inseggan_ros.segment import labels_from_renders


def average(axis, t, loss, radius, top):
    """Axes (B, H, n, 3), translations (B, H, n, 3), losses (B, H) -> averaged (B, n, 3) x 2."""
    B, H, n, _ = axis.shape
    out_a, out_t = np.zeros((B, n, 3)), np.zeros((B, n, 3))
    for b in range(B):
        order = np.argsort(loss[b])[:top]
        ref_a, ref_t = axis[b, order[0]], t[b, order[0]]
        sum_a, sum_t, cnt = ref_a.copy(), ref_t.copy(), np.ones(n)
        for h in order[1:]:
            d = np.linalg.norm(ref_t[:, None, :2] - t[b, h][None, :, :2], axis=-1)
            r, c = linear_sum_assignment(d)
            for i, j in zip(r, c):
                if d[i, j] < radius:
                    a = axis[b, h, j] * np.sign(np.dot(axis[b, h, j], ref_a[i]) or 1.0)
                    sum_a[i] += a
                    sum_t[i] += t[b, h, j]
                    cnt[i] += 1
        out_a[b] = sum_a / np.linalg.norm(sum_a, axis=-1, keepdims=True)
        out_t[b] = sum_t / cnt[:, None]
    return out_a, out_t


def main():
    ap = arguments(__doc__)
    ap.add_argument("--radius", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    ap.add_argument("--top", type=int, nargs="+", default=[8])
    a = ap.parse_args()
    bench = load(a.model, a.data, a.split)
    pose, loss = bench.starts()
    B, H, n = pose.shape[:3]
    axis = rodrigues(pose.reshape(-1, 6)[:, :3])[:, :, 0].reshape(B, H, n, 3).numpy()
    t = pose[..., 3:].numpy()

    def score(ax, tr):
        with torch.no_grad():
            p = pose_from_axis(torch.as_tensor(ax, dtype=torch.float32),
                               torch.as_tensor(tr, dtype=torch.float32))
            lab = labels_from_renders(bench.seg.G.render_poses(p), bench.seg.tau, bench.fg)
        return bench.row(bench.finish(lab))

    best = loss.argmin(1)
    print("best start", score(axis[np.arange(B), best], t[np.arange(B), best]))
    for r in a.radius:
        for top in a.top:
            print(f"radius {r} top {top}", score(*average(axis, t, loss, r, top)))
    bench.print_baselines()


if __name__ == "__main__":
    main()
