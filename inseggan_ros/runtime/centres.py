"""Centre votes at test time: each instance found by its pixels' votes for its centre.

A small fully convolutional network (the instance branch of Panoptic-DeepLab, Cheng et al. 2020)
reads, for every pixel of the model's input, a heatmap of part centres (the mean of each part's
visible pixels) and the offset from the pixel to its part's centre. The heatmap's peaks (at most
n) are the instances, and each foreground pixel joins the peak nearest where its offset points.
How the net is taught on simulated piles of the learned part: `learning.centres`.

    net = net_from_state(state["centre_net"])
    labels = centre_labels(net, x, fg, n)        # (B, 64, 64) uint8, 0 = background
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment


OFFSET_UNIT = 8.0  # offsets are predicted in units of 8 pixels (about a part's half-length)


HEAT_SIGMA = 2.0  # pixels: the Gaussian round each centre in the heatmap's target


PEAK_THRESHOLD = 0.3  # a heatmap peak below this is no instance (the highest always is one)


PEAK_RADIUS = 3  # pixels: a peak is the highest point within this distance


MIN_PIXELS = 4  # a true instance with fewer visible pixels has no centre in the target


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.GroupNorm(4, cout),
                         nn.LeakyReLU(0.2))


class CentreNet(nn.Module):
    """(B, 2, 64, 64) heights and foreground -> (B, 3, 64, 64): the centre heatmap's logit and
    the offset (dy, dx) from each pixel to its part's centre, in OFFSET_UNIT pixels. A U-Net
    with three levels (64, 32, 16 pixels)."""

    def __init__(self, width: int = 16):
        super().__init__()
        w = self.width = width
        self.e1 = nn.Sequential(_block(2, w), _block(w, w))
        self.e2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))
        self.e3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w),
                                _block(4 * w, 4 * w))
        self.d2 = nn.Sequential(_block(6 * w, 2 * w), _block(2 * w, 2 * w))
        self.d1 = nn.Sequential(_block(3 * w, w), _block(w, w))
        self.out = nn.Conv2d(w, 3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.e1(x)
        b = self.e2(a)
        c = self.e3(b)
        b = self.d2(torch.cat([_up2(c), b], 1))
        a = self.d1(torch.cat([_up2(b), a], 1))
        return self.out(a.to(self.out.weight.dtype))  # a float32 last layer: `CastCentreNet`


def _up2(x: torch.Tensor) -> torch.Tensor:
    """Nearest-neighbour upsampling by 2: F.interpolate's values, at a third of its time on
    one CPU thread at these sizes."""
    return x.repeat_interleave(2, -2).repeat_interleave(2, -1)


def net_input(x, fg) -> torch.Tensor:
    """(B, 1, H, W) model input and (B, H, W) foreground -> (B, 2, H, W)."""
    x = torch.as_tensor(x, dtype=torch.float32)
    fg = torch.as_tensor(fg).to(torch.float32)
    return torch.cat([x, fg[:, None]], 1)


def _grid(H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.arange(H, dtype=torch.float32).view(H, 1).expand(H, W),
            torch.arange(W, dtype=torch.float32).view(1, W).expand(H, W))


@torch.no_grad()
def decode(pred: torch.Tensor, fg, n: int, min_votes: float | torch.Tensor = 0.0) -> torch.Tensor:
    """(B, 3, H, W) net output and (B, H, W) foreground -> (B, H, W) uint8 labels: the
    heatmap's peaks (at most n, each the highest within PEAK_RADIUS, above PEAK_THRESHOLD),
    labelled 1.. in order of height, and every foreground pixel given the peak nearest where
    its offset points. A peak may lie off the foreground: the centre of a part with a hole (a
    nut lying flat) is in the hole (peaks on the foreground only cost a net taught on the nut's
    frames 0.918 -> 0.648 on its validation split; the cylinder's and the bolt's labels are the
    same either way: docs/experiments.md, 2026-11-29).

    `min_votes` (pixels; a number or one per frame): a peak is an instance only where at least
    that many foreground pixels vote for it; the peak with the fewest votes below it is dropped
    and its pixels vote again, until every peak left has enough, so that a bin of fewer parts
    than n, or none, gets no instance from a weak peak or from foreground that is no part (a
    wall's top). 0: the highest peak always counts, as the net was taught (n parts a bin)."""
    pred = pred.float()
    fg = torch.as_tensor(fg, dtype=torch.bool, device=pred.device)
    B, _, H, W = pred.shape
    heat = torch.sigmoid(pred[:, 0])
    k, r = 2 * PEAK_RADIUS + 1, PEAK_RADIUS  # the square's max as a row's then a column's
    local = F.max_pool2d(F.max_pool2d(heat[:, None], (1, k), 1, (0, r)), (k, 1), 1, (r, 0))[:, 0]
    score = torch.where(heat == local, heat, torch.zeros_like(heat)).flatten(1)
    top = score.topk(min(n, H * W), dim=1)
    keep = top.values > PEAK_THRESHOLD
    ys, xs = _grid(H, W)
    cy, cx = ys.flatten()[top.indices], xs.flatten()[top.indices]  # (B, k)
    vy = ys + pred[:, 1] * OFFSET_UNIT  # where each pixel's vote lands
    vx = xs + pred[:, 2] * OFFSET_UNIT
    d = (vy[:, None] - cy[..., None, None]) ** 2 + (vx[:, None] - cx[..., None, None]) ** 2
    min_votes = torch.as_tensor(min_votes, dtype=torch.float32, device=pred.device)
    if (min_votes <= 0).all():
        keep[:, 0] = True
    else:
        keep = _enough_votes(d, keep, fg, min_votes.expand(B))
    d = torch.where(keep[..., None, None], d, torch.full_like(d, float("inf")))
    labels = (d.min(1).indices + 1).to(torch.uint8)  # argmin's, at a twentieth of its time
    labels[~fg | ~keep.any(1)[:, None, None]] = 0
    return labels


def _enough_votes(d: torch.Tensor, keep: torch.Tensor, fg: torch.Tensor,
                  min_votes: torch.Tensor) -> torch.Tensor:
    """`keep` (B, k) less the peaks that fewer than `min_votes` (B,) foreground pixels vote
    for, dropped one at a time (the fewest votes first, the others voting again), given each
    pixel's squared distance `d` (B, k, H, W) from where its vote lands to each peak."""
    keep = keep.clone()
    inf = torch.full_like(d, float("inf"))
    for _ in range(keep.shape[1]):
        nearest = torch.where(keep[..., None, None], d, inf).min(1).indices  # (B, H, W)
        votes = F.one_hot(nearest, keep.shape[1]).mul_(fg[..., None]).flatten(1, 2).sum(1)
        weak = keep & (votes < min_votes[:, None])
        if not weak.any():
            break
        fewest = torch.where(weak, votes, torch.full_like(votes, votes.max() + 1)).argmin(1)
        keep[torch.arange(len(keep))[weak.any(1)], fewest[weak.any(1)]] = False
    return keep


@torch.no_grad()
def centre_labels(net: CentreNet, x, fg, n: int, min_votes: float = 0.0,
                  founding: bool = False):
    """(B, 1, H, W) model inputs and (B, H, W) foreground -> (B, H, W) uint8 labels
    (`decode`, its `min_votes`); with `founding`, also (B, H, W) bool: where the heatmap is
    above PEAK_THRESHOLD, where a part's centre may be (`superpixels.split_frame`'s)."""
    pred = net(net_input(x, fg))
    labels = decode(pred, fg, n, min_votes)
    return (labels, torch.sigmoid(pred[:, 0].float()) > PEAK_THRESHOLD) if founding else labels


def match_to_renders(labels: torch.Tensor, zbuffer: torch.Tensor, n: int) -> torch.Tensor:
    """Centre-vote labels renumbered so that each takes the id of the z-buffer label it overlaps
    most (Hungarian assignment on the overlap, frame by frame): an instance's id then names the
    render nearest it, whose pose, score and pick the node reports."""
    lab, zb = labels.cpu().numpy(), zbuffer.cpu().numpy()
    out = np.zeros_like(lab)
    for b in range(len(lab)):
        overlap = np.zeros((n + 1, n + 1), np.int64)
        np.add.at(overlap, (lab[b].ravel(), zb[b].ravel()), 1)
        rows, cols = linear_sum_assignment(-overlap[1:, 1:])
        mapping = np.zeros(n + 1, lab.dtype)
        mapping[rows + 1] = cols + 1
        out[b] = mapping[lab[b]]
    return torch.from_numpy(out).to(labels.device)


def net_state(net: CentreNet) -> dict:
    """What a checkpoint stores of the net (its "centre_net" entry)."""
    from inseggan_ros.core.checkpoint import width_state
    return width_state(net)


def net_from_state(state: dict) -> CentreNet:
    from inseggan_ros.core.checkpoint import from_width_state
    return from_width_state(CentreNet, state)
