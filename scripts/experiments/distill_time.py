"""The loop's encoder stage (`distill` with labels), timed with the label losses' matching as
shipped (`losses.matched_masks`: masks gathered on their own device) and as it was before
(each frame's masks copied to the CPU and back), on one device, then profiled.

    python scripts/experiments/distill_time.py PACKED CHECKPOINT [--device cuda] [--iterations 60]

PACKED: `scripts/device_train.py pack --with-labels` of a loop's simulated piles; CHECKPOINT:
the loop's shape stage (best.pt). Prints seconds per iteration for both, and the profiler's
top operations of a few iterations as shipped.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from device_train import unpack  # noqa: E402
from inseggan_ros import losses  # noqa: E402
from inseggan_ros.distill import DistillConfig, distill  # noqa: E402


def per_frame_copies(cost: np.ndarray, onehot: torch.Tensor, n: int) -> torch.Tensor:
    """The matching as it was: each frame's matched masks copied to the CPU, then all back."""
    from scipy.optimize import linear_sum_assignment

    B, m, H, W = onehot.shape
    target = torch.zeros(B, n, H, W, dtype=onehot.dtype)
    for b in range(B):
        rows, cols = linear_sum_assignment(cost[b])
        target[b, torch.as_tensor(rows)] = onehot[b, torch.as_tensor(cols)].cpu()
    return target.to(onehot.device)


def run(x, labels, ckpt, device, iterations, batch) -> float:
    cfg = DistillConfig(frames=len(x), iterations=iterations, lambda_pose=0.0, lambda_label=1.0,
                        lambda_ownership=0.2, batch_size=batch, eval_every=10 ** 9)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        distill(ckpt, x, None, tmp, cfg, progress=False, train_labels=labels, device=device)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        return (time.perf_counter() - t0) / iterations


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("packed", type=Path)
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--batch-size", type=int, default=32)
    args = ap.parse_args(argv)
    tr, _, _, _ = unpack(args.packed)
    x, labels = tr["x"].astype(np.float32), tr["labels"]
    shipped = losses.matched_masks
    run(x, labels, args.checkpoint, args.device, 5, args.batch_size)  # warm-up
    for name, fn in (("as shipped", shipped), ("per-frame copies", per_frame_copies),
                     ("as shipped, again", shipped)):
        losses.matched_masks = fn
        s = run(x, labels, args.checkpoint, args.device, args.iterations, args.batch_size)
        print(f"{args.device}, batch {args.batch_size}, {name}: {s:.4f} s an iteration",
              flush=True)
    losses.matched_masks = shipped
    acts = [torch.profiler.ProfilerActivity.CPU]
    if args.device.startswith("cuda"):
        acts.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=acts) as prof:
        run(x, labels, args.checkpoint, args.device, 10, args.batch_size)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
    return 0


if __name__ == "__main__":
    sys.exit(main())
