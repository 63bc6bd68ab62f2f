"""How many large depth frames reach another process, with the DDS set-up a plain `ros2 run` of
the package's nodes gives (no profile variable in the environment; each process applies the
shipped profile itself, as nodes/common.py does) or with Fast DDS's built-in transports.

    python delivery_probe.py sub WIDTH HEIGHT COUNT TIMEOUT_S ros2run|builtin
    python delivery_probe.py pub WIDTH HEIGHT COUNT RATE_HZ ros2run|builtin

The subscriber has the segmenter's QoS (sensor data, keep last 1) and a callback that only
counts; it prints 'ready', then the number of distinct frames received. The publisher waits
for the subscriber, sends COUNT 16UC1 frames at RATE_HZ, best effort.
"""
import copy
import os
import sys
import time

import numpy as np


def main() -> int:
    mode, width, height, count, value, dds = sys.argv[1:7]
    width, height, count, value = int(width), int(height), int(count), float(value)
    from inseggan_ros.ros.dds import PROFILE_VARIABLES

    for v in PROFILE_VARIABLES:  # what the user's shell would not have set
        os.environ.pop(v, None)
    if dds == "ros2run":
        from inseggan_ros.ros.common import use_large_frames_profile

        assert use_large_frames_profile() is not None
    import rclpy
    from rclpy.qos import QoSHistoryPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import Image

    from inseggan_ros.ros import conversions

    rclpy.init()
    node = rclpy.create_node(f"delivery_{mode}")
    topic = "delivery_frames"
    if mode == "pub":
        pub = node.create_publisher(Image, topic, qos_profile_sensor_data)
        deadline = time.time() + 30
        while pub.get_subscription_count() == 0 and time.time() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(1.0)  # let the match settle both ways
        depth = (np.arange(width * height, dtype=np.uint32) % 4000).astype(np.uint16)
        msg = conversions.numpy_to_image(depth.reshape(height, width), "16UC1")
        start = time.monotonic()
        for i in range(count):
            time.sleep(max(0.0, start + i / value - time.monotonic()))
            msg.header.frame_id = str(i)
            pub.publish(msg)
        time.sleep(1.0)
    else:
        qos = copy.copy(qos_profile_sensor_data)
        qos.history, qos.depth = QoSHistoryPolicy.KEEP_LAST, 1
        got = set()
        size = width * height * 2
        node.create_subscription(
            Image, topic, lambda m: got.add(m.header.frame_id) if len(m.data) == size else None,
            qos)
        print("ready", flush=True)
        deadline = time.time() + value
        while len(got) < count and time.time() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        print(len(got), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
