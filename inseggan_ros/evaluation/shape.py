r"""How close a learned template is to the true part: volumetric IoU after the best
alignment, dimensions (bounding box along principal axes), and a three-view drawing for model
cards.

Both bodies are unions of convex pieces given as half-spaces {x : n . x <= d}: the template from
`ConvexGenerator.halfspaces()`, or a rod of spheres (`SphereGenerator.spheres()`) each as the
polytope of its tangent planes in `SPHERE_FACES` directions (which holds it, and is 1.6 % larger
in volume: the rod's IoU is exact to that), in image half-widths, scaled to metres by
`metres_per_unit`; the true part from the convex hulls of its collision pieces (`sim.objects`,
metres). Occupancy is tested exactly at voxel centres. Alignment: both bodies' principal axes,
then every signed permutation of them (24 rotations, 48 with mirror images: training flips the
frames, so a template may learn the part's mirror image; mirrored fits are reported as such),
and turns in 10 degree steps about an axis whose other two are undetermined (a nut, a cylinder),
centroids matched, then a Nelder-Mead refinement of a small rotation and translation. The scale
is not searched: it is the data's (the bin crop's width in metres over 2 per template unit), so
the dimensions compare true sizes.

    python -m inseggan_ros.evaluation.shape --checkpoint runs/block/best.pt --object wooden_block \\
        --data data/wooden_block --drawing three_view.png
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from inseggan_ros.runtime.pieces import (  # noqa: F401  (shared with sim.learned)
    SPHERE_FACES, Pieces, metres_per_unit, template_pieces, vertices)


def part_pieces(name: str) -> Pieces:
    """The true part `name` (`sim.objects`) as the convex hulls of its collision pieces, metres."""
    from scipy.spatial import ConvexHull

    from inseggan_ros.sim.objects import get_object

    out = []
    for corners in get_object(name).parts:
        eq = ConvexHull(corners).equations  # n . x + b <= 0 inside
        out.append((eq[:, :3], -eq[:, 3]))
    return out


def part_voxel(name: str, voxels: int = 30) -> float:
    """The voxel (metres) that puts `voxels` of them along part `name`'s largest extent: the
    resolution the cards measure fidelity at."""
    return float(np.ptp(vertices(part_pieces(name)), axis=0).max()) / voxels


def scaled(pieces: Pieces, scale) -> Pieces:
    """Pieces stretched by `scale` (3,) along x, y, z (template units -> metres)."""
    s = np.asarray(scale, float)
    out = []
    for n, d in pieces:
        m = n / s
        norm = np.linalg.norm(m, axis=1)
        out.append((m / norm[:, None], d / norm))
    return out


def transformed(pieces: Pieces, R: np.ndarray, t: np.ndarray) -> Pieces:
    """Pieces moved by x -> R x + t (R may be a reflection)."""
    return [(n @ R.T, d + (n @ R.T) @ t) for n, d in pieces]


def occupancy(pieces: Pieces, points: np.ndarray) -> np.ndarray:
    """(N, 3) points -> (N,) bool: inside any piece."""
    inside = np.zeros(len(points), bool)
    for n, d in pieces:
        inside |= (points @ n.T <= d).all(1)
    return inside


def components(pieces: Pieces) -> int:
    """How many separate bodies the union makes: connected components of the graph whose
    edges join pieces that overlap (their intersection holds a ball; an LP per pair). For
    convex pieces this is exact, no voxels involved."""
    from scipy.optimize import linprog
    from scipy.sparse.csgraph import connected_components

    K = len(pieces)
    adjacent = np.eye(K, dtype=bool)
    for i in range(K):
        for j in range(i + 1, K):
            n = np.vstack([pieces[i][0], pieces[j][0]])
            d = np.concatenate([pieces[i][1], pieces[j][1]])
            lp = linprog(np.r_[0, 0, 0, -1], A_ub=np.c_[n, np.linalg.norm(n, axis=1)], b_ub=d,
                         bounds=[(None, None)] * 3 + [(0, 1e3)])
            adjacent[i, j] = adjacent[j, i] = lp.success and lp.x[3] > 1e-9
    return int(connected_components(adjacent, directed=False)[0])


def voxel_points(pieces: Pieces, voxel: float) -> np.ndarray:
    """Centres of the voxels (side `voxel`) whose centre is inside the body, (N, 3)."""
    v = vertices(pieces)
    lo, hi = v.min(0), v.max(0)
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return grid[occupancy(pieces, grid)]


def principal_axes(points: np.ndarray, with_spreads: bool = False):
    """-> centroid (3,), axes (3, 3) as columns, largest spread first (and the spreads)."""
    c = points.mean(0)
    w, U = np.linalg.eigh(np.cov((points - c).T))
    return (c, U[:, ::-1], w[::-1]) if with_spreads else (c, U[:, ::-1])


def _spin_axes(spreads: np.ndarray, ratio: float = 0.85) -> list[int]:
    """Principal axes about which a body is about as wide one way as the other (two spreads
    within `ratio`): its other two principal axes are arbitrary, so the alignment also
    tries turns about this one."""
    return [3 - i - j for i, j in ((0, 1), (1, 2), (0, 2)) if spreads[j] > ratio * spreads[i]]


def dimensions(pieces: Pieces, points: np.ndarray) -> np.ndarray:
    """Length, width, height of the body, largest first: the sides of its bounding box along
    the principal axes of its voxels `points` (turned about an axis whose other two are
    undetermined, a square footprint's, to the smallest box), exact from its corners."""
    _, U, w = principal_axes(points, with_spreads=True)
    corners = vertices(pieces)
    frames = [U] + [_rotvec(U[:, k] * a) @ U for k in _spin_axes(w)
                    for a in np.radians(np.arange(5, 90, 5))]
    sides = min((np.ptp(corners @ F, axis=0) for F in frames), key=np.prod)
    return np.sort(sides)[::-1]


def signed_permutations(mirror: bool = True) -> list[np.ndarray]:
    """The 48 signed permutation matrices, the 24 rotations first (only those when not
    `mirror`)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            M[range(3), perm] = signs
            if mirror or np.linalg.det(M) > 0:
                out.append(M)
    return sorted(out, key=lambda M: -np.linalg.det(M))  # rotations first: they win ties


# ------------------------------------------------------------------------------ fidelity
@dataclass
class Fit:
    """The best alignment of a template onto the true part, and what it scores."""

    iou: float  # volumetric IoU after the best alignment
    iou_before_refinement: float
    mirrored: bool  # the best alignment is a reflection (the template is the mirror image)
    R: np.ndarray  # template -> true frame: x_true = R x + t (metres)
    t: np.ndarray
    dims_template_mm: np.ndarray  # length, width, height (`dimensions`), largest first
    dims_true_mm: np.ndarray
    voxel_mm: float

    @property
    def dims_error(self) -> float:
        """Mean relative error of the three dimensions."""
        return float(np.mean(np.abs(self.dims_template_mm / self.dims_true_mm - 1)))

    def to_dict(self) -> dict:
        """The numbers, rounded, for JSON (the alignment itself left out)."""
        return {"iou": round(self.iou, 4),
                "iou_before_refinement": round(self.iou_before_refinement, 4),
                "mirrored": self.mirrored,
                "dims_template_mm": np.round(self.dims_template_mm, 2).tolist(),
                "dims_true_mm": np.round(self.dims_true_mm, 2).tolist(),
                "dims_rel_error": round(self.dims_error, 4), "voxel_mm": round(self.voxel_mm, 3)}


def _rotvec(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def fit(template: Pieces, truth: Pieces, voxel: float | None = None, mirror: bool = True,
        refine_evals: int = 120) -> Fit:
    """Best alignment of `template` onto `truth` (both in metres) by volumetric IoU.

    The overlap is measured both ways on voxel centres (the template's voxels inside the
    posed truth, the truth's inside the posed template; their mean, times a voxel's volume):
    no common grid is needed and the cost scales with the bodies' own volumes. `voxel`:
    default the true part's largest extent / 50."""
    if voxel is None:
        voxel = float(np.ptp(vertices(truth), axis=0).max()) / 50
    pts_t = voxel_points(truth, voxel)
    pts_a = voxel_points(template, voxel)
    if len(pts_a) < 4:
        raise ValueError("the template holds fewer than 4 voxels: too small to align")
    c_t, U_t, w_t = principal_axes(pts_t, with_spreads=True)
    c_a, U_a, w_a = principal_axes(pts_a, with_spreads=True)
    spins = [np.eye(3)]  # turns about a truth axis that principal axes leave undetermined
    for k in sorted(set(_spin_axes(w_t)) | set(_spin_axes(w_a))):
        spins += [_rotvec(U_t[:, k] * a) for a in np.radians(np.arange(10, 360, 10))]

    def iou(R, t):
        a_in_t = occupancy(truth, pts_a @ R.T + t).sum()
        t_in_a = occupancy(template, (pts_t - t) @ np.linalg.inv(R).T).sum()
        inter = (a_in_t + t_in_a) / 2
        return float(inter / (len(pts_a) + len(pts_t) - inter))

    best = (-1.0, None, None)
    for spin in spins:
        for D in signed_permutations(mirror):
            R = spin @ U_t @ D @ U_a.T
            t = c_t - R @ c_a
            s = iou(R, t)
            if s > best[0]:
                best = (s, R, t)
    s0, R0, t0 = best
    if refine_evals > 0:
        from scipy.optimize import minimize

        def pose(p):  # a small turn about the true centroid, and a shift (in voxels)
            Rd = _rotvec(p[:3])
            return Rd @ R0, Rd @ (t0 - c_t) + c_t + p[3:] * voxel

        simplex = np.vstack([np.zeros(6), np.diag([0.08] * 3 + [1.5] * 3)])
        res = minimize(lambda p: -iou(*pose(p)), np.zeros(6), method="Nelder-Mead",
                       options={"maxfev": refine_evals, "initial_simplex": simplex})
        if -res.fun > s0:
            best = (-res.fun, *pose(res.x))
    s, R, t = best
    return Fit(iou=s, iou_before_refinement=s0, mirrored=bool(np.linalg.det(R) < 0), R=R, t=t,
               dims_template_mm=dimensions(template, pts_a) * 1e3,
               dims_true_mm=dimensions(truth, pts_t) * 1e3, voxel_mm=voxel * 1e3)


# ------------------------------------------------------------------------------ drawing
def views(pieces: Pieces, lo: np.ndarray, hi: np.ndarray, voxel: float) -> list[np.ndarray]:
    """Height maps of a body seen along -z (top), +y (front) and -x (side); NaN where empty."""
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    occ = occupancy(pieces, np.stack([X, Y, Z], -1).reshape(-1, 3)).reshape(X.shape)

    def project(coord, axis, far):  # the nearest surface along `axis`
        v = np.where(occ, coord, -np.inf if far > 0 else np.inf)
        m = v.max(axis) if far > 0 else v.min(axis)
        return np.where(np.isfinite(m), m, np.nan)

    top = project(Z, 2, 1).T  # rows y, columns x
    front = project(Y, 1, -1).T  # rows z, columns x: seen from -y
    side = project(X, 0, 1).T  # rows z, columns y: seen from +x
    return [top, front, side]


def three_view(template: Pieces, truth: Pieces, path, title: str = "",
               voxel: float | None = None) -> Path:
    """PNG: the aligned template (top row) and the true part (bottom row) seen from the top,
    the front and the side, shaded by distance to the viewer; axes in millimetres. Both bodies
    in the true part's own frame (`transformed(template, fit.R, fit.t)`). Written atomically."""
    return views_figure([("learned template", template), ("true part", truth)], path, title,
                        voxel)


def views_figure(bodies: list[tuple[str, Pieces]], path, title: str = "",
                 voxel: float | None = None, unit: float = 1e3, unit_name: str = "mm",
                 dpi: int = 90, voxels: int = 120) -> Path:
    """PNG: each (name, body) a row, seen from the top, the front and the side (`views`), all
    in one box and one shading per view, so that sizes compare; axes in `unit_name`
    (coordinates times `unit`); `voxel` by default 1/`voxels` of the box's largest side.
    Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = np.vstack([vertices(body) for _, body in bodies])
    lo, hi = v.min(0), v.max(0)
    pad = 0.05 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    if voxel is None:
        voxel = float((hi - lo).max()) / voxels
    rows = [(name, views(body, lo, hi, voxel)) for name, body in bodies]
    extents = [(lo[0], hi[0], lo[1], hi[1]), (lo[0], hi[0], lo[2], hi[2]),
               (lo[1], hi[1], lo[2], hi[2])]
    labels = [("x", "y"), ("x", "z"), ("y", "z")]
    fig, ax = plt.subplots(len(rows), 3, figsize=(9, 3 * len(rows)), squeeze=False)
    ranges = [(np.nanmin([r[1][j] for r in rows]), np.nanmax([r[1][j] for r in rows]))
              for j in range(3)]
    for i, (name, imgs) in enumerate(rows):
        for j, (img, ext, (lx, ly), view) in enumerate(
                zip(imgs, extents, labels, ("top", "front", "side"))):
            a = ax[i, j]
            a.imshow(img, origin="lower", extent=[e * unit for e in ext], cmap="viridis",
                     vmin=ranges[j][0], vmax=ranges[j][1])  # one shading per view
            a.set_title(f"{name}: {view}", fontsize=9)
            a.set_xlabel(f"{lx} ({unit_name})", fontsize=8)
            a.set_ylabel(f"{ly} ({unit_name})", fontsize=8)
            a.tick_params(labelsize=7)
            a.set_aspect("equal")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".png.tmp")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, format="png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


# ------------------------------------------------------------------------------ command line
def evaluate_generator(G, object_name: str, scale, drawing=None, **fit_kw) -> dict:
    """Shape fidelity of a generator's template (convex or spheres) against part
    `object_name`; `scale`: `metres_per_unit`. Also draws the three views to `drawing` if given."""
    truth = part_pieces(object_name)
    template = scaled(template_pieces(G), scale)
    f = fit(template, truth, **fit_kw)
    out = {"object": object_name, "metres_per_unit": np.round(np.asarray(scale), 6).tolist(),
           **f.to_dict()}
    if drawing is not None:
        three_view(transformed(template, f.R, f.t), truth, drawing,
                   title=f"{object_name}: IoU {f.iou:.3f}"
                   + (" (mirror image)" if f.mirrored else ""))
        out["drawing"] = str(drawing)
    return out


def main(argv=None) -> int:
    """Command line: print a checkpoint's shape fidelity as JSON, draw its three views."""
    p = argparse.ArgumentParser(prog="python -m inseggan_ros.evaluation.shape",
                                description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", type=Path, required=True,
                   help="a model with an explicit template (convex or spheres)")
    p.add_argument("--object", required=True, help="the true part (sim.objects name)")
    p.add_argument("--data", type=Path, help="the simulated data set (for its camera: the scale)")
    p.add_argument("--drawing", type=Path, help="write the three-view PNG here")
    args = p.parse_args(argv)
    from inseggan_ros.core.checkpoint import load
    from inseggan_ros.runtime.model import build_models

    state = load(args.checkpoint)
    if state["model_config"].get("renderer") not in ("convex", "spheres"):
        raise SystemExit(f"{args.checkpoint}: renderer {state['model_config'].get('renderer')!r}; "
                         "shape fidelity needs an explicit template (renderer 'convex' or "
                         "'spheres')")
    G = build_models(state, args.checkpoint)[1]
    camera = None
    if args.data:
        from inseggan_ros.sim.dataset import load_meta
        from inseggan_ros.sim.scene import SceneConfig

        camera = SceneConfig.from_dict(load_meta(args.data)["scene"]).camera
    scale = metres_per_unit(state["preprocess_config"], camera,
                            state["model_config"]["height_gain"])
    print(json.dumps(evaluate_generator(G, args.object, scale, args.drawing), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
