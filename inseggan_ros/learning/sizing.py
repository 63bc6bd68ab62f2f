"""A learned rod's size, set from the user's unlabelled frames: no label, no size given by hand.

A rod learned as a GAN from a recording can come out much larger than the part, and a
template of the wrong size teaches the loop's encoder on piles of the wrong part. Two
label-free rules (`inseggan loop`, on by default for a rod the loop learns itself:
`loop.size_plan`; what they measured: docs/experiments.md, 2026-11-27):

* `frame_thickness` / `size_to_thickness`: parts lying on the floor show their thickness as the
  height of their tops. The lowest well-populated mode of the heights of the frames' local
  maxima becomes the height of the rod's thickest part resting on the floor; the rod keeps its
  learned length-to-width ratio. This assumes a part lying on its side, whose thickness is its
  width; a part that lies flat (a nut) breaks it, so by default it sizes only a rod that came
  out elongated (`elongated`).
* `choose_scale`: the template scaled at test time (`scaled`), tau calibrated anew on some of
  the user's frames, and the scale whose renders explain other frames best (least
  reconstruction L1) kept. The loop then simulates and fits again at that scale, until the
  scale it chooses is 1.

Both apply to rod (sphere) templates only; another template is refused with a named error.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import torch
from scipy import ndimage

from inseggan_ros.runtime.model import SphereGenerator

# the scales `choose_scale` tries, and how much lower (relative) a scale's error must be than
# the template's own size for it to be taken: within that, the size is left as it is
SCALES = (0.8, 0.9, 1.0, 1.1, 1.2, 1.3)
MIN_GAIN = 0.01
PEAK_WINDOW = 7  # pixels: a local maximum is the highest point of its 7 x 7 window
# a rod at least this many times as long as it is wide is taken for a part that lies on its
# side, whose thickness is its width (what `size_to_thickness` assumes); a shorter one (a hex
# nut's learned rod is about as long as wide) is not resized to the thickness by default
ELONGATED = 1.2
# a rod thinned with its length kept (`size_to_thickness(keep_length=True)`) gets spheres at
# most this many of its smallest radii apart: their tops dip by at most 6 % between two
# spheres (at 0.95, the most that keeps them overlapping, by 12 %)
KEEP_LENGTH_SPACING = 0.7


def _rod(G) -> SphereGenerator:
    if not isinstance(G, SphereGenerator):
        raise ValueError(f"renderer {G.cfg.renderer!r}: only a rod of spheres (renderer "
                         "'spheres') can be sized this way")
    return G


def frame_thickness(x: np.ndarray, fg: np.ndarray, max_height: float) -> float:
    """Frames x (N, 1, H, W) in the model's input units ([-1, 1] over 0..max_height metres
    above the floor) with foreground fg (N, H, W) -> the parts' thickness in metres: the lowest
    mode (1 mm bins, at least a fifth of the largest) of the heights of the local maxima, the
    median of the peaks within 2 mm of it. Heights at max_height (clipped) are left out."""
    peaks = []
    for xi, fi in zip(np.asarray(x), np.asarray(fg, bool)):
        h = (xi[0].astype(np.float64) + 1) / 2 * max_height
        top = (h == ndimage.maximum_filter(h, size=PEAK_WINDOW)) & fi & (h < max_height - 1e-3)
        peaks.append(h[top])
    mm = np.concatenate(peaks) * 1000 if peaks else np.zeros(0)
    mm = mm[mm > 0.5]
    if mm.size < 10:
        raise ValueError(f"{mm.size} height peaks in {len(x)} frames: too few to measure the "
                         "parts' thickness; valid: frames with parts in the bin")
    counts = np.bincount(np.rint(mm).astype(int))
    first = int(np.flatnonzero(counts >= 0.2 * counts.max())[0])
    while first + 1 < len(counts) and counts[first + 1] > counts[first]:
        first += 1  # climb to the top of that mode
    return float(np.median(mm[np.abs(mm - first) <= 2])) / 1000


def size_to_thickness(state: dict, G, metres_per_height_unit: float, thickness: float,
                      keep_length: bool = False) -> float:
    """Resize the rod of checkpoint `state` (in place; `G` is its generator) so that its thickest
    sphere, resting on the floor, is `thickness` metres high: every sphere and the centres'
    span scaled alike, the axis lifted to that sphere's radius. With `keep_length` only the
    radii are scaled and the centres keep their span (a thick rod learned for a long, thin part:
    a bolt), on more spheres where they would be more than KEEP_LENGTH_SPACING of the smallest
    radius apart (`reshaped`). -> the scale applied to the radii."""
    _rod(G)
    with torch.no_grad():
        centres, radii = G.spheres()
        r_max, r_min = float(radii.max()), float(radii.min())
        span = float(centres[:, 0].max() - centres[:, 0].min())
    r_new = thickness / 2 / metres_per_height_unit
    s = r_new / r_max
    if keep_length:
        spheres = max(G.cfg.spheres, math.ceil(span / (KEEP_LENGTH_SPACING * r_min * s)) + 1)
        if spheres > 256:
            raise ValueError(f"a rod {span / (r_min * s):.0f} times as long as its thinnest "
                             "sphere's radius needs more than 256 spheres; valid: keep_length "
                             "off for so thin a part")
        H, _ = reshaped(G, 1.0, s, spheres)
        state["generator"] = {k: v.detach().clone() for k, v in H.state_dict().items()}
        state["model_config"] = {**state["model_config"], "spheres": spheres}
    else:
        scale_state(state, s)
    g = state["generator"]
    g["lift"] = torch.as_tensor(r_new, dtype=g["lift"].dtype)  # resting on the floor
    return s


def elongated(dimensions) -> bool:
    """Whether a rod of `dimensions` (length, width, height: `rod_dimensions_mm`) is at least
    ELONGATED times as long as it is wide."""
    return dimensions[0] >= ELONGATED * dimensions[1]


def rod_dimensions_mm(G, metres_per_unit) -> list[float]:
    """The rod's extent along its axis, across it and its height (its thickest sphere), in
    millimetres, with `metres_per_unit` (3,) of its template (`sim.learned.template_scale`)."""
    with torch.no_grad():
        centres, radii = (t.double().cpu().numpy() for t in _rod(G).spheres())
    m = np.asarray(metres_per_unit, np.float64) * 1000
    length = float((centres[:, 0] + radii).max() - (centres[:, 0] - radii).min())
    return [length * m[0], 2 * float(radii.max()) * m[1], 2 * float(radii.max()) * m[2]]


def scaled(G, s: float):
    """A copy of the rod generator `G` whose template is `s` times as large (spheres, span and
    lift; the poses the encoder reads are unchanged)."""
    G = copy.deepcopy(_rod(G))
    with torch.no_grad():
        G.log_radius += math.log(s)
        G.length *= s
        G.lift *= s
    return G


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(1e-4, 1 - 1e-4)
    return torch.log(p) - torch.log1p(-p)


def reshaped(G, length: float = 1.0, radius: float = 1.0, spheres: int | None = None):
    """A copy of the rod generator `G` whose centres span `length` times as much and whose
    spheres are `radius` times as large (the axis lifted alike), resampled to `spheres` spheres
    (default: as many as it has) along the same profile: the radii interpolated linearly between
    the old centres. A rod's centres can span at most 0.95 (K - 1) times its smallest radius
    (`SphereGenerator.spheres`), so a rod made longer and thinner needs more spheres; the span
    the copy gets is returned with it. -> (copy, span in template units)."""
    from dataclasses import replace

    G = _rod(G)
    K = int(spheres or G.cfg.spheres)
    if K < 2 and length != 1.0:
        raise ValueError(f"spheres {K} invalid for a change of length; valid: >= 2")
    if length <= 0 or radius <= 0:
        raise ValueError(f"length {length}, radius {radius} invalid; valid: > 0")
    with torch.no_grad():
        centres, radii = (t.double() for t in G.spheres())
        t_old = np.linspace(-0.5, 0.5, len(radii)) if len(radii) > 1 else np.zeros(1)
        t_new = np.linspace(-0.5, 0.5, K) if K > 1 else np.zeros(1)
        r = torch.from_numpy(np.interp(t_new, t_old, radii.numpy())) * radius
        span = float(centres[:, 0].max() - centres[:, 0].min()) * length
        new = SphereGenerator(replace(G.cfg, spheres=K)).to(G.log_radius.device)
        state = {k: v for k, v in G.state_dict().items() if k != "radius_shape"}
        if G.cfg.radius_profile == "monotone":  # r_j = r_0 prod(0.75 + 0.25 sigmoid(shape_j))
            steps = (r[1:] / r[:-1]).clamp(0.75, 1.0)
            shape = torch.cat([torch.full((1,), 4.0, dtype=r.dtype), _logit((steps - 0.75) / 0.25)])
            log_r = math.log(float(r[0]))
        else:  # r_j = r_max (0.5 + 0.5 sigmoid(shape_j))
            shape = _logit(2 * r / r.max() - 1)
            log_r = math.log(float(r.max()))
        dtype = G.log_radius.dtype
        state.update(radius_shape=shape.to(dtype), log_radius=torch.tensor(log_r, dtype=dtype),
                     length=torch.tensor(span, dtype=dtype), lift=G.lift.detach() * radius)
        new.load_state_dict(state)
        got = new.spheres()[0][:, 0]
    return new, float(got.max() - got.min())


def scale_state(state: dict, s: float) -> None:
    """The rod of checkpoint `state` made `s` times as large, in place (as `scaled`)."""
    g = state["generator"]
    g["log_radius"] = g["log_radius"] + math.log(s)
    g["length"] = g["length"] * s
    g["lift"] = g["lift"] * s


def choose_scale(seg, calib: dict, held: dict, scales=SCALES) -> tuple[float, list[dict]]:
    """The template scale of `seg` (a segment.Segmenter with a rod, at the settings it will ship
    with) whose renders explain the `held` frames best, tau calibrated on the `calib` frames
    for each (`selfcheck.calibrate`, `selfcheck.measure`; no label read) -> (scale, a row per
    scale). A scale is taken only if its error is MIN_GAIN (relative) below that of the size
    as it is (1.0, which is always tried)."""
    from inseggan_ros.evaluation.selfcheck import calibrate, measure

    G0, tau0 = _rod(seg.G), seg.tau
    scales = sorted(set(float(s) for s in scales) | {1.0})
    if min(scales) <= 0:
        raise ValueError(f"scales {scales} invalid; valid: > 0")
    rows = []
    try:
        for s in scales:
            seg.G = scaled(G0, s)
            seg.tau = calibrate(seg, calib["x"], calib["fg"])[0]
            m = measure(seg, held["x"], held["fg"])
            rows.append({"scale": s, "tau": seg.tau, "recon_l1": m["recon_l1"],
                         "coverage": m["coverage"], "spill": m["spill"],
                         "count_equals_n": m["count_equals_n"]})
    finally:
        seg.G, seg.tau = G0, tau0
    own = next(r["recon_l1"] for r in rows if r["scale"] == 1.0)
    best = min(rows, key=lambda r: r["recon_l1"])
    return (best["scale"] if best["recon_l1"] < own * (1 - MIN_GAIN) else 1.0), rows
