"""Image pyramids for the pose fit and the shape fits: 2 x 2 pooling and a pyramid L1."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def pool2x2(x: torch.Tensor) -> torch.Tensor:
    """2 x 2 average pooling of (..., H, W) images with even sides: the same numbers as
    `F.avg_pool2d(x, 2)` (its CPU kernel's sum in its order, then the exact division by 4: bit
    for bit with the PyTorch of requirements.txt, natively and in AVX2 mode), without
    `F.avg_pool2d`'s per-channel cost, which dominates on a CPU for the test-time fit's batches
    of hundreds of single-channel 32 x 32 renders (docs/benchmarks.md). With gradients,
    `F.avg_pool2d`'s own backward is the faster, so `pyramid_l1` keeps it there. Odd sides go
    to `F.avg_pool2d`, which drops the last row or column."""
    if x.shape[-1] % 2 or x.shape[-2] % 2:
        return F.avg_pool2d(x, 2)
    return (((x[..., 0::2, 0::2] + x[..., 0::2, 1::2]) + x[..., 1::2, 0::2])
            + x[..., 1::2, 1::2]) * 0.25


def pyramid_l1(a: torch.Tensor, b: torch.Tensor, levels: int = 1,
               background_weight: float = 1.0, per_frame: bool = False) -> torch.Tensor:
    """Mean L1 over an image pyramid (2x2 average pooling between levels); levels=1 is plain L1.

    The coarse levels see a misplaced object and its target overlap where the fine level does
    not, so a render far from its object still gets pulled towards it. `background_weight`
    weighs the pixels where the target `b` is floor (-1): above 1, drawing an object where there
    is none costs more than missing one, so that an explicit template does not grow to cover
    the objects an imprecise encoder misses. `per_frame`: one loss per frame, (B,), instead of
    their mean."""
    w = None
    if background_weight != 1.0:
        w = torch.where(b <= -1 + 1e-4, background_weight, 1.0)
    pool = (lambda t: F.avg_pool2d(t, 2)) if torch.is_grad_enabled() else pool2x2
    loss = 0.0
    for level in range(levels):
        if level:
            a, b = pool(a), pool(b)
            w = pool(w) if w is not None else None
        err = (a - b).abs() if w is None else w * (a - b).abs()
        loss = loss + (err.flatten(1).mean(1) if per_frame else err.mean())
    return loss / levels
