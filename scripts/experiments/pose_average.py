"""Experiment: the instances of the 8 starting points averaged pose by pose. The best-fitting
start's instances are matched to each other start's (Hungarian assignment on the distance of
their centres), and each instance's axis (sign-aligned) and translation are averaged over the
starts whose match lies within `--radius` image half-widths; the averaged poses are rendered
and the labels made from them, then smoothing, vote and split as the model ships them. If the
encoder's readings scatter about the true pose, their mean is closer. Prints all / K-Means-hard
/ Felzenszwalb-hard mIoU on a split, the best start alone first."""
import argparse

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

from inseggan_ros import data as data_mod
from inseggan_ros.baselines import BASELINES
from inseggan_ros.metrics import miou_batch
from inseggan_ros.model import pose_from_axis, rodrigues
from inseggan_ros.refine import _fit_loss, start_poses
from inseggan_ros.segment import Segmenter, labels_from_renders
from inseggan_ros.smoothing import smooth_labels
from inseggan_ros.superpixels import split_labels, vote_labels


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
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--radius", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    ap.add_argument("--top", type=int, nargs="+", default=[8])
    a = ap.parse_args()
    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(a.model)
    cfg = seg.inference
    d = data_mod.load_sim_split(a.data, a.split, seg.prep_cfg)
    x, fg, gt = torch.as_tensor(d["x"]), torch.as_tensor(d["fg"]), d["labels"]
    n = seg.model_cfg.n_instances
    heights = (d["x"][:, 0] + 1) / 2
    base = {m: miou_batch(np.stack([BASELINES[m](heights[i], d["fg"][i], n, seed=i)
                                    for i in range(len(x))]), gt)
            for m in ("kmeans", "felzenszwalb", "spectral")}
    hardk, hardf = base["kmeans"] < 0.6, base["felzenszwalb"] < 0.8
    G, E = seg.G, seg.encoder(cfg.encoder_precision)
    poses, losses = [], []
    with torch.no_grad():
        for i in range(0, len(x), 50):
            xb = x[i:i + 50]
            pose = start_poses(G, E, xb, cfg.refine_hypotheses)
            poses.append(pose)
            losses.append(_fit_loss(G, pose, F.adaptive_avg_pool2d(xb, 32), G.geometry()))
    pose, loss = torch.cat(poses), torch.cat(losses).numpy()
    B, H = pose.shape[:2]
    axis = rodrigues(pose.reshape(-1, 6)[:, :3])[:, :, 0].reshape(B, H, n, 3).numpy()
    t = pose[..., 3:].numpy()

    def finish(ax, tr):
        with torch.no_grad():
            p = pose_from_axis(torch.as_tensor(ax, dtype=torch.float32),
                               torch.as_tensor(tr, dtype=torch.float32))
            lab = labels_from_renders(G.render_poses(p), seg.tau, fg)
        lab = smooth_labels(lab, x, n, cfg.smooth)
        lab = vote_labels(lab, x, n, cfg.superpixel_scale)
        lab, _ = split_labels(lab, x, n, cfg.split_scale)
        return miou_batch(lab.numpy(), gt)

    def fmt(s):
        return " / ".join(["%.3f" % s.mean(), "%.3f" % s[hardk].mean() if hardk.any() else "-",
                           "%.3f" % s[hardf].mean()])

    best = loss.argmin(1)
    print(f"{a.model} {a.split}: {len(x)} frames, {hardk.sum()} / {hardf.sum()} hard")
    print("best start", fmt(finish(axis[np.arange(B), best], t[np.arange(B), best])))
    for r in a.radius:
        for top in a.top:
            print(f"radius {r} top {top}", fmt(finish(*average(axis, t, loss, r, top))))
    for m, s in base.items():
        print(m, fmt(s))


if __name__ == "__main__":
    main()
