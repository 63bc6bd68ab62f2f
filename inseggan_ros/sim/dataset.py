"""Simulated data sets: many bin scenes, split into train / val / test, stored as npz shards.

Layout of a data set directory:
    meta.json                  scene config, seed, splits, shard list, timing
    train/shard-00000.npz      depth (N, H, W) float32 metres, labels (N, H, W) uint8,
    val/...                    seeds (N,) int64, instances (N,) int64 (parts in the scene),
    test/...                   poses (N, n, 7) float32 (NaN past a scene's own count)
    bags/<split>/              rosbag2 (MCAP) of the same frames, when asked for
Scene i of a split is simulated from a seed derived from (seed, split, i) alone, so the data set is
the same whatever the number of worker processes. Everything is written into a hidden temporary
directory that is renamed into place at the end: an interrupted run leaves nothing behind.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from inseggan_ros.sim.scene import BinSimulator, Scene, SceneConfig

FORMAT = "inseggan-sim-v1"
SPLITS = ("train", "val", "test")
BAG_PERIOD_NS = 100_000_000  # frames 0.1 s apart in bags
BAG_START_NS = 1_700_000_000 * 1_000_000_000


def scene_seed(seed: int, split: str, index: int) -> int:
    state = np.random.SeedSequence([int(seed), SPLITS.index(split), int(index)])
    return int(state.generate_state(1, np.uint32)[0])


@dataclass(frozen=True)
class DatasetSpec:
    scene: SceneConfig
    counts: dict  # split -> number of scenes
    seed: int = 0
    shard_size: int = 128

    def __post_init__(self):
        for split, n in self.counts.items():
            if split not in SPLITS:
                raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
            if n < 0:
                raise ValueError(f"scene count for {split} must be >= 0, got {n}")
        if sum(self.counts.values()) == 0:
            raise ValueError("data set would be empty: ask for at least one scene")
        if not 1 <= self.shard_size <= 10000:
            raise ValueError(f"shard_size must be in 1..10000, got {self.shard_size}")

    @staticmethod
    def from_fractions(scene: SceneConfig, total: int, fractions=(0.8, 0.1, 0.1), **kw):
        if total < 1:
            raise ValueError(f"count must be >= 1, got {total}")
        if len(fractions) != 3 or any(f < 0 for f in fractions) or sum(fractions) <= 0:
            raise ValueError(f"split fractions {fractions} invalid; valid: three numbers >= 0, "
                             "e.g. 0.8,0.1,0.1")
        f = np.asarray(fractions, float) / sum(fractions)
        val, test = int(round(total * f[1])), int(round(total * f[2]))
        return DatasetSpec(scene, {"train": total - val - test, "val": val, "test": test}, **kw)


# ------------------------------------------------------------------------ worker processes
_SIM: BinSimulator | None = None


def _init_worker(scene_cfg: dict) -> None:
    global _SIM
    _SIM = BinSimulator(SceneConfig.from_dict(scene_cfg))


def _make_shard(task: tuple) -> tuple[str, str, int, int, list[int]]:
    """-> (split, file name, scenes, scenes that had to be piled again, each scene's count)."""
    split, name, seeds, out_dir = task
    scenes, repiled = [], 0
    for s in seeds:
        scenes.append(_SIM.render(s))
        repiled += int(_SIM.last_piles > 1)
    save_shard(Path(out_dir) / split / name, scenes, _SIM.cfg.instances)
    return split, name, len(scenes), repiled, [len(s.poses) for s in scenes]


def save_shard(path: Path, scenes: list[Scene], instances: int | None = None) -> None:
    """Write scenes as one npz shard. Scenes of mixed counts (`SceneConfig.min_instances`)
    share one poses array of `instances` (default: the largest count) rows a scene, NaN past
    each scene's own count, which the shard's `instances` array gives."""
    tmp = path.with_name(path.name + ".tmp")
    counts = np.array([len(s.poses) for s in scenes], np.int64)
    rows = int(counts.max()) if instances is None else int(instances)
    poses = np.full((len(scenes), rows, 7), np.nan, np.float32)
    for i, s in enumerate(scenes):
        poses[i, :len(s.poses)] = s.poses
    with open(tmp, "wb") as f:
        np.savez_compressed(f, depth=np.stack([s.depth for s in scenes]),
                            labels=np.stack([s.labels for s in scenes]),
                            seeds=np.array([s.seed for s in scenes], np.int64),
                            instances=counts, poses=poses)
    os.replace(tmp, path)


# ------------------------------------------------------------------------ generation
def generate(spec: DatasetSpec, out: Path, workers: int = 1, bags: bool = False,
             bag_encoding: str = "16UC1", overwrite: bool = False, progress: bool = True) -> dict:
    """Simulate the data set into `out`; returns its meta data (also in out/meta.json)."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists already; choose another output or pass --overwrite")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the data set is not
    try:
        tasks = []
        for split in SPLITS:
            n = spec.counts.get(split, 0)
            (tmp / split).mkdir()
            for k, start in enumerate(range(0, n, spec.shard_size)):
                seeds = [scene_seed(spec.seed, split, i)
                         for i in range(start, min(n, start + spec.shard_size))]
                tasks.append((split, f"shard-{k:05d}.npz", seeds, str(tmp)))
        total = sum(len(t[2]) for t in tasks)
        t0 = time.perf_counter()
        shards = {s: [] for s in SPLITS}
        parts = {s: {} for s in SPLITS}  # split -> {parts in a scene: scenes}
        repiled = 0
        with ProcessPoolExecutor(workers, initializer=_init_worker,
                                 initargs=(spec.scene.to_dict(),)) as pool, \
                tqdm(total=total, unit="scene", desc="simulating", disable=not progress) as bar:
            for split, name, n, again, counts in pool.map(_make_shard, tasks):
                shards[split].append({"file": f"{split}/{name}", "scenes": n})
                for c in counts:
                    parts[split][str(c)] = parts[split].get(str(c), 0) + 1
                repiled += again
                bar.update(n)
        sim_seconds = time.perf_counter() - t0
        meta = {"format": FORMAT, "scene": spec.scene.to_dict(), "seed": spec.seed,
                "counts": {s: spec.counts.get(s, 0) for s in SPLITS}, "shards": shards,
                "workers": workers, "simulation_seconds": round(sim_seconds, 2),
                "scenes_per_second": round(total / sim_seconds, 2),
                "repiled_scenes": repiled,  # a part bounced out of the first pile (sim.scene)
                "instance_counts": {s: dict(sorted(parts[s].items(), key=lambda kv: int(kv[0])))
                                    for s in SPLITS},
                "bags": {}}
        if bags:
            for split in SPLITS:
                if spec.counts.get(split, 0):
                    write_split_bag(tmp, split, tmp / "bags" / split, spec.scene.camera,
                                    bag_encoding, progress)
                    meta["bags"][split] = f"bags/{split}"
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
        return meta
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_split_bag(root: Path, split: str, bag_path: Path, camera, encoding: str = "16UC1",
                    progress: bool = False) -> int:
    """Write the scenes of one split as a rosbag2 (depth, camera info, ground-truth labels)."""
    from inseggan_ros.io import bags

    info = bags.CameraInfo.from_camera(camera)
    files = sorted((Path(root) / split).glob("shard-*.npz"))

    def frames():
        i = 0
        for f in files:
            with np.load(f) as z:
                for depth, labels in zip(z["depth"], z["labels"]):
                    yield BAG_START_NS + i * BAG_PERIOD_NS, depth, labels, info
                    i += 1

    it = tqdm(frames(), desc=f"bag {split}", unit="frame", disable=not progress)
    return bags.write_frames(bag_path, it, encoding=encoding)


# ------------------------------------------------------------------------ reading
def load_meta(root) -> dict:
    root = Path(root)
    path = root / "meta.json"
    if not path.is_file():
        raise FileNotFoundError(f"{root}: not a simulated data set (no meta.json)")
    meta = json.loads(path.read_text())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
    return meta


def iter_scenes(root, split: str) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(depth metres, labels) of every scene of a split, in order."""
    root = Path(root)
    meta = load_meta(root)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    for shard in meta["shards"][split]:
        with np.load(root / shard["file"]) as z:
            yield from zip(z["depth"], z["labels"])
