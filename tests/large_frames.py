"""Helper process for test_dds: `pub N RATE` sends N 1280 x 720 16UC1 frames (sensor-data QoS)
once a subscriber is matched; `sub N TIMEOUT` prints how many distinct frames it received."""
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image

from inseggan_ros.ros import conversions


def main() -> int:
    mode, n, value = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node(f"large_frames_{mode}")
    if mode == "pub":
        pub = node.create_publisher(Image, "large_frames", qos_profile_sensor_data)
        deadline = time.time() + 20
        while pub.get_subscription_count() == 0 and time.time() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(0.5)  # let the match settle both ways
        depth = (np.arange(1280 * 720, dtype=np.uint32) % 4000).astype(np.uint16).reshape(720, 1280)
        for i in range(n):
            msg = conversions.numpy_to_image(depth, "16UC1")
            msg.header.frame_id = str(i)
            pub.publish(msg)
            time.sleep(1.0 / value)
        time.sleep(1.0)
    else:
        got = set()
        node.create_subscription(Image, "large_frames",
                                 lambda m: got.add(m.header.frame_id)
                                 if len(m.data) == 1280 * 720 * 2 else None,
                                 qos_profile_sensor_data)
        print("ready", flush=True)
        deadline = time.time() + value
        while len(got) < n and time.time() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        print(len(got), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
