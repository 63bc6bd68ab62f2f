"""A simple structured-light / stereo depth-sensor noise model.

Applied to a clean metric depth image (metres); missing pixels come out as 0, as RealSense-class
cameras report them.
  * Gaussian noise whose standard deviation grows with the square of the distance,
  * missing pixels along depth discontinuities (object edges) and at random,
  * the occlusion holes of a stereo camera: on the far side of a depth discontinuity, the
    surface that the second imager cannot see behind a nearer one (RealSense D400: depth is
    given in the left imager's view, so the holes lie left of nearer surfaces) is missing, a
    band of baseline * fx * (1 / z_near - 1 / z_far) pixels (the disparity difference: 8 px
    beside a 3 cm object at 0.3 m with a 50 mm baseline and fx = 426),
  * quantisation to the sensor's depth unit (1 mm for 16UC1 cameras).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class NoiseConfig:
    sigma_base: float = 0.0  # metres
    sigma_per_m2: float = 0.0  # metres of sigma per metre^2 of depth
    edge_dropout: float = 0.0  # probability that a pixel on a depth edge is lost
    edge_threshold: float = 0.004  # metres of depth jump that makes an edge
    random_dropout: float = 0.0  # probability that any pixel is lost
    quantum: float = 0.0  # metres; 0 = no quantisation
    stereo_baseline: float = 0.0  # metres between the imagers; 0 = no occlusion holes

    def __post_init__(self):
        for name, value in asdict(self).items():
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"noise {name} must be finite and >= 0, got {value}")
        for name in ("edge_dropout", "random_dropout"):
            if getattr(self, name) > 1:
                raise ValueError(f"noise {name} is a probability in [0, 1], got "
                                 f"{getattr(self, name)}")

    @property
    def enabled(self) -> bool:
        return any(v > 0 for k, v in asdict(self).items() if k != "edge_threshold")

    def to_dict(self) -> dict:
        return asdict(self)


NOISE_PRESETS: dict[str, NoiseConfig] = {
    "none": NoiseConfig(),
    # Roughly an Intel RealSense D435 at 0.3-0.6 m: ~1 mm RMS at 0.5 m, holes at edges and
    # the occlusion holes of its 50 mm stereo baseline.
    "realsense": NoiseConfig(sigma_base=0.0004, sigma_per_m2=0.0025, edge_dropout=0.5,
                             random_dropout=0.003, quantum=0.001, stereo_baseline=0.05),
}


def get_noise(preset: str) -> NoiseConfig:
    try:
        return NOISE_PRESETS[preset]
    except KeyError:
        raise ValueError(f"unknown noise preset {preset!r}; valid: "
                         f"{', '.join(NOISE_PRESETS)}") from None


def occlusion_holes(depth: np.ndarray, baseline_px: float) -> np.ndarray:
    """Pixels of `depth` (metres, > 0) that a second imager `baseline_px` = baseline * fx
    (metres x pixels) to the right cannot see: (H, W) bool.

    A pixel at column u appears in the second image at u - baseline_px / z; it is hidden when
    a pixel to its right lands at or left of it there while being nearer (one running minimum
    per row, from the right)."""
    h, w = depth.shape
    z = np.where(depth > 0, depth, np.inf).astype(np.float64)
    seen_at = np.arange(w) - baseline_px / z  # column in the second image
    # the leftmost position reached in the second image by any pixel to the right of u
    right_min = np.minimum.accumulate(seen_at[:, ::-1], axis=1)[:, ::-1]
    hidden = np.zeros((h, w), bool)
    hidden[:, :-1] = right_min[:, 1:] < seen_at[:, :-1] - 0.5  # half a pixel: one step
    return hidden


def apply_noise(depth: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator,
                fx: float | None = None) -> np.ndarray:
    """Return a noisy copy of `depth` (metres, float32); lost pixels are 0. `fx` (pixels, the
    camera's focal length) is needed for the occlusion holes (`stereo_baseline` > 0)."""
    out = depth.astype(np.float32, copy=True)
    if not cfg.enabled:
        return out
    if cfg.stereo_baseline > 0 and not (fx is not None and np.isfinite(fx) and fx > 0):
        raise ValueError(f"noise stereo_baseline {cfg.stereo_baseline} m needs the camera's "
                         f"focal length fx (pixels > 0), got {fx!r}")
    sigma = cfg.sigma_base + cfg.sigma_per_m2 * out * out
    if np.any(sigma > 0):
        out += (rng.standard_normal(out.shape) * sigma).astype(np.float32)
    lost = np.zeros(out.shape, bool)
    if cfg.edge_dropout > 0:
        jump = np.maximum(ndimage.maximum_filter(depth, 3) - depth,
                          depth - ndimage.minimum_filter(depth, 3))
        edges = ndimage.binary_dilation(jump > cfg.edge_threshold)
        lost |= edges & (rng.random(out.shape) < cfg.edge_dropout)
    if cfg.random_dropout > 0:
        lost |= rng.random(out.shape) < cfg.random_dropout
    if cfg.stereo_baseline > 0:
        lost |= occlusion_holes(depth, cfg.stereo_baseline * fx)
    if cfg.quantum > 0:
        out = (np.round(out / cfg.quantum) * cfg.quantum).astype(np.float32)
    out[lost] = 0.0
    return out
