"""A template as a union of convex pieces, each given by half-spaces {x : n . x <= d}: the
pieces of a learned generator, their corners, and template units in metres. Shared by the model
cards' shape measures (`evaluation.shape`) and the simulator's learned parts (`sim.learned`)."""
from __future__ import annotations

import numpy as np


Pieces = list  # of (normals (P, 3), offsets (P,)) pairs: a union of convex pieces


# ------------------------------------------------------------------------------ bodies
SPHERE_FACES = 200  # tangent planes per sphere


def _directions(count: int) -> np.ndarray:
    """`count` unit vectors spread evenly over the sphere (a Fibonacci lattice), (count, 3)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = k * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def template_pieces(G) -> Pieces:
    """A generator's template in its own frame (image half-widths): a convex template's pieces,
    or a rod of spheres, each the polytope of its tangent planes."""
    if hasattr(G, "halfspaces"):
        n, d = (t.detach().double().cpu().numpy() for t in G.halfspaces())
        return [(n[k], d[k]) for k in range(len(n))]
    if not hasattr(G, "spheres"):
        raise ValueError(f"{type(G).__name__}: no explicit template (valid: renderer 'convex' "
                         "or 'spheres')")
    centres, radii = (t.detach().double().cpu().numpy() for t in G.spheres())
    n = _directions(SPHERE_FACES)
    return [(n, n @ c + r) for c, r in zip(centres, radii)]


def vertices(pieces: Pieces) -> np.ndarray:
    """The corners of every piece (each the meeting point of three of its planes), (V, 3)."""
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection

    out = []
    for n, d in pieces:
        # an interior point: the centre of the largest ball inside (Chebyshev centre, an LP)
        norm = np.linalg.norm(n, axis=1)
        lp = linprog(np.r_[0, 0, 0, -1], A_ub=np.c_[n, norm], b_ub=d,
                     bounds=[(None, None)] * 3 + [(0, None)])
        if not lp.success or lp.x[3] <= 0:
            raise ValueError("a convex piece is empty or unbounded")
        out.append(HalfspaceIntersection(np.c_[n, -d], lp.x[:3]).intersections)
    return np.concatenate(out)


def metres_per_unit(prep: dict, camera=None, height_gain: float | None = None) -> np.ndarray:
    """Template units -> metres along x, y, z: (3,).

    Template x and y are image half-widths: the bin crop (`prep["roi"]` less `margin`, pixels)
    spans 2 units, and at the floor a pixel is floor_depth / f metres (`camera`: the data set's
    `sim.camera.CameraConfig`). Heights: 2 / height_gain units are `max_height` metres
    (`model.ModelConfig.height_gain`). Without a camera, roi or floor depth the crop is taken
    to be height_gain * max_height wide (how height_gain is defined) in x and y too."""
    gain = height_gain if height_gain is not None else 1.8
    z = gain * float(prep["max_height"]) / 2
    roi, floor = prep.get("roi"), prep.get("floor_depth")
    if camera is None or roi is None or floor is None:
        return np.array([z, z, z])
    x0, y0, x1, y1 = roi
    m = int(prep.get("margin", 0))
    return np.array([(x1 - x0 - 2 * m) * floor / camera.fx / 2,
                     (y1 - y0 - 2 * m) * floor / camera.fy / 2, z])
