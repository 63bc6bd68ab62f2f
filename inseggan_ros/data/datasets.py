"""Data sets for training and evaluation: simulated shards and rosbag2 bags -> model tensors.

Both sources go through the very same `preprocess.prepare`, so a model trained on simulated
shards sees bag frames exactly as it saw its training data. A loaded split is a dict of numpy
arrays:
    x            (N, 1, size, size) float32 in [-1, 1], background exactly -1
    fg           (N, size, size) bool, x > -1
    labels       (N, size, size) uint8 ground truth at the model's resolution, 0 off the
                 foreground (`preprocess.resize_labels`); None for bags without labels
    roi          (N, 4) int32 region used, floor_depth (N,) float32 metres, config (the
                 PreprocessConfig used); bags also give stamp_ns (N,) int64
For simulated data the bin region and floor are known: unless the config sets them,
`roi` is the camera projection of the bin's inner floor (`preprocess.roi_from_camera`) and
`floor_depth` the camera's mount height, both from the data set's meta.json — deterministic and
the same for every frame (`sim_preprocess_config`).

`DepthTensorDataset` serves such a dict to a torch DataLoader, with the reference code's
augmentation on request: random horizontal / vertical flips and rotations (nearest neighbour,
so the background stays exactly -1 and no new depth values appear).

Speed (this project's 2-core machine, busy with a simulation run at the time): load_sim_split
reads 1000 simulated 224 x 224 frames in 0.6-0.7 s, 0.45 s of it decompressing the npz shards.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from inseggan_ros.io import bags
from inseggan_ros.runtime.preprocess import (
    PreprocessConfig, prepare, resize_labels, roi_from_camera)
from inseggan_ros.sim.dataset import SPLITS, iter_scenes, load_meta
from inseggan_ros.sim.scene import SceneConfig


# ------------------------------------------------------------------------------ loading
def sim_preprocess_config(meta_or_root, **overrides) -> PreprocessConfig:
    """The preprocessing of a simulated data set (a meta dict, or the data set's directory):
    `roi` from the camera and bin of its scene config, and the floor: `floor_depth` = the
    camera's mount height when it looks straight down, else the floor plane it sees; any
    PreprocessConfig field can be overridden (roi=None finds the bin per frame)."""
    meta = meta_or_root if isinstance(meta_or_root, dict) else load_meta(meta_or_root)
    scene = SceneConfig.from_dict(meta["scene"])
    cam = scene.camera
    level = cam.tilt == 0  # a roll about the optical axis keeps every floor pixel at one depth
    fields = {"roi": roi_from_camera(cam, scene.bin),
              "floor_depth": cam.mount_height if level else None,
              "floor_plane": None if level else tuple(cam.floor_plane())}
    if "floor_depth" in overrides or "floor_plane" in overrides:  # the caller's floor only
        fields.update(floor_depth=None, floor_plane=None)
    unknown = set(overrides) - set(PreprocessConfig.__dataclass_fields__)
    if unknown:
        raise ValueError(f"unknown preprocessing keys {sorted(unknown)}; valid: "
                         f"{', '.join(PreprocessConfig.__dataclass_fields__)}")
    fields.update(overrides)
    return PreprocessConfig(**fields)


def _empty(n: int, size: int) -> dict:
    return {"x": np.empty((n, 1, size, size), np.float32),
            "fg": np.empty((n, size, size), bool),
            "labels": np.empty((n, size, size), np.uint8),
            "roi": np.empty((n, 4), np.int32),
            "floor_depth": np.empty(n, np.float32)}


def _store(out: dict, i: int, depth_m: np.ndarray, labels: np.ndarray | None,
           cfg: PreprocessConfig) -> bool:
    p = prepare(depth_m, cfg)
    out["x"][i, 0], out["fg"][i], out["roi"][i], out["floor_depth"][i] = \
        p.x, p.fg, p.roi, p.floor_depth
    if labels is None:
        return False
    out["labels"][i] = resize_labels(labels, p)
    return True


def load_sim_split(root, split: str, cfg: PreprocessConfig | None = None,
                   limit: int | None = None, progress: bool = False,
                   as_given: bool = False) -> dict:
    """Every scene of one split of a simulated data set (`inseggan simulate`), preprocessed.

    cfg.roi / cfg.floor_depth left None are taken from the data set (see the module docstring);
    cfg None = `sim_preprocess_config(root)`. With `as_given`, cfg is used as it is: what it
    leaves None is found in every frame, as for a bag (simulated piles of a part learned from a
    bag, seen as that bag's frames were). `limit` keeps the first scenes only."""
    meta = load_meta(root)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    if limit is not None and limit < 0:
        raise ValueError(f"limit must be >= 0 or None, got {limit}")
    known = sim_preprocess_config(meta)
    if as_given:
        if cfg is None:
            raise ValueError("as_given needs a preprocessing config")
    elif cfg is None:
        cfg = known
    else:
        cfg = replace(
            cfg, roi=cfg.roi if cfg.roi is not None else known.roi,
            floor_depth=cfg.floor_depth if cfg.floor_depth is not None else known.floor_depth)
    n = int(meta["counts"][split]) if limit is None else min(limit, int(meta["counts"][split]))
    out = _empty(n, cfg.size)
    if n:
        scenes = tqdm(iter_scenes(root, split), total=n, unit="frame",
                      desc=f"loading {split}", disable=not progress)
        for i, (depth, labels) in enumerate(scenes):
            if i >= n:
                break
            _store(out, i, depth, labels, cfg)
        scenes.close()
    out["config"] = cfg
    return out


def parts_per_bin(root) -> int:
    """How many parts every bin of a simulated data set holds (its scenes' `instances`): the n
    a model of it renders."""
    return int(load_meta(root)["scene"]["instances"])


def load_sim_training(root, train_frames: int | None = None, val_frames: int | None = None,
                      progress: bool = False) -> tuple[dict, dict, PreprocessConfig, dict]:
    """What `inseggan train` learns from in a simulated data set: (train split, val split, their
    preprocessing, a description for the checkpoint: source, path, frame counts, the parts per
    bin and the camera, which sets the template's scale). `*_frames` keep the first scenes only."""
    prep = sim_preprocess_config(root)
    train = load_sim_split(root, "train", prep, limit=train_frames, progress=progress)
    val = load_sim_split(root, "val", prep, limit=val_frames)
    info = {"source": "simulated data set", "path": str(root), "train_frames": len(train["x"]),
            "val_frames": len(val["x"]), "instances": parts_per_bin(root),
            "camera": load_meta(root)["scene"]["camera"]}
    return train, val, prep, info


def load_bag(path, cfg: PreprocessConfig | None = None, depth_topic: str | None = None,
             limit: int | None = None, progress: bool = False) -> dict:
    """Every depth frame of a rosbag2 bag (bags.read_frames), preprocessed with prepare().

    cfg None = PreprocessConfig(): bin and floor found in every frame. `labels` is the ground
    truth when every frame has it (simulated bags), else None. Raises bags.BagError for bag
    problems and ValueError for frames prepare() cannot use."""
    cfg = PreprocessConfig() if cfg is None else cfg
    if limit is not None and limit < 0:
        raise ValueError(f"limit must be >= 0 or None, got {limit}")
    rows: list[dict] = []
    stamps: list[int] = []
    all_labelled = True
    frames = bags.read_frames(path, depth_topic=depth_topic, limit=limit) if limit != 0 else ()
    for frame in tqdm(frames, unit="frame", desc=f"loading {Path(path).name}",
                      disable=not progress):
        row = _empty(1, cfg.size)
        try:
            all_labelled &= _store(row, 0, frame.metres(), frame.labels, cfg)
        except ValueError as e:
            raise ValueError(f"{path}: frame {len(rows)} (stamp {frame.stamp_ns}): {e}") from None
        rows.append(row)
        stamps.append(frame.stamp_ns)
    out = ({k: np.concatenate([r[k] for r in rows]) for k in rows[0]} if rows
           else _empty(0, cfg.size))
    if not (rows and all_labelled):
        out["labels"] = None
    out["stamp_ns"] = np.array(stamps, np.int64)
    out["config"] = cfg
    return out


def bag_view(frames: dict) -> dict:
    """Where a bag's frames were cut, for a model trained on them (its checkpoint's data record):
    the median bin region used (margin already shaved) and floor depth at its centre. The
    template's size in metres needs them (`sim.learned.template_scale`) when the preprocessing
    finds the bin in every frame and so stores neither."""
    if not len(frames["x"]):
        raise ValueError("no frames to take the bin region from")
    return {"roi": [int(v) for v in np.median(frames["roi"], axis=0).round()],
            "floor_depth": float(np.median(frames["floor_depth"]))}


# ------------------------------------------------------------------------------ torch
class DepthTensorDataset(torch.utils.data.Dataset):
    """A loaded split as torch tensors: item i is x (1, size, size) float32, or (x, labels)
    with labels (size, size) int64 when return_labels is set.

    augment: random horizontal and vertical flips (each with probability 1/2); rotation: also
    rotate by a uniform angle in [-rotation, +rotation] degrees when augmenting (the reference
    code uses 20), nearest neighbour about the image centre, corners filled with background.
    Both keep background pixels exactly -1. Uses torch's random generator, so DataLoader
    workers draw different augmentations."""

    def __init__(self, data: dict, augment: bool = False, rotation: float = 0.0,
                 return_labels: bool = False):
        x = np.asarray(data["x"])
        if x.ndim != 4 or x.shape[1] != 1 or x.shape[2] != x.shape[3]:
            raise ValueError(f"data['x'] has shape {x.shape}; valid: (N, 1, size, size)")
        if not (math.isfinite(rotation) and 0 <= rotation <= 180):
            raise ValueError(f"rotation {rotation!r} invalid; valid: degrees in [0, 180]")
        if return_labels and data.get("labels") is None:
            raise ValueError("return_labels needs data['labels'], and this data has none")
        self.x = torch.from_numpy(np.ascontiguousarray(x, np.float32))
        self.labels = (torch.from_numpy(np.asarray(data["labels"]).astype(np.int64))
                       if return_labels else None)
        self.augment, self.rotation = bool(augment), float(rotation)

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, i: int):
        x = self.x[i]
        lab = self.labels[i][None] if self.labels is not None else None
        if self.augment:
            dims = [d for d, flip in zip((2, 1), torch.rand(2) < 0.5) if flip]  # h, v
            if dims:
                x = torch.flip(x, dims)
                lab = torch.flip(lab, dims) if lab is not None else None
            if self.rotation > 0:
                angle = (torch.rand(()).item() * 2 - 1) * self.rotation
                x, lab = rotate(x, angle, lab)
        if lab is None:
            return x
        return x, lab[0]


def rotate(x: torch.Tensor, degrees: float, labels: torch.Tensor | None = None
           ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Rotate (C, H, W) images (and (1, H, W) labels) by `degrees` about the centre,
    counter-clockwise as displayed with row 0 at the top (90 is torch.rot90(x, 1, (1, 2))),
    nearest neighbour; what comes from outside is background (-1 in x, 0 in labels). Every
    output value is an input value or background."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    theta = torch.tensor([[[c, -s, 0.0], [s, c, 0.0]]], dtype=torch.float32)
    h, w = x.shape[-2:]
    parts = [x.float(), torch.ones(1, h, w)]  # the ones say which pixels came from inside
    if labels is not None:
        parts.append(labels.float())
    stack = torch.cat(parts)[None]
    grid = torch.nn.functional.affine_grid(theta, list(stack.shape), align_corners=False)
    out = torch.nn.functional.grid_sample(stack, grid, mode="nearest", padding_mode="zeros",
                                          align_corners=False)[0]
    k = x.shape[0]
    inside = out[k] > 0.5
    x_out = torch.where(inside, out[:k], torch.full_like(out[:k], -1.0))
    lab_out = out[k + 1:].round().to(labels.dtype) if labels is not None else None
    return x_out, lab_out
