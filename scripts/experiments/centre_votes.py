"""Instances from per-pixel votes for their centre, taught on piles of the learned part.

The shipped pipeline reads n poses from a 64 x 64 frame in one encoder pass (a global
regression), renders them and z-buffers the renders; on the cylinder even an encoder taught on
piles of the *true* part stays about 0.04 above Felzenszwalb on all frames, and most of what it
loses is the renders' placement (docs/experiments.md, 2026-11-28, day). A fully convolutional
net reads positions locally instead: every foreground pixel predicts the offset to the centre of
its part's visible pixels, and a heatmap marks the centres (Panoptic-DeepLab's instance
branch, small). It is taught on the loop's labelled piles of the learned part (no label of the
user's frames), and its instances then go through the shipped smoothing, vote and split.

    python scripts/experiments/centre_votes.py train --piles data/cyl_piles --out runs/dense/cyl
    python scripts/experiments/centre_votes.py eval --net runs/dense/cyl/net.pt \
        --model models/cylinder --data data/cylinder --split val
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm


def block(cin, cout, stride=1):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.GroupNorm(4, cout),
                         nn.LeakyReLU(0.2))


class CentreNet(nn.Module):
    """(B, 2, 64, 64) heights and foreground -> (B, 3, 64, 64): centre heatmap logit and the
    offset (dy, dx, in pixels / 8) from each pixel to its part's centre."""

    def __init__(self, width=16):
        super().__init__()
        w = width
        self.e1 = nn.Sequential(block(2, w), block(w, w))
        self.e2 = nn.Sequential(block(w, 2 * w, 2), block(2 * w, 2 * w))
        self.e3 = nn.Sequential(block(2 * w, 4 * w, 2), block(4 * w, 4 * w), block(4 * w, 4 * w))
        self.d2 = nn.Sequential(block(6 * w, 2 * w), block(2 * w, 2 * w))
        self.d1 = nn.Sequential(block(3 * w, w), block(w, w))
        self.out = nn.Conv2d(w, 3, 1)

    def forward(self, x):
        a = self.e1(x)
        b = self.e2(a)
        c = self.e3(b)
        b = self.d2(torch.cat([F.interpolate(c, scale_factor=2), b], 1))
        a = self.d1(torch.cat([F.interpolate(b, scale_factor=2), a], 1))
        return self.out(a)


def net_input(x, fg):
    x = torch.as_tensor(x, dtype=torch.float32)
    fg = torch.as_tensor(fg, dtype=torch.float32)
    return torch.cat([x, fg[:, None]], 1)


def targets(labels, n, sigma=2.0):
    """(B, H, W) int labels -> heatmap (B, H, W), offsets (B, 2, H, W), mask (B, H, W)."""
    B, H, W = labels.shape
    onehot = F.one_hot(labels.long(), n + 1).permute(0, 3, 1, 2)[:, 1:].float()  # (B,n,H,W)
    ys = torch.arange(H, dtype=torch.float32).view(1, 1, H, 1)
    xs = torch.arange(W, dtype=torch.float32).view(1, 1, 1, W)
    count = onehot.sum((2, 3))
    cy = (onehot * ys).sum((2, 3)) / count.clamp_min(1)
    cx = (onehot * xs).sum((2, 3)) / count.clamp_min(1)
    present = count >= 4
    g = torch.exp(-((ys - cy[..., None, None]) ** 2 + (xs - cx[..., None, None]) ** 2)
                  / (2 * sigma ** 2)) * present[..., None, None]
    heat = g.amax(1)
    oy = ((cy[..., None, None] - ys) * onehot).sum(1)
    ox = ((cx[..., None, None] - xs) * onehot).sum(1)
    return heat, torch.stack([oy, ox], 1) / 8.0, labels > 0


SYMS = [(False, False, False), (True, False, False), (False, True, False), (True, True, False),
        (False, False, True), (True, False, True), (False, True, True), (True, True, True)]


def sym(t, s):
    flip_h, flip_w, transpose = s
    if flip_h:
        t = t.flip(-2)
    if flip_w:
        t = t.flip(-1)
    if transpose:
        t = t.transpose(-1, -2)
    return t


def train(args):
    from inseggan_ros.data import load_sim_split, parts_per_bin
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    n = parts_per_bin(args.piles)
    tr = load_sim_split(args.piles, "train", progress=True)
    va = load_sim_split(args.piles, "val", progress=True)
    X, L = net_input(tr["x"], tr["fg"]), torch.from_numpy(tr["labels"].astype(np.int64))
    Xv, Lv = net_input(va["x"], va["fg"]), torch.from_numpy(va["labels"].astype(np.int64))
    net = CentreNet(args.width)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.iterations,
                                                pct_start=max(0.05, 2 / args.iterations))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(args.seed)
    log = []
    best = -1.0
    t0 = time.time()
    for it in tqdm(range(1, args.iterations + 1), desc="centre net", unit="it"):
        idx = torch.randint(len(X), (args.batch,), generator=gen)
        s = SYMS[int(torch.randint(8, (1,), generator=gen))]
        xb, lb = sym(X[idx], s), sym(L[idx], s)
        heat, off, mask = targets(lb, n)
        pred = net(xb)
        w = 1 + 10 * heat
        l_heat = (w * (torch.sigmoid(pred[:, 0]) - heat) ** 2).mean() * 10
        l_off = ((pred[:, 1:] - off).abs().sum(1) * mask).sum() / mask.sum().clamp_min(1)
        loss = l_heat + l_off
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if it % args.eval_every == 0 or it == args.iterations:
            net.eval()
            with torch.no_grad():
                lab = np.concatenate([decode(net(Xv[i:i + 100]), va["fg"][i:i + 100], n)
                                      for i in range(0, len(Xv), 100)])
            net.train()
            from inseggan_ros.metrics import mean_miou, miou_batch
            score = float(mean_miou(miou_batch(lab, va["labels"])))
            log.append({"iteration": it, "loss": float(loss), "heat": float(l_heat),
                        "offset": float(l_off), "val_miou": score,
                        "minutes": (time.time() - t0) / 60})
            tqdm.write(json.dumps(log[-1]))
            if score > best:
                best = score
                torch.save({"state": net.state_dict(), "width": args.width, "n": n,
                            "iteration": it, "val_miou": score}, out / "net.pt")
    (out / "log.json").write_text(json.dumps(log, indent=1))
    print(f"best piles val mIoU {best:.3f}")


def decode(pred, fg, n, threshold=0.3, min_dist=3):
    """(B, 3, H, W) net output, (B, H, W) bool foreground -> (B, H, W) uint8 labels: the
    heatmap's peaks (at most n, above `threshold`, 3x3 local maxima) are the centres, and
    every foreground pixel goes to the centre nearest where its offset points."""
    pred = pred.float()
    heat = torch.sigmoid(pred[:, 0])
    peaks = (heat == F.max_pool2d(heat[:, None], 2 * min_dist + 1, 1, min_dist)[:, 0])
    B, H, W = heat.shape
    ys = torch.arange(H, dtype=torch.float32).view(H, 1).expand(H, W)
    xs = torch.arange(W, dtype=torch.float32).view(1, W).expand(H, W)
    fg = torch.as_tensor(fg)
    out = np.zeros((B, H, W), np.uint8)
    for b in range(B):
        score = torch.where(peaks[b] & fg[b], heat[b], torch.zeros_like(heat[b])).flatten()
        top = score.topk(n)
        keep = top.values > threshold
        if not keep.any():
            keep[0] = True
        idx = top.indices[keep]
        centres = torch.stack([ys.flatten()[idx], xs.flatten()[idx]], 1)  # (k, 2)
        vy = ys + pred[b, 1] * 8
        vx = xs + pred[b, 2] * 8
        d = (vy[None] - centres[:, 0, None, None]) ** 2 + (vx[None] - centres[:, 1, None, None]) ** 2
        lab = d.argmin(0).numpy().astype(np.uint8) + 1
        out[b] = np.where(fg[b].numpy(), lab, 0)
    return out


def evaluate(args):
    from inseggan_ros.data import load_sim_split
    from inseggan_ros.metrics import miou_batch
    from inseggan_ros.segment import Segmenter
    from inseggan_ros.smoothing import smooth_labels
    from inseggan_ros.superpixels import split_labels, vote_labels
    from inseggan_ros.baselines import BASELINES
    torch.set_num_threads(args.threads)
    state = torch.load(args.net, weights_only=False)
    net = CentreNet(state["width"])
    net.load_state_dict(state["state"])
    net.eval()
    seg = Segmenter.from_checkpoint(Path(args.model) / "model.pt", device="cpu")
    cfg = seg.inference
    n = seg.model_cfg.n_instances
    data = load_sim_split(args.data, args.split, seg.prep_cfg, limit=args.limit)
    x, fg, gt = data["x"], data["fg"], data["labels"]
    rows = {}
    shipped = np.concatenate([seg.segment_batch(x[i:i + 50], fg[i:i + 50])["labels"].numpy()
                              for i in range(0, len(x), 50)])
    rows["shipped"] = miou_batch(shipped, gt)
    with torch.no_grad():
        raw = np.concatenate([decode(net(net_input(x[i:i + 100], fg[i:i + 100])),
                                     fg[i:i + 100], n, args.threshold)
                              for i in range(0, len(x), 100)])
    rows["centre votes"] = miou_batch(raw, gt)
    xt = torch.from_numpy(x)
    lab = torch.from_numpy(raw)
    lab = smooth_labels(lab, xt, n, cfg.smooth)
    rows["+ smoothing"] = miou_batch(lab.numpy(), gt)
    lab = vote_labels(lab, xt, n, cfg.superpixel_scale)
    rows["+ vote"] = miou_batch(lab.numpy(), gt)
    lab, _ = split_labels(lab, xt, n, cfg.split_scale)
    rows["+ split"] = miou_batch(lab.numpy(), gt)
    lab = smooth_labels(torch.from_numpy(raw), xt, n, cfg.smooth)
    lab, _ = split_labels(lab, xt, n, cfg.split_scale)
    rows["smooth + split"] = miou_batch(lab.numpy(), gt)
    heights = (x[:, 0] + 1) / 2
    for m in ("kmeans", "felzenszwalb"):
        labels = np.stack([BASELINES[m](heights[i], fg[i], n, seed=i) for i in range(len(x))])
        rows[m] = miou_batch(labels, gt)
    hard = {"all": np.ones(len(x), bool), "K-hard": rows["kmeans"] < 0.6,
            "F-hard": rows["felzenszwalb"] < 0.8}
    print(f"{args.data} {args.split}: {len(x)} frames; K-hard {hard['K-hard'].sum()}, "
          f"F-hard {hard['F-hard'].sum()}")
    for k, v in rows.items():
        cols = " / ".join(f"{v[m].mean():.3f}" if m.any() else "-" for m in hard.values())
        print(f"  {k:14s} {cols}")


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--piles", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--iterations", type=int, default=3000)
    t.add_argument("--batch", type=int, default=32)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--width", type=int, default=16)
    t.add_argument("--eval-every", type=int, default=500)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    e = sub.add_parser("eval")
    e.add_argument("--net", required=True)
    e.add_argument("--model", required=True)
    e.add_argument("--data", required=True)
    e.add_argument("--split", default="val")
    e.add_argument("--limit", type=int, default=None)
    e.add_argument("--threshold", type=float, default=0.3)
    e.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    train(args) if args.cmd == "train" else evaluate(args)


if __name__ == "__main__":
    main()
