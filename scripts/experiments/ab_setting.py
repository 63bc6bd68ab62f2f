"""Two values of one test-time setting on the same frames, interleaved frame by frame in one
process, so that a shared, noisy machine slows both alike.

    python scripts/experiments/ab_setting.py MODEL[,MODEL...] SETTING A B [--frames 12]

Each model segments the bench's simulated 1280 x 720 frames (`bench_node`'s) on one torch
thread with the superpixel thread, as the node does, with its shipped settings and SETTING
(an `InferenceConfig` field, an integer) set to A and to B. Prints both medians and the median
of the per-frame ratios B / A (`ab_inference.interleave`: the same timing loop).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import cv2
import numpy as np
import torch
from ab_inference import interleave  # this script's folder is on sys.path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models")
    ap.add_argument("setting")
    ap.add_argument("a", type=int)
    ap.add_argument("b", type=int)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=8)
    args = ap.parse_args(argv)
    if args.a == args.b:
        ap.error(f"A and B are both {args.a}; give two different values")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from inseggan_ros import preprocess, segment
    from inseggan_ros.bench_node import simulated_frames
    from inseggan_ros.image_codec import depth_to_metres
    from inseggan_ros.nodes.segmenter import resolve_model

    frames = [depth_to_metres(f, "16UC1") for f in simulated_frames(args.frames, 1280, 720)]
    for name in args.models.split(","):
        segs = {}
        for value in (args.a, args.b):
            seg = segment.Segmenter.from_checkpoint(resolve_model(name), device="cpu",
                                                    superpixel_thread=True)
            seg.inference = dataclasses.replace(seg.inference, **{args.setting: value})
            segs[value] = seg
        prep = preprocess.node_defaults(segs[args.a].prep_cfg, frames[:preprocess.BIN_FRAMES])
        ms, _ = interleave(segs, {args.a: prep, args.b: prep}, frames, args.rounds)
        a, b = np.array(ms[args.a]), np.array(ms[args.b])
        print(f"{name}: {args.setting} {args.a} p50 {np.median(a):.2f} ms, {args.b} p50 "
              f"{np.median(b):.2f} ms, per-frame ratio median {np.median(b / a):.3f}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
