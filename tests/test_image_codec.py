import numpy as np
import pytest

from inseggan_ros.core import image_codec
from inseggan_ros.core.image_codec import ImageFormatError, decode, encode


@pytest.mark.parametrize("encoding,dtype", [("16UC1", np.uint16), ("32FC1", np.float32),
                                            ("mono8", np.uint8)])
def test_round_trip(encoding, dtype):
    a = (np.random.default_rng(0).random((7, 5)) * 200).astype(dtype)
    step, data = encode(a, encoding)
    assert step == 5 * np.dtype(dtype).itemsize
    np.testing.assert_array_equal(decode(7, 5, encoding, 0, step, data), a)


def test_row_padding_is_skipped():
    a = np.arange(12, dtype=np.uint16).reshape(3, 4)
    padded = np.zeros((3, 16), np.uint8)  # step 16 > 4 * 2 bytes
    padded[:, :8] = a.view(np.uint8).reshape(3, 8)
    padded[:, 8:] = 0xEE  # garbage in the padding must not leak
    np.testing.assert_array_equal(decode(3, 4, "16UC1", 0, 16, padded.tobytes()), a)


def test_without_copy_a_frame_is_a_view_where_it_can_be():
    a = np.arange(12, dtype=np.uint16).reshape(3, 4)
    data = bytearray(a.tobytes())
    view = decode(3, 4, "16UC1", 0, 8, data, copy=False)
    np.testing.assert_array_equal(view, a)
    data[0] = 7  # the view sees the message's bytes; the default copy does not
    assert view[0, 0] == 7
    copied = decode(3, 4, "16UC1", 0, 8, data)
    data[0] = 9
    assert copied[0, 0] == 7
    # padded rows and the other byte order cannot be viewed: still right, as a copy
    swapped = decode(1, 2, "32FC1", 1, 8, np.array([[1.5, -2.25]], ">f4").tobytes(), copy=False)
    assert swapped.dtype.byteorder in "=<|"
    np.testing.assert_array_equal(swapped, [[1.5, -2.25]])


def test_big_endian_is_swapped():
    a = np.array([[1.5, -2.25]], np.float32)
    out = decode(1, 2, "32FC1", 1, 8, a.astype(">f4").tobytes())
    assert out.dtype == np.float32 and out.dtype.byteorder in "=<|"
    np.testing.assert_array_equal(out, a)


def test_multichannel_masks():
    a = np.zeros((2, 3, 4), np.uint8)
    a[1, 2, 3] = 255
    step, data = encode(a, "8UC4")
    np.testing.assert_array_equal(decode(2, 3, "8UC4", 0, step, data), a)


@pytest.mark.parametrize("fields,match", [
    ((4, 4, "rgb16", 0, 24, bytes(96)), "unsupported encoding 'rgb16'; valid:"),
    ((0, 4, "16UC1", 0, 8, b""), "empty image"),
    ((4, 4, "16UC1", 0, 6, bytes(24)), "step 6 < width"),
    ((4, 4, "16UC1", 0, 8, bytes(31)), "data has 31 bytes, expected"),
])
def test_bad_images_name_the_problem(fields, match):
    with pytest.raises(ImageFormatError, match=match):
        decode(*fields)


def test_allowed_encodings_are_enforced():
    with pytest.raises(ImageFormatError, match="valid: 16UC1, mono16, 32FC1"):
        decode(1, 1, "mono8", 0, 1, b"\x00", allowed=image_codec.DEPTH_ENCODINGS)


def test_depth_units():
    mm = np.array([[0, 500, 65535]], np.uint16)
    np.testing.assert_allclose(image_codec.depth_to_metres(mm, "16UC1"), [[0, 0.5, 65.535]], 1e-6)
    m = np.array([[np.nan, np.inf, -1, 0.25]], np.float32)
    np.testing.assert_array_equal(image_codec.depth_to_metres(m, "32FC1"), [[0, 0, 0, 0.25]])
    np.testing.assert_array_equal(image_codec.metres_to_depth(
        np.array([[0.4996, np.nan, 0]]), "16UC1"), [[500, 0, 0]])


# ------------------------------------------------------------ compressedDepth (image_transport)
def _layout(data: bytes):
    """(ConfigHeader fields, the PNG's image) read with struct and cv2 alone: the layout
    compressed_depth_image_transport writes, checked without the decoder under test."""
    import struct

    import cv2

    assert data[12:20] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack("<iff", data[:12]), cv2.imdecode(np.frombuffer(data[12:], np.uint8),
                                                          cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("encoding", ["16UC1", "mono16"])
def test_compressed_depth_16bit_round_trip_is_exact(encoding):
    rng = np.random.default_rng(1)
    depth = rng.integers(0, 10001, (37, 53)).astype(np.uint16)  # up to depth_max, 10 m
    depth[0, :4] = [0, 1, 10000, 65535]  # 65535 mm: beyond depth_max, dropped as image_transport
    fmt, data = image_codec.encode_compressed_depth(depth, encoding)
    assert fmt == f"{encoding}; compressedDepth png"
    header, png = _layout(data)
    assert header == (0, 0.0, 0.0)  # INV_DEPTH, no quantisation parameters for 16 bits
    kept = depth.copy()
    kept[0, 3] = 0
    np.testing.assert_array_equal(png, kept)
    back, enc = image_codec.decode_compressed_depth(fmt, data)
    assert enc == encoding and back.dtype == np.uint16
    np.testing.assert_array_equal(back, kept)
    # depth_max in metres moves the cut; PNG level changes the size, never the values
    back, _ = image_codec.decode_compressed_depth(
        *image_codec.encode_compressed_depth(depth, encoding, depth_max=70.0, png_level=1))
    np.testing.assert_array_equal(back, depth)


@pytest.mark.parametrize("depth_max, quantization", [(10.0, 100.0), (2.0, 30.0)])
def test_compressed_depth_32fc1_within_the_quantisation_bound(depth_max, quantization):
    rng = np.random.default_rng(2)
    a, b = image_codec.inverse_depth_params(depth_max, quantization)
    assert (a, b) == (np.float32(quantization * (quantization + 1)),
                      np.float32(1 - np.float32(a) / np.float32(depth_max)))
    near = a / (65535 - b)  # the nearest depth the 16 bits hold
    depth = rng.uniform(near * 1.001, depth_max * 0.999, (40, 60)).astype(np.float32)
    depth[0, :6] = [np.nan, 0.0, -1.0, depth_max, np.inf, near * 0.9]  # none are readings
    fmt, data = image_codec.encode_compressed_depth(depth, "32FC1", depth_max=depth_max,
                                                    depth_quantization=quantization)
    assert fmt == "32FC1; compressedDepth png"
    header, inv = _layout(data)
    assert header == (0, a, b) and inv.dtype == np.uint16
    assert (inv[0, :6] == 0).all() and (inv.reshape(-1)[6:] > 0).all()
    back, enc = image_codec.decode_compressed_depth(fmt, data)
    assert enc == "32FC1" and back.dtype == np.float32
    assert np.isnan(back[0, :6]).all()  # no reading, as image_transport decodes it
    d, got = depth.reshape(-1)[6:].astype(np.float64), back.reshape(-1)[6:].astype(np.float64)
    bound = image_codec.quantisation_bound(d, a)
    slack = 4 * np.spacing(np.float32(d)).astype(np.float64)  # float32 arithmetic
    err = got - d
    assert (err >= -slack).all() and (err <= bound + slack).all(), np.max(err / bound)
    assert np.max(err / bound) > 0.9  # the bound is what truncation reaches, not a loose one
    # decoding is a / (v - b) in float32, on the PNG's own values
    np.testing.assert_array_equal(
        back.reshape(-1)[6:], (np.float32(a) / (inv.astype(np.float32) - np.float32(b)))
        .reshape(-1)[6:])


def test_decodes_the_older_format_string_and_a_hand_made_message():
    """A message built from the layout alone (struct + cv2), with the format older
    image_transport releases write ('32FC1; compressedDepth', no codec name)."""
    import struct

    import cv2

    inv = np.array([[0, 1000, 20000], [65535, 5, 300]], np.uint16)
    data = struct.pack("<iff", 0, 10100.0, -1009.0) + cv2.imencode(".png", inv)[1].tobytes()
    depth, enc = image_codec.decode_compressed_depth("32FC1; compressedDepth", data)
    expected = np.float32(10100.0) / (inv.astype(np.float32) - np.float32(-1009.0))
    expected[inv == 0] = np.nan
    assert enc == "32FC1"
    np.testing.assert_array_equal(depth, expected)
    mm, enc = image_codec.decode_compressed_depth("16UC1; compressedDepth", data)
    assert enc == "16UC1"
    np.testing.assert_array_equal(mm, inv)


def _png_with_size(width: int, height: int) -> bytes:
    """A 16-bit PNG of 4 x 3 pixels whose IHDR claims width x height (its CRC made right)."""
    import struct
    import zlib

    import cv2

    png = bytearray(cv2.imencode(".png", np.ones((3, 4), np.uint16))[1].tobytes())
    png[16:24] = struct.pack(">II", width, height)
    png[29:33] = struct.pack(">I", zlib.crc32(bytes(png[12:29])))
    return bytes(png)


def _bad_messages():
    import struct

    import cv2

    fmt, good = image_codec.encode_compressed_depth(np.full((6, 8), 700, np.uint16), "16UC1")
    garbled = bytearray(good)
    garbled[-20] ^= 0xFF  # inside the image data: its chunk's CRC fails
    eight_bit = cv2.imencode(".png", np.zeros((6, 8), np.uint8))[1].tobytes()
    head = good[:12]
    return [
        ("jpeg", good, "not compressed_depth_image_transport's"),
        ("16UC1; compressedDepth rvl", good, "'compressedDepth rvl' is not supported"),
        ("rgb8; compressedDepth png", good, "depth encoding 'rgb8' unsupported"),
        (fmt, good[:8], "8 bytes is truncated; valid: a 12-byte ConfigHeader, then a PNG"),
        (fmt, good[:12], "12 bytes is truncated"),
        (fmt, struct.pack("<iff", 3, 0, 0) + good[12:], "compression format 3; valid: 0"),
        (fmt, head + b"GIF89a" + bytes(40), "is not a PNG"),
        (fmt, good[:-30], "cut short before its IEND chunk"),
        (fmt, bytes(garbled), "fails its CRC"),
        (fmt, head + eight_bit, "uint8 image of shape \\(6, 8\\); valid: 16-bit single-channel"),
        (fmt, head + _png_with_size(20000, 3), "PNG of 20000x3; valid: 1 to 16384 per side"),
        (fmt, head + _png_with_size(4, 300), "the 4x300 PNG does not decode"),
        ("32FC1; compressedDepth png", struct.pack("<iff", 0, 0.0, 1.0) + good[12:],
         "depthParam \\(0.0, 1.0\\) cannot dequantise"),
    ]


@pytest.mark.parametrize("fmt, data, match", _bad_messages())
def test_bad_compressed_depth_names_the_problem(fmt, data, match):
    with pytest.raises(ImageFormatError, match=match):
        image_codec.decode_compressed_depth(fmt, data)


@pytest.mark.parametrize("array, encoding, kwargs, match", [
    (np.zeros((4, 4), np.float32), "16UC1", {}, "dtype float32 does not fit encoding '16UC1'"),
    (np.zeros((4, 4, 3), np.uint8), "rgb8", {}, "compressedDepth encoding 'rgb8' unsupported"),
    (np.zeros((0, 4), np.uint16), "16UC1", {}, "empty depth image"),
    (np.zeros((4, 4), np.uint16), "16UC1", {"png_level": 10}, "PNG level 10 invalid; valid: 0"),
    (np.zeros((4, 4), np.float32), "32FC1", {"depth_max": 0.0}, "invalid; valid: > 0"),
])
def test_bad_compressed_depth_input_is_refused(array, encoding, kwargs, match):
    with pytest.raises(ImageFormatError, match=match):
        image_codec.encode_compressed_depth(array, encoding, **kwargs)
