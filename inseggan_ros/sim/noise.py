"""A simple structured-light / stereo depth-sensor noise model.

Applied to a clean metric depth image (metres); missing pixels come out as 0, as RealSense-class
cameras report them.
  * Gaussian noise whose standard deviation grows with the square of the distance,
  * missing pixels along depth discontinuities (object edges) and at random,
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

    def __post_init__(self):
        for name, value in asdict(self).items():
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"noise {name} must be finite and >= 0, got {value}")
        for name in ("edge_dropout", "random_dropout"):
            if getattr(self, name) > 1:
                raise ValueError(f"noise {name} is a probability in [0, 1], got {getattr(self, name)}")

    @property
    def enabled(self) -> bool:
        return any(v > 0 for k, v in asdict(self).items() if k != "edge_threshold")

    def to_dict(self) -> dict:
        return asdict(self)


NOISE_PRESETS: dict[str, NoiseConfig] = {
    "none": NoiseConfig(),
    # Roughly an Intel RealSense D435 at 0.3-0.6 m: ~1 mm RMS at 0.5 m, holes at edges.
    "realsense": NoiseConfig(sigma_base=0.0004, sigma_per_m2=0.0025, edge_dropout=0.5,
                             random_dropout=0.003, quantum=0.001),
}


def get_noise(preset: str) -> NoiseConfig:
    try:
        return NOISE_PRESETS[preset]
    except KeyError:
        raise ValueError(f"unknown noise preset {preset!r}; valid: {', '.join(NOISE_PRESETS)}") from None


def apply_noise(depth: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Return a noisy copy of `depth` (metres, float32); lost pixels are 0."""
    out = depth.astype(np.float32, copy=True)
    if not cfg.enabled:
        return out
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
    if cfg.quantum > 0:
        out = (np.round(out / cfg.quantum) * cfg.quantum).astype(np.float32)
    out[lost] = 0.0
    return out
