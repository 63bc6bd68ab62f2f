"""The model's instances voted within depth superpixels (`InferenceConfig.superpixel_scale`).

The z-buffered labels come from renders of the encoder's poses: the instances are right (how
many parts, which pixels belong together) but their outlines are a few pixels off, and at 64 x
64 a few pixels are much of a part. A graph segmentation of the input's own heights at a fine
scale (Felzenszwalb and Huttenlocher 2004, the algorithm of the classical baseline, with more,
smaller segments) cuts the frame along its height edges into superpixels that rarely straddle
two parts; each superpixel then takes the label most of its pixels have. The model still
decides which superpixels form one part, so parts that touch at one height, which the
baseline merges, stay apart wherever the superpixels separate them. Measured on the seven
parts' validation splits and chosen there, never on the test splits (docs/experiments.md,
2026-11-26).
"""
from __future__ import annotations

import numpy as np
import torch
from skimage.segmentation import felzenszwalb as _skimage_felzenszwalb

SIGMA = 0.3  # Gaussian pre-smoothing, pixels (the baseline's: keeps height steps sharp)
MIN_SIZE = 20  # pixels: smaller superpixels are merged into a neighbour


def depth_superpixels(heights: np.ndarray, fg: np.ndarray, scale: float = 200,
                      sigma: float = SIGMA, min_size: int = MIN_SIZE) -> np.ndarray:
    """Felzenszwalb-Huttenlocher graph segmentation of a height image -> (H, W) int segment
    ids. The heights are rescaled to 0..1 over fg and the background set to -1, a strong edge
    round every object; `scale` sets how large segments grow (smaller: more, finer segments)."""
    h = heights[fg]
    span = h.max() - h.min() if h.size else 0.0
    image = np.full(fg.shape, -1.0)
    image[fg] = (h - h.min()) / span if span > 0 else 0.0
    return _skimage_felzenszwalb(image, scale=scale, sigma=sigma, min_size=min_size,
                                 channel_axis=None)


def vote_frame(lab: np.ndarray, heights: np.ndarray, n: int, scale: int) -> np.ndarray:
    """(H, W) labels (0 = background, 1..n) and heights -> labels constant on each superpixel
    of the foreground (its most frequent label; ties to the lower label). Background stays
    background."""
    fg = lab > 0
    if scale <= 0 or not fg.any():
        return lab
    seg = depth_superpixels(np.asarray(heights, np.float64), fg, scale=scale)
    ids = seg[fg]
    counts = np.bincount(ids * (n + 1) + lab[fg], minlength=(seg.max() + 1) * (n + 1))
    counts = counts.reshape(-1, n + 1)  # foreground pixels only: column 0 stays empty
    out = lab.copy()
    out[fg] = counts.argmax(1)[ids]
    return out


def vote_labels(labels: torch.Tensor, x: torch.Tensor, n: int, scale: int) -> torch.Tensor:
    """(B, H, W) labels of the (B, 1, H, W) model input -> `vote_frame` of each frame."""
    if scale <= 0:
        return labels
    lab, heights = labels.cpu().numpy(), x[:, 0].float().cpu().numpy()
    out = np.stack([vote_frame(lab[b], heights[b], n, scale) for b in range(len(lab))])
    return torch.from_numpy(out).to(labels.device)
