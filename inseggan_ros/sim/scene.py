"""The physics bin: n identical objects dropped one at a time into a box, seen from above.

pybullet in DIRECT mode (no GUI, no files, no downloads), its CPU TinyRenderer for the depth and
segmentation buffers. Every scene starts from `resetSimulation`, so a scene depends on its seed
alone, not on what the simulator did before (the same seed gives the same bytes).
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial import ConvexHull

from inseggan_ros.sim.camera import CameraConfig
from inseggan_ros.sim.noise import NoiseConfig, apply_noise
from inseggan_ros.sim.objects import ObjectSpec, get_object


DROPS = 5  # tries to drop each part into the bin before the pile is started again
# Piles started from scratch (each from a seed derived from the scene's) before the scene is
# given up: a part that fits the bin still falls out now and then (more often the larger it is),
# and one such scene must not stop a data set of thousands.
PILES = 4
COUNT_STREAM = 0x636F756E  # the seed stream that draws a scene's count (`SceneConfig.count`)


class PileError(ValueError):
    """A scene's parts do not stay in the bin (the part is too large for that many)."""


@dataclass(frozen=True)
class BinConfig:
    inner_size: tuple[float, float] = (0.09, 0.09)  # metres (x, y)
    wall_height: float = 0.05
    wall_thickness: float = 0.01

    def __post_init__(self):
        if min(self.inner_size) <= 0.03 or max(self.inner_size) > 2.0:
            raise ValueError(f"bin inner_size {self.inner_size} invalid; valid: 0.03..2 m per side")
        if not 0.005 <= self.wall_height <= 1.0:
            raise ValueError(f"bin wall_height {self.wall_height} invalid; valid: 0.005..1 m")

    def corners(self, height: float = 0.0) -> np.ndarray:
        """The four inner corners of the bin at `height` above its floor, world metres (the
        floor: 0, the top of the walls: wall_height)."""
        hx, hy = self.inner_size[0] / 2, self.inner_size[1] / 2
        return np.array([[-hx, -hy, height], [hx, -hy, height], [hx, hy, height],
                         [-hx, hy, height]])


MAX_INSTANCES = 20


@dataclass(frozen=True)
class SceneConfig:
    """One kind of bin scene. `instances` parts are dropped into the bin (0: an empty bin, whose
    labels are all 0); with `min_instances` set, each scene draws its own count, uniformly in
    min_instances..instances from its seed, as a robot that empties the bin sees it (full,
    then fewer parts, then none)."""

    object: str = "cylinder"
    instances: int = 5
    camera: CameraConfig = field(default_factory=CameraConfig)
    bin: BinConfig = field(default_factory=BinConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    drop_spread: float = 0.25  # objects drop within this fraction of the bin's inner size
    time_step: float = 1.0 / 120.0
    settle_speed: float = 0.02  # m/s (and rad/s scaled by the object radius)
    max_settle_steps: int = 240
    min_instances: int | None = None  # None: every scene holds `instances` parts

    def __post_init__(self):
        get_object(self.object)  # raises with the list of valid names
        if not 0 <= self.instances <= MAX_INSTANCES:
            raise ValueError(f"instances must be in 0..{MAX_INSTANCES} (0 = an empty bin), got "
                             f"{self.instances}")
        if self.min_instances is not None and not 0 <= self.min_instances <= self.instances:
            raise ValueError(f"min_instances must be in 0..instances ({self.instances}) or None "
                             f"(every scene holds `instances` parts), got {self.min_instances}")
        if not 0 < self.drop_spread <= 1:
            raise ValueError(f"drop_spread must be in (0, 1], got {self.drop_spread}")

    def to_dict(self) -> dict:
        return asdict(self)

    def count(self, seed: int) -> int:
        """How many parts the scene of `seed` holds: `instances`, or with `min_instances` a
        count drawn from the seed alone (from a stream of its own, so that the piles' random
        numbers are those of a scene of that many parts)."""
        if self.min_instances is None:
            return self.instances
        rng = np.random.default_rng([COUNT_STREAM, int(seed)])
        return int(rng.integers(self.min_instances, self.instances + 1))

    @staticmethod
    def from_dict(d: dict) -> "SceneConfig":
        d = dict(d)
        d["camera"] = CameraConfig(**d["camera"])
        b = dict(d["bin"])
        b["inner_size"] = tuple(b["inner_size"])
        d["bin"] = BinConfig(**b)
        d["noise"] = NoiseConfig(**d["noise"])
        return SceneConfig(**d)


@dataclass
class Scene:
    depth: np.ndarray  # (H, W) float32 metres; 0 = no reading (noise model only)
    labels: np.ndarray  # (H, W) uint8, 0 = bin / background, 1..n = instance
    poses: np.ndarray  # (n, 7) float32: x, y, z, qx, qy, qz, qw (world frame); n may be 0
    seed: int


@contextlib.contextmanager
def _quiet_c_output():
    """Silence C-level output: pybullet prints its build time when imported (clean CLI)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


PARTS_DIR = "inseggan_sim_parts"  # under the system's temp dir: `part_files`' folders
PARTS_KEEP_S = 86400.0  # a part's folder unused this long is removed when another is made


def part_files(parts) -> list[str]:
    """A part's convex pieces ((V, 3) vertices each) -> OBJ files of their hulls, which is how
    pybullet takes a compound's pieces. They lie in a folder named by their content under
    PARTS_DIR in the system's temp dir, written once (each file atomically) and shared by
    every simulator of the part; making one removes the folders unused for PARTS_KEEP_S. Why
    not a folder per simulator, removed when it closes: pool workers end without running
    finalisers, and their folders piled up (thousands a day of loops)."""
    texts = ["".join([*(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in part),
                      *(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in ConvexHull(part).simplices)])
             for part in parts]
    key = hashlib.sha256("\0".join(texts).encode()).hexdigest()[:16]
    root = os.path.join(tempfile.gettempdir(), PARTS_DIR)
    folder = os.path.join(root, key)
    if not os.path.isdir(folder):
        _prune(root)
        os.makedirs(folder, exist_ok=True)
    os.utime(folder)  # in use: not pruned
    paths = []
    for i, text in enumerate(texts):
        path = os.path.join(folder, f"part{i}.obj")
        if not os.path.isfile(path) or _read(path) != text:
            tmp = f"{path}.{os.getpid()}.tmp"
            with open(tmp, "w") as f:
                f.write(text)
            os.replace(tmp, path)
        paths.append(path)
    return paths


def _prune(root: str) -> None:
    """Remove `part_files`' folders under `root` unused for PARTS_KEEP_S (another process's
    removal or a file in use is left as it is)."""
    import shutil

    now = time.time()
    for entry in os.scandir(root) if os.path.isdir(root) else ():
        try:
            if entry.is_dir() and now - entry.stat().st_mtime > PARTS_KEEP_S:
                shutil.rmtree(entry.path, ignore_errors=True)
        except OSError:
            pass


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


class BinSimulator:
    """Owns one pybullet physics client; `render(seed)` makes one scene."""

    def __init__(self, config: SceneConfig):
        with _quiet_c_output():  # imported here so that `import inseggan_ros.sim` stays light
            import pybullet
            self.client = pybullet.connect(pybullet.DIRECT)
        self.p = pybullet
        self.cfg = config
        self.spec: ObjectSpec = get_object(config.object)
        self._part_files = part_files(self.spec.parts) if len(self.spec.parts) > 1 else []
        self._view = config.camera.view_matrix()
        self._proj = config.camera.projection_matrix()
        self.last_piles = 0  # how many piles the last scene took (1: its seed's own)

    def close(self) -> None:
        if self.client is not None:
            self.p.disconnect(physicsClientId=self.client)
            self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ world building
    def _reset_world(self) -> tuple[int, int]:
        p, c, b = self.p, self.client, self.cfg.bin
        p.resetSimulation(physicsClientId=c)
        p.setGravity(0, 0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=self.cfg.time_step, numSolverIterations=10,
                                    deterministicOverlappingPairs=1, physicsClientId=c)
        hx, hy, t, h = b.inner_size[0] / 2, b.inner_size[1] / 2, b.wall_thickness, b.wall_height
        boxes = [([1.0, 1.0, t / 2], [0, 0, -t / 2]),  # bin floor on a 2 m table, top at z = 0
                 ([t / 2, hy + t, h / 2], [hx + t / 2, 0, h / 2]),
                 ([t / 2, hy + t, h / 2], [-hx - t / 2, 0, h / 2]),
                 ([hx, t / 2, h / 2], [0, hy + t / 2, h / 2]),
                 ([hx, t / 2, h / 2], [0, -hy - t / 2, h / 2])]
        for half, pos in boxes:
            col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c)
            vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, physicsClientId=c)
            body = p.createMultiBody(0, col, vis, basePosition=pos, physicsClientId=c)
            p.changeDynamics(body, -1, lateralFriction=0.6, physicsClientId=c)
        spec = self.spec
        if len(spec.parts) == 1:
            col = p.createCollisionShape(p.GEOM_MESH, vertices=spec.parts[0].tolist(),
                                         physicsClientId=c)
        else:  # a compound of convex hulls; pybullet takes those only from mesh files
            k = len(spec.parts)
            col = p.createCollisionShapeArray([p.GEOM_MESH] * k, fileNames=self._part_files,
                                              meshScales=[[1, 1, 1]] * k, physicsClientId=c)
        vis = p.createVisualShape(p.GEOM_MESH, vertices=spec.mesh.vertices.tolist(),
                                  indices=spec.mesh.triangles.reshape(-1).tolist(),
                                  physicsClientId=c)
        return col, vis

    def _settle(self, bodies: list[int]) -> None:
        p, c = self.p, self.client
        r = self.spec.radius
        for step in range(self.cfg.max_settle_steps):
            p.stepSimulation(physicsClientId=c)
            if step % 4 == 3:
                fastest = 0.0
                for b in bodies:
                    lin, ang = p.getBaseVelocity(b, physicsClientId=c)
                    fastest = max(fastest, max(map(abs, lin)), r * max(map(abs, ang)))
                if fastest < self.cfg.settle_speed:
                    return

    def _inside_bin(self, body: int) -> bool:
        (x, y, z), _ = self.p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        hx, hy = self.cfg.bin.inner_size[0] / 2, self.cfg.bin.inner_size[1] / 2
        return abs(x) < hx and abs(y) < hy and z > -0.01  # on the floor or on the pile

    # ------------------------------------------------------------------ one scene
    def _pile(self, rng: np.random.Generator, count: int) -> tuple[list[int], int | None]:
        """Drop `count` parts one by one into an empty bin -> (their bodies, None), or (the
        bodies so far, k) when part k fell out of the bin in each of its DROPS drops."""
        p, c, cfg = self.p, self.client, self.cfg
        col, vis = self._reset_world()
        spread = np.asarray(cfg.bin.inner_size) * cfg.drop_spread / 2
        bodies: list[int] = []
        top = 0.0
        for k in range(count):
            for _attempt in range(DROPS):
                q = rng.standard_normal(4)
                q /= np.linalg.norm(q)
                pos = [*rng.uniform(-spread, spread), top + self.spec.radius + 0.01]
                body = p.createMultiBody(self.spec.mass, col, vis, basePosition=pos,
                                         baseOrientation=q.tolist(), physicsClientId=c)
                p.changeDynamics(body, -1, lateralFriction=0.6, rollingFriction=0.002,
                                 spinningFriction=0.002, linearDamping=0.1, angularDamping=0.1,
                                 physicsClientId=c)
                self._settle(bodies + [body])
                if self._inside_bin(body):
                    break
                p.removeBody(body, physicsClientId=c)  # bounced out: drop it again
            else:
                return bodies, k
            bodies.append(body)
            top = max(p.getAABB(b, physicsClientId=c)[1][2] for b in bodies)
        return bodies, None

    def render(self, seed: int) -> Scene:
        p, c, cfg = self.p, self.client, self.cfg
        t0 = time.perf_counter()
        count = cfg.count(seed)
        for pile in range(PILES):  # the first pile from the seed itself: data sets unchanged
            rng = np.random.default_rng(seed if pile == 0 else [seed, pile])
            bodies, fell = self._pile(rng, count)
            if fell is None:
                break
        else:
            size = " x ".join(f"{1000 * v:.0f}" for v in self.spec.extent)
            inner = " x ".join(f"{1000 * v:.0f}" for v in cfg.bin.inner_size)
            raise PileError(
                f"seed {seed}: part {fell + 1} of {count} ({self.spec.name}, {size} mm) "
                f"fell out of the {inner} mm bin in {DROPS} drops, in each of {PILES} piles "
                "started afresh; valid: a part that fits that many times in the bin (a learned "
                "shape this large is not learned yet: train it longer), or fewer instances, or "
                "a larger bin")
        self.last_piles = pile + 1

        t1 = time.perf_counter()
        cam = cfg.camera
        _, _, _, zbuf, seg = p.getCameraImage(
            cam.width, cam.height, self._view, self._proj, shadow=0,
            renderer=p.ER_TINY_RENDERER, physicsClientId=c)
        zbuf = np.asarray(zbuf, np.float32).reshape(cam.height, cam.width)
        seg = np.asarray(seg, np.int32).reshape(cam.height, cam.width)
        depth = cam.depth_from_zbuffer(zbuf)
        lut = np.zeros(max(bodies + [int(seg.max())]) + 2, np.uint8)  # an empty bin: all 0
        lut[np.array(bodies, np.int64) + 1] = np.arange(1, len(bodies) + 1)
        labels = lut[np.clip(seg, -1, None) + 1]
        if cfg.noise.enabled:
            depth = apply_noise(depth, cfg.noise, rng, fx=cam.fx)
        poses = np.array([sum(map(list, p.getBasePositionAndOrientation(b, physicsClientId=c)), [])
                          for b in bodies], np.float32).reshape(len(bodies), 7)
        self.last_timing = {"physics": t1 - t0, "render": time.perf_counter() - t1}
        return Scene(depth=depth, labels=labels, poses=poses, seed=int(seed))
