"""InSeGAN against the classical baselines: the same frames, the same foreground, the paper's mIoU.

Every method segments the model's 64 x 64 input (the bin region, heights above the floor) and is
scored against the ground truth resized to 64 x 64, restricted to ground-truth foreground (the
paper's protocol). The hard subset is the frames where K-Means scores below 0.6, as the paper
chose its test images.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

HARD_THRESHOLD = 0.6


def run_methods(data: dict, n: int, segmenter=None, methods=None, progress: bool = True) -> dict:
    """-> {method: {"scores": (N,) per-frame mIoU, "labels": (N, 64, 64), "seconds": total}}."""
    from .baselines import BASELINES
    from .metrics import miou_batch

    methods = list(BASELINES) if methods is None else methods
    unknown = [m for m in methods if m not in BASELINES]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}; valid: {', '.join(BASELINES)}")
    x, fg, gt = data["x"], data["fg"], data["labels"]
    heights = (x[:, 0] + 1) / 2
    results = {}
    if segmenter is not None:
        t0 = time.perf_counter()
        outs = [segmenter.segment_batch(x[i:i + 50], fg[i:i + 50]) for i in range(0, len(x), 50)]
        results["inseggan"] = {
            "labels": np.concatenate([o["labels"].cpu().numpy() for o in outs]),
            "reconstruction": np.concatenate([o["reconstruction"].cpu().numpy() for o in outs]),
            "seconds": time.perf_counter() - t0}
    for name in methods:
        fn = BASELINES[name]
        t0 = time.perf_counter()
        labels = np.stack([fn(heights[i], fg[i], n, seed=i) for i in
                           tqdm(range(len(x)), desc=name, unit="frame", disable=not progress,
                                leave=False)])
        results[name] = {"labels": labels, "seconds": time.perf_counter() - t0}
    for r in results.values():
        r["scores"] = miou_batch(r["labels"], gt)
    return results


def summarise(results: dict, frames: int) -> dict:
    from .metrics import mean_miou

    ref = results.get("kmeans")
    hard = ref["scores"] < HARD_THRESHOLD if ref is not None else np.zeros(frames, bool)
    table = {}
    for name, r in results.items():
        table[name] = {"miou_all": float(mean_miou(r["scores"])),
                       "miou_hard": float(mean_miou(r["scores"][hard])) if hard.any() else None,
                       "ms_per_frame": 1000 * r["seconds"] / max(frames, 1)}
    return {"frames": int(frames), "hard_frames": int(hard.sum()),
            "hard_rule": f"kmeans mIoU < {HARD_THRESHOLD}", "methods": table}


def format_table(summary: dict) -> str:
    lines = [f"| method | mIoU, all {summary['frames']} frames | mIoU, hard subset "
             f"({summary['hard_frames']} frames) | ms / frame |", "|---|---|---|---|"]
    for name, m in summary["methods"].items():
        hard = f"{m['miou_hard']:.3f}" if m["miou_hard"] is not None else "-"
        lines.append(f"| {name} | {m['miou_all']:.3f} | {hard} | {m['ms_per_frame']:.1f} |")
    return "\n".join(lines)


def pick_frames(results: dict, count: int = 6) -> list[int]:
    """Frames to show: up to half from the hard subset (K-Means < 0.6), the rest in order."""
    n = len(next(iter(results.values()))["labels"])
    hard = list(np.nonzero(results["kmeans"]["scores"] < HARD_THRESHOLD)[0][:count // 2]) \
        if "kmeans" in results else []
    return (hard + [i for i in range(n) if i not in hard])[:count]


def qualitative_png(path, data: dict, results: dict, frames=None, count: int = 6) -> Path:
    """Rows of: input | reconstruction | InSeGAN | each baseline | ground truth."""
    from . import viz

    frames = pick_frames(results, count) if frames is None else frames
    recon = results.get("inseggan", {}).get("reconstruction")
    rows, titles = [], ["input"] + (["reconstruction"] if recon is not None else []) + \
        list(results) + ["ground truth"]
    for i in frames:
        row = [viz.gray(data["x"][i, 0])] + ([viz.gray(recon[i, 0])] if recon is not None else [])
        row += [viz.colorize_labels(r["labels"][i]) for r in results.values()]
        row.append(viz.colorize_labels(data["labels"][i]))
        rows.append(row)
    return viz.save_sheet(path, rows, col_titles=titles, cell_inches=1.3, dpi=70)


def write_json(path, obj) -> None:
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)
