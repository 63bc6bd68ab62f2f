"""Pinhole depth camera looking down into the bin, straight or at a tilt.

Conventions (those of ROS `sensor_msgs/CameraInfo` and the optical frame REP 103 names
`*_optical_frame`): x right, y down, z forward; pixel (u, v) = (column, row), pixel centres at
integer coordinates; u = fx * X / Z + cx, v = fy * Y / Z + cy.
With the default pose the camera sits `mount_height` metres above the centre of the bin floor
(world z = 0), its x axis along world +x and its y axis along world -y, so the image is the bin
seen from above with world +y at the top. The pose options turn and move it as a real mount does:
`tilt` turns it about its own x axis (degrees; positive: the top of the image looks farther
away), `roll` about its optical axis (the bin turns in the image), and `bin_offset` moves it
sideways, at the same height, until the bin's centre appears at that fraction of the image
width and height from the principal point (the bin off-centre, or partly out of view).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np


@dataclass(frozen=True)
class CameraConfig:
    width: int = 224
    height: int = 224
    fx: float = 420.0
    fy: float = 420.0
    cx: float = 111.5
    cy: float = 111.5
    mount_height: float = 0.35  # metres above the bin floor
    near: float = 0.05
    far: float = 2.0
    tilt: float = 0.0  # degrees about the camera's x axis (|tilt| <= 45)
    roll: float = 0.0  # degrees about the optical axis (|roll| <= 180)
    bin_offset: tuple[float, float] = (0.0, 0.0)  # bin centre in the image: fraction of (W, H)

    def __post_init__(self):
        if self.width < 8 or self.height < 8 or self.width > 4096 or self.height > 4096:
            raise ValueError(f"camera size {self.width}x{self.height} invalid; valid: 8..4096")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0 < self.near < self.mount_height < self.far:
            raise ValueError("need 0 < near < mount_height < far, got "
                             f"{self.near}, {self.mount_height}, {self.far}")
        if not (math.isfinite(self.tilt) and abs(self.tilt) <= 45):
            raise ValueError(f"camera tilt {self.tilt!r} invalid; valid: degrees in [-45, 45]")
        if not (math.isfinite(self.roll) and abs(self.roll) <= 180):
            raise ValueError(f"camera roll {self.roll!r} invalid; valid: degrees in [-180, 180]")
        try:
            off = tuple(float(v) for v in self.bin_offset)
        except (TypeError, ValueError):
            off = ()
        if len(off) != 2 or not all(math.isfinite(v) and abs(v) <= 0.75 for v in off):
            raise ValueError(f"camera bin_offset {self.bin_offset!r} invalid; valid: two fractions "
                             "of the image (width, height) in [-0.75, 0.75]; (0, 0) = bin centre "
                             "on the principal point, +-0.5 = on the image border")
        object.__setattr__(self, "bin_offset", off)
        if self.position()[2] <= 0:
            raise ValueError(f"camera bin_offset {off} with tilt {self.tilt} and roll {self.roll} "
                             "puts the bin at or above the horizon; valid: a pixel that looks "
                             "down at the floor")

    # ------------------------------------------------------------------ pose
    def rotation(self) -> np.ndarray:
        """3 x 3 rotation from world axes to the camera's optical axes."""
        t, r = math.radians(self.tilt), math.radians(self.roll)
        down = np.diag([1.0, -1.0, -1.0])  # the default: looking straight down, world +y up
        rx = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
        rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
        return rz @ rx @ down

    def position(self) -> np.ndarray:
        """The camera's centre in world metres: `mount_height` above the floor, moved sideways
        so that the bin's centre (the world origin) appears at `bin_offset`."""
        u = self.cx + self.bin_offset[0] * self.width
        v = self.cy + self.bin_offset[1] * self.height
        ray = self.rotation().T @ np.array([(u - self.cx) / self.fx, (v - self.cy) / self.fy, 1])
        if ray[2] >= 0:  # that pixel looks at or above the horizon: no such position
            return np.array([0.0, 0.0, -1.0])
        return self.mount_height / ray[2] * ray  # ray from it hits the origin; z = mount_height

    def floor_plane(self) -> tuple[float, float, float]:
        """The floor (world z = 0) as (a, b, c) with 1 / depth = a * u + b * v + c at pixel
        (u, v): a plane seen through a pinhole camera is affine in inverse depth."""
        n = self.rotation() @ np.array([0.0, 0.0, 1.0])  # world up, in camera axes
        h = self.mount_height
        a, b = -n[0] / (self.fx * h), -n[1] / (self.fy * h)
        c = -(n[2] - n[0] * self.cx / self.fx - n[1] * self.cy / self.fy) / h
        return float(a), float(b), float(c)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def resized(self, width: int, height: int) -> "CameraConfig":
        """Same field of view at another resolution."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def to_dict(self) -> dict:
        return asdict(self)

    # ------------------------------------------------------------------ OpenGL matrices
    def view_matrix(self) -> list[float]:
        """Column-major 4x4 view matrix of the camera's pose (OpenGL eye axes: x right, y up,
        looking along -z, i.e. the optical axes with y and z flipped)."""
        m = np.eye(4)
        gl = np.diag([1.0, -1.0, -1.0]) @ self.rotation()
        m[:3, :3] = gl
        m[:3, 3] = -gl @ self.position()
        return m.T.reshape(-1).tolist()

    def projection_matrix(self) -> list[float]:
        """Column-major OpenGL projection that reproduces the pinhole model above exactly."""
        w, h, n, f = self.width, self.height, self.near, self.far
        p = np.zeros((4, 4))
        p[0, 0] = 2 * self.fx / w
        p[0, 2] = 1 - 2 * (self.cx + 0.5) / w
        p[1, 1] = 2 * self.fy / h
        p[1, 2] = 2 * (self.cy + 0.5) / h - 1
        p[2, 2] = -(f + n) / (f - n)
        p[2, 3] = -2 * f * n / (f - n)
        p[3, 2] = -1
        return p.T.reshape(-1).tolist()

    def depth_from_zbuffer(self, zbuf: np.ndarray) -> np.ndarray:
        """Metric depth along the optical axis (metres) from an OpenGL z-buffer in [0, 1]."""
        n, f = self.near, self.far
        return (f * n / (f - (f - n) * zbuf)).astype(np.float32)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> pixel coordinates (N, 2) (u, v)."""
        X, Y, Z = self.to_camera(points_world).T
        return np.stack([self.fx * X / Z + self.cx, self.fy * Y / Z + self.cy], 1)

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> the camera's optical axes (N, 3); column 2 is the depth."""
        p = np.asarray(points_world, float).reshape(-1, 3)
        return (p - self.position()) @ self.rotation().T


PRESETS: dict[str, CameraConfig] = {
    # 224x224 square image of the bin, as the paper renders (Insta-10).
    "default": CameraConfig(),
    # Intel RealSense D435 depth stream at 848x480 (~87 x 58 degree field of view),
    # mounted 0.3 m above the bin floor.
    "realsense_d435": CameraConfig(width=848, height=480, fx=426.0, fy=426.0, cx=423.5,
                                   cy=239.5, mount_height=0.3, near=0.1, far=3.0),
    # The same camera as a real mount holds it: tilted 3 degrees, turned 1.5 degrees about its
    # axis, the bin off-centre (its centre 15 % of the width left of and 8 % of the height
    # below the principal point).
    "realsense_d435_tilted": CameraConfig(width=848, height=480, fx=426.0, fy=426.0, cx=423.5,
                                          cy=239.5, mount_height=0.3, near=0.1, far=3.0,
                                          tilt=3.0, roll=1.5, bin_offset=(-0.15, 0.08)),
}


def get_camera(preset: str, width: int | None = None, height: int | None = None) -> CameraConfig:
    try:
        cam = PRESETS[preset]
    except KeyError:
        raise ValueError(f"unknown camera preset {preset!r}; valid: {', '.join(PRESETS)}") from None
    if width is not None or height is not None:
        cam = cam.resized(width or cam.width, height or cam.height)
    return cam
