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
