"""Two model files' in-process frame time, interleaved frame by frame in one process (this
checkout's code), so that a shared, noisy machine slows both alike.

    git show COMMIT:models/cylinder/model.pt > /tmp/old.pt
    python scripts/experiments/ab_models.py /tmp/old.pt models/cylinder/model.pt

`Segmenter.__call__` on `bench_node`'s eight simulated 1280 x 720 frames, ten rounds, one torch
thread, the superpixel thread on (as the node runs), each model's own settings and the bin found
as the node finds it. Prints each model's median and the median per-frame ratio second / first.
"""
import argparse
import time

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("first")
    ap.add_argument("second")
    ap.add_argument("--rounds", type=int, default=10)
    args = ap.parse_args(argv)
    from inseggan_ros import preprocess
    from inseggan_ros.bench_node import simulated_frames
    from inseggan_ros.image_codec import depth_to_metres
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(1)
    depths = [depth_to_metres(f, "16UC1") for f in simulated_frames(8, 1280, 720)]
    segs = [Segmenter.from_checkpoint(p, device="cpu", superpixel_thread=True)
            for p in (args.first, args.second)]
    preps = [preprocess.node_defaults(s.prep_cfg, depths[:preprocess.BIN_FRAMES]) for s in segs]
    times = [[], []]
    for _ in range(args.rounds):
        for depth in depths:
            for k, (seg, prep) in enumerate(zip(segs, preps)):
                t0 = time.perf_counter()
                seg(depth, prep, reconstruction=False)
                times[k].append(time.perf_counter() - t0)
    first, second = (np.array(t[len(depths):]) * 1e3 for t in times)  # the first round warms up
    print(f"{args.first}: p50 {np.median(first):.2f} ms; {args.second}: p50 "
          f"{np.median(second):.2f} ms; per-frame ratio second / first, median "
          f"{np.median(second / first):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
