"""Why the node takes longer per frame than bench_node's in-process reference.

`Segmenter.__call__` on the bench's 1280 x 720 frames (the cylinder, one torch thread, the
superpixel thread on, the settings of a shipped parameters file), three ways, twice each:
back to back (as the in-process reference runs), with 33 ms of sleep before every frame (as
the node waits for a 30 Hz camera), and with that sleep while a second process copies a 1.8 MB
buffer 30 times a second (a stand-in for the bench's publisher and DDS beside the node).

    python scripts/experiments/idle_gap.py fastest
    python scripts/experiments/idle_gap.py realtime
"""
import argparse
import multiprocessing as mp
import time

import numpy as np
import torch


def _copier(stop) -> None:
    frame = np.ones(1280 * 720, np.uint16)
    while not stop.is_set():
        copy = frame.copy()
        copy[0] = 1
        time.sleep(1 / 30)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("profile", help="a shipped parameters file's name (realtime, fastest, ...)")
    ap.add_argument("--frames", type=int, default=96, help="frames per measurement")
    args = ap.parse_args(argv)
    from inseggan_ros import preprocess, settings
    from inseggan_ros.bench_node import simulated_frames
    from inseggan_ros.image_codec import depth_to_metres
    from inseggan_ros.nodes import conversions
    from inseggan_ros.nodes.segmenter import resolve_model
    from inseggan_ros.paths import resolve_config
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(1)
    raw = simulated_frames(8, 1280, 720)
    seg = Segmenter.from_checkpoint(resolve_model("cylinder"), device="cpu",
                                    superpixel_thread=True)
    cfg = settings.apply(seg.inference,
                         settings.read_params_file(resolve_config(args.profile)))
    prep = preprocess.node_defaults(
        seg.prep_cfg, [depth_to_metres(f, "16UC1") for f in raw[:preprocess.BIN_FRAMES]])
    msgs = [conversions.numpy_to_image(f, "16UC1") for f in raw]

    def median_ms(sleep: float, n: int) -> float:
        times = []
        for k in range(n):
            if sleep:
                time.sleep(sleep)
            depth = conversions.depth_to_metres(msgs[k % len(msgs)])
            t0 = time.perf_counter()
            seg(depth, prep, reconstruction=False, settings=cfg)
            times.append(time.perf_counter() - t0)
        return float(np.median(times)) * 1e3

    median_ms(0, 16)  # warm-up
    results = {}
    for _ in range(2):
        results.setdefault("back to back", []).append(median_ms(0, args.frames))
        results.setdefault("33 ms sleep", []).append(median_ms(0.033, args.frames))
        stop = mp.Event()
        copier = mp.Process(target=_copier, args=(stop,))
        copier.start()
        results.setdefault("33 ms sleep + copier", []).append(median_ms(0.033, args.frames))
        stop.set()
        copier.join()
    for name, values in results.items():
        print(f"{args.profile}: {name}: median ms a frame "
              + ", ".join(f"{v:.2f}" for v in values))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
