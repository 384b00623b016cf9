"""Mesh refinement: selective midpoint subdivision, QEM simplification, gradient selection, and the
scene + Adam versions that keep every per-vertex parameter and its moments aligned."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from triplet_cl.autodiff import Param

from triplet_cl.mesh.remesh import (
    mesh_edges,
    refine_scene,
    select_by_gradient,
    simplify,
    simplify_scene,
    subdivide_scene,
    subdivide_selected,
)
from triplet_cl.optim import Adam
from triplet_cl.scene import Scene


def _sphere(sub=2):
    s = trimesh.creation.icosphere(sub, radius=1.0)
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64)


def _edge_face_counts(F):
    _, fe = mesh_edges(F)
    return np.bincount(fe.reshape(-1))


# ---------------------------------------------------------------------------------------------- subdivision


def test_subdivide_selected_is_crack_free_and_keeps_surface(rng):
    V, F = _sphere(2)
    mask = np.zeros(len(F), bool)
    mask[rng.choice(len(F), 25, replace=False)] = True
    attrs = {"const": np.full((len(V), 2), 0.25), "pos": V.copy(), "sh": rng.normal(size=(len(V), 6, 4))}
    V2, F2, a2, index_map, parents = subdivide_selected(V, F, mask, attrs)
    # no T-junction: on a closed mesh every edge still has exactly two faces
    assert (_edge_face_counts(F2) == 2).all()
    m = trimesh.Trimesh(V2, F2, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume == pytest.approx(trimesh.Trimesh(V, F).volume, rel=1e-12)  # midpoints: the same surface
    # old vertices first and unchanged, midpoints after with the mean of the edge endpoints
    n = len(V)
    np.testing.assert_array_equal(index_map[:n], np.arange(n))
    assert (index_map[n:] == -1).all()
    np.testing.assert_array_equal(V2[:n], V)
    np.testing.assert_allclose(a2["pos"], V2, atol=1e-15)  # a linear attribute = the position
    assert (a2["const"] == 0.25).all()  # a constant attribute stays constant
    assert a2["sh"].shape == (len(V2), 6, 4)
    # every selected face became 4 children; closure may add red faces; greens split in 2
    n_children = np.bincount(parents, minlength=len(F))
    assert (n_children[mask] == 4).all()
    assert set(np.unique(n_children)) <= {1, 2, 4}
    assert len(F2) == len(F) + 3 * (n_children == 4).sum() + (n_children == 2).sum()
    # the children of each parent cover its area exactly
    area = trimesh.Trimesh(V2, F2, process=False).area_faces
    np.testing.assert_allclose(np.bincount(parents, area), trimesh.Trimesh(V, F).area_faces, rtol=1e-10)


def test_subdivide_single_face_makes_green_neighbours():
    V, F = _sphere(1)
    mask = np.zeros(len(F), bool)
    mask[0] = True
    _, F2, _, _, parents = subdivide_selected(V, F, mask)
    counts = np.bincount(parents, minlength=len(F))
    assert counts[0] == 4 and (counts == 2).sum() == 3  # three edge neighbours bisected
    assert len(F2) == len(F) + 3 + 3
    assert (_edge_face_counts(F2) == 2).all()


def test_subdivide_nothing_selected_is_identity():
    V, F = _sphere(1)
    V2, F2, _, index_map, parents = subdivide_selected(V, F, np.zeros(len(F), bool))
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_array_equal(F2, F)
    np.testing.assert_array_equal(index_map, np.arange(len(V)))
    np.testing.assert_array_equal(parents, np.arange(len(F)))


# ---------------------------------------------------------------------------------------------- simplification


def test_simplify_protected_region_and_representatives():
    V, F = _sphere(3)
    prot = V[F].mean(axis=1)[:, 2] > 0  # keep the upper half untouched
    attrs = {"pos": V.copy(), "const": np.full(len(V), 3.0)}
    V2, F2, a2, vmap = simplify(V, F, target_fraction=0.25, attrs=attrs, protect_mask=prot)
    n_region = int((~prot).sum())
    assert abs(len(F2) - (int(prot.sum()) + round(0.25 * n_region))) <= 1  # an edge collapse removes 2 faces
    m = trimesh.Trimesh(V2, F2, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    # the protected faces are still there, vertex for vertex
    got = {tuple(np.round(t, 12)) for t in V2[F2].reshape(-1, 9)}
    assert all(tuple(np.round(t, 12)) in got for t in V[F[prot]].reshape(-1, 9))
    # each new vertex carries its representative's values; kept vertices did not move
    assert (vmap >= 0).all() and len(np.unique(vmap)) == len(vmap)
    np.testing.assert_array_equal(a2["pos"], V[vmap])
    assert (a2["const"] == 3.0).all()
    kept = np.isin(vmap, np.unique(F[prot]))
    np.testing.assert_array_equal(V2[kept], V[vmap[kept]])


def test_simplify_target_count_whole_mesh():
    V, F = _sphere(2)
    V2, F2, _, vmap = simplify(V, F, target_count=100)
    assert len(F2) == 100 and len(vmap) == len(V2)
    assert trimesh.Trimesh(V2, F2, process=False).is_watertight


def test_simplify_errors():
    V, F = _sphere(1)
    with pytest.raises(ValueError, match="exactly one"):
        simplify(V, F)
    with pytest.raises(ValueError, match="target_fraction"):
        simplify(V, F, target_fraction=0.0)
    with pytest.raises(ValueError, match="no faces"):
        simplify(V, np.zeros((0, 3), int), target_fraction=0.5)
    with pytest.raises(ValueError, match="protect_mask"):
        simplify(V, F, target_fraction=0.5, protect_mask=np.zeros(3, bool))
    with pytest.raises(ValueError, match=r"attrs\['c'\] must have"):
        simplify(V, F, target_fraction=0.5, attrs={"c": np.zeros(2)})


# ---------------------------------------------------------------------------------------------- selection


def test_select_by_gradient():
    g = np.array([5.0, 0.0, 3.0, 1.0, 4.0, 2.0, 0.5, 6.0, 7.0, 8.0])
    hi, lo = select_by_gradient(g, 0.2, 0.3)
    np.testing.assert_array_equal(np.flatnonzero(hi), [8, 9])
    np.testing.assert_array_equal(np.flatnonzero(lo), [1, 3, 6])
    assert not (hi & lo).any()
    with pytest.raises(ValueError, match="<= 1"):
        select_by_gradient(g, 0.7, 0.5)
    with pytest.raises(ValueError, match="shape"):
        select_by_gradient(np.zeros((2, 2)))


# ---------------------------------------------------------------------------------------------- scene + Adam


def _mesh_scene(rng, sub=2, vsh=True):
    V, F = _sphere(sub)
    n = len(V)
    scene = Scene.from_arrays(V, F, material=np.tile([0.3, -0.2, 0.1, 1.0, -1.0, 2.0], (n, 1)),
                              alpha=rng.normal(size=(n, 1)),
                              vertex_sh=rng.normal(size=(n, 6, 4)) if vsh else None)
    opt = Adam()
    opt.add_group("V", [scene.V], lr=1e-3)
    opt.add_group("material", [scene.material], lr=1e-2)
    opt.add_group("alpha", [scene.alpha], lr=1e-2)
    if vsh:
        opt.add_group("vertex_sh", [scene.vertex_sh], lr=1e-2)
    # one step with row-identifying gradients so the moments are distinct per row
    for p in scene.params:
        p.grad = (np.arange(p.data.shape[0], dtype=np.float64) + 1.0).reshape(-1, *[1] * (p.data.ndim - 1)) \
            * np.ones_like(p.data)
    opt.step()
    return scene, opt


def _moments(opt, name):
    g = opt.groups[name]
    return g.exp_avg[0], g.exp_avg_sq[0]


def _assert_aligned(scene, opt):
    n = scene.V.data.shape[0]
    for p in (scene.V, scene.material, scene.alpha, scene.vertex_sh):
        if p is None:
            continue
        assert p.data.shape[0] == n
        m, v = _moments(opt, p.name)
        assert m.shape == p.data.shape and v.shape == p.data.shape
    assert scene.F.dtype == np.int32 and scene.F.max() < n


def test_subdivide_scene_keeps_params_and_moments_aligned(rng):
    scene, opt = _mesh_scene(rng)
    n, m = scene.V.data.shape[0], len(scene.F)
    old = {p.name: p.data.copy() for p in scene.params}
    old_m = {k: _moments(opt, k)[0].copy() for k in ("V", "material", "alpha", "vertex_sh")}
    mask = np.zeros(m, bool)
    mask[:10] = True
    rep = subdivide_scene(scene, opt, mask)
    _assert_aligned(scene, opt)
    assert rep.faces_after == len(scene.F) and rep.vertices_after == scene.V.data.shape[0] > n
    # old rows unchanged, with their moments; new rows zero moments
    for k in ("V", "material", "alpha", "vertex_sh"):
        np.testing.assert_array_equal(getattr(scene, k).data[:n], old[k])
        np.testing.assert_array_equal(_moments(opt, k)[0][:n], old_m[k])
        assert not _moments(opt, k)[0][n:].any() and not _moments(opt, k)[1][n:].any()
    # the constant material stays constant, midpoint values are endpoint means
    np.testing.assert_allclose(scene.material.data, np.tile(old["material"][0], (len(scene.V.data), 1)), rtol=1e-6)
    E, _ = mesh_edges(scene.F)
    assert (_edge_face_counts(scene.F) == 2).all()
    assert trimesh.Trimesh(scene.V.data, scene.F, process=False).is_watertight
    assert len(E) > 0


def test_simplify_scene_carries_representative_rows(rng):
    scene, opt = _mesh_scene(rng, sub=3)
    m = len(scene.F)
    old = {p.name: p.data.copy() for p in scene.params}
    old_m = {k: [a.copy() for a in _moments(opt, k)] for k in ("V", "material", "alpha", "vertex_sh")}
    mask = scene.V.data[scene.F].mean(axis=1)[:, 0] < 0
    rep = simplify_scene(scene, opt, mask, keep_fraction=0.3)
    _assert_aligned(scene, opt)
    assert rep.faces_after == len(scene.F)
    assert abs(rep.faces_after - (int((~mask).sum()) + round(0.3 * mask.sum()))) <= 1  # an edge collapse removes 2
    assert rep.faces_after < m
    # find each new vertex's representative through the alpha rows (random, so unique per old row)
    a_old = old["alpha"][:, 0]
    rep_idx = np.array([np.flatnonzero(a_old == a)[0] for a in scene.alpha.data[:, 0]])
    for k in ("material", "vertex_sh"):
        np.testing.assert_array_equal(getattr(scene, k).data, old[k][rep_idx])
    for k in ("V", "material", "alpha", "vertex_sh"):
        np.testing.assert_array_equal(_moments(opt, k)[0], old_m[k][0][rep_idx])
        np.testing.assert_array_equal(_moments(opt, k)[1], old_m[k][1][rep_idx])
    assert trimesh.Trimesh(scene.V.data, scene.F, process=False).is_watertight
    # Adam still steps on the new shapes
    for p in scene.params:
        p.grad = np.ones_like(p.data)
    opt.step()


def test_refine_scene_counts(rng):
    scene, opt = _mesh_scene(rng, sub=3, vsh=False)
    m = len(scene.F)
    g = np.linalg.norm(scene.V.data[scene.F].mean(axis=1) - [1, 0, 0], axis=1)[::-1].copy()
    rep = refine_scene(scene, opt, g, fraction_hi=0.05, fraction_lo=0.4, keep_fraction=0.5)
    _assert_aligned(scene, opt)
    assert rep.faces_before == m and rep.faces_after == len(scene.F)
    assert rep.subdivided == round(0.05 * m) and rep.simplified >= round(0.4 * m)
    assert trimesh.Trimesh(scene.V.data, scene.F, process=False).is_watertight


def test_scene_functions_reject_bad_input(rng):
    scene, opt = _mesh_scene(rng, sub=1, vsh=False)
    with pytest.raises(ValueError, match="face_mask"):
        subdivide_scene(scene, opt, np.zeros(3, bool))
    with pytest.raises(ValueError, match="face_grad"):
        refine_scene(scene, opt, np.zeros(3))
    empty = Scene.from_arrays(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="no faces"):
        subdivide_scene(empty, None, np.zeros(0, bool))
    assert isinstance(scene.V, Param)
