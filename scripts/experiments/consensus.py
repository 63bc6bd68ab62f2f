"""Experiment: the labels of several starting points voted together, against the best-fitting
start alone (realtime.yaml's choice). Each start's z-buffer labels are matched to the best
start's instances (Hungarian on overlap), then every pixel takes the label most starts give it
(weighted by exp(-(loss - best loss) / T)). The rest of the pipeline (smoothing, superpixel
vote, split) as the model ships it. Prints all / K-Means-hard / Felzenszwalb-hard mIoU."""
import argparse
import json

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from inseggan_ros import data as data_mod
from inseggan_ros.baselines import BASELINES
from inseggan_ros.metrics import miou_batch
from inseggan_ros.refine import _fit_loss, start_poses
from inseggan_ros.segment import Segmenter, labels_from_renders
from inseggan_ros.smoothing import smooth_labels
from inseggan_ros.superpixels import split_labels, vote_labels
import torch.nn.functional as F


def consensus(lab, loss, T, top):
    """Labels (B, H, s, s) uint8 of each start, fit losses (B, H) -> voted labels (B, s, s)."""
    B, H = loss.shape
    n = int(lab.max())
    out = np.zeros(lab.shape[:1] + lab.shape[2:], np.uint8)
    for b in range(B):
        order = np.argsort(loss[b])[:top]
        ref = lab[b, order[0]]
        votes = np.zeros((n + 1,) + ref.shape, np.float64)
        for h in order:
            w = np.exp(-(loss[b, h] - loss[b, order[0]]) / T) if T > 0 else 1.0
            lh = lab[b, h]
            if h != order[0]:
                ov = np.zeros((n, n))
                for i in range(n):
                    for j in range(n):
                        ov[i, j] = np.sum((ref == i + 1) & (lh == j + 1))
                r, c = linear_sum_assignment(-ov)
                m = np.zeros(n + 1, np.int64)
                m[c + 1] = r + 1
                lh = m[lh]
            for k in range(n + 1):
                votes[k] += w * (lh == k)
        fgm = ref > 0
        v = votes[1:].argmax(0) + 1
        out[b] = np.where(fgm, v, 0)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--T", type=float, nargs="+", default=[0.0])
    ap.add_argument("--top", type=int, nargs="+", default=[8])
    ap.add_argument("--frames", type=int, default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(a.model)
    cfg = seg.inference
    d = data_mod.load_sim_split(a.data, a.split, seg.prep_cfg, limit=a.frames)
    x, fg, gt = torch.as_tensor(d["x"]), torch.as_tensor(d["fg"]), d["labels"]
    n = seg.model_cfg.n_instances
    heights = (d["x"][:, 0] + 1) / 2
    base = {}
    for m in ("kmeans", "felzenszwalb", "spectral"):
        base[m] = miou_batch(np.stack([BASELINES[m](heights[i], d["fg"][i], n, seed=i)
                                       for i in range(len(x))]), gt)
    hardk, hardf = base["kmeans"] < 0.6, base["felzenszwalb"] < 0.8
    G, E = seg.G, seg.encoder(cfg.encoder_precision)
    labs, losses = [], []
    with torch.no_grad():
        for i in range(0, len(x), 50):
            xb = x[i:i + 50]
            pose = start_poses(G, E, xb, cfg.refine_hypotheses)
            B, H = pose.shape[:2]
            loss = _fit_loss(G, pose, F.adaptive_avg_pool2d(xb, 32), G.geometry())
            renders = G.render_poses(pose.reshape(B * H, n, 6))
            lab = labels_from_renders(renders, seg.tau, fg[i:i + 50].repeat_interleave(H, 0))
            labs.append(lab.reshape(B, H, 64, 64).numpy())
            losses.append(loss.numpy())
    lab, loss = np.concatenate(labs), np.concatenate(losses)

    def finish(l0):
        t = torch.as_tensor(l0)
        t = smooth_labels(t, x, n, cfg.smooth)
        t = vote_labels(t, x, n, cfg.superpixel_scale)
        t, _ = split_labels(t, x, n, cfg.split_scale)
        s = miou_batch(t.numpy(), gt)
        return [float(s.mean()), float(s[hardk].mean()) if hardk.any() else None,
                float(s[hardf].mean())]

    rows = {"best": finish(lab[np.arange(len(lab)), loss.argmin(1)])}
    for T in a.T:
        for top in a.top:
            rows[f"T{T}_top{top}"] = finish(consensus(lab, loss, T, top))
    for m, s in base.items():
        rows[m] = [float(s.mean()), float(s[hardk].mean()) if hardk.any() else None,
                   float(s[hardf].mean())]
    print(f"{a.model} {a.data} {a.split}: {len(x)} frames, {hardk.sum()} / {hardf.sum()} hard")
    for k, v in rows.items():
        print(k, " / ".join("-" if e is None else f"{e:.3f}" for e in v))
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
