"""core.arrays: the sort-based unique and duplicate count equal NumPy's definitions; the
kernels' argument form."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.arrays import contiguous64, duplicates, sorted_unique


@pytest.mark.parametrize('a', [np.array([], np.uint32), np.array([7], np.int64),
                               np.array([3, 1, 3, 3, 2, 1], np.uint32),
                               np.random.default_rng(0).integers(0, 500, 2000)])
def test_sorted_unique_and_duplicates_match_numpy(a):
    np.testing.assert_array_equal(sorted_unique(a), np.unique(a))
    assert sorted_unique(a).dtype == a.dtype
    assert duplicates(a) == a.size - np.unique(a).size


def test_contiguous64_converts_only_what_it_must():
    a = np.zeros((3, 4))
    b = np.arange(12, dtype=np.float32).reshape(3, 4)
    c = np.zeros((4, 3)).T
    out = contiguous64(a, b, c)
    assert out[0] is a
    assert all(o.dtype == np.float64 and o.flags.c_contiguous for o in out)
    np.testing.assert_array_equal(out[1], b)
    np.testing.assert_array_equal(out[2], c)
