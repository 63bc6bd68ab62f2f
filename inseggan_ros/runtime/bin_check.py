"""Does the bin look like the model's part? Label-free measures of a frame, each instance's fit,
and a verdict against the model card's own measures (no ROS).

The measures (`label_free`), on the model's input (64 x 64, heights in [-1, 1]: -1 the floor,
+1 max_height), its renders (each instance alone) and their z-buffered reconstruction:

  recon_l1             mean |reconstruction - input| over all pixels
  recon_l1_foreground  the same over the input's foreground (None without foreground)
  coverage             the share of input-foreground pixels some instance's render reaches
                       (render >= tau); None without foreground
  spill                the share of rendered pixels that are not input foreground; None when
                       nothing is rendered
  visible              per frame, the instances labelling at least MIN_VISIBLE_PIXELS pixels

`selfcheck.measure` pools them over a recording for a model card (its `measures` block); the
segmenter node computes them per frame and compares the median of its last frames with the
card's (`BinCheck`). Measured on the seven tilted RealSense models, each on its own sample bag
and on the six others (the 8 frames of each, medians): on its own bag no model's spill exceeded
its card's by more than 0.011, nor its coverage fell below its card's by more than 0.016, and
its reconstruction error stayed at or below its card's; shown a part smaller than its own, a
model's spill rises (the cylinder's from its card's 0.12 to 0.24-0.36 on the hex nuts, bolts,
pin connectors and cones), shown a larger one, its reconstruction error (the hex nut's from
0.23 to 0.35-0.63 on the cylinders, stoppers and wooden blocks). Parts of about one size and
shape (the hex nut, bolt and pin connector; the cone and stopper) are not told apart by these
measures.
"""
from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# An instance counts as visible in a frame when it labels at least this many of the 64 x 64
# pixels (a cylinder seen end-on covers about 20; a few stray pixels are not an object).
MIN_VISIBLE_PIXELS = 8
# Metres: a rendered pixel is explained by the input where the input's surface is at most this
# far below the render (the camera cannot see through a part; higher is an occluder on top).
FIT_TOLERANCE = 0.003
# The card values the verdict compares with (selfcheck.measure writes them).
REFERENCE_KEYS = ("recon_l1", "recon_l1_foreground", "coverage", "spill")


def visible_counts(labels: np.ndarray, n: int) -> np.ndarray:
    """(N, H, W) labels 0..n -> (N,) instances labelling at least MIN_VISIBLE_PIXELS pixels."""
    labels = np.asarray(labels)
    per = np.stack([(labels == k).reshape(len(labels), -1).sum(1) for k in range(1, n + 1)], 1)
    return (per >= MIN_VISIBLE_PIXELS).sum(1)


def label_free(x: np.ndarray, fg: np.ndarray, renders: np.ndarray, reconstruction: np.ndarray,
               labels: np.ndarray, tau: float) -> dict:
    """The measures of N frames, pooled: x (N, H, W) inputs, fg (N, H, W) their foreground,
    renders (N, n, H, W), reconstruction (N, H, W), labels (N, H, W) -> {recon_l1,
    recon_l1_foreground, coverage, spill (each None where undefined), visible (N,) counts}.
    One frame: N = 1."""
    x, fg = np.asarray(x, np.float32), np.asarray(fg, bool)
    renders = np.asarray(renders)
    drawn = renders.max(1) >= tau
    err = np.abs(np.asarray(reconstruction, np.float32) - x)
    fg_pixels, drawn_pixels = int(fg.sum()), int(drawn.sum())
    return {
        "recon_l1": float(err.mean()),
        "recon_l1_foreground": float(err[fg].mean()) if fg_pixels else None,
        "coverage": float((drawn & fg).sum() / fg_pixels) if fg_pixels else None,
        "spill": float((drawn & ~fg).sum() / drawn_pixels) if drawn_pixels else None,
        "visible": visible_counts(labels, renders.shape[1]),
    }


def instance_fit(renders: np.ndarray, x: np.ndarray, fg: np.ndarray, tau: float,
                 max_height: float, labels: np.ndarray | None = None,
                 scores: np.ndarray | None = None) -> np.ndarray:
    """(n,) each instance's fit in [0, 1]: the share of its render's pixels (render >= tau;
    renders (n, H, W), one frame) that the input explains: input foreground whose surface is
    not more than FIT_TOLERANCE below the render (a part hidden under others still fits; one
    floating over the floor or above what the camera sees does not). 0 where it is not
    rendered, and (given `labels` and `scores`, the Segmentation's) for a piece split off
    another instance, which has no render of its own (it holds pixels but scores 0)."""
    renders, x, fg = np.asarray(renders), np.asarray(x), np.asarray(fg, bool)
    tol = 2.0 * FIT_TOLERANCE / max_height  # metres -> the model's units
    drawn = renders >= tau
    explained = drawn & fg[None] & (x[None] >= renders - tol)
    count = drawn.reshape(len(renders), -1).sum(1)
    fit = np.where(count > 0, explained.reshape(len(renders), -1).sum(1) / np.maximum(count, 1),
                   0.0)
    if labels is not None and scores is not None:
        present = np.bincount(np.asarray(labels).ravel(),
                              minlength=len(renders) + 1)[1:len(renders) + 1] > 0
        fit = np.where(present & (np.asarray(scores) <= 0), 0.0, fit)
    return fit


def card_reference(model_path) -> tuple[dict | None, str]:
    """The label-free measures of the model card beside `model_path` (card.json's `measures`,
    as `inseggan export --bag` writes them) -> ({key: value} of REFERENCE_KEYS, where it came
    from), or (None, why there is none)."""
    card = Path(model_path).with_name("card.json")
    if not card.is_file():
        return None, f"no reference: no card.json beside {Path(model_path).name}"
    try:
        measures = json.loads(card.read_text()).get("measures")
    except (OSError, ValueError, AttributeError) as e:
        return None, f"no reference: {card.name} unreadable ({e})"
    if not isinstance(measures, dict):
        return None, ("no reference: the model card has no label-free measures (`measures`, "
                      "from `inseggan export --bag`)")
    ref = {k: measures.get(k) for k in REFERENCE_KEYS}
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in ref.values()):
        return None, f"no reference: the card's measures lack one of {', '.join(REFERENCE_KEYS)}"
    return {k: float(v) for k, v in ref.items()}, f"{card.parent.name}/card.json measures"


@dataclass(frozen=True)
class Margins:
    """How far the recent frames' medians may leave the card's values before the bin counts
    as unlike the model's part (see the module's figures: each model on its own bag stayed
    well inside these, most others outside one of them)."""

    recon_ratio: float = 1.3  # recon_l1 above the card's times this
    spill_excess: float = 0.08  # spill above the card's plus this
    coverage_drop: float = 0.10  # coverage below the card's minus this


@dataclass(frozen=True)
class Verdict:
    level: str  # "ok" or "warn"
    message: str
    values: dict  # name -> text, for /diagnostics


CAUSES = ("another part in the bin, the camera moved, or fewer parts than the model's n "
          "(an emptying bin)")


class BinCheck:
    """The last `window` frames' measures and what they say against the card's (`reference`,
    from `card_reference`; None: the values are shown, nothing is judged)."""

    MIN_FRAMES = 5  # the medians of fewer frames (a node's first, its bin not yet found) judge not

    def __init__(self, reference: dict | None, source: str, n: int, window: int = 15,
                 margins: Margins = Margins()):
        self.reference, self.source, self.n, self.margins = reference, source, n, margins
        self.frames = deque(maxlen=window)  # measures of recent frames with foreground
        self.min_frames = min(window, self.MIN_FRAMES)
        self.last = None  # the last frame's measures (an empty bin's too)

    def add(self, measures: dict) -> None:
        """One frame's `label_free` measures (N = 1)."""
        m = {**measures, "visible": int(np.asarray(measures["visible"]).reshape(-1)[0]),
             "empty": measures["coverage"] is None}
        self.last = m
        if not m["empty"]:
            self.frames.append(m)

    def medians(self) -> dict:
        """{measure: its median over the window's frames (those where it is defined)}."""
        out = {}
        for k in (*REFERENCE_KEYS, "visible"):
            values = [f[k] for f in self.frames if f[k] is not None]
            if values:
                out[k] = float(np.median(values))
        return out

    def verdict(self) -> Verdict:
        if self.last is None:
            return Verdict("ok", "no frame yet", {"reference": self.source})
        values = {"reference": self.source, "frames_in_window": str(len(self.frames))}
        for k, v in self.last.items():
            if k != "empty":
                values[f"last_{k}"] = "-" if v is None else (f"{v:.4f}" if isinstance(v, float)
                                                             else str(v))
        med = self.medians()
        values.update({f"median_{k}": f"{v:.4f}" for k, v in med.items()})
        if self.reference is not None:
            values.update({f"card_{k}": f"{v:.4f}" for k, v in self.reference.items()})
        if self.last["empty"]:
            return Verdict("warn", "bin empty: no foreground above min_height in the last frame, "
                                   "no instances", values)
        if self.reference is None:
            return Verdict("ok", f"not checked ({self.source})", values)
        if len(self.frames) < self.min_frames:
            return Verdict("ok", f"collecting frames ({len(self.frames)} of the "
                                 f"{self.min_frames} it judges on)", values)
        off = self.departures(med)
        if off:
            return Verdict("warn", f"the bin does not look like the model's part ({'; '.join(off)}"
                                   f"): {CAUSES} = {self.n}", values)
        return Verdict("ok", "the bin looks like the model's part", values)

    def departures(self, med: dict) -> list[str]:
        """What of the medians `med` leaves the card's range, as text."""
        ref, mg, out = self.reference, self.margins, []
        if med.get("recon_l1", -math.inf) > ref["recon_l1"] * mg.recon_ratio:
            out.append(f"reconstruction error {med['recon_l1']:.3f} > card "
                       f"{ref['recon_l1']:.3f} x {mg.recon_ratio:g}")
        if med.get("spill", -math.inf) > ref["spill"] + mg.spill_excess:
            out.append(f"spill {med['spill']:.3f} > card {ref['spill']:.3f} + "
                       f"{mg.spill_excess:g}")
        if med.get("coverage", math.inf) < ref["coverage"] - mg.coverage_drop:
            out.append(f"coverage {med['coverage']:.3f} < card {ref['coverage']:.3f} - "
                       f"{mg.coverage_drop:g}")
        return out
