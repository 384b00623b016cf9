"""The mesh metrics: the generalised winding number, a reference's closed parts, the samples buried inside another
part, and the Chamfer distance against the reference's outer surface (``triplet_cl.mesh.metrics``)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from triplet_cl.mesh.metrics import buried_samples, chamfer_distance, closed_parts, sample_surface, winding_number


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _concat(*meshes) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.util.concatenate(meshes)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_winding_number_of_a_closed_box():
    b = _box([0, 0, 0], [1, 2, 3])
    X = np.array([[0.5, 1, 1.5], [0.1, 0.1, 0.1], [2, 1, 1.5], [0.5, -0.1, 1.5], [-5, 7, 3]])
    w = winding_number(b.triangles, X)
    np.testing.assert_allclose(w, [1, 1, 0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(winding_number(b.triangles, X, chunk_elems=1), w, atol=1e-12)  # chunked the same


def test_closed_parts_labels_and_closedness():
    a, b = _box([0, 0, 0], [1, 1, 1]), _box([3, 0, 0], [4, 1, 1])
    V, F = _concat(a, b)
    label, closed = closed_parts(F, len(V))
    assert sorted(set(label.tolist())) == [0, 1] and closed == [0, 1]
    assert (label[:12] == label[0]).all() and (label[12:] != label[0]).all()
    label, closed = closed_parts(F[:-1], len(V))  # a box with a face missing is open
    assert len(closed) == 1


def test_buried_samples_of_overlapping_parts():
    """A cab sunk into a plate: the cab's faces inside the plate and the plate's top under the cab are buried; an
    exact fraction of the area."""
    plate, cab = _box([-1, -1, 0], [1, 1, 0.5]), _box([-0.5, -0.5, 0.25], [0.5, 0.5, 1.25])
    V, F = _concat(plate, cab)
    P, face = sample_surface_with_faces(V, F, 200_000)
    buried = buried_samples(V, F, P, face)
    # buried: the plate's top under the cab (1×1), the cab's bottom (1×1) and its four sides' lower quarter (4·1·0.25)
    total = plate.area + cab.area
    assert buried.mean() == pytest.approx(3.0 / total, abs=0.005)
    # a lone part has nothing buried
    V1, F1 = np.asarray(plate.vertices), np.asarray(plate.faces)
    P1, f1 = sample_surface_with_faces(V1, F1, 1000)
    assert not buried_samples(V1, F1, P1, f1).any()


def test_flush_faces_count_by_orientation():
    """Two boxes side by side sharing a bottom plane (faces flush and facing the same way) keep their bottoms; two
    boxes pressed face to face bury the touching faces."""
    a, b = _box([0, 0, 0], [1, 1, 1]), _box([1.5, 0, 0], [2.5, 1, 0.5])  # both bottoms on z = 0, apart
    c = _box([-1, -1, -0.5], [3, 2, 0])  # a slab under both: its top touches their bottoms, face to face
    V, F = _concat(a, b)
    P, face = sample_surface_with_faces(V, F, 50_000)
    assert not buried_samples(V, F, P, face).any()
    V, F = _concat(a, b, c)
    P, face = sample_surface_with_faces(V, F, 100_000)
    buried = buried_samples(V, F, P, face)
    n = np.cross(V[F[face, 1]] - V[F[face, 0]], V[F[face, 2]] - V[F[face, 0]])
    z = P[:, 2]
    on_contact = (np.abs(z) < 1e-9) & (((P[:, 0] < 1) & (P[:, 0] > 0) | (P[:, 0] > 1.5) & (P[:, 0] < 2.5))
                                       & (P[:, 1] > 0) & (P[:, 1] < 1))
    assert buried[on_contact].all()
    assert not buried[~on_contact].any()  # every other face (the tops, the sides, the slab around) is outside
    assert n.shape == (len(P), 3)


def test_chamfer_surface_drops_the_buried_reference_only():
    """The reference against itself: the raw Chamfer is the sampling floor; against its outer surface the reverse
    direction (outer samples to the mesh) stays at the floor and the forward one grows by the mesh's buried
    squares. A one-part reference gives the raw numbers."""
    plate, cab = _box([-1, -1, 0], [1, 1, 0.5]), _box([-0.5, -0.5, 0.25], [0.5, 0.5, 1.25])
    V, F = _concat(plate, cab)
    r = chamfer_distance(V, F, V, F, n=60_000)
    assert r["buried_fraction"] == pytest.approx(3.0 / (plate.area + cab.area), abs=0.01)
    assert r["d21_surface"] < 1.3 * r["d21"]
    assert r["d12_surface"] > 3 * r["d12"]  # the mesh's own buried faces are far from the outer surface
    one = chamfer_distance(np.asarray(cab.vertices), np.asarray(cab.faces), np.asarray(plate.vertices),
                           np.asarray(plate.faces), n=5000)
    assert one["buried_fraction"] == 0
    for k in ("chamfer", "d12", "d21", "hausdorff90"):
        assert one[f"{k}_surface"] == one[k]


def sample_surface_with_faces(V, F, n, seed=0):
    from triplet_cl.mesh.metrics import _sample_with_faces

    P, face = _sample_with_faces(V, F, n, seed)
    np.testing.assert_array_equal(P, sample_surface(V, F, n, seed))  # the same draws as sample_surface
    return P, face


def test_a_part_with_a_flipped_face_is_not_closed():
    """Every edge used twice but one face flipped: its winding number is ±1 just outside that face, so it would bury
    samples of the parts around; closed means each edge once in each direction."""
    a, b = _box([0, 0, 0], [1, 1, 1]), _box([3, 0, 0], [4, 1, 1])
    V, F = _concat(a, b)
    F = F.copy()
    F[0] = F[0, ::-1]
    _, closed = closed_parts(F, len(V))
    assert len(closed) == 1


def test_a_buried_test_too_large_gives_no_surface_numbers():
    plate, cab = _box([-1, -1, 0], [1, 1, 0.5]), _box([-0.5, -0.5, 0.25], [0.5, 0.5, 1.25])
    V, F = _concat(plate, cab)
    P, face = sample_surface_with_faces(V, F, 1000)
    with pytest.raises(ValueError, match="point-triangle pairs"):
        buried_samples(V, F, P, face, max_pairs=10)
    r = chamfer_distance(V, F, V, F, n=2000, max_buried_pairs=10)
    assert r["chamfer"] >= 0 and r["chamfer_surface"] is None and r["buried_fraction"] is None
