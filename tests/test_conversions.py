"""numpy <-> sensor_msgs/Image in the nodes: every encoding they publish round-trips exactly."""
import numpy as np
import pytest

from inseggan_ros.ros import conversions


@pytest.mark.parametrize("encoding, dtype, channels", [
    ("mono8", np.uint8, 1), ("16UC1", np.uint16, 1), ("32FC1", np.float32, 1),
    ("rgb8", np.uint8, 3), ("8UC5", np.uint8, 5)])
def test_images_round_trip(encoding, dtype, channels):
    rng = np.random.default_rng(0)
    shape = (7, 9) if channels == 1 else (7, 9, channels)
    arr = (rng.random(shape) * 200).astype(dtype)
    msg = conversions.numpy_to_image(arr[::1], encoding)
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian) == (7, 9, encoding, 0)
    assert msg.step == 9 * channels * np.dtype(dtype).itemsize and len(msg.data) == 7 * msg.step
    np.testing.assert_array_equal(conversions.image_to_numpy(msg), arr)
    # a non-contiguous view (a crop) is written as the image it shows
    crop = arr[1:5, 2:8]
    np.testing.assert_array_equal(
        conversions.image_to_numpy(conversions.numpy_to_image(crop, encoding)), crop)


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_compressed_depth_messages(encoding):
    """An array -> CompressedImage (image_transport's compressedDepth) -> array and metres, as the
    nodes publish and read it; a recorded message's bytes pass through unchanged."""
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import Header

    from inseggan_ros.core import image_codec

    rng = np.random.default_rng(3)
    metres = rng.uniform(0.3, 1.2, (12, 16)).astype(np.float32)
    metres[0, 0] = 0.0
    raw = image_codec.metres_to_depth(metres, encoding)
    header = Header(frame_id="cam")
    msg = conversions.numpy_to_compressed_depth(raw, encoding, header, png_level=1)
    assert isinstance(msg, CompressedImage) and msg.header.frame_id == "cam"
    assert msg.format == f"{encoding}; compressedDepth png"
    back, enc = conversions.depth_to_numpy(msg)
    assert enc == encoding
    got = conversions.depth_to_metres(msg)
    assert got[0, 0] == 0.0 and got.dtype == np.float32
    if encoding == "16UC1":
        np.testing.assert_array_equal(back, raw)
        np.testing.assert_array_equal(got, conversions.depth_to_metres(
            conversions.numpy_to_image(raw, encoding)))
    else:
        a, _ = image_codec.inverse_depth_params()
        assert (np.abs(got - metres) <= image_codec.quantisation_bound(metres, a) + 1e-6).all()
    same = conversions.compressed_image(msg.format, bytes(msg.data), header)
    assert same.format == msg.format and bytes(same.data) == bytes(msg.data)
    with pytest.raises(image_codec.ImageFormatError, match="truncated"):
        conversions.depth_to_metres(conversions.compressed_image(msg.format, b"\0" * 8))
