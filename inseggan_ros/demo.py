"""The main job, one command (`make demo`): a simulated bin streamed over DDS and received.

Starts `bin_replay` (resolved as `ros2 run inseggan_ros bin_replay` resolves it) as its own
process, publishing simulated bins; this process subscribes like any downstream node would,
prints each frame as it arrives (transport latency, instances in the ground truth), and at the
end writes an overlay contact sheet (PNG) and an MCAP bag of what it received, which it reads
back to check. When a trained model is shipped (models/), the segmenter joins this pipeline.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _executable(name: str) -> str:
    from ament_index_python.packages import get_package_prefix

    return str(Path(get_package_prefix("inseggan_ros")) / "lib" / "inseggan_ros" / name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="inseggan-demo", description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--object", default="cylinder")
    ap.add_argument("--rate", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=Path("demo_out"))
    ap.add_argument("--timeout", type=float, default=120.0)
    args = ap.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from . import bags, viz
    from .nodes import conversions

    rclpy.init()
    node = rclpy.create_node("inseggan_demo")
    received: list[tuple] = []
    labels_by_stamp: dict[int, np.ndarray] = {}

    def on_labels(msg: Image):
        labels_by_stamp[conversions.stamp_to_ns(msg.header.stamp)] = conversions.image_to_numpy(msg)

    def on_depth(msg: Image):
        now = time.time_ns()
        stamp = conversions.stamp_to_ns(msg.header.stamp)
        received.append((stamp, now, msg.encoding, conversions.depth_to_metres(msg)))

    node.create_subscription(Image, "camera/depth/instance_labels", on_labels,
                             qos_profile_sensor_data)
    node.create_subscription(Image, "camera/depth/image_rect_raw", on_depth,
                             qos_profile_sensor_data)
    replay = subprocess.Popen(
        [_executable("bin_replay"), "--ros-args", "-p", f"object:={args.object}",
         "-p", f"rate:={args.rate}", "-p", f"max_frames:={args.frames + 10}"],
        stderr=subprocess.PIPE, text=True)
    print(f"demo: bin_replay (pid {replay.pid}) publishes simulated {args.object} bins at "
          f"{args.rate} Hz; receiving {args.frames} frames over DDS "
          f"(ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")
    print(f"{'frame':>5} {'stamp [s]':>16} {'latency [ms]':>12} {'size':>9} {'instances':>9}")
    t0 = time.monotonic()
    shown = 0
    try:
        while shown < args.frames and time.monotonic() - t0 < args.timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
            while shown < min(len(received), args.frames):
                stamp, now, enc, depth = received[shown]
                rclpy.spin_once(node, timeout_sec=0.01)  # its labels, if still in flight
                lab = labels_by_stamp.get(stamp)
                n = len(np.unique(lab)) - 1 if lab is not None else -1
                print(f"{shown:>5} {stamp / 1e9:>16.3f} {(now - stamp) / 1e6:>12.2f} "
                      f"{depth.shape[1]:>4}x{depth.shape[0]:<4} {n:>9}")
                shown += 1
            if replay.poll() is not None:
                break
    finally:
        if replay.poll() is None:
            replay.send_signal(signal.SIGINT)
        try:
            replay.wait(timeout=15)
        except subprocess.TimeoutExpired:
            replay.kill()
        node.destroy_node()
        rclpy.try_shutdown()

    frames = received[:args.frames]
    if len(frames) < args.frames:
        err = replay.stderr.read() if replay.stderr else ""
        print(f"demo: error: received {len(frames)} of {args.frames} frames in "
              f"{args.timeout:.0f} s\n{err}", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for stamp, _, _, depth in frames[:8]:
        lab = labels_by_stamp.get(stamp, np.zeros(depth.shape, np.uint8))
        rows.append([viz.colorize_depth(depth), viz.overlay(depth, lab)])
    sheet = viz.save_sheet(args.out / "received_sheet.png", rows,
                           col_titles=["received depth", "ground truth overlay"])
    bag = args.out / f"received_{time.strftime('%Y%m%d_%H%M%S')}"
    bags.write_frames(bag, [(s, d, labels_by_stamp.get(s), None) for s, _, _, d in frames])
    back = bags.read_all(bag)
    lat = np.array([(now - s) / 1e6 for s, now, _, _ in frames])
    print(f"demo: received {len(frames)} frames; transport latency p50 {np.percentile(lat, 50):.2f}"
          f" ms, p99 {np.percentile(lat, 99):.2f} ms; labels for "
          f"{sum(s in labels_by_stamp for s, *_ in frames)}/{len(frames)}")
    print(f"demo: wrote {sheet} and {bag} (read back: {len(back)} frames)")
    print("demo: no trained model is shipped yet (models/), so the segmenter is not run")
    return 0 if len(back) == len(frames) else 1


if __name__ == "__main__":
    sys.exit(main())
