"""Self-labelling experiment, step 2 (see self_labels.py).

The shipped cone encoder fitted further to quality.yaml's own labels of the data set's unlabelled
training frames; no true label is used for training or for picking (the last checkpoint is
kept). Arguments: the iterations (1500 in the experiment), then optionally the part (cone) and
the number of frames (1500), as given to self_labels.py.
"""
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from inseggan_ros import data  # noqa: E402
from inseggan_ros.distill import DistillConfig, distill  # noqa: E402
from inseggan_ros.metrics import mean_miou, miou_batch  # noqa: E402

if __name__ == "__main__":
    torch.set_num_threads(2)
    name = sys.argv[2] if len(sys.argv) > 2 else "cone"
    frames = int(sys.argv[3]) if len(sys.argv) > 3 else 1500
    tr = data.load_sim_split(f"data/{name}", "train", limit=frames)
    lab = np.zeros((frames, 64, 64), np.uint8)
    for i in (0, 1):
        z = np.load(f"runs/self_labels_{name}_{i}.npz")
        lab[z["idx"]] = z["labels"]
    print("self-labels' mIoU against the true labels (a report only):",
          round(float(mean_miou(miou_batch(lab, tr["labels"]))), 4), flush=True)
    cfg = DistillConfig(frames=frames, iterations=int(sys.argv[1]), lr=3e-4,
                        lr_schedule="cosine", eval_every=10**6, lambda_pose=0.0,
                        lambda_label=1.0, lambda_ownership=0.2, seed=11)
    s = distill(f"models/{name}/model.pt", tr["x"], None, f"runs/{name}_self", cfg,
                progress=False, train_labels=lab)
    print(s["iterations"], s["seconds"])
