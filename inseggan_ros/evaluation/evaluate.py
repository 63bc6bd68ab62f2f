"""InSeGAN against the classical baselines: the same frames, the same foreground, the paper's mIoU.

Every method segments the model's 64 x 64 input (the bin region, heights above the floor) and is
scored against the ground truth resized to 64 x 64, restricted to ground-truth foreground (the
paper's protocol). Two hard subsets: the paper's, frames where K-Means scores below 0.6 (as the
paper chose its test images), and frames where Felzenszwalb's graph segmentation scores below
0.8 (touching parts at one height, heavy occlusion: where a shape model should win).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

HARD_THRESHOLD = 0.6  # the paper's hard subset: K-Means below this
HARD_FELZENSZWALB_THRESHOLD = 0.8  # the second hard subset: Felzenszwalb below this


def run_methods(data: dict, n: int, segmenter=None, methods=None, progress: bool = True) -> dict:
    """-> {method: {"scores": (N,) per-frame mIoU, "labels": (N, 64, 64), "seconds": total}}."""
    from inseggan_ros.evaluation.baselines import BASELINES
    from inseggan_ros.core.metrics import miou_batch

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


def hard_subsets(results: dict, frames: int) -> dict:
    """{name: (rule, (N,) bool)} of the hard subsets whose reference method was run."""
    subsets = {}
    for key, method, threshold in (("hard", "kmeans", HARD_THRESHOLD),
                                   ("hard_felzenszwalb", "felzenszwalb",
                                    HARD_FELZENSZWALB_THRESHOLD)):
        if method in results:
            subsets[key] = (f"{method} mIoU < {threshold}", results[method]["scores"] < threshold)
    return subsets


def summarise(results: dict, frames: int) -> dict:
    """Mean mIoU of every method on all frames and on each hard subset, and time per frame."""
    from inseggan_ros.core.metrics import mean_miou

    subsets = hard_subsets(results, frames)
    hard = subsets.get("hard", (None, np.zeros(frames, bool)))[1]
    table = {}
    for name, r in results.items():
        table[name] = {"miou_all": float(mean_miou(r["scores"])),
                       "ms_per_frame": 1000 * r["seconds"] / max(frames, 1)}
        for key, (_, mask) in subsets.items():
            table[name][f"miou_{key}"] = float(mean_miou(r["scores"][mask])) if mask.any() else None
        table[name].setdefault("miou_hard", None)
    out = {"frames": int(frames), "hard_frames": int(hard.sum()),
           "hard_rule": f"kmeans mIoU < {HARD_THRESHOLD}", "methods": table}
    if "hard_felzenszwalb" in subsets:
        rule, mask = subsets["hard_felzenszwalb"]
        out.update(hard_felzenszwalb_frames=int(mask.sum()), hard_felzenszwalb_rule=rule)
    return out


def format_table(summary: dict) -> str:
    second = "hard_felzenszwalb_frames" in summary
    head = (f"| method | mIoU, all {summary['frames']} frames | hard: K-Means < 0.6 "
            f"({summary['hard_frames']} frames) |")
    if second:
        head += f" hard: Felzenszwalb < 0.8 ({summary['hard_felzenszwalb_frames']} frames) |"
    lines = [head + " ms / frame |", "|---" * (4 + second) + "|"]

    def cell(v):
        return f"{v:.3f}" if v is not None else "-"

    for name, m in summary["methods"].items():
        row = f"| {name} | {m['miou_all']:.3f} | {cell(m['miou_hard'])} |"
        if second:
            row += f" {cell(m.get('miou_hard_felzenszwalb'))} |"
        lines.append(row + f" {m['ms_per_frame']:.1f} |")
    return "\n".join(lines)


def pick_frames(results: dict, count: int = 6) -> list[int]:
    """Frames to show: up to half from the hard subset (K-Means < 0.6), the rest in order."""
    n = len(next(iter(results.values()))["labels"])
    hard = list(np.nonzero(results["kmeans"]["scores"] < HARD_THRESHOLD)[0][:count // 2]) \
        if "kmeans" in results else []
    return (hard + [i for i in range(n) if i not in hard])[:count]


def qualitative_png(path, data: dict, results: dict, frames=None, count: int = 6) -> Path:
    """Rows of: input | reconstruction | InSeGAN | each baseline | ground truth."""
    from inseggan_ros.core import viz

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
    """`obj` as indented JSON at `path`, atomically (a killed run leaves the old file or the
    new one); what JSON has no type for (paths) as its str()."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str))
    os.replace(tmp, path)
