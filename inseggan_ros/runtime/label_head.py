"""A label head at test time: the z-buffered labels corrected by a small network.

For every instance slot k the head looks at the input, slot k's render, the highest of the other
renders and the pixels the z-buffer gave k, and scores each foreground pixel for k (one small
U-Net shared by all slots, so it is the same for any slot order and any number of instances);
each pixel takes the slot that scores highest. How it is taught on simulated piles:
`learning.label_head`.

    head = head_from_state(state["label_head"])
    labels = head_labels(head, x, renders, labels, fg)
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


IN_CHANNELS = 4  # input heights, slot k's render, the other renders' maximum, z-buffer mask of k


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, 1, 1), nn.ReLU(inplace=True))


class LabelHead(nn.Module):
    """A three-level U-Net scoring each pixel for one instance slot, run on every slot."""

    def __init__(self, width: int = 8):
        super().__init__()
        w = width
        self.width = width
        self.enc1 = _block(IN_CHANNELS, w)
        self.enc2 = _block(w, 2 * w, stride=2)
        self.enc3 = _block(2 * w, 4 * w, stride=2)
        self.dec2 = _block(4 * w + 2 * w, 2 * w)
        self.dec1 = _block(2 * w + w, w)
        self.out = nn.Conv2d(w, 1, 1)
        # the head corrects the z-buffer: its own mask of slot k, times this, is added to the
        # score, so that an untrained head gives the z-buffer's labels
        self.prior = nn.Parameter(torch.tensor(1.0))

    @staticmethod
    def inputs(x: torch.Tensor, renders: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) input, (B, n, H, W) renders, (B, H, W) z-buffer labels (0..n) ->
        (B * n, 4, H, W): per slot the input, its render, the others' maximum, its mask."""
        B, n, H, W = renders.shape
        if n == 1:
            others = torch.full_like(renders, -1.0)
        else:
            # the maximum over the other slots: the top two per pixel are enough
            top2 = renders.topk(2, dim=1).values
            others = torch.where(renders >= top2[:, :1], top2[:, 1:2], top2[:, :1])
        slots = torch.arange(1, n + 1, device=labels.device).view(1, n, 1, 1)
        mine = (labels[:, None] == slots).float()
        stack = torch.stack([x.expand(B, n, H, W), renders, others, mine * 2 - 1], dim=2)
        return stack.reshape(B * n, IN_CHANNELS, H, W)

    def forward(self, x: torch.Tensor, renders: torch.Tensor, labels: torch.Tensor
                ) -> torch.Tensor:
        """-> (B, n, H, W) logits, one map per slot."""
        B, n, H, W = renders.shape
        h = self.inputs(x, renders, labels)
        e1 = self.enc1(h)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d2 = self.dec2(torch.cat([F.interpolate(e3, size=e2.shape[-2:]), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=e1.shape[-2:]), e1], 1))
        return (self.out(d1) + self.prior * h[:, 3:4]).reshape(B, n, H, W)


@torch.no_grad()
def head_labels(head: LabelHead, x: torch.Tensor, renders: torch.Tensor, labels: torch.Tensor,
                fg: torch.Tensor) -> torch.Tensor:
    """(B, H, W) labels 1..n on the foreground `fg` (0 elsewhere): each pixel's best slot."""
    out = (head(x, renders, labels).argmax(1) + 1).to(torch.uint8)
    out[~fg] = 0
    return out


def head_state(head: LabelHead) -> dict:
    """What a checkpoint stores of a head (its "label_head" entry)."""
    from inseggan_ros.core.checkpoint import width_state
    return width_state(head)


def head_from_state(state: dict) -> LabelHead:
    from inseggan_ros.core.checkpoint import from_width_state
    return from_width_state(LabelHead, state)
