"""Centre votes made in the second thread (as the node runs them) against the same votes made in
the main thread after the encoder, one model, interleaved frame by frame in one process.

    python scripts/experiments/votes_thread.py models/cylinder/model.pt

`Segmenter.__call__` on `bench_node`'s eight simulated 1280 x 720 frames, one torch thread, the
superpixel thread on for both (it makes the split's segments either way); for the second one the
thread is handed no centre votes, so `model_labels` makes them itself. Prints each one's median,
the median per-frame ratio, and whether every frame's labels were identical.
"""
import argparse
import time
from concurrent.futures import Future

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a model with centre votes")
    ap.add_argument("--rounds", type=int, default=10)
    args = ap.parse_args(argv)
    from inseggan_ros import preprocess
    from inseggan_ros.bench_node import simulated_frames
    from inseggan_ros.image_codec import depth_to_metres
    from inseggan_ros.segment import Segmenter

    torch.set_num_threads(1)
    depths = [depth_to_metres(f, "16UC1") for f in simulated_frames(8, 1280, 720)]
    threaded = Segmenter.from_checkpoint(args.model, device="cpu", superpixel_thread=True)
    inline = Segmenter.from_checkpoint(args.model, device="cpu", superpixel_thread=True)
    if threaded.inference.centre_votes != "on":
        raise SystemExit(f"{args.model}: its settings do not use centre votes")
    inline(depths[0], reconstruction=False)  # makes its pool
    submit = inline._pool.submit

    def no_votes(fn, *a):  # the votes then come from model_labels, in this thread
        if fn == inline.centre_votes:
            done = Future()
            done.set_result(None)
            return done
        return submit(fn, *a)

    inline._pool.submit = no_votes
    prep = preprocess.node_defaults(threaded.prep_cfg, depths[:preprocess.BIN_FRAMES])
    times = {"threaded": [], "inline": []}
    same = True
    for r in range(args.rounds):
        for d in depths:
            order = [("threaded", threaded), ("inline", inline)]
            labels = {}
            for name, seg in (order if r % 2 else order[::-1]):
                t0 = time.perf_counter()
                labels[name] = seg(d, prep, reconstruction=False).labels
                times[name].append(time.perf_counter() - t0)
            same &= bool(np.array_equal(labels["threaded"], labels["inline"]))
    t, i = np.array(times["threaded"]), np.array(times["inline"])
    print(f"votes in the second thread: p50 {np.median(t) * 1e3:.2f} ms; in the main thread: "
          f"p50 {np.median(i) * 1e3:.2f} ms; per-frame ratio second thread / main thread, "
          f"median {np.median(t / i):.3f}; identical labels on every frame: {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
