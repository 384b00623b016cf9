"""Host connectivity helpers of triplet_cl.topology."""

from __future__ import annotations

import numpy as np
import pytest

from triplet_cl.topology import unique_ints


@pytest.mark.parametrize("shape,high", [((0,), 5), ((1,), 5), ((1000,), 7), ((500, 3), 10**12), ((20000,), 10**6)])
def test_unique_ints_is_np_unique(shape, high):
    x = np.random.default_rng(0).integers(-high, high, shape)
    got, want = unique_ints(x), np.unique(x)
    assert got.dtype == want.dtype
    np.testing.assert_array_equal(got, want)
