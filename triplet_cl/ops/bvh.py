"""Bounding-volume hierarchy over a triangle soup: build (host) and refit (device, ``kernels_cl/bvh.cl``).

Design (measured in ``bench/raytrace.py``):

* **Build** = sort the faces by the 30-bit Morton code of their centroids
  (:func:`~triplet_cl.topology.morton_order`, numpy) and lay an implicit complete binary tree over
  the sorted list (heap order, ``P = 2^D`` leaves of ``ceil(M/P) ≤ leaf_size`` faces each). The
  tree's topology is implied by ``P``: no node links to build or store, and any OpenCL device
  traverses it without recursion and with a stack of at most ``D + 1`` entries. This is the "median
  split in Morton order" flavour of an LBVH; its quality is close to a Karras LBVH on the
  well-spread soups of the method, and the build costs one ``argsort``.
* **Refit** = leaf bounds from the current vertices, then one launch per level up to the root
  (the launch order is the synchronisation: no atomics, deterministic). Run it after every optimiser
  step (positions move, topology does not); rebuild (re-sort) when the topology changes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pyopencl.array as cla

from ..device import Device
from ..topology import morton_order
from .common import check_real, device_empty, grid_1d, real_of, to_device
from .mesh import DeviceMesh

LEAF_SIZE = 4
MAX_DEPTH = 30  # leaves <= 2^30: the traversal stack (trace.cl) holds MAX_DEPTH + 2 entries


@dataclass
class BVH:
    """A refittable hierarchy over the faces of a :class:`DeviceMesh`.

    Attributes:
        mesh: the topology it was built for.
        prim: ``[M] int32`` device array, face ids in leaf order (Morton order of the centroids).
        nodes: ``[2P - 1, 6]`` device array of node bounds (lo xyz, hi xyz) in heap order.
        num_leaves: ``P`` (a power of two); ``depth`` = log2 P.
        real: dtype of the bounds (that of the vertices given to :func:`refit`).
        build_ms / refit_ms: host wall-clock times of the last build (sort + upload) and refit.
    """

    mesh: DeviceMesh
    prim: cla.Array
    nodes: cla.Array
    num_leaves: int
    depth: int
    real: np.dtype
    build_ms: float = 0.0
    refit_ms: float = 0.0
    stats: dict = field(default_factory=dict)

    @property
    def num_nodes(self) -> int:
        return 2 * self.num_leaves - 1


def _num_leaves(M: int, leaf_size: int) -> int:
    need = max(1, -(-M // leaf_size))
    P = 1 << int(np.ceil(np.log2(need))) if need > 1 else 1
    if P > (1 << MAX_DEPTH):
        raise ValueError(f"too many faces for the BVH ({M}; at most {leaf_size << MAX_DEPTH})")
    return P


def build_bvh(device: Device, V, mesh: DeviceMesh, leaf_size: int = LEAF_SIZE) -> BVH:
    """Build the hierarchy for ``mesh`` at positions ``V`` and refit it.

    Args:
        V: ``[N, 3]`` vertex positions (numpy, or a device array); float32 or float64 (bounds dtype).
        mesh: the :class:`DeviceMesh` (faces).
        leaf_size: most faces per leaf (≥ 1).

    Returns:
        a :class:`BVH` (bounds already fitted to ``V``).
    """
    if not (isinstance(leaf_size, int | np.integer) and leaf_size >= 1):
        raise ValueError(f"leaf_size must be a positive integer, got {leaf_size!r}")
    real = real_of(V, "V") if hasattr(V, "dtype") else np.dtype(np.float64)
    t0 = time.perf_counter()
    Vh = V.get() if isinstance(V, cla.Array) else check_real("V", V, (mesh.num_vertices, 3), real)
    if Vh.shape != (mesh.num_vertices, 3):
        raise ValueError(f"V must have shape [{mesh.num_vertices}, 3], got {list(Vh.shape)}")
    M = mesh.num_faces
    order = morton_order(Vh[mesh.faces].mean(axis=1)) if M else np.zeros(0, np.int64)
    P = _num_leaves(M, int(leaf_size))
    q = device.queue
    prim = cla.to_device(q, order.astype(np.int32) if M else np.zeros(1, np.int32))
    nodes = device_empty(q, (2 * P - 1, 6), real, allocator=device.allocator)
    bvh = BVH(mesh, prim, nodes, P, int(round(np.log2(P))), np.dtype(real))
    bvh.build_ms = (time.perf_counter() - t0) * 1e3
    refit(device, bvh, V if isinstance(V, cla.Array) else Vh)
    return bvh


def refit(device: Device, bvh: BVH, V) -> None:
    """Recompute every node's bounds for new positions ``V [N, 3]`` (same topology), on the device.

    ``V``'s dtype must be the BVH's (``bvh.real``). Bottom-up, one launch per level, no atomics.
    """
    t0 = time.perf_counter()
    m = bvh.mesh
    if isinstance(V, cla.Array):
        if V.shape != (m.num_vertices, 3) or V.dtype != bvh.real:
            raise ValueError(f"V must be a [{m.num_vertices}, 3] {bvh.real} device array, got "
                             f"{list(V.shape)} {V.dtype}")
        Vd = V
    else:
        Vd = to_device(device.queue, check_real("V", V, (m.num_vertices, 3), bvh.real))
    q, P = device.queue, bvh.num_leaves
    device.kernel("bvh", "bvh_leaf_bounds", real=bvh.real)(
        q, *grid_1d(P), Vd.data, m.F.data, bvh.prim.data, np.int32(m.num_faces), np.int32(P), bvh.nodes.data)
    k = device.kernel("bvh", "bvh_level_bounds", real=bvh.real)
    for level in range(bvh.depth - 1, -1, -1):
        first, count = (1 << level) - 1, 1 << level
        k(q, *grid_1d(count), np.int32(first), np.int32(count), bvh.nodes.data)
    q.finish()
    bvh.refit_ms = (time.perf_counter() - t0) * 1e3


__all__ = ["BVH", "LEAF_SIZE", "build_bvh", "refit"]
