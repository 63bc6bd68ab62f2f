"""Procedural object library: industrial parts built from code, no mesh files, no downloads.

Every object is described in its own body frame (metres, origin near the centre of mass) by
  * `parts`: convex pieces for collision (pybullet makes a convex hull of each vertex set), and
  * `mesh`:  one triangle mesh (vertices, triangle indices) that is rendered.
Concave parts (the hole of a hex nut) are modelled as several convex pieces, so the hole is
real for physics and for the depth camera alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (V, 3) float, metres
    triangles: np.ndarray  # (T, 3) int, counter-clockwise seen from outside

    @staticmethod
    def merge(meshes: list["Mesh"]) -> "Mesh":
        verts, tris, offset = [], [], 0
        for m in meshes:
            verts.append(m.vertices)
            tris.append(m.triangles + offset)
            offset += len(m.vertices)
        return Mesh(np.concatenate(verts), np.concatenate(tris))

    def translated(self, offset) -> "Mesh":
        return Mesh(self.vertices + np.asarray(offset, float), self.triangles)


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    description: str
    parts: tuple[np.ndarray, ...]  # convex vertex sets (N_i, 3) for collision
    mesh: Mesh
    mass: float  # kg

    @property
    def extent(self) -> np.ndarray:
        """Axis-aligned size (x, y, z) of the object in its own frame, metres."""
        v = self.mesh.vertices
        return v.max(0) - v.min(0)

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere around the body origin, metres."""
        return float(np.linalg.norm(self.mesh.vertices, axis=1).max())


# --------------------------------------------------------------------------- mesh builders
def _circle(radius: float, segments: int, phase: float = 0.0) -> np.ndarray:
    a = phase + np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a)], 1)


def _hexagon(across_flats: float, points_per_side: int = 1) -> np.ndarray:
    """Regular hexagon (flat sides), optionally resampled with several points per side."""
    corner = across_flats / np.sqrt(3.0)
    corners = _circle(corner, 6, phase=np.pi / 6)
    pts = []
    for i in range(6):
        a, b = corners[i], corners[(i + 1) % 6]
        for k in range(points_per_side):
            pts.append(a + (b - a) * k / points_per_side)
    return np.array(pts)


def frustum(r_bottom: float, r_top: float, height: float, segments: int = 24) -> Mesh:
    """Closed cylinder, cone (r_top = 0) or truncated cone, centred on the origin, axis z."""
    z0, z1 = -height / 2, height / 2
    bottom = np.column_stack([_circle(r_bottom, segments), np.full(segments, z0)])
    top = np.column_stack([_circle(max(r_top, 1e-6), segments), np.full(segments, z1)])
    verts = np.concatenate([bottom, top, [[0, 0, z0], [0, 0, z1]]])
    cb, ct = 2 * segments, 2 * segments + 1
    tris = []
    for i in range(segments):
        j = (i + 1) % segments
        tris += [[i, j, segments + j], [i, segments + j, segments + i]]  # side
        tris += [[cb, j, i], [ct, segments + i, segments + j]]  # caps
    return Mesh(verts, np.array(tris))


def prism(polygon: np.ndarray, height: float) -> Mesh:
    """Extrude a convex polygon (counter-clockwise, xy) along z, centred on the origin."""
    n = len(polygon)
    z0, z1 = -height / 2, height / 2
    verts = np.concatenate([np.column_stack([polygon, np.full(n, z0)]),
                            np.column_stack([polygon, np.full(n, z1)]),
                            [[*polygon.mean(0), z0], [*polygon.mean(0), z1]]])
    cb, ct = 2 * n, 2 * n + 1
    tris = []
    for i in range(n):
        j = (i + 1) % n
        tris += [[i, j, n + j], [i, n + j, n + i], [cb, j, i], [ct, n + i, n + j]]
    return Mesh(verts, np.array(tris))


def ring(outer: np.ndarray, inner: np.ndarray, height: float) -> Mesh:
    """Extruded ring between two closed xy polylines with the same number of points."""
    n = len(outer)
    z0, z1 = -height / 2, height / 2
    rings = [np.column_stack([p, np.full(n, z)]) for p, z in
             ((outer, z0), (outer, z1), (inner, z0), (inner, z1))]
    verts = np.concatenate(rings)
    ob, ot, ib, it = 0, n, 2 * n, 3 * n
    tris = []
    for i in range(n):
        j = (i + 1) % n
        tris += [[ob + i, ob + j, ot + j], [ob + i, ot + j, ot + i]]  # outer wall
        tris += [[ib + j, ib + i, it + i], [ib + j, it + i, it + j]]  # inner wall
        tris += [[ot + i, ot + j, it + j], [ot + i, it + j, it + i]]  # top face
        tris += [[ob + j, ob + i, ib + i], [ob + j, ib + i, ib + j]]  # bottom face
    return Mesh(verts, np.array(tris))


def box(size) -> Mesh:
    sx, sy, sz = np.asarray(size, float) / 2
    return prism(np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]), 2 * sz)


# --------------------------------------------------------------------------- the library
def _single(name, description, mesh, density=1200.0) -> ObjectSpec:
    volume = float(np.prod(mesh.vertices.max(0) - mesh.vertices.min(0)))
    return ObjectSpec(name, description, (mesh.vertices,), mesh, mass=density * volume * 0.6)


def _hex_nut() -> ObjectSpec:
    # An M16 nut: 24 mm across flats, 13 mm thick, 16 mm hole.
    af, thickness, hole_r, per_side = 0.024, 0.013, 0.008, 4
    outer = _hexagon(af, per_side)
    inner = _circle(hole_r, 6 * per_side, phase=np.pi / 6)
    mesh = ring(outer, inner, thickness)
    # Collision: six convex wedges, one per side of the hexagon, leaving the hole open.
    parts = []
    for s in range(6):
        idx = [(s * per_side + k) % len(outer) for k in range(per_side + 1)]
        ring_pts = np.concatenate([outer[idx], inner[idx][::-1]])
        parts.append(np.concatenate([np.column_stack([ring_pts, np.full(len(ring_pts), z)])
                                     for z in (-thickness / 2, thickness / 2)]))
    volume = thickness * (np.sqrt(3) / 2 * af ** 2 - np.pi * hole_r ** 2)
    return ObjectSpec("hex_nut", "M16 hex nut with its hole (24 mm AF, 13 mm)", tuple(parts),
                      mesh, mass=7850.0 * volume)


def _bolt() -> ObjectSpec:
    # An M10x40 hex bolt: head 17 mm AF x 6.4 mm, shaft 10 mm x 40 mm.
    head_h, shaft_l, shaft_r = 0.0064, 0.040, 0.005
    total = head_h + shaft_l
    head = prism(_hexagon(0.017), head_h).translated([0, 0, total / 2 - head_h / 2])
    shaft = frustum(shaft_r, shaft_r, shaft_l, 16).translated([0, 0, -total / 2 + shaft_l / 2])
    # Centre of mass is closer to the head; keep the origin at the geometric centre for
    # simplicity (the physics engine uses the link frame as the inertial frame).
    return ObjectSpec("bolt", "M10x40 hex bolt (17 mm head, 10 mm shaft)",
                      (head.vertices, shaft.vertices), Mesh.merge([head, shaft]), mass=0.03)


def _pin_connector() -> ObjectSpec:
    # A flanged dowel pin: shaft 10 mm x 36 mm with a 24 mm x 5 mm flange a third of the way up.
    shaft = frustum(0.005, 0.005, 0.036, 16)
    flange = frustum(0.012, 0.012, 0.005, 24).translated([0, 0, 0.006])
    return ObjectSpec("pin_connector", "flanged pin (10 x 36 mm shaft, 24 mm flange)",
                      (shaft.vertices, flange.vertices), Mesh.merge([shaft, flange]), mass=0.02)


def _box_overlap(a, b) -> tuple[float, np.ndarray]:
    """(volume, centre) of what two axis-aligned boxes share, each given as (size (3,),
    centre (3,)), metres."""
    lo = np.maximum(np.subtract(a[1], np.divide(a[0], 2)), np.subtract(b[1], np.divide(b[0], 2)))
    hi = np.minimum(np.add(a[1], np.divide(a[0], 2)), np.add(b[1], np.divide(b[0], 2)))
    return float(np.prod(np.clip(hi - lo, 0, None))), (lo + hi) / 2


def _bars(name: str, description: str, bars, density: float) -> ObjectSpec:
    """A part made of rectangular bars, each (size (3,), centre (3,)) in metres, axis-aligned
    in the part's frame: one convex collision piece per bar, one rendered mesh, the origin
    moved to the centre of mass. Neighbouring bars overlap by a little, so that the union is
    one body (`evaluation.shape.components`) and not bars that merely touch; what two bars
    share is counted once in the mass and its centre (no three bars may share a point)."""
    sizes = np.array([b[0] for b in bars], float)
    centres = np.array([b[1] for b in bars], float)
    volume, moment = sizes.prod(1).sum(), (sizes.prod(1)[:, None] * centres).sum(0)
    for i in range(len(bars)):
        for j in range(i + 1, len(bars)):
            v, c = _box_overlap(bars[i], bars[j])
            volume, moment = volume - v, moment - v * c
    com = moment / volume
    meshes = [box(size).translated(c - com) for size, c in zip(sizes, centres)]
    return ObjectSpec(name, description, tuple(m.vertices for m in meshes), Mesh.merge(meshes),
                      mass=density * volume)


def _t_piece() -> ObjectSpec:
    # A flat T of two bars 8 mm thick: a 40 x 10 mm cross bar and a 10 x 31 mm stem that
    # reaches 1 mm into it (40 x 40 mm overall), aluminium.
    return _bars("t_piece", "flat aluminium T of two bars (40 x 40 mm, 10 mm wide, 8 mm thick)",
                 [((0.040, 0.010, 0.008), (0.0, 0.015, 0.0)),
                  ((0.010, 0.031, 0.008), (0.0, -0.0045, 0.0))], density=2700.0)


def _l_bracket() -> ObjectSpec:
    # A steel angle bracket of two 5 mm plates at a right angle: a 30 x 20 mm base and a 20 mm
    # wide upright 26 mm tall overall, sharing the corner's 5 x 20 x 5 mm.
    return _bars("l_bracket", "steel angle bracket (30 x 20 mm base, 26 mm upright, 5 mm plate)",
                 [((0.030, 0.020, 0.005), (0.0, 0.0, 0.0)),
                  ((0.005, 0.020, 0.026), (0.0125, 0.0, 0.0105))], density=7850.0)


def _u_clip() -> ObjectSpec:
    # A flat U of three bars 6 mm thick: a 36 x 8 mm base and two 8 x 29 mm arms at its ends
    # that reach 1 mm into it (36 x 36 mm overall), aluminium.
    return _bars("u_clip", "flat aluminium U of three bars (36 x 36 mm, 8 mm wide, 6 mm thick)",
                 [((0.036, 0.008, 0.006), (0.0, -0.014, 0.0)),
                  ((0.008, 0.029, 0.006), (-0.014, 0.0035, 0.0)),
                  ((0.008, 0.029, 0.006), (0.014, 0.0035, 0.0))], density=2700.0)


def _z_bracket() -> ObjectSpec:
    # A flat Z of three bars 8 mm thick: two 24 x 8 mm flanges at opposite ends of a 8 x 26 mm
    # web that reaches 1 mm into each (40 x 40 mm overall), aluminium.
    return _bars("z_bracket", "flat aluminium Z of three bars (40 x 40 mm, 8 mm wide, 8 mm thick)",
                 [((0.024, 0.008, 0.008), (0.008, 0.016, 0.0)),
                  ((0.008, 0.026, 0.008), (0.0, 0.0, 0.0)),
                  ((0.024, 0.008, 0.008), (-0.008, -0.016, 0.0))], density=2700.0)


OBJECTS: dict[str, ObjectSpec] = {
    o.name: o for o in (
        _single("cylinder", "solid cylinder, 24 mm diameter x 40 mm",
                frustum(0.012, 0.012, 0.040)),
        _single("cone", "cone, 30 mm base diameter x 40 mm", frustum(0.015, 0.0, 0.040)),
        _hex_nut(),
        _bolt(),
        _single("wooden_block", "wooden block 50 x 25 x 15 mm", box([0.050, 0.025, 0.015]),
                density=600.0),
        _single("stopper", "tapered rubber stopper, 22/30 mm diameter x 25 mm",
                frustum(0.011, 0.015, 0.025)),
        _pin_connector(),
        _t_piece(),
        _l_bracket(),
        _u_clip(),
        _z_bracket(),
    )
}


def get_object(name: str) -> ObjectSpec:
    """A part of the library by name, or the learned template of a model (a model folder or a
    .pt checkpoint: `sim.learned`)."""
    if name in OBJECTS:
        return OBJECTS[name]
    from inseggan_ros.sim.learned import cached_template_object, is_model_path

    if is_model_path(name):
        return cached_template_object(name)
    raise ValueError(f"unknown object {name!r}; valid: {', '.join(OBJECTS)}, or a model folder "
                     "or .pt checkpoint (its learned template)")
