"""A separate rclpy process that subscribes to bin_replay's topics and saves what it receives.

    python receiver.py OUT.npz COUNT TIMEOUT_S [NAMESPACE] [--labels-optional] [--compressed]
Saves depth (raw), labels, encodings, stamps, frame_ids and camera K of the first COUNT depth
frames whose camera info and labels (of the same stamp) arrived too. Exit 0 when COUNT were
received. With --compressed the depth is taken from image_transport's compressedDepth topic
(sensor_msgs/CompressedImage, .../image_rect_raw/compressedDepth), decoded with
image_codec, and each message's format and data are saved as they came too.

The three topics are matched one by one when bin_replay starts, and sensor-data QoS drops what a
subscription was not yet matched for: the first frames may come without their labels or camera
info. They are skipped rather than saved half. With --labels-optional a frame needs only its
camera info (a bag whose frames lack labels); its labels are saved where they came.
"""
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from inseggan_ros.core import image_codec


def main():
    out, count, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    rest = [a for a in sys.argv[4:] if not a.startswith("--")]
    compressed = "--compressed" in sys.argv[4:]
    ns = rest[0] if rest else ""
    labels_required = "--labels-optional" not in sys.argv[4:]
    rclpy.init()
    node = rclpy.create_node("test_receiver")
    depth, labels, infos = [], {}, {}

    def key(msg):
        return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec

    node.create_subscription(CompressedImage if compressed else Image,
                             f"{ns}/camera/depth/image_rect_raw"
                             + ("/compressedDepth" if compressed else ""),
                             lambda m: depth.append(m), qos_profile_sensor_data)
    node.create_subscription(Image, f"{ns}/camera/depth/instance_labels",
                             lambda m: labels.__setitem__(key(m), m), qos_profile_sensor_data)
    node.create_subscription(CameraInfo, f"{ns}/camera/depth/camera_info",
                             lambda m: infos.__setitem__(key(m), m), qos_profile_sensor_data)
    print("receiver ready", flush=True)

    def whole(m):
        return key(m) in infos and (key(m) in labels or not labels_required)

    t0 = time.monotonic()
    frames = []
    while len(frames) < count and time.monotonic() - t0 < timeout:
        rclpy.spin_once(node, timeout_sec=0.05)
        frames = [m for m in depth if whole(m)][:count]
    if not labels_required:
        # labels travel on their own topic and may come later than the depth on a loaded
        # machine: wait for them (up to 3 s) rather than a fixed time
        end = time.monotonic() + 3.0
        while time.monotonic() < end and not all(key(m) in labels for m in frames):
            rclpy.spin_once(node, timeout_sec=0.05)

    def raw(m):
        if isinstance(m, CompressedImage):
            return image_codec.decode_compressed_depth(m.format, m.data)[0]
        dt = {"16UC1": "<u2", "32FC1": "<f4", "mono8": "u1"}[m.encoding]
        a = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.step)
        a = a[:, : m.width * np.dtype(dt).itemsize].copy().view(dt)
        return a.reshape(m.height, m.width)

    np.savez(out,
             depth=np.array([raw(m) for m in frames], dtype=object),
             labels=np.array([raw(labels[key(m)]) if key(m) in labels else None
                              for m in frames], dtype=object),
             K=np.array([np.array(infos[key(m)].k) if key(m) in infos else None
                         for m in frames], dtype=object),
             encoding=np.array([image_codec.decode_compressed_depth(m.format, m.data)[1]
                                if compressed else m.encoding for m in frames]),
             format=np.array([m.format if compressed else "" for m in frames]),
             data=np.array([bytes(m.data) if compressed else b"" for m in frames], dtype=object),
             frame_id=np.array([m.header.frame_id for m in frames]),
             stamp=np.array([key(m) for m in frames], np.int64))
    node.destroy_node()
    rclpy.shutdown()
    sys.exit(0 if len(frames) == count else 1)


if __name__ == "__main__":
    main()
