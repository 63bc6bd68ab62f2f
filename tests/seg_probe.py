"""A separate rclpy process that talks to the segmenter over DDS and saves what it sees.

    python seg_probe.py OUT.npz NAMESPACE COUNT TIMEOUT_S [FRAMES.npz]

Subscribes to NAMESPACE/segmenter/{labels,masks,overlay,reconstruction}, /diagnostics and (to
know the inputs and their ground truth) NAMESPACE/camera/depth/{image_rect_raw,instance_labels}.
With FRAMES.npz it also publishes those frames itself (raw Image fields: encoding, width,
height, step, data; one every 0.3 s) to NAMESPACE/camera/depth/image_rect_raw, bad ones included;
frame 0 (which must be good) is repeated until its labels come back, so that none of the others
is lost to DDS discovery.
Stops once COUNT label images arrived (or at TIMEOUT_S), waits up to 10 s more for the other
topics of those stamps, and saves everything keyed by stamp.
"""
import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image


def key(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def raw(m):
    channels = int(m.encoding[3:]) if m.encoding.startswith("8UC") else 1
    dt, ch = {"16UC1": ("<u2", 1), "32FC1": ("<f4", 1), "mono8": ("u1", 1),
              "rgb8": ("u1", 3)}.get(m.encoding, ("u1", channels))
    a = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.step)
    a = a[:, : m.width * ch * np.dtype(dt).itemsize].copy().view(dt)
    return a.reshape(m.height, m.width, ch) if ch > 1 else a.reshape(m.height, m.width)


def main():
    out, ns, count, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    to_send = dict(np.load(sys.argv[5], allow_pickle=True)) if len(sys.argv) > 5 else None
    rclpy.init()
    node = rclpy.create_node("seg_probe")
    got = {k: {} for k in ("labels", "masks", "overlay", "reconstruction", "depth", "gt")}
    headers = {}
    diags = []

    def store(kind):
        def cb(m):
            got[kind][key(m)] = m
            if kind == "labels":
                headers[key(m)] = m.header.frame_id
        return cb

    for kind in ("labels", "masks", "overlay", "reconstruction"):
        node.create_subscription(Image, f"{ns}/segmenter/{kind}", store(kind), 10)
    node.create_subscription(Image, f"{ns}/camera/depth/image_rect_raw", store("depth"),
                             qos_profile_sensor_data)
    node.create_subscription(Image, f"{ns}/camera/depth/instance_labels", store("gt"),
                             qos_profile_sensor_data)
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    pub = node.create_publisher(Image, f"{ns}/camera/depth/image_rect_raw", qos_profile_sensor_data)
    print("probe ready", flush=True)

    t0 = time.monotonic()
    sent, next_send = 0, t0 + 1.0
    n_send = len(to_send["encoding"]) if to_send else 0
    while len(got["labels"]) < count and time.monotonic() - t0 < timeout:
        rclpy.spin_once(node, timeout_sec=0.02)
        if sent < n_send and time.monotonic() >= next_send:
            if sent == 1 and 1000 * 10**9 not in got["labels"]:
                sent = 0  # frame 0 again until it is answered: the segmenter is connected
            m = Image()
            m.header.stamp.sec, m.header.stamp.nanosec = 1000 + sent, 0
            m.header.frame_id = f"probe_{sent}"
            m.encoding = str(to_send["encoding"][sent])
            m.width, m.height = int(to_send["width"][sent]), int(to_send["height"][sent])
            m.step = int(to_send["step"][sent])
            m.data = bytes(to_send["data"][sent])
            pub.publish(m)
            sent += 1
            next_send = time.monotonic() + 0.3
    wanted = list(got["labels"])

    def complete():  # those stamps have each kind that came at all (a looping source brings a
        # frame again whose input or ground truth was lost while discovery settled)
        return all(s in got[kind] for kind in got if got[kind] for s in wanted)

    t1 = time.monotonic()  # the last frame's extras and one more diagnostics message (2.5 s)
    while time.monotonic() < t1 + 2.5 or (not complete() and time.monotonic() < t1 + 10.0):
        rclpy.spin_once(node, timeout_sec=0.05)

    stamps = sorted(got["labels"])
    last_diag = {}
    mine = [d for d in diags if d.status and "segmenter" in d.status[0].name]
    if mine:
        last_diag = {kv.key: kv.value for kv in mine[-1].status[0].values}
        last_diag["_level"] = str(int.from_bytes(bytes(mine[-1].status[0].level), "little")
                                  if isinstance(mine[-1].status[0].level, bytes)
                                  else int(mine[-1].status[0].level))

    def obj(kind):  # one array per stamp (None where that message did not arrive)
        out = np.empty(len(stamps), dtype=object)
        for i, s in enumerate(stamps):
            out[i] = raw(got[kind][s]) if s in got[kind] else None
        return out

    np.savez(out, stamp=np.array(stamps, np.int64),
             frame_id=np.array([headers[s] for s in stamps]),
             depth_encoding=np.array([got["depth"][s].encoding if s in got["depth"] else ""
                                      for s in stamps]),
             labels=obj("labels"), masks=obj("masks"), overlay=obj("overlay"),
             reconstruction=obj("reconstruction"), depth=obj("depth"), gt=obj("gt"),
             sent=np.int64(sent), diagnostics=np.array(last_diag, dtype=object))
    node.destroy_node()
    rclpy.shutdown()
    sys.exit(0 if len(stamps) >= count else 1)


if __name__ == "__main__":
    main()
