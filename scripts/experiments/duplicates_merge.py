"""Experiment: two renders on one part. Where two instances' rendered masks (render >= tau) of
the chosen start overlap by IoU > thr, the less visible one's labels go to the other before the
smoothing, the superpixel vote and the split (which can then give the freed id to a part the
model missed). Prints all / K-Means-hard / Felzenszwalb-hard mIoU on a split, per threshold."""
import argparse

import numpy as np
import torch
import torch.nn.functional as F

from inseggan_ros import data as data_mod
from inseggan_ros.baselines import BASELINES
from inseggan_ros.metrics import miou_batch
from inseggan_ros.refine import _fit_loss, start_poses
from inseggan_ros.segment import Segmenter, labels_from_renders
from inseggan_ros.smoothing import smooth_labels
from inseggan_ros.superpixels import split_labels, vote_labels


def merge(lab, renders, tau, thr):
    out = lab.copy()
    n = renders.shape[1]
    merged = 0
    for b in range(len(lab)):
        m = renders[b] >= tau
        vis = np.array([(out[b] == k + 1).sum() for k in range(n)])
        for i in range(n):
            for j in range(i + 1, n):
                inter = (m[i] & m[j]).sum()
                union = (m[i] | m[j]).sum()
                if union and inter / union > thr and vis[i] and vis[j]:
                    lo, hi = (i, j) if vis[i] < vis[j] else (j, i)
                    out[b][out[b] == lo + 1] = hi + 1
                    vis[hi] += vis[lo]
                    vis[lo] = 0
                    merged += 1
    return out, merged


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--thr", type=float, nargs="+", default=[0.3, 0.5, 0.7])
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
    labs, rends = [], []
    with torch.no_grad():
        for i in range(0, len(x), 50):
            xb = x[i:i + 50]
            pose = start_poses(G, E, xb, cfg.refine_hypotheses)
            loss = _fit_loss(G, pose, F.adaptive_avg_pool2d(xb, 32), G.geometry())
            best = pose[torch.arange(len(xb)), loss.argmin(1)]
            r = G.render_poses(best)
            labs.append(labels_from_renders(r, seg.tau, fg[i:i + 50]).numpy())
            rends.append(r.numpy())
    lab, rend = np.concatenate(labs), np.concatenate(rends)

    def finish(l0):
        t = smooth_labels(torch.as_tensor(l0), x, n, cfg.smooth)
        t = vote_labels(t, x, n, cfg.superpixel_scale)
        t, _ = split_labels(t, x, n, cfg.split_scale)
        s = miou_batch(t.numpy(), gt)
        return s

    def fmt(s):
        return " / ".join(["%.3f" % s.mean(), "%.3f" % s[hardk].mean() if hardk.any() else "-",
                           "%.3f" % s[hardf].mean()])

    s0 = finish(lab)
    print(f"{a.model} {a.split}: {len(x)} frames, {hardk.sum()} / {hardf.sum()} hard")
    print("shipped", fmt(s0))
    for thr in a.thr:
        l1, merged = merge(lab, rend, seg.tau, thr)
        s1 = finish(l1)
        changed = (np.abs(s1 - s0) > 1e-9).sum()
        print(f"thr {thr}: {merged} merges;", fmt(s1), f"frames changed {changed}")
    for m, s in base.items():
        print(m, fmt(s))


if __name__ == "__main__":
    main()
