"""Simulator throughput: scenes per second on one core, and with several worker processes."""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from inseggan_ros.sim.scene import BinSimulator, SceneConfig

PAPER_SECONDS_PER_SCENE = 2.0  # the paper's PhysX pipeline (InSeGAN, Sec. 5)


def _worker(args) -> int:
    cfg, seeds = args
    with BinSimulator(SceneConfig.from_dict(cfg)) as sim:
        for s in seeds:
            sim.render(s)
    return len(seeds)


def run(cfg: SceneConfig, scenes: int = 100, workers: int = 2, warmup: int = 3) -> dict:
    """Measure and return figures (also printed by the CLI)."""
    with BinSimulator(cfg) as sim:
        for s in range(warmup):
            sim.render(10_000 + s)
        phys, rend = [], []
        t0 = time.perf_counter()
        for s in range(scenes):
            sim.render(s)
            phys.append(sim.last_timing["physics"])
            rend.append(sim.last_timing["render"])
        single = time.perf_counter() - t0
    result = {
        "object": cfg.object, "instances": cfg.instances,
        "resolution": f"{cfg.camera.width}x{cfg.camera.height}", "scenes": scenes,
        "one_core_scenes_per_s": scenes / single,
        "ms_per_scene": 1000 * single / scenes,
        "ms_physics": 1000 * float(np.mean(phys)), "ms_render": 1000 * float(np.mean(rend)),
        "speedup_vs_paper_physx": PAPER_SECONDS_PER_SCENE / (single / scenes),
    }
    if workers > 1:
        per = [list(range(20_000 + k * scenes, 20_000 + k * scenes + scenes // workers))
               for k in range(workers)]
        with ProcessPoolExecutor(workers) as pool:
            list(pool.map(_worker, [(cfg.to_dict(), [20_000 + k]) for k in range(workers)]))
            t0 = time.perf_counter()
            done = sum(pool.map(_worker, [(cfg.to_dict(), seeds) for seeds in per]))
            elapsed = time.perf_counter() - t0
        result.update({"workers": workers, "parallel_scenes_per_s": done / elapsed,
                       "parallel_scaling": (done / elapsed) / result["one_core_scenes_per_s"]})
    return result
