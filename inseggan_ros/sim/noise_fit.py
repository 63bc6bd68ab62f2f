"""The sensor noise of a user's recording, measured on its own frames: the simulator's piles are
then seen through the noise the user's camera has, with no preset named.

Measured on the bin floor, which every frame shows and whose true shape is a plane
(`user_camera.estimate_camera` fits it):
  * `quantum`: the depth unit, the smallest step between readings (1 mm for 16UC1 cameras);
  * the Gaussian part: the robust spread (1.4826 x median absolute deviation) of the floor
    readings about the plane, less the quantisation's own (q^2 / 12), as `sigma_per_m2` at the
    floor's depth (stereo depth noise grows with the square of the distance);
  * `random_dropout`: the share of floor pixels with no reading, away from any part;
  * `edge_dropout`: how often the runs of holes right of the parts (pixels standing out of
    the floor) are empty, on the side where no stereo occlusion reaches;
  * `stereo_baseline`: the holes a second imager leaves beside nearer surfaces lie on one side
    of each part (the left for a RealSense D400). Where the holes beside the parts' left edges
    outnumber those beside their right edges, the baseline is what the holes' widths give:
    width = baseline * fx * (1 / z_part - 1 / z_floor).
A recording without noise (a simulated one) measures as no noise.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from inseggan_ros.sim.noise import NoiseConfig

PART_RISE = 0.004  # metres above the floor: a part's pixel, not floor noise
ONE_SIDED = 2.0  # left holes this many times the right ones: a stereo camera's occlusion


def _plane_depth(plane, shape) -> np.ndarray:
    a, b, c = plane
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    with np.errstate(divide="ignore"):
        return 1.0 / (a * u + b * v + c)


def _quantum(stack: np.ndarray) -> float:
    """The depth unit: the smallest common step between readings (0 when they are continuous)."""
    vals = np.unique(stack[stack > 0][:200000].astype(np.float64))
    if len(vals) < 3:
        return 0.0
    step = np.diff(vals)
    q = float(np.median(step[step > 1e-7])) if np.any(step > 1e-7) else 0.0
    if q < 1e-5:
        return 0.0
    on_grid = np.abs(vals / q - np.round(vals / q)) < 0.05
    return round(q, 6) if on_grid.mean() > 0.95 else 0.0


def _hole_runs(depth: np.ndarray, part: np.ndarray, floor_z: np.ndarray, floor_mask,
               reach: int = 64):
    """The runs of holes beside each row's part segments, between a floor reading and a part:
    left of a segment, (where the run starts, the floor's inverse depth there, the columns and
    inverse depths of the part's pixels up to `reach` to its right); right of one, its width.
    A floor reading is one on the plane inside the bin (not a wall, whose own holes differ)."""
    holes = depth <= 0
    floor = (depth > 0) & (np.abs(floor_z - depth) < PART_RISE) & floor_mask
    left, right = [], []
    w = depth.shape[1]
    for r in np.nonzero(part.any(1))[0]:
        row, hole = part[r], holes[r]
        for s in np.nonzero(row[1:] & ~row[:-1])[0] + 1:
            k = s
            while k > 0 and hole[k - 1]:
                k -= 1
            if 0 < k and s - k < reach and floor[r, k - 1]:
                j = np.arange(s, min(s + reach, w))
                j = j[part[r, j]]
                left.append((k, 1.0 / floor_z[r, k - 1], j, 1.0 / depth[r, j]))
        for e in np.nonzero(row[:-1] & ~row[1:])[0]:
            k = e
            while k < w - 1 and hole[k + 1]:
                k += 1
            if k < w - 1 and k - e < reach and floor[r, k + 1]:
                right.append(k - e)
    return left, right


def _run_baseline(k: float, inv_floor: float, j: np.ndarray, inv_z: np.ndarray) -> float:
    """The baseline x fx (pixel metres) at which the part's pixels (columns `j`, inverse depths
    `inv_z`) hide the floor from column `k` on: min over j of j - B (1 / z_j - 1 / z_floor) = k,
    solved by bisection (the left side falls as B grows)."""
    gap = inv_z - inv_floor
    if not np.any(gap > 1e-3) or j.min() <= k:
        return float("nan")
    lo, hi = 0.0, float((j.max() - k) / gap[gap > 1e-3].min()) + 1.0
    for _ in range(40):
        mid = (lo + hi) / 2
        if np.min(j - mid * gap) > k:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


def _baseline(stack, floor_z, fx, part_masks, floor_mask) -> tuple[float, float, float]:
    """(baseline metres, mean hole width left over right of the parts, edge dropout).

    Right of a part, where no occlusion reaches, a reading follows the part's last one when
    neither of the two pixels of the edge's band there is lost: the share of runs of no holes
    is (1 - p)^2 for an edge dropout p."""
    left, right = [], []
    for depth, part in zip(stack, part_masks):
        a, b = _hole_runs(depth, part, floor_z, floor_mask)
        left += a
        right += b
    if len(left) < 20 or not right:
        return 0.0, 0.0, 0.0
    dropout = 1.0 - float(np.sqrt(np.mean(np.asarray(right) == 0)))
    edge = float(np.mean(right))  # what holes the edges alone leave on either side
    widths = np.array([j[0] - k for k, _, j, _ in left], np.float64)
    ratio = float(widths.mean() / max(edge, 0.5))
    if ratio < ONE_SIDED:
        return 0.0, ratio, dropout
    b = np.array([_run_baseline(k + edge, f, j, z) for k, f, j, z in left])
    b = b[np.isfinite(b)]
    return (float(np.median(b)) / fx if len(b) >= 20 else 0.0), ratio, dropout


def estimate_noise(depths, plane, floor_mask: np.ndarray, fx: float) -> tuple[NoiseConfig, dict]:
    """The `NoiseConfig` that makes simulated frames look like `depths` (metres, 0 = no
    reading; frames of one camera) -> (config, what was measured). `plane`: the floor, 1 / z =
    a u + b v + c (`user_camera.estimate_camera`'s "plane"); `floor_mask`: the bin floor's
    pixels (inside its outline, clear of the walls); `fx`: the focal length in pixels."""
    stack = np.asarray(depths, np.float32)
    if stack.ndim != 3 or stack.shape[1:] != floor_mask.shape:
        raise ValueError(f"depths of shape {stack.shape} and a floor mask of shape "
                         f"{floor_mask.shape}; valid: (frames, H, W) and (H, W)")
    floor_z = _plane_depth(plane, floor_mask.shape)
    q = _quantum(stack)
    rise = np.where(stack > 0, floor_z - stack, 0.0)
    part = (rise > PART_RISE) & floor_mask
    near_part = np.stack([ndimage.binary_dilation(p, iterations=3) for p in part])
    open_floor = floor_mask & ~near_part
    reading = stack > 0
    resid = (stack - floor_z)[open_floor & reading]
    resid = resid[np.abs(resid) < 0.02]
    mad = 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) if len(resid) else 0.0
    sigma = float(np.sqrt(max(mad ** 2 - q ** 2 / 12, 0.0)))
    if sigma < 1e-4:  # below a tenth of a millimetre: the floor's own fit, no sensor noise
        sigma = 0.0
    z_floor = float(np.median(floor_z[floor_mask]))
    # isolated holes: a random dropout of p leaves most holes without a hole beside them, where
    # edges, walls and occlusions leave runs
    holes = ~reading & open_floor
    lone = holes & (ndimage.uniform_filter(holes.astype(np.float32), (1, 3, 3)) * 9 < 1.5)
    random = float(lone.sum() / max(open_floor.sum(), 1))
    baseline, ratio, edge = _baseline(stack, floor_z, fx, part, floor_mask)
    cfg = NoiseConfig(sigma_base=0.0, sigma_per_m2=sigma / z_floor ** 2,
                      edge_dropout=min(edge, 1.0) if edge > 0.02 else 0.0,
                      random_dropout=random if random > 1e-4 else 0.0, quantum=q,
                      stereo_baseline=baseline)
    return cfg, {"floor_sigma_m": sigma, "floor_depth_m": z_floor, "quantum_m": q,
                 "random_dropout": random, "edge_dropout": edge, "left_right_holes": ratio,
                 "stereo_baseline_m": baseline, "floor_pixels": int(len(resid))}
