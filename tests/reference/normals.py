"""Reference implementation of face and area-weighted vertex normals (numpy, complex-step safe)."""

from __future__ import annotations

import numpy as np

EPS2 = 1e-20


def safe_normalize(v):
    """``v / sqrt(max(|v|^2, EPS2))`` along the last axis (analytic: works for complex steps)."""
    l2 = np.sum(v * v, axis=-1, keepdims=True)
    return v / np.sqrt(np.where(l2.real > EPS2, l2, EPS2))


def face_cross(V, F):
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return np.cross(v1 - v0, v2 - v0)


def face_normals(V, F):
    """Reference implementation of face_normals: ``[M, 3]``."""
    return safe_normalize(face_cross(V, F))


def vertex_normals(V, F):
    """Reference implementation of vertex_normals (area weighted): ``[N, 3]``."""
    fc = face_cross(V, F)
    s = np.zeros(V.shape, dtype=fc.dtype)
    for c in range(3):
        np.add.at(s, F[:, c], fc)
    return safe_normalize(s)
