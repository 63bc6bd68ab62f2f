"""sensor_msgs/Image and CameraInfo <-> numpy. The only place that touches message fields."""
from __future__ import annotations

import array

import numpy as np
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from .. import image_codec
from ..bags import CameraInfo as CameraInfoData


def image_to_numpy(msg: Image, allowed: tuple[str, ...] | None = None) -> np.ndarray:
    """Decode an Image (row padding, endianness); raises image_codec.ImageFormatError."""
    return image_codec.decode(msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step,
                              msg.data, allowed=allowed)


def depth_to_metres(msg: Image) -> np.ndarray:
    """Depth Image (16UC1/mono16 millimetres or 32FC1 metres) -> float32 metres, 0 = no reading."""
    raw = image_to_numpy(msg, allowed=image_codec.DEPTH_ENCODINGS)
    return image_codec.depth_to_metres(raw, msg.encoding)


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
