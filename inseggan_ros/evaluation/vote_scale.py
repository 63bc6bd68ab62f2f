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
on the recording).

Over centre votes the vote is off: where the model's part is the frames' part, their labels
already follow its edges, and the vote only merges touching parts (on fresh recordings it
left or lowered every shipped tilted model's mIoU at scale 50, by up to 0.020, and lowered
every one at 160, by 0.019-0.097).
Where the kept template is not the part's shape (Z-brackets piled as a U, U-clips as an L),
the net's instances cut across the parts, and the vote gains 0.05-0.08 (docs/experiments.md,
2026-12-07). The piles cannot show which case holds (they are of the template), but the
frames can: there the labels' boundaries leave the heights' edges (`off_edge`) far more often
than on the piles. Where they do (`MISMATCH`), the vote over centre votes is turned on
(`centre_superpixel_scale`) at the largest scale that costs the piles at most `VOTE_COST`
(coarser superpixels follow the frames' edges over larger surfaces, and merge more parts).
Nothing here imports ROS.
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
EDGE_STEP = 0.1  # model-input units (2.5 mm at the default max_height): a height edge
MISMATCH = (2.5, 0.03)  # the frames' off-edge share at least this times the piles', and above
# it by this much: the template is not the frames' part. Measured at EDGE_STEP 0.1: Z-brackets
# 0.092 against 0.015, U-clips 0.072 against 0.018; T-pieces (the T kept) 0.019 against 0.013
VOTE_COST = 0.02  # mIoU on the piles the vote over centre votes may cost at the scale chosen


def choose(seg, piles: dict, scales=SCALES, tolerance: float = TOLERANCE,
           frames: dict | None = None) -> dict:
    """A `segment.Segmenter` (its tau and shipped settings) and labelled piles {x, fg,
    labels} -> {"scale": the chosen scale, "default": the settings' own, "frames": how many
    piles, "rows": [{"scale", "miou", "gain" over the settings' own, "gain_se" its standard
    error}, ...] by scale, "setting": the setting it is for}. With the vote off in the
    settings (scale 0) nothing is scored and the scale stays 0; on a single pile the
    settings' own scale is kept. With centre votes on: `over_centres` (the user's `frames`,
    {x, fg}, no label)."""
    cfg = seg.inference
    default = cfg.superpixel_scale
    if cfg.centre_votes == "on":
        return over_centres(seg, piles, frames, scales)
    if default == 0:
        return {"scale": 0, "default": 0, "frames": 0, "rows": [],
                "note": "the vote is off in these settings", "setting": "superpixel_scale"}
    _check(piles, scales)
    outs = _labels(seg, piles["x"], piles["fg"], cfg)  # once: only the vote differs
    return {**_by_gain(seg, outs, piles, scales, default, "superpixel_scale", tolerance),
            "setting": "superpixel_scale"}


def _by_gain(seg, outs: list, piles: dict, scales, default: int, setting: str,
             tolerance: float = TOLERANCE) -> dict:
    """Each scale's mIoU on the labelled piles and its gain over `default`'s, pile by pile;
    the best scale whose gain is above `tolerance` and SIGNIFICANCE standard errors, else
    `default` -> {"scale", "default", "frames", "rows", "tolerance"}."""
    cfg = seg.inference
    candidates = sorted({int(s) for s in scales} | {default})
    scores = {s: np.asarray(miou_batch(_voted(seg, outs, replace(cfg, **{setting: s})),
                                       piles["labels"])) for s in candidates}
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


def _check(piles: dict, scales) -> None:
    if len(piles["x"]) == 0:
        raise ValueError("no labelled piles to choose the vote's scale on")
    if any(int(s) < 1 for s in scales):
        raise ValueError(f"vote scales {tuple(scales)} invalid; valid: integers >= 1")


def _labels(seg, x, fg, cfg) -> list:
    """The model's labels of frames `x`, `fg` before the vote (`Segmenter.model_labels`), a
    chunk at a time -> [(out, x tensor)] for `vote_and_split`."""
    import torch

    outs = []
    for i in range(0, len(x), CHUNK):
        xt = torch.as_tensor(x[i:i + CHUNK], dtype=torch.float32, device=seg.device)
        with torch.no_grad():
            outs.append((seg.model_labels(xt, fg[i:i + CHUNK], settings=cfg), xt))
    return outs


def _voted(seg, outs: list, cfg) -> np.ndarray:
    """`_labels`' outputs voted (and split) as the settings `cfg` say -> (N, H, W) labels."""
    import torch

    with torch.no_grad():
        return np.concatenate([seg.vote_and_split(o, xt, cfg)["labels"].cpu().numpy()
                               for o, xt in outs])


def off_edge(x, fg, labels, step: float = EDGE_STEP) -> float:
    """The share of the label boundaries inside the foreground (neighbouring foreground
    pixels of two instances, (N, H, W) `labels`) that lie more than a pixel from a height
    edge (neighbouring foreground pixels whose heights, (N, 1, H, W) model inputs `x`, differ
    by more than `step`): 0 where every boundary follows the heights. NaN without boundaries."""
    from scipy import ndimage

    h, fg, labels = np.asarray(x)[:, 0], np.asarray(fg, bool), np.asarray(labels)
    edge, cut = np.zeros_like(fg), np.zeros_like(fg)
    for axis in (1, 2):
        a = [slice(None)] * 3
        b = list(a)
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        a, b = tuple(a), tuple(b)
        both = fg[a] & fg[b]
        for mask, pair in ((edge, both & (np.abs(h[a] - h[b]) > step)),
                           (cut, both & (labels[a] != labels[b]))):
            mask[a] |= pair
            mask[b] |= pair
    near = ndimage.binary_dilation(edge, structure=np.ones((1, 3, 3), bool))
    return float((cut & ~near).sum() / cut.sum()) if cut.any() else float("nan")


def over_centres(seg, piles: dict, frames: dict | None, scales=SCALES) -> dict:
    """Over centre votes: the labels' `off_edge` share on the piles and on the user's `frames`
    ({x, fg}, no label); where the frames' is MISMATCH above the piles' (the template is not
    the frames' part), the largest of `scales` whose vote costs the piles at most VOTE_COST
    mIoU -> the choice, as `choose`'s, for `centre_superpixel_scale` ("mismatch": whether the
    shares say so; "off_edge": both). Without frames nothing is measured and the vote stays
    off.

    Piles that taught the net themselves (`piles["taught"]`: pasted from the user's frames,
    `learning.pasted`) are of the frames' own part, so the shares compare nothing: there the
    scale is the best by its gain on them, as `choose` picks it for the z-buffer's labels (on a
    crank the net's piles chose 80, 0.593 -> 0.630 on a fresh recording; docs/experiments.md,
    2026-12-08)."""
    cfg = seg.inference
    none = {"scale": 0, "default": 0, "frames": 0, "rows": [],
            "setting": "centre_superpixel_scale"}
    if piles.get("taught"):
        _check(piles, scales)
        cfg = replace(cfg, centre_superpixel_scale=0)
        outs = _labels(seg, piles["x"], piles["fg"], cfg)
        return {**none, **_by_gain(seg, outs, piles, scales, 0, "centre_superpixel_scale"),
                "taught": True, "note": "chosen on the piles the centre votes were taught on"}
    if frames is None or not len(frames["x"]):
        return {**none, "note": "no vote over centre votes"}
    _check(piles, scales)
    cfg = replace(cfg, centre_superpixel_scale=0)
    outs_p = _labels(seg, piles["x"], piles["fg"], cfg)
    plain = _voted(seg, outs_p, cfg)
    outs_f = _labels(seg, frames["x"], frames["fg"], cfg)
    shares = {"piles": off_edge(piles["x"], piles["fg"], plain),
              "frames": off_edge(frames["x"], frames["fg"], _voted(seg, outs_f, cfg))}
    ratio, gap = MISMATCH  # a share without boundaries (NaN) says nothing: no mismatch
    mismatch = bool(shares["frames"] >= ratio * shares["piles"]
                    and shares["frames"] - shares["piles"] >= gap)
    record = {**none, "frames": len(piles["x"]), "user_frames": len(frames["x"]),
              "off_edge": {k: None if np.isnan(v) else round(v, 4) for k, v in shares.items()},
              "mismatch": mismatch, "vote_cost": VOTE_COST}
    if not mismatch:
        return {**record, "note": "the labels follow the frames' edges as the piles': no vote "
                                  "over centre votes"}
    base = miou_batch(plain, piles["labels"])
    for s in sorted({int(v) for v in scales}):
        gain = miou_batch(_voted(seg, outs_p, replace(cfg, centre_superpixel_scale=s)),
                          piles["labels"]) - base
        record["rows"].append({"scale": s, "miou": float(mean_miou(base + gain)),
                               "gain": float(np.nanmean(gain))})
    fits = [r["scale"] for r in record["rows"] if r["gain"] >= -VOTE_COST]
    record["scale"] = max(fits) if fits else 0
    return record


def describe(choice: dict) -> str:
    """One line for a model card: the scores and the scale kept."""
    if choice.get("setting") == "centre_superpixel_scale" and "off_edge" in choice:
        off = {k: "none" if v is None else f"{v:.3f}" for k, v in choice["off_edge"].items()}
        share = (f"the labels' boundaries off the heights' edges: {off['frames']} of them "
                 f"on {choice['user_frames']} of the user's frames, "
                 f"{off['piles']} on {choice['frames']} labelled piles")
        if not choice["mismatch"]:
            return f"off over centre votes ({share})"
        return (f"over centre votes at scale {choice['scale']}: {share}, so the template is not "
                f"the frames' part; the largest scale costing the piles at most "
                f"{choice['vote_cost']} mIoU (" + ", ".join(
                    f"{r['scale']}: {r['gain']:+.3f}" for r in choice["rows"]) + ")")
    if not choice.get("rows"):
        return f"not chosen ({choice.get('note', 'no piles')})"
    if choice.get("taught"):
        scores = ", ".join(f"{r['scale']}: {r['miou']:.3f}" for r in choice["rows"])
        return (f"over centre votes at scale {choice['scale']} (0: off), chosen on "
                f"{choice['frames']} piles pasted from the user's frames, of those the centre "
                f"votes were taught on (mIoU by scale: {scores}; off unless a scale beats it "
                f"by more than {choice['tolerance']} and {SIGNIFICANCE:g} standard errors)")
    scores = ", ".join(f"{r['scale']}: {r['miou']:.3f}" for r in choice["rows"])
    return (f"scale {choice['scale']}, chosen on {choice['frames']} labelled simulated piles of "
            f"the learned part (mIoU by scale: {scores}; the settings' own {choice['default']} "
            f"is kept unless another beats it by more than {choice['tolerance']} and "
            f"{SIGNIFICANCE:g} standard errors)")
