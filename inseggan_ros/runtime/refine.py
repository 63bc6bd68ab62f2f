"""Test-time pose fitting: analysis by synthesis with the generator frozen.

The encoder's poses (`start_poses`: from the input and its 7 symmetric images, plus jittered
ones) are fitted to the input (`refine_poses`): Levenberg-Marquardt on each instance's
translation and axis direction against a pyramid L1 of the z-buffered render (`_lm_fit`), with the
least visible instance moved onto unexplained parts of the input between rounds (`_reseed`), and
of several starting points the best-fitting kept. Generators without explicit poses (the learned
renderer) get a few Adam steps on their codes instead (`refine`).
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt, label

from inseggan_ros.runtime.pyramid import pool2x2, pyramid_l1
from inseggan_ros.runtime.model import SphereGenerator, pose_from_axis, rodrigues
from inseggan_ros.runtime.symmetry import (
    SYMMETRIES, map_poses, map_rotations, symmetry_matrix, transform_image)


def _adam_fit(param: torch.Tensor, loss_of, steps: int, lr: float,
              betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> torch.Tensor:
    """`steps` Adam steps on a copy of `param` minimising loss_of(param); -> the result.

    Adam written out for the one small tensor (the update of torch.optim.Adam, in its order of
    operations): torch's optimizer costs about 0.65 ms a step in bookkeeping here, these few
    tensor operations a tenth of that."""
    param = param.detach().clone().requires_grad_(True)
    m, v = torch.zeros_like(param), torch.zeros_like(param)
    b1, b2 = betas
    with torch.enable_grad():
        for t in range(1, steps + 1):
            grad, = torch.autograd.grad(loss_of(param), param)
            with torch.no_grad():
                m.lerp_(grad, 1 - b1)
                v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
                denom = (v.sqrt() / math.sqrt(1 - b2 ** t)).add_(eps)
                param.addcdiv_(m, denom, value=-lr / (1 - b1 ** t))
    return param.detach()


def refine(G, z: torch.Tensor, x: torch.Tensor, steps: int, lr: float = 0.05,
           levels: int = 3) -> torch.Tensor:
    """Analysis by synthesis at test time, for generators without explicit poses: a few Adam
    steps on the codes so that the frozen generator's composite matches the input better
    (pyramid L1), starting from E(x). Each frame's codes are optimised on their own (the loss is
    a sum over frames)."""
    return _adam_fit(z, lambda z_: pyramid_l1(G(z_), x, levels) * len(x), steps, lr)


def _coords(i: torch.Tensor, size: int) -> torch.Tensor:
    return (i.float() + 0.5) / size * 2 - 1


@torch.no_grad()
def _reseed(G, pose: torch.Tensor, target: torch.Tensor, min_pixels: int) -> torch.Tensor:
    """Move poorly used instances onto the parts of the input that no render explains (objects
    the encoder missed, while two renders share another object or one sank out of sight).

    Unexplained blobs are taken largest first; each gets the least visible instance not moved
    yet, if that instance explains fewer pixels than the blob has. A moved instance keeps its
    rotation and takes the median height of the frame's visible instances, so that it shows."""
    size, n = target.shape[-1], pose.shape[1]
    singles = G.render_poses(pose, size)  # (B, n, s, s)
    top, idx = singles.max(dim=1)
    missing = ((target[:, 0] - top) > 0.25).cpu().numpy()  # object here, nothing rendered
    drawn = top > -0.95
    pose = pose.clone()
    for b in range(len(pose)):
        blobs, count = label(missing[b])
        if count == 0:
            continue
        sizes = np.bincount(blobs.ravel())[1:]
        won = [int(((idx[b] == k) & drawn[b]).sum()) for k in range(n)]
        visible = [k for k in range(n) if won[k] > 0]
        z_typical = float(pose[b, visible, 5].median()) if visible else float(pose[b, :, 5].max())
        candidates = sorted(range(n), key=lambda k: won[k])
        for blob_id in np.argsort(-sizes):
            if sizes[blob_id] < min_pixels or not candidates:
                break
            k = candidates.pop(0)
            if won[k] >= sizes[blob_id]:
                break
            dist = distance_transform_edt(blobs == blob_id + 1)
            r, c = np.unravel_index(int(dist.argmax()), dist.shape)
            pose[b, k, 3] = _coords(torch.tensor(c), size)
            pose[b, k, 4] = _coords(torch.tensor(r), size)
            pose[b, k, 5] = z_typical
    return pose


# How far the jittered starting points of multi-start refinement lie from the encoder's poses:
# axis-angle (radians) and translation (x, y, height; image half-widths).
HYPOTHESIS_JITTER = (0.6, 0.6, 0.6, 0.12, 0.12, 0.05)


@torch.no_grad()
def start_poses(G, E, x: torch.Tensor, hypotheses: int = 1) -> torch.Tensor:
    """(B, 1, 64, 64) inputs -> (B, H, n, 6) starting poses for `refine_poses`.

    Hypothesis 0 is the encoder's estimate. The next (up to 7) are its estimates on the input
    under the other symmetries of the square (`SYMMETRIES`: the 3 mirror images, then the 4
    transposed ones), mapped back: test-time augmentation that gives genuinely different
    guesses. Any more are the earlier ones jittered by HYPOTHESIS_JITTER (a fixed random draw:
    deterministic). Measured on 100 cylinder validation frames, 30 steps: mIoU 0.742 with 4
    jittered starts, 0.754 with the 4 mirrors; without refinement, the best-fitting start, 3
    smoothing iterations: 0.740 of the 4 mirrors, 0.756 of all 8 symmetries
    (docs/experiments.md)."""
    if hypotheses < 1:
        raise ValueError(f"hypotheses must be >= 1, got {hypotheses}")
    B = len(x)
    syms = SYMMETRIES[:hypotheses]
    codes = E(torch.cat([transform_image(x, sym) for sym in syms]))  # one encoder pass
    pose = G.pose(codes.reshape(-1, codes.shape[-1])).reshape(len(syms), B, codes.shape[1], 6)
    back = torch.stack([symmetry_matrix(sym).T for sym in syms]).to(pose)  # the inverses
    from inseggan_ros.runtime.model import ConvexGenerator

    mapping = map_rotations if isinstance(G, ConvexGenerator) else map_poses  # any rotation
    pose = torch.cat([pose[:1], mapping(pose[1:], back[1:, None, None])]).transpose(0, 1)
    extra = hypotheses - len(syms)
    if extra > 0:
        gen = torch.Generator().manual_seed(0)
        base = pose[:, torch.arange(extra) % len(syms)]
        jitter = torch.randn(base.shape, generator=gen) * torch.tensor(HYPOTHESIS_JITTER)
        pose = torch.cat([pose, base + jitter.to(pose)], 1)
    return pose


# Levenberg-Marquardt refinement. An instance's unknowns: its translation (x, y, height) and
# the direction of its axis, turned about the vertical (yaw) or tilted out of the floor plane
# (elevation); the templates are solids of revolution about that axis, so nothing else of the
# rotation shows. Jacobian columns: x, y and yaw from the render's own image gradient (they move
# the render rigidly); height and elevation by finite differences of LM_EPS. The IRLS weights
# 1 / |residual| (an L1 fit) are floored at LM_IRLS_FLOOR.
LM_EPS = 0.01
LM_IRLS_FLOOR = 0.02
LM_DAMPING, LM_DOWN, LM_DAMPING_MIN = 1e-2, 0.3, 1e-4
LM_CHUNK = 32  # scenes (frames x hypotheses) per batch of perturbed renders: bounds memory
SWAP_CHUNK = 1 << 22  # pixels of trial composites per batch of `_swap_in` (16 MB in float32)


def _pyramid_features(img: torch.Tensor, levels: int = 3) -> torch.Tensor:
    """(M, 1, s, s) -> (M, D): the image and its 2x2-average-pooled levels, each divided by its
    side, side by side: the residual vector that `_lm_fit` fits (the pyramid's coarse levels
    pull a misplaced render towards its object, as in `pyramid_l1`)."""
    out = []
    for level in range(levels):
        if level:
            img = pool2x2(img)
        out.append(img.flatten(1) / img.shape[-1])
    return torch.cat(out, 1)


def _rotate(v: torch.Tensor, k: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Vectors v (..., 3) turned about unit axes k (..., 3) by `angle` (...) (Rodrigues)."""
    c, s = torch.cos(angle)[..., None], torch.sin(angle)[..., None]
    return v * c + torch.cross(k, v, dim=-1) * s + k * (k * v).sum(-1, keepdim=True) * (1 - c)


def _tilt_axes(axis: torch.Tensor) -> torch.Tensor:
    """The horizontal unit vectors normal to `axis` (..., 3): turning about one tilts the axis
    out of the floor plane. For a vertical axis, x."""
    k = torch.stack([-axis[..., 1], axis[..., 0], torch.zeros_like(axis[..., 0])], -1)
    norm = k.norm(dim=-1, keepdim=True)
    x = torch.zeros_like(axis)
    x[..., 0] = 1
    return torch.where(norm > 1e-6, k / norm.clamp_min(1e-12), x)


def _others(singles: torch.Tensor) -> torch.Tensor:
    """(M, n, s, s) renders -> for each instance, the z-buffer of all the others."""
    M, n = singles.shape[:2]
    if n == 1:
        return torch.full_like(singles, -1.0)
    top2, top_idx = singles.topk(2, dim=1)
    k = torch.arange(n, device=singles.device).view(1, n, 1, 1)
    return torch.where(top_idx[:, :1] == k, top2[:, 1:], top2[:, :1])


@torch.no_grad()
def _lm_fit(G, pose: torch.Tensor, target_features: torch.Tensor, iters: int, size: int,
            template) -> torch.Tensor:
    """`iters` Levenberg-Marquardt iterations on (M, n, 6) poses, each scene on its own,
    minimising sum |zbuffer(renders) - target| over `_pyramid_features` (an L1 fit, by
    iteratively reweighted least squares). -> (M, n, 6) poses (`pose_from_axis`).

    Every Jacobian column of an instance is taken where it wins the z-buffer against the
    others: its analytic columns on the pixels where it is on top, its finite differences
    z-buffered with the maximum of the others, so occlusion changes are seen. A step is kept
    only where it lowers the scene's loss (then the damping falls), otherwise the damping
    rises; so the loss never rises and every scene is independent of the others in the
    batch."""
    M, n, _ = pose.shape
    axis = rodrigues(pose.reshape(M * n, 6)[:, :3])[:, :, 0].reshape(M, n, 3)
    t = pose[..., 3:]
    grid = G.pixel_grid(size)
    px, py = grid
    pixel = 2.0 / size
    up = torch.zeros_like(axis)
    up[..., 2] = 1
    lift = up * LM_EPS
    eps = torch.full(axis.shape[:-1], LM_EPS, dtype=axis.dtype, device=axis.device)

    def render(a, t_):
        return G.render_axes(a, t_, size, template, grid)

    singles = render(axis, t)  # (M, n, s, s)
    current = _pyramid_features(singles.amax(1, keepdim=True))
    residual = current - target_features
    loss = residual.abs().sum(1)
    damping = torch.full((M,), LM_DAMPING, dtype=pose.dtype, device=pose.device)
    for _ in range(iters):
        others = _others(singles)
        pad = F.pad(singles, (1, 1, 1, 1), mode="replicate")
        gx = (pad[..., 1:-1, 2:] - pad[..., 1:-1, :-2]) / (2 * pixel)
        gy = (pad[..., 2:, 1:-1] - pad[..., :-2, 1:-1]) / (2 * pixel)
        yaw = gx * (py - t[..., 1, None, None]) - gy * (px - t[..., 0, None, None])
        rigid = torch.stack([-gx, -gy, yaw], 2) * (singles >= others)[:, :, None]
        J_rigid = _pyramid_features(rigid.reshape(-1, 1, size, size)).reshape(M, n, 3, -1)
        tilt = _tilt_axes(axis)
        moved = render(torch.stack([axis, _rotate(axis, tilt, eps)], 2).reshape(M, 2 * n, 3),
                       torch.stack([t + lift, t], 2).reshape(M, 2 * n, 3))
        comp = torch.maximum(moved.reshape(M, n, 2, size, size), others[:, :, None])
        J_fd = (_pyramid_features(comp.reshape(-1, 1, size, size)).reshape(M, n, 2, -1)
                - current[:, None, None]) / LM_EPS
        J = torch.cat([J_rigid, J_fd], 2).reshape(M, 5 * n, -1)  # x, y, yaw, height, elevation
        w = 1 / residual.abs().clamp_min(LM_IRLS_FLOOR)
        Jw = J * w[:, None]
        A = Jw @ J.transpose(1, 2)
        g = (Jw * residual[:, None]).sum(2)
        A = A + torch.diag_embed(damping[:, None] * torch.diagonal(A, dim1=1, dim2=2) + 1e-6)
        step = torch.linalg.solve(A, -g[..., None])[..., 0].reshape(M, n, 5)
        new_t = t + torch.stack([step[..., 0], step[..., 1], step[..., 3]], -1)
        new_axis = _rotate(_rotate(axis, tilt, step[..., 4]), up, step[..., 2])
        new_axis = new_axis / new_axis.norm(dim=-1, keepdim=True)
        new_singles = render(new_axis, new_t)
        new_current = _pyramid_features(new_singles.amax(1, keepdim=True))
        new_loss = (new_current - target_features).abs().sum(1)
        better = new_loss < loss  # NaN from a singular step is never better
        axis = torch.where(better[:, None, None], new_axis, axis)
        t = torch.where(better[:, None, None], new_t, t)
        singles = torch.where(better[:, None, None, None], new_singles, singles)
        current = torch.where(better[:, None], new_current, current)
        residual = current - target_features
        loss = torch.where(better, new_loss, loss)
        damping = torch.where(better, damping * LM_DOWN, damping * 10).clamp(LM_DAMPING_MIN, 1e4)
    return pose_from_axis(axis, t)


def _composite_loss(composite: torch.Tensor, target: torch.Tensor, levels: int = 3
                    ) -> torch.Tensor:
    """(B K, 1, s, s) composites, K for each frame in turn, (B, 1, s, s) inputs -> (B, K): how
    badly each explains its frame (`pyramid_l1` over 3 levels, per frame; the same numbers,
    with each input's pyramid made once for its K composites instead of K times)."""
    B, s = len(target), target.shape[-1]
    a, b = composite.reshape(B, -1, s, s), target.reshape(B, 1, s, s)
    loss = 0.0
    for level in range(levels):
        if level:
            a, b = pool2x2(a), pool2x2(b)
        loss = loss + (a - b).abs().flatten(2).mean(2)
    return loss / levels


def _fit_loss(G, pose: torch.Tensor, target: torch.Tensor, template) -> torch.Tensor:
    """(B, H, n, 6) poses, (B, 1, s, s) inputs -> (B, H): how badly each hypothesis explains
    its frame (`_composite_loss` of the z-buffered renders at the input's size)."""
    B, H, n, _ = pose.shape
    renders = G.render_poses(pose.reshape(B * H, n, 6), target.shape[-1], template)
    return _composite_loss(G.zbuffer(renders), target)


def _swap_in_chunked(G, pose: torch.Tensor, target: torch.Tensor, template,
                     rounds: int) -> torch.Tensor:
    """`_swap_in` on as many frames at a time as keep its trial composites (B, n, H n, s, s)
    within SWAP_CHUNK pixels: each frame is swapped on its own, so the result is the same as
    in one batch, and the memory no longer grows with the batch (the model export's 50 frames,
    `refine_hypotheses` up to 32)."""
    B, H, n, _ = pose.shape
    per_frame = n * H * n * target.shape[-1] ** 2
    step = max(1, SWAP_CHUNK // per_frame)
    return torch.cat([_swap_in(G, pose[i:i + step], target[i:i + step], template, rounds)
                      for i in range(0, B, step)])


def _swap_in(G, pose: torch.Tensor, target: torch.Tensor, template, rounds: int) -> torch.Tensor:
    """(B, H, n, 6) starting points, (B, 1, s, s) inputs -> (B, n, 6): the best-fitting start,
    into which, `rounds` times, the single instance of any start that lowers the fit loss most
    is swapped for one of its instances (where one lowers it at all). The starts often read
    different parts of a pile right: one the bolt on the left, another the one on the right
    (docs/experiments.md, 2026-11-27). With 0 rounds: the best-fitting start, as
    `_fit_loss(...).argmin` chooses it."""
    B, H, n, _ = pose.shape
    s = target.shape[-1]
    renders = G.render_poses(pose.reshape(B * H, n, 6), s, template)
    loss = _composite_loss(G.zbuffer(renders), target)  # (B, H), as `_fit_loss`
    renders = renders.reshape(B, H, n, s, s)
    frames = torch.arange(B, device=pose.device)
    best = loss.argmin(1)
    cur, cur_r = pose[frames, best].clone(), renders[frames, best].clone()
    cur_loss = loss[frames, best]
    cand, cand_r = pose.reshape(B, H * n, 6), renders.reshape(B, H * n, s, s)
    slots = torch.arange(n, device=pose.device)
    for _ in range(rounds):
        # the composite without instance i (B, n, s, s), then with each candidate in its place
        without = torch.stack([cur_r[:, slots != i].amax(1) for i in range(n)], 1)
        comp = torch.maximum(without[:, :, None], cand_r[:, None])  # (B, n, H n, s, s)
        trial = _composite_loss(comp.reshape(-1, 1, s, s), target)  # (B, n H n)
        trial_loss, which = trial.min(1)
        better = trial_loss < cur_loss
        if not better.any():
            break
        f, slot, c = frames[better], (which // (H * n))[better], (which % (H * n))[better]
        cur[f, slot], cur_r[f, slot] = cand[f, c], cand_r[f, c]
        cur_loss = torch.where(better, trial_loss, cur_loss)
    return cur


@torch.no_grad()
def refine_poses(G, pose: torch.Tensor, x: torch.Tensor, steps: int, reseeds: int = 2,
                 size: int = 32, keep: int = 0, swaps: int = 0) -> torch.Tensor:
    """Analysis by synthesis at test time, on the poses themselves (generators with explicit
    templates): `steps` Levenberg-Marquardt iterations in all (`_lm_fit`) on the n poses of
    each frame so that the z-buffered composite matches the input at size x size (L1 over a
    3-level pyramid), in `reseeds` + 1 rounds; between rounds the least visible instance is
    moved onto the largest unexplained part of the input (`_reseed`).

    `pose`: (B, H, n, 6) starting points (`start_poses`). `keep` (0, the default: all H) of
    them, the best-fitting, are refined side by side; each frame then keeps the one that fits its
    input best (multi-start). Every scene is fitted on its own, so hypothesis 0 follows exactly
    the path it would follow alone and more hypotheses never fit worse. Choosing the start
    before refining (`keep` 1) costs one render per start instead of a refinement per start.
    Levenberg-Marquardt rather than Adam: at equal time it fits better and keeps gaining with
    iterations; fitting each rod's axis, with image-gradient Jacobian columns for x, y and yaw,
    halves its cost at the same quality (docs/experiments.md, 2026-11-21). `swaps`: where the
    best-fitting start is chosen, up to that many single instances of the other starts swapped
    into it, each where it lowers the fit loss (`_swap_in`): with `keep` 1 before the fit, from
    the unfitted starts; else after it, from the fitted ones. -> (B, n, 6) poses."""
    B, H, n, _ = pose.shape
    if steps > 0 and not isinstance(G, SphereGenerator):
        raise ValueError(f"refine_steps {steps}: the Levenberg-Marquardt pose fit moves a rod's "
                         f"axis; the {G.cfg.renderer} template has none yet (refine_steps: 0)")
    template = G.geometry()  # fixed while the poses move: computed once
    target = F.adaptive_avg_pool2d(x, size)
    if keep < 0:
        raise ValueError(f"keep must be >= 0 (0 = all), got {keep}")
    if swaps < 0:
        raise ValueError(f"swaps must be >= 0 (0 = off), got {swaps}")
    if swaps and keep == 1 and H > 1:
        pose, H = _swap_in_chunked(G, pose, target, template, swaps)[:, None], 1
    elif 0 < keep < H:
        best = _fit_loss(G, pose, target, template).argsort(1)[:, :keep]
        pose, H = pose[torch.arange(B)[:, None], best], keep
    flat = pose.reshape(B * H, n, 6)
    if steps > 0:
        features = _pyramid_features(target).repeat_interleave(H, dim=0)
        rounds = reseeds + 1 if steps >= 2 * (reseeds + 1) else 1
        for r in range(rounds):
            iters = steps // rounds + (steps % rounds if r == rounds - 1 else 0)
            flat = torch.cat([_lm_fit(G, flat[i:i + LM_CHUNK], features[i:i + LM_CHUNK], iters,
                                      size, template) for i in range(0, len(flat), LM_CHUNK)])
            if r < rounds - 1:
                flat = _reseed(G, flat, target.repeat_interleave(H, dim=0),
                               min_pixels=max(4, size * size // 150))
    pose = flat.reshape(B, H, n, 6)
    if H == 1:
        return pose[:, 0]
    if swaps:
        return _swap_in_chunked(G, pose, target, template, swaps)
    return pose[torch.arange(B), _fit_loss(G, pose, target, template).argmin(1)]
