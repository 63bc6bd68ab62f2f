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
    from .model import pose_from_axis, rodrigues

    axis = rodrigues(pose.reshape(-1, 6)[:, :3])[:, :, 0].reshape(*pose.shape[:-1], 3)
    return pose_from_axis((S @ axis[..., None])[..., 0], (S @ pose[..., 3:, None])[..., 0])


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
