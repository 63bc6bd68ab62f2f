"""Self-fitting: the encoder taught by the model's own best labels of the user's frames.

A model that has learned its part from unlabelled frames segments them best with its slow
settings (`config/quality.yaml`: test-time refinement from several starting points, label
smoothing), and in real time with its fast ones (`config/realtime.yaml`: the encoder's poses
alone). The gap between the two is what the encoder has not learned. So:

  1. label `frames` of the user's unlabelled training frames with the model at the slow
     settings (tau calibrated on the validation frames without their labels, as the export
     does), in `workers` processes, chunk by chunk into labels.npz so that a killed run resumes;
  2. fit the encoder further to those labels, with the loss the loop fits simulated piles with
     (`distill` with the label and ownership losses, its generator frozen), for `iterations`,
     and keep the last checkpoint (there is no labelled validation set to pick another by).

No label of the user's data is read. The result is a training checkpoint (out/last.pt) whose
distillation record says where its labels came from, for `modelcard`:

    inseggan self-fit --model models/cone --data data/cone --out runs/cone_self
    inseggan loop ... --self-frames 1500        # the same, as the loop's last stage

It helps where the slow settings' labels are better than the fast ones (docs/experiments.md,
2026-11-26: the cone 0.842 -> 0.904 test mIoU at the default settings, the pin connector 0.822
-> 0.851).
"""
from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm


@dataclass(frozen=True)
class SelfFitConfig:
    frames: int = 1500  # of the user's training frames, labelled and fitted to
    iterations: int = 1500  # of the encoder
    settings: str = "quality"  # the labelling settings: a parameters file, a shipped one's
    # name, or "own": the model's stored settings
    lr: float = 3e-4  # cosine schedule down to 0
    label_weight: float = 1.0
    ownership_weight: float = 0.2
    workers: int = 2  # labelling processes (one thread each)
    chunk: int = 25  # frames labelled (and saved) at a time
    seed: int = 11

    def __post_init__(self):
        for key in ("frames", "iterations", "workers", "chunk"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 1")
        if not 0 < self.lr < 1:
            raise ValueError(f"lr {self.lr!r} invalid; valid: in (0, 1)")
        if not (self.label_weight > 0 and self.ownership_weight >= 0):
            raise ValueError(f"label_weight {self.label_weight!r} and ownership_weight "
                             f"{self.ownership_weight!r} invalid; valid: > 0 and >= 0")


def check_settings(name: str) -> None:
    """Raises (naming the file) unless `name` is "own", a readable parameters file or a shipped
    settings name."""
    from inseggan_ros.core import settings
    from inseggan_ros.core.paths import resolve_config

    if name != "own":
        settings.read_params_file(resolve_config(name))


def _settings(model: Path, name: str, tau: float | None, overrides: dict | None = None):
    from dataclasses import replace

    from inseggan_ros.core import settings
    from inseggan_ros.runtime.segment import Segmenter

    seg = Segmenter.from_checkpoint(model, device="cpu", tau=tau)
    cfg = (seg.inference if name == "own"
           else settings.apply_file(seg.inference, name, seg.stored_settings))
    return seg, replace(cfg, **(overrides or {}))


def _label_chunk(job) -> tuple[int, np.ndarray]:
    """One chunk: (start, labels (B, 64, 64) uint8)."""
    model, name, tau, overrides, start, x, fg = job
    global _CACHE
    key = (str(model), name, tau, json.dumps(overrides, sort_keys=True))
    if _CACHE is None or _CACHE[0] != key:  # a worker builds the model once
        _CACHE = (key, *_settings(Path(model), name, tau, overrides))
    _, seg, cfg = _CACHE
    with torch.no_grad():
        return start, seg.segment_batch(x, fg, settings=cfg)["labels"].cpu().numpy()


_CACHE = None


def self_labels(model, x: np.ndarray, fg: np.ndarray, tau: float | None, out_file,
                cfg: SelfFitConfig, progress: bool = True,
                overrides: dict | None = None) -> np.ndarray:
    """(N, 64, 64) uint8 labels of prepared frames x (N, 1, 64, 64) with foreground fg, by the
    model at `cfg.settings` (then `overrides`, InferenceConfig fields) and `tau` (None: the
    model's own); saved to `out_file` (npz, atomically) after every chunk and resumed from it
    when it holds the same job's first chunks: the same model, settings and tau over the same
    frames (their bytes' SHA-1: other frames of the same count are labelled anew)."""
    out_file = Path(out_file)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    n = len(x)
    labels = np.zeros((n, 64, 64), np.uint8)
    done = np.zeros(n, bool)
    overrides = dict(overrides or {})
    tau = None if tau is None else float(tau)
    job = {"model": str(model), "settings": cfg.settings, "tau": tau, "frames": n,
           "frames_sha1": hashlib.sha1(np.ascontiguousarray(x, np.float32).tobytes()).hexdigest(),
           **({"overrides": overrides} if overrides else {})}
    if out_file.is_file():
        with np.load(out_file) as saved:
            if json.loads(str(saved["job"])) == job:
                labels, done = saved["labels"].copy(), saved["done"].copy()
    todo = [s for s in range(0, n, cfg.chunk) if not done[s:s + cfg.chunk].all()]
    bar = tqdm(total=n, initial=int(done.sum()), desc="self-labels", unit="frame",
               disable=not progress, dynamic_ncols=True)

    def save():
        tmp = out_file.with_name(out_file.name + ".tmp.npz")
        np.savez(tmp, labels=labels, done=done, job=json.dumps(job))
        os.replace(tmp, out_file)

    jobs = ((str(model), cfg.settings, tau, overrides, s, x[s:s + cfg.chunk],
             fg[s:s + cfg.chunk]) for s in todo)
    if cfg.workers == 1:  # in this process, with its threads
        results = map(_label_chunk, jobs)
        pool = None
    else:  # spawn: a forked torch may hang on the parent's thread pool; one thread a worker
        pool = ProcessPoolExecutor(cfg.workers, mp_context=get_context("spawn"),
                                   initializer=torch.set_num_threads, initargs=(1,))
        results = pool.map(_label_chunk, jobs)
    try:
        for start, lab in results:
            labels[start:start + len(lab)] = lab
            done[start:start + len(lab)] = True
            save()
            bar.update(len(lab))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
    return labels


def self_fit(model, frames: dict, calib: dict, out, cfg: SelfFitConfig = SelfFitConfig(),
             progress: bool = True) -> Path:
    """Steps 1 and 2 for `model` (a training checkpoint or model.pt) on the user's training
    `frames` ({x, fg}; labels, if any, are not read) with tau from `calib` ({x, fg}: validation
    frames, without labels) -> out/last.pt. Skipped when out/summary.json is there."""
    from inseggan_ros.learning.distill import DistillConfig, distill
    from inseggan_ros.runtime.segment import Segmenter
    from inseggan_ros.evaluation.selfcheck import calibrate

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if (out / "summary.json").is_file() and (out / "last.pt").is_file():
        return out / "last.pt"
    n = min(cfg.frames, len(frames["x"]))
    if n < 1:
        raise ValueError("self-fitting needs training frames; none were given")
    tau, _ = calibrate(Segmenter.from_checkpoint(model, device="cpu"), calib["x"], calib["fg"])
    x, fg = frames["x"][:n], frames["fg"][:n]
    labels = self_labels(model, x, fg, tau, out / "labels.npz", cfg, progress)
    dcfg = DistillConfig(frames=n, iterations=cfg.iterations, lr=cfg.lr, lr_schedule="cosine",
                         eval_every=max(1, min(500, cfg.iterations)), lambda_pose=0.0,
                         lambda_label=cfg.label_weight, lambda_ownership=cfg.ownership_weight,
                         seed=cfg.seed, labels="self")
    distill(model, x, None, out, dcfg, resume=True, progress=progress, train_labels=labels,
            self_fit={**asdict(cfg), "tau": float(tau)})
    return out / "last.pt"
