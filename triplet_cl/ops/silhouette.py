"""The silhouette edges of a connected mesh seen from an eye, on the device (``kernels_cl/silhouette.cl``).

:func:`silhouette_bits` gives what ``tests/reference/silhouette.py`` (the host reference, in double)
computes — ``[M] int32`` soft-edge bit masks for :func:`~triplet_cl.ops.raster.rasterize`: bit k where edge k
(opposite vertex k) separates a face turned towards the eye from one turned away, or has no single face across
it — from the device positions the render already holds, so that nothing of ``[M]`` size goes through the host
per render (the host version was ~7 ms of a 60k-face mesh-stage step). The front test runs in the positions'
precision: only faces seen exactly edge-on can decide differently from the double-precision reference.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_rows, grid_1d, launch, real_of
from .mesh import DeviceMesh


def silhouette_bits(dev: Device, V: cla.Array, mesh: DeviceMesh, eye) -> cla.Array:
    """Device ``[M] int32`` soft-edge masks of ``mesh`` with device positions ``V [N, 3]`` seen from ``eye``
    (3 numbers, world units)."""
    real = real_of(V, "V")
    if V.shape != (mesh.num_vertices, 3):
        raise ValueError(f"V must have shape [{mesh.num_vertices}, 3], got {list(V.shape)}")
    e = np.asarray(eye, np.float64).reshape(-1)
    if e.shape != (3,) or not np.isfinite(e).all():
        raise ValueError(f"eye must be 3 finite numbers, got {np.asarray(eye).tolist()}")
    M = mesh.num_faces
    soft = device_rows(dev, (M,), np.int32)
    if M == 0:
        return soft
    front = device_rows(dev, (M,), np.uint8)
    launch(dev, "silhouette", "face_front", *grid_1d(M), real=real, V=V, F=mesh.F, M=M, ex=e[0], ey=e[1], ez=e[2],
           front=front)
    launch(dev, "silhouette", "silhouette_bits", *grid_1d(M), real=real, front=front, nb=mesh.device_edge_neighbors,
           M=M, soft=soft)
    return soft


__all__ = ["silhouette_bits"]
