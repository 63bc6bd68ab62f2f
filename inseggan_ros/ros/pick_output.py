"""The segmenter's picks: the CameraInfo they need, the frame they are published in, their
confidence, and the messages ~/picks, ~/pick_confidence and ~/markers.

The picks are computed in the depth image's frame (picks.py) and moved to `target_frame` with a
fixed transform (the parameters target_translation and target_rotation) or, with use_tf, the one
tf holds for the frame's stamp. Each pick's confidence is its instance's fit
(`bin_check.instance_fit`): the share of the model's render of it that the input explains.
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseArray
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Float32MultiArray, MultiArrayDimension
from visualization_msgs.msg import MarkerArray

from inseggan_ros.ros import conversions
from inseggan_ros.ros.common import ConfigError, FrameError


def confidence_msg(values, stamp) -> Float32MultiArray:
    """Float32MultiArray of the picks' confidences in pick order; the message has no header, so
    its one dimension's label is the picks' stamp, '<sec>.<nanosec, 9 digits>'."""
    msg = Float32MultiArray()
    n = len(values)
    msg.layout.dim = [MultiArrayDimension(label=f"{stamp.sec}.{stamp.nanosec:09d}", size=n,
                                          stride=n)]
    msg.data = [float(v) for v in values]
    return msg


class PickOutput:
    """Publishers, CameraInfo subscription and target frame of the picks of one node."""

    def __init__(self, node, cfg, use_tf: bool):
        from inseggan_ros.runtime.picks import PickConfig

        self.node, self.cfg = node, PickConfig(**cfg, areas=False)  # no area is published
        self.pub_picks = node.create_lifecycle_publisher(PoseArray, "~/picks", 5)
        self.pub_markers = node.create_lifecycle_publisher(MarkerArray, "~/markers", 5)
        self.pub_confidence = node.create_lifecycle_publisher(Float32MultiArray,
                                                              "~/pick_confidence", 5)
        self.frame, self.translation, self.rotation = "", np.zeros(3), np.array([0, 0, 0, 1.0])
        self.tf_buffer = self.tf_listener = None
        if use_tf:
            try:
                from tf2_ros import Buffer, TransformListener
            except ImportError:
                self.destroy()
                raise ConfigError("use_tf true needs tf2_ros (ROS 2 from apt: "
                                  "ros-jazzy-tf2-ros), which is not importable here; valid: "
                                  "use_tf false with target_translation and target_rotation")
            self.tf_buffer = Buffer()
            self.tf_listener = TransformListener(self.tf_buffer, node)
        self.sub_info = None
        self.camera_info = None  # the latest CameraInfo message
        self._warm_up()

    def _warm_up(self) -> None:
        """Picks of a synthetic frame, so that the first real one does not pay the imports
        (scipy's, half a second)."""
        from inseggan_ros.runtime.picks import compute_picks

        depth = np.full((40, 40), 0.5)
        labels = np.zeros(depth.shape, np.uint8)
        depth[5:20, 5:20], labels[5:20, 5:20] = 0.48, 1
        labels[15:30, 15:30] = 2
        compute_picks(depth, labels, np.array([[50.0, 0, 20], [0, 50.0, 20], [0, 0, 1]]), None,
                      self.cfg)[0].orientation()

    def destroy(self) -> None:
        for pub in (self.pub_picks, self.pub_markers, self.pub_confidence):
            self.node.destroy_lifecycle_publisher(pub)
        self.unsubscribe()
        self.tf_listener = self.tf_buffer = None

    def subscribe(self, topic: str, qos) -> None:
        self.sub_info = self.node.create_subscription(
            CameraInfo, topic, lambda m: setattr(self, "camera_info", m), qos)

    def unsubscribe(self) -> None:
        if self.sub_info is not None:
            self.node.destroy_subscription(self.sub_info)
            self.sub_info = None

    def set_target(self, frame: str, translation, rotation) -> None:
        self.frame, self.translation, self.rotation = frame, translation, rotation

    def subscribed(self) -> bool:
        return sum(p.get_subscription_count() for p in
                   (self.pub_picks, self.pub_markers, self.pub_confidence)) > 0

    def camera_matrix(self, shape: tuple[int, int]) -> np.ndarray:
        """K of the latest CameraInfo for a depth frame of `shape`; raises FrameError(reason,
        why) when there is none, its size differs or its K is unusable."""
        from inseggan_ros.runtime.picks import check_intrinsics

        topic = self.sub_info.topic_name if self.sub_info is not None else "camera_info"
        if self.camera_info is None:
            raise FrameError("no_camera_info", f"no CameraInfo received on {topic}: no picks")
        w, h, K = conversions.camera_info_size_and_K(self.camera_info)
        if (h, w) != tuple(shape):
            raise FrameError("camera_info_size", f"CameraInfo on {topic} is {w}x{h} but the "
                                                 f"depth is {shape[1]}x{shape[0]}: no picks")
        try:
            return check_intrinsics(K)
        except ValueError as e:
            raise FrameError("camera_info_k", f"CameraInfo on {topic}: {e}: no picks") from None

    def compute(self, header, depth: np.ndarray, seg, tau: float, max_height: float):
        """The picks of a segmented frame in the target frame and their confidences, in pick
        order; raises FrameError when the CameraInfo or the transform is missing."""
        from inseggan_ros.runtime.bin_check import instance_fit
        from inseggan_ros.runtime.picks import compute_picks, hidden_from_renders, transform_picks

        K = self.camera_matrix(depth.shape)
        transform = self._transform(header) if self.frame else None
        occluded = hidden_from_renders(seg.renders64, seg.labels64, tau, seg.scores)
        picks = compute_picks(depth, seg.labels, K, occluded, self.cfg)
        fit = instance_fit(seg.renders64, seg.x64, seg.fg64, tau, max_height, seg.labels64,
                           seg.scores)
        confidence = [float(fit[p.instance - 1]) if p.instance <= len(fit) else 0.0
                      for p in picks]
        if transform is not None:
            picks = transform_picks(picks, *transform)
        return picks, confidence

    def _transform(self, header):
        """(translation, rotation) target_frame <- the frame's own: the parameters', or tf's."""
        if self.tf_buffer is None:
            return self.translation, self.rotation
        from rclpy.time import Time

        try:
            tf = self.tf_buffer.lookup_transform(self.frame, header.frame_id,
                                                 Time.from_msg(header.stamp)).transform
        except Exception as e:  # tf2's lookup, connectivity and extrapolation errors
            raise FrameError("tf", f"no transform {self.frame} <- {header.frame_id} at the "
                                   f"frame's stamp in tf ({type(e).__name__}: {e}): no picks")
        r = tf.rotation
        return (np.array([tf.translation.x, tf.translation.y, tf.translation.z]),
                np.array([r.x, r.y, r.z, r.w]))

    def publish(self, header, picks, confidence) -> None:
        """~/picks, ~/pick_confidence (same order) and, when subscribed, ~/markers, in the
        target frame with the input's stamp."""
        from std_msgs.msg import Header

        out = Header(stamp=header.stamp, frame_id=self.frame or header.frame_id)
        self.pub_picks.publish(conversions.picks_to_pose_array(picks, out))
        self.pub_confidence.publish(confidence_msg(confidence, out.stamp))
        if self.pub_markers.get_subscription_count() > 0:
            self.pub_markers.publish(conversions.picks_to_markers(picks, out))
