r"""bin_replay: publish depth frames of bins, simulated live with pybullet or replayed from a bag.

    ros2 run inseggan_ros bin_replay                                   # simulated cylinders, 5 Hz
    ros2 run inseggan_ros bin_replay --ros-args -p object:=hex_nut -p noise:=realsense
    ros2 run inseggan_ros bin_replay --ros-args -p source:=bag -p bag_path:=cylinder_sim \
        -p loop:=true

Publishes (sensor-data QoS; relative names, so namespaces and remapping work; the segmenter
listens on the same names, so the two started side by side connect with no remap):
    camera/depth/image_rect_raw     sensor_msgs/Image       16UC1 mm (or 32FC1 m)
    camera/depth/camera_info        sensor_msgs/CameraInfo
    camera/depth/instance_labels    sensor_msgs/Image mono8 ground truth, when known
With depth_transport:=compressedDepth the depth goes instead, as image_transport's
compressedDepth plugin publishes it (32FC1 quantised with its defaults, depth_max 10 m and
depth_quantization 100; PNG level png_level, default 1 where image_transport's is 9: measured
here on 848 x 480 RealSense frames 0.02 s and 200 kB a frame, level 9 1.5-2.5 s and 150 kB), on
    camera/depth/image_rect_raw/compressedDepth   sensor_msgs/CompressedImage
A bag's depth is read whichever way it was recorded (raw Image or compressedDepth) and published
as depth_transport says: decoded to an Image, or a recorded compressedDepth message's bytes as
they are (no second quantisation of 32FC1), or encoded from a raw one.
Simulated frame k is scene_seed(seed, "test", k): the same scenes as the test split of
`inseggan simulate --seed <seed>` with the same object/camera/noise settings. Unless
FASTRTPS_DEFAULT_PROFILES_FILE is set, the node uses the shipped Fast DDS profile for large
frames (nodes/common.py).
"""
from __future__ import annotations

import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from inseggan_ros.io import bags
from inseggan_ros.core import image_codec
from inseggan_ros.sim.camera import PRESETS
from inseggan_ros.sim.noise import NOISE_PRESETS
from inseggan_ros.sim.objects import OBJECTS
from inseggan_ros.core.paths import resolve_bag
from inseggan_ros.ros import common
from inseggan_ros.ros import conversions
from inseggan_ros.ros.common import ConfigError

CHOICES = {
    "source": ("sim", "bag"),
    "object": tuple(OBJECTS),
    "camera": tuple(PRESETS),
    "noise": tuple(NOISE_PRESETS),
    "encoding": ("16UC1", "32FC1"),
    "depth_transport": bags.TRANSPORTS,
}
COMPRESSED_DEPTH_TOPIC = common.DEPTH_TOPIC + bags.COMPRESSED_SUFFIX


class BinReplay(Node):
    def __init__(self, **kwargs):
        super().__init__("bin_replay", **kwargs)
        self._declare()
        self.p = {name: self.get_parameter(name).value for name in self._names}
        self._validate(self.p)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        if self.p["depth_transport"] == "raw":
            self.pub_depth = self.create_publisher(Image, common.DEPTH_TOPIC,
                                                   qos_profile_sensor_data)
        else:
            self.pub_depth = self.create_publisher(CompressedImage, COMPRESSED_DEPTH_TOPIC,
                                                   qos_profile_sensor_data)
        self.pub_info = self.create_publisher(CameraInfo, common.CAMERA_INFO_TOPIC,
                                              qos_profile_sensor_data)
        self.pub_labels = self.create_publisher(Image, common.LABELS_TOPIC,
                                                qos_profile_sensor_data)
        self.frames_published = 0
        self.done = Future()
        self._stop = threading.Event()
        if self.p["source"] == "sim":
            self._frames = self._sim_frames()
            what = (f"simulated {self.p['instances']} x {self.p['object']} "
                    f"({self.p['camera']}, noise {self.p['noise']}) at {self.p['rate']} Hz")
        else:
            self._bag = resolve_bag(self.p["bag_path"])
            # Open now so that a bad bag or topic fails at start-up with one clear line.
            next(iter(bags.read_frames(self._bag, depth_topic=self.p["topic"] or None, limit=1,
                                       on_bad_frame=self._bad_frame)), None)
            self._frames = self._bag_frames()
            timing = "recorded timing" if self.p["rate"] == 0 else f"{self.p['rate']} Hz"
            what = f"bag {self._bag} ({timing}{', looping' if self.p['loop'] else ''})"
        self.get_logger().info(f"publishing {what} on {self.pub_depth.topic_name}")
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ parameters
    def _declare(self) -> None:
        def d(desc, read_only=True, **ranges):  # most of this node's parameters are read-only
            return common.descriptor(desc, read_only=read_only, **ranges)

        specs = {
            "source": ("sim", d("'sim': simulate bins live; 'bag': replay a rosbag2 bag")),
            "object": ("cylinder", d(f"object to simulate: {', '.join(OBJECTS)}")),
            "instances": (5, d("objects per simulated bin", int_range=(1, 20))),
            "seed": (0, d("simulation seed; frame k uses scene_seed(seed, 'test', k)",
                          int_range=(0, 2 ** 31 - 1))),
            "camera": ("default", d(f"camera preset: {', '.join(PRESETS)}")),
            "noise": ("none", d(f"sensor noise model: {', '.join(NOISE_PRESETS)}")),
            "encoding": ("16UC1", d("published depth encoding: 16UC1 (mm) or 32FC1 (m)")),
            "depth_transport": ("raw", d("'raw': depth as sensor_msgs/Image on "
                                         f"{common.DEPTH_TOPIC}; 'compressedDepth': as "
                                         "image_transport's compressedDepth CompressedImage on "
                                         f"{COMPRESSED_DEPTH_TOPIC}")),
            "png_level": (1, d("PNG level of compressedDepth frames this node encodes (0-9; "
                               "9 is image_transport's default, the smallest and slowest)",
                               int_range=(0, 9))),
            "rate": (5.0, d("frames per second; for bags 0 = the recorded timing",
                            read_only=False, float_range=(0.0, 1000.0))),
            "bag_path": ("cylinder_sim", d("rosbag2 directory, .mcap/.db3 file, or the name of "
                                           "a bag shipped in share/inseggan_ros/bags")),
            "topic": ("", d("depth topic in the bag, an Image or a compressedDepth "
                            "CompressedImage ('' = /camera/depth/image_rect_raw, its "
                            "/compressedDepth, or the only depth topic)")),
            "loop": (False, d("replay the bag again from the start when it ends",
                              read_only=False)),
            "restamp": (True, d("stamp frames with the current time (false: keep the bag's "
                                "stamps)")),
            "frame_id": ("camera_depth_optical_frame", d("header frame_id of simulated frames")),
            "publish_labels": (True, d("publish ground-truth labels when known",
                                       read_only=False)),
            "max_frames": (0, d("stop after this many frames (0 = never)",
                                int_range=(0, 2 ** 31 - 1))),
        }
        self._names = list(specs)
        common.declare(self, specs)

    def _validate(self, p: dict) -> None:
        for name, valid in CHOICES.items():
            if p[name] not in valid:
                raise ConfigError(f"parameter {name}={p[name]!r} invalid; valid: "
                                  f"{', '.join(valid)}")
        if p["source"] == "sim" and p["rate"] <= 0:
            raise ConfigError(f"parameter rate={p['rate']} invalid for source 'sim'; valid: > 0 Hz")

    def _on_set_parameters(self, params) -> SetParametersResult:
        new = dict(self.p)
        new.update({x.name: x.value for x in params})
        try:
            self._validate(new)
        except ConfigError as e:
            return SetParametersResult(successful=False, reason=str(e))
        self.p = new
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ frame sources
    def _sim_frames(self):
        from inseggan_ros.sim.camera import get_camera
        from inseggan_ros.sim.dataset import scene_seed
        from inseggan_ros.sim.noise import get_noise
        from inseggan_ros.sim.scene import BinSimulator, SceneConfig

        p = self.p
        cfg = SceneConfig(object=p["object"], instances=p["instances"],
                          camera=get_camera(p["camera"]), noise=get_noise(p["noise"]))
        info = bags.CameraInfo.from_camera(cfg.camera)
        with BinSimulator(cfg) as sim:
            k = 0
            while True:
                scene = sim.render(scene_seed(p["seed"], "test", k))
                yield None, p["frame_id"], p["encoding"], \
                    image_codec.metres_to_depth(scene.depth, p["encoding"]), scene.labels, info, \
                    None
                k += 1

    def _bag_frames(self):
        while True:
            good = 0
            for f in bags.read_frames(self._bag, depth_topic=self.p["topic"] or None,
                                      on_bad_frame=self._bad_frame):
                good += 1
                yield (f.stamp_ns, f.frame_id, f.encoding, f.depth, f.labels, f.camera_info,
                       f.compressed)
            if not self.p["loop"] or not good:  # no frame to loop over: done
                return

    def _bad_frame(self, line: str) -> None:
        """A bag frame that does not decode: said, skipped, and the replay goes on."""
        self.get_logger().warning(line)

    # ------------------------------------------------------------------ publishing loop
    def _run(self) -> None:
        try:
            self._publish_all()
        except bags.BagError as e:
            self.get_logger().error(str(e))
        except Exception as e:  # keep the node's process alive enough to report
            self.get_logger().error(f"frame source failed: {type(e).__name__}: {e}")
        finally:
            if not self.done.done():
                self.done.set_result(self.frames_published)

    def _publish_all(self) -> None:
        start_wall = time.monotonic()
        first_stamp = None
        next_due = start_wall
        for stamp_ns, frame_id, encoding, depth, labels, info, compressed in self._frames:
            if self._stop.is_set():
                return
            rate = self.p["rate"]
            if stamp_ns is not None and rate == 0:  # recorded timing
                first_stamp = stamp_ns if first_stamp is None else first_stamp
                next_due = start_wall + (stamp_ns - first_stamp) * 1e-9
            if self._stop.wait(max(0.0, next_due - time.monotonic())):
                return
            if rate > 0:
                next_due = max(next_due + 1.0 / rate, time.monotonic() - 1.0 / rate)
            header = Header(frame_id=frame_id)
            if stamp_ns is None or self.p["restamp"]:
                header.stamp = self.get_clock().now().to_msg()
            else:
                header.stamp = conversions.ns_to_stamp(stamp_ns)
            if info is not None:
                self.pub_info.publish(conversions.camera_info_to_msg(info, header))
            if labels is not None and self.p["publish_labels"]:
                self.pub_labels.publish(conversions.numpy_to_image(labels, "mono8", header))
            self.pub_depth.publish(self._depth_msg(depth, encoding, compressed, header))
            self.frames_published += 1
            if self.p["max_frames"] and self.frames_published >= self.p["max_frames"]:
                return

    def _depth_msg(self, depth, encoding: str, compressed, header: Header):
        if self.p["depth_transport"] == "raw":
            return conversions.numpy_to_image(depth, encoding, header)
        if compressed is not None:  # recorded so: the bytes as they are
            return conversions.compressed_image(*compressed, header)
        return conversions.numpy_to_compressed_depth(depth, encoding, header,
                                                     png_level=self.p["png_level"])

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    close = stop  # common.run calls it before the node is destroyed


def _spin_until_done(node: BinReplay) -> None:
    rclpy.spin_until_future_complete(node, node.done)
    node.get_logger().info(f"published {node.frames_published} frames; done")


def main(args=None) -> int:
    return common.run("bin_replay", BinReplay, args, errors=(bags.BagError,),
                      spin=_spin_until_done)


if __name__ == "__main__":
    sys.exit(main())
