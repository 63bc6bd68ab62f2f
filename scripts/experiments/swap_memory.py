"""Peak memory and time of `refine_poses`' swaps (keep 1, 4 swaps) on 50 random frames with
the bolt model, in one batch or in SWAP_CHUNK-sized chunks.

    python scripts/experiments/swap_memory.py whole|chunked HYPOTHESES
"""
import resource
import sys
import time

import torch

from inseggan_ros import refine, segment
from inseggan_ros.nodes.segmenter import resolve_model

torch.set_num_threads(1)
seg = segment.Segmenter.from_checkpoint(resolve_model("bolt"), device="cpu")
if sys.argv[1] == "whole":
    refine.SWAP_CHUNK = 1 << 40
G = seg.G
torch.manual_seed(0)
H = int(sys.argv[2])
x = torch.rand(50, 1, 64, 64) * 2 - 1
with torch.no_grad():
    starts = refine.start_poses(G, seg.E, x, H)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    out = refine.refine_poses(G, starts, x, 0, keep=1, swaps=4)
    dt = time.perf_counter() - t0
rise = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
print(f"{sys.argv[1]}, {H} starts: peak RSS rise {rise:.0f} MB, {dt:.2f} s, "
      f"checksum of the poses {float(out.sum()):.6f}")
