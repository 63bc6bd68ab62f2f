"""sensor_msgs/Image, CompressedImage (image_transport's compressedDepth) and CameraInfo <->
numpy. The only place that touches message fields."""
from __future__ import annotations

import array

import numpy as np
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from inseggan_ros.core import image_codec
from inseggan_ros.io.bags import CameraInfo as CameraInfoData


def image_to_numpy(msg: Image, allowed: tuple[str, ...] | None = None,
                   copy: bool = True) -> np.ndarray:
    """Decode an Image (row padding, endianness); raises image_codec.ImageFormatError.
    `copy=False`: a view of the message's data where possible (`image_codec.decode`)."""
    return image_codec.decode(msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step,
                              msg.data, allowed=allowed, copy=copy)


def depth_to_numpy(msg: Image | CompressedImage) -> tuple[np.ndarray, str]:
    """A depth Image, or a compressedDepth CompressedImage -> (raw depth, encoding): uint16
    millimetres or float32 metres (image_codec). Raises image_codec.ImageFormatError."""
    if isinstance(msg, CompressedImage):
        return image_codec.decode_compressed_depth(msg.format, msg.data)
    return image_to_numpy(msg, allowed=image_codec.DEPTH_ENCODINGS), msg.encoding


def depth_to_metres(msg: Image | CompressedImage) -> np.ndarray:
    """Depth Image (16UC1/mono16 millimetres or 32FC1 metres), or a compressedDepth
    CompressedImage of one -> float32 metres, 0 = no reading."""
    if isinstance(msg, CompressedImage):
        return image_codec.depth_to_metres(*depth_to_numpy(msg))
    raw = image_to_numpy(msg, allowed=image_codec.DEPTH_ENCODINGS, copy=False)
    return image_codec.depth_to_metres(raw, msg.encoding)


def numpy_to_compressed_depth(arr: np.ndarray, encoding: str, header: Header | None = None,
                              **codec) -> CompressedImage:
    """Raw depth (uint16 mm for 16UC1, float32 m for 32FC1) -> a CompressedImage as
    image_transport's compressedDepth plugin publishes it; `codec`: its parameters
    (image_codec.encode_compressed_depth: depth_max, depth_quantization, png_level)."""
    fmt, data = image_codec.encode_compressed_depth(arr, encoding, **codec)
    return compressed_image(fmt, data, header)


def compressed_image(fmt: str, data: bytes, header: Header | None = None) -> CompressedImage:
    """A CompressedImage of the given format and bytes (e.g. a bag's, passed on unchanged)."""
    msg = CompressedImage(format=fmt)
    if header is not None:
        msg.header = header
    buf = array.array("B")
    buf.frombytes(data)
    msg.data = buf
    return msg


def numpy_to_image(arr: np.ndarray, encoding: str, header: Header | None = None) -> Image:
    step, data = image_codec.encode_array(arr, encoding)  # copied once, into the message
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding, msg.is_bigendian, msg.step = encoding, 0, step
    buf = array.array("B")
    buf.frombytes(data.reshape(-1).view(np.uint8))  # array.array: rclpy's fast path
    msg.data = buf
    return msg


def camera_info_to_msg(info: CameraInfoData, header: Header | None = None) -> CameraInfo:
    msg = CameraInfo()
    if header is not None:
        msg.header = header
    msg.width, msg.height = int(info.width), int(info.height)
    msg.distortion_model = info.distortion_model
    msg.d = [float(x) for x in np.asarray(info.D).reshape(-1)]
    K = np.asarray(info.K, float).reshape(3, 3)
    msg.k = K.reshape(-1).tolist()
    msg.r = np.eye(3).reshape(-1).tolist()
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg.p = P.reshape(-1).tolist()
    return msg


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def camera_info_size_and_K(msg: CameraInfo) -> tuple[int, int, np.ndarray]:
    """(width, height, K 3 x 3) of a CameraInfo message."""
    return int(msg.width), int(msg.height), np.asarray(msg.k, float).reshape(3, 3)


def picks_to_pose_array(picks, header: Header):
    """geometry_msgs/PoseArray: per pick (in pick order) position = the visible surface's
    centroid, orientation = a frame whose z axis is the surface normal, toward the camera."""
    from geometry_msgs.msg import Pose, PoseArray

    msg = PoseArray(header=header)
    for pk in picks:
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in pk.position)
        q = pk.orientation()
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = \
            (float(v) for v in q)
        msg.poses.append(pose)
    return msg


ARROW_LENGTH = 0.03  # metres, the normal arrows in ~/markers


def picks_to_markers(picks, header: Header):
    """visualization_msgs/MarkerArray for RViz: a DELETEALL (clears the last frame's), then per
    pick an arrow along its normal from its centroid (green: free, orange: something on it)
    and a text '<rank>: #<label>' (+ ' under' when not free) above it."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker, MarkerArray

    out = MarkerArray()
    out.markers.append(Marker(header=header, ns="picks", action=Marker.DELETEALL))
    for rank, pk in enumerate(picks, 1):
        colour = (0.1, 0.9, 0.2) if pk.free else (1.0, 0.55, 0.0)
        tip = pk.position + ARROW_LENGTH * pk.normal
        arrow = Marker(header=header, ns="picks", id=2 * rank, type=Marker.ARROW,
                       action=Marker.ADD)
        arrow.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in
                        (pk.position, tip)]
        arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.002, 0.004, 0.006  # shaft, head, head
        arrow.pose.orientation.w = 1.0
        arrow.color.r, arrow.color.g, arrow.color.b = colour
        arrow.color.a = 1.0
        text = Marker(header=header, ns="picks", id=2 * rank + 1, type=Marker.TEXT_VIEW_FACING,
                      action=Marker.ADD, text=f"{rank}: #{pk.instance}"
                      + ("" if pk.free else " under"))
        text.pose.position.x, text.pose.position.y, text.pose.position.z = \
            (float(v) for v in pk.position + 1.2 * ARROW_LENGTH * pk.normal)
        text.pose.orientation.w = 1.0
        text.scale.z = 0.008  # letter height, metres
        text.color.r, text.color.g, text.color.b = colour
        text.color.a = 1.0
        out.markers.append(text)
        out.markers.append(arrow)
    return out
