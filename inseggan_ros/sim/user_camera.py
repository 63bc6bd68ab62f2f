"""The simulator's camera (and bin) estimated from a user's recorded depth frames.

A user who records a few depth frames of their bin (`sensor_msgs/Image`, with the
`sensor_msgs/CameraInfo` beside it) gets a `CameraConfig` that renders simulated bins as their
camera sees theirs, so that a model trained on simulated scenes meets the same view at run time:

1. the intrinsics (size, fx, fy, cx, cy) are the CameraInfo's K, as they are;
2. the bin floor's plane: `preprocess.find_bin` on the per-pixel 80th percentile of the
   frames' depths (objects move between frames, the floor and walls stay: that image is the
   bin as empty as most frames show it; on the median, a pile that stays put between frames
   made find_bin take a wall into the floor in one of the measured views), then refitted by
   least squares on the floor pixels of every frame inside the bin's outline
   (`_refine_plane`): one frame's plane is good to about half a degree, the roll of a
   slightly tilted camera needs a tenth of that;
3. the pose: a plane seen through a pinhole camera is affine in inverse depth,
   1 / z = a u + b v + c, and `CameraConfig.floor_plane` makes (a, b, c) from the mount height
   and the floor's normal in camera axes; `pose_from_plane` inverts that exactly;
4. the bin: its walls, found in a top-down view of the frames' points on the floor
   (`_bin_walls`), give the inner size and the centre, the centre's pixel the `bin_offset`.

The simulator's bin is square to the camera's roll (its sides along the world axes the tilt and
roll define), and its floor is the plane here; a bin turned on the floor against those axes is
measured along them, and a lens's distortion is ignored (depth streams are rectified).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from inseggan_ros.runtime import preprocess
from inseggan_ros.sim.camera import CameraConfig
from inseggan_ros.sim.noise_fit import estimate_noise

MAX_TILT = 45.0  # degrees: what CameraConfig takes
ROLL_MIN_TILT = 0.5  # degrees: below it the floor does not show which way the camera leans
WALL_MIN_HEIGHT = 0.005  # metres: lower walls are no walls
WALL_TOP_FRACTION = 0.85  # of the walls' height: a point on a wall's top


def pose_from_plane(plane, fx: float, fy: float, cx: float, cy: float
                    ) -> tuple[float, float, float]:
    """(mount_height metres, tilt degrees >= 0, roll degrees) of a camera whose floor is
    `plane` = (a, b, c), 1 / depth = a u + b v + c: the exact inverse of
    `CameraConfig.floor_plane`.

    The plane is m . K^-1 (u, v, 1) with m = (-a fx, -b fy, -c - a cx - b cy) = n / h, n the
    world's up in camera axes and h the camera's height above the floor, so h = 1 / |m| and
    n = m h. `CameraConfig.rotation` = rz(roll) rx(tilt) diag(1, -1, -1) puts up at
    n = (-sin roll sin tilt, cos roll sin tilt, -cos tilt): tilt = atan2(|n_xy|, -n_z) and
    roll = atan2(-n_x, n_y). Below `ROLL_MIN_TILT` degrees of tilt the roll is 0: a floor
    seen (nearly) square on looks the same whatever the roll, so the floor alone does not
    tell it. A tilt of t with roll r and one of -t with r + 180 are the same camera for a
    bin, which looks the same turned half a turn: the tilt here is never negative.
    """
    a, b, c = (float(x) for x in plane)
    m = np.array([-a * fx, -b * fy, -c - a * cx - b * cy])
    norm = float(np.linalg.norm(m))
    if not math.isfinite(norm) or norm == 0:
        raise ValueError(f"floor plane {plane} has no finite distance from the camera")
    h = 1.0 / norm
    n = m * h
    tilt = math.degrees(math.atan2(math.hypot(n[0], n[1]), -n[2]))
    roll = math.degrees(math.atan2(-n[0], n[1])) if tilt > ROLL_MIN_TILT else 0.0
    return h, tilt, roll


def _stack(depths, info) -> np.ndarray:
    """The frames as one (N, H, W) float32 array of metres (0 = no reading), checked."""
    frames = [np.asarray(d) for d in depths]
    if not frames:
        raise ValueError("no depth frames to estimate the camera from; valid: one or more "
                         "(H, W) depth images in metres")
    size = (int(info.height), int(info.width))
    for i, d in enumerate(frames):
        if d.shape != size:
            raise ValueError(f"depth frame {i} is {d.shape[::-1] if d.ndim == 2 else d.shape} "
                             f"(width x height) but the camera info says {size[1]}x{size[0]}; "
                             "valid: frames of the camera info's size")
        if not np.issubdtype(d.dtype, np.floating):
            raise ValueError(f"depth frame {i} has dtype {d.dtype}; valid: float metres "
                             "(bags.DepthFrame.metres())")
    stack = np.stack(frames).astype(np.float32)
    stack[~np.isfinite(stack) | (stack < 0)] = 0.0
    if not (stack > 0).any():
        raise ValueError("the depth frames hold no reading at all (every pixel 0 or NaN)")
    return stack


def _percentile_image(stack: np.ndarray, q: float) -> np.ndarray:
    """Per pixel, the q-th percentile (nearest rank) of the frames' readings, 0 where a pixel
    never read (np.nanpercentile does the same a hundred times slower)."""
    valid = (stack > 0).sum(0)
    ordered = np.sort(np.where(stack > 0, stack, np.inf), axis=0)  # readings first
    rank = np.rint(np.maximum(valid - 1, 0) * (q / 100.0)).astype(np.intp)
    img = np.take_along_axis(ordered, rank[None], 0)[0]
    return np.where(valid > 0, img, 0).astype(np.float32)


def _floor_mask(shape: tuple[int, int], polygon, erode: int) -> np.ndarray:
    """Pixels inside the outline, `erode` pixels clear of it (off the walls' feet)."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.rint(np.asarray(polygon) * 256).astype(np.int32)], 1, shift=8)
    if erode > 0:
        mask = cv2.erode(mask, np.ones((2 * erode + 1, 2 * erode + 1), np.uint8))
    return mask.astype(bool)


def _refine_plane(stack: np.ndarray, region: preprocess.BinRegion, iterations: int = 4):
    """The floor plane fitted again on every frame's floor pixels inside the bin's outline.

    Least squares in inverse depth (rows weighted by z^2, so residuals are in metres of
    depth) over the pixels within a tolerance of the current plane: 3 mm (or 0.5 % of the
    depth) at first, then three robust standard deviations of the residuals, at least 1.5 mm.
    Objects differ from frame to frame, the floor does not: pooled, the frames pin the plane
    down to hundredths of a degree. Returns (plane, number of floor pixels used)."""
    mask = _floor_mask(stack.shape[1:], region.polygon, erode=max(2, stack.shape[2] // 200))
    v, u = np.nonzero(mask)
    z = stack[:, v, u].astype(np.float64)
    ok = z > 0
    U = np.broadcast_to(u, z.shape)[ok].astype(np.float64)
    V = np.broadcast_to(v, z.shape)[ok].astype(np.float64)
    Z = z[ok]
    plane = np.asarray(region.plane, np.float64)
    if len(Z) < 10:
        return tuple(plane), 0
    tol = max(0.003, 0.005 * float(np.median(Z)))
    u0, v0 = U.mean(), V.mean()  # centred coordinates: well-conditioned
    used = 0
    for _ in range(iterations):
        with np.errstate(divide="ignore", invalid="ignore"):
            r = 1.0 / (plane[0] * U + plane[1] * V + plane[2]) - Z
        inl = np.abs(r) < tol
        if inl.sum() < 10:
            break
        w = Z[inl] ** 2
        A = np.stack([U[inl] - u0, V[inl] - v0, np.ones(int(inl.sum()))], 1) * w[:, None]
        p = np.linalg.lstsq(A, w / Z[inl], rcond=None)[0]
        plane = np.array([p[0], p[1], p[2] - p[0] * u0 - p[1] * v0])
        used = int(inl.sum())
        tol = max(0.0015, 3 * 1.4826 * float(np.median(np.abs(r[inl]))))
    return tuple(float(x) for x in plane), used


def _floor_points(depth: np.ndarray, cam: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """The readings of a depth image as points in world-aligned axes (x, y along the floor,
    origin under the camera) and their heights above the floor."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    p = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    world = p @ cam.rotation()  # rotation() maps world axes to camera axes: its transpose back
    return world[:, :2], world[:, 2] + cam.mount_height


def _bin_walls(depth: np.ndarray, cam: CameraConfig, polygon
               ) -> tuple[np.ndarray, np.ndarray, list[bool], float]:
    """(low corner, high corner, found per side, wall height) of the bin's inside on the
    floor, metres in world-aligned axes (origin under the camera); sides -x, +x, -y, +y.

    `polygon` (the visible floor `find_bin` outlines) is the bin only where the camera sees
    the floor up to the wall: a tilted camera sees over the near walls, which hide a band of
    floor behind them. Seen from above instead (every reading put on the floor with the
    camera's pose) each wall is where it stands, whatever the view: the inner edge of its top
    is the inside's edge. So, for each side, across the middle 60 % of it and outwards from a
    little inside the floor's edge, in bands two pixels' footprint wide: the wall's top is the
    height most of a band reaches at most (the same for every side: their median), and the
    first band where half the points stand that high is the wall. Objects lower than the
    walls, and the flying pixels of a depth camera along the rays that graze a wall's top
    (between its top and the floor behind it, so lower), do not count. A side with no such
    band (the bin partly out of view, no walls) keeps the floor's edge, and says so."""
    xy, height = _floor_points(depth, cam)
    a, b, c = cam.floor_plane()
    poly = np.asarray(polygon, np.float64)
    z = 1.0 / (a * poly[:, 0] + b * poly[:, 1] + c)
    corners = np.stack([(poly[:, 0] - cam.cx) / cam.fx * z, (poly[:, 1] - cam.cy) / cam.fy * z,
                        z], 1) @ cam.rotation()
    lo, hi = corners[:, :2].min(0), corners[:, :2].max(0)
    span = hi - lo
    step = 2 * float(np.median(z)) / min(cam.fx, cam.fy)  # two pixels' footprint on the floor
    sides = []  # per side: (axis, sign, search start, band heights)
    for axis in (0, 1):
        other = 1 - axis
        across = np.abs(xy[:, other] - (lo[other] + hi[other]) / 2) < 0.3 * span[other]
        for sign in (-1, 1):
            edge = hi[axis] if sign > 0 else lo[axis]
            start = edge - sign * max(0.005, 0.1 * span[axis])
            out = sign * (xy[across, axis] - start)  # outwards from the search's start
            sel = (out >= 0) & (out < 0.02 + 0.6 * span[axis])
            band = (out[sel] / step).astype(np.intp)
            order = np.argsort(band, kind="stable")
            bands = np.split(height[across][sel][order],
                             np.flatnonzero(np.diff(band[order])) + 1)
            index = np.unique(band)
            sides.append((axis, sign, start, [(k, hb) for k, hb in zip(index, bands)
                                              if len(hb) >= 5]))
    tops = [max((float(np.median(hb)) for _, hb in bands), default=0.0)
            for *_, bands in sides]
    top = float(np.median(tops))
    found = []
    for axis, sign, start, bands in sides:
        wall = [k for k, hb in bands if top >= WALL_MIN_HEIGHT
                and np.mean(hb >= WALL_TOP_FRACTION * top) >= 0.5]
        found.append(bool(wall))
        if wall:
            edge = start + sign * wall[0] * step
            if sign > 0:
                hi[axis] = edge
            else:
                lo[axis] = edge
    return lo, hi, found, top


def estimate_camera(depths, info, near: float = 0.05, far: float = 3.0
                    ) -> tuple[CameraConfig, dict]:
    """The simulator's camera for frames of a user's bin: (CameraConfig, details).

    `depths`: depth frames in metres (0 or NaN = no reading) of one bin seen by one fixed
    camera, objects in it moving between frames (a handful to a few dozen; more frames, less
    of the floor hidden); `info`: its `bags.CameraInfo`. The details: "plane" (the floor,
    a, b, c), "bin_region" (`preprocess.BinRegion` found), "bin_inner_size"
    (metres along the camera's world x and y, for a `BinConfig`), "walls_found" (sides -x,
    +x, -y, +y: where False the size comes from the floor seen, not a wall), "wall_height"
    (metres, the walls' top above the floor), "floor_pixels" (readings the plane was fitted
    to), "frames", and "noise" (the `NoiseConfig` its frames show, `noise_fit.estimate_noise`;
    what was measured: "noise_measured"). Raises ValueError naming what is wrong:
    no frames, frames of another size than the camera info, no bin floor, a tilt above 45
    degrees, a pose the simulator cannot take."""
    K = np.asarray(info.K, np.float64).reshape(3, 3)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    if not (fx > 0 and fy > 0):
        raise ValueError(f"camera info K has focal lengths fx={fx}, fy={fy}; valid: > 0 (a "
                         "calibrated camera)")
    stack = _stack(depths, info)
    emptier = _percentile_image(stack, 80)  # the walls stand still, objects come and go
    try:
        region = preprocess.find_bin(emptier)
    except ValueError as e:
        raise ValueError(f"no bin floor found in {len(stack)} frame(s): {e}; "
                         "valid: frames of a bin seen from above, its floor in view") from None
    plane, used = _refine_plane(stack, region)
    h, tilt, roll = pose_from_plane(plane, fx, fy, cx, cy)
    if tilt > MAX_TILT:
        raise ValueError(f"the bin floor is tilted {tilt:.1f} degrees from the camera's view; "
                         f"valid: at most {MAX_TILT:g} (a camera looking down into the bin)")
    if not near < h < far:
        raise ValueError(f"the camera is {h:.3f} m above the bin floor; valid: between near "
                         f"{near} and far {far} m")
    cam = CameraConfig(width=int(info.width), height=int(info.height), fx=fx, fy=fy, cx=cx,
                       cy=cy, mount_height=h, near=near, far=far, tilt=tilt, roll=roll)
    lo, hi, found, wall = _bin_walls(emptier, cam, region.polygon)
    centre = cam.rotation() @ np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, -h])
    u, v = fx * centre[0] / centre[2] + cx, fy * centre[1] / centre[2] + cy
    offset = ((u - cx) / cam.width, (v - cy) / cam.height)
    try:
        cam = CameraConfig(**{**cam.to_dict(), "bin_offset": offset})
    except ValueError as e:
        raise ValueError(f"the bin's centre at pixel ({u:.0f}, {v:.0f}) gives no simulator "
                         f"camera: {e}") from None
    noise, measured = estimate_noise(stack, plane, _floor_mask(
        stack.shape[1:], region.polygon, erode=max(2, stack.shape[2] // 200)), fx)
    return cam, {"plane": plane, "bin_region": region, "frames": len(stack),
                 "bin_inner_size": (float(hi[0] - lo[0]), float(hi[1] - lo[1])),
                 "walls_found": found, "wall_height": wall, "floor_pixels": used,
                 "noise": noise, "noise_measured": measured}


def camera_from_bag(path, depth_topic: str | None = None, frames: int = 30
                    ) -> tuple[CameraConfig, dict, str]:
    """`estimate_camera` on the first `frames` depth frames of a bag and the CameraInfo beside
    them -> (camera, details, one line saying what was found). Raises ValueError when the bag
    has no CameraInfo (no intrinsics to simulate with)."""
    from inseggan_ros.io.bags import read_frames

    got = list(read_frames(path, depth_topic=depth_topic, limit=frames))
    info = next((f.camera_info for f in reversed(got) if f.camera_info is not None), None)
    if info is None:
        raise ValueError(f"{path}: no sensor_msgs/CameraInfo beside the depth topic, so no "
                         "intrinsics to simulate with; valid: a bag with a "
                         "sensor_msgs/CameraInfo beside the depth topic, or --camera PRESET")
    cam, est = estimate_camera([f.metres() for f in got], info)
    size = est["bin_inner_size"]
    line = (f"camera from {path} ({est['frames']} frames): {cam.width}x{cam.height} "
            f"fx {cam.fx:.1f} fy {cam.fy:.1f} cx {cam.cx:.1f} cy {cam.cy:.1f}, mount height "
            f"{cam.mount_height:.4f} m, tilt {cam.tilt:.2f} deg, roll {cam.roll:.2f} deg, bin "
            f"offset ({cam.bin_offset[0]:.3f}, {cam.bin_offset[1]:.3f}), bin inner size "
            f"{size[0]:.3f} x {size[1]:.3f} m"
            + ("" if all(est["walls_found"]) else " (walls not all in view: from the floor seen)"))
    return cam, est, line
