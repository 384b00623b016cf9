"""Face and area-weighted vertex normals: forward, adjoint (complex-step reference), float64 FD."""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import cs_grad, fd_grad
from tests.reference import normals as ref
from triplet_cl.ops.normals import face_normals, face_normals_backward, vertex_normals, vertex_normals_backward
from triplet_cl.topology import vertex_corner_csr


def _mesh(rng, n=12, m=20):
    V = rng.standard_normal((n, 3))
    F = np.stack([rng.choice(n, 3, replace=False) for _ in range(m)]).astype(np.int32)
    return V, F






def test_forward_float32(device, rng):
    V, F = _mesh(rng)
    np.testing.assert_allclose(face_normals(V, F, device=device), ref.face_normals(V, F), atol=1e-5)
    np.testing.assert_allclose(vertex_normals(V, F, device=device), ref.vertex_normals(V, F), atol=1e-5)


def test_vertex_normals_area_weighted(device):
    # a unit square split in two triangles plus a tiny tilted triangle sharing vertex 0
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1e-3], [1e-3, 0, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 5, 4]], np.int32)
    n = vertex_normals(V, F, device=device)
    assert np.allclose(n[0], [0, 0, 1], atol=1e-5)  # the small face barely tilts it
    assert np.allclose(n[1], [0, 0, 1], atol=1e-6)


@pytest.mark.parametrize("kind", ["face", "vertex"])
def test_vjp_float32_vs_reference(device, rng, kind):
    V, F = _mesh(rng)
    fwd = ref.face_normals if kind == "face" else ref.vertex_normals
    bwd = face_normals_backward if kind == "face" else vertex_normals_backward
    v = rng.standard_normal(fwd(V, F).shape)
    got = bwd(V, F, v, device=device)
    want = cs_grad(lambda x: np.sum(fwd(x, F) * v), V)
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-4 * np.abs(want).max())


@pytest.mark.parametrize("kind", ["face", "vertex"])
def test_vjp_float64_finite_differences(device64, rng, kind):
    V, F = _mesh(rng, n=8, m=10)
    csr = vertex_corner_csr(F, len(V))
    fwd = face_normals if kind == "face" else vertex_normals
    bwd = face_normals_backward if kind == "face" else vertex_normals_backward
    kw = {"device": device64, "real": np.float64}
    v = rng.standard_normal(fwd(V, F, **kw).shape)
    got = bwd(V, F, v, csr=csr, **kw)
    fd = fd_grad(lambda x: np.sum(fwd(x, F, **kw) * v), V)
    np.testing.assert_allclose(got, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


def test_degenerate_and_unused(device):
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 5, 5]], float)  # collinear face, unused vertex 3
    F = np.array([[0, 1, 2]], np.int32)
    assert np.array_equal(face_normals(V, F, device=device), np.zeros((1, 3), np.float32))
    assert np.array_equal(vertex_normals(V, F, device=device), np.zeros((4, 3), np.float32))
    for bwd in (face_normals_backward, vertex_normals_backward):
        g = bwd(V, F, np.ones((1 if bwd is face_normals_backward else 4, 3)), device=device)
        assert np.isfinite(g).all() and np.all(g[3] == 0)


def test_validation(device):
    V = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"V must have shape \[\*, 3\], got \[3, 2\]"):
        face_normals(np.zeros((3, 2)), [[0, 1, 2]], device=device)
    with pytest.raises(ValueError, match="F indices must lie in"):
        vertex_normals(V, [[0, 1, 3]], device=device)
    with pytest.raises(ValueError, match="F must be an integer array"):
        face_normals(V, [[0.0, 1.0, 2.0]], device=device)
    with pytest.raises(ValueError, match="V must be finite"):
        face_normals(np.full((3, 3), np.nan), [[0, 1, 2]], device=device)
    with pytest.raises(ValueError, match=r"v_n must have shape \[3, 3\]"):
        vertex_normals_backward(V, [[0, 1, 2]], np.zeros((1, 3)), device=device)
    assert face_normals(V, np.zeros((0, 3), np.int32), device=device).shape == (0, 3)
