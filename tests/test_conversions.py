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
