"""The in-process segmentation path of an earlier commit against this checkout's, interleaved
frame by frame in one process, so that a shared, noisy machine slows both alike.

    python scripts/experiments/ab_inference.py COMMIT [MODEL,MODEL,...] [--frames 12]
        [--superpixel-thread]

The earlier commit's `inseggan_ros` is extracted (`git archive`) under another package name;
both segment the same simulated 1280 x 720 RealSense frames of cylinders (`bench_node`'s) on
one thread, with each model's default settings and the bin found as the node finds it. Prints,
per model, both medians, the median of the per-frame ratios new / old and whether the labels
are identical. `--superpixel-thread`: the segmenters make the superpixels in a second thread,
as the node does by default (`superpixel_thread`), each where its commit can.
"""
from __future__ import annotations

import argparse
import importlib
import inspect
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]


def extract(commit: str, into: Path) -> str:
    """`inseggan_ros` of `commit` as package `inseggan_ab_old` under `into` -> its name."""
    tar = subprocess.run(["git", "-C", str(REPO), "archive", commit, "inseggan_ros"],
                         check=True, capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(tar)) as t:
        t.extractall(into, filter="data")
    (into / "inseggan_ros").rename(into / "inseggan_ab_old")
    return "inseggan_ab_old"


def interleave(segs: dict, preps: dict, frames: list, rounds: int) -> tuple[dict, dict]:
    """Each of the two segmenters `segs` (key -> Segmenter, with its `preps[key]`) on every
    frame in turn, their order alternating from round to round; round 0 warms up and keeps the
    labels. -> ({key: [ms per frame of rounds 1..]}, {key: [labels of round 0]})."""
    keys = list(segs)
    ms, labels = {k: [] for k in keys}, {k: [] for k in keys}
    for r in range(rounds + 1):
        for f in frames:
            for key in (keys if r % 2 else keys[::-1]):
                t0 = time.perf_counter()
                out = segs[key](f, preps[key], reconstruction=False)
                if r == 0:
                    labels[key].append(out.labels)
                else:
                    ms[key].append((time.perf_counter() - t0) * 1e3)
    return ms, labels


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("commit")
    ap.add_argument("models", nargs="?", default="cylinder")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--superpixel-thread", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    from inseggan_ros import preprocess, segment
    from inseggan_ros.bench_node import simulated_frames
    from inseggan_ros.image_codec import depth_to_metres
    from inseggan_ros.nodes.segmenter import resolve_model

    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        old = extract(args.commit, Path(tmp))
        old_segment = importlib.import_module(f"{old}.segment")
        old_preprocess = importlib.import_module(f"{old}.preprocess")
        frames = [depth_to_metres(f, "16UC1") for f in simulated_frames(args.frames, 1280, 720)]
        for name in args.models.split(","):
            path = resolve_model(name)
            runs = {"old": (old_segment.Segmenter, old_preprocess),
                    "new": (segment.Segmenter, preprocess)}
            segs, preps = {}, {}
            for key, (cls, pre) in runs.items():
                threaded = args.superpixel_thread and "superpixel_thread" in \
                    inspect.signature(cls.from_checkpoint).parameters  # both, where both can
                extra = {"superpixel_thread": True} if threaded else {}
                segs[key] = cls.from_checkpoint(path, device="cpu", **extra)
                preps[key] = pre.node_defaults(segs[key].prep_cfg, frames[:pre.BIN_FRAMES])
            ms, labels = interleave(segs, preps, frames, args.rounds)
            o, n = np.array(ms["old"]), np.array(ms["new"])
            same = all(np.array_equal(a, b) for a, b in zip(labels["old"], labels["new"]))
            print(f"{name}: {args.commit} p50 {np.median(o):.2f} ms, this checkout p50 "
                  f"{np.median(n):.2f} ms, per-frame ratio median {np.median(n / o):.3f}, "
                  f"identical labels: {same}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
