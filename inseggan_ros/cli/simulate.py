"""Simulated bins: `simulate` (a data set), `simulate-bag` (a recording) and `contact-sheet`
(a picture of every part)."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from inseggan_ros.cli import common


def _camera_from_bag(args):
    """--camera-from: (camera, bin inner size, one line saying so) estimated from a bag's
    depth frames and their camera info (sim.user_camera)."""
    from inseggan_ros.sim.user_camera import camera_from_bag

    cam, est, line = camera_from_bag(args.camera_from, args.topic)
    return cam, est["bin_inner_size"], line


def cmd_simulate(args) -> int:
    from dataclasses import replace

    from inseggan_ros.sim.dataset import DatasetSpec, generate

    if args.camera_from is not None and args.camera is not None:
        raise ValueError("--camera-from and --camera are mutually exclusive; valid: one of them")
    args.camera = args.camera or "default"
    scene = common.scene_config(args)
    if args.camera_from is not None:
        cam, size, line = _camera_from_bag(args)
        print(line)
        if args.width is not None or args.height is not None:
            cam = cam.resized(args.width or cam.width, args.height or cam.height)
        scene = replace(scene, **common.cell(args, cam,
                                             replace(scene.bin, inner_size=tuple(size))))
    spec = DatasetSpec.from_fractions(scene, args.count, args.split,
                                      seed=args.seed, shard_size=args.shard_size)
    t0 = time.perf_counter()
    meta = generate(spec, args.out, workers=args.workers, bags=args.bags,
                    bag_encoding=args.bag_encoding, overwrite=args.overwrite,
                    progress=not args.quiet)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"simulated {sum(meta['counts'].values())} scenes of {args.instances} x {args.object} "
          f"({', '.join(f'{k} {v}' for k, v in meta['counts'].items())}) into {args.out}")
    print(f"  {meta['scenes_per_second']:.1f} scenes/s with {args.workers} worker(s), "
          f"{time.perf_counter() - t0:.1f} s in all, {size / 1e6:.1f} MB on disk"
          + (f", bags: {', '.join(meta['bags'].values())}" if meta["bags"] else ""))
    if meta["repiled_scenes"]:
        print(f"  {meta['repiled_scenes']} scene(s) piled again: a part bounced out of the bin "
              "in every drop of the seed's own pile")
    return 0


def cmd_simulate_bag(args) -> int:
    from inseggan_ros.io.bags import BagWriter, CameraInfo
    from inseggan_ros.sim.dataset import BAG_PERIOD_NS, BAG_START_NS, scene_seed
    from inseggan_ros.sim.scene import BinSimulator
    from tqdm import tqdm

    cfg = common.scene_config(args)
    if args.count < 1:
        raise ValueError(f"count must be >= 1, got {args.count}")
    period = int(1e9 / args.rate) if args.rate > 0 else BAG_PERIOD_NS
    info = CameraInfo.from_camera(cfg.camera)
    with BinSimulator(cfg) as sim, BagWriter(args.out, encoding=args.encoding,
                                             storage=args.storage,
                                             compression=args.compression) as w:
        for k in tqdm(range(args.count), desc="simulating", unit="frame", disable=args.quiet):
            s = sim.render(scene_seed(args.seed, "test", k))
            w.write(BAG_START_NS + k * period, s.depth, s.labels, info)
    size = sum(f.stat().st_size for f in Path(args.out).rglob("*") if f.is_file())
    print(f"wrote {args.out}: {args.count} frames of {args.instances} x {args.object}, "
          f"{cfg.camera.width}x{cfg.camera.height} {args.encoding}, {args.storage} "
          f"({w.compression}), "
          f"{size / 1e6:.1f} MB")
    return 0


def cmd_contact_sheet(args) -> int:
    from inseggan_ros.core import viz
    from inseggan_ros.sim.objects import OBJECTS
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    base = common.scene_config(args)
    rows, titles = [[], [], []], []
    for name in OBJECTS:
        cfg = SceneConfig(**{**base.__dict__, "object": name})
        with BinSimulator(cfg) as sim:
            for k in range(args.per_object):
                s = sim.render(args.seed + k)
                rows[0].append(viz.colorize_depth(s.depth))
                rows[1].append(viz.colorize_labels(s.labels))
                rows[2].append(viz.overlay(s.depth, s.labels))
                titles.append(name)
    viz.save_sheet(args.out, rows, col_titles=titles,
                   row_titles=["depth", "ground-truth labels", "overlay"])
    print(f"wrote {args.out}: {len(OBJECTS)} objects x {args.per_object} scene(s)")
    return 0


def add_simulate(sub) -> argparse.ArgumentParser:
    """The `simulate` command's options."""
    p = sub.add_parser("simulate", help="simulate a data set of bins (npz shards, optional bags)")
    common.add_scene_args(p)
    p.add_argument("--count", type=int, default=1000, help="scenes in all (default 1000)")
    p.add_argument("--split", type=common.fractions, default=(0.8, 0.1, 0.1),
                   help="train,val,test fractions (default 0.8,0.1,0.1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--shard-size", type=int, default=128)
    p.add_argument("--bags", action="store_true", help="also write a rosbag2 (MCAP) per split")
    p.add_argument("--bag-encoding", default="16UC1", choices=["16UC1", "32FC1"])
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--camera-from", type=Path, metavar="BAG",
                   help="the camera (and bin inner size) estimated from up to 30 depth frames "
                        "of a bag with a sensor_msgs/CameraInfo beside them, instead of "
                        "--camera PRESET (--tilt, --roll, --bin-offset, --mount-height, "
                        "--bin-size, --width, --height still override)")
    p.add_argument("--topic", help="with --camera-from: the depth topic (default: auto)")
    p.set_defaults(func=cmd_simulate, camera=None)  # None: not given (default preset)
    return p


def add_simulate_bag(sub) -> argparse.ArgumentParser:
    """The `simulate-bag` command's options."""
    p = sub.add_parser("simulate-bag", help="simulate bins straight into a rosbag2 bag")
    common.add_scene_args(p)
    p.add_argument("--count", type=int, default=20, help="frames (default 20)")
    p.add_argument("--seed", type=int, default=0,
                   help="frame k is scene_seed(seed, 'test', k), as bin_replay publishes")
    p.add_argument("--rate", type=float, default=10.0, help="recorded frame rate, Hz")
    p.add_argument("--encoding", default="16UC1", choices=["16UC1", "32FC1"])
    p.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"])
    p.add_argument("--compression", choices=["zstd", "none"],
                   help="MCAP chunk compression (default zstd for mcap, none for sqlite3)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, type=Path, help="bag directory to create")
    p.set_defaults(func=cmd_simulate_bag)
    return p


def add_contact_sheet(sub) -> argparse.ArgumentParser:
    """The `contact-sheet` command's options."""
    p = sub.add_parser("contact-sheet", help="PNG of a simulated bin of every object")
    common.add_scene_args(p)
    p.add_argument("--per-object", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="contact_sheet.png")
    p.set_defaults(func=cmd_contact_sheet)
    return p
