"""The shape loop: finish a model with labelled piles of the shape it learned.

A user has only unlabelled frames of their part. Once a model has learned the part's shape from
them (`inseggan train`), that shape becomes a simulator part (`sim.learned`), and piles of it,
seen through the user's camera with its noise, are scenes whose every label is known. The
encoder is then fitted to those labels (`distill --label-weight`), and the model shipped with a
card made from the user's own frames, without their labels (`modelcard.export_from_dataset`).
Without a model, the loop first learns the shape itself (`inseggan train` on the data set's
unlabelled frames), so one command goes from frames to a shipped model:

    inseggan loop --model runs/my_part/best.pt --data data/my_part --out runs/my_part_loop
    inseggan loop --data data/my_part --out runs/my_part_loop --train-minutes 40   # all of it

Stages, each skipped when a killed run is started again and its result is there (the
simulation is written to a temporary folder and renamed when complete; the encoder's training
resumes from its last checkpoint; the export writes its folder atomically):
  0. shape (only without `--model`): `train.train` on the data set's training frames (no labels;
     validation by reconstruction when the data set has none) into out/shape, for the training
     config's budget; a killed run resumes from out/shape/last.pt; its best.pt is the model;
  1. simulate: `--scenes` labelled scenes of the learned part, with the camera, noise, bin and
     number of instances of the user's data set (its meta.json);
  2. encoder: the model's encoder fitted to them (`distill.DistillConfig` with the label losses),
     with `--user-weight`, while also reconstructing the user's own unlabelled training frames;
  3. head (only with `head_iterations`): a label head (`label_head.py`) taught on the same
     piles to correct the z-buffer's labels; the model with it is out/head/model.pt;
  4. export: out/model, tau and the card from the user's validation and test frames as if they
     had no labels (the test split's labels, where it has them, give the card's mIoU rows).
Writes out/summary.json with the time of each stage.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from tqdm import tqdm


@dataclass(frozen=True)
class LoopConfig:
    scenes: int = 3000  # labelled scenes of the learned part to train the encoder on
    val_scenes: int = 200  # and to choose its best checkpoint with
    iterations: int = 3000  # encoder iterations
    lr: float = 3e-4  # their learning rate (cosine schedule down to 0)
    label_weight: float = 1.0
    ownership_weight: float = 0.2
    user_weight: float = 0.0  # reconstruction of the user's own (unlabelled) training frames,
    # mixed into every encoder iteration (`DistillConfig.lambda_user`)
    user_frames: int = 3000  # at most this many of them
    head_iterations: int = 0  # of a label head on the same scenes (0 = none; it helped the
    # cone and hurt the pin connector: docs/experiments.md)
    seed: int = 11  # of the simulated scenes
    workers: int = 1  # simulation processes
    name: str = "model"  # the exported model's name

    def __post_init__(self):
        for key in ("scenes", "val_scenes", "iterations", "workers", "user_frames"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} {getattr(self, key)!r} invalid; valid: >= 1")
        if self.head_iterations < 0:
            raise ValueError(f"head_iterations {self.head_iterations!r} invalid; valid: >= 0 "
                             "(0 = no label head)")
        if not 0 < self.lr < 1:
            raise ValueError(f"lr {self.lr!r} invalid; valid: in (0, 1)")
        if not self.user_weight >= 0:
            raise ValueError(f"user_weight {self.user_weight!r} invalid; valid: >= 0")


def _model_file(model) -> Path:
    path = Path(model)
    file = path / "model.pt" if path.is_dir() else path
    if not file.is_file():
        raise ValueError(f"{model}: no model there; valid: a model folder with model.pt, or a "
                         ".pt checkpoint (`inseggan train`'s best.pt)")
    return file


def _same_view(file: Path, data) -> None:
    """The model's template is in units of its training crop: the user's frames must be cut
    and scaled the same way (same camera and bin), else the simulated part and the template
    disagree in size."""
    from . import checkpoint
    from .data import sim_preprocess_config

    trained = checkpoint.load(file).get("preprocess_config") or {}
    user = sim_preprocess_config(data).to_dict()
    keys = ("roi", "floor_depth", "floor_plane", "max_height", "size")
    diff = {k: (trained.get(k), user.get(k)) for k in keys
            if k in user and _as_list(trained.get(k)) != _as_list(user.get(k))}
    if diff:
        raise ValueError(f"{data}: its frames are not cut as the model's were "
                         + ", ".join(f"{k} {a} (model) vs {b} (data)" for k, (a, b) in diff.items())
                         + "; valid: the data set of the camera and bin the model was trained on")


def _as_list(v):
    return [round(float(e), 6) for e in v] if isinstance(v, (list, tuple)) else v


def learn_shape(data, out, train_cfg, progress: bool = True, val_frames: int = 100) -> Path:
    """Stage 0: learn the part's shape from the data set's unlabelled training frames with
    `train_cfg` (a `train.TrainConfig`; its instance count is the data set's) -> out/best.pt.
    Skipped when out/summary.json says the run finished; resumed from out/last.pt after a kill."""
    from dataclasses import replace

    from .data import load_sim_training
    from .sim.dataset import load_meta
    from .train import train

    out = Path(out)
    if (out / "summary.json").is_file() and (out / "best.pt").is_file():
        return out / "best.pt"
    n = int(load_meta(data)["scene"]["instances"])
    train_cfg = replace(train_cfg, model=replace(train_cfg.model, n_instances=n))
    frames, val, prep, info = load_sim_training(data, val_frames=val_frames, progress=progress)
    frames.pop("labels", None)  # the shape is learned without labels
    train(train_cfg, frames, val, out, prep.to_dict(), info, resume=(out / "last.pt").is_file(),
          progress=progress)
    return out / "best.pt"


def label_head_stage(model: Path, sim: Path, data, out: Path, cfg: LoopConfig,
                     progress: bool = True) -> Path:
    """Stage 3: a label head (`label_head.fit`) for the encoder's model on the simulated piles,
    at the tau the user's validation frames give without their labels (as the export will
    calibrate it) -> out/model.pt. Skipped when that exists."""
    from . import data as data_mod
    from .label_head import HeadConfig, fit
    from .segment import Segmenter
    from .selfcheck import calibrate

    if (out / "model.pt").is_file():
        return out / "model.pt"
    seg = Segmenter.from_checkpoint(model, device="cpu")
    calib = data_mod.load_sim_split(data, "val", seg.prep_cfg, limit=200)
    tau, _ = calibrate(seg, calib["x"], calib["fg"])
    hcfg = HeadConfig(iterations=cfg.head_iterations, seed=cfg.seed,
                      eval_every=max(1, min(250, cfg.head_iterations)))
    return Path(fit(model, sim, out, hcfg, tau=tau, progress=progress)["model"])


def run(model, data, out, cfg: LoopConfig = LoopConfig(), progress: bool = True,
        train_cfg=None) -> dict:
    """The loop for `model` (its learned template) and the user's data set `data` -> summary
    (also out/summary.json). With `model` None the shape is learned first with `train_cfg`."""
    from . import data as data_mod
    from .distill import DistillConfig, distill
    from .modelcard import export_from_dataset
    from .sim.dataset import DatasetSpec, generate, load_meta
    from .sim.scene import SceneConfig

    if (model is None) == (train_cfg is None):
        raise ValueError("give a trained model, or a training config to learn the shape with "
                         "(not both)")
    if model is not None:
        _model_file(model)  # a missing model is named before anything else
    meta = load_meta(data)  # raises with what is wrong
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    stages = tqdm(total=(3 if model is not None else 4) + bool(cfg.head_iterations), desc="loop",
                  unit="stage",
                  disable=not progress, position=0)
    if model is None:
        t0 = time.monotonic()
        model = learn_shape(data, out / "shape", train_cfg, progress)
        seconds["shape"] = round(time.monotonic() - t0, 1)
        stages.update(1)
    file = _model_file(model).resolve()
    _same_view(file, data)

    t0 = time.monotonic()
    sim = out / "sim"
    if not (sim / "meta.json").is_file():
        scene = SceneConfig.from_dict({**meta["scene"], "object": str(file)})
        spec = DatasetSpec(scene, {"train": cfg.scenes, "val": cfg.val_scenes, "test": 0},
                           seed=cfg.seed)
        generate(spec, sim, workers=cfg.workers, progress=progress)
    seconds["simulate"] = round(time.monotonic() - t0, 1)
    stages.update(1)

    t0 = time.monotonic()
    encoder = out / "encoder"
    if not (encoder / "summary.json").is_file():
        train = data_mod.load_sim_split(sim, "train", progress=progress)
        val = data_mod.load_sim_split(sim, "val", limit=100)
        dcfg = DistillConfig(frames=cfg.scenes, iterations=cfg.iterations, lr=cfg.lr,
                             lr_schedule="cosine",
                             eval_every=max(1, min(500, cfg.iterations)), lambda_pose=0.0,
                             lambda_label=cfg.label_weight,
                             lambda_ownership=cfg.ownership_weight,
                             lambda_user=cfg.user_weight, seed=cfg.seed)
        user = (data_mod.load_sim_split(data, "train", limit=cfg.user_frames,
                                        progress=progress)["x"]  # its frames, not its labels
                if cfg.user_weight > 0 else None)
        distill(file, train["x"], val, encoder, dcfg, resume=True, progress=progress,
                train_labels=train["labels"], user_x=user)
    seconds["encoder"] = round(time.monotonic() - t0, 1)
    stages.update(1)

    finished = encoder / "best.pt"
    if cfg.head_iterations:
        t0 = time.monotonic()
        finished = label_head_stage(finished, sim, data, out / "head", cfg, progress)
        seconds["head"] = round(time.monotonic() - t0, 1)
        stages.update(1)

    t0 = time.monotonic()
    card = export_from_dataset(finished, data, cfg.name, out / "model")
    seconds["export"] = round(time.monotonic() - t0, 1)
    stages.update(1)
    stages.close()

    summary = {"model": str(model), "data": str(data), "config": asdict(cfg),
               "seconds": seconds, "encoder": json.loads((encoder / "summary.json").read_text()),
               "card": str(out / "model" / "card.json"), "tau": card.get("tau")}
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2, default=str))
    tmp.replace(out / "summary.json")
    return summary
