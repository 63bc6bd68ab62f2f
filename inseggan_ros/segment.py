"""Inference: depth frame -> instance labels, masks, reconstruction, per-instance scores (no ROS).

The paper's recipe: E(x) -> n codes; every code rendered alone, G_r(F(z_i)); each render median-
and Gaussian-filtered; per pixel the instance whose render is nearest the camera (largest height)
wins (z-buffer); a pixel is background where every render is below the threshold tau. Labels are
made at the model's 64 x 64 and mapped back to the input's pixels, on input foreground only.
tau is calibrated on validation data and stored in the checkpoint (no per-object hand tuning).

    seg = Segmenter.from_checkpoint("models/cylinder/model.pt")
    out = seg(depth_m)            # any resolution, metres; 0 = no reading
    out.labels, out.masks, out.reconstruction, out.scores
"""
from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

TAU_GRID = tuple(np.round(np.linspace(-0.95, 0.5, 30), 3))


def _median3(x: torch.Tensor) -> torch.Tensor:
    """3x3 median filter of (M, 1, H, W)."""
    patches = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3)
    return patches.median(dim=1).values.reshape(x.shape)


def _gauss(x: torch.Tensor, sigma: float = 0.8) -> torch.Tensor:
    r = torch.arange(-2, 3, dtype=x.dtype, device=x.device)
    k = torch.exp(-r ** 2 / (2 * sigma ** 2))
    k = k / k.sum()
    x = F.conv2d(F.pad(x, (2, 2, 0, 0), mode="replicate"), k.view(1, 1, 1, 5))
    return F.conv2d(F.pad(x, (0, 0, 2, 2), mode="replicate"), k.view(1, 1, 5, 1))


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
    from .losses import pyramid_l1

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
    from scipy.ndimage import distance_transform_edt, label

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
# The 8 symmetries of the square image (the dihedral group D4) as (flip x, flip y, transpose):
# the identity, the 3 mirror images, then the same transposed (x and y swapped).
SYMMETRIES = tuple((fx, fy, tr) for tr in (False, True)
                   for fx, fy in ((False, False), (True, False), (False, True), (True, True)))


def transform_image(x: torch.Tensor, sym: tuple[bool, bool, bool]) -> torch.Tensor:
    """(..., H, W) images -> the same under the symmetry `sym` (mirrored, then transposed)."""
    fx, fy, tr = sym
    x = torch.flip(x, [d for d, f in ((-1, fx), (-2, fy)) if f]) if fx or fy else x
    return x.transpose(-1, -2) if tr else x


def _symmetry_matrix(sym: tuple[bool, bool, bool]) -> torch.Tensor:
    """The signed permutation of x and y (3 x 3, height unchanged) that `sym` applies."""
    fx, fy, tr = sym
    S = torch.diag(torch.tensor([-1.0 if fx else 1.0, -1.0 if fy else 1.0, 1.0]))
    return S[[1, 0, 2]] if tr else S


def _map_poses(pose: torch.Tensor, S: torch.Tensor) -> torch.Tensor:
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
    S = _symmetry_matrix(sym)
    return _map_poses(pose, (S.T if inverse else S).to(pose))


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
    back = torch.stack([_symmetry_matrix(sym).T for sym in syms]).to(pose)  # the inverses
    pose = torch.cat([pose[:1], _map_poses(pose[1:], back[1:, None, None])]).transpose(0, 1)
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


def _pyramid_features(img: torch.Tensor, levels: int = 3) -> torch.Tensor:
    """(M, 1, s, s) -> (M, D): the image and its 2x2-average-pooled levels, each divided by its
    side, side by side: the residual vector that `_lm_fit` fits (the pyramid's coarse levels
    pull a misplaced render towards its object, as in `pyramid_l1`)."""
    out = []
    for level in range(levels):
        if level:
            img = F.avg_pool2d(img, 2)
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
    from .model import pose_from_axis, rodrigues

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


def _fit_loss(G, pose: torch.Tensor, target: torch.Tensor, template) -> torch.Tensor:
    """(B, H, n, 6) poses, (B, 1, s, s) inputs -> (B, H): how badly each hypothesis explains
    its frame (`pyramid_l1` of the z-buffered renders at the input's size)."""
    from .losses import pyramid_l1

    B, H, n, _ = pose.shape
    renders = G.render_poses(pose.reshape(B * H, n, 6), target.shape[-1], template)
    return pyramid_l1(G.zbuffer(renders), target.repeat_interleave(H, dim=0), 3,
                      per_frame=True).reshape(B, H)


@torch.no_grad()
def refine_poses(G, pose: torch.Tensor, x: torch.Tensor, steps: int, reseeds: int = 2,
                 size: int = 32, keep: int = 0) -> torch.Tensor:
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
    Levenberg-Marquardt replaced 30 Adam steps (session 5), and in session 6 fitted each rod's
    axis with image-gradient columns, twice as fast (docs/experiments.md). -> (B, n, 6) poses."""
    B, H, n, _ = pose.shape
    template = G.spheres()  # fixed while the poses move: computed once
    target = F.adaptive_avg_pool2d(x, size)
    if keep < 0:
        raise ValueError(f"keep must be >= 0 (0 = all), got {keep}")
    if 0 < keep < H:
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
    return pose[torch.arange(B), _fit_loss(G, pose, target, template).argmin(1)]


@torch.no_grad()
def infer(G, E, x: torch.Tensor, filtered: bool | None = None, refine_steps: int = 0,
          hypotheses: int = 1, keep: int = 0) -> dict:
    """(B, 1, 64, 64) inputs -> single-instance renders (B, n, 64, 64), reconstruction, and the
    codes ("z") or, with test-time refinement, the poses ("pose").

    `filtered` (default: for the learned renderer only, whose renders are noisy; the explicit
    templates render clean edges that a blur would only soften) median- and Gauss-filters
    every render, as the reference code does. `refine_steps`, `hypotheses`, `keep`: test-time
    refinement (`refine_poses` from `start_poses`, also with 0 steps when there are several
    starts to choose from; for the learned renderer `refine` on the codes, from the encoder's
    codes only)."""
    if hasattr(G, "render_poses") and (refine_steps > 0 or hypotheses > 1):
        # the input and its symmetric images through the encoder in one batch
        pose = refine_poses(G, start_poses(G, E, x, hypotheses), x, refine_steps, keep=keep)
        renders = G.render_poses(pose)
        return {"pose": pose, "renders": renders, "reconstruction": G.zbuffer(renders)}
    z = E(x)
    if refine_steps > 0:
        z = refine(G, z, x, refine_steps)
    renders = G.render_instances(z)
    if filtered is None:
        filtered = G.cfg.renderer == "learned"
    if filtered:
        B, n, H, W = renders.shape
        r = renders.reshape(B * n, 1, H, W)
        renders = _gauss(_median3(r)).reshape(B, n, H, W)
    # the explicit templates' composite is the z-buffer of their renders: no second render
    recon = G.zbuffer(renders) if hasattr(G, "render_poses") and not filtered else G(z)
    return {"z": z, "renders": renders, "reconstruction": recon}


def labels_from_renders(renders: torch.Tensor, tau: float, fg: torch.Tensor | None = None,
                        fill: bool = True):
    """z-buffer: (B, n, H, W) renders -> (B, H, W) labels (0 = background, 1..n).

    With the input's foreground `fg`, labels are kept on it only, and (`fill`) a foreground
    pixel that no render reaches (every render below tau there: a slightly too small or
    misplaced render) takes the label of the nearest labelled pixel, so that every object pixel
    gets an instance."""
    top, idx = renders.max(dim=1)
    labels = (idx + 1).to(torch.uint8)
    labels[top < tau] = 0
    if fg is None:
        return labels
    labels[~fg] = 0
    if fill:
        labels = _fill_nearest(labels, fg)
    return labels


@dataclass(frozen=True)
class SmoothConfig:
    """Depth-aware smoothing of the z-buffered labels: mean-field inference in a fully connected
    CRF (Kraehenbuehl and Koltun 2011) restricted to a (2 radius + 1)^2 window. The unary term is
    the model's label (weight 1), the pairwise term a Potts reward for agreeing with neighbours
    of similar height, weight * exp(-dh^2 / 2 sigma_height^2 - dp^2 / 2 sigma_px^2). Labels
    then follow the input's height edges instead of the 64 x 64 render's. iters = 0: off.
    Heights are the model input's units ([-1, 1] over max_height); distances in 64 x 64 pixels."""
    iters: int = 20
    radius: int = 4
    sigma_height: float = 0.2
    sigma_px: float = 2.5
    weight: float = 3.0
    full_res_iters: int = 10  # then at the input's resolution near boundaries (`smooth_full`)

    @property
    def full_res_active(self) -> int:
        """The full-resolution iterations that run: none when smoothing is off."""
        return self.full_res_iters if self.iters else 0

    def __post_init__(self):
        for name, ok, valid in (("iters", self.iters >= 0, ">= 0"),
                                ("full_res_iters", self.full_res_iters >= 0, ">= 0"),
                                ("radius", self.radius >= 1, ">= 1"),
                                ("sigma_height", self.sigma_height > 0, "> 0"),
                                ("sigma_px", self.sigma_px > 0, "> 0"),
                                ("weight", self.weight >= 0, ">= 0")):
            if not ok:
                raise ValueError(f"smoothing {name} {getattr(self, name)!r} invalid; valid: {valid}")


# The encoder's arithmetic at test time: float32, bfloat16 (weights and activations; about 1.3-1.6x
# faster on a CPU that computes it natively, e.g. AVX512-BF16, with the same labels to 0.001 mIoU
# on the sample bags), or auto: bfloat16 where the device computes it natively, else float32.
PRECISIONS = ("float32", "bfloat16", "auto")


def native_bfloat16(device: str) -> bool:
    """Whether `device` computes bfloat16 natively (not emulated: slower than float32)."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()


class CastEncoder(torch.nn.Module):
    """An encoder run in another dtype (a copy of its weights), float32 in and out."""

    def __init__(self, E, dtype: torch.dtype):
        super().__init__()
        import copy

        self.E, self.dtype = copy.deepcopy(E).to(dtype), dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.E(x.to(self.dtype)).float()


@dataclass(frozen=True)
class InferenceConfig:
    """How a model segments at test time: stored with a shipped model (its card gives the
    measured quality and time), overridden by the node's parameters or `inseggan eval` flags.

    refine_steps: Levenberg-Marquardt iterations in all (`refine_poses`; 0 = the starting
    poses as they are); hypotheses: starting points (`start_poses`: the encoder's poses, then
    those on its mirrored and transposed images, then jittered ones); keep: how many of them,
    the best-fitting first, are refined (0 = all); smooth: label smoothing (`SmoothConfig`)."""
    refine_steps: int = 0
    hypotheses: int = 1
    keep: int = 0
    smooth: SmoothConfig = SmoothConfig(iters=0)
    precision: str = "float32"  # the encoder's arithmetic (`PRECISIONS`)

    def __post_init__(self):
        for name, ok, valid in (("refine_steps", self.refine_steps >= 0, ">= 0"),
                                ("hypotheses", self.hypotheses >= 1, ">= 1"),
                                ("keep", self.keep >= 0, ">= 0 (0 = all hypotheses)"),
                                ("precision", self.precision in PRECISIONS, ", ".join(PRECISIONS))):
            if not ok:
                raise ValueError(f"{name} {getattr(self, name)!r} invalid; valid: {valid}")

    def to_dict(self) -> dict:
        return {"refine_steps": self.refine_steps, "hypotheses": self.hypotheses,
                "keep": self.keep, "smooth": asdict(self.smooth), "precision": self.precision}

    @staticmethod
    def from_dict(d: dict) -> "InferenceConfig":
        """From a checkpoint's "inference" record (older ones lack keep, smoothing, precision)."""
        return InferenceConfig(refine_steps=int(d.get("refine_steps", 0)),
                               hypotheses=int(d.get("hypotheses", 1)), keep=int(d.get("keep", 0)),
                               smooth=SmoothConfig(**d.get("smooth", {"iters": 0})),
                               precision=str(d.get("precision", "float32")))

    def with_smoothing(self, iters: int | None = None,
                       full_res_iters: int | None = None) -> "InferenceConfig":
        smooth = self.smooth
        if iters is not None:
            smooth = replace(smooth, iters=int(iters))
        if full_res_iters is not None:
            smooth = replace(smooth, full_res_iters=int(full_res_iters))
        return replace(self, smooth=smooth)


def smooth_labels(labels: torch.Tensor, x: torch.Tensor, n: int,
                  cfg: SmoothConfig = SmoothConfig()) -> torch.Tensor:
    """(B, H, W) labels (0 = background, 1..n) of the (B, 1, H, W) input -> smoothed labels
    (`SmoothConfig`). Background stays background; every foreground pixel keeps a label 1..n.
    The pairwise weights between foreground pixels form one sparse matrix per frame."""
    if cfg.iters == 0:
        return labels
    lab, heights = labels.cpu().numpy(), x[:, 0].float().cpu().numpy()
    out = np.stack([smooth_frame(lab[b], heights[b], n, cfg) for b in range(len(lab))])
    return torch.from_numpy(out).to(labels.device)


def smooth_frame(lab: np.ndarray, h: np.ndarray, n: int, cfg: SmoothConfig) -> np.ndarray:
    """`smooth_labels` of one (H, W) label image with heights `h` (the model input's units).

    Only pixels within 1.5 x radius of another instance's label may change; the others keep
    theirs and only vote (on 100 cylinder validation frames: the same mIoU, 0.820, in half the
    time, 13 ms a frame instead of 26)."""
    import cv2

    rows, cols = np.nonzero(lab > 0)
    if len(rows) == 0 or cfg.iters == 0:
        return lab
    size = 2 * int(np.ceil(1.5 * cfg.radius)) + 1
    lab = np.ascontiguousarray(lab, np.uint8)
    other = np.where(lab > 0, lab, np.iinfo(np.uint8).max).astype(np.uint8)  # background: ignored
    window = np.ones((size, size), np.uint8)  # max and min over it (OpenCV: 7x scipy's speed)
    free = (lab > 0) & (cv2.dilate(lab, window) != cv2.erode(other, window))
    r, (H, W) = cfg.radius, lab.shape
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1].reshape(2, -1)
    keep = (dy != 0) | (dx != 0)
    dy, dx = dy[keep], dx[keep]
    spatial = (cfg.weight * np.exp(-(dy ** 2 + dx ** 2) / (2 * cfg.sigma_px ** 2))).astype(np.float32)
    moving = np.nonzero(free[rows, cols])[0]
    if len(moving) == 0:
        return lab
    # the image padded by r, flattened: a neighbour is the pixel's flat index plus an offset
    Wp = W + 2 * r
    flat = (rows + r) * Wp + cols + r
    index = np.full((H + 2 * r) * Wp, -1, np.int64)  # padded pixel -> its foreground number
    index[flat] = np.arange(len(rows))
    heights = np.zeros((H + 2 * r) * Wp, np.float32)
    heights[flat] = h[rows, cols]
    around = flat[moving, None] + (dy * Wp + dx)  # (M, K) neighbours, flat
    nb = index.take(around)
    dh = heights[flat[moving], None] - heights.take(around)
    w = np.exp(dh * dh * np.float32(-0.5 / cfg.sigma_height ** 2)) * spatial
    w[nb < 0] = 0  # background neighbours do not vote
    K = nb.shape[1]
    with warnings.catch_warnings():  # torch calls its CSR tensors beta; 4x faster than scipy's
        warnings.simplefilter("ignore", UserWarning)
        pair = torch.sparse_csr_tensor(  # one row of K entries per moving pixel
            torch.arange(0, w.size + 1, K), torch.from_numpy(np.maximum(nb, 0).ravel()),
            torch.from_numpy(w.ravel()), size=(len(moving), len(rows)))
    q = torch.from_numpy(np.eye(n, dtype=np.float32)[lab[rows, cols] - 1])  # (P, n) one-hot
    moving_t = torch.from_numpy(moving)
    unary = q[moving_t]
    for _ in range(cfg.iters):
        x = unary + pair @ q
        x = x.sub_(x.amax(1, keepdim=True)).exp_()  # softmax over the labels, written out:
        q[moving_t] = x.div_(x.sum(1, keepdim=True))  # torch.softmax is 4x slower for 5 columns
    out = lab.copy()
    out[rows[moving], cols[moving]] = q[moving_t].argmax(1).numpy() + 1
    return out


# Label smoothing at the input's resolution (`smooth_full`, SmoothConfig.full_res_iters
# iterations), on the pixels near a boundary only, the same height kernel; sigma_px in model
# pixels, the window +-1.9 sigma.
FULL_RES_SIGMA_PX = 1.0
# Regions wider than this many pixels per model pixel are smoothed on a coarser grid (every s-th
# pixel) and upsampled: the cost grows with the square of the window.
FULL_RES_MAX_CELL = 2.1


def smooth_full(labels: np.ndarray, depth_m: np.ndarray, floor_depth: float, max_height: float,
                n: int, cfg: SmoothConfig, model_size: int, roi) -> np.ndarray:
    """Full-resolution labels (upsampled from the model's grid, hence blocky) -> labels whose
    boundaries follow the input's own height edges (`smooth_frame`), on a grid of at most
    FULL_RES_MAX_CELL pixels per model pixel."""
    if cfg.full_res_active == 0 or not labels.any():
        return labels
    ys, xs = np.flatnonzero(labels.any(1)), np.flatnonzero(labels.any(0))  # the labels' box
    Y0, Y1, X0, X1 = ys[0], ys[-1] + 1, xs[0], xs[-1] + 1
    side = max(roi[2] - roi[0], roi[3] - roi[1])
    step = int(np.ceil(side / (FULL_RES_MAX_CELL * model_size)))
    lab = labels[Y0:Y1:step, X0:X1:step]
    d = np.nan_to_num(np.asarray(depth_m, np.float32)[Y0:Y1:step, X0:X1:step])
    h = (floor_depth - d) / max_height * 2 - 1  # the model's units, not clipped
    sigma = FULL_RES_SIGMA_PX * side / step / model_size  # in working pixels
    full_cfg = replace(cfg, iters=cfg.full_res_iters, sigma_px=sigma,
                       radius=max(1, round(1.9 * sigma)))
    smoothed = smooth_frame(lab, h, n, full_cfg)
    out = labels.copy()
    if step == 1:
        out[Y0:Y1, X0:X1] = smoothed
    else:
        up = np.repeat(np.repeat(smoothed, step, 0), step, 1)[:Y1 - Y0, :X1 - X0]
        box = out[Y0:Y1, X0:X1]
        np.copyto(box, up, where=(box > 0) & (up > 0))
    return out


def _fill_nearest(labels: torch.Tensor, fg: torch.Tensor) -> torch.Tensor:
    """`preprocess.fill_labels_nearest` on every frame that has a label and a hole to fill."""
    from .preprocess import fill_labels_nearest

    lab, fgn = labels.cpu().numpy(), fg.cpu().numpy()
    for b in range(len(lab)):
        if (fgn[b] & (lab[b] == 0)).any() and lab[b].any():
            lab[b] = fill_labels_nearest(lab[b], fgn[b])
    return torch.from_numpy(lab).to(labels.device)


def instance_scores(renders: torch.Tensor, labels: torch.Tensor, tau: float) -> torch.Tensor:
    """Visible fraction of each instance: |won pixels| / |rendered pixels| in [0, 1] (B, n).

    1 = nothing lies on top of it (a good first pick), 0 = hidden or not rendered."""
    n = renders.shape[1]
    drawn = (renders >= tau).flatten(2).sum(-1).float()
    won = torch.stack([(labels == k + 1).flatten(1).sum(-1) for k in range(n)], 1).float()
    return torch.where(drawn > 0, won / drawn.clamp_min(1), torch.zeros_like(drawn))


def calibrate_tau(renders: torch.Tensor, fg: torch.Tensor, labels_gt: np.ndarray | None = None,
                  grid=TAU_GRID) -> tuple[float, dict]:
    """Choose tau on validation frames.

    With ground truth: the tau of the best mean mIoU. Without: the tau whose rendered foreground
    (max render >= tau) best matches the input foreground (IoU) - the reconstruction criterion."""
    from .metrics import mean_miou, miou_batch

    scores = {}
    top = renders.max(dim=1).values
    for tau in grid:
        if labels_gt is not None:
            pred = labels_from_renders(renders, tau, fg).cpu().numpy()
            scores[tau] = float(mean_miou(miou_batch(pred, labels_gt)))
        else:
            drawn = top >= tau
            inter = (drawn & fg).flatten(1).sum(-1).float()
            union = (drawn | fg).flatten(1).sum(-1).float().clamp_min(1)
            scores[tau] = float((inter / union).mean())
    best = max(scores, key=lambda t: (scores[t], -abs(t)))
    return float(best), scores


@dataclass
class Segmentation:
    labels: np.ndarray  # (H, W) uint8 at the input resolution, 0 = background
    reconstruction: np.ndarray | None  # (H, W) float32 metres, the model's re-rendered depth
    scores: np.ndarray  # (n,) visible fraction per instance
    labels64: np.ndarray  # (64, 64) at the model's resolution
    x64: np.ndarray  # (64, 64) the model input
    roi: tuple[int, int, int, int]  # the bin region used (x0, y0, x1, y1)
    floor_depth: float  # metres

    @property
    def masks(self) -> np.ndarray:
        """(n, H, W) bool, one per instance: labels == k + 1."""
        n = len(self.scores)
        return self.labels[None] == np.arange(1, n + 1, dtype=np.uint8)[:, None, None]


class Segmenter:
    """A trained model + its preprocessing + tau + its test-time settings (`InferenceConfig`):
    depth frames in, segmentations out."""

    def __init__(self, G, E, model_cfg, prep_cfg, tau: float, device: str = "cpu",
                 inference: InferenceConfig = InferenceConfig()):
        self.G, self.E = G.eval().to(device), E.eval().to(device)
        for p in self.G.parameters():  # test-time refinement optimises codes, never weights
            p.requires_grad_(False)
        self.model_cfg, self.prep_cfg, self.tau, self.device = model_cfg, prep_cfg, tau, device
        self.inference = inference
        self._encoders = {}  # precision -> the encoder that computes in it

    def encoder_changed(self) -> None:
        """Call after changing E's weights: its copies in other precisions are made anew."""
        self._encoders.clear()

    def resolve_precision(self, precision: str) -> str:
        """`PRECISIONS` -> what the encoder computes in: auto is bfloat16 where native."""
        if precision == "auto":
            return "bfloat16" if native_bfloat16(self.device) else "float32"
        return precision

    def encoder(self, precision: str = "float32"):
        """The encoder in `precision` (`PRECISIONS`)."""
        precision = self.resolve_precision(precision)
        if precision == "float32":
            return self.E
        if precision not in self._encoders:
            self._encoders[precision] = CastEncoder(self.E, getattr(torch, precision)).eval()
        return self._encoders[precision]

    @staticmethod
    def from_checkpoint(path, device: str = "auto", tau: float | None = None) -> "Segmenter":
        from .checkpoint import load_for_inference

        return load_for_inference(path, device=device, tau=tau)

    @torch.no_grad()
    def segment_batch(self, x: np.ndarray | torch.Tensor, fg=None, tau: float | None = None,
                      settings: InferenceConfig | None = None) -> dict:
        """(B, 1, 64, 64) prepared inputs -> labels (B, 64, 64) uint8, renders, scores, recon.
        `tau` and `settings` override the model's."""
        tau = self.tau if tau is None else float(tau)
        cfg = self.inference if settings is None else settings
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        out = infer(self.G, self.encoder(cfg.precision), x, refine_steps=cfg.refine_steps,
                    hypotheses=cfg.hypotheses, keep=cfg.keep)
        fg_t = (x[:, 0] > -1 + 1e-4) if fg is None else torch.as_tensor(fg, device=self.device)
        labels = labels_from_renders(out["renders"], tau, fg_t)
        labels = smooth_labels(labels, x, out["renders"].shape[1], cfg.smooth)
        out["labels"] = labels
        out["scores"] = instance_scores(out["renders"], labels, tau)
        return out

    def __call__(self, depth_m: np.ndarray, prep_cfg=None, tau: float | None = None,
                 reconstruction: bool = True, settings: InferenceConfig | None = None
                 ) -> Segmentation:
        """One depth frame (H, W) in metres -> Segmentation at the input's resolution.

        `prep_cfg` overrides the model's preprocessing (bin region, floor, min_height: the
        node's parameters); `tau` the calibrated threshold; `reconstruction=False` skips the
        metric re-rendered depth; `settings` the model's refinement and smoothing.
        Raises ValueError on a bad frame."""
        from .preprocess import extend_labels, labels_to_full, prepare

        prep_cfg = self.prep_cfg if prep_cfg is None else prep_cfg
        cfg = self.inference if settings is None else settings
        if prep_cfg.max_height != self.prep_cfg.max_height or prep_cfg.size != self.prep_cfg.size:
            raise ValueError("max_height and size are fixed by the model: "
                             f"{self.prep_cfg.max_height} m, {self.prep_cfg.size} px")
        prep = prepare(depth_m, prep_cfg)
        out = self.segment_batch(prep.x[None, None], fg=prep.fg[None], tau=tau, settings=cfg)
        labels64 = out["labels"][0].cpu().numpy()
        labels = extend_labels(labels_to_full(labels64, prep), depth_m, prep, prep_cfg)
        labels = smooth_full(labels, depth_m, prep.floor_depth, prep_cfg.max_height,
                             self.model_cfg.n_instances, cfg.smooth, prep_cfg.size, prep.roi)
        recon = None
        if reconstruction:
            recon64 = out["reconstruction"][0, 0].cpu().numpy()
            recon = self._heights_to_depth(recon64, prep, prep.shape)
        return Segmentation(labels, recon, out["scores"][0].cpu().numpy(), labels64, prep.x,
                            prep.roi, prep.floor_depth)

    def _heights_to_depth(self, recon64: np.ndarray, prep, shape) -> np.ndarray:
        """Model output in [-1, 1] (64 x 64) -> metric depth at the input resolution (ROI only)."""
        import cv2

        x0, y0, x1, y1 = prep.roi
        h = (np.clip(recon64, -1, 1) + 1) / 2 * self.prep_cfg.max_height
        h = cv2.resize(h.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
        out = np.zeros(shape, np.float32)
        out[y0:y1, x0:x1] = prep.floor_depth - h
        return out
