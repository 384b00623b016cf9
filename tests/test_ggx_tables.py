"""The Cook-Torrance lobe's tables (triplet_cl/ggx_tables.py, kernels_cl/common/ggx_tables.h): the committed header is
what the module integrates, the tables have the lobe's known limits, and the host lookups are the kernel's."""

from __future__ import annotations

import numpy as np
from numpy.polynomial import legendre

from triplet_cl import ggx_tables


def test_committed_header_is_what_the_module_computes():
    # the header holds 7 decimals (float32 in the kernels); a regenerated table differs only by summation order
    for have, want in zip(ggx_tables.load(), ggx_tables.compute(), strict=True):
        np.testing.assert_allclose(have, want, atol=2e-6)


def test_tables_have_the_lobes_limits():
    A, B, bands = ggx_tables.load()
    nv = np.linspace(0, 1, ggx_tables.N_NV)
    # a mirror (roughness 0) reflects everything along the mirror direction, Schlick's share B = (1 - n.v)^5, and
    # passes every band
    np.testing.assert_allclose((A + B)[0, 1:], 1.0, atol=2e-3)
    np.testing.assert_allclose(B[0, 1:], (1 - nv[1:]) ** 5, atol=2e-3)
    np.testing.assert_allclose(bands[0], 1.0, atol=1e-6)
    np.testing.assert_allclose(bands[:, 0], 1.0, atol=1e-6)  # band 0 is the lobe's normalisation
    # the energy and the low bands fall as the lobe roughens (at normal incidence; the higher bands ring)
    assert np.all(np.diff((A + B)[:, -1]) <= 1e-6)
    assert np.all(np.diff(bands[:, 1:3], axis=0) <= 1e-6)
    # roughness 1 (alpha = 1: D = 1/pi, G1(x) = 2x / (x + 1)) at normal incidence: the reflected weight over the
    # hemisphere is mu / (2 pi (mu + 1)), mu = n.l: 1 - ln 2 of the light comes back, and band l is the ratio of two
    # 1D integrals over mu
    np.testing.assert_allclose(A[-1, -1] + B[-1, -1], 1 - np.log(2), atol=2e-3)
    mu = (np.arange(200000) + 0.5) / 200000
    w = mu / (mu + 1)
    for band in (1, 2, 3):
        want = np.sum(w * legendre.legval(mu, [0] * band + [1])) / np.sum(w)
        np.testing.assert_allclose(bands[-1, band], want, atol=2e-4)
    # a GGX lobe's reflection is wider than the Gaussian exp(-l (l + 1) alpha^2 / 2) of the same alpha (its tails):
    # at roughness 10/31 ~ 0.32, band 2 passes ~0.83 where that Gaussian passes ~0.97
    assert bands[10, 2] < np.exp(-3 * (10 / 31) ** 4) - 0.1


def test_host_lookups_interpolate_the_kernels_nodes():
    A, B, bands = ggx_tables.load()
    a, b = ggx_tables.dfg(np.array([0.0, 3 / 31, 1.0]), np.array([5 / 31, 1.0, 0.0]))
    np.testing.assert_allclose(a, [A[0, 5], A[3, 31], A[31, 0]], rtol=1e-6)
    np.testing.assert_allclose(b, [B[0, 5], B[3, 31], B[31, 0]], rtol=1e-6)
    mid, _ = ggx_tables.dfg(np.array([3.5 / 31]), np.array([1.0]))
    np.testing.assert_allclose(mid, 0.5 * (A[3, 31] + A[4, 31]), rtol=1e-6)
    lb = ggx_tables.lobe_bands(np.array([[10 / 31], [0.0], [1.0], [10.25 / 31]]), np.arange(9)[None, :])
    np.testing.assert_allclose(lb[:3], bands[[10, 0, 31]], rtol=1e-6)
    np.testing.assert_allclose(lb[3], 0.75 * bands[10] + 0.25 * bands[11], rtol=1e-6)
