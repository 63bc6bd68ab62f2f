"""Piles pasted from the recording's own parts: centre votes taught without a template.

The centre votes learn what a part looks like from labelled piles. The loop's piles are piles of
its kept template, and where no template family has the part's outline (a crank, a Z-bracket)
they teach the votes the wrong part: they cut the part where the template would end and join
pieces of neighbours. The user's frames hold the right part, unlabelled: a part on top of the
pile is seen whole, and every foreground pixel round it is lower. So the frames are cut into
depth segments (Felzenszwalb's graph segmentation at a few scales, skimage), and a segment is
kept as a whole part where

* every neighbouring foreground pixel but a few is at least `step` lower than the segment's
  pixels beside it (nothing lies on it, and it is not a piece of a part that goes on higher);
* it keeps clear of the crop's border (not cut by the bin's wall or the view);
* its area is that of one part: between `min_area` and `max_area` times the frames' mean
  foreground per part (the recording's n parts).

Piles are then made by pasting those parts, each turned and mirrored at random, one over
another at heights on what lies below, with a z-buffer: the last pasted is seen whole, those
under it as much as it leaves visible, as in a real pile. The labels come from the pasting.
This is copy-paste augmentation (Dwibedi et al. 2017, "Cut, Paste and Learn"; Ghiasi et al.
2021) on depth, with no label read. The parts' sensor noise is the recording's own.

    parts = harvest(frames["x"], frames["fg"], n, prep)
    splits = paste_splits(frames, n, prep)      # {"train": {x, fg, labels}, "val": ...}
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class PasteConfig:
    scales: tuple[float, ...] = (400.0, 800.0, 1600.0)  # Felzenszwalb scales the frames are cut at
    sigma: float = 0.3  # Felzenszwalb's smoothing, in pixels (the baseline's)
    min_area: float = 0.8  # a part's area, times the frames' mean foreground per part: at least
    max_area: float = 1.8  # and at most (parts overlap: one seen whole is above the mean)
    step: float = 0.002  # metres: a neighbour this much lower than the segment's edge is below
    tolerance: float = 0.1  # the share of neighbouring pixels that may be no lower (noise)
    margin: int = 2  # pixels: a kept part keeps this far from the crop's border
    train: int = 3000  # piles to learn from
    val: int = 200  # piles to choose the best iteration by
    seed: int = 0

    def __post_init__(self):
        if not self.scales or any(not s > 0 for s in self.scales):
            raise ValueError(f"scales {self.scales!r} invalid; valid: one or more, each > 0")
        if not 0 < self.min_area < self.max_area:
            raise ValueError(f"min_area {self.min_area!r}, max_area {self.max_area!r} invalid; "
                             "valid: 0 < min_area < max_area")
        if not 0 <= self.tolerance < 1 or self.step < 0 or self.margin < 0:
            raise ValueError("tolerance in [0, 1), step >= 0 and margin >= 0 are valid; got "
                             f"{self.tolerance!r}, {self.step!r}, {self.margin!r}")
        if self.train < 1 or self.val < 1:
            raise ValueError(f"train {self.train!r}, val {self.val!r} invalid; valid: >= 1 each")


@dataclass(frozen=True)
class Part:
    heights: np.ndarray  # (h, w) float32 metres above its lowest visible point, 0 off the part
    mask: np.ndarray  # (h, w) bool


def heights_of(x: np.ndarray, prep) -> np.ndarray:
    """The model's input (B, 1, S, S) or (B, S, S) in [-1, 1] -> heights above the floor in
    metres (0 where x is -1, the background)."""
    x = np.asarray(x, np.float32)
    if x.ndim == 4:
        x = x[:, 0]
    return (x + 1) * np.float32(prep.max_height / 2)


def harvest(x: np.ndarray, fg: np.ndarray, n: int, prep,
            cfg: PasteConfig = PasteConfig()) -> list[Part]:
    """The parts seen whole in the frames `x` (the model's input) and `fg`: see the module's
    docstring. A segment kept at one scale is not kept again at another (80 % overlap)."""
    from skimage.segmentation import felzenszwalb

    if n < 1:
        raise ValueError(f"n {n!r} invalid; valid: >= 1 (the parts in the bin)")
    H, FG = heights_of(x, prep), np.asarray(fg, bool)
    if H.shape != FG.shape:
        raise ValueError(f"x {H.shape} and fg {FG.shape} differ; valid: the same frames")
    if not len(H):
        return []
    per_part = float(FG.sum((1, 2)).mean()) / n
    lo, hi = cfg.min_area * per_part, cfg.max_area * per_part
    size = H.shape[-1]
    parts: list[Part] = []
    for h, f in zip(H, FG):
        if not f.any():
            continue
        image = np.where(f, h / max(float(h[f].max()), 1e-9), -1.0)
        top = None
        kept: list[np.ndarray] = []
        for scale in cfg.scales:
            segments = np.where(f, felzenszwalb(image, scale=scale, sigma=cfg.sigma,
                                                min_size=20) + 1, 0)
            areas = np.bincount(segments.ravel())
            for s in np.flatnonzero((areas >= lo) & (areas <= hi)):
                if s == 0:
                    continue
                m = segments == s
                ys, xs = np.nonzero(m)
                y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
                if min(y0, x0) < cfg.margin or max(y1, x1) > size - cfg.margin:
                    continue
                if any((m & k).sum() > 0.8 * min(len(ys), k.sum()) for k in kept):
                    continue
                ring = ndimage.binary_dilation(m) & ~m & f
                if ring.any():
                    top = ndimage.maximum_filter(np.where(m, h, -np.inf), size=3)
                    if (h[ring] > top[ring] - cfg.step).mean() > cfg.tolerance:
                        continue
                kept.append(m)
                mask = m[y0:y1, x0:x1]
                part = np.where(mask, h[y0:y1, x0:x1], 0.0)
                part = np.where(mask, part - part[mask].min(), 0.0).astype(np.float32)
                parts.append(Part(part, mask.copy()))
    return parts


def _turned(part: Part, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The part mirrored (half the time) and turned by a uniform angle, on a square canvas."""
    h, m = part.heights, part.mask
    if rng.random() < 0.5:
        h, m = h[:, ::-1], m[:, ::-1]
    side = int(np.ceil(np.hypot(*m.shape))) + 2
    canvas, cmask = np.zeros((side, side), np.float32), np.zeros((side, side), np.uint8)
    oy, ox = (side - m.shape[0]) // 2, (side - m.shape[1]) // 2
    canvas[oy:oy + m.shape[0], ox:ox + m.shape[1]] = h
    cmask[oy:oy + m.shape[0], ox:ox + m.shape[1]] = m
    middle = (side - 1) / 2  # pixel centres at integers (OpenCV): the canvas turns on itself
    turn = cv2.getRotationMatrix2D((middle, middle), float(rng.uniform(0, 360)), 1.0)
    return (cv2.warpAffine(canvas, turn, (side, side), flags=cv2.INTER_NEAREST),
            cv2.warpAffine(cmask, turn, (side, side), flags=cv2.INTER_NEAREST) > 0)


def pile(parts: list[Part], count: int, centres: np.ndarray, prep, size: int,
         rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pile of `count` parts drawn from `parts`, each centred on a point drawn from
    `centres` ((k, 2) pixels: where the frames have foreground), resting at the 60th
    percentile of the heights under it -> (x (S, S) as the model's input, fg, labels 1..m in
    pasting order, only the parts left visible)."""
    h = np.zeros((size, size), np.float32)
    labels = np.zeros((size, size), np.uint8)
    for k in range(1, count + 1):
        heights, mask = _turned(parts[int(rng.integers(len(parts)))], rng)
        cy, cx = centres[int(rng.integers(len(centres)))]
        side = mask.shape[0]
        y0, x0 = int(cy) - side // 2, int(cx) - side // 2
        ty0, tx0, ty1, tx1 = max(0, y0), max(0, x0), min(size, y0 + side), min(size, x0 + side)
        if ty1 <= ty0 or tx1 <= tx0:
            continue
        m = mask[ty0 - y0:ty1 - y0, tx0 - x0:tx1 - x0]
        if not m.any():
            continue
        window = h[ty0:ty1, tx0:tx1]
        new = heights[ty0 - y0:ty1 - y0, tx0 - x0:tx1 - x0] + np.float32(
            np.percentile(window[m], 60)) + np.float32(1e-4)
        win = m & (new > window)
        window[win] = new[win]
        labels[ty0:ty1, tx0:tx1][win] = k
    fg = h > prep.min_height
    labels[~fg] = 0
    present = np.unique(labels)
    present = present[present > 0]
    relabel = np.zeros(count + 1, np.uint8)
    relabel[present] = np.arange(1, len(present) + 1)
    x = np.clip(h / np.float32(prep.max_height), 0, 1) * 2 - 1
    x[~fg] = -1.0
    return x.astype(np.float32), fg, relabel[labels]


def paste_splits(frames: dict, n: int, prep, cfg: PasteConfig = PasteConfig(),
                 min_instances: int | None = None) -> dict:
    """{"train", "val"}: `cfg.train` and `cfg.val` piles ({x (B, 1, S, S), fg, labels}) of the
    parts `harvest` finds in `frames` ({x, fg}: the user's frames as the model cuts them), each
    of n parts (or a count drawn in min_instances..n), placed where the frames have
    foreground; also "parts", how many were found. Raises ValueError where the frames show no
    part whole."""
    parts = harvest(frames["x"], frames["fg"], n, prep, cfg)
    if not parts:
        raise ValueError("no part is seen whole (on top, clear of the border, one part's "
                         "area) in any frame; valid: frames in which the top parts of the pile "
                         "are in view, or piles of the template (centre_teacher piles)")
    fg = np.asarray(frames["fg"], bool)
    centres = np.column_stack(np.nonzero(fg))[:, 1:]
    size = fg.shape[-1]
    low = n if min_instances is None else min_instances
    if not 0 <= low <= n:
        raise ValueError(f"min_instances {min_instances!r} invalid; valid: 0..{n}")
    out = {"parts": len(parts)}
    for split, count, seed in (("train", cfg.train, cfg.seed), ("val", cfg.val, cfg.seed + 1)):
        rng = np.random.default_rng(seed)
        xs, fgs, labels = zip(*(pile(parts, int(rng.integers(low, n + 1)), centres, prep,
                                     size, rng) for _ in range(count)))
        out[split] = {"x": np.stack(xs)[:, None], "fg": np.stack(fgs),
                      "labels": np.stack(labels)}
    return out
