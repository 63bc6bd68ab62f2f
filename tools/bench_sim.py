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
    """Measure and return figures (`report` prints them)."""
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


def report(r: dict) -> str:
    """The figures as `make bench` prints them."""
    lines = [f"simulator benchmark: {r['instances']} x {r['object']} at {r['resolution']}, "
             f"{r['scenes']} scenes",
             f"  one core : {r['one_core_scenes_per_s']:7.1f} scenes/s  "
             f"({r['ms_per_scene']:.1f} ms/scene:"
             f" physics {r['ms_physics']:.1f} ms, render {r['ms_render']:.1f} ms)"]
    if "workers" in r:
        lines.append(f"  {r['workers']} workers: {r['parallel_scenes_per_s']:7.1f} scenes/s  "
                     f"(x{r['parallel_scaling']:.2f} of one core)")
    lines.append(f"  vs the paper's PhysX pipeline (~2 s/scene): "
                 f"x{r['speedup_vs_paper_physx']:.0f}")
    if (r["resolution"], r["instances"]) == ("224x224", 5):
        met = "met" if r["one_core_scenes_per_s"] >= 25 else "NOT met"
        lines.append(f"  target >= 25 scenes/s per core (224x224, 5 objects): {met}")
    return "\n".join(lines)


def main(argv=None) -> int:
    """`python -m tools.bench_sim [--scenes 100 --workers 2 --json FILE]` (`make bench`): the
    scene flags of `inseggan simulate`."""
    import argparse

    from inseggan_ros.cli.common import add_scene_args, scene_config

    parser = argparse.ArgumentParser(prog="python -m tools.bench_sim",
                                     description="simulator throughput (scenes/s)")
    add_scene_args(parser)
    parser.add_argument("--scenes", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    r = run(scene_config(args), scenes=args.scenes, workers=args.workers)
    print(report(r))
    if args.json:
        from inseggan_ros.evaluation.evaluate import write_json

        write_json(args.json, r)  # atomic
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
