"""Density control of the soup: statistics, split, clone, prune, budgets, optimizer moments, alpha reset."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit
from triplet_cl.autodiff import Param

from triplet_cl.density import (
    DensifyReport,
    DensityConfig,
    DensityStats,
    check_soup,
    densify_and_prune,
    face_alpha,
    face_areas,
    face_longest_edges,
    reset_alpha,
    visible_faces,
)
from triplet_cl.optim import Adam
from triplet_cl.scene import Scene, logit

SH_K = 4


def tri(center, size, rng=None):
    """A triangle of roughly ``size`` around ``center``: ``[3, 3]``."""
    base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.1]])
    if rng is not None:
        base = base + 0.1 * rng.standard_normal((3, 3))
    return np.asarray(center, np.float64) + size * base


def soup(tris, rng, alpha=0.5, vertex_sh=True, brdf="cook_torrance", dtype=np.float64):
    V = np.concatenate(tris)
    n = V.shape[0]
    F = np.arange(n).reshape(-1, 3)
    cm = 6 if brdf == "cook_torrance" else 10
    mat = rng.standard_normal((n, cm))
    al = np.full((n, 1), logit(alpha)) + 0.1 * rng.standard_normal((n, 1))
    vsh = rng.standard_normal((n, 6, SH_K)) if vertex_sh else None
    return Scene.from_arrays(V, F, material=mat, alpha=al, vertex_sh=vsh, brdf=brdf, dtype=dtype)


def cfg(**kw):
    base = dict(grad_threshold=1.0, split_edge_ratio=0.5, prune_alpha=0.05, prune_world_area=10.0,
                prune_screen_frac=0.5, min_faces=0, clone_step=0.5)
    base.update(kw)
    return DensityConfig(**base)


def set_grads(stats, F, per_face, directions=None):
    """One view where face f has screen gradient norm ``per_face[f]`` (spread over its corners)."""
    m = len(F)
    v_vs = np.zeros((3 * m, 3))
    v_vs[F[:, 0], 0] = per_face  # Σ_corners (u, v) = (g, 0)
    v_vs[F[:, 1], 2] = 123.0  # depth component is ignored
    v_V = None
    if directions is not None:
        v_V = np.zeros((3 * m, 3))
        v_V[F[:, 2]] = directions
    stats.add(v_vs, np.ones(m, bool), F, v_V=v_V)


def assert_soup(scene):
    m = check_soup(scene)
    assert scene.F.dtype == np.int32
    np.testing.assert_array_equal(scene.F, np.arange(3 * m).reshape(m, 3))
    for p in scene.params:
        if p is not scene.light_params:
            assert p.data.shape[0] == 3 * m
    return m


# ---------------------------------------------------------------------------------------------- stats


def test_stats_accumulation_maths(rng):
    m = 3
    F = np.arange(9).reshape(3, 3)
    st = DensityStats(m)
    v1 = rng.standard_normal((9, 3))
    v2 = rng.standard_normal((9, 3))
    w1 = rng.standard_normal((9, 3))
    vs1 = rng.uniform(0, 50, (9, 3))
    vis1 = np.array([True, True, False])
    vis2 = np.array([True, False, True])
    st.add(v1, vis1, F, vs=vs1, image_size=(100, 50), v_V=w1)
    st.add(v2[:, :2], vis2, F, grad_scale=2.0)  # [N, 2] accepted

    def gn(v, f):
        return np.linalg.norm(v[F[f], :2].sum(axis=0))

    np.testing.assert_allclose(st.grad_accum, [gn(v1, 0) + 2 * gn(v2, 0), gn(v1, 1), 2 * gn(v2, 2)])
    np.testing.assert_array_equal(st.denom, [2, 1, 1])
    np.testing.assert_allclose(st.mean_grad(), st.grad_accum / np.array([2, 1, 1]))
    np.testing.assert_allclose(st.world_grad_accum, [w1[0:3].sum(0), w1[3:6].sum(0), [0, 0, 0]])
    for f in (0, 1):
        uv = vs1[F[f], :2]
        ext = uv.max(0) - uv.min(0)
        assert st.max_screen_area[f] == pytest.approx(ext[0] * ext[1])
        assert st.max_screen_frac[f] == pytest.approx(ext[0] * ext[1] / 5000)
    assert st.max_screen_area[2] == 0
    # the max is a max: a smaller view does not lower it
    before = st.max_screen_area.copy()
    st.add(v1, np.ones(3, bool), F, vs=vs1 * 0.1, image_size=(100, 50))
    np.testing.assert_array_equal(st.max_screen_area[:2], before[:2])
    assert st.max_screen_area[2] > 0
    st.reset(5)
    assert st.num_faces == 5 and not st.grad_accum.any() and not st.denom.any()
    assert st.mean_grad().shape == (5,) and not st.mean_grad().any()


def test_stats_validation():
    F = np.arange(6).reshape(2, 3)
    st = DensityStats(2)
    with pytest.raises(ValueError, match="visible"):
        st.add(np.zeros((6, 3)), np.ones(3, bool), F)
    with pytest.raises(ValueError, match="F must"):
        st.add(np.zeros((6, 3)), np.ones(2, bool), F[:1])
    with pytest.raises(ValueError, match="image_size"):
        st.add(np.zeros((6, 3)), np.ones(2, bool), F, vs=np.zeros((6, 3)))


def test_visible_faces():
    ids = np.full((2, 2, 3), -1, np.int32)
    ids[0, 0, :2] = [4, 1]
    ids[1, 1, 0] = 4
    np.testing.assert_array_equal(visible_faces(ids, 6), [False, True, False, False, True, False])


# ---------------------------------------------------------------------------------------------- split


@pytest.mark.parametrize("brdf", ["cook_torrance", "blinn_phong"])
def test_split_one_face_tiles_parent_and_interpolates_raw(rng, brdf):
    sc = soup([tri([0, 0, 0], 2.0, rng)], rng, brdf=brdf)
    P = sc.V.data.copy()
    mat, al, sh = sc.material.data.copy(), sc.alpha.data.copy(), sc.vertex_sh.data.copy()
    st = DensityStats(1)
    set_grads(st, sc.F, [5.0])
    rep = densify_and_prune(sc, None, st, cfg(), extent=1.0)
    assert isinstance(rep, DensifyReport)
    assert (rep.split, rep.cloned, rep.pruned, rep.faces_before, rep.faces_after) == (1, 0, 0, 1, 4)
    assert assert_soup(sc) == 4
    parent_area = face_areas(P, np.arange(3).reshape(1, 3))[0]
    areas = face_areas(sc.V.data, sc.F)
    np.testing.assert_allclose(areas, parent_area / 4, rtol=1e-12)
    assert areas.sum() == pytest.approx(parent_area)
    n_parent = np.cross(P[1] - P[0], P[2] - P[0])
    Q = sc.V.data[sc.F]
    n_child = np.cross(Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0])
    assert np.all(n_child @ n_parent > 0)  # orientation kept
    # every child vertex is a corner or an edge midpoint, with attributes interpolated the same way
    pts = {0: [0], 1: [1], 2: [2], 3: [0, 1], 4: [1, 2], 5: [2, 0]}
    kids = [[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]]
    for k, child in enumerate(kids):
        for c, point in enumerate(child):
            row = 3 * k + c
            src = pts[point]
            np.testing.assert_allclose(sc.V.data[row], P[src].mean(0), atol=1e-14)
            np.testing.assert_allclose(sc.material.data[row], mat[src].mean(0), atol=1e-14)
            np.testing.assert_allclose(sc.alpha.data[row], al[src].mean(0), atol=1e-14)
            np.testing.assert_allclose(sc.vertex_sh.data[row], sh[src].mean(0), atol=1e-14)
    assert st.num_faces == 4 and not st.grad_accum.any()  # stats reset for the new soup


def test_split_activated_interpolation(rng):
    sc = soup([tri([0, 0, 0], 2.0, rng)], rng, brdf="blinn_phong")
    sc.alpha.data[:, 0] = [-3.0, 0.5, 4.0]
    mat, al = sc.material.data.copy(), sc.alpha.data.copy()
    st = DensityStats(1)
    set_grads(st, sc.F, [5.0])
    densify_and_prune(sc, None, st, cfg(split_interp="activated"), extent=1.0)
    # child 0 = (a, m01, m20): corner exact, midpoints mean of activated values
    np.testing.assert_array_equal(sc.alpha.data[0], al[0])
    np.testing.assert_allclose(expit(sc.alpha.data[1, 0]), expit(al[[0, 1], 0]).mean(), rtol=1e-12)
    np.testing.assert_allclose(expit(sc.alpha.data[2, 0]), expit(al[[2, 0], 0]).mean(), rtol=1e-12)
    np.testing.assert_allclose(expit(sc.material.data[1, :6]), expit(mat[[0, 1], :6]).mean(0), rtol=1e-10)
    softplus = np.logaddexp(0, mat[[0, 1], 6]).mean()
    assert np.logaddexp(0, sc.material.data[1, 6]) == pytest.approx(softplus, rel=1e-10)


# ---------------------------------------------------------------------------------------------- clone


def test_clone_moves_along_negative_gradient_and_copies_attributes(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([3, 0, 0], 0.1, rng)], rng)
    old = {p.name: p.data.copy() for p in sc.params}
    st = DensityStats(2)
    g = np.array([[1.0, -2.0, 2.0], [0.0, 0.0, 0.0]])
    set_grads(st, sc.F, [5.0, 0.0], directions=g)
    set_grads(st, sc.F, [5.0, 0.0], directions=g)  # accumulated over two views
    c = cfg(clone_step=0.25)
    rep = densify_and_prune(sc, None, st, c, extent=1.0)
    assert (rep.split, rep.cloned, rep.faces_after) == (0, 1, 3)
    assert_soup(sc)
    for name, before in old.items():  # survivors untouched, in order
        np.testing.assert_array_equal(getattr(sc, name).data[:6], before)
    longest = face_longest_edges(old["V"][:3], np.arange(3).reshape(1, 3))[0]
    expected = old["V"][:3] - 0.25 * longest * g[0] / 3.0  # ‖(1, −2, 2)‖ = 3
    np.testing.assert_allclose(sc.V.data[6:9], expected, atol=1e-14)
    for name in ("material", "alpha", "vertex_sh"):
        np.testing.assert_array_equal(getattr(sc, name).data[6:9], old[name][:3])


def test_clone_without_world_gradient_stays_in_place(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng)], rng)
    V0 = sc.V.data.copy()
    st = DensityStats(1)
    set_grads(st, sc.F, [5.0])
    densify_and_prune(sc, None, st, cfg(), extent=1.0)
    np.testing.assert_array_equal(sc.V.data[3:], V0)


def test_masks_are_computed_before_reordering(rng):
    """Face 0 is split (big), face 1 cloned (small), face 2 left alone. With the original bug (clone mask
    taken on the soup after the split removed face 0), index 1 would be face 2 and the wrong face cloned."""
    sc = soup([tri([0, 0, 0], 2.0, rng), tri([5, 0, 0], 0.1, rng), tri([9, 0, 0], 0.1, rng)], rng)
    old = {p.name: p.data.copy() for p in sc.params}
    st = DensityStats(3)
    set_grads(st, sc.F, [5.0, 5.0, 0.0], directions=np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 0]]))
    rep = densify_and_prune(sc, None, st, cfg(), extent=1.0)
    assert (rep.split, rep.cloned, rep.faces_after) == (1, 1, 7)
    assert_soup(sc)
    # layout: survivors (old faces 1, 2), 4 children of old face 0, clone of old face 1
    np.testing.assert_array_equal(sc.material.data[:6], old["material"][3:9])
    np.testing.assert_allclose(sc.V.data[6:18].mean(0), old["V"][:3].mean(0), atol=1e-12)
    np.testing.assert_array_equal(sc.material.data[18:21], old["material"][3:6])  # clone of face 1 ...
    np.testing.assert_array_equal(sc.vertex_sh.data[18:21], old["vertex_sh"][3:6])
    assert sc.V.data[18:21, 0].mean() == pytest.approx(old["V"][3:6, 0].mean())  # ... near x = 5, not 9
    assert np.all(sc.V.data[18:21, 2] < old["V"][3:6, 2])  # moved along −∇ (−z)


# ---------------------------------------------------------------------------------------------- prune


def test_prune_by_alpha(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 0.1, rng), tri([2, 0, 0], 0.1, rng)], rng)
    sc.alpha.data[3:6] = logit(0.04)  # face 1: transparent everywhere
    sc.alpha.data[6:9] = logit(0.01)
    sc.alpha.data[7] = logit(0.2)  # face 2: one opaque corner → max alpha 0.2, kept
    np.testing.assert_allclose(face_alpha(sc.alpha.data, sc.F)[1:], [0.04, 0.2])
    keep = {p.name: p.data.copy() for p in sc.params}
    st = DensityStats(3)
    rep = densify_and_prune(sc, None, st, cfg(), extent=1.0)
    assert (rep.pruned, rep.pruned_alpha, rep.faces_after) == (1, 1, 2)
    assert_soup(sc)
    np.testing.assert_array_equal(sc.V.data, np.concatenate([keep["V"][:3], keep["V"][6:]]))
    np.testing.assert_array_equal(sc.vertex_sh.data, np.concatenate([keep["vertex_sh"][:3], keep["vertex_sh"][6:]]))


def test_prune_by_world_area(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 3.0, rng)], rng)
    areas = face_areas(sc.V.data, sc.F)
    extent = 2.0
    c = cfg(prune_world_area=0.5 * (areas[0] + areas[1]) / extent**2)
    rep = densify_and_prune(sc, None, DensityStats(2), c, extent=extent)
    assert (rep.pruned, rep.pruned_world_area, rep.faces_after) == (1, 1, 1)
    assert face_areas(sc.V.data, sc.F)[0] == pytest.approx(areas[0])


def test_prune_by_screen_size(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 0.1, rng)], rng)
    st = DensityStats(2)
    vs = np.zeros((6, 3))
    vs[:3, :2] = [[0, 0], [10, 0], [0, 10]]  # 100 px² of 10 000: 1 %
    vs[3:, :2] = [[0, 0], [2, 0], [0, 2]]  # 4 px²: 0.04 %
    st.add(np.zeros((6, 3)), np.ones(2, bool), sc.F, vs=vs, image_size=(100, 100))
    c = cfg(prune_screen_frac=0.001)
    st_off = DensityStats(2)
    st_off.max_screen_frac[:] = st.max_screen_frac
    V0 = sc.V.data.copy()
    assert densify_and_prune(sc, None, st_off, c, extent=1.0, prune_screen=False).pruned == 0
    rep = densify_and_prune(sc, None, st, c, extent=1.0)
    assert (rep.pruned, rep.pruned_screen, rep.faces_after) == (1, 1, 1)
    np.testing.assert_array_equal(sc.V.data, V0[3:])


def test_min_faces_spares_the_least_transparent(rng):
    sc = soup([tri([i, 0, 0], 0.1, rng) for i in range(4)], rng)
    for f, a in enumerate([0.03, 0.5, 0.001, 0.02]):
        sc.alpha.data[3 * f:3 * f + 3] = logit(a)
    rep = densify_and_prune(sc, None, DensityStats(4), cfg(min_faces=2), extent=1.0)
    assert (rep.pruned, rep.spared_min_faces, rep.faces_after) == (2, 1, 2)
    np.testing.assert_allclose(face_alpha(sc.alpha.data, sc.F), [0.03, 0.5], rtol=1e-6)


def test_a_prune_that_would_empty_the_soup_is_refused(rng):
    """Every face is a prune candidate (e.g. right after an alpha reset): the call removes at most
    ``max_prune_fraction`` of the faces, the most transparent first, and the soup survives."""
    sc = soup([tri([i, 0, 0], 0.1, rng) for i in range(10)], rng)
    alphas = [0.03, 0.001, 0.02, 0.04, 0.005, 0.01, 0.045, 0.002, 0.03, 0.015]
    for f, a in enumerate(alphas):
        sc.alpha.data[3 * f:3 * f + 3] = logit(a)
    rep = densify_and_prune(sc, None, DensityStats(10), cfg(max_prune_fraction=0.3), extent=1.0)
    assert (rep.pruned, rep.pruned_alpha, rep.spared_min_faces, rep.faces_after) == (3, 10, 7, 7)
    np.testing.assert_allclose(np.sort(face_alpha(sc.alpha.data, sc.F)), np.sort(alphas)[3:], rtol=1e-6)
    assert_soup(sc)
    # repeated calls shrink it geometrically but never empty it, even with min_faces = 0
    for _ in range(20):
        densify_and_prune(sc, None, DensityStats(len(sc.F)), cfg(max_prune_fraction=0.3), extent=1.0)
    assert len(sc.F) >= 1
    with pytest.raises(ValueError, match="max_prune_fraction"):
        DensityConfig(max_prune_fraction=0.0)


def test_pruned_faces_are_not_densified(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng)], rng, alpha=0.01)
    st = DensityStats(1)
    set_grads(st, sc.F, [5.0])
    rep = densify_and_prune(sc, None, st, cfg(), extent=1.0)
    assert (rep.pruned, rep.cloned, rep.faces_after) == (1, 0, 0)
    assert_soup(sc)


# ---------------------------------------------------------------------------------------------- budgets


def test_max_faces_takes_highest_gradient_first(rng):
    # faces 0, 1 small (clone, +1), face 2 big (split, +3), face 3 below threshold
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 0.1, rng), tri([2, 0, 0], 2.0, rng),
               tri([5, 0, 0], 0.1, rng)], rng)
    grads = np.array([2.0, 9.0, 5.0, 0.5])
    st = DensityStats(4)
    set_grads(st, sc.F, grads)
    old_mat = sc.material.data.copy()
    # budget 4: face 1 (+1), then face 2 (+3) fit; face 0 (+1) does not
    rep = densify_and_prune(sc, None, st, cfg(max_faces=8), extent=1.0)
    assert (rep.split, rep.cloned, rep.skipped_max_faces, rep.faces_after) == (1, 1, 1, 8)
    assert_soup(sc)
    np.testing.assert_array_equal(sc.material.data[21:24], old_mat[3:6])  # the clone is of face 1
    # budget 2: face 1 (+1) fits, face 2 (+3) does not; nothing after it is taken
    sc2 = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 0.1, rng), tri([2, 0, 0], 2.0, rng),
                tri([5, 0, 0], 0.1, rng)], rng)
    st2 = DensityStats(4)
    set_grads(st2, sc2.F, grads)
    rep2 = densify_and_prune(sc2, None, st2, cfg(max_faces=6), extent=1.0)
    assert (rep2.split, rep2.cloned, rep2.faces_after) == (0, 1, 5)
    assert rep2.faces_after <= 6
    # already at the limit: nothing added
    st3 = DensityStats(5)
    set_grads(st3, sc2.F, np.full(5, 9.0))
    assert densify_and_prune(sc2, None, st3, cfg(max_faces=5), extent=1.0).faces_after == 5


# ---------------------------------------------------------------------------------------------- optimizer


def _adam(sc, rng):
    opt = Adam()
    opt.add_group("V", [sc.V], lr=1e-3)
    opt.add_group("appearance", [sc.material, sc.vertex_sh], lr=1e-2)  # a multi-parameter group
    opt.add_group("alpha", [sc.alpha], lr=5e-2)
    for p in (sc.V, sc.material, sc.alpha, sc.vertex_sh):
        p.grad = rng.standard_normal(p.data.shape)
    opt.step()
    return opt


def test_optimizer_moments_follow_densification(rng):
    sc = soup([tri([0, 0, 0], 2.0, rng), tri([5, 0, 0], 0.1, rng), tri([9, 0, 0], 0.1, rng),
               tri([12, 0, 0], 0.1, rng)], rng)
    sc.alpha.data[9:12] = logit(0.01)  # face 3 pruned
    opt = _adam(sc, rng)
    m_old = {g: [m.copy() for m in opt.groups[g].exp_avg] for g in opt.groups}
    v_old = {g: [v.copy() for v in opt.groups[g].exp_avg_sq] for g in opt.groups}
    vals = {p.name: p.data.copy() for p in sc.params}
    st = DensityStats(4)
    set_grads(st, sc.F, [5.0, 5.0, 0.0, 0.0])
    rep = densify_and_prune(sc, opt, st, cfg(), extent=1.0)
    assert (rep.split, rep.cloned, rep.pruned, rep.faces_after) == (1, 1, 1, 7)
    assert_soup(sc)
    survivors = np.arange(3, 9)  # faces 1, 2 → rows 0..5
    for g in opt.groups.values():
        for k, p in enumerate(g.params):
            assert g.exp_avg[k].shape == p.data.shape == g.exp_avg_sq[k].shape
            np.testing.assert_array_equal(g.exp_avg[k][:6], m_old[g.name][k][survivors])
            np.testing.assert_array_equal(g.exp_avg_sq[k][:6], v_old[g.name][k][survivors])
            assert not g.exp_avg[k][6:].any() and not g.exp_avg_sq[k][6:].any()
            np.testing.assert_array_equal(p.data[:6], vals[p.name][survivors])
            assert p.grad is None
    # the optimizer still steps on the new shapes and updates the scene's own parameters
    for p in (sc.V, sc.material, sc.alpha, sc.vertex_sh):
        p.grad = np.ones_like(p.data)
    before = sc.V.data.copy()
    opt.step()
    assert np.all(sc.V.data < before)


def test_children_and_clones_can_inherit_the_moments(rng):
    """``inherit_moments``: a child vertex gets the moments of its parent's corner (a midpoint: its
    edge's first corner), a clone those of its source; survivors keep theirs."""
    sc = soup([tri([0, 0, 0], 2.0, rng), tri([5, 0, 0], 0.1, rng), tri([9, 0, 0], 0.1, rng)], rng)
    opt = _adam(sc, rng)
    m_old = {g: [m.copy() for m in opt.groups[g].exp_avg] for g in opt.groups}
    v_old = {g: [v.copy() for v in opt.groups[g].exp_avg_sq] for g in opt.groups}
    st = DensityStats(3)
    set_grads(st, sc.F, [5.0, 5.0, 0.0])
    rep = densify_and_prune(sc, opt, st, cfg(inherit_moments=True), extent=1.0)
    assert (rep.split, rep.cloned, rep.faces_after) == (1, 1, 7)
    # rows: survivor faces 1, 2 (0..5), the 4 children of face 0 (6..17), the clone of face 1 (18..20)
    corner = np.array([0, 1, 2, 0, 1, 2])[np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])].reshape(-1)
    src = np.concatenate([np.arange(3, 9), corner, [3, 4, 5]])
    for g in opt.groups.values():
        for k in range(len(g.params)):
            np.testing.assert_array_equal(g.exp_avg[k], m_old[g.name][k][src])
            np.testing.assert_array_equal(g.exp_avg_sq[k], v_old[g.name][k][src])


def test_mixed_group_is_rejected(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng)], rng)
    other = Param(np.zeros(3), "light_params")
    opt = Adam()
    opt.add_group("bad", [sc.V, other])
    with pytest.raises(ValueError, match="mixes"):
        densify_and_prune(sc, opt, DensityStats(1), cfg(), extent=1.0)


def test_rejects_non_soup_and_stale_stats(rng):
    V = rng.standard_normal((4, 3))
    mesh = Scene.from_arrays(V, np.array([[0, 1, 2], [0, 2, 3]]))
    with pytest.raises(ValueError, match="soup"):
        densify_and_prune(mesh, None, DensityStats(2), cfg(), extent=1.0)
    sc = soup([tri([0, 0, 0], 0.1, rng)], rng)
    with pytest.raises(ValueError, match="stats"):
        densify_and_prune(sc, None, DensityStats(2), cfg(), extent=1.0)


def test_float32_scene(rng):
    sc = soup([tri([0, 0, 0], 2.0, rng), tri([5, 0, 0], 0.1, rng)], rng, dtype=np.float32)
    opt = _adam(sc, rng)
    st = DensityStats(2)
    set_grads(st, sc.F, [5.0, 5.0], directions=np.ones((2, 3)))
    densify_and_prune(sc, opt, st, cfg(), extent=1.0)
    for p in sc.params:
        assert p.data.dtype == np.float32 and p.data.flags.c_contiguous
    for g in opt.groups.values():
        assert all(m.dtype == np.float32 for m in g.exp_avg)


# ---------------------------------------------------------------------------------------------- alpha reset


def test_reset_alpha(rng):
    sc = soup([tri([0, 0, 0], 0.1, rng), tri([1, 0, 0], 0.1, rng)], rng)
    opt = _adam(sc, rng)
    sc.alpha.data[:, 0] = logit(np.array([0.9, 0.5, 0.005, 0.2, 0.001, 0.02]))
    mat_m = opt.groups["appearance"].exp_avg[0].copy()
    lowered = reset_alpha(sc, opt, value=0.01)
    assert lowered == 4
    np.testing.assert_allclose(expit(sc.alpha.data[:, 0]), [0.01, 0.01, 0.005, 0.01, 0.001, 0.01], rtol=1e-9)
    g = opt.groups["alpha"]
    assert not g.exp_avg[0].any() and not g.exp_avg_sq[0].any()
    np.testing.assert_array_equal(opt.groups["appearance"].exp_avg[0], mat_m)  # other groups untouched


# ---------------------------------------------------------------------------------------------- config


def test_config_schedule_and_validation():
    c = DensityConfig()
    assert (c.interval, c.densify_from, c.densify_until, c.grad_threshold) == (100, 500, 15_000, 7.5e-5)
    assert (c.prune_alpha, c.prune_world_area, c.prune_screen_frac) == (0.05, 0.1, 0.001)
    assert [it for it in (400, 500, 600, 650, 14_900, 15_000) if c.densify_at(it)] == [600, 14_900]
    assert [it for it in (0, 3000, 4500, 6000, 15_000) if c.reset_alpha_at(it)] == [3000, 6000]
    with pytest.raises(ValueError):
        DensityConfig(split_interp="log")
    with pytest.raises(ValueError):
        DensityConfig(min_faces=10, max_faces=5)


def test_reorder_faces_keeps_rows_and_moments_aligned():
    from triplet_cl.density import reorder_faces
    from triplet_cl.topology import morton_order

    rng = np.random.default_rng(5)
    M = 7
    V = rng.normal(size=(3 * M, 3))
    scene = Scene.from_arrays(V, np.arange(3 * M).reshape(M, 3))
    opt = Adam()
    opt.add_group("V", [scene.V], lr=0.1)
    opt.add_group("alpha", [scene.alpha], lr=0.1)
    scene.V.grad = rng.normal(size=scene.V.data.shape)
    scene.alpha.grad = rng.normal(size=scene.alpha.data.shape)
    opt.step()
    mV = opt.groups["V"].exp_avg[0].copy()
    V0 = scene.V.data.copy()
    order = morton_order(V0.reshape(M, 3, 3).mean(1))
    assert sorted(order) == list(range(M))
    reorder_faces(scene, opt, order)
    idx = (3 * order[:, None] + np.arange(3)).reshape(-1)
    np.testing.assert_array_equal(scene.V.data, V0[idx])
    np.testing.assert_array_equal(opt.groups["V"].exp_avg[0], mV[idx])
    with pytest.raises(ValueError, match="permutation"):
        reorder_faces(scene, opt, np.zeros(M, int))


# ---------------------------------------------------------------------------------------------- device statistics


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_stats_add_on_device_matches_numpy(device, rng, dtype):
    """DensityStats.add as the density.cl kernel: the same statistics as numpy, bit for bit on PoCL,
    over several views with different visible sets, with and without v_V / vs, [N, 2] and [N, 3]."""
    if not device.fp64:
        pytest.skip("the device statistics need fp64")
    exact = "portable" in device.info.platform_name.lower() or "pocl" in device.info.platform_name.lower()
    m = 57
    F = np.arange(3 * m).reshape(m, 3)
    host, dev = DensityStats(m), DensityStats(m)
    for view in range(6):
        vis = rng.random(m) < 0.6
        if view == 0:
            vis[:] = False  # a view that sees nothing
        cols = 3 if view % 2 else 2
        v_vs = rng.standard_normal((3 * m, cols)).astype(dtype)
        kw = {"grad_scale": 0.5 * (100 + view)}
        if view != 2:  # the front-visibility and error statistics (the nearest face of each of 70 pixels)
            front = np.where(rng.random(70) < 0.8, rng.integers(0, m, 70), -1).reshape(7, 10)
            if view == 5:
                front[0, :3] = np.flatnonzero(~vis)[:3]  # inconsistent inputs: nearest somewhere, not visible
            kw.update(front=front, error=rng.random((7, 10)))
        if view != 3:
            kw["v_V"] = rng.standard_normal((3 * m, 3)).astype(np.float32)
        if view != 4:
            kw.update(vs=(rng.random((3 * m, 3)) * 90).astype(dtype), image_size=(100 + view, 80))
        host.add(v_vs, vis, F, **kw)
        dev.add(v_vs, vis, F, device=device, **kw)
        for k in ("grad_accum", "denom", "world_grad_accum", "max_screen_area", "max_screen_frac", "front_views",
                  "front_grad_accum", "err_accum", "err_pixels"):
            a, b = getattr(host, k), getattr(dev, k)
            assert a.dtype == b.dtype and a.shape == b.shape, k
            if exact:
                np.testing.assert_array_equal(b, a, err_msg=k)
            else:
                np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-300, err_msg=k)
    assert host.denom.max() > 1 and host.max_screen_frac.max() > 0
    assert host.front_views.max() > 1 and host.front_grad_accum.max() > 0 and host.err_pixels.sum() > 0
    # validation runs before any work, on either path
    with pytest.raises(ValueError, match="visible"):
        dev.add(np.zeros((3 * m, 3), np.float32), np.ones(m - 1, bool), F, device=device)


# ---------------------------------------------------------------------------------------------- error-driven growth


def _plane_soup(n=8, albedo_shift=0.0):
    """An ``n × n`` grid of squares (2 triangles each) on z = 0, x, y ∈ [−1, 1], as a soup; the faces
    with x < 0 get ``albedo_shift`` added to their raw albedo."""
    from triplet_cl.lights import AmbientLight, PointLight

    t = np.linspace(-1.0, 1.0, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = ([t[i], t[j], 0], [t[i + 1], t[j], 0], [t[i + 1], t[j + 1], 0], [t[i], t[j + 1], 0])
            tris += [[a, b, c], [a, c, d]]
    V = np.asarray(tris, np.float64).reshape(-1, 3)
    m = len(tris)
    mat = np.zeros((3 * m, 6))
    mat[:, 3] = 1.0
    left = V.reshape(m, 3, 3).mean(axis=1)[:, 0] < 0
    mat[np.repeat(left, 3), :3] += albedo_shift
    scene = Scene.from_arrays(V, np.arange(3 * m).reshape(m, 3), material=mat, alpha=np.full((3 * m, 1), 4.0),
                              lights=[PointLight([0.5, 1.0, 3.0], [20.0, 20.0, 20.0]), AmbientLight([0.6, 0.6, 0.6])],
                              brdf="cook_torrance", dtype=np.float32)
    return scene, left


def test_error_criterion_grows_faces_where_the_image_error_is_high(device):
    """A flat grid whose left half has the wrong colour (the target is the same grid with another albedo
    there): the geometry is right, so the screen-space gradient barely moves, but the per-pixel error
    over the left faces is high. With the training defaults (gradient and error criteria), density
    control splits faces on the left only; the right half (rendered exactly) is left alone."""
    import copy
    import dataclasses

    from triplet_cl.camera import Camera
    from triplet_cl.density import front_faces
    from triplet_cl.losses import photometric_loss_and_grad
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.train import TrainConfig

    dens = TrainConfig().density
    assert dens.error_threshold is not None
    scene, left = _plane_soup()
    target_scene, _ = _plane_soup(albedo_shift=-5.0)
    settings = RenderSettings(K=8, sigma=2.0)
    stats = DensityStats(len(scene.F))
    for eye in ([0.0, 0.0, 3.0], [0.4, 0.3, 3.0], [-0.4, -0.2, 3.0]):
        cam = Camera.look_at(eye, [0, 0, 0], [0, 1, 0], 45, 48, 48)
        target = render(target_scene, cam, settings, device).image
        r = render(scene, cam, settings, device)
        _, v_img = photometric_loss_and_grad(r.image, target)
        r.backward(v_img)
        fr = r.info["frags"]
        stats.add(r.info["v_vs"].get(), visible_faces(fr.face, len(scene.F)), scene.F, vs=r.info["vs"].get(),
                  image_size=(cam.width, cam.height), grad_scale=0.5 * cam.width,
                  error=np.abs(r.image - target).mean(axis=2), front=front_faces(fr))
        # the alpha-aware nearest face: the same on an opaque soup, none where every face is faint
        m0 = len(scene.F)
        np.testing.assert_array_equal(front_faces(fr, np.ones(m0), 0.5), front_faces(fr))
        fa = np.where(left, 0.1, 1.0)
        fmap, nearest = front_faces(fr, fa, 0.5), front_faces(fr)
        assert (fmap[nearest >= 0] >= 0).mean() < 0.9 and not left[fmap[fmap >= 0]].any()
        assert (front_faces(fr, np.zeros(m0), 0.5) == -1).all()
    err = stats.mean_error()
    assert np.median(err[left]) > dens.error_threshold and err[~left].max() < 0.1 * dens.error_threshold
    m = len(scene.F)
    V0 = scene.V.data.reshape(m, 3, 3).copy()
    # the defaults (gradient or error), then the error criterion alone (gradient threshold out of reach)
    for config, by_error in ((dens, None), (dataclasses.replace(dens, grad_threshold=1e30), True)):
        sc, st = copy.deepcopy(scene), copy.deepcopy(stats)
        rep = densify_and_prune(sc, None, st, config, extent=1.0, prune_screen=False)  # as before a reset
        grown = rep.split + rep.cloned
        assert rep.pruned == 0 and grown >= 0.5 * left.sum()
        if by_error:
            assert rep.by_error == grown
        # the survivors come first, in order: every face away from the colour edge at x = 0 (the right
        # half beyond the first column, whose faces see the edge's gradient) survives unchanged, and
        # every child / clone lies on the left or in that first column
        kept = m - grown
        Vn = sc.V.data.reshape(-1, 3, 3)
        far = V0.mean(axis=1)[:, 0] > 0.25
        np.testing.assert_array_equal(Vn[:kept][Vn[:kept].mean(axis=1)[:, 0] > 0.25], V0[far])
        assert (Vn[kept:].mean(axis=1)[:, 0] < 0.25).all()
        assert (Vn[kept:].mean(axis=1)[:, 0] < 0).mean() > 0.75


def test_stats_accumulate_the_error_over_each_faces_nearest_pixels(rng):
    """``front`` / ``error``: per face, the mean error over the pixels where it is the nearest face
    (over views), the views where it is nearest, and its gradient over those views only."""
    sc = soup([tri([i, 0, 0], 0.1, rng) for i in range(3)], rng)
    st = DensityStats(3)
    front = np.array([[0, 0, -1], [2, 0, -1]])
    error = np.array([[0.1, 0.3, 9.0], [0.5, 0.2, 9.0]])  # the background's error is nobody's
    set_grads(st, sc.F, [1.0, 2.0, 4.0])  # a view without front / error: only the gradient statistic
    v_vs = np.zeros((9, 3))
    v_vs[sc.F[:, 0], 0] = [3.0, 5.0, 7.0]
    st.add(v_vs, np.ones(3, bool), sc.F, front=front, error=error)
    np.testing.assert_allclose(st.mean_error(), [0.2, 0.0, 0.5])
    np.testing.assert_array_equal(st.front_views, [1, 0, 1])
    np.testing.assert_allclose(st.mean_front_grad(), [3.0, 0.0, 7.0])
    np.testing.assert_allclose(st.mean_grad(), [2.0, 3.5, 5.5])
    with pytest.raises(ValueError, match="error must have the shape"):
        st.add(v_vs, np.ones(3, bool), sc.F, front=front, error=error[:, :2])
    with pytest.raises(ValueError, match="front holds face ids"):
        st.add(v_vs, np.ones(3, bool), sc.F, front=np.array([[3]]))


def _error_stats(m, errors, pixels=100.0):
    """Statistics of ``m`` faces with no gradient, mean error ``errors[f]`` and a projected bbox of ``pixels``."""
    st = DensityStats(m)
    st.err_accum[:] = np.asarray(errors, np.float64) * 10
    st.err_pixels[:] = 10
    st.max_screen_area[:] = pixels
    st.denom[:] = 1
    return st


def test_error_resplit_needs_the_error_to_drop_since_the_last_split(rng):
    """``error_resplit_ratio``: a face split by the error criterion records its error and its 4 children
    inherit the record; a child is split by error again only when its own error has dropped to ≤ ratio ×
    the record (the split helped), not when it stays as high (a shading mismatch a split cannot fix).
    Without records (None: ``inf``) or with the rule off, every face over the threshold is split."""
    c = cfg(error_threshold=0.1, error_min_pixels=4.0, error_resplit_ratio=0.9, split_edge_ratio=0.01)
    sc = soup([tri([2 * i, 0, 0], 1.0, rng) for i in range(2)], rng, alpha=0.9)
    # step 1: both faces over the threshold, no records: both split by error, the records are their errors
    rep = densify_and_prune(sc, None, _error_stats(2, [0.3, 0.3]), c, extent=1.0)
    assert (rep.split, rep.by_error, rep.error_blocked) == (2, 2, 0)
    assert rep.faces_after == 8 and assert_soup(sc) == 8
    np.testing.assert_array_equal(rep.split_error, np.full(8, 0.3))
    # step 2: the first parent's children stayed at 0.3 (no drop), the second's dropped to 0.2 (still > 0.1)
    err = np.repeat([0.3, 0.2], 4)
    rep2 = densify_and_prune(sc, None, _error_stats(8, err), c, extent=1.0, split_error=rep.split_error)
    assert (rep2.split, rep2.by_error, rep2.error_blocked) == (4, 4, 4)
    assert rep2.faces_after == 4 + 16
    # survivors first (the 4 stuck children keep their record), then the grandchildren with the new one
    np.testing.assert_array_equal(rep2.split_error, np.r_[np.full(4, 0.3), np.full(16, 0.2)])
    V = sc.V.data.reshape(-1, 3, 3).mean(axis=1)
    assert (V[:4, 0] < 1.5).all() and (V[4:, 0] > 1.5).all()  # the split ones are the second parent's
    # a drop just above the ratio is not enough; at the ratio it is
    sc3 = soup([tri([2 * i, 0, 0], 1.0, rng) for i in range(2)], rng, alpha=0.9)
    rep3 = densify_and_prune(sc3, None, _error_stats(2, [0.271, 0.27]), c, extent=1.0,
                             split_error=np.array([0.3, 0.3]))
    assert (rep3.split, rep3.error_blocked) == (1, 1)
    # the rule off (None) or no records: the stuck faces are split as before
    for conf, rec in ((cfg(error_threshold=0.1, error_min_pixels=4.0, split_edge_ratio=0.01), np.full(2, 0.3)),
                      (c, None)):
        sc4 = soup([tri([2 * i, 0, 0], 1.0, rng) for i in range(2)], rng, alpha=0.9)
        rep4 = densify_and_prune(sc4, None, _error_stats(2, [0.3, 0.3]), conf, extent=1.0, split_error=rec)
        assert (rep4.split, rep4.error_blocked) == (2, 0)
    # a face over the gradient threshold is densified whatever its error record (the rule is the error's)
    sc5 = soup([tri([2 * i, 0, 0], 1.0, rng) for i in range(2)], rng, alpha=0.9)
    st5 = _error_stats(2, [0.3, 0.3])
    st5.grad_accum[:] = [2.0, 0.0]
    rep5 = densify_and_prune(sc5, None, st5, c, extent=1.0, split_error=np.array([0.3, 0.3]))
    assert (rep5.split, rep5.by_error, rep5.error_blocked) == (1, 0, 1)
    np.testing.assert_array_equal(rep5.split_error, np.r_[0.3, np.full(4, 0.3)])
    with pytest.raises(ValueError, match="split_error must have shape"):
        densify_and_prune(sc5, None, _error_stats(5, np.zeros(5)), c, extent=1.0, split_error=np.zeros(3))
    with pytest.raises(ValueError, match="error_resplit_ratio"):
        cfg(error_resplit_ratio=0.0)


# ---------------------------------------------------------------------------------------------- device visibility


def _layered_soup(rng, m=60):
    """``m`` random overlapping triangles around the origin (several fragments per pixel), as a soup."""
    from triplet_cl.lights import AmbientLight

    c = rng.uniform(-0.6, 0.6, (m, 1, 3))
    V = (c + rng.normal(scale=0.35, size=(m, 3, 3))).reshape(-1, 3)
    return Scene.from_arrays(V, np.arange(3 * m).reshape(m, 3), alpha=np.full((3 * m, 1), 2.0),
                             lights=[AmbientLight([1.0, 1.0, 1.0])], dtype=np.float32)


@pytest.mark.parametrize("K", [1, 8, 150])
def test_visibility_on_device_matches_the_host(device, rng, K):
    """visible_faces / front_faces with a device (the face_visibility.cl kernels, only [M] / [H, W] come
    down) against the host reference (the [P] face ids downloaded, bincount / sort): identical, with and
    without the alpha threshold, for K = 1, 8, 150, and for a view that sees nothing."""
    from triplet_cl.camera import Camera
    from triplet_cl.render import RenderSettings, render

    scene = _layered_soup(rng)
    m = len(scene.F)
    settings = RenderSettings(K=K, sigma=1.0)
    eyes = ([0.0, 0.0, 3.0], [1.5, 0.7, 2.0], [0.0, 0.0, -3.0])
    for eye, target in zip(eyes, ([0, 0, 0], [0, 0, 0], [0, 0, -9.0]), strict=True):  # the last one looks away
        cam = Camera.look_at(eye, target, [0, 1, 0], 45, 40, 32)
        fr = render(scene, cam, settings, device).info["frags"]
        host_vis = visible_faces(fr.face, m)
        np.testing.assert_array_equal(visible_faces(fr.face, m, device=device), host_vis)
        np.testing.assert_array_equal(visible_faces(fr.face, m - 5, device=device), visible_faces(fr.face, m - 5))
        from triplet_cl.density import front_faces

        fa = rng.uniform(0, 1, m)
        for args in ((), (fa, 0.5), (fa, 0.0), (np.zeros(m), 0.5), (np.ones(m), 0.5)):
            host = front_faces(fr, *args)
            dev = front_faces(fr, *args, device=device)
            assert dev.dtype == host.dtype and dev.shape == host.shape == (32, 40)
            np.testing.assert_array_equal(dev, host)
        if eye[2] < 0:
            assert fr.P == 0 and not host_vis.any()
        else:
            assert host_vis.sum() > 10 and (front_faces(fr) >= 0).any()
            assert (front_faces(fr, fa, 0.5) != front_faces(fr)).any()  # the threshold changes some pixels
