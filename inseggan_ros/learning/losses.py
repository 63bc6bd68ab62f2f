"""InSeGAN's losses: adversarial, and the encoder's alignment / intermediate / re-render losses.

The alignment loss compares two unordered sets of n codes, Z (sampled) and Z_hat (encoded):
    L_a = min over matchings pi of mean || z_i - z_hat_pi(i) ||^2
The matching is found without gradients; the loss then flows through the matched pairs.
  * "hungarian": exact (scipy.optimize.linear_sum_assignment), fast for small n: the default;
  * "ot": entropic optimal transport (Sinkhorn iterations, as the paper's IPOT), a soft plan;
  * "greedy": repeatedly take the closest remaining pair (the paper shows it is worse).
All are normalised per element, so predicting the mean code (0) gives L_a = 1 for z ~ N(0, I).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from inseggan_ros.runtime.pyramid import (  # noqa: F401  (shared with the pose fit)
    pool2x2, pyramid_l1)

MATCHINGS = ("hungarian", "ot", "greedy")


def pairwise_cost(z: torch.Tensor, z_hat: torch.Tensor) -> torch.Tensor:
    """(B, n, d) x (B, n, d) -> (B, n, n) mean squared distance between every pair."""
    return (z[:, :, None, :] - z_hat[:, None, :, :]).pow(2).mean(-1)


def hungarian_plan(cost: torch.Tensor) -> torch.Tensor:
    """(B, n, n) cost -> (B, n, n) 0/1 permutation matrices of the optimal matching."""
    c = cost.detach().float().cpu().numpy()
    plan = np.zeros_like(c)
    for b in range(c.shape[0]):
        rows, cols = linear_sum_assignment(c[b])
        plan[b, rows, cols] = 1.0
    return torch.from_numpy(plan).to(cost)


def greedy_plan(cost: torch.Tensor) -> torch.Tensor:
    c = cost.detach().float().cpu().numpy().copy()
    B, n, _ = c.shape
    plan = np.zeros_like(c)
    for b in range(B):
        cb = c[b]
        for _ in range(n):
            i, j = np.unravel_index(np.argmin(cb), cb.shape)
            plan[b, i, j] = 1.0
            cb[i, :] = np.inf
            cb[:, j] = np.inf
    return torch.from_numpy(plan).to(cost)


def sinkhorn_plan(cost: torch.Tensor, epsilon: float = 0.02, iterations: int = 100) -> torch.Tensor:
    """Entropic OT between uniform marginals; returned scaled so rows sum to 1
    (like a permutation)."""
    c = cost.detach().float()
    c = c / c.amax(dim=(1, 2), keepdim=True).clamp_min(1e-8)
    log_k = -c / epsilon
    n = c.shape[1]
    log_u = torch.zeros(c.shape[:2], device=c.device)
    log_v = torch.zeros(c.shape[:2], device=c.device)
    log_mu = torch.full_like(log_u, -np.log(n))
    for _ in range(iterations):
        log_u = log_mu - torch.logsumexp(log_k + log_v[:, None, :], dim=2)
        log_v = log_mu - torch.logsumexp(log_k + log_u[:, :, None], dim=1)
    plan = torch.exp(log_u[:, :, None] + log_k + log_v[:, None, :]) * n
    return plan.to(cost)


def alignment_loss(z: torch.Tensor, z_hat: torch.Tensor,
                   matching: str = "hungarian") -> torch.Tensor:
    """L_a: mean squared error between the sampled codes and the best-matched encoded codes."""
    cost = pairwise_cost(z, z_hat)
    if matching == "hungarian":
        plan = hungarian_plan(cost)
    elif matching == "ot":
        plan = sinkhorn_plan(cost)
    elif matching == "greedy":
        plan = greedy_plan(cost)
    else:
        raise ValueError(f"matching {matching!r} invalid; valid: {', '.join(MATCHINGS)}")
    return (plan * cost).sum(dim=(1, 2)).mean() / z.shape[1]


def d_loss(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> torch.Tensor:
    """Discriminator: real -> 1, generated -> 0 (binary cross-entropy on logits)."""
    return (F.binary_cross_entropy_with_logits(real_logits, torch.ones_like(real_logits))
            + F.binary_cross_entropy_with_logits(fake_logits, torch.zeros_like(fake_logits)))


def g_loss(fake_logits: torch.Tensor) -> torch.Tensor:
    """Generator: non-saturating, generated -> 1."""
    return F.binary_cross_entropy_with_logits(fake_logits, torch.ones_like(fake_logits))


def r1_penalty(real_logits: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """R1 gradient penalty on real images (Mescheder et al. 2018): E ||grad_x D(x)||^2."""
    (grad,) = torch.autograd.grad(real_logits.sum(), real, create_graph=True)
    return grad.pow(2).flatten(1).sum(1).mean()


def matched_masks(cost: np.ndarray, onehot: torch.Tensor, n: int) -> torch.Tensor:
    """(B, n, m) costs of n renders against m true masks, (B, m, H, W) the masks -> (B, n, H, W):
    each render's mask under the frame's cheapest one-to-one matching (Hungarian, scipy), zeros
    for a render left unmatched. The matching runs on the CPU frame by frame, on the small cost
    matrices alone; the masks are gathered in one indexing on their own device (no copy of
    them back and forth, which made the loop's encoder stage slower on a GPU than on a CPU)."""
    B, m = onehot.shape[:2]
    index = np.full((B, n), m, dtype=np.int64)  # m: the all-zero mask appended below
    for b in range(B):
        rows, cols = linear_sum_assignment(cost[b])
        index[b, rows] = cols
    padded = torch.cat([onehot, onehot.new_zeros(B, 1, *onehot.shape[2:])], 1)
    frames = torch.arange(B, device=onehot.device)[:, None]
    return padded[frames, torch.as_tensor(index, device=onehot.device)]


def label_loss(renders: torch.Tensor, labels: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Supervision from ground-truth instance labels (simulated scenes of the part, whose every
    label is known): each true instance is explained by one rendered instance, and no rendered
    instance rises above the observed surface.

    renders (B, n, H, W) single-instance renders in [-1, 1]; labels (B, H, W) integers, 0 the
    background; x (B, 1, H, W) the input. The renders are matched to the true instances per
    frame (Hungarian) by how well each explains each one's visible pixels (mean |render - x|
    on its mask). Then
      * own: mean |render - x| over every true instance's pixels, under its matched render;
      * above: mean relu(render - x) over all renders and pixels (a render above the surface
        would be seen; below it, it is hidden, which is allowed).
    A true instance left without a match (more of them than n) costs nothing; an unmatched
    render only has to stay under the surface. Height errors are what a pose error shows, so
    this does not pull instances up to win pixels (a cross-entropy on the soft z-buffer did, and
    the reconstruction error doubled: docs/experiments.md). -> own + above."""
    B, n, H, W = renders.shape
    m = int(labels.max()) if labels.numel() else 0
    above = F.relu(renders - x).mean()
    if m == 0:
        return above
    onehot = F.one_hot(labels.long(), m + 1)[..., 1:].permute(0, 3, 1, 2).to(renders)  # (B, m, ..)
    err = (renders - x).abs()  # (B, n, H, W)
    area = onehot.sum((2, 3))  # (B, m)
    with torch.no_grad():
        cost = torch.einsum("bihw,bjhw->bij", err, onehot) / area[:, None].clamp_min(1.0)
        cost = torch.where(area[:, None] > 0, cost, torch.zeros_like(cost)).cpu().numpy()
    target = matched_masks(cost, onehot, n)  # target[b, i]: the true mask matched to render i
    own = (target * err).sum() / target.sum().clamp_min(1.0)
    return own + above


def ownership_loss(renders: torch.Tensor, labels: torch.Tensor, temperature: float = 0.05
                   ) -> torch.Tensor:
    """Cross-entropy of each foreground pixel's true instance under the soft z-buffer
    (ownership softmax(renders / temperature)), renders matched to true instances by soft IoU
    (Hungarian). Pulls a render up to win its pixels; see `label_loss`."""
    B, n, H, W = renders.shape
    own = torch.softmax(renders / temperature, dim=1)
    m = int(labels.max()) if labels.numel() else 0
    if m == 0:
        return renders.sum() * 0
    onehot = F.one_hot(labels.long(), m + 1)[..., 1:].permute(0, 3, 1, 2).to(own)
    fg = onehot.sum(1, keepdim=True)
    with torch.no_grad():
        inter = torch.einsum("bihw,bjhw->bij", own * fg, onehot)
        union = (own * fg).sum((2, 3))[:, :, None] + onehot.sum((2, 3))[:, None, :] - inter
        cost = (-(inter / union.clamp_min(1e-6))).cpu().numpy()
    target = matched_masks(cost, onehot, n)
    logp = torch.log_softmax(renders / temperature, dim=1)
    return -(target * logp).sum() / target.sum().clamp_min(1.0)
