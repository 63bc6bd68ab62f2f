"""Self-labelling experiment, step 1 (docs/experiments.md, 2026-11-26).

The shipped cone model's quality.yaml labels of the first 1,500 of the cone data set's
unlabelled training frames, one shard of them per process; no true label is read:

    for i in 0 1; do python scripts/experiments/self_labels.py $i 2 & done; wait
    python scripts/experiments/self_distill.py 1500

Optional arguments after those: the part (cone) and the number of frames (1500).
"""
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from inseggan_ros import data, settings  # noqa: E402
from inseggan_ros.segment import Segmenter  # noqa: E402

if __name__ == "__main__":
    torch.set_num_threads(1)
    part, parts = int(sys.argv[1]), int(sys.argv[2])
    name = sys.argv[3] if len(sys.argv) > 3 else "cone"
    frames = int(sys.argv[4]) if len(sys.argv) > 4 else 1500
    x = data.load_sim_split(f"data/{name}", "train", limit=frames)
    idx = np.arange(part, len(x["x"]), parts)
    seg = Segmenter.from_checkpoint(f"models/{name}/model.pt", device="cpu")
    cfg = settings.apply(seg.inference, settings.read_params_file("config/quality.yaml"))
    out = np.zeros((len(idx), 64, 64), np.uint8)
    t0 = time.time()
    for k in range(0, len(idx), 25):
        b = idx[k:k + 25]
        out[k:k + 25] = seg.segment_batch(x["x"][b], x["fg"][b], settings=cfg)["labels"].numpy()
        print(part, k, round(time.time() - t0), flush=True)
    np.savez(f"runs/self_labels_{name}_{part}.npz", idx=idx, labels=out)
