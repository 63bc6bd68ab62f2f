"""The superpixel vote's scale chosen on labelled piles of the learned part (`inseggan loop`).

The vote (`superpixels.vote_frame`) gives each depth superpixel its most frequent label. How
large the superpixels should be depends on the part and the camera: on the straight-down data
sets the nut and the pin connector gain with scale 160 and the cone loses from 80 on
(docs/experiments.md, 2026-11-27, evening), and on a tilted RealSense recording of bolts scale
160-250 is 0.03-0.04 above realtime.yaml's 50 (2026-11-28, evening). The shipped models had
their scale chosen with their data sets' validation labels; a user's own part comes with no
labels, but the loop's simulated piles of the shape it learned have them. So the loop scores
each candidate scale there, the model's other settings as it ships, and keeps the best;
the settings' own scale stays unless another beats it there by more than TOLERANCE and by
SIGNIFICANCE standard errors of its gain over the piles (a flat curve is noise, not a reason
to move: on a tilted bolt loop's piles scale 35 beat 50 by 0.0022, and scored 0.009 below it
on the recording). Nothing here imports ROS.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from inseggan_ros.core.metrics import mean_miou, miou_batch

# the scales scored (the settings' own is always added); realtime.yaml's is 50
SCALES = (35, 50, 80, 120, 160, 250, 400)
TOLERANCE = 0.002  # mIoU on the piles by which another scale must beat the settings' own,
SIGNIFICANCE = 2.0  # and by this many standard errors of its gain, pile by pile
CHUNK = 50  # piles segmented at a time


def choose(seg, piles: dict, scales=SCALES, tolerance: float = TOLERANCE) -> dict:
    """A `segment.Segmenter` (its tau and shipped settings) and labelled piles {x, fg,
    labels} -> {"scale": the chosen scale, "default": the settings' own, "frames": how many
    piles, "rows": [{"scale", "miou", "gain" over the settings' own, "gain_se" its standard
    error}, ...] by scale}. With the vote off in the settings (scale 0) nothing is scored and
    the scale stays 0; on a single pile the settings' own scale is kept."""
    cfg = seg.inference
    default = cfg.superpixel_scale
    if cfg.centre_votes == "on":
        return {"scale": default, "default": default, "frames": 0, "rows": [],
                "note": "no vote over centre votes"}
    if default == 0:
        return {"scale": 0, "default": 0, "frames": 0, "rows": [],
                "note": "the vote is off in these settings"}
    if len(piles["x"]) == 0:
        raise ValueError("no labelled piles to choose the vote's scale on")
    if any(int(s) < 1 for s in scales):
        raise ValueError(f"vote scales {tuple(scales)} invalid; valid: integers >= 1")
    import torch

    candidates = sorted({int(s) for s in scales} | {default})
    labels = {s: [] for s in candidates}
    for i in range(0, len(piles["x"]), CHUNK):
        x = torch.as_tensor(piles["x"][i:i + CHUNK], dtype=torch.float32, device=seg.device)
        with torch.no_grad():
            out = seg.model_labels(x, piles["fg"][i:i + CHUNK])  # once: only the vote differs
            for s in candidates:
                voted = seg.vote_and_split(out, x, replace(cfg, superpixel_scale=s))
                labels[s].append(voted["labels"].cpu().numpy())
    scores = {s: np.asarray(miou_batch(np.concatenate(labels[s]), piles["labels"]))
              for s in candidates}
    rows = []
    for s in candidates:  # the gain over the settings' own scale, pile by pile
        gain = scores[s] - scores[default]
        se = float(gain.std(ddof=1) / np.sqrt(len(gain))) if len(gain) > 1 else None
        rows.append({"scale": s, "miou": float(mean_miou(scores[s])),
                     "gain": float(gain.mean()), "gain_se": se})
    better = [r for r in rows if r["gain_se"] is not None  # one pile: no spread to judge by
              and r["gain"] > max(tolerance, SIGNIFICANCE * r["gain_se"])]
    scale = max(better, key=lambda r: r["miou"])["scale"] if better else default
    return {"scale": scale, "default": default, "frames": len(piles["x"]), "rows": rows,
            "tolerance": tolerance}


def describe(choice: dict) -> str:
    """One line for a model card: the scores and the scale kept."""
    if not choice.get("rows"):
        return f"not chosen ({choice.get('note', 'no piles')})"
    scores = ", ".join(f"{r['scale']}: {r['miou']:.3f}" for r in choice["rows"])
    return (f"scale {choice['scale']}, chosen on {choice['frames']} labelled simulated piles of "
            f"the learned part (mIoU by scale: {scores}; the settings' own {choice['default']} "
            f"is kept unless another beats it by more than {choice['tolerance']} and "
            f"{SIGNIFICANCE:g} standard errors)")
