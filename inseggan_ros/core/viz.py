"""Pictures people look at: depth and label images as colour, contact sheets as PNG."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# Distinct colours for instance labels 1..n (0 = background, black).
PALETTE = np.array([
    [0, 0, 0], [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
    [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212],
    [0, 128, 128], [220, 190, 255], [170, 110, 40], [255, 250, 200], [128, 0, 0],
    [170, 255, 195], [128, 128, 0], [255, 215, 180], [0, 0, 128], [128, 128, 128]], np.uint8)


def colorize_labels(labels: np.ndarray) -> np.ndarray:
    """(H, W) integer labels -> (H, W, 3) uint8 RGB."""
    return PALETTE[np.asarray(labels) % len(PALETTE)]


def gray(x: np.ndarray) -> np.ndarray:
    """(H, W) model image in [-1, 1] (floor -1) -> (H, W, 3) uint8 gray."""
    g = ((np.clip(x, -1, 1) + 1) * 127.5).astype(np.uint8)
    return np.repeat(g[..., None], 3, -1)


def colorize_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) uint8 RGB; near is bright; missing (0) is black."""
    import cv2

    d = np.asarray(depth_m, np.float32)
    valid = np.isfinite(d) & (d > 0)
    if not valid.any():
        return np.zeros((*d.shape, 3), np.uint8)
    # far end: the bin floor (the most common depth); near end: the nearest few pixels, so
    # that objects on the floor use the whole colour range and bin walls saturate
    lo, hi = np.percentile(d[valid], [0.5, 60])
    g = np.clip((hi - d) / max(hi - lo, 1e-6), 0, 1)
    rgb = cv2.applyColorMap((g * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
    rgb[~valid] = 0
    return rgb


def overlay(depth_m: np.ndarray, labels: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    gray = colorize_depth(depth_m).mean(-1, keepdims=True).repeat(3, -1)
    col = colorize_labels(labels).astype(np.float32)
    out = np.where(labels[..., None] > 0, (1 - alpha) * gray + alpha * col, gray)
    return out.astype(np.uint8)


def save_sheet(path, rows: list[list[np.ndarray]], row_titles=None, col_titles=None,
               cell_inches: float = 2.2, dpi: int = 80) -> Path:
    """Save a grid of RGB images (rows x columns) as a PNG, written atomically."""
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nr, nc = len(rows), max(len(r) for r in rows)
    fig, axes = plt.subplots(nr, nc, figsize=(cell_inches * nc, cell_inches * nr), squeeze=False)
    for i, row in enumerate(rows):
        for j in range(nc):
            ax = axes[i][j]
            ax.axis("off")
            if j < len(row):
                ax.imshow(row[j], interpolation="nearest")
            if i == 0 and col_titles and j < len(col_titles):
                ax.set_title(col_titles[j], fontsize=9)
            if j == 0 and row_titles:
                ax.text(-0.05, 0.5, row_titles[i], transform=ax.transAxes, rotation=90,
                        ha="right", va="center", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def plot_history(history: list, path, panels) -> None:
    """Training curves as PNG, written atomically. `history`: records with "kind" ("train" or
    "val") and "iteration"; `panels`: (title, kind, keys) per subplot; validation keys are
    drawn with markers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 3.5), squeeze=False)
    for ax, (title, kind, keys) in zip(axes[0], panels):
        for key in keys:
            pts = [(h["iteration"], h[key]) for h in history if h["kind"] == kind and key in h]
            if pts:
                ax.plot(*zip(*pts), **({"marker": "o", "label": f"val {key}"} if kind == "val"
                                       else {"label": key}))
        ax.set_title(title)
        ax.set_xlabel("iteration")
        if ax.get_legend_handles_labels()[0]:  # a panel with no records yet has no legend
            ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=70)
    plt.close(fig)
    tmp.replace(path)
