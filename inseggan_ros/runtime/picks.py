"""Grasp candidates from a segmented depth frame: what a picking robot consumes (no ROS).

Per instance, in the camera's optical frame (x right, y down, z forward; metres):
  * `position`: the centroid of its visible surface as the camera sees it: the mean of its
    pixels' 3D points (from the depth and the intrinsics K), each weighted by its footprint at
    its depth, Z^2 / (fx fy), so the result does not depend on the resolution. A surface seen
    at a grazing angle (the side wall of a standing part) counts by what the camera sees of it,
    not by its full area: that keeps the point on the face a gripper approaches (with full-area
    weights the centroid of a standing cylinder drifts toward its rim: bench_picks, normal
    errors 2x as large);
  * `normal`: the unit normal of the plane fitted (least squares) to the instance's points
    within `normal_radius` of its point nearest the centroid, turned toward the camera. Near
    the centroid, not over the whole instance: a curved part's overall plane says little about
    the surface a suction cup or gripper meets;
  * `area`: its visible surface area (m^2);
  * `occluded`: the fraction of it hidden under other instances, in [0, 1], as the model sees
    it (`occluded_from_scores`), when given;
  * `rise`: how far the highest instance next to it rises above it where the two meet (m; the
    median depths of the two within BAND pixels of their shared boundary): more than
    `free_rise` and that neighbour lies on it. `free` = no such neighbour. Measured from the
    depth itself, so it holds whatever the model's renders do (bench_picks has the figures);
  * `top_depth`: the depth of its highest part (the 5th percentile of its depths), for the order.
The order: free instances first, then within each group the top-most first (smallest
`top_depth`). Instances with fewer than `min_pixels` valid pixels get no pick: their plane is
not determined.

    picks = compute_picks(depth_m, labels, K, occluded=occluded_from_scores(seg.scores))
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inseggan_ros.core.order_stats import median, percentile

# A pixel's surface area grows as 1 / cos(angle between the ray and the normal); below this
# cosine (about 78 degrees) it is capped, so that a few grazing pixels cannot dominate.
MIN_COS = 0.2
# Instances of more pixels than this are sampled on a coarser grid (every s-th pixel).
MAX_PIXELS = 6000
# Pixels either side of a boundary between two instances whose depths `rise` compares.
BAND = 2


@dataclass(frozen=True)
class PickConfig:
    # metres: the patch around the centroid the normal is fitted to. Wider takes in a cylinder's
    # cap rim or a neighbour's edge more often; narrower follows the depth noise (bench_picks)
    normal_radius: float = 0.004
    free_rise: float = 0.003  # metres: a neighbour higher than this where they meet covers it
    min_pixels: int = 20  # fewer valid pixels: no pick
    normal_window: float = 0.004  # metres: side of the window for per-pixel normals (area)
    # compute each pick's visible `area` (NaN when off): the per-pixel normals it needs are
    # about 40 % of the picks' time; the segmenter node publishes no area and turns it off
    areas: bool = True

    def __post_init__(self):
        for name, ok, valid in (
                ("normal_radius", self.normal_radius > 0, "> 0 metres"),
                ("free_rise", self.free_rise >= 0, ">= 0 metres"),
                ("min_pixels", self.min_pixels >= 3, ">= 3"),
                ("normal_window", self.normal_window > 0, "> 0 metres")):
            if not ok:
                raise ValueError(f"pick {name} {getattr(self, name)!r} invalid; valid: {valid}")


@dataclass(frozen=True)
class Pick:
    instance: int  # its label, 1..n
    position: np.ndarray  # (3,) metres, camera frame: the visible surface's centroid
    normal: np.ndarray  # (3,) unit, toward the camera (normal . position < 0)
    area: float  # m^2 of visible surface (NaN where PickConfig.areas is off)
    occluded: float  # fraction hidden under other instances, 0..1 (the model's; 0 if unknown)
    rise: float  # metres the highest neighbour rises above it where they meet (-inf: none)
    free: bool  # rise <= PickConfig.free_rise: nothing on top of it
    top_depth: float  # metres: the depth of its highest part
    pixels: int  # valid pixels it was computed from
    # quaternion (x, y, z, w) of its pose where it was moved to another frame
    # (`transform_picks`); None: the camera's, from `normal`
    rotation: np.ndarray | None = None

    def orientation(self) -> np.ndarray:
        """Quaternion (x, y, z, w) of a frame whose z axis is `normal` and whose x axis is the
        camera's x axis projected onto the surface (the camera's y axis where x is normal);
        in another frame (`transform_picks`) that same pose, expressed there."""
        if self.rotation is not None:
            return np.asarray(self.rotation, float)
        return quaternion_from_matrix(frame_from_normal(self.normal))


def frame_from_normal(normal: np.ndarray) -> np.ndarray:
    """3 x 3 rotation whose columns are x, y, z with z = `normal` (unit)."""
    z = np.asarray(normal, float) / np.linalg.norm(normal)
    ref = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a 3 x 3 rotation matrix: scipy's Rotation.from_matrix(R)
    .as_quat() (the same branch on the largest of the diagonal and the trace, the same sign),
    written out for one matrix, without the checks and array set-up that outweigh it there."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, float).tolist()
    trace = a + e + i
    choice = max(range(4), key=(a, e, i, trace).__getitem__)  # the first of equal ones
    if choice == 0:
        q = (1 - trace + 2 * a, d + b, g + c, h - f)
    elif choice == 1:
        q = (d + b, 1 - trace + 2 * e, h + f, c - g)
    elif choice == 2:
        q = (g + c, h + f, 1 - trace + 2 * i, d - b)
    else:
        q = (h - f, c - g, d - b, 1 + trace)
    q = np.array(q)
    return q / np.linalg.norm(q)


# A target_rotation whose norm is further than this from 1 is refused (a typo, or the
# components in another order); within it, it is normalised.
QUATERNION_TOLERANCE = 1e-3


def check_transform(translation, rotation) -> tuple[np.ndarray, np.ndarray]:
    """A camera-to-target transform as parameters give it -> (translation (3,), unit quaternion
    (x, y, z, w)); raises ValueError naming what is wrong and what is valid."""
    t, q = np.asarray(list(translation), float), np.asarray(list(rotation), float)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ValueError(f"target_translation {list(translation)} invalid; valid: [x, y, z], "
                         "three finite numbers (metres: the camera frame's origin in the "
                         "target frame)")
    if q.shape != (4,) or not np.isfinite(q).all():
        raise ValueError(f"target_rotation {list(rotation)} invalid; valid: [x, y, z, w], four "
                         "finite numbers (a unit quaternion: the camera frame's orientation in "
                         "the target frame)")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"target_rotation {list(rotation)} invalid: its norm is {norm:.6f}; "
                         f"valid: a unit quaternion [x, y, z, w] (norm within "
                         f"{QUATERNION_TOLERANCE:g} of 1; [0, 0, 0, 1] = no rotation)")
    return t, q / norm


def transform_picks(picks: list[Pick], translation, rotation) -> list[Pick]:
    """`picks` (camera frame) in a target frame where the camera frame has the pose
    (`translation` (3,) metres, `rotation` unit quaternion (x, y, z, w)), as tf gives the
    transform target <- camera: a point p moves to R p + t, the normal to R n, the pick's pose
    (`Pick.orientation`) to R times it. The measures that belong to the camera (top_depth,
    rise, area) are kept as they are."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    R, t = Rotation.from_quat(rotation), np.asarray(translation, float)
    return [replace(p, position=R.apply(p.position) + t, normal=R.apply(p.normal),
                    rotation=(R * Rotation.from_quat(p.orientation())).as_quat())
            for p in picks]


def check_intrinsics(K, shape: tuple[int, int] | None = None) -> np.ndarray:
    """K as a 3 x 3 float array; raises ValueError naming what is wrong."""
    K = np.asarray(K, float)
    if K.size != 9:
        raise ValueError(f"camera matrix K has {K.size} values; valid: 9 (3 x 3, row-major)")
    K = K.reshape(3, 3)
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1:
        raise ValueError(f"camera matrix K {K.reshape(-1).tolist()} invalid; valid: fx > 0, "
                         "fy > 0, K[2][2] = 1 (an uncalibrated camera reports zeros)")
    return K


def rays(K: np.ndarray, shape: tuple[int, int], origin: tuple[int, int] = (0, 0)
         ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates x = (u - cx) / fx, y = (v - cy) / fy of every pixel of an
    image of `shape` (or of its crop of that shape whose top-left pixel is `origin`, (row,
    column)): a pixel of depth Z is the point (x Z, y Z, Z). (Skew K[0, 1] is taken into
    account.)"""
    h, w = shape
    v, u = np.mgrid[origin[0]:origin[0] + h, origin[1]:origin[1] + w].astype(np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return x, y


def points(depth_m: np.ndarray, K) -> np.ndarray:
    """(H, W) depth in metres -> (H, W, 3) points in the camera frame (0 depth -> 0 point)."""
    K = check_intrinsics(K)
    x, y = rays(K, depth_m.shape)
    z = np.nan_to_num(np.asarray(depth_m, np.float64))
    return np.stack([x * z, y * z, z], -1)


def _box_sum(a: np.ndarray, k: int) -> np.ndarray:
    """Sum over a k x k window at every pixel (zero outside the image)."""
    import cv2

    return cv2.boxFilter(a, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)


def plane_normal(pts: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The unit normal of the least-squares plane through (N, 3) points, toward the camera
    (its dot product with the points' mean is negative)."""
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, float)
    mean = (pts * w[:, None]).sum(0) / w.sum()
    d = pts - mean
    cov = (d * w[:, None]).T @ d
    n = np.linalg.eigh(cov)[1][:, 0]  # the eigenvector of the smallest eigenvalue
    return -n if n @ mean > 0 else n


def pixel_normals(P: np.ndarray, mask: np.ndarray, window: int) -> np.ndarray:
    """(H, W, 3) unit normals, toward the camera, of the plane Z = a X + b Y + c fitted (least
    squares, closed form) to the masked points in a window x window neighbourhood of each pixel
    (the same instance only); (0, 0, -1) where the fit is not determined (fewer than 3 points
    or all on a line). Only the pixel areas use them: a fit in Z suits surfaces that face the
    camera, and the areas of steep ones are capped anyway (MIN_COS)."""
    m = mask.astype(np.float64)
    X, Y, Z = (P[..., i] * m for i in range(3))
    count = _box_sum(m, window)
    c = np.maximum(count, 1)
    mx, my, mz = (_box_sum(a, window) / c for a in (X, Y, Z))
    sxx = _box_sum(X * X, window) / c - mx * mx
    syy = _box_sum(Y * Y, window) / c - my * my
    sxy = _box_sum(X * Y, window) / c - mx * my
    sxz = _box_sum(X * Z, window) / c - mx * mz
    syz = _box_sum(Y * Z, window) / c - my * mz
    det = sxx * syy - sxy * sxy
    ok = (count >= 3) & (det > 1e-6 * np.maximum(sxx + syy, 1e-30) ** 2)
    det = np.where(ok, det, 1.0)
    a = (sxz * syy - syz * sxy) / det
    b = (syz * sxx - sxz * sxy) / det
    n = np.stack([a, b, -np.ones_like(a)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~ok] = (0.0, 0.0, -1.0)
    return n


def pixel_areas(depth: np.ndarray, normals: np.ndarray, x: np.ndarray, y: np.ndarray,
                K: np.ndarray) -> np.ndarray:
    """Surface area (m^2) each pixel covers: Z^2 / (fx fy) / |n . (x, y, 1)| (its footprint on
    a fronto-parallel plane, grown as the surface turns away from the ray; capped at MIN_COS)."""
    ray = np.stack([x, y, np.ones_like(x)], -1)
    ray_norm = np.linalg.norm(ray, axis=-1)
    cos = np.abs(np.sum(normals * ray, -1)) / ray_norm
    return depth ** 2 / (K[0, 0] * K[1, 1]) / (np.maximum(cos, MIN_COS) * ray_norm)


def rises(depth: np.ndarray, labels: np.ndarray, instances, boxes=None) -> dict[int, float]:
    """{label: how far (m) its highest neighbour rises above it where the two meet}: per pair
    of touching instances, the median depth of this one's pixels within BAND pixels of the
    other minus the other's within BAND pixels of this one; the largest over its neighbours
    (-inf without any). `boxes` ({label: (rows, cols) slices of its pixels}, as
    compute_picks finds them): only the region where two instances' boxes, grown by BAND,
    overlap is read for a pair (the same numbers as over the whole image)."""
    import cv2

    kernel = np.ones((2 * BAND + 1, 2 * BAND + 1), np.uint8)
    valid = depth > 0
    H, W = labels.shape
    if boxes is None:
        boxes = {k: (slice(0, H), slice(0, W)) for k in instances}
    grown = {k: (max(0, b[0].start - BAND), min(H, b[0].stop + BAND),
                 max(0, b[1].start - BAND), min(W, b[1].stop + BAND)) for k, b in boxes.items()}
    out = {}
    for k in instances:
        out[k] = -np.inf
        for j in instances:
            a, b = grown[k], grown[j]
            r0, r1, c0, c1 = max(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), min(a[3], b[3])
            if j == k or r0 >= r1 or c0 >= c1:
                continue
            # the pair's region, grown by BAND more: a dilation there sees every pixel it needs
            R0, R1, C0, C1 = max(0, r0 - BAND), min(H, r1 + BAND), max(0, c0 - BAND), \
                min(W, c1 + BAND)
            win = (slice(R0, R1), slice(C0, C1))
            mk, mj = valid[win] & (labels[win] == k), valid[win] & (labels[win] == j)
            near_j = cv2.dilate(mj.view(np.uint8), kernel).view(bool)
            near_k = cv2.dilate(mk.view(np.uint8), kernel).view(bool)
            mine, theirs = mk & near_j, mj & near_k
            if mine.sum() >= 3 and theirs.sum() >= 3:
                d = depth[win]
                out[k] = max(out[k], float(median(d[mine]) - median(d[theirs])))
    return out


def occluded_from_scores(scores: np.ndarray) -> np.ndarray:
    """segment.Segmentation.scores (the visible share of each instance's single-instance render)
    -> the hidden share, 1 - score, clipped to [0, 1]. An upper bound: the part of a render
    that overhangs its object onto the floor counts as hidden too (`hidden_from_renders` is
    exact where the renders are at hand)."""
    return np.clip(1.0 - np.asarray(scores, float), 0.0, 1.0)


def hidden_from_renders(renders: np.ndarray, labels: np.ndarray, tau: float,
                        scores: np.ndarray | None = None) -> np.ndarray:
    """(n,) the share of each instance's single-instance render (renders[k] >= tau; (n, s, s),
    the model's) on which another instance's label lies (labels (s, s): 0 background, 1..n):
    the part of it hidden under other instances. 0 where it is not drawn at all. (On the 50
    bench_picks scenes it follows the simulator's truth better than 1 - score: correlation
    0.84 against 0.80.) With `scores` (the Segmentation's), an instance that holds pixels but
    scores 0 is a piece split off another (`split_scale`): it has no render of its own, so as
    far as the model knows it may lie under others: 1."""
    renders, labels = np.asarray(renders), np.asarray(labels)
    drawn = renders >= tau
    ks = np.arange(1, len(renders) + 1)[:, None, None]
    under = drawn & (labels[None] > 0) & (labels[None] != ks)
    count = drawn.reshape(len(renders), -1).sum(1)
    hidden = np.where(count > 0, under.reshape(len(renders), -1).sum(1) / np.maximum(count, 1),
                      0.0)
    if scores is not None:
        present = np.bincount(labels.ravel(), minlength=len(renders) + 1)[1:len(renders) + 1] > 0
        hidden = np.where(present & (np.asarray(scores) <= 0), 1.0, hidden)
    return hidden


def compute_picks(depth_m: np.ndarray, labels: np.ndarray, K, occluded=None,
                  cfg: PickConfig = PickConfig()) -> list[Pick]:
    """Picks of every labelled instance (labels 1..n; 0 = background), in pick order.

    `depth_m` (H, W) metres, 0 or NaN = no reading; `K` the 3 x 3 intrinsics of this image
    size; `occluded[k]` the hidden fraction of instance k + 1 (None: every instance counts as
    free, and only the height orders them). Raises ValueError when the sizes do not match.

    Only the labelled pixels' bounding box is read, and each instance's own box within it:
    the cost follows the parts' size, not the frame's (the same numbers as over the whole
    frame)."""
    depth_in, labels = np.asarray(depth_m), np.asarray(labels)
    if depth_in.ndim != 2 or labels.shape != depth_in.shape:
        raise ValueError(f"depth {depth_in.shape} and labels {labels.shape} must be the same "
                         "(H, W) size")
    K = check_intrinsics(K)
    box = _box(labels > 0)
    if box is None:
        return []
    origin = (box[0].start, box[1].start)
    labels = labels[box]
    depth = np.asarray(depth_in[box], np.float64)  # a copy: only the box is converted
    bad = ~np.isfinite(depth)
    if bad.any():
        depth[bad] = 0.0  # NaN and +-inf: no reading
    valid = (depth > 0) & (labels > 0)
    counts = np.bincount(labels[valid].ravel(), minlength=2)
    instances = [int(k) for k in np.flatnonzero(counts) if k > 0 and counts[k] >= cfg.min_pixels]
    if not instances:
        return []
    boxes = _instance_boxes(labels, instances)
    rise = rises(depth, labels, instances, boxes)
    picks = [_pick(k, depth, labels, valid, boxes[k], origin, K, occluded, rise[k], cfg)
             for k in instances]
    return sorted(picks, key=lambda p: (not p.free, p.top_depth))


def _box(mask: np.ndarray):
    """(rows, cols) slices of the bounding box of `mask`'s True pixels, or None."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return None
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def _instance_boxes(labels: np.ndarray, instances) -> dict:
    """{label: (rows, cols) slices of its pixels' bounding box} (scipy.ndimage.find_objects)."""
    from scipy import ndimage

    found = ndimage.find_objects(labels, max_label=max(instances))
    return {k: found[k - 1] for k in instances}


def _pick(k: int, depth, labels, valid, box, origin, K, occluded, rise: float,
          cfg: PickConfig) -> Pick:
    """The pick of instance `k` from its pixels (labels == k within `box` of the frame's
    labelled region, whose top-left pixel is `origin` (row, column) of the frame)."""
    mask = valid[box] & (labels[box] == k)
    rows, cols = np.nonzero(mask)
    pixels = len(rows)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    # the instance's box, every s-th pixel of it where it is large (a pixel then stands for
    # s x s): the cost stays bounded at any resolution
    s = max(1, int(np.sqrt(pixels / MAX_PIXELS)) + 1) if pixels > MAX_PIXELS else 1
    sub = (slice(r0, r1, s), slice(c0, c1, s))
    top = (origin[0] + box[0].start + r0, origin[1] + box[1].start + c0)
    m, dk = mask[sub], depth[box][sub]
    area = np.nan
    if cfg.areas:
        x, y = rays(K, (r1 - r0, c1 - c0), top)
        x, y = x[::s, ::s], y[::s, ::s]
        Pk = np.stack([x * dk, y * dk, dk], -1)
        z = float(np.median(dk[m]))
        window = max(3, int(round(cfg.normal_window * K[0, 0] / z / s)) | 1)
        normals = pixel_normals(Pk, m, window)
        area = float((pixel_areas(dk, normals, x, y, K)[m] * (s * s)).sum())
        pts, zs = Pk[m], dk[m]
    else:  # the same points, from the instance's pixels alone (`rays`' arithmetic)
        mr, mc = (rows - r0, cols - c0) if s == 1 else np.nonzero(m)
        v, u = (top[0] + mr * s).astype(np.float64), (top[1] + mc * s).astype(np.float64)
        y = (v - K[1, 2]) / K[1, 1]
        x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
        zs = dk[mr, mc]
        pts = np.stack([x * zs, y * zs, zs], 1)
    centroid, normal = _surface(pts, zs, cfg.normal_radius)
    occ = 0.0 if occluded is None or k > len(occluded) else float(occluded[k - 1])
    return Pick(instance=k, position=centroid, normal=normal, area=area,
                occluded=occ, rise=rise, free=rise <= cfg.free_rise,
                top_depth=float(percentile(zs, 5)), pixels=pixels)


def _surface(pts: np.ndarray, zs: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points of an instance and their depths -> (its centroid, each point weighted by
    its footprint Z^2 (/ fx fy, the same for all: left out), the unit normal of the plane
    fitted to its points within `radius` of its point nearest the centroid (at least 3)).
    Per coordinate on contiguous columns: the numbers of the (N, 3) array's reductions, up to
    the order of the centroid's sums."""
    footprint = zs ** 2
    px, py, pz = (np.ascontiguousarray(pts[:, i]) for i in range(3))
    total = footprint.sum()
    centroid = np.array([np.dot(footprint, c) for c in (px, py, pz)]) / total
    dist = np.sqrt((px - centroid[0]) ** 2 + (py - centroid[1]) ** 2 + (pz - centroid[2]) ** 2)
    near = dist <= dist.min() + radius
    if near.sum() < 3:
        near = dist <= np.sort(dist)[2]
    return centroid, plane_normal(pts[near], footprint[near])
