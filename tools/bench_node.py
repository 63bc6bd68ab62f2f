"""Segmenter node benchmark (`make bench-node`): latency, throughput and memory, measured.

The segmenter runs as its own process (as `ros2 run` starts it), on the shipped model; this
process publishes 1280 x 720 16UC1 depth frames (simulated RealSense-like bins with sensor noise,
a few distinct frames in turn) with their CameraInfo at 30 Hz for 60 s, and subscribes to the
labels and the picks (so that the node computes them). Printed:
  * node latency, message received -> labels published and -> everything published, picks
    included, measured inside the node (p50, p99 over every frame; the node's own
    /diagnostics), and each stage's median and share of the mean: preprocess (message decode,
    bin region, floor, the model's input), network (encoder, renders, centre votes), labels
    (from the renders to the full-resolution label image), picks (computed and published),
    publish (labels and the other images);
  * end-to-end latency as a subscriber sees it (depth stamp -> labels received, -> picks
    received);
  * frames sent, received by the node, answered, and dropped (keep-last 1: a frame that arrives
    while the node is busy replaces the waiting one);
  * the node's peak resident memory (VmHWM of its process);
  * for reference, in this process on the same frames: preprocessing + inference alone, and
    decoding/encoding the Image messages alone.
With `--baseline REF` (a git revision), the segmenter of the code at REF (`git archive` into a
temporary folder, run from there on the same installed model) is measured in the same run on
the same frames, alternately with this tree's (`--rounds` times each, baseline first), and a
table sets each round's figures side by side: a change's figure beside the figure of the code
before it, on a machine whose load varies from minute to minute.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from inseggan_ros.core import settings


def _vm_hwm_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def simulated_frames(count: int, width: int, height: int) -> list[np.ndarray]:
    from inseggan_ros.core.image_codec import metres_to_depth
    from inseggan_ros.sim.camera import get_camera
    from inseggan_ros.sim.dataset import scene_seed
    from inseggan_ros.sim.noise import get_noise
    from inseggan_ros.sim.scene import BinSimulator, SceneConfig

    cfg = SceneConfig(object="cylinder", camera=get_camera("realsense_d435", width, height),
                      noise=get_noise("realsense"))
    with BinSimulator(cfg) as sim:
        return [metres_to_depth(sim.render(scene_seed(7, "test", k)).depth, "16UC1")
                for k in range(count)]


def in_process_reference(frames, model_path: str, params: dict, repeats: int = 3,
                         superpixel_thread: bool = False) -> dict:
    """Inference alone and conversion alone, in this process (one torch thread, and the
    superpixel thread as the node's `superpixel_thread`), for comparison."""
    import torch

    from inseggan_ros.core.image_codec import depth_to_metres
    from inseggan_ros.ros import conversions
    from inseggan_ros.ros.segmenter import resolve_model
    from inseggan_ros.runtime.preprocess import BIN_FRAMES, node_defaults
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(resolve_model(model_path), device="cpu",
                                    superpixel_thread=superpixel_thread)
    # as the node: a checkpoint without settings runs realtime.yaml's
    cfg = settings.apply(settings.file_base(seg.inference, seg.stored_settings), params)
    prep = node_defaults(seg.prep_cfg,
                         [depth_to_metres(f, "16UC1") for f in frames[:BIN_FRAMES]])
    infer_ms, conv_ms = [], []
    for _ in range(repeats):
        for raw in frames:
            msg = conversions.numpy_to_image(raw, "16UC1")
            t0 = time.perf_counter()
            depth = conversions.depth_to_metres(msg)
            t1 = time.perf_counter()
            out = seg(depth, prep, reconstruction=False, settings=cfg)
            t2 = time.perf_counter()
            conversions.numpy_to_image(out.labels, "mono8", msg.header)
            t3 = time.perf_counter()
            infer_ms.append((t2 - t1) * 1e3)
            conv_ms.append((t1 - t0 + t3 - t2) * 1e3)
    return {"inference_ms": np.array(infer_ms), "conversion_ms": np.array(conv_ms),
            "settings": cfg}


def camera_info(width: int, height: int):
    """The simulated camera's CameraInfo (the picks need it)."""
    from inseggan_ros.io.bags import CameraInfo as CameraInfoData
    from inseggan_ros.ros import conversions
    from inseggan_ros.sim.camera import get_camera

    cam = get_camera("realsense_d435", width, height)
    return conversions.camera_info_to_msg(CameraInfoData(
        width=width, height=height, K=cam.K, D=np.zeros(5), distortion_model="plumb_bob"))


STAGES = ("preprocess", "network", "labels", "picks", "publish")


def print_stages(last: dict) -> None:
    """Each stage's median and share of the mean total, as the node's /diagnostics give them
    (a node without them: a line saying so)."""
    if f"stage_{STAGES[0]}_mean_ms" not in last:
        print("    stages: not reported by this node")
        return
    total = float(last["total_mean_ms"])
    parts = [f"{s} {last[f'stage_{s}_p50_ms']} ms "
             f"({100 * float(last[f'stage_{s}_mean_ms']) / total:.0f} %)" for s in STAGES]
    print(f"    stages, p50 (share of the mean {total:.2f} ms): " + ", ".join(parts))


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="inseggan-bench-node", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--model", default="", help="segmenter model_path ('' = shipped default)")
    ap.add_argument("--distinct-frames", type=int, default=8)
    ap.add_argument("--params-file", type=Path,
                    help="ROS 2 parameters file for the segmenter (e.g. config/quality.yaml)")
    for s in settings.exposed():  # the segmenter's inference settings, one name each
        ap.add_argument(s.flag, type=s.type, choices=s.choices, help=f"segmenter {s.name}")
    ap.add_argument("--superpixel-thread", choices=("on", "off"), default="on",
                    help="the segmenter's superpixel_thread (default on, as the node's)")
    ap.add_argument("--default-transport", action="store_true",
                    help="Fast DDS's built-in transports instead of the shipped large-frames "
                         "profile (config/fastdds_large_frames.xml)")
    ap.add_argument("--node-sets-profile", action="store_true",
                    help="start the segmenter without the profile variable, as a plain "
                         "`ros2 run` does, so that it must set the profile itself")
    ap.add_argument("--baseline", metavar="REF",
                    help="also measure the segmenter of git revision REF (e.g. HEAD~1, main), "
                         "alternately with this tree's, and print the two side by side")
    ap.add_argument("--rounds", type=int, default=1,
                    help="with --baseline: runs of each, alternating (default 1)")
    return ap.parse_args(argv)


def segmenter_command(args, flags: dict, program: list[str] | None = None) -> list[str]:
    """The segmenter's command line: the parameters file first (rcl gathers every -p into one
    set at the first -p's place, so a file after any -p would override even the -p flags that
    follow it), then the model, the settings' flags, the second thread. `program`: what runs
    the node (default: the installed executable)."""
    from tools.demo import _executable

    model = ["--params-file", str(args.params_file)] if args.params_file else []
    if args.model:
        model += ["-p", f"model_path:={args.model}"]
    for name, value in flags.items():
        model += ["-p", f"{name}:={value}"]
    model += ["-p", f"superpixel_thread:={str(args.superpixel_thread == 'on').lower()}"]
    program = program or [_executable("segmenter")]
    return [*program, "--ros-args", *model, "-p", "latency_window:=100000"]


def baseline_tree(ref: str, folder: str) -> list[str]:
    """The source of git revision `ref` of this repository, extracted into `folder` -> the
    command that runs its segmenter (from `folder`, so that its package is the one imported;
    the model and the Fast DDS profile are the installed ones). Raises ValueError when git
    does not know `ref`."""
    root = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(root), "archive", ref], capture_output=True)
    if archive.returncode != 0:
        raise ValueError(f"--baseline {ref}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", folder], input=archive.stdout, check=True)
    return [sys.executable, "-c",
            "import sys; from inseggan_ros.ros.segmenter import main; sys.exit(main())"]


def stream(args, frames, command: list[str], env, cwd: str | None = None) -> dict:
    """Start the segmenter (in `cwd`), wait until it answers, publish the frames (with their
    CameraInfo) at args.rate for args.seconds -> {sent, answered, picked (stamp -> received
    time), first and last diagnostics, peak_mb}; {"error": ...} when the node never
    answered."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image

    from inseggan_ros.ros import conversions
    from tools.demo import _stop

    rclpy.init()
    node = rclpy.create_node("bench_node")
    pub = node.create_publisher(Image, "camera/depth/image_rect_raw", qos_profile_sensor_data)
    pub_info = node.create_publisher(CameraInfo, "camera/depth/camera_info",
                                     qos_profile_sensor_data)
    info = camera_info(args.width, args.height)
    out = {"answered": {}, "picked": {}, "sent": [], "base": None}
    diags = []
    for kind, msg_type, topic in (("answered", Image, "segmenter/labels"),
                                  ("picked", PoseArray, "segmenter/picks")):
        node.create_subscription(msg_type, topic, lambda m, d=out[kind]: d.__setitem__(
            conversions.stamp_to_ns(m.header.stamp), time.time_ns()), 10)
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    seg = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)
    msgs = [conversions.numpy_to_image(f, "16UC1") for f in frames]

    def send(m):
        m.header.stamp = info.header.stamp = node.get_clock().now().to_msg()
        pub_info.publish(info)
        pub.publish(m)

    def spin_until(t):
        while time.monotonic() < t:
            rclpy.spin_once(node, timeout_sec=max(0.0, min(0.05, t - time.monotonic())))

    try:
        t0 = time.monotonic()  # wait until the segmenter answers a frame: it is connected
        while not out["answered"] and time.monotonic() - t0 < 60 and seg.poll() is None:
            send(msgs[0])
            spin_until(time.monotonic() + 0.5)
        if not out["answered"]:
            return {"error": "the segmenter did not answer\n" + seg.stderr.read()}
        out["answered"].clear()
        out["picked"].clear()
        diags.clear()
        print(f"bench-node: publishing at {args.rate:.0f} Hz for {args.seconds:.0f} s", flush=True)
        start, k = time.monotonic(), 0
        while time.monotonic() - start < args.seconds:
            spin_until(start + k / args.rate)
            send(msgs[k % len(msgs)])
            out["sent"].append(conversions.stamp_to_ns(msgs[k % len(msgs)].header.stamp))
            k += 1
            if out["base"] is None and diags:
                out["base"] = {kv.key: kv.value for kv in diags[-1].status[0].values}
        spin_until(time.monotonic() + 3.0)  # the last answers and a final diagnostics message
        out["peak_mb"] = _vm_hwm_mb(seg.pid)
    finally:
        _stop(seg)
        node.destroy_node()
        rclpy.try_shutdown()
    out["last"] = {kv.key: kv.value for kv in diags[-1].status[0].values} if diags else {}
    return out


def report(args, ref: dict, profile, run: dict) -> None:
    last, sent, answered, picked = run["last"], run["sent"], run["answered"], run["picked"]
    got = [s for s in sent if s in answered]
    e2e = np.array([(answered[s] - s) / 1e6 for s in got])
    e2e_picks = np.array([(picked[s] - s) / 1e6 for s in sent if s in picked])
    received = int(last.get("frames_received", 0)) - \
        int((run["base"] or {}).get("frames_received", 0))
    cfg = ref["settings"]
    print(f"\nsegmenter node, {args.width}x{args.height} 16UC1 at {args.rate:.0f} Hz for "
          f"{args.seconds:.0f} s (model {last.get('model', '?')}, {last.get('device', '?')}, "
          f"Fast DDS: {profile})")
    print(f"  settings: {cfg.refine_steps} refinement iterations, {cfg.refine_hypotheses} "
          f"starting points ({cfg.refine_keep or 'all'} refined, {cfg.refine_swaps} swaps), "
          f"smoothing {cfg.smooth.iters} + "
          f"{cfg.smooth.full_res_active} at full resolution, encoder in "
          f"{last.get('encoder_precision', cfg.encoder_precision)}, centre votes "
          f"{cfg.centre_votes} (net in {last.get('centre_precision', cfg.centre_precision)}), "
          f"second thread "
          f"{args.superpixel_thread}"
          + (f" (params file {args.params_file})" if args.params_file else ""))
    print(f"  frames: sent {len(sent)}, answered {len(got)} "
          f"({100 * len(got) / max(len(sent), 1):.1f} %),"
          f" dropped {len(sent) - len(got)} (node received about {received}; skipped "
          f"{last.get('frames_skipped', '?')})")
    print(f"  node latency (received -> labels published): p50 {last.get('latency_p50_ms')} ms, "
          f"p99 {last.get('latency_p99_ms')} ms")
    print(f"  node latency (received -> labels, images and picks published): p50 "
          f"{last.get('total_p50_ms', '?')} ms, p99 {last.get('total_p99_ms', '?')} ms   "
          "[target p50 <= 10, picks included]")
    print(f"    of which inference p50 {last.get('inference_p50_ms')} ms, message conversion "
          f"p50 {last.get('conversion_p50_ms')} ms")
    print_stages(last)
    for name, values in (("labels", e2e), ("picks", e2e_picks)):
        if len(values):
            print(f"  end to end (stamp -> {name} received here): p50 "
                  f"{np.percentile(values, 50):.1f} ms, p99 {np.percentile(values, 99):.1f} ms "
                  f"({len(values)} frames)")
    print(f"  peak resident memory of the node: {run['peak_mb']:.0f} MB   [target <= 1024]")
    print(f"  in this process, same frames, one torch thread (second thread "
          f"{args.superpixel_thread}): preprocessing + inference p50 "
          f"{np.percentile(ref['inference_ms'], 50):.1f} ms (p99 "
          f"{np.percentile(ref['inference_ms'], 99):.1f}); conversion p50 "
          f"{np.percentile(ref['conversion_ms'], 50):.2f} ms")


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        params = settings.read_params_file(args.params_file) if args.params_file else {}
    except ValueError as e:
        print(f"bench-node: error: {e}", file=sys.stderr)
        return 2
    flags = settings.from_flags(args)
    params.update(flags)
    from inseggan_ros.ros.dds import PROFILE_VARIABLES, use_large_frames_profile

    if args.default_transport:
        for v in PROFILE_VARIABLES:
            os.environ.pop(v, None)
    profile = "built-in transports" if args.default_transport else use_large_frames_profile()
    print(f"bench-node: Fast DDS profile: {profile}", flush=True)
    print(f"bench-node: simulating {args.distinct_frames} {args.width}x{args.height} frames ...",
          flush=True)
    from inseggan_ros.core.checkpoint import CheckpointError
    from inseggan_ros.ros.segmenter import ConfigError

    frames = simulated_frames(args.distinct_frames, args.width, args.height)
    try:
        ref = in_process_reference(frames, args.model, params,
                                   superpixel_thread=args.superpixel_thread == "on")
    except (CheckpointError, ConfigError, ValueError) as e:
        print(f"bench-node: error: {e}", file=sys.stderr)
        return 2
    env = None
    if args.node_sets_profile:
        env = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES}
    if args.baseline:
        return compare(args, frames, flags, env, ref, profile)
    run = stream(args, frames, segmenter_command(args, flags), env)
    if "error" in run:
        print(f"bench-node: error: {run['error']}", file=sys.stderr)
        return 1
    report(args, ref, profile, run)
    return 0


def compare(args, frames, flags: dict, env, ref: dict, profile) -> int:
    """`--baseline`: the code at args.baseline and this tree's, alternately, args.rounds times
    each -> each run's report, then the table of both."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_node_baseline_") as folder:
        try:
            program = baseline_tree(args.baseline, folder)
        except ValueError as e:
            print(f"bench-node: error: {e}", file=sys.stderr)
            return 2
        for k in range(args.rounds):
            for name, command, cwd in (
                    (f"baseline {args.baseline}", segmenter_command(args, flags, program),
                     folder),
                    ("this tree", segmenter_command(args, flags), None)):
                print(f"\nbench-node: round {k + 1}/{args.rounds}: {name}", flush=True)
                run = stream(args, frames, command, env, cwd)
                if "error" in run:
                    print(f"bench-node: error ({name}): {run['error']}", file=sys.stderr)
                    return 1
                report(args, ref, profile, run)
                rows.append((k + 1, name, run["last"]))
    print_comparison(rows)
    return 0


def print_comparison(rows) -> None:
    """One line per run: node latency, labels published and everything (picks included), p50
    and p99, and each stage's median (ms)."""
    print(f"\n{'round':>5}  {'code':<22} {'labels p50':>10} {'p99':>7} {'total p50':>10} "
          f"{'p99':>7}  " + " ".join(f"{s:>10}" for s in STAGES))
    for k, name, last in rows:
        stages = " ".join(f"{last.get(f'stage_{s}_p50_ms', '?'):>10}" for s in STAGES)
        print(f"{k:>5}  {name:<22} {last.get('latency_p50_ms', '?'):>10} "
              f"{last.get('latency_p99_ms', '?'):>7} {last.get('total_p50_ms', '?'):>10} "
              f"{last.get('total_p99_ms', '?'):>7}  {stages}")


if __name__ == "__main__":
    sys.exit(main())
