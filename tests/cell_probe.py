"""A separate rclpy process that drives the segmenter as a robot cell does, over its services,
and records what it publishes.

    python cell_probe.py OUT.json NAMESPACE STEPS.json

STEPS.json is a list of steps, run in order:
    ["state"]                      the lifecycle state (~/get_state) -> its label
    ["transition", LABEL]          ~/change_state by label (configure, activate, ...) -> success
    ["enable", true|false]         ~/enable -> [success, message]
    ["segment_next"]               ~/segment_next -> [success, message]
    ["publish", FRAMES.npz, RATE]  from now on, publish FRAMES.npz's `depth` (N, H, W) uint16
                                   frames in turn as 16UC1 at RATE Hz, stamped with the wall
                                   clock, each with a CameraInfo of `K` (3 x 3) beside it;
                                   a fourth item "compressedDepth": as image_transport's
                                   compressedDepth (PNG) on <depth topic>/compressedDepth
    ["labels", COUNT, TIMEOUT]     wait until COUNT label images have arrived in this step
    ["idle", SECONDS]              keep spinning (and publishing)
    ["diagnostics", NAME]          the last status under NAME received so far (as below)
Writes OUT.json: "steps", per step {step, t0_ns, t1_ns (wall clock), result, labels: the stamps
of the label images received during it}; "labels": every label image as [stamp_ns,
instances]; "picks": [stamp_ns, frame_id, poses]; "confidence": [label, values];
"diagnostics": the last status of each of the segmenter's names as {_level, _message, key:
value}. Exit status 1 when a step timed out.
"""
import json
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Float32MultiArray
from std_srvs.srv import SetBool, Trigger


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def compressed_depth(header, depth):
    """image_transport's compressedDepth of a 16UC1 image: its 12-byte ConfigHeader (compression
    format INV_DEPTH = 0, as compressed_depth_image_transport writes it for every encoding; two
    depth parameters, unused for 16 bits), then the PNG."""
    import struct

    import cv2

    ok, png = cv2.imencode(".png", depth.astype(np.uint16))
    return CompressedImage(header=header, format="16UC1; compressedDepth png",
                           data=struct.pack("<iff", 0, 0.0, 0.0) + png.tobytes())


class Probe:
    def __init__(self, ns: str):
        self.node = rclpy.create_node("cell_probe")
        self.ns = ns
        self.labels, self.picks, self.confidence, self.diagnostics = [], [], [], {}
        seg = f"{ns}/segmenter"
        self.node.create_subscription(Image, f"{seg}/labels", self._on_labels, 10)
        self.node.create_subscription(
            PoseArray, f"{seg}/picks", lambda m: self.picks.append(
                [stamp_ns(m.header), m.header.frame_id, len(m.poses)]), 10)
        self.node.create_subscription(
            Float32MultiArray, f"{seg}/pick_confidence", lambda m: self.confidence.append(
                [m.layout.dim[0].label if m.layout.dim else "", list(m.data)]), 10)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.pub = self.node.create_publisher(Image, f"{ns}/camera/depth/image_rect_raw",
                                              qos_profile_sensor_data)
        self.pub_info = self.node.create_publisher(CameraInfo, f"{ns}/camera/depth/camera_info",
                                                   qos_profile_sensor_data)
        self.pub_compressed = self.node.create_publisher(
            CompressedImage, f"{ns}/camera/depth/image_rect_raw/compressedDepth",
            qos_profile_sensor_data)
        self.frames, self.K, self.period, self.next_send, self.sent = None, None, 0.0, 0.0, 0
        self.compressed = False

    def _on_labels(self, m):
        lab = np.frombuffer(bytes(m.data), np.uint8)
        self.labels.append([stamp_ns(m.header), int(len(np.unique(lab[lab > 0])))])

    def _on_diag(self, arr):
        for s in arr.status:
            if s.name.startswith("segmenter"):
                level = int.from_bytes(s.level, "little") if isinstance(s.level, bytes) \
                    else int(s.level)
                self.diagnostics[s.name] = {"_level": level, "_message": s.message,
                                            **{kv.key: kv.value for kv in s.values}}

    def _publish_due(self) -> None:
        if self.frames is None or time.monotonic() < self.next_send:
            return
        depth = self.frames[self.sent % len(self.frames)]
        m = Image(encoding="16UC1", height=depth.shape[0], width=depth.shape[1],
                  step=depth.shape[1] * 2, data=depth.astype("<u2").tobytes())
        now = time.time_ns()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(now, 1_000_000_000)
        m.header.frame_id = "probe_camera"
        info = CameraInfo(header=m.header, width=m.width, height=m.height)
        info.k = [float(v) for v in self.K.reshape(-1)]
        self.pub_info.publish(info)
        if self.compressed:
            self.pub_compressed.publish(compressed_depth(m.header, depth))
        else:
            self.pub.publish(m)
        self.sent += 1
        self.next_send = time.monotonic() + self.period

    def spin_until(self, done, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while not done() and time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.01)
            self._publish_due()
        return done()

    def call(self, srv_type, name: str, request, timeout: float = 60.0):
        client = self.node.create_client(srv_type, f"{self.ns}/segmenter/{name}")
        if not self.spin_until(client.service_is_ready, 30.0):
            raise TimeoutError(f"no service {name}")
        future = client.call_async(request)
        if not self.spin_until(future.done, timeout):
            raise TimeoutError(f"{name} not answered")
        return future.result()

    def step(self, step):
        kind = step[0]
        if kind == "state":
            return self.call(GetState, "get_state", GetState.Request()).current_state.label
        if kind == "transition":
            req = ChangeState.Request(transition=Transition(label=step[1]))
            return self.call(ChangeState, "change_state", req).success
        if kind == "enable":
            r = self.call(SetBool, "enable", SetBool.Request(data=bool(step[1])))
            return [r.success, r.message]
        if kind == "segment_next":
            r = self.call(Trigger, "segment_next", Trigger.Request())
            return [r.success, r.message]
        if kind == "publish":
            data = np.load(step[1])
            self.frames, self.K, self.period = data["depth"], data["K"], 1.0 / float(step[2])
            self.compressed = len(step) > 3 and step[3] == "compressedDepth"
            return True
        if kind == "labels":
            start = len(self.labels)
            return self.spin_until(lambda: len(self.labels) - start >= step[1], step[2])
        if kind == "idle":
            self.spin_until(lambda: False, step[1])
            return True
        if kind == "diagnostics":
            return dict(self.diagnostics.get(step[1], {}))
        raise ValueError(f"unknown step {step}")


def main():
    out, ns, steps = sys.argv[1], sys.argv[2], json.loads(open(sys.argv[3]).read())
    rclpy.init()
    probe = Probe(ns)
    print("probe ready", flush=True)
    results, ok = [], True
    for step in steps:
        t0, before = time.time_ns(), len(probe.labels)
        try:
            result = probe.step(step)
        except TimeoutError as e:
            result, ok = f"timeout: {e}", False
        if step[0] == "labels" and result is False:
            ok = False
        results.append({"step": step, "t0_ns": t0, "t1_ns": time.time_ns(), "result": result,
                        "labels": [s for s, _ in probe.labels[before:]]})
    with open(out, "w") as f:
        json.dump({"steps": results, "labels": probe.labels, "picks": probe.picks,
                   "confidence": probe.confidence, "diagnostics": probe.diagnostics}, f)
    probe.node.destroy_node()
    rclpy.shutdown()
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
