"""Shared by the experiments that try another rule for the labels of the default settings
(`consensus.py`, `duplicates_merge.py`, `pose_average.py`, `label_choice.py`,
`centre_views.py`, `centre_ensemble.py`): a model and a split of its data set
with the classical methods' scores and both hard subsets, the 8 starting points' poses and fit
losses, and the rest of the shipped pipeline (smoothing, superpixel vote, split) scored on
labels made another way."""
from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from inseggan_ros import data as data_mod
from inseggan_ros.baselines import BASELINES
from inseggan_ros.metrics import miou_batch
from inseggan_ros.refine import _fit_loss, start_poses
from inseggan_ros.segment import Segmenter
from inseggan_ros.smoothing import smooth_labels
from inseggan_ros.superpixels import split_labels, vote_labels


@dataclass
class Bench:
    seg: Segmenter
    x: torch.Tensor  # (N, 1, 64, 64) model inputs
    fg: torch.Tensor  # (N, 64, 64) foreground
    gt: np.ndarray  # (N, 64, 64) true labels
    base: dict  # {method: (N,) mIoU} of the classical methods
    hard_kmeans: np.ndarray  # (N,) bool: K-Means < 0.6
    hard_felzenszwalb: np.ndarray  # (N,) bool: Felzenszwalb < 0.8

    @property
    def n(self) -> int:
        return self.seg.model_cfg.n_instances

    def starts(self) -> tuple[torch.Tensor, np.ndarray]:
        """-> the starting poses (N, 8, n, 6) and their fit losses (N, 8), as realtime.yaml
        chooses among them."""
        G, E = self.seg.G, self.seg.encoder(self.seg.inference.encoder_precision)
        poses, losses = [], []
        with torch.no_grad():
            for i in range(0, len(self.x), 50):
                xb = self.x[i:i + 50]
                pose = start_poses(G, E, xb, self.seg.inference.refine_hypotheses)
                poses.append(pose)
                losses.append(_fit_loss(G, pose, F.adaptive_avg_pool2d(xb, 32), G.geometry()))
        return torch.cat(poses), torch.cat(losses).numpy()

    def finish(self, labels) -> np.ndarray:
        """(N, 64, 64) z-buffer labels -> (N,) mIoU after the model's smoothing, vote, split."""
        cfg, n = self.seg.inference, self.n
        t = smooth_labels(torch.as_tensor(labels), self.x, n, cfg.smooth)
        t = vote_labels(t, self.x, n, cfg.superpixel_scale)
        t, _ = split_labels(t, self.x, n, cfg.split_scale)
        return miou_batch(t.numpy(), self.gt)

    def labels(self, settings=None) -> np.ndarray:
        """(N, 64, 64) the segmenter's labels with `settings` (default: the model's own)."""
        return np.concatenate([self.seg.segment_batch(self.x[i:i + 50], self.fg[i:i + 50],
                                                      settings=settings)["labels"].numpy()
                               for i in range(0, len(self.x), 50)])

    def scores(self, settings=None) -> np.ndarray:
        """(N,) mIoU of `labels(settings)`."""
        return miou_batch(self.labels(settings), self.gt)

    def row(self, scores: np.ndarray) -> str:
        """All / K-Means hard / Felzenszwalb hard."""
        k, f = self.hard_kmeans, self.hard_felzenszwalb
        return " / ".join([f"{scores.mean():.3f}", f"{scores[k].mean():.3f}" if k.any() else "-",
                           f"{scores[f].mean():.3f}"])

    def print_baselines(self) -> None:
        for method, scores in self.base.items():
            print(method, self.row(scores))


def arguments(doc: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=doc)
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="val")
    return ap


def load(model: str, data: str, split: str) -> Bench:
    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(model)
    d = data_mod.load_sim_split(data, split, seg.prep_cfg)
    n = seg.model_cfg.n_instances
    heights = (d["x"][:, 0] + 1) / 2
    base = {m: miou_batch(np.stack([BASELINES[m](heights[i], d["fg"][i], n, seed=i)
                                    for i in range(len(heights))]), d["labels"])
            for m in ("kmeans", "felzenszwalb", "spectral")}
    b = Bench(seg, torch.as_tensor(d["x"]), torch.as_tensor(d["fg"]), d["labels"], base,
              base["kmeans"] < 0.6, base["felzenszwalb"] < 0.8)
    print(f"{model} {data} {split}: {len(heights)} frames, {b.hard_kmeans.sum()} / "
          f"{b.hard_felzenszwalb.sum()} hard")
    return b
