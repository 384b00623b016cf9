"""Reference for ``kernels_cl/silhouette.cl`` (``triplet_cl.ops.silhouette``): the silhouette edges of a connected
mesh seen from an eye, in double precision on the host (the render marked them this way before the kernel)."""

from __future__ import annotations

import numpy as np

from triplet_cl.topology import face_edge_neighbors


def silhouette_edges(vertices: np.ndarray, faces: np.ndarray, eye: np.ndarray, neighbors=None) -> np.ndarray:
    """``[M] int32`` soft-edge bit masks for :func:`~triplet_cl.ops.raster.rasterize`: bit k set where
    edge k (opposite vertex k) lies on the silhouette seen from ``eye`` — the faces on its two sides
    face the camera differently, or it is a boundary / non-manifold edge. ``neighbors``: a cached
    :func:`triplet_cl.topology.face_edge_neighbors`. For a soup (no shared edges) every edge is set."""
    V = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nb = face_edge_neighbors(f) if neighbors is None else neighbors
    if len(f) == 0:
        return np.zeros(0, np.int32)
    tri = V[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = np.einsum("md,md->m", n, np.asarray(eye, np.float64)[None] - tri.mean(axis=1)) > 0
    other = np.where(nb >= 0, front[np.maximum(nb, 0)], ~front[:, None])
    soft = (nb < 0) | (other != front[:, None])
    return (soft[:, 0] * 1 + soft[:, 1] * 2 + soft[:, 2] * 4).astype(np.int32)
