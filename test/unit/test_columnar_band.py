"""The replay's CSV text of doubles in [1e-5, 1e-4), sliced from polars' digits, is repr's."""

import numpy as np
import pytest

pl = pytest.importorskip('polars')

from kf_train.io import columnar  # noqa: E402, I100


def test_band_text_is_repr_for_every_bit_pattern_of_the_band():
    """Random bit patterns of 1e-5 <= |v| < 1e-4, both signs, and the band's edges."""
    rng = np.random.default_rng(13)
    low, high = np.float64(1e-5).view(np.int64), np.float64(1e-4).view(np.int64)
    bits = rng.integers(low, high, 200_000).view(np.float64)
    edges = np.array([1e-5, 2e-5, 5e-5, 1.5e-5, 1.0000000000000001e-05,
                      9.999999999999999e-05, np.nextafter(1e-5, 1.0),
                      np.nextafter(1e-4, 0.0)])
    values = np.concatenate([edges, -edges, bits, -bits[::2]])
    text = columnar.repr_strings(values, 'var_position')
    assert text.name == 'var_position'
    assert text.to_list() == [repr(v) for v in values.tolist()]


def test_band_mixed_with_other_magnitudes_keeps_every_row_in_place():
    """A column crossing the band (a Q = 0 variance) is repr's row by row."""
    values = 4.0 / np.arange(1.0, 600_001.0, 7.0)          # 4 .. 6.7e-6: three layouts
    values[::5] *= -1.0
    assert columnar.repr_strings(values).to_list() == [repr(v) for v in values.tolist()]
