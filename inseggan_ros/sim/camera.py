"""Pinhole depth camera looking straight down into the bin.

Conventions (those of ROS `sensor_msgs/CameraInfo` and the optical frame REP 103 names
`*_optical_frame`): x right, y down, z forward; pixel (u, v) = (column, row), pixel centres at
integer coordinates; u = fx * X / Z + cx, v = fy * Y / Z + cy.
The camera sits at `height` metres above the bin floor (world z = 0), its x axis along world +x and
its y axis along world -y, so the image is the bin seen from above with world +y at the top.
"""
from __future__ import annotations

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

    def __post_init__(self):
        if self.width < 8 or self.height < 8 or self.width > 4096 or self.height > 4096:
            raise ValueError(f"camera size {self.width}x{self.height} invalid; valid: 8..4096")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0 < self.near < self.mount_height < self.far:
            raise ValueError("need 0 < near < mount_height < far, got "
                             f"{self.near}, {self.mount_height}, {self.far}")

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
        """Column-major 4x4 view matrix: eye above the origin, looking down, world +y up."""
        m = np.eye(4)
        m[2, 3] = -self.mount_height  # camera axes = world axes (OpenGL: looks along -z)
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
        """OpenGL z-buffer in [0, 1] -> metric depth along the optical axis (metres)."""
        n, f = self.near, self.far
        return (f * n / (f - (f - n) * zbuf)).astype(np.float32)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> pixel coordinates (N, 2) (u, v)."""
        p = np.asarray(points_world, float)
        X, Y, Z = p[:, 0], -p[:, 1], self.mount_height - p[:, 2]
        return np.stack([self.fx * X / Z + self.cx, self.fy * Y / Z + self.cy], 1)


PRESETS: dict[str, CameraConfig] = {
    # 224x224 square image of the bin, as the paper renders (Insta-10).
    "default": CameraConfig(),
    # Intel RealSense D435 depth stream at 848x480 (~87 x 58 degree field of view),
    # mounted 0.3 m above the bin floor.
    "realsense_d435": CameraConfig(width=848, height=480, fx=426.0, fy=426.0, cx=423.5,
                                   cy=239.5, mount_height=0.3, near=0.1, far=3.0),
}


def get_camera(preset: str, width: int | None = None, height: int | None = None) -> CameraConfig:
    try:
        cam = PRESETS[preset]
    except KeyError:
        raise ValueError(f"unknown camera preset {preset!r}; valid: {', '.join(PRESETS)}") from None
    if width is not None or height is not None:
        cam = cam.resized(width or cam.width, height or cam.height)
    return cam
