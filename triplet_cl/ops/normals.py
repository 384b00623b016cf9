"""Face and area-weighted vertex normals with adjoints to the vertex positions (``kernels_cl/normals.cl``).

* ``face_normals(V, F)``: unit normals ``normalize((v1 - v0) x (v2 - v0))`` per face ``[M, 3]``.
* ``vertex_normals(V, F)``: ``normalize(sum over incident faces of the unnormalised cross product)``
  per vertex ``[N, 3]`` (area weighted). Vertices used by no face get the zero vector.

Degenerate faces / vertices get zero normals and finite gradients (``safe_normalize``). The
adjoints are gathered per vertex over the corner CSR table of :mod:`triplet_cl.topology` (no
atomics, deterministic). For an independent-triangle soup, use face normals repeated on the 3
vertices of each face.

``face_forward`` / ``face_backward`` / ``vertex_forward`` / ``vertex_backward`` work on validated
device arrays; the public functions accept numpy arrays and validate them.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device, get_device
from ..topology import vertex_corner_csr
from .common import check_faces, check_real, empty, to_device, to_host
from .common import run_1d as _run


def _csr_device(dev: Device, F: np.ndarray, N: int, csr) -> tuple[cla.Array, cla.Array]:
    if csr is None:
        csr = vertex_corner_csr(F, N)
    offsets, corners = (np.ascontiguousarray(a, dtype=np.int32) for a in csr)
    if offsets.shape != (N + 1,) or corners.shape != (3 * len(F),):
        raise ValueError(
            f"csr must be (offsets [{N + 1}], corners [{3 * len(F)}]) from vertex_corner_csr, "
            f"got {list(offsets.shape)}, {list(corners.shape)}"
        )
    q = dev.queue
    return to_device(q, offsets), to_device(q, corners if corners.size else np.zeros(1, np.int32))


# ---- device-level pairs ----------------------------------------------------------------------


def face_forward(dev: Device, V: cla.Array, F: cla.Array, unit: bool = True, real=np.float32) -> cla.Array:
    """``[M, 3]`` face normals (``unit``) or cross products of device arrays ``V [N, 3]``, ``F [M, 3]``."""
    M = F.shape[0]
    out = empty(dev.queue, (M, 3), real)
    k = dev.kernel("normals", "face_normals_fwd", real=real)
    _run(dev, k, M, V.data, F.data, np.int32(M), np.int32(unit), out.data)
    return out


def face_backward(dev: Device, V: cla.Array, F: cla.Array, v_n: cla.Array, offsets: cla.Array,
                  corners: cla.Array, unit: bool = True, real=np.float32,
                  corners_are_vertices: bool = False) -> cla.Array:
    """``v_V [N, 3]`` from ``v_n [M, 3]`` (adjoint of the unit normal when ``unit``, else of the cross).
    ``corners_are_vertices`` (``DeviceMesh.corners_are_vertices``: face f on vertices 3f … 3f + 2):
    the per-corner adjoints are the per-vertex ones, the gather is skipped."""
    N, M = V.shape[0], F.shape[0]
    v_corner = empty(dev.queue, (M, 3, 3), real)
    k = dev.kernel("normals", "face_normals_bwd", real=real)
    _run(dev, k, M, V.data, F.data, np.int32(M), np.int32(unit), v_n.data, v_corner.data)
    if corners_are_vertices and N == 3 * M:
        return v_corner.reshape(N, 3)
    v_V = empty(dev.queue, (N, 3), real)
    k = dev.kernel("normals", "corner_gather", real=real)
    _run(dev, k, N, offsets.data, corners.data, np.int32(N), v_corner.data, v_V.data)
    return v_V


def vertex_forward(dev: Device, V: cla.Array, F: cla.Array, offsets: cla.Array, corners: cla.Array,
                   real=np.float32) -> cla.Array:
    """``[N, 3]`` area-weighted unit vertex normals."""
    N = V.shape[0]
    fc = face_forward(dev, V, F, unit=False, real=real)
    out = empty(dev.queue, (N, 3), real)
    k = dev.kernel("normals", "vertex_normals_fwd", real=real)
    _run(dev, k, N, fc.data, offsets.data, corners.data, np.int32(N), out.data)
    return out


def vertex_backward(dev: Device, V: cla.Array, F: cla.Array, v_n: cla.Array, offsets: cla.Array,
                    corners: cla.Array, real=np.float32) -> cla.Array:
    """``v_V [N, 3]`` from the adjoint ``v_n [N, 3]`` of the vertex normals."""
    N, M = V.shape[0], F.shape[0]
    fc = face_forward(dev, V, F, unit=False, real=real)
    v_s = empty(dev.queue, (N, 3), real)
    k = dev.kernel("normals", "vertex_normals_bwd", real=real)
    _run(dev, k, N, fc.data, offsets.data, corners.data, np.int32(N), v_n.data, v_s.data)
    v_c = empty(dev.queue, (M, 3), real)
    k = dev.kernel("normals", "face_gather_vertex", real=real)
    _run(dev, k, M, F.data, np.int32(M), v_s.data, v_c.data)
    return face_backward(dev, V, F, v_c, offsets, corners, unit=False, real=real)


# ---- validating public functions -------------------------------------------------------------


def _prep(V, F, device, real):
    dev = device or get_device()
    V = check_real("V", V, (None, 3), real)
    F = check_faces("F", F, V.shape[0])
    q = dev.queue
    if V.size == 0 or F.size == 0:  # nothing to launch; callers return zeros
        return dev, V, F, None, None
    return dev, V, F, to_device(q, V), to_device(q, F)


def face_normals(V, F, *, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Unit face normals.

    Args:
        V: ``[N, 3]`` vertex positions.  F: ``[M, 3]`` integer vertex indices (counter-clockwise
        faces give normals by the right-hand rule).
    Returns:
        ``[M, 3]`` unit normals (zero for degenerate faces), dtype ``real``.
    """
    dev, V, F, Vd, Fd = _prep(V, F, device, real)
    if Fd is None:
        return np.zeros((F.shape[0], 3), real)
    return to_host(face_forward(dev, Vd, Fd, True, real))


def face_normals_backward(V, F, v_n, *, csr=None, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Adjoint of :func:`face_normals`: ``v_n [M, 3]`` → ``v_V [N, 3]``.

    ``csr`` is ``vertex_corner_csr(F, N)`` (built here when omitted; pass it to reuse it).
    """
    dev, V, F, Vd, Fd = _prep(V, F, device, real)
    v_n = check_real("v_n", v_n, (F.shape[0], 3), real)
    if Fd is None:
        return np.zeros((V.shape[0], 3), real)
    off, cor = _csr_device(dev, F, V.shape[0], csr)
    return to_host(face_backward(dev, Vd, Fd, to_device(dev.queue, v_n), off, cor, True, real))


def vertex_normals(V, F, *, csr=None, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Area-weighted unit vertex normals ``normalize(sum_f (v1 - v0) x (v2 - v0))``.

    Args:
        V: ``[N, 3]``.  F: ``[M, 3]``.  csr: optional ``vertex_corner_csr(F, N)``.
    Returns:
        ``[N, 3]`` (zero for vertices without faces or with a vanishing sum).
    """
    dev, V, F, Vd, Fd = _prep(V, F, device, real)
    if Fd is None:
        return np.zeros((V.shape[0], 3), real)
    off, cor = _csr_device(dev, F, V.shape[0], csr)
    return to_host(vertex_forward(dev, Vd, Fd, off, cor, real))


def vertex_normals_backward(V, F, v_n, *, csr=None, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Adjoint of :func:`vertex_normals`: ``v_n [N, 3]`` → ``v_V [N, 3]``."""
    dev, V, F, Vd, Fd = _prep(V, F, device, real)
    v_n = check_real("v_n", v_n, (V.shape[0], 3), real)
    if Fd is None:
        return np.zeros((V.shape[0], 3), real)
    off, cor = _csr_device(dev, F, V.shape[0], csr)
    return to_host(vertex_backward(dev, Vd, Fd, to_device(dev.queue, v_n), off, cor, real))
