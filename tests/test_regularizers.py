"""Mesh regularisers: closed-form values on tiny meshes, float64 gradchecks, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from triplet_cl.autodiff import Param, Tape, assert_gradcheck

from triplet_cl import regularizers as reg

# an octahedron: 6 vertices, 8 faces, 12 edges, every vertex of valence 4
OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def _noisy(rng, scale=0.1):
    return OCTA_V + scale * rng.standard_normal(OCTA_V.shape)


def test_mesh_edges_of_octahedron():
    e = reg.mesh_edges(OCTA_F)
    assert e.shape == (12, 2) and (e[:, 0] < e[:, 1]).all() and len(np.unique(e, axis=0)) == 12


def test_normal_consistency_flat_is_zero_and_octahedron_closed_form():
    quad_v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    assert float(reg.face_normal_consistency(quad_v, quad_f)) == pytest.approx(0.0, abs=1e-15)
    # adjacent octahedron faces meet at cos = 1/3 (dihedral angle arccos(-1/3)): 12 pairs of 1 - 1/3
    assert float(reg.face_normal_consistency(OCTA_V, OCTA_F, "sum")) == pytest.approx(12 * (2 / 3))


def test_normal_consistency_gradcheck(rng):
    assert_gradcheck(lambda v: reg.FaceNormalConsistency(OCTA_F, 6)(v), {"vertices": _noisy(rng)},
                     rtol=1e-6, atol=1e-10)


def test_robust_normal_consistency_closed_form_gradcheck_and_crease_slope(rng):
    k = 0.05
    # the octahedron's 12 pairs bend by x = 2/3 each: ρ(x) = κ·log(1 + x/κ) + x⁵/5
    assert float(reg.face_normal_consistency(OCTA_V, OCTA_F, "sum", kappa=k)) == pytest.approx(
        12 * (k * np.log1p((2 / 3) / k) + (2 / 3) ** 5 / 5))
    assert_gradcheck(lambda v: reg.FaceNormalConsistency(OCTA_F, 6, kappa=k)(v), {"vertices": _noisy(rng)},
                     rtol=1e-6, atol=1e-10)
    # two faces whose normals meet at 60° (x = 1/2) and at 120° (x = 3/2, a fold): the plain term's gradient times
    # ρ'(x) = 1 / (1 + x/κ) + x⁴ — a crease costs a sixth of the plain term's pull, a fold more than the plain term
    for angle, x in ((np.pi / 3, 0.5), (2 * np.pi / 3, 1.5)):
        V = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0.5], [np.cos(np.pi - angle), np.sin(np.pi - angle), 0.5]])
        F = np.array([[0, 1, 2], [1, 0, 3]])
        grads = []
        for kappa in (None, k):
            v = Param(V.copy(), "V")
            with Tape() as tape:
                out = reg.FaceNormalConsistency(F, 4, "sum", kappa=kappa)(v)
            tape.backward(out, np.ones(()))
            grads.append(np.asarray(v.grad))
        assert float(reg.face_normal_consistency(V, F, "sum")) == pytest.approx(x)
        assert np.abs(grads[0]).max() > 0.1
        np.testing.assert_allclose(grads[1], grads[0] * (1 / (1 + x / k) + x**4), rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="kappa"):
        reg.FaceNormalConsistency(F, 4, kappa=0.0)


def test_laplacian_closed_form_and_gradcheck(rng):
    # vertex 4 = (0,0,1): its ring {0,1,2,3} averages to the origin, so δ_4 = -(0,0,1); by symmetry
    # every vertex has |δ|² = 1, energy 6 (sum) / 1 (mean)
    assert float(reg.uniform_laplacian(OCTA_V, OCTA_F, "sum")) == pytest.approx(6.0)
    assert float(reg.uniform_laplacian(OCTA_V, OCTA_F)) == pytest.approx(1.0)
    lap = reg.uniform_laplacian_matrix(OCTA_F, 7).toarray()  # vertex 6 isolated → zero row
    assert np.allclose(lap[6], 0) and np.allclose(lap[:6].sum(axis=1), 0)
    assert_gradcheck(lambda v: reg.UniformLaplacian(OCTA_F, 6)(v), {"x": _noisy(rng)}, rtol=1e-6, atol=1e-10)


def test_rest_laplacian_zero_at_rest_closed_form_and_gradcheck(rng):
    rest = _noisy(rng)
    # zero energy and zero gradient at the rest shape (a curved shape is not pulled flat) ...
    assert float(reg.rest_laplacian(rest, OCTA_F, rest)) == pytest.approx(0.0, abs=1e-28)
    op = reg.RestLaplacian(OCTA_F, 6, rest)
    from triplet_cl.autodiff import Tape, Variable

    x = Variable(rest.copy(), requires_grad=True)
    with Tape() as tape:
        e = op(x)
    tape.backward(e, np.asarray(1.0))
    assert np.abs(x.grad).max() == 0.0
    # ... the plain Laplacian's energy against a zero rest shape, and a translated shape costs nothing
    assert float(reg.rest_laplacian(OCTA_V, OCTA_F, np.zeros((6, 3)))) == pytest.approx(1.0)
    assert float(reg.rest_laplacian(rest + [0.3, -1.0, 2.0], OCTA_F, rest)) == pytest.approx(0.0, abs=1e-24)
    # the energy of a displacement d is the plain Laplacian energy of d
    d = 0.05 * rng.standard_normal((6, 3))
    assert float(reg.rest_laplacian(rest + d, OCTA_F, rest)) == pytest.approx(float(reg.uniform_laplacian(d, OCTA_F)))
    assert_gradcheck(lambda v: reg.RestLaplacian(OCTA_F, 6, rest)(v), {"x": _noisy(rng)}, rtol=1e-6, atol=1e-10)
    with pytest.raises(ValueError, match="rest must have shape"):
        reg.RestLaplacian(OCTA_F, 6, rest[:5])
    with pytest.raises(ValueError, match="columns"):
        reg.rest_laplacian(rest[:, :2], OCTA_F, rest)


def test_material_gtv_closed_form_and_gradcheck(rng):
    x = np.zeros((6, 2))
    x[4] = [1.0, -2.0]  # only the 4 edges at vertex 4 differ, |Δ|₁ = 3, counted in both directions
    assert float(reg.material_gtv(x, OCTA_F, reduction="sum")) == pytest.approx(2 * 4 * 3.0)
    w = np.full(12, 4.0)
    assert float(reg.material_gtv(x, OCTA_F, w, reduction="sum")) == pytest.approx(2 * 2 * 4 * 3.0)
    v = _noisy(rng, 0.2)
    weights = reg.gtv_edge_weights(v, reg.mesh_edges(OCTA_F))
    assert weights.shape == (12,) and np.mean(1 / weights) == pytest.approx(1.0)  # ℓ̄/ℓ: harmonic normalisation
    assert_gradcheck(lambda a: reg.MaterialGTV(OCTA_F, 6, weights)(a), {"x": rng.random((6, 3))},
                     rtol=1e-6, atol=1e-10)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="vertices must have shape"):
        reg.face_normal_consistency(OCTA_V[:, :2], OCTA_F)
    with pytest.raises(ValueError, match="faces indices"):
        reg.UniformLaplacian(OCTA_F, 4)
    with pytest.raises(ValueError, match="x must be finite"):
        reg.material_gtv(np.full((6, 1), np.nan), OCTA_F)
    with pytest.raises(ValueError, match="weights must be"):
        reg.MaterialGTV(OCTA_F, 6, np.ones(5))
    with pytest.raises(ValueError, match="reduction"):
        reg.uniform_laplacian(OCTA_V, OCTA_F, "max")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_row_scatter_is_np_add_at_bit_for_bit(rng, dtype):
    """``RowScatter`` (the regularisers' adjoint scatter as a cached sparse product) gives ``np.add.at``'s result bit
    for bit (each row summed in index order in the values' dtype), empty indices included; bad shapes are refused."""
    from triplet_cl.regularizers import RowScatter, _scatter_rows

    for n, k, c in [(300, 5000, 3), (7, 40, 1), (5, 0, 3)]:
        idx = rng.integers(0, n, k)
        v = (rng.standard_normal((k, c)) * 10.0 ** rng.uniform(-4, 4, (k, 1))).astype(dtype)
        s = RowScatter(n, idx)
        got = s(v)
        assert got.dtype == dtype and got.shape == (n, c)
        np.testing.assert_array_equal(got, _scatter_rows(n, idx, v))
        np.testing.assert_array_equal(s(2 * v), _scatter_rows(n, idx, 2 * v))  # the cached matrix, again
    with pytest.raises(ValueError, match="values must have shape"):
        RowScatter(4, np.arange(3))(np.ones((2, 3)))


def _bumpy_sphere(rng, dtype, degenerate: bool):
    """An icosphere (642 vertices) with jittered vertices (creases of all angles, a few folds), and optionally
    faces collapsed to a point and to a segment (normalize's eps path)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.array(s.vertices, np.float64), np.array(s.faces, np.int64)
    V = V + 0.05 * rng.standard_normal(V.shape)
    if degenerate:
        V[F[3]] = V[F[3][0]]
        V[F[40, 1]] = V[F[40, 0]]
    return V.astype(dtype), F


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("kappa", [None, 0.05])
@pytest.mark.parametrize("degenerate", [False, True])
def test_normal_consistency_columns_are_the_row_form_bit_for_bit(rng, dtype, kappa, degenerate):
    # session 62 rewrote the energy column by column (17.7 -> 5.9 ms on spot's 61k-face mesh): the values and the
    # gradient must be the row form's (tests/reference/regularizers.py) to the bit, so that the mesh stage's
    # trajectories do not move
    from tests.reference import regularizers as ref

    V, F = _bumpy_sphere(rng, dtype, degenerate)
    fn = reg.FaceNormalConsistency(F, len(V), kappa=kappa)
    p = Param(V, name="V")
    with Tape() as tape:
        e = fn(p)
    tape.backward(e, np.asarray(0.7, np.float64))
    e_ref, g_ref = ref.face_normal_consistency(V, F, fn.pairs, fn.scale, kappa, reg.FACE_NORMAL_EPS, v_out=0.7)
    assert np.asarray(e.data).dtype == e_ref.dtype and np.array_equal(np.asarray(e.data), e_ref)
    assert p.grad.dtype == g_ref.dtype == dtype and np.array_equal(p.grad, g_ref)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("weights", ["uniform", "random"])
def test_material_gtv_signed_scatter_is_the_concatenated_scatter_bit_for_bit(rng, dtype, weights):
    from triplet_cl.autodiff.function import Context

    from tests.reference import regularizers as ref

    V, F = _bumpy_sphere(rng, np.float64, False)
    X = rng.random((len(V), 4)).astype(dtype)
    X[::5] = X[0]  # ties: sign 0 on the edges between these vertices
    w = None if weights == "uniform" else rng.random(len(reg.mesh_edges(F)))
    fn = reg.MaterialGTV(F, len(V), weights=w)
    ctx = Context((True,))  # the op itself (a Param would cast its float64 gradient to the parameter's dtype)
    e = fn.forward(ctx, X)
    g = fn.backward(ctx, np.asarray(1.3, np.float64))
    e_ref, g_ref = ref.material_gtv(X, fn.edges, fn.sqrt_w, 1.0 / (2 * len(fn.edges) * X.shape[1]), v_out=1.3)
    assert np.array_equal(np.asarray(e), e_ref)
    assert g.dtype == g_ref.dtype and g.shape == g_ref.shape and np.array_equal(g, g_ref)
