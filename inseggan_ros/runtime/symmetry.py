"""The 8 symmetries of the square image (the dihedral group D4) and what they do to poses.

Test-time augmentation: the encoder also reads the input mirrored and transposed, and its poses
there map back to the input exactly (`transform_poses`), giving genuinely different starting
points for the pose fit (`refine.start_poses`) and augmented training pairs (`distill`).
"""
from __future__ import annotations

import torch

# The 8 symmetries of the square image (the dihedral group D4) as (flip x, flip y, transpose):
# the identity, the 3 mirror images, then the same transposed (x and y swapped).
SYMMETRIES = tuple((fx, fy, tr) for tr in (False, True)
                   for fx, fy in ((False, False), (True, False), (False, True), (True, True)))


def transform_image(x: torch.Tensor, sym: tuple[bool, bool, bool]) -> torch.Tensor:
    """(..., H, W) images -> the same under the symmetry `sym` (mirrored, then transposed)."""
    fx, fy, tr = sym
    x = torch.flip(x, [d for d, f in ((-1, fx), (-2, fy)) if f]) if fx or fy else x
    return x.transpose(-1, -2) if tr else x


def symmetry_matrix(sym: tuple[bool, bool, bool]) -> torch.Tensor:
    """The signed permutation of x and y (3 x 3, height unchanged) that `sym` applies."""
    fx, fy, tr = sym
    S = torch.diag(torch.tensor([-1.0 if fx else 1.0, -1.0 if fy else 1.0, 1.0]))
    return S[[1, 0, 2]] if tr else S


def map_poses(pose: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    """(..., 6) poses -> axis S a and translation S t (S (..., 3, 3), broadcast)."""
    from inseggan_ros.runtime.model import pose_from_axis, rodrigues

    axis = rodrigues(pose.reshape(-1, 6)[:, :3])[:, :, 0].reshape(*pose.shape[:-1], 3)
    return pose_from_axis((S @ axis[..., None])[..., 0], (S @ pose[..., 3:, None])[..., 0])


def map_rotations(pose: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
    """(..., 6) poses of any template -> rotation S R M and translation S t, M = diag(det S,
    1, 1): the pose of the body mirrored by S when the template is symmetric under M (a mirror
    image is not a pose, but a template symmetric in its own x, as the convex template's
    starting box is about its centre, mirrored by S is the same template turned: S R M). For a
    template without that symmetry the result is still a proper rotation near the mirrored
    pose: a starting point, which the fit keeps only if it explains the input best."""
    from inseggan_ros.runtime.model import rodrigues

    shape = pose.shape[:-1]
    S = S.expand(*shape, 3, 3) if S.dim() == 2 else S.expand(*shape, 3, 3)
    R = rodrigues(pose.reshape(-1, 6)[:, :3]).reshape(*shape, 3, 3)
    det = torch.linalg.det(S)
    M = torch.diag_embed(torch.stack([det, torch.ones_like(det), torch.ones_like(det)], -1))
    w = matrix_to_rotvec((S @ R @ M).reshape(-1, 3, 3)).reshape(*shape, 3)
    return torch.cat([w, (S @ pose[..., 3:, None])[..., 0]], -1)


def matrix_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) rotation matrices -> (M, 3) axis-angle vectors (angles in [0, pi]), through
    the quaternion (Shepperd's method: the branch with the largest pivot, stable everywhere)."""
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    d = torch.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], 1)
    k = d.argmax(1)
    a = R[:, 2, 1] - R[:, 1, 2]
    b = R[:, 0, 2] - R[:, 2, 0]
    c = R[:, 1, 0] - R[:, 0, 1]
    xy, xz, yz = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]
    r = torch.sqrt((1 + 2 * d.gather(1, k[:, None])[:, 0] - tr).clamp_min(1e-12))  # 4 |q_k| ...
    q = torch.stack([  # (w, x, y, z) for each branch, times 2 r
        torch.stack([r * r, a, b, c], 1),
        torch.stack([a, r * r, xy, xz], 1),
        torch.stack([b, xy, r * r, yz], 1),
        torch.stack([c, xz, yz, r * r], 1)], 1)[torch.arange(len(R)), k]
    q = q / q.norm(dim=1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    v = q[:, 1:]
    s = v.norm(dim=1, keepdim=True)
    angle = 2 * torch.atan2(s, q[:, :1])
    return torch.where(s > 1e-8, v / s.clamp_min(1e-12) * angle, 2 * v)


def transform_poses(pose: torch.Tensor, sym: tuple[bool, bool, bool],
                    inverse: bool = False) -> torch.Tensor:
    """(..., 6) poses in an image -> the poses that render `transform_image(image, sym)`; with
    `inverse`, poses estimated on the transformed image -> poses in the original.

    The symmetry is a signed permutation S of x and y; the rod's axis a and translation t map to
    S a and S t (height unchanged). The templates are solids of revolution about their axis, so
    the axis is all of the rotation that shows (`model.pose_from_axis`), and the mapping is exact
    for any template, asymmetric ones (a bolt's head) included."""
    S = symmetry_matrix(sym)
    return map_poses(pose, (S.T if inverse else S).to(pose))
