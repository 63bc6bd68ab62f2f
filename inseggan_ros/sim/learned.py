"""A learned template as a simulator part: the shape InSeGAN learned from unlabelled frames,
dropped into the bin as a rigid body (convex pieces for collision, their surface for the depth
camera), at its learned size in metres.

    inseggan simulate --object models/cylinder --count 2000 --out data/my_part_sim

The rod of spheres becomes one convex piece per sphere (each sphere a convex hull of
SPHERE_POINTS points on it), a convex template its convex pieces (the corners of each piece's
half-spaces). Template units become metres with `shape.metres_per_unit`, the bin crop's pixel
size taken at the depth of the template's middle rather than at the floor: the camera sees a
part's top larger than its floor-level footprint (perspective), and the template learned the
size it saw. The body frame is the template's own, moved so that the origin is the centroid of
its pieces' corners (the physics engine takes the link frame as the inertial frame).
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from inseggan_ros.sim.objects import Mesh, ObjectSpec

SPHERE_POINTS = 256  # points on each sphere of a rod template: its hull is within 1 % of it
DENSITY = 1000.0  # kg / m^3: the mass does not change how parts come to rest, only how fast


def is_model_path(name: str) -> bool:
    """Whether `--object NAME` names a model (a model folder or a .pt checkpoint), not a part of
    the built-in library."""
    p = Path(name)
    return name.endswith(".pt") or (p.is_dir() and (p / "model.pt").is_file())


def _fibonacci_sphere(k: int) -> np.ndarray:
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    r = np.sqrt(1 - z ** 2)
    a = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(a), r * np.sin(a), z], 1)


def _hull_mesh(points: np.ndarray) -> Mesh:
    """The convex hull of `points` as a triangle mesh, counter-clockwise seen from outside."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    tris = hull.simplices.copy()
    # orient each triangle so that its normal points away from the hull's centre
    centre = points[hull.vertices].mean(0)
    a, b, c = (points[tris[:, k]] for k in range(3))
    flip = (np.cross(b - a, c - a) * (a - centre)).sum(1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return Mesh(points, tris)


def model_camera(path: Path, state: dict | None = None):
    """The camera the model was trained with (for its scale): its card's (model folders: a data
    set's camera, or the one the loop estimated from a recording), else the one its checkpoint
    records, else its training data set's; None if none is known."""
    import json

    from inseggan_ros.sim.camera import CameraConfig

    card = path.parent / "card.json" if path.suffix == ".pt" else path / "card.json"
    card = json.loads(card.read_text()) if card.is_file() else {}
    cam = card.get("camera") or (card.get("training_data") or {}).get("camera")
    data = (state or {}).get("data") or {}
    if cam is None:
        cam = data.get("camera")
    if cam is None and data.get("path") and (Path(data["path"]) / "meta.json").is_file():
        cam = json.loads((Path(data["path"]) / "meta.json").read_text())["scene"]["camera"]
    return CameraConfig(**cam) if isinstance(cam, dict) else None


def template_pieces_units(G) -> list[np.ndarray]:
    """The template of a sphere or convex generator as convex vertex sets in template units,
    in its own frame with the rendering's height offset (a rod's `lift`) applied: (N_i, 3)."""
    import torch

    from inseggan_ros.runtime.model import ConvexGenerator, SphereGenerator

    with torch.no_grad():
        if isinstance(G, SphereGenerator):
            centres, radii = (t.double().cpu().numpy() for t in G.spheres())
            unit = _fibonacci_sphere(SPHERE_POINTS)
            return [c + r * unit for c, r in zip(centres, radii)]
        if isinstance(G, ConvexGenerator):
            from inseggan_ros.runtime.pieces import template_pieces, vertices

            return [vertices([piece]) for piece in template_pieces(G)]
    raise ValueError(f"renderer {G.cfg.renderer!r} has no explicit template to export; valid: "
                     "spheres, convex")


def template_scale(state: dict, G, camera=None) -> np.ndarray:
    """Template units -> metres (3,): `shape.metres_per_unit` with the crop's pixel size at the
    depth of the template's middle (see the module docstring)."""
    from inseggan_ros.runtime.pieces import metres_per_unit

    prep = dict(state["preprocess_config"])
    view = (state.get("data") or {}).get("view")  # a bag's: the bin found in every frame
    if view and prep.get("roi") is None and prep.get("floor_depth") is None:
        prep.update(roi=view["roi"], floor_depth=view["floor_depth"], margin=0)
    gain = float(state["model_config"].get("height_gain", 1.8))
    z = metres_per_unit(prep, None, gain)[2]
    if camera is not None and prep.get("floor_depth") is not None:
        v = np.concatenate(template_pieces_units(G))
        middle = float(np.ptp(v[:, 2])) * z / 2
        prep["floor_depth"] = float(prep["floor_depth"]) - middle
    return metres_per_unit(prep, camera, gain)


def template_object(path, camera=None) -> ObjectSpec:
    """A model (folder or checkpoint) -> its learned template as a simulator part (metres).
    `camera`: the training camera (`sim.camera.CameraConfig`) for the scale; default: the
    model card's, else the crop is taken to be as wide as its height range (see
    `shape.metres_per_unit`)."""
    from inseggan_ros.core.checkpoint import load
    from inseggan_ros.runtime.model import build_models

    path = Path(path)
    file = path / "model.pt" if path.is_dir() else path
    if not file.is_file():
        raise ValueError(f"{path}: no model checkpoint there; valid: a model folder with "
                         "model.pt, or a .pt checkpoint")
    state = load(file)
    G = build_models(state, file)[1]
    camera = camera if camera is not None else model_camera(file, state)
    scale = template_scale(state, G, camera)
    parts = [v * scale for v in template_pieces_units(G)]
    centre = np.concatenate(parts).mean(0)
    parts = tuple(np.ascontiguousarray(v - centre) for v in parts)
    mesh = Mesh.merge([_hull_mesh(v) for v in parts])
    volume = _volume(parts)
    name = path.name if path.is_dir() else path.stem
    return ObjectSpec(str(path), f"learned template of {name} ({G.cfg.renderer}, "
                      f"{len(parts)} convex pieces)", parts, mesh, mass=DENSITY * volume)


def template_origin(path, camera=None) -> np.ndarray:
    """Where the template frame's origin lies in the exported body's frame, metres (3,): the
    body frame is the template's, shifted to the centroid of its corners."""
    from inseggan_ros.core.checkpoint import load
    from inseggan_ros.runtime.model import build_models

    path = Path(path)
    file = path / "model.pt" if path.is_dir() else path
    state = load(file)
    G = build_models(state, file)[1]
    camera = camera if camera is not None else model_camera(file, state)
    scale = template_scale(state, G, camera)
    return -np.concatenate([v * scale for v in template_pieces_units(G)]).mean(0)


def _volume(parts) -> float:
    """Volume of the union of convex pieces, by Monte Carlo on a fixed grid of 40^3 points."""
    from scipy.spatial import Delaunay

    v = np.concatenate(parts)
    lo, hi = v.min(0), v.max(0)
    axes = [np.linspace(a, b, 40) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.zeros(len(grid), bool)
    for part in parts:
        inside |= Delaunay(part).find_simplex(grid) >= 0
    return float(inside.mean() * np.prod(hi - lo))


@functools.lru_cache(maxsize=8)
def cached_template_object(path: str) -> ObjectSpec:
    """`template_object` once per process (simulation workers build many scenes)."""
    return template_object(path)
