"""Topology and self-intersection repair of the exported mesh (triplet_cl/mesh/repair.py, issue 21)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from triplet_cl.mesh.repair import mesh_topology, repair_self_intersections, self_intersections


def _brute_force_pairs(V, F) -> set:
    """Every pair of faces without a common vertex that intersect, by an independent test: Möller–Trumbore
    ray/triangle on each edge as a ray, the hit inside the edge (0 < t < 1)."""
    tri = np.asarray(V, np.float64)[np.asarray(F)]

    def edge_hits(p, q, t3):
        d = q - p
        e1, e2 = t3[1] - t3[0], t3[2] - t3[0]
        h = np.cross(d, e2)
        a = e1 @ h
        if abs(a) < 1e-15:
            return False
        f = 1 / a
        s = p - t3[0]
        u = f * (s @ h)
        qv = np.cross(s, e1)
        v = f * (d @ qv)
        t = f * (e2 @ qv)
        return 0 < u < 1 and 0 < v and u + v < 1 and 0 < t < 1

    out = set()
    lo, hi = tri.min(1), tri.max(1)
    for a in range(len(F)):
        for b in range(a + 1, len(F)):
            if set(F[a]) & set(F[b]) or (lo[a] > hi[b]).any() or (lo[b] > hi[a]).any():  # boxes apart: no hit
                continue
            A, B = tri[a], tri[b]
            if any(edge_hits(A[i], A[(i + 1) % 3], B) or edge_hits(B[i], B[(i + 1) % 3], A) for i in range(3)):
                out.add((a, b))
    return out


def test_two_overlapping_spheres_match_brute_force():
    s1 = trimesh.creation.icosphere(1, radius=1.0)
    s2 = trimesh.creation.icosphere(1, radius=0.8)
    s2.vertices += [0.9, 0.13, 0.07]
    m = trimesh.util.concatenate([s1, s2])
    got = {tuple(p) for p in self_intersections(m.vertices, m.faces)}
    want = _brute_force_pairs(m.vertices, m.faces)
    assert len(want) > 10 and got == want
    top = mesh_topology(m.vertices, m.faces)
    assert top["components"] == 2 and top["watertight"] and top["genus"] == 0
    assert top["self_intersections"] == len(want)


def test_topology_of_known_shapes():
    sphere = trimesh.creation.icosphere(2)
    torus = trimesh.creation.torus(1.0, 0.3, major_sections=24, minor_sections=12)
    t = mesh_topology(sphere.vertices, sphere.faces)
    assert (t["genus"], t["watertight"], t["self_intersections"], t["euler"]) == (0, True, 0, 2)
    t = mesh_topology(torus.vertices, torus.faces)
    assert (t["genus"], t["watertight"], t["self_intersections"]) == (1, True, 0)
    # two tetrahedra sharing one vertex (a bow tie): every edge has two faces, but the vertex is not manifold
    t1 = trimesh.creation.box().subdivide()
    t2 = t1.copy()
    t2.vertices = -t2.vertices + 2 * t1.vertices[0]  # point-mirrored through vertex 0 of t1: touches there
    both = trimesh.util.concatenate([t1, t2])
    Vb, inv = np.unique(np.round(both.vertices, 9), axis=0, return_inverse=True)
    t = mesh_topology(Vb, inv.reshape(-1)[both.faces])
    assert t["nonmanifold_edges"] == 0 and t["nonmanifold_vertices"] == 1 and not t["watertight"]
    assert mesh_topology(sphere.vertices, sphere.faces)["nonmanifold_vertices"] == 0
    open_f = sphere.faces[1:]
    t = mesh_topology(sphere.vertices, open_f)
    assert not t["watertight"] and t["genus"] is None and t["boundary_edges"] == 3


def test_a_fold_and_a_poke_are_found_and_repaired_locally():
    """A vertex pushed through the far side of a sphere (a spike crossing the surface) and a fold of two
    neighbours: found; the repair removes every crossing and leaves far vertices exactly where they were."""
    m = trimesh.creation.icosphere(3)
    V = np.asarray(m.vertices, np.float64).copy()
    F = np.asarray(m.faces)
    assert len(self_intersections(V, F)) == 0
    k = int(np.argmax(V[:, 0]))
    V[k] = [-1.3, 0.0, 0.0] + 0.0 * V[k]  # through the sphere and out of the far side
    pairs = self_intersections(V, F)
    assert len(pairs) > 0
    Vn, rep = repair_self_intersections(V, F)
    assert rep.before == len(pairs) and rep.after == 0 and len(self_intersections(Vn, F)) == 0
    far = np.linalg.norm(np.asarray(m.vertices) - [1, 0, 0], axis=1) > 0.9
    far &= np.linalg.norm(np.asarray(m.vertices) - [-1, 0, 0], axis=1) > 0.9
    assert np.array_equal(Vn[far], V[far]) and far.sum() > len(V) // 3
    assert rep.moved_vertices < len(V) // 2
    # the mesh stage's first neighbourhood (no extra rings): the crossings go too, fewer vertices move
    Vn0, rep0 = repair_self_intersections(V, F, rings=0)
    assert rep0.after == 0 and len(self_intersections(Vn0, F)) == 0
    assert rep0.moved_vertices < rep.moved_vertices, (rep0, rep)
    # a fold: two neighbours flattened onto each other (the second's free corner mirrored onto the first's side)
    V2 = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0.8, 0.0]], np.float64)
    F2 = np.array([[0, 1, 2], [1, 0, 3]])
    assert {tuple(p) for p in self_intersections(V2, F2)} == {(0, 1)}
    V2[3] = [0.5, -0.8, 0.0]  # unfolded: flat and fine
    assert len(self_intersections(V2, F2)) == 0


def test_no_faces_and_float32():
    assert mesh_topology(np.zeros((0, 3)), np.zeros((0, 3), int))["faces"] == 0
    m = trimesh.creation.icosphere(2)
    V = np.asarray(m.vertices, np.float32)
    Vn, rep = repair_self_intersections(V, m.faces)
    assert rep.before == 0 and np.array_equal(Vn, V.astype(np.float64))


@pytest.mark.parametrize("seed", [0, 1])
def test_random_triangles_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    V = rng.uniform(-1, 1, (150, 3))
    F = rng.integers(0, 150, (50, 3))
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    got = {tuple(p) for p in self_intersections(V, F)
           if not set(F[p[0]]) & set(F[p[1]])}
    assert got == _brute_force_pairs(V, F)


def test_repair_stops_when_smoothing_removes_no_crossing():
    """Crossings smoothing cannot undo (two closed parts through each other) are left, not chased with ever larger
    neighbourhoods: after a round that removed none the best state found is returned — here the mesh as it was (every
    vertex in place; with the rule before, 12 rounds shrank both spheres around their intersection)."""
    a = trimesh.creation.icosphere(3, radius=0.8)
    V = np.concatenate([a.vertices, a.vertices + [1.0, 0.0, 0.0]])
    F = np.concatenate([a.faces, a.faces + len(a.vertices)])
    Vn, rep = repair_self_intersections(V, F)
    assert rep.before == rep.after > 20 and rep.rounds == 0 and rep.moved_vertices == 0
    np.testing.assert_array_equal(Vn, V)
    _, rep = repair_self_intersections(V, F, patience=100)  # the old rule's growth: a few crossings fewer, much moved
    assert rep.after < rep.before and rep.moved_vertices > 300


def test_broad_phase_lists_each_overlapping_pair_once_and_subsets_match():
    """The grid keeps a pair only in the cell of its boxes' larger low corner: every overlapping pair once, sorted, the
    same set as an all-pairs box test (faces of very different sizes span many cells); ``faces=`` / ``active`` keeps
    exactly the pairs with a chosen face."""
    from triplet_cl.mesh.repair import _candidate_pairs

    rng = np.random.default_rng(3)
    c = rng.uniform(-1, 1, (300, 1, 3))
    tri = c + rng.normal(size=(300, 3, 3)) * rng.choice([0.02, 0.3], (300, 1, 1))
    lo, hi = tri.min(1), tri.max(1)
    ov = ((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None])).all(2)
    want = np.argwhere(np.triu(ov, 1))
    got = _candidate_pairs(tri)
    np.testing.assert_array_equal(got, want)  # np.argwhere's order: sorted by (a, b)
    active = rng.random(300) < 0.1
    np.testing.assert_array_equal(_candidate_pairs(tri, active=active), want[active[want[:, 0]] | active[want[:, 1]]])
    V, F = tri.reshape(-1, 3), np.arange(900).reshape(300, 3)
    full = self_intersections(V, F)
    sub = self_intersections(V, F, faces=active)
    assert len(full) > 5
    np.testing.assert_array_equal(sub, full[active[full[:, 0]] | active[full[:, 1]]])


def _reference_repair(V, F, rings=0, steps=5, max_rounds=12, lam=0.5, patience=1):
    """The repair with a full self-intersection test every round (the rule before the incremental one)."""
    from triplet_cl.mesh.repair import _neighbours

    Vn = np.asarray(V, np.float64).copy()
    pairs = self_intersections(Vn, F)
    A = _neighbours(F, len(Vn))
    deg = np.maximum(np.asarray(A.sum(1)).ravel(), 1)
    best = (len(pairs), Vn.copy())
    stalled = 0
    for r in range(1, max_rounds + 1):
        sel = np.zeros(len(Vn), bool)
        sel[F[pairs.ravel()].ravel()] = True
        for _ in range(rings + r - 1):
            sel |= (A @ sel.astype(np.float64)) > 0
        for _ in range(steps):
            avg = (A @ Vn) / deg[:, None]
            Vn[sel] += lam * (avg[sel] - Vn[sel])
        pairs = self_intersections(Vn, F)
        if len(pairs) < best[0]:
            best, stalled = (len(pairs), Vn.copy()), 0
        else:
            stalled += 1
        if len(pairs) == 0 or stalled >= patience:
            break
    return best


@pytest.mark.parametrize("shift", [2.0, 3.0])
def test_repair_retests_only_moved_faces_and_matches_a_full_retest(shift):
    """Each round re-tests only the pairs with a moved face (the others keep their answer): the same repaired mesh,
    bit for bit, as a full test every round."""
    a = trimesh.creation.icosphere(3, radius=1.0)
    rng = np.random.default_rng(0)
    V = np.asarray(a.vertices, np.float64).copy()
    idx = rng.choice(len(V), 40, replace=False)
    t = rng.normal(size=(40, 3))
    t -= (t * V[idx]).sum(1, keepdims=True) * V[idx]
    V[idx] += shift * 0.08 * t / np.linalg.norm(t, axis=1, keepdims=True) + rng.normal(size=(40, 3)) * 0.02  # folds
    F = np.asarray(a.faces, np.int64)
    Vn, rep = repair_self_intersections(V, F, rings=0, steps=1, lam=0.1)  # gentle: several rounds
    n_ref, V_ref = _reference_repair(V, F, steps=1, lam=0.1)
    assert rep.before > 20 and rep.rounds >= 3
    assert rep.after == n_ref == len(self_intersections(Vn, F))
    np.testing.assert_array_equal(Vn, V_ref)
