"""Mesh connectivity helpers shared by the ops (host side, numpy).

The adjoint of every "vertex attribute → face corner" gather is a "face corner → vertex" sum. On
devices without float atomics we do that sum as a deterministic gather over a CSR table of the
corners of each vertex, built once per topology here.
"""

from __future__ import annotations

import numpy as np


def vertex_corner_csr(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR table from vertices to the face corners that use them.

    Args:
        faces: ``[M, 3]`` integer vertex indices.
        num_vertices: ``N``.

    Returns:
        ``offsets [N+1] int32`` and ``corners [3M] int32`` where the corners of vertex ``v`` are
        ``corners[offsets[v]:offsets[v+1]]``, each encoded as ``3 * face + corner`` (in increasing
        order, so sums over them are deterministic).
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1)
    order = np.argsort(f, kind="stable").astype(np.int32)
    counts = np.bincount(f, minlength=num_vertices)
    offsets = np.zeros(num_vertices + 1, np.int32)
    np.cumsum(counts, out=offsets[1:])
    return offsets, order


def edge_adjacent_faces(faces: np.ndarray) -> np.ndarray:
    """Pairs of faces sharing an (undirected) edge: ``[P, 2] int64`` (each pair once)."""
    f = np.asarray(faces, dtype=np.int64)
    if f.size == 0:
        return np.zeros((0, 2), np.int64)
    e = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    e.sort(axis=1)
    face_of = np.repeat(np.arange(len(f)), 3)
    key = e[:, 0] * (int(f.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key_s, face_s = key[order], face_of[order]
    same = np.nonzero(key_s[1:] == key_s[:-1])[0]
    return np.stack([face_s[same], face_s[same + 1]], axis=1)
