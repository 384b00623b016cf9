"""Faces binned into ``TILE``×``TILE`` screen tiles: the (tile, face) entries (``kernels_cl/binning.cl``).

Each face is counted into the tiles of its pixel bounding box with int atomics (counts → prefix
sums, :mod:`~triplet_cl.ops.scan` → per-tile entry lists), so each pixel of the list builders
(:func:`~triplet_cl.ops.raster.rasterize`, :func:`~triplet_cl.ops.blend.raster_blend`) tests only
the faces of its tile; each entry carries the face's edge-function set-up (``SETUP`` numbers), and
the face-major list of entries lets the atomics-free adjoints (:mod:`~triplet_cl.ops.fragment_bwd`)
sum per face in a fixed order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_empty, device_rows, grid_1d, launch, real_of, to_device
from .mesh import DeviceMesh
from .scan import prefix_offsets

TILE = 8
SETUP = 12  # REALs of edge-function set-up per (tile, face) entry (binning.cl)


@dataclass
class Binning:
    """Faces binned into ``TILE``×``TILE`` screen tiles: the (tile, face) "entries".

    Device arrays: ``tile_off [T+1]`` (entries of tile t: ``tile_off[t]:tile_off[t+1]``),
    ``entry_face [E]``, ``entry_setup [E, SETUP]`` (edge-function set-up, ``kernels_cl/binning.cl``),
    ``entry_rows [E]`` (bit r: row r of the tile has pixel centres inside the face's bounding box;
    bits 8 and up: the entry's estimated coverage in quarter pixels),
    ``entry_order [E]`` (the order in which the list builders visit each tile's entries: nearest
    first, bucketed, where the tile's lists fill up, else the binning's),
    ``face_off [M+1]`` / ``face_entries [E]`` (the entries of each face, for the adjoint gather).
    """

    width: int
    height: int
    tiles_x: int
    tiles_y: int
    num_entries: int
    tile_off: cla.Array
    face_off: cla.Array
    entry_face: cla.Array
    entry_setup: cla.Array
    face_entries: cla.Array
    entry_rows: cla.Array
    entry_order: cla.Array

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def check_soft_edges(soft_edges, num_faces: int):
    """Validate a per-face soft-edge bit mask ``[M]`` (bit k: edge k, opposite vertex k, has the window)."""
    if soft_edges is None:
        return None
    if isinstance(soft_edges, cla.Array):  # made on the device (ops/silhouette.py): 3-bit masks by construction
        if soft_edges.dtype != np.int32 or soft_edges.shape != (num_faces,):
            raise ValueError(f"soft_edges must be an int32 device array of shape [{num_faces}], got "
                             f"{soft_edges.dtype} {list(soft_edges.shape)}")
        return soft_edges
    m = np.asarray(soft_edges)
    if m.dtype.kind not in "iu" or m.shape != (num_faces,):
        raise ValueError(f"soft_edges must be an integer array of shape [{num_faces}], got {m.dtype} {list(m.shape)}")
    if m.size and (m.min() < 0 or m.max() > 7):
        raise ValueError(f"soft_edges values must be 3-bit masks in [0, 7], found [{m.min()}, {m.max()}]")
    return np.ascontiguousarray(m, np.int32)


def bin_faces(device: Device, vs: cla.Array, mesh: DeviceMesh, width: int, height: int,
              near: float = 0.01, far: float = 1000.0, cull_backface: bool = False, soft_edges=None,
              K: int = 1) -> Binning:
    """Bin the faces of projected vertices ``vs [N, 3]`` into screen tiles (culling as
    :func:`~triplet_cl.ops.raster.rasterize`).

    Used by :func:`~triplet_cl.ops.raster.rasterize`, :func:`~triplet_cl.ops.blend.raster_blend` and
    the ray tracer's packing: any renderer whose fragments need the atomics-free adjoint
    (:func:`~triplet_cl.ops.fragment_bwd.fragments_backward` sums per (tile, face) entry).
    ``soft_edges``: see :func:`~triplet_cl.ops.raster.rasterize`.
    ``K``: the list length the entries will be rasterized with (it sets ``entry_order``: tiles whose
    lists fill up are visited nearest first).
    """
    real = real_of(vs, "vs")
    q, alloc = device.queue, device.allocator
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    T = tiles_x * tiles_y
    M = mesh.num_faces
    defines = {"TILE": TILE}
    tile_count = cla.zeros(q, T, np.int32, allocator=alloc)
    face_ntiles = device_rows(device, M, np.int32)
    face_bbox = device_empty(q, (max(M, 1), 4), np.int32, allocator=alloc)
    if M:
        launch(device, "binning", "bin_count", *grid_1d(M), defines=defines, real=real,
               vs=vs, F=mesh.F, m=M, width=width, height=height, tiles_x=tiles_x, near=near, far=far,
               cull_back=bool(cull_backface), face_ntiles=face_ntiles, face_bbox=face_bbox, tile_count=tile_count)
    tile_off, E = prefix_offsets(device, tile_count)
    face_off, _ = prefix_offsets(device, face_ntiles, total=False)  # the same total E: no second read back
    device.check_alloc(E * SETUP * real.itemsize, f"binned face list ({E} tile-face entries)")
    entry_face = device_empty(q, max(E, 1), np.int32, allocator=alloc)
    # one spare row: the 16-lane kernels read each set-up 16 values wide (ops/blend.py)
    entry_setup = device_empty(q, (max(E, 1) + 1, SETUP), real, allocator=alloc)
    face_entries = device_empty(q, max(E, 1), np.int32, allocator=alloc)
    entry_rows = device_empty(q, max(E, 1), np.int32, allocator=alloc)
    entry_order = device_empty(q, max(E, 1), np.int32, allocator=alloc)
    soft = check_soft_edges(soft_edges, M)
    if E:
        tile_cursor = cla.zeros(q, T, np.int32, allocator=alloc)
        soft_arg = {} if soft is None else {"soft_edges": to_device(q, soft)}
        launch(device, "binning", "bin_fill", *grid_1d(M), defines={**defines, "SOFT_EDGES": soft is not None},
               real=real, vs=vs, F=mesh.F, m=M, tiles_x=tiles_x, height=height, face_ntiles=face_ntiles,
               face_bbox=face_bbox, face_off=face_off, tile_off=tile_off, tile_cursor=tile_cursor,
               entry_face=entry_face, entry_setup=entry_setup, entry_rows=entry_rows, face_entries=face_entries,
               **soft_arg)
        launch(device, "binning", "bin_depth_order", *grid_1d(T), defines=defines, real=real,
               tile_off=tile_off, entry_setup=entry_setup, entry_rows=entry_rows, num_tiles=T, K=K,
               entry_order=entry_order)
    return Binning(width, height, tiles_x, tiles_y, E, tile_off, face_off, entry_face, entry_setup, face_entries,
                   entry_rows, entry_order)


__all__ = ["SETUP", "TILE", "Binning", "bin_faces", "check_soft_edges"]
