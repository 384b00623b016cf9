"""Geometry metrics of the mesh phase: symmetric Chamfer distance against a reference mesh, also against the
reference's **outer surface** where the reference is several overlapping closed parts.

Why the outer surface: a reference modelled as overlapping parts (gadget's ``gt_mesh.ply``: 39 closed boxes and
cylinders, a cab sunk into its base plate) has faces inside other parts — 28 % of its area on gadget — that no
photo shows and no reconstruction of the object can have. Measured on gadget (session 36): the exact outer
surface (the parts' boolean union, computed with manifold3d in a bench script) scores 0.0089 against the raw
reference, so issue 19's 0.008 was out of reach of a perfect answer; against the union our mesh scores 0.0081 and
the union itself 0.0034 (the sampling floor). :func:`buried_samples` drops the reference's samples that lie inside
another of its closed parts (generalised winding number); the Chamfer against what is left agrees with the
union's within the sampling noise. A one-part reference (spot, Bob) has nothing buried: both numbers are equal.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


def sample_surface(V: np.ndarray, F: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points ``[n, 3]`` uniformly distributed over the area of the mesh ``V [N,3]``, ``F [M,3]``."""
    return _sample_with_faces(V, F, n, seed)[0]


def _sample_with_faces(V: np.ndarray, F: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_surface`'s ``n`` points and the face each lies on."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if len(F) == 0:
        raise ValueError("cannot sample the surface of a mesh with no faces")
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("cannot sample the surface of a mesh whose faces all have zero area")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(F), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("nk,nkd->nd", w, tri[face]), face


def winding_number(tri: np.ndarray, X: np.ndarray, chunk_elems: int = 500_000) -> np.ndarray:
    """The generalised winding number ``[Q]`` of the triangles ``tri [M, 3, 3]`` at the points ``X [Q, 3]``
    (Van Oosterom–Strackee solid angles / 4π): 1 inside a closed outward-oriented surface, 0 outside. Points ×
    triangles go through in chunks of ``chunk_elems`` pairs (~100 MB of temporaries at the default)."""
    tri = np.asarray(tri, np.float64)
    X = np.asarray(X, np.float64)
    out = np.zeros(len(X))
    step = max(1, chunk_elems // max(len(tri), 1))
    for s in range(0, len(X), step):
        a = tri[None] - X[s:s + step, None, None, :]  # [q, M, 3 corners, 3]
        la = np.linalg.norm(a, axis=-1)
        a0, a1, a2 = a[:, :, 0], a[:, :, 1], a[:, :, 2]
        det = np.einsum("qmi,qmi->qm", a0, np.cross(a1, a2))
        den = (la[..., 0] * la[..., 1] * la[..., 2] + np.einsum("qmi,qmi->qm", a0, a1) * la[..., 2]
               + np.einsum("qmi,qmi->qm", a1, a2) * la[..., 0] + np.einsum("qmi,qmi->qm", a2, a0) * la[..., 1])
        out[s:s + step] = np.arctan2(det, den).sum(1) / (2 * np.pi)
    return out


def closed_parts(F: np.ndarray, n_vertices: int) -> tuple[np.ndarray, list[int]]:
    """``(label [M] per face, closed)``: the faces' connected parts (sharing a vertex) and the labels of the parts
    that are closed and consistently oriented (every edge used by exactly two of its faces, once in each direction:
    it bounds a volume whose winding number is ±1 inside; a flipped face would make it ±1 just outside too)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(F, np.int64)
    m = len(F)
    rows = np.repeat(np.arange(m), 3)
    g = coo_matrix((np.ones(3 * m), (rows, F.reshape(-1) + m)), shape=(m + n_vertices, m + n_vertices))
    _, lab = connected_components(g, directed=False)
    label = np.unique(lab[:m], return_inverse=True)[1]
    d = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # directed edges: a closed, consistently oriented part uses each
    _, dcnt_inv, dcnt = np.unique(d, axis=0, return_inverse=True, return_counts=True)  # once each way
    e = np.sort(d, axis=1)
    _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    edge_ok = ((cnt == 2)[inv.reshape(-1)] & (dcnt == 1)[dcnt_inv.reshape(-1)]).reshape(m, 3).all(1)
    closed = [int(c) for c in range(label.max() + 1) if edge_ok[label == c].all()]
    return label, closed


MAX_BURIED_PAIRS = 2e9  # the winding-number test's point-triangle pairs (~8M/s here: about 4 minutes at most)


def buried_samples(V: np.ndarray, F: np.ndarray, P: np.ndarray, face: np.ndarray,
                   max_pairs: float = MAX_BURIED_PAIRS) -> np.ndarray:
    """``[Q]`` bool: the surface samples ``P`` (on the faces ``face`` of ``V``, ``F``) that lie inside another
    closed part of the mesh — faces no camera sees. Each sample is tested a hair (1e-5 of the bounding box's
    diagonal) off its face along the face's normal: a face flush with another part's face and facing the same way
    (two parts' coplanar bottoms) is on the outer surface, one pressed against another part's face (facing it) is
    buried, where the winding number on the plane itself is ±½ by rounding. A :class:`ValueError` when the test would
    take more than ``max_pairs`` point-triangle pairs (large overlapping parts)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    label, closed = closed_parts(F, len(V))
    out = np.zeros(len(P), bool)
    if not closed or label.max() == 0:  # one part, or no part that bounds a volume: nothing is inside another
        return out
    tri = V[F]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    eps = 1e-5 * float(np.linalg.norm(V.max(0) - V.min(0)))
    Pt = np.asarray(P, np.float64) + eps * nrm[face]
    own = label[face]
    work = []
    for c in closed:
        fc = np.flatnonzero(label == c)
        lo, hi = V[F[fc]].reshape(-1, 3).min(0), V[F[fc]].reshape(-1, 3).max(0)
        cand = np.flatnonzero((own != c) & np.all((Pt >= lo) & (Pt <= hi), axis=1))
        work.append((fc, cand))
    pairs = sum(len(fc) * len(cand) for fc, cand in work)
    if pairs > max_pairs:
        raise ValueError(f"the buried-sample test would take {pairs:.3g} point-triangle pairs (at most "
                         f"{max_pairs:.3g}): a reference of large overlapping parts")
    for fc, cand in work:
        cand = cand[~out[cand]]
        if len(cand):
            out[cand[np.abs(winding_number(tri[fc], Pt[cand])) > 0.5]] = True
    return out


def chamfer_distance(V1, F1, V2, F2, n: int = 100_000, seed: int = 0,
                     max_buried_pairs: float = MAX_BURIED_PAIRS) -> dict:
    """Symmetric mean Chamfer distance between two meshes, from ``n`` area-uniform samples of each; mesh 2 is the
    reference.

    Returns ``{"chamfer": (d12 + d21) / 2, "d12": mean distance of mesh-1 samples to mesh 2,
    "d21": the reverse, "hausdorff90": the larger of the two 90th percentiles}`` (same units as V), and the same
    four against the reference's outer surface (module docstring), ``"chamfer_surface"``, ``"d12_surface"``,
    ``"d21_surface"``, ``"hausdorff90_surface"``, with ``"buried_fraction"``, the share of the reference's area
    inside another of its closed parts (0: the two sets are equal). The outer surface is sampled with about
    ``n`` points too (``n / (1 − buried_fraction)`` drawn, at most 4 n), so that both sets have the same density.
    All five are None where the test would take more than ``max_buried_pairs`` point-triangle pairs.
    """
    p1 = sample_surface(V1, F1, n, seed)
    p2, f2 = _sample_with_faces(V2, F2, n, seed + 1)
    d12 = cKDTree(p2).query(p1, workers=-1)[0]
    d21 = cKDTree(p1).query(p2, workers=-1)[0]
    out = {"chamfer": float(0.5 * (d12.mean() + d21.mean())), "d12": float(d12.mean()), "d21": float(d21.mean()),
           "hausdorff90": float(max(np.percentile(d12, 90), np.percentile(d21, 90)))}
    try:
        buried = buried_samples(V2, F2, p2, f2, max_buried_pairs)
        frac = float(buried.mean())
        if 0 < frac < 1:  # the outer surface at about n samples too (at most 4 n drawn)
            p2, f2 = _sample_with_faces(V2, F2, int(np.ceil(n / max(1 - frac, 0.25))), seed + 2)
            p2 = p2[~buried_samples(V2, F2, p2, f2, max_buried_pairs)]
            if len(p2) == 0:
                raise ValueError("no sample of the reference lies on its outer surface")
            d12 = cKDTree(p2).query(p1, workers=-1)[0]
            d21 = cKDTree(p1).query(p2, workers=-1)[0]
    except ValueError:  # too large to test, or nothing outside: the outer-surface numbers are not given
        return {**out, "chamfer_surface": None, "d12_surface": None, "d21_surface": None,
                "hausdorff90_surface": None, "buried_fraction": None}
    out.update({"chamfer_surface": float(0.5 * (d12.mean() + d21.mean())), "d12_surface": float(d12.mean()),
                "d21_surface": float(d21.mean()),
                "hausdorff90_surface": float(max(np.percentile(d12, 90), np.percentile(d21, 90))),
                "buried_fraction": frac})
    return out


def load_reference_mesh(data_dir) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground-truth mesh of a dataset (``gt_mesh.ply`` beside its transforms), or None."""
    import trimesh

    path = Path(data_dir) / "gt_mesh.ply"
    if not path.is_file():
        return None
    m = trimesh.load(path, process=False, force="mesh")
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
