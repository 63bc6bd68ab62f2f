"""core.order_stats: numpy's percentile and median, the same numbers in the same dtype."""
import numpy as np

from inseggan_ros.core.order_stats import median, percentile


def test_percentile_and_median_are_numpys_numbers_in_its_dtype():
    rng = np.random.default_rng(3)
    for trial in range(3000):
        dtype = np.float32 if trial % 2 else np.float64
        values = (rng.random(int(rng.integers(1, 400))) * [1e-3, 1.0, 1e3][trial % 3])
        if trial % 5 == 0:  # ties
            values = np.round(values, 2)
        values = values.astype(dtype)
        for q in (0, 5, 37.3, 50, 70, 100):
            want, got = np.percentile(values, q), percentile(values, q)
            assert got == want and np.asarray(got).dtype == np.asarray(want).dtype, (q, values)
        assert percentile(values, 70) == np.quantile(values, 0.7)
        want, got = np.median(values), median(values)
        assert got == want and np.asarray(got).dtype == np.asarray(want).dtype, values


def test_the_input_is_left_as_it_is():
    values = np.array([3.0, 1.0, 2.0, 5.0])
    percentile(values, 5), median(values)
    np.testing.assert_array_equal(values, [3.0, 1.0, 2.0, 5.0])
