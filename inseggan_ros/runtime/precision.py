"""The encoder's and the centre-vote net's arithmetic at test time: float32, bfloat16 (weights
and activations; faster on a CPU that computes it natively, e.g. AVX512-BF16, with labels that
agree with float32 to about 0.001 mIoU on the sample bags), or auto: bfloat16 where the device
computes it natively, else float32 (emulated bfloat16 is slower than float32).
"""
from __future__ import annotations

import copy

import torch


def native_bfloat16(device: str) -> bool:
    """Whether `device` computes bfloat16 natively (not emulated: slower than float32)."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()


class CastEncoder(torch.nn.Module):
    """An encoder run in another dtype (a copy of its weights), float32 in and out.

    The copy's convolution weights are stored channels-last, the layout oneDNN's bfloat16
    convolutions work in: with native bfloat16 (AMX) the encoder then takes about 0.7 of the
    time for the same numbers; elsewhere it changes little (docs/benchmarks.md, 2026-11-27,
    night)."""

    def __init__(self, E, dtype: torch.dtype):
        super().__init__()
        self.E = copy.deepcopy(E).to(dtype=dtype, memory_format=torch.channels_last)
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.E(x.to(self.dtype)).float()


class CastCentreNet(torch.nn.Module):
    """A centre-vote net (`centres.CentreNet`) run in another dtype (a copy of its weights), but
    for its last layer, float32 in and out.

    The last layer, a 1 x 1 convolution, reads out the heatmap and the offsets to the centres;
    in bfloat16 its rounding moved votes between neighbouring peaks (validation mIoU: the cone
    0.973 -> 0.963, the bolt 0.875 -> 0.867). Kept in float32, the labels are the float32
    net's on the cone's 200 validation frames and on all but 0.03 % of the bolt's pixels, at
    about 0.6 of the float32 net's time with native bfloat16 (docs/benchmarks.md, 2026-12-02,
    day). Channels-last weights, which speed the encoder up, slowed this net down."""

    def __init__(self, net, dtype: torch.dtype):
        super().__init__()
        self.net = copy.deepcopy(net).to(dtype)
        self.net.out.float()
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.to(self.dtype))
