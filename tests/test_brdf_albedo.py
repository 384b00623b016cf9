"""The directional-albedo table of the Cook-Torrance BRDF (triplet_cl/brdf_albedo.py, kernels_cl/common/brdf_albedo.h)."""

from __future__ import annotations

import numpy as np

from triplet_cl import brdf_albedo


def test_generated_header_is_the_generator_output():
    """The committed header is what ``python -m triplet_cl.brdf_albedo`` writes (regenerate it after a BRDF change)."""
    np.testing.assert_allclose(brdf_albedo.table(), brdf_albedo.compute(), atol=6e-7)
    assert brdf_albedo.header_path().read_text() == brdf_albedo.header_text(brdf_albedo.compute())


def test_known_limits():
    t = brdf_albedo.table()
    n = t.shape[1]
    nv = np.linspace(0, 1, n)
    # a mirror (r = 0) reflects everything (A1 = 1) with Schlick's grazing term exactly (1 - nv)^5
    np.testing.assert_allclose(t[1, 0, 1:], 1.0, atol=2e-3)
    np.testing.assert_allclose(t[2, 0, 1:], (1 - nv[1:]) ** 5, atol=2e-3)
    # Disney diffuse seen along the normal, smooth: (1 - 1/2 * 1/21)... its hemispherical mean 1 - 1/42 at nv = 1
    np.testing.assert_allclose(t[0, 0, -1], 1 - 1 / 42, atol=1e-3)
    # masking loses energy: monotone in roughness at normal view, a white rough metal ~0.3
    assert np.all(np.diff(t[1, :, -1]) < 1e-3) and 0.25 < t[1, -1, -1] < 0.35
    assert np.all(t[2] <= t[1] + 1e-6) and np.all(t >= 0)


def test_lookup_is_bilinear_between_the_grid():
    t = brdf_albedo.table()
    n = t.shape[1]
    i, j = 7, 20
    r0, v0 = i / (n - 1), j / (n - 1)
    np.testing.assert_allclose(brdf_albedo.lookup(r0, v0), t[:, i, j], atol=1e-12)
    mid = brdf_albedo.lookup(r0 + 0.5 / (n - 1), v0 + 0.5 / (n - 1))
    np.testing.assert_allclose(mid, t[:, i:i + 2, j:j + 2].mean(axis=(1, 2)), atol=1e-12)
    np.testing.assert_allclose(brdf_albedo.lookup(1.5, -1.0), t[:, -1, 0], atol=1e-12)  # clamped
