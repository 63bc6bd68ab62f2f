"""sensor_msgs/Image fields <-> numpy, without ROS: shared by the bag tools and the nodes.

Follows the `sensor_msgs/image_encodings.hpp` names. Rows may be padded (`step` > width * bytes
per pixel); big-endian data is byte-swapped. Every violation raises `ImageFormatError` with a
message that says what was wrong and what is valid.
"""
from __future__ import annotations

import struct
import zlib

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


# ------------------------------------------------------------ compressedDepth (image_transport)
# compressed_depth_image_transport's sensor_msgs/CompressedImage: `format` is
# "<encoding>; compressedDepth png" (older releases: "<encoding>; compressedDepth"), `data` a
# 12-byte ConfigHeader -- int32 compression format (INV_DEPTH = 0), float32 depthParam[2], little
# endian -- then a 16-bit single-channel PNG. 16UC1/mono16: the PNG holds the millimetres as they
# are (depthParam unused, zero). 32FC1: it holds inverse depth, value = (uint16)(a / depth + b)
# with a = q (q + 1) and b = 1 - a / depth_max (q: depth_quantization); depth = a / (value - b),
# value 0 = no reading. The defaults are image_transport's (depth_max 10 m, q 100, PNG level 9).
COMPRESSED_DEPTH = "compressedDepth"
CONFIG_HEADER = struct.Struct("<iff")
INV_DEPTH = 0
DEPTH_MAX = 10.0
DEPTH_QUANTIZATION = 100.0
PNG_LEVEL = 9
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def is_compressed_depth(fmt: str) -> bool:
    """A CompressedImage `format` written by compressed_depth_image_transport."""
    return COMPRESSED_DEPTH in str(fmt)


def _compressed_depth_encoding(fmt: str) -> str:
    """The depth encoding a compressedDepth `format` names; PNG payloads only."""
    valid = ("valid: '<16UC1|mono16|32FC1>; compressedDepth png' (or '...; compressedDepth', "
             "as older image_transport releases write it)")
    if not is_compressed_depth(fmt):
        raise ImageFormatError(f"format {fmt!r} is not compressed_depth_image_transport's; {valid}")
    encoding, _, rest = str(fmt).partition(";")
    encoding, codec = encoding.strip(), rest.strip()
    if codec not in (COMPRESSED_DEPTH, f"{COMPRESSED_DEPTH} png"):
        raise ImageFormatError(f"format {fmt!r}: compression {codec!r} is not supported (RVL is "
                               f"not read here); {valid}")
    if encoding not in DEPTH_ENCODINGS:
        raise ImageFormatError(f"format {fmt!r}: depth encoding {encoding!r} unsupported; {valid}")
    return encoding


def _png_size(png: bytes, fmt: str) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR, checked before decoding allocates anything."""
    if len(png) < 24 or png[:8] != _PNG_MAGIC or png[12:16] != b"IHDR":
        raise ImageFormatError(f"format {fmt!r}: the data after the 12-byte ConfigHeader is not "
                               f"a PNG ({len(png)} bytes, starting {png[:8]!r}); valid: a PNG "
                               "of the 16-bit single-channel image")
    width, height = struct.unpack(">II", png[16:24])
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise ImageFormatError(f"format {fmt!r}: PNG of {width}x{height}; valid: 1 to "
                               f"{MAX_SIDE} per side")
    _check_png_chunks(png, fmt)
    return width, height


def _check_png_chunks(png: bytes, fmt: str) -> None:
    """Every chunk whole, its CRC right, through IEND: a cut or garbled PNG is named here rather
    than by libpng's messages on stderr."""
    pos = len(_PNG_MAGIC)
    while pos + 12 <= len(png):
        length, kind = struct.unpack(">I4s", png[pos:pos + 8])
        end = pos + 12 + length
        if end > len(png):
            break
        if zlib.crc32(png[pos + 4:end - 4]) != struct.unpack(">I", png[end - 4:end])[0]:
            raise ImageFormatError(f"format {fmt!r}: the PNG's {kind!r} chunk at byte {pos} "
                                   "fails its CRC; valid: an intact PNG")
        if kind == b"IEND":
            return
        pos = end
    raise ImageFormatError(f"format {fmt!r}: the PNG ({len(png)} bytes) is cut short before "
                           "its IEND chunk; valid: a whole PNG")


def decode_compressed_depth(fmt: str, data) -> tuple[np.ndarray, str]:
    """A compressedDepth CompressedImage's `format` and `data` -> (depth, encoding): uint16
    millimetres for 16UC1/mono16 (exactly what was encoded), float32 metres for 32FC1 (NaN = no
    reading, as image_transport decodes it). Raises ImageFormatError naming the problem."""
    import cv2

    encoding = _compressed_depth_encoding(fmt)
    buf = bytes(np.asarray(data, np.uint8).reshape(-1)) if isinstance(data, np.ndarray) \
        else bytes(data)
    if len(buf) <= CONFIG_HEADER.size:
        raise ImageFormatError(f"format {fmt!r}: data of {len(buf)} bytes is truncated; valid: a "
                               f"{CONFIG_HEADER.size}-byte ConfigHeader, then a PNG")
    kind, a, b = CONFIG_HEADER.unpack_from(buf)
    if kind != INV_DEPTH:
        raise ImageFormatError(f"format {fmt!r}: ConfigHeader compression format {kind}; valid: "
                               f"{INV_DEPTH} (INV_DEPTH)")
    png = buf[CONFIG_HEADER.size:]
    width, height = _png_size(png, fmt)
    try:
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        image, why = None, str(e).strip().splitlines()[-1]
    else:
        why = "cv2.imdecode found it corrupt or cut short"
    if image is None:
        raise ImageFormatError(f"format {fmt!r}: the {width}x{height} PNG does not decode "
                               f"({why}); valid: a whole PNG")
    if image.dtype != np.uint16 or image.ndim != 2 or image.shape != (height, width):
        raise ImageFormatError(f"format {fmt!r}: the PNG holds a {image.dtype} image of shape "
                               f"{image.shape}; valid: 16-bit single-channel {width}x{height}")
    if encoding != "32FC1":
        return image, encoding
    if not (np.isfinite(a) and np.isfinite(b) and a > 0):
        raise ImageFormatError(f"format {fmt!r}: depthParam ({a}, {b}) cannot dequantise; "
                               "valid: finite, a > 0")
    with np.errstate(divide="ignore"):
        depth = np.float32(a) / (image.astype(np.float32) - np.float32(b))
    depth[image == 0] = np.nan
    return depth, encoding


def inverse_depth_params(depth_max: float = DEPTH_MAX,
                         depth_quantization: float = DEPTH_QUANTIZATION) -> tuple[float, float]:
    """(a, b) of 32FC1 compressedDepth, in float32 as image_transport computes them."""
    q, dmax = np.float32(depth_quantization), np.float32(depth_max)
    a = np.float32(q * (q + np.float32(1.0)))
    return float(a), float(np.float32(np.float32(1.0) - a / dmax))


def quantisation_bound(depth: np.ndarray, a: float) -> np.ndarray:
    """The most a 32FC1 depth (metres) moves through compressedDepth and back: truncating
    a / d + b to an integer v, decoding a / (v - b), gives d <= d' < d a / (a - d), so
    0 <= d' - d < d^2 / (a - d) (1e-4 m at 1 m, 1 cm at 10 m with the defaults' a = 10100),
    plus float32 rounding (a few units in the last place of d)."""
    d = np.asarray(depth, np.float64)
    return d * d / (a - d)


def encode_compressed_depth(depth: np.ndarray, encoding: str, depth_max: float = DEPTH_MAX,
                            depth_quantization: float = DEPTH_QUANTIZATION,
                            png_level: int = PNG_LEVEL) -> tuple[str, bytes]:
    """Depth (uint16 millimetres for 16UC1/mono16, float32 metres for 32FC1) -> (format, data)
    as compressed_depth_image_transport publishes them, with its parameters.

    16UC1: values above depth_max (in mm) become 0, as image_transport drops them; the rest
    round-trip exactly. 32FC1: NaN, <= 0 and >= depth_max are 0 (no reading); so are depths too
    near to quantise (a / d + b > 65535: below 0.152 m at the defaults), which image_transport's
    cast would wrap to a wrong depth; the rest come back within `quantisation_bound`."""
    import cv2

    if encoding not in DEPTH_ENCODINGS:
        raise ImageFormatError(f"compressedDepth encoding {encoding!r} unsupported; valid: "
                               f"{', '.join(DEPTH_ENCODINGS)}")
    _, a = encode_array(depth, encoding)  # checks shape and dtype
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageFormatError(f"empty depth image {a.shape}; width and height must be > 0")
    if not (0 <= int(png_level) <= 9):
        raise ImageFormatError(f"PNG level {png_level} invalid; valid: 0 to 9")
    if not (depth_max > 0 and depth_quantization > 0):
        raise ImageFormatError(f"depth_max {depth_max} and depth_quantization "
                               f"{depth_quantization} invalid; valid: > 0")
    qa = qb = 0.0
    if encoding == "32FC1":
        qa, qb = inverse_depth_params(depth_max, depth_quantization)
        d = a.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(qa) / d + np.float32(qb)
            keep = np.isfinite(d) & (d > 0) & (d < np.float32(depth_max)) & (inv < 65536)
        image = np.where(keep, inv, 0).astype(np.uint16)  # truncates, as C++'s cast does
    else:
        image = np.where(a > min(int(depth_max * 1000.0), 65535), 0, a).astype(np.uint16)
    ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise ImageFormatError(f"cv2.imencode could not write a {image.shape} PNG")
    return (f"{encoding}; {COMPRESSED_DEPTH} png",
            CONFIG_HEADER.pack(INV_DEPTH, qa, qb) + png.tobytes())
