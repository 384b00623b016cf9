"""Geometry metrics of the mesh phase: symmetric Chamfer distance against a reference mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


def sample_surface(V: np.ndarray, F: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points ``[n, 3]`` uniformly distributed over the area of the mesh ``V [N,3]``, ``F [M,3]``."""
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
    return np.einsum("nk,nkd->nd", w, tri[face])


def chamfer_distance(V1, F1, V2, F2, n: int = 100_000, seed: int = 0) -> dict:
    """Symmetric mean Chamfer distance between two meshes, from ``n`` area-uniform samples of each.

    Returns ``{"chamfer": (d12 + d21) / 2, "d12": mean distance of mesh-1 samples to mesh 2,
    "d21": the reverse, "hausdorff90": the larger of the two 90th percentiles}`` (same units as V).
    """
    p1 = sample_surface(V1, F1, n, seed)
    p2 = sample_surface(V2, F2, n, seed + 1)
    d12 = cKDTree(p2).query(p1, workers=-1)[0]
    d21 = cKDTree(p1).query(p2, workers=-1)[0]
    return {"chamfer": float(0.5 * (d12.mean() + d21.mean())), "d12": float(d12.mean()), "d21": float(d21.mean()),
            "hausdorff90": float(max(np.percentile(d12, 90), np.percentile(d21, 90)))}


def load_reference_mesh(data_dir) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground-truth mesh of a dataset (``gt_mesh.ply`` beside its transforms), or None."""
    import trimesh

    path = Path(data_dir) / "gt_mesh.ply"
    if not path.is_file():
        return None
    m = trimesh.load(path, process=False, force="mesh")
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
