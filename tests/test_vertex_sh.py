"""Per-vertex SH light: forward, adjoint to coefficients and positions, float64 FD."""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import cs_grad, fd_grad
from tests.reference import sh as ref
from triplet_cl.ops.vertex_sh import vertex_sh, vertex_sh_backward

CAM = np.array([0.3, -2.5, 1.7])


def _inputs(rng, n=50, D=3):
    V = rng.standard_normal((n, 3)) * 0.5
    c = rng.standard_normal((n, 6, (D + 1) ** 2)) * 0.4
    return V, c




@pytest.mark.parametrize("degree", [0, 2, 3])
def test_forward_float32(device, rng, degree):
    V, c = _inputs(rng)
    got = vertex_sh(V, c, CAM, degree, device=device)
    np.testing.assert_allclose(got, ref.vertex_sh(V, c, CAM, degree), rtol=1e-5, atol=1e-5)


def test_init_gives_unit_radiance(device, rng):
    V, c = _inputs(rng, D=2)
    c[:] = 0
    c[:, :3, 0] = 0.5 / ref.sh_eval(0, np.array([[0.0, 0, 1]]))[0, 0]
    out = vertex_sh(V, c, CAM, device=device)
    np.testing.assert_allclose(out[:, :3], 1.0, rtol=1e-6)


def test_vjp_float32_vs_reference(device, rng):
    n, degree = 12, 2
    V, c = _inputs(rng, n=n)
    c[0, :3] = 0
    c[0, 0, 0] = -5  # a clamped radiance channel
    v = rng.standard_normal((n, 6))
    v_c, v_V = vertex_sh_backward(V, c, CAM, v, degree, device=device)
    assert np.all(v_c[:, :, (degree + 1) ** 2:] == 0)  # inactive bands get nothing
    want_c = cs_grad(lambda x: np.sum(ref.vertex_sh(V, x, CAM, degree) * v), c)
    want_V = cs_grad(lambda x: np.sum(ref.vertex_sh(x, c, CAM, degree) * v), V)
    np.testing.assert_allclose(v_c, want_c, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(v_V, want_V, rtol=1e-3, atol=1e-4 * np.abs(want_V).max())


def test_vjp_float64_finite_differences(device64, rng):
    n, D, h = 4, 3, 1e-6
    V, c = _inputs(rng, n=n, D=D)
    v = rng.standard_normal((n, 6))
    kw = {"device": device64, "real": np.float64}
    v_c, v_V = vertex_sh_backward(V, c, CAM, v, **kw)

    def fd(f, x):
        return fd_grad(f, x, h)

    np.testing.assert_allclose(v_V, fd(lambda x: np.sum(vertex_sh(x, c, CAM, **kw) * v), V), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(v_c, fd(lambda x: np.sum(vertex_sh(V, x, CAM, **kw) * v), c), rtol=1e-6, atol=1e-8)


def test_validation(device):
    V = np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"coeffs must have shape \[2, 6, \*\]"):
        vertex_sh(V, np.zeros((2, 5, 4)), CAM, device=device)
    with pytest.raises(ValueError, match=r"\(D\+1\)\^2 coefficients"):
        vertex_sh(V, np.zeros((2, 6, 5)), CAM, device=device)
    with pytest.raises(ValueError, match=r"degree must lie in \[0, 1\]"):
        vertex_sh(V, np.zeros((2, 6, 4)), CAM, 2, device=device)
    with pytest.raises(ValueError, match=r"cam must have shape \[3\]"):
        vertex_sh(V, np.zeros((2, 6, 4)), [0, 0], device=device)
