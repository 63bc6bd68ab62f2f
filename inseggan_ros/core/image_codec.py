"""sensor_msgs/Image fields <-> numpy, without ROS: shared by the bag tools and the nodes.

Follows the `sensor_msgs/image_encodings.hpp` names. Rows may be padded (`step` > width * bytes
per pixel); big-endian data is byte-swapped. Every violation raises `ImageFormatError` with a
message that says what was wrong and what is valid.
"""
from __future__ import annotations

import numpy as np

# encoding -> (numpy dtype, channels)
ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "16UC1": (np.dtype(np.uint16), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
}
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")  # 16-bit: millimetres; 32FC1: metres
MAX_SIDE = 16384


class ImageFormatError(ValueError):
    """An Image whose fields do not describe a valid image of a supported encoding."""


def _dtype_channels(encoding: str) -> tuple[np.dtype, int]:
    if encoding in ENCODINGS:
        return ENCODINGS[encoding]
    if encoding.startswith("8UC") and encoding[3:].isdigit() and 1 <= int(encoding[3:]) <= 255:
        return np.dtype(np.uint8), int(encoding[3:])
    raise ImageFormatError(f"unsupported encoding {encoding!r}; "
                           f"valid: {', '.join(ENCODINGS)}, 8UC<n>")


def decode(height: int, width: int, encoding: str, is_bigendian: int, step: int,
           data, allowed: tuple[str, ...] | None = None, copy: bool = True) -> np.ndarray:
    """Image fields -> (H, W) or (H, W, C) array (a copy, native byte order). `copy=False`:
    a view of `data` where no copy is needed (native byte order, no row padding), possibly
    read-only, for a caller that converts it at once (the node: one pass over the frame less)."""
    if allowed is not None and encoding not in allowed:
        raise ImageFormatError(f"unsupported encoding {encoding!r}; valid: {', '.join(allowed)}")
    dtype, channels = _dtype_channels(encoding)
    if height <= 0 or width <= 0:
        raise ImageFormatError(f"empty image {width}x{height}; width and height must be > 0")
    if height > MAX_SIDE or width > MAX_SIDE:
        raise ImageFormatError(f"image {width}x{height} too large; "
                               f"valid: up to {MAX_SIDE} per side")
    row = width * channels * dtype.itemsize
    if step < row:
        raise ImageFormatError(f"step {step} < width*bytes per pixel = {row} for {width}x{height} "
                               f"{encoding}")
    buf = (np.asarray(data).reshape(-1).view(np.uint8) if isinstance(data, np.ndarray)
           else np.frombuffer(data, np.uint8))  # bytes, array.array('B'), memoryview
    if buf.size != step * height:
        raise ImageFormatError(f"data has {buf.size} bytes, "
                               f"expected step*height = {step}*{height} = "
                               f"{step * height} for {width}x{height} {encoding}")
    rows = np.ascontiguousarray(buf.reshape(height, step)[:, :row])
    order = ">" if is_bigendian and dtype.itemsize > 1 else "<"
    arr = rows.view(dtype.newbyteorder(order)).astype(dtype, copy=copy)  # native order
    return arr.reshape(height, width, channels) if channels > 1 else arr.reshape(height, width)


def encode(array: np.ndarray, encoding: str) -> tuple[int, bytes]:
    """(H, W[, C]) array -> (step, little-endian bytes) for the given encoding."""
    step, a = encode_array(array, encoding)
    return step, a.tobytes()


def encode_array(array: np.ndarray, encoding: str) -> tuple[int, np.ndarray]:
    """`encode` without the copy into bytes: (step, C-contiguous little-endian array)."""
    dtype, channels = _dtype_channels(encoding)
    a = np.asarray(array)
    shape_ok = a.ndim == 2 and channels == 1 or a.ndim == 3 and a.shape[2] == channels
    if not shape_ok:
        raise ImageFormatError(f"array of shape {a.shape} does not fit encoding {encoding!r} "
                               f"({channels} channel(s))")
    if a.dtype != dtype:
        raise ImageFormatError(f"array dtype {a.dtype} does not fit encoding {encoding!r} "
                               f"({dtype})")
    a = np.ascontiguousarray(a, dtype.newbyteorder("<"))
    return a.shape[1] * channels * dtype.itemsize, a


def depth_to_metres(raw: np.ndarray, encoding: str) -> np.ndarray:
    """Raw depth (16-bit millimetres or 32-bit float metres) -> float32 metres, 0 = no reading."""
    if encoding in ("16UC1", "mono16"):
        return np.multiply(raw, np.float32(0.001), dtype=np.float32)  # one pass, a new array
    if encoding == "32FC1":
        out = raw.astype(np.float32, copy=True)
        out[~np.isfinite(out) | (out < 0)] = 0.0
        return out
    raise ImageFormatError(f"unsupported depth encoding {encoding!r}; "
                           f"valid: {', '.join(DEPTH_ENCODINGS)}")


def metres_to_depth(depth_m: np.ndarray, encoding: str) -> np.ndarray:
    """Float metres -> raw depth of the given encoding (0 = no reading)."""
    d = np.asarray(depth_m, np.float32)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    if encoding in ("16UC1", "mono16"):
        return np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
    if encoding == "32FC1":
        return d.astype(np.float32)
    raise ImageFormatError(f"unsupported depth encoding {encoding!r}; "
                           f"valid: {', '.join(DEPTH_ENCODINGS)}")
