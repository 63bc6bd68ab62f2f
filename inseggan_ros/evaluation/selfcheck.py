"""How well a model explains depth frames that come without ground truth, and tau from them.

A recording of a user's own part has no instance labels, so neither the paper's mIoU nor the
labelled calibration of tau (`segment.calibrate_tau` with labels) applies. What can be measured
on the frames alone:

* **tau from the frames** (`tau_from_frames`): the render threshold at which the model's
  foreground (pixels where some instance's render reaches tau) best matches the input's own
  foreground (the preprocessed x > -1, heights above min_height), by mean per-frame IoU.
* **label-free measures** (`measure`), the model run frame by frame with its shipped settings:
  reconstruction error (L1 of the z-buffered render vs the input, in the model's [-1, 1] units);
  coverage (the fraction of input-foreground pixels some instance's render explains) and spill
  (the fraction of rendered pixels that are not input foreground); how consistent the count of
  visible instances is (how often it equals n, its mean and spread); time per frame.

`inseggan export --bag` writes these into a model card; `inseggan check` prints them for a few
frames and draws a sheet (`sheet_png`). Nothing here imports ROS.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

# the per-frame measures are the runtime's, which the segmenter node computes on every frame
from inseggan_ros.runtime.bin_check import MIN_VISIBLE_PIXELS, label_free

# Scores within this much of the best IoU count as a tie (`tau_from_frames`).
TIE = 0.002


def foreground_threshold(prep_cfg) -> float:
    """Where the input's foreground starts, in the model's units: min_height above the floor
    (the input is -1 below it; heights 0..max_height map to -1..+1)."""
    return float(-1 + 2 * prep_cfg.min_height / prep_cfg.max_height)


def tau_from_frames(renders: torch.Tensor, fg: torch.Tensor, prep_cfg=None,
                    grid=None) -> tuple[float, dict]:
    """(B, n, H, W) single-instance renders and the inputs' (B, H, W) foreground -> (tau,
    {tau: mean IoU}) without labels.

    For each tau of the grid (`segment.TAU_GRID`): per frame the IoU of the rendered foreground
    (max render >= tau) with the input's foreground, averaged over the frames that have any
    foreground. The best tau wins; scores within TIE of the best count as equal, and among them
    the one nearest the input's own foreground threshold (`foreground_threshold`, when
    `prep_cfg` is given) is taken: the renders are heights in the input's units, so an instance
    ends where the input's object ends. (`segment.calibrate_tau` without labels breaks ties
    towards tau = 0 and counts frames without foreground, which score 0 at every tau.)"""
    from inseggan_ros.runtime.segment import (  # the lead may move the grid out of segment.py
        TAU_GRID)

    grid = TAU_GRID if grid is None else grid
    fg = torch.as_tensor(fg, device=renders.device).bool()
    has_fg = fg.flatten(1).any(1)
    if not bool(has_fg.any()):
        raise ValueError("no foreground in any frame: tau cannot be calibrated on empty bins "
                         "(check min_height and the bin region)")
    top, fg = renders.max(dim=1).values[has_fg], fg[has_fg]
    scores = {}
    for tau in grid:
        drawn = top >= tau
        inter = (drawn & fg).flatten(1).sum(-1).float()
        union = (drawn | fg).flatten(1).sum(-1).float()
        scores[float(tau)] = float((inter / union).mean())
    best = max(scores.values())
    ties = [t for t, s in scores.items() if s >= best - TIE]
    anchor = foreground_threshold(prep_cfg) if prep_cfg is not None else None
    tau = (min(ties, key=lambda t: (abs(t - anchor), t)) if anchor is not None
           else max(ties, key=lambda t: scores[t]))
    return float(tau), scores


@torch.no_grad()
def calibrate(seg, x: np.ndarray, fg: np.ndarray, chunk: int = 50) -> tuple[float, dict]:
    """The tau of `seg` (a segment.Segmenter) from its own renders of frames x (N, 1, 64, 64) with
    its test-time settings (refinement, starting points) -> (tau, {tau: IoU})."""
    if len(x) == 0:
        raise ValueError("no frames to calibrate tau on")
    renders = torch.cat([seg.segment_batch(x[i:i + chunk], fg[i:i + chunk])["renders"].cpu()
                         for i in range(0, len(x), chunk)])
    return tau_from_frames(renders, torch.from_numpy(np.asarray(fg)), seg.prep_cfg)


@torch.no_grad()
def segment_frames(seg, x: np.ndarray, fg: np.ndarray) -> dict:
    """Every frame through `seg.segment_batch` on its own, as the segmenter node runs ->
    {labels (N, 64, 64), reconstruction (N, 64, 64), renders (N, n, 64, 64), seconds (N,)}."""
    if len(x) == 0:
        raise ValueError("no frames to segment")
    seg.segment_batch(x[:1], fg[:1])  # warm-up: first-call allocations are not a frame's time
    out = {"labels": [], "reconstruction": [], "renders": [], "seconds": []}
    for i in range(len(x)):
        t0 = time.perf_counter()
        o = seg.segment_batch(x[i:i + 1], fg[i:i + 1])
        out["seconds"].append(time.perf_counter() - t0)
        out["labels"].append(o["labels"][0].cpu().numpy())
        out["reconstruction"].append(o["reconstruction"][0, 0].cpu().numpy())
        out["renders"].append(o["renders"][0].cpu().numpy())
    return {k: np.stack(v) if k != "seconds" else np.array(v) for k, v in out.items()}


def measure(seg, x: np.ndarray, fg: np.ndarray, out: dict | None = None) -> dict:
    """The label-free measures of `seg` on frames x (N, 1, 64, 64) with foreground fg (N, 64,
    64) (`out`: their `segment_frames`, if already run) -> a dict for the model card."""
    out = segment_frames(seg, x, fg) if out is None else out
    x0 = np.asarray(x)[:, 0]
    n = seg.model_cfg.n_instances
    m = label_free(x0, fg, out["renders"], out["reconstruction"], out["labels"], seg.tau)
    counts = m.pop("visible")
    return {
        "frames": int(len(x0)), "n_instances": n, "tau": float(seg.tau), **m,
        "count_equals_n": float((counts == n).mean()),
        "count_mean": float(counts.mean()), "count_std": float(counts.std()),
        "count_histogram": {str(k): int((counts == k).sum()) for k in range(n + 1)},
        "min_visible_pixels": MIN_VISIBLE_PIXELS,
        "ms_per_frame": float(1000 * np.median(out["seconds"])),
        "ms_per_frame_p90": float(1000 * np.percentile(out["seconds"], 90)),
    }


def format_measures(m: dict) -> str:
    """The measures of `measure` as a few lines of text (for the terminal and the card)."""
    hist = ", ".join(f"{k}: {v}" for k, v in m["count_histogram"].items() if v)
    cov = "-" if m["coverage"] is None else f"{m['coverage']:.3f}"
    spill = "-" if m["spill"] is None else f"{m['spill']:.3f}"
    return "\n".join([
        f"frames: {m['frames']}, tau {m['tau']:.3f}",
        f"reconstruction L1 (model units, [-1, 1]): {m['recon_l1']:.4f} over all pixels"
        + (f", {m['recon_l1_foreground']:.4f} on the input's foreground"
           if m["recon_l1_foreground"] is not None else ""),
        f"coverage of the input foreground by the instances: {cov}; rendered pixels off the "
        f"input foreground: {spill}",
        f"visible instances (>= {m['min_visible_pixels']} pixels) = n = {m['n_instances']} in "
        f"{100 * m['count_equals_n']:.0f} % of frames; mean {m['count_mean']:.2f}, std "
        f"{m['count_std']:.2f}; frames per count: {hist}",
        f"time per frame (64 x 64 input, the model's settings, one frame at a time): median "
        f"{m['ms_per_frame']:.1f} ms, p90 {m['ms_per_frame_p90']:.1f} ms",
    ])


def sheet_png(path, x: np.ndarray, out: dict, frames=None, labels_gt: np.ndarray | None = None,
              count: int = 6) -> Path:
    """Rows of: input | reconstruction | labels | each instance rendered alone (| ground truth,
    when given), for `frames` (default: `count` spread over the frames)."""
    from inseggan_ros.core import viz

    N = len(x)
    frames = (np.unique(np.linspace(0, N - 1, min(count, N)).round().astype(int))
              if frames is None else frames)
    n = out["renders"].shape[1]
    rows = []
    for i in frames:
        row = [viz.gray(x[i, 0]), viz.gray(out["reconstruction"][i]),
               viz.colorize_labels(out["labels"][i])]
        row += [viz.gray(r) for r in out["renders"][i]]
        if labels_gt is not None:
            row.append(viz.colorize_labels(labels_gt[i]))
        rows.append(row)
    titles = (["input", "reconstruction", "labels"] + [f"instance {k + 1}" for k in range(n)]
              + (["ground truth"] if labels_gt is not None else []))
    return viz.save_sheet(path, rows, col_titles=titles, cell_inches=1.2, dpi=70)


def load_bag_frames(path, prep_cfg, depth_topic: str | None = None,
                    labels_topic: str | None = None, count: int | None = None) -> dict:
    """Depth frames of a bag, preprocessed as `data.load_bag` does -> {x, fg, labels (or None),
    stamp_ns, index (the frames' positions in the bag), roi and floor_depth (where each was
    cut)}. Labels only from `labels_topic`, when named (a bag's label topic is otherwise
    ignored: these are label-free measures). `count`: that many frames spread evenly over the
    bag (default: all)."""
    from inseggan_ros.io import bags
    from inseggan_ros.runtime.preprocess import prepare, resize_labels

    topics = bags.list_topics(path)
    if labels_topic is not None and labels_topic not in topics:
        raise bags.BagError(path, f"labels topic {labels_topic!r} is not in the bag; topics: "
                                  f"{', '.join(sorted(topics))}")
    wanted = None  # frame numbers to keep (None: all, or the first `count` where unknown)
    if count is not None:
        if count < 1:
            raise ValueError(f"frames {count} invalid; valid: >= 1")
        total = topics[bags.resolve_depth_topic(path, topics, depth_topic)][1]
        if total:
            wanted = set(np.linspace(0, total - 1, min(count, total)).round().astype(int).tolist())
    rows = {"x": [], "fg": [], "labels": [], "stamp_ns": [], "index": [], "roi": [],
            "floor_depth": []}
    for i, f in enumerate(bags.read_frames(path, depth_topic=depth_topic,
                                           labels_topic=labels_topic)):
        if wanted is not None and i not in wanted:
            continue
        if labels_topic is not None and f.labels is None:
            raise bags.BagError(path, f"frame {i} (stamp {f.stamp_ns}) has no label image on "
                                      f"{labels_topic!r} with the same stamp")
        try:
            p = prepare(f.metres(), prep_cfg)
        except ValueError as e:
            raise ValueError(f"{path}: frame {i} (stamp {f.stamp_ns}): {e}") from None
        rows["x"].append(p.x[None])
        rows["fg"].append(p.fg)
        rows["labels"].append(resize_labels(f.labels, p) if labels_topic is not None else None)
        rows["stamp_ns"].append(f.stamp_ns)
        rows["index"].append(i)
        rows["roi"].append(p.roi)
        rows["floor_depth"].append(p.floor_depth)
        if wanted is None and count is not None and len(rows["x"]) >= count:
            break
    if not rows["x"]:
        raise bags.BagError(path, "no depth frames")
    return {"x": np.stack(rows["x"]).astype(np.float32), "fg": np.stack(rows["fg"]),
            "labels": np.stack(rows["labels"]) if labels_topic is not None else None,
            "stamp_ns": np.array(rows["stamp_ns"], np.int64),
            "index": np.array(rows["index"], np.int64),
            "roi": np.array(rows["roi"], np.int32).reshape(-1, 4),
            "floor_depth": np.array(rows["floor_depth"], np.float32)}


def split_held_out(frames: dict, fraction: float = 0.2, limit: int | None = None
                   ) -> tuple[dict, dict]:
    """(calibration, held-out) of a recording's frames: the held-out ones are the last
    `fraction` in time order, the others calibrate tau; each at most `limit` frames, spread
    evenly."""
    if not 0 < fraction < 1:
        raise ValueError(f"held-out fraction {fraction} invalid; valid: between 0 and 1")
    N = len(frames["x"])
    k = int(round(N * fraction))
    if k < 1 or N - k < 1:
        raise ValueError(f"{N} frames are too few: need at least one to calibrate tau on and "
                         f"one held out (the last {100 * fraction:.0f} %)")

    def take(idx):
        if limit is not None and len(idx) > limit:
            idx = idx[np.unique(np.linspace(0, len(idx) - 1, limit).round().astype(int))]
        return {key: (v[idx] if isinstance(v, np.ndarray) and len(v) == N else v)
                for key, v in frames.items()}

    return take(np.arange(N - k)), take(np.arange(N - k, N))
