"""The main job, one command (`make demo`): a simulated bin segmented live over DDS.

Starts two processes, resolved as `ros2 run inseggan_ros <name>` resolves them:
  * bin_replay publishes simulated bins (depth + ground-truth labels, the test scenes of seed 0);
  * segmenter (the shipped model) subscribes to the depth and publishes labels.
This process listens like any downstream node: it prints, per frame, the end-to-end latency
(depth stamp -> labels received) and the mIoU of the labels against the simulator's ground truth
(with K-Means on the same frame for reference), then a summary; it writes an overlay contact sheet
(PNG) and an MCAP bag of the inputs and outputs, and reads the bag back with rosbags.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def _executable(name: str) -> str:
    from ament_index_python.packages import get_package_prefix

    return str(Path(get_package_prefix("inseggan_ros")) / "lib" / "inseggan_ros" / name)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@dataclass
class _Received:
    """What this process heard, by stamp: (arrival ns, array) of each depth frame, ground-truth
    label image and segmenter label image; the stamps shown so far, in order, and their
    scores."""

    depth: dict = field(default_factory=dict)
    gt: dict = field(default_factory=dict)
    seg: dict = field(default_factory=dict)
    done: list = field(default_factory=list)
    scores: list = field(default_factory=list)  # (mIoU, K-Means mIoU, latency ms) of each


def _parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="inseggan-demo", description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--object", default="cylinder")
    ap.add_argument("--model", default="", help="segmenter model_path ('' = shipped default)")
    ap.add_argument("--rate", type=float, default=2.0)
    ap.add_argument("--out", type=Path, default=Path("demo_out"))
    ap.add_argument("--timeout", type=float, default=120.0)
    return ap.parse_args(argv)


def _scorer():
    """-> score(labels, depth, gt): (mIoU of the labels, of K-Means on the same frame).
    Imported here, before the nodes start, so that no frame waits for scikit-learn."""
    from inseggan_ros.core.metrics import miou
    from inseggan_ros.evaluation.baselines import kmeans

    def score(labels, depth, gt):
        return miou(labels, gt), miou(kmeans(-depth, gt > 0, int(gt.max())), gt)

    return score


def _subscribe(node, rx: _Received) -> None:
    """Depth, ground truth (from bin_replay) and the segmenter's labels, kept by stamp."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from inseggan_ros.ros import conversions

    def keep(store, decode):
        def cb(msg: Image):
            store[conversions.stamp_to_ns(msg.header.stamp)] = (time.time_ns(), decode(msg))
        return cb

    node.create_subscription(Image, "camera/depth/image_rect_raw",
                             keep(rx.depth, conversions.depth_to_metres), qos_profile_sensor_data)
    node.create_subscription(Image, "camera/depth/instance_labels",
                             keep(rx.gt, conversions.image_to_numpy), qos_profile_sensor_data)
    node.create_subscription(Image, "segmenter/labels",
                             keep(rx.seg, conversions.image_to_numpy), 10)


def _start(node, args):
    """The segmenter, and once it is up (its labels publisher is seen), bin_replay ->
    (segmenter process, bin_replay process, time.monotonic() when the segmenter started)."""
    import rclpy

    model = ["-p", f"model_path:={args.model}"] if args.model else []
    segmenter = subprocess.Popen(
        [_executable("segmenter"), "--ros-args", *model], stderr=subprocess.PIPE, text=True)
    # the segmenter is up (its labels publisher is seen) before the first frame is sent
    t0 = time.monotonic()
    while node.count_publishers("segmenter/labels") == 0 and segmenter.poll() is None \
            and time.monotonic() - t0 < args.timeout:
        rclpy.spin_once(node, timeout_sec=0.1)
    replay = subprocess.Popen(
        [_executable("bin_replay"), "--ros-args", "-p", f"object:={args.object}",
         "-p", f"rate:={args.rate}", "-p", f"max_frames:={4 * args.frames + 10}"],
        stderr=subprocess.PIPE, text=True)
    print(f"demo: bin_replay (pid {replay.pid}) publishes simulated {args.object} bins at "
          f"{args.rate} Hz; segmenter (pid {segmenter.pid}) segments them "
          f"(ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")
    return segmenter, replay, t0


def _show_ready(rx: _Received, frames: int, score) -> None:
    """Scores and prints each frame whose depth, ground truth and labels have all arrived."""
    for stamp in sorted(s for s in rx.seg if s not in rx.done and s in rx.depth and s in rx.gt):
        arrival, labels = rx.seg[stamp]
        depth, gt = rx.depth[stamp][1], rx.gt[stamp][1]
        ours, km = score(labels, depth, gt)
        rx.scores.append((ours, km, (arrival - stamp) / 1e6))
        rx.done.append(stamp)
        print(f"{len(rx.done) - 1:>5} {stamp / 1e9:>14.3f} {rx.scores[-1][2]:>12.1f} "
              f"{depth.shape[1]:>4}x{depth.shape[0]:<4} {ours:>6.3f} {km:>7.3f}",
              flush=True)
        if len(rx.done) >= frames:
            break


def _write(args, rx: _Received):
    """The contact sheet of the first frames and the MCAP bag of them all, read back ->
    (sheet, bag, the frames read back, whether their labels are those received)."""
    from inseggan_ros.core import viz
    from inseggan_ros.io import bags

    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for stamp in rx.done[:6]:
        depth, gt, lab = rx.depth[stamp][1], rx.gt[stamp][1], rx.seg[stamp][1]
        rows.append([viz.colorize_depth(depth), viz.overlay(depth, lab), viz.overlay(depth, gt)])
    sheet = viz.save_sheet(args.out / "segmentation_sheet.png", rows,
                           col_titles=["depth", "segmenter labels", "ground truth"])
    bag = args.out / f"demo_{time.strftime('%Y%m%d_%H%M%S')}"
    with bags.BagWriter(bag) as w:
        for stamp in rx.done:
            w.write(stamp, rx.depth[stamp][1], rx.gt[stamp][1])
            w.write_image("/segmenter/labels", stamp, rx.seg[stamp][1], "mono8")
    back = bags.read_all(bag, labels_topic="/segmenter/labels")
    same = all(np.array_equal(f.labels, rx.seg[f.stamp_ns][1]) for f in back)
    return sheet, bag, back, same


def main(argv=None) -> int:
    args = _parse(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from inseggan_ros.ros.dds import use_large_frames_profile

    print(f"demo: Fast DDS profile {use_large_frames_profile()}")

    import rclpy

    score = _scorer()
    rclpy.init()
    node = rclpy.create_node("inseggan_demo")
    rx = _Received()
    _subscribe(node, rx)
    segmenter, replay, t0 = _start(node, args)
    print(f"{'frame':>5} {'stamp [s]':>14} {'latency [ms]':>12} {'size':>9} {'mIoU':>6} "
          f"{'K-Means':>7}")
    try:
        while len(rx.done) < args.frames and time.monotonic() - t0 < args.timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
            _show_ready(rx, args.frames, score)
            if segmenter.poll() is not None or (replay.poll() is not None and
                                                time.monotonic() - t0 > args.timeout / 2):
                break
    finally:
        _stop(replay)
        _stop(segmenter)
        node.destroy_node()
        rclpy.try_shutdown()

    if len(rx.done) < args.frames:
        err = (segmenter.stderr.read() or "") + (replay.stderr.read() or "")
        print(f"demo: error: {len(rx.done)} of {args.frames} frames segmented in "
              f"{args.timeout:.0f} s\n{err}", file=sys.stderr)
        return 1
    sheet, bag, back, same = _write(args, rx)
    s, done = np.array(rx.scores), rx.done
    print(f"demo: {len(done)} frames segmented; end-to-end latency (stamp -> labels received) "
          f"p50 {np.percentile(s[:, 2], 50):.1f} ms, p99 {np.percentile(s[:, 2], 99):.1f} ms; "
          f"mIoU {s[:, 0].mean():.3f} (K-Means on the same frames {s[:, 1].mean():.3f})")
    sent = sum(1 for s_ in rx.depth if s_ <= done[-1])
    print(f"demo: bin_replay published {sent} frames up to the last one shown; the segmenter "
          f"answered {sum(1 for s_ in rx.seg if s_ <= done[-1])} (with keep-last 1 it drops "
          f"the frames that arrive while it is busy)")
    print(f"demo: wrote {sheet} and {bag} (read back: {len(back)} frames, segmenter labels "
          f"{'identical' if same else 'DIFFERENT'})")
    return 0 if len(back) == len(done) and same else 1


if __name__ == "__main__":
    sys.exit(main())
