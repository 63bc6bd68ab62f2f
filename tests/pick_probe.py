"""A separate rclpy process that listens to the segmenter's picks over DDS and saves them.

    python pick_probe.py OUT.npz NAMESPACE COUNT TIMEOUT_S picks|labels [INFO_TOPIC WIDTH HEIGHT]

Subscribes to NAMESPACE/segmenter/{picks,markers,labels,pick_confidence} (the confidences keyed
by the stamp their label names), /diagnostics and (for the inputs)
NAMESPACE/camera/depth/image_rect_raw. With INFO_TOPIC it also publishes a CameraInfo of WIDTH x
HEIGHT there twice a second (to feed the segmenter a wrong one). Stops once COUNT frames have
their depth, labels and picks (`picks`) or their depth and labels (`labels`), or at TIMEOUT_S;
saves them keyed by stamp, with the last diagnostics of both of the segmenter's statuses.
"""
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float32MultiArray
from visualization_msgs.msg import MarkerArray

from seg_probe import key, raw


def main():
    out, ns, count, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    wait_for, wrong = sys.argv[5], sys.argv[6:9]
    rclpy.init()
    node = rclpy.create_node("pick_probe")
    got = {k: {} for k in ("picks", "markers", "labels", "depth", "confidence")}
    statuses = {}

    def store(kind):
        return lambda m: got[kind].__setitem__(key(m.markers[0] if kind == "markers" else m), m)

    def on_diag(arr):
        for s in arr.status:
            if s.name.startswith("segmenter"):
                statuses[s.name] = s

    node.create_subscription(PoseArray, f"{ns}/segmenter/picks", store("picks"), 10)
    node.create_subscription(MarkerArray, f"{ns}/segmenter/markers", store("markers"), 10)
    node.create_subscription(Image, f"{ns}/segmenter/labels", store("labels"), 10)

    def on_confidence(m):  # no header: its dimension's label is the stamp, '<sec>.<nanosec>'
        sec, nanosec = m.layout.dim[0].label.split(".")
        got["confidence"][int(sec) * 10**9 + int(nanosec)] = {"label": m.layout.dim[0].label,
                                                              "values": list(m.data)}

    node.create_subscription(Float32MultiArray, f"{ns}/segmenter/pick_confidence",
                             on_confidence, 10)
    node.create_subscription(Image, f"{ns}/camera/depth/image_rect_raw", store("depth"),
                             qos_profile_sensor_data)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    info_pub = node.create_publisher(CameraInfo, wrong[0], 10) if wrong else None
    print("probe ready", flush=True)

    needed = ("depth", "labels", "picks") if wait_for == "picks" else ("depth", "labels")

    def complete():
        return sorted(set.intersection(*(set(got[k]) for k in needed)))

    t0 = time.monotonic()
    next_info = t0
    while len(complete()) < count and time.monotonic() - t0 < timeout:
        rclpy.spin_once(node, timeout_sec=0.02)
        if info_pub is not None and time.monotonic() >= next_info:
            info = CameraInfo(width=int(wrong[1]), height=int(wrong[2]))
            info.k = [100.0, 0.0, 50.0, 0.0, 100.0, 50.0, 0.0, 0.0, 1.0]
            info_pub.publish(info)
            next_info = time.monotonic() + 0.5
    end = time.monotonic() + 2.5  # one more diagnostics message
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)

    stamps = complete()[:count]

    def obj(values):
        a = np.empty(len(values), dtype=object)
        a[:] = values
        return a

    def poses(s):
        if s not in got["picks"]:
            return np.zeros((0, 7))
        return np.array([[p.position.x, p.position.y, p.position.z, p.orientation.x,
                          p.orientation.y, p.orientation.z, p.orientation.w]
                         for p in got["picks"][s].poses]).reshape(-1, 7)

    def markers(s):
        m = got["markers"].get(s)
        return [] if m is None else [(x.type, x.action, x.text, x.header.frame_id)
                                     for x in m.markers]

    diag = {name: {"_level": str(int.from_bytes(s.level, "little") if isinstance(s.level, bytes)
                                 else int(s.level)), "_message": s.message,
                   **{kv.key: kv.value for kv in s.values}} for name, s in statuses.items()}
    np.savez(out, stamp=np.array(stamps, np.int64),
             depth=obj([raw(got["depth"][s]) for s in stamps]),
             labels=obj([raw(got["labels"][s]) for s in stamps]),
             poses=obj([poses(s) for s in stamps]),
             picks_frame_id=np.array([got["picks"][s].header.frame_id if s in got["picks"]
                                      else "" for s in stamps]),
             depth_frame_id=np.array([got["depth"][s].header.frame_id for s in stamps]),
             markers=obj([markers(s) for s in stamps]),
             confidence=obj([got["confidence"].get(s) for s in stamps]),
             picks_total=np.int64(len(got["picks"])),
             diagnostics=np.array(diag, dtype=object))
    node.destroy_node()
    rclpy.shutdown()
    sys.exit(0 if len(stamps) >= count else 1)


if __name__ == "__main__":
    main()
