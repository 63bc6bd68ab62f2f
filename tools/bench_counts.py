"""Bins that hold fewer parts than the model's n (`python -m tools.bench_counts`): instance
counts and mIoU of shipped models on simulated bins of 0, 1, n - 1 and n parts.

A robot empties the bin it picks from, so a model of n parts meets every count from n down to
0 in one recording. For each model and count this simulates `--frames` bins of the model's own
part, camera and noise (its card's; a model learned from a recording has its camera estimated
on the card, and the recordings were simulated with RealSense noise), fresh seeds, segments
each frame at the input's resolution as the segmenter node does (the model's shipped settings,
or those of a parameters file), and prints per model and count:

  count right   frames whose number of instances (labels present in the output) equals the
                parts in view: ground-truth instances of at least MIN_VISIBLE model pixels
                (`evaluation.selfcheck.MIN_VISIBLE_PIXELS` cells of the 64 x 64 grid);
  counts        how many frames gave each number of instances;
  mIoU          the paper's mIoU (`core.metrics`) at the input's resolution (an empty bin has
                none: its row says how many frames gave no instance).

Scenes can be kept in `--scenes DIR` (one npz per model, count and seed) so that another
checkout (a base commit) segments the very same frames:

    python -m tools.bench_counts --models cylinder hex_nut --frames 20 --json out.json
"""
from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
MIN_VISIBLE = 8  # model pixels: a part showing fewer is not counted as in view


def scene_source(model_dir: Path) -> dict:
    """The part, camera and noise a model's bins are simulated with, from its card."""
    card = json.loads((model_dir / "card.json").read_text())
    if "camera" in card:  # a model of a simulated data set
        return {"object": card["object"], "camera": card["camera"], "noise": card["noise"]}
    from dataclasses import asdict

    from inseggan_ros.sim.noise import get_noise

    return {"object": card["shape"]["object"], "camera": card["training_data"]["camera"],
            "noise": asdict(get_noise("realsense"))}


def frame_seed(seed: int, count: int, index: int) -> int:
    """The simulator seed of frame `index` of the bins of `count` parts."""
    return int(np.random.SeedSequence([seed, count, index]).generate_state(1, np.uint32)[0])


def scenes(source: dict, count: int, seeds: list[int], cache: Path | None):
    """(seed, depth metres, labels) of each seed's bin of `count` parts, from `cache` where
    there (the simulator's only where not: a base checkout may lack bins of 0 parts)."""
    sim = None
    digest = hashlib.sha1(json.dumps(source, sort_keys=True).encode()).hexdigest()[:10]
    key = f"{source['object']}_{digest}"
    try:
        for s in seeds:
            path = cache / key / f"{count}_{s}.npz" if cache is not None else None
            if path is not None and path.is_file():
                with np.load(path) as z:
                    yield s, z["depth"], z["labels"]
                continue
            if sim is None:
                sim = _simulator(source, count)
            scene = sim.render(s)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(path, depth=scene.depth, labels=scene.labels)
            yield s, scene.depth, scene.labels
    finally:
        if sim is not None:
            sim.close()


def _simulator(source: dict, count: int):
    from inseggan_ros.sim.camera import CameraConfig
    from inseggan_ros.sim.noise import NoiseConfig
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    cam = dict(source["camera"], bin_offset=tuple(source["camera"]["bin_offset"]))
    return BinSimulator(SceneConfig(object=source["object"], instances=count,
                                    camera=CameraConfig(**cam),
                                    noise=NoiseConfig(**source["noise"])))


def visible_parts(labels: np.ndarray, roi, size: int = 64) -> int:
    """Ground-truth instances of at least MIN_VISIBLE cells of the model's grid over `roi`."""
    x0, y0, x1, y1 = roi
    cell = (x1 - x0) / size * (y1 - y0) / size
    areas = np.bincount(labels.ravel())[1:]
    return int((areas >= MIN_VISIBLE * cell).sum())


def measure(seg, settings, source: dict, count: int, seeds: list[int], cache) -> dict:
    """One model on the bins of `count` parts -> counts, mIoU, time per frame."""
    from inseggan_ros.core.metrics import miou

    right, hist, scores, ms, wrong = 0, {}, [], [], []
    for s, depth, labels in tqdm(scenes(source, count, seeds, cache), total=len(seeds),
                                 desc=f"{source['object']} x{count}", leave=False):
        t0 = time.perf_counter()
        out = seg(depth, reconstruction=False, settings=settings)
        ms.append((time.perf_counter() - t0) * 1e3)
        got = len(np.unique(out.labels)) - 1
        want = visible_parts(labels, out.roi)
        hist[got] = hist.get(got, 0) + 1
        right += got == want
        if got != want:
            wrong.append({"seed": s, "instances": got, "in_view": want})
        if labels.any():
            scores.append(miou(out.labels, labels))
    return {"parts": count, "frames": len(seeds), "count_right": right / len(seeds),
            "counts": {str(k): hist[k] for k in sorted(hist)},
            "miou": float(np.mean(scores)) if scores else None,
            "ms_per_frame": float(np.median(ms)), "wrong": wrong}


def parse_count(text: str, n: int) -> int:
    """'3', 'N' or 'N-1' (N: the model's n) -> a count in 0..n."""
    m = re.fullmatch(r"\s*(N|\d+)\s*(?:-\s*(\d+))?\s*", text)
    if m is None:
        raise ValueError(f"count {text!r} invalid; valid: an integer, N or N-k (N: the "
                         "model's n), e.g. 0 1 N-1 N")
    value = (n if m[1] == "N" else int(m[1])) - int(m[2] or 0)
    return min(n, max(0, value))


def model_settings(seg, args):
    """The model's settings, with the --params file and the --set pairs over them."""
    from inseggan_ros.core.settings import apply, read_params_file

    cfg = seg.inference
    if args.params is not None:
        cfg = apply(cfg, read_params_file(args.params))
    pairs = dict(p.split("=", 1) for p in args.set)
    return apply(cfg, {k: (int(v) if v.lstrip("-").isdigit() else v) for k, v in pairs.items()})


def model_dir(name: str) -> Path | None:
    """A shipped model's name (a folder of models/) or a model folder -> its folder (None:
    neither holds a model.pt)."""
    for path in (REPO / "models" / name, Path(name)):
        if (path / "model.pt").is_file():
            return path
    return None


def run_model(name: str, args) -> list[dict]:
    import torch

    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    folder = model_dir(name)
    seg = Segmenter.from_checkpoint(folder / "model.pt", device="cpu")
    settings = model_settings(seg, args)
    n = seg.model_cfg.n_instances
    counts = sorted({parse_count(c, n) for c in args.counts})
    source = scene_source(model_dir(args.bins_of) if args.bins_of else folder)
    rows = []
    for count in counts:
        seeds = [frame_seed(args.seed, count, i) for i in range(args.frames)]
        row = measure(seg, settings, source, count, seeds, args.scenes)
        rows.append({"model": name, "n": n, **row})
    return rows


def print_table(rows: list[dict]) -> None:
    print(f"{'model':22s} {'n':>2s} {'parts':>5s} {'frames':>6s} {'count right':>11s}  "
          f"{'mIoU':>6s} {'ms':>6s}  instances: frames")
    for r in rows:
        m = "-" if r["miou"] is None else f"{r['miou']:.3f}"
        hist = " ".join(f"{k}:{v}" for k, v in r["counts"].items())
        print(f"{r['model']:22s} {r['n']:2d} {r['parts']:5d} {r['frames']:6d} "
              f"{r['count_right']:11.1%}  {m:>6s} {r['ms_per_frame']:6.1f}  {hist}")


def _commit() -> str | None:
    """The commit of the checkout whose `inseggan_ros` segments (PYTHONPATH may name
    another's: a base commit's), and whether its files differ from it."""
    import inseggan_ros

    root = Path(inseggan_ros.__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, check=True).stdout
        return head + ("+changes" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_counts",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--models", nargs="+",
                    default=["cylinder", "hex_nut", "wooden_block", "cylinder_tilted"],
                    help="shipped models (folders of models/) or model folders (a loop's "
                         "OUT/model)")
    ap.add_argument("--bins-of", metavar="MODEL",
                    help="simulate every model's bins with this model's part, camera and noise "
                         "(its card's), so that models of one part segment the same frames "
                         "(default: each model's own card)")
    ap.add_argument("--counts", nargs="+", default=["0", "1", "N-1", "N"],
                    help="parts in the bin; N is the model's n (default: 0 1 N-1 N)")
    ap.add_argument("--frames", type=int, default=20, help="frames per model and count")
    ap.add_argument("--seed", type=int, default=2027, help="seeds of the simulated bins")
    ap.add_argument("--params", type=Path,
                    help="a segmenter parameters file (config/quality.yaml) over the model's "
                         "settings (default: the model's own)")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="segmenter parameters over those, e.g. centre_votes=off")
    ap.add_argument("--scenes", type=Path, help="keep and reuse the simulated bins here")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error(f"--frames {args.frames}: valid: 1 or more")
    given = [("--models", m) for m in args.models] + [("--bins-of", args.bins_of)] * bool(
        args.bins_of)
    for flag, name in given:
        if model_dir(name) is None:
            ap.error(f"{flag} {name}: no models/{name}/model.pt and no folder with a model.pt; "
                     "valid: " + ", ".join(sorted(p.parent.name
                                                  for p in REPO.glob("models/*/model.pt")))
                     + " (models/), or a model folder")
    try:
        [parse_count(c, 5) for c in args.counts]
    except ValueError as e:
        ap.error(f"--counts: {e}")
    if any("=" not in p for p in args.set):
        ap.error(f"--set {args.set}: valid: NAME=VALUE pairs, e.g. centre_votes=off")
    rows = [r for name in args.models for r in run_model(name, args)]
    print_table(rows)
    if args.json is not None:
        args.json.write_text(json.dumps({"commit": _commit(), "frames": args.frames,
                                         "seed": args.seed, "params": str(args.params),
                                         "set": args.set, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
