"""Real SH basis of kernels_cl/common/sh.h: definition (scipy), device evaluation and adjoint."""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import cs_grad
from tests.reference import sh as ref
from triplet_cl.ops.vertex_sh import sh_basis, sh_basis_backward


def _unit(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)




def test_recurrence_matches_scipy_definition(rng):
    d = _unit(rng, 200)
    d[:3] = [[0, 0, 1], [0, 0, -1], [1, 0, 0]]  # poles and the seam
    np.testing.assert_allclose(ref.sh_eval(8, d), ref.sh_scipy(8, d), atol=1e-10)


def test_low_degrees_match_3dgs_constants(rng):
    d = _unit(rng, 5)
    x, y, z = d.T
    c0, c1 = 0.28209479177387814, 0.4886025119029199
    Y = ref.sh_eval(2, d)
    np.testing.assert_allclose(Y[:, 0], c0)
    np.testing.assert_allclose(Y[:, 1:4], np.stack([-c1 * y, c1 * z, -c1 * x], 1), atol=1e-14)
    np.testing.assert_allclose(Y[:, 4], 1.0925484305920792 * x * y, atol=1e-14)
    np.testing.assert_allclose(Y[:, 8], 0.5462742152960396 * (x * x - y * y), atol=1e-14)


def test_orthonormal():
    # Gauss-Legendre in cos(theta) x uniform in phi: exact for polynomials of this degree
    z, w = np.polynomial.legendre.leggauss(12)
    phi = (np.arange(24) + 0.5) * 2 * np.pi / 24
    Z, PH = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z**2)
    d = np.stack([s * np.cos(PH), s * np.sin(PH), Z], -1).reshape(-1, 3)
    wt = np.repeat(w, 24) * 2 * np.pi / 24
    Y = ref.sh_eval(5, d)
    np.testing.assert_allclose(Y.T @ (Y * wt[:, None]), np.eye(36), atol=1e-12)


@pytest.mark.parametrize("deg", [0, 3, 8])
def test_device_forward_float32(device, rng, deg):
    d = _unit(rng, 300)
    Y = sh_basis(d, deg, device=device)
    np.testing.assert_allclose(Y, ref.sh_eval(deg, d), rtol=1e-4, atol=2e-5)


def test_device_vjp_float32_vs_reference(device, rng):
    deg = 8
    d = _unit(rng, 40)
    v_Y = rng.standard_normal((40, 81))
    got = sh_basis_backward(d, deg, v_Y, device=device)
    want = cs_grad(lambda x: np.sum(ref.sh_eval(deg, x) * v_Y), d)
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=2e-3 * np.abs(want).max())


def test_device_vjp_float64_finite_differences(device64, rng):
    deg, n, h = 8, 6, 1e-6
    d = _unit(rng, n)
    v_Y = rng.standard_normal((n, 81))
    got = sh_basis_backward(d, deg, v_Y, device=device64, real=np.float64)
    fd = np.zeros_like(d)
    for i in np.ndindex(d.shape):
        dp, dm = d.copy(), d.copy()
        dp[i] += h
        dm[i] -= h
        fp = np.sum(sh_basis(dp, deg, device=device64, real=np.float64) * v_Y)
        fm = np.sum(sh_basis(dm, deg, device=device64, real=np.float64) * v_Y)
        fd[i] = (fp - fm) / (2 * h)
    np.testing.assert_allclose(got, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def test_band_factors_match_formula():
    from math import factorial, pi

    for l in range(2, 9, 2):
        a = 2 * pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1)) * factorial(l) / (2**l * factorial(l // 2) ** 2)
        assert ref.BAND_A[l] == pytest.approx(a, rel=1e-14)


def test_validation(device):
    with pytest.raises(ValueError, match=r"dirs must have shape \[\*, 3\], got \[4, 2\]"):
        sh_basis(np.zeros((4, 2)), 2, device=device)
    with pytest.raises(ValueError, match="degree"):
        sh_basis(np.zeros((4, 3)), 9, device=device)
