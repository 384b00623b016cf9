"""The K nearest fragments of every pixel (``kernels_cl/raster.cl``), packed.

This module was the one host module of the whole raster chain; it now fronts ``raster.cl`` only and
re-exports the public names of its neighbours, so ``triplet_cl.ops.raster`` keeps working:

* :mod:`~triplet_cl.ops.project`: ``project`` / ``project_backward`` (``project.cl``);
* :mod:`~triplet_cl.ops.binning`: ``bin_faces`` → :class:`Binning` (``binning.cl``), with
  :mod:`~triplet_cl.ops.scan` for the offsets (``scan.cl``);
* :mod:`~triplet_cl.ops.fragments`: the packed :class:`Fragments` (no kernel);
* :mod:`~triplet_cl.ops.fragment_bwd`: ``fragments_backward`` / ``raster_backward`` and the vertex
  gathers (``fragment_bwd.cl``).

Design (chosen for CPUs through PoCL, correct on every OpenCL 1.2 device):

* faces are binned into 8×8-pixel tiles (``bin_faces``), so each pixel tests only the faces of its
  tile;
* the forward pass keeps the K nearest fragments of each pixel sorted by (depth, face id) in
  private memory: one work-item per pixel in 8×8 work-groups on GPUs; on CPUs one work-item per two
  tile rows, the 16 pixels as vector lanes with a lane-wise insertion (``raster_fwd_rows16``:
  PoCL does not vectorise across work-items), identical results;
* the lists are then packed (:class:`Fragments`): every per-fragment array is ``[P, C]``, pixel
  after pixel, nearest first, so memory follows the fragments (not H·W·K) and per-fragment passes
  stream through memory;
* the adjoint (``fragments_backward``) sums per (tile, face) entry without float atomics.
"""

from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .binning import SETUP, TILE, Binning, bin_faces, check_soft_edges
from .common import (
    check_contiguous,
    check_real,
    check_shape,
    device_empty,
    device_head,
    grid_1d,
    launch,
    real_of,
    to_device,
)
from .fragment_bwd import MOMENTS, corners_to_vertices, fragments_backward, gather_to_vertices, raster_backward
from .fragments import Fragments, frag_input, read_fragments, valid_faces
from .mesh import DeviceMesh
from .project import camera_params, project, project_backward
from .scan import prefix_offsets

K_LIMIT = 1024
#: the coverage window computed inside ``pack_raster_fragments``'s per-pixel loop (the reference the separate
#: ``window_from_distance`` pass is tested against bit for bit: ``tests/test_raster.py``); False, the default
WINDOW_IN_PACK = False
RASTER_VARIANTS = ("auto", "pixel", "rows", "rows16")
ROWS16_LOCAL = 4  # work-items (2-row pairs) per work-group of raster_fwd_rows16: one 8x8 tile
# raster_fwd_rows16 keeps its lists lane-wise (16 lanes x K slots x 12 bytes of private memory) and
# inserts back to front from the deepest hit lane (PoCL, 400², 100k faces: surface-like soup 2x
# faster than raster_fwd_rows at K = 1, 1.5x at K = 30; dense soup 1.4-1.6x at K = 60 and 150);
# above ROWS16_K_LIMIT the scalar rows kernel takes over (its lists are per pixel).
ROWS16_K_LIMIT = 256


def check_raster_args(device: Device, vs, mesh: DeviceMesh, width, height, K, near, far, sigma, variant):
    """Validate the arguments shared by the rasterizers (:func:`rasterize`, ``ops.blend.raster_blend``);
    returns ``(vs as a device array [N, 3], width, height, K)``."""
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a finite positive number or None, got {sigma!r}")
    if variant == "rows16" and K > ROWS16_K_LIMIT:
        raise ValueError(f"variant 'rows16' supports K <= {ROWS16_K_LIMIT}, got K={K}")
    K = int(K)
    if not 1 <= K <= K_LIMIT:
        raise ValueError(f"K must be in [1, {K_LIMIT}], got {K}")
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ValueError(f"image size must be at least 1x1, got {width}x{height}")
    if not (0 < near < far):
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    if not isinstance(vs, cla.Array):
        vs = to_device(device.queue, check_real("vs", vs, (mesh.num_vertices, 3), real_of(np.asarray(vs), "vs")))
    check_shape("vs", vs, (mesh.num_vertices, 3))
    check_contiguous("vs", vs)
    return vs, width, height, K


def rasterize(device: Device, vs, mesh: DeviceMesh, width: int, height: int, K: int,
              near: float = 0.01, far: float = 1000.0, cull_backface: bool = False,
              variant: str = "auto", sigma: float | None = None, soft_edges=None) -> Fragments:
    """The K nearest fragments per pixel (discrete: no adjoint of its own; see :func:`raster_backward`).

    Args:
        vs: ``[N, 3]`` projected vertices (u, v, z) from :func:`project`.
        mesh: the :class:`DeviceMesh` (faces).
        width, height: image size in pixels; K: fragments kept per pixel (1 ≤ K ≤ 1024).
        near, far: depth range; faces with a vertex nearer than ``near`` are culled (not clipped).
        cull_backface: drop faces whose normal (right-hand rule) points away from the camera.
            Off by default: a triangle soup is seen from both sides.
        variant: ``"pixel"`` (one work-item per pixel: GPU-shaped), ``"rows"`` (one work-item per
            8-pixel row with vector edge tests: CPU-shaped), ``"rows16"`` (one work-item per two
            tile rows, the 16 pixels' lists in vector lanes with a vector insertion: CPU-shaped,
            K ≤ 256), or ``"auto"`` (on CPU devices rows16 up to K = 256, rows above; pixel on
            others). All give identical fragments.
        sigma: also compute the soft-coverage window (``frags.win``) for this sharpness, in the
            same pass (see :func:`~triplet_cl.ops.composite.coverage`).
        soft_edges: ``[M]`` int bit masks (bit k: edge k, opposite vertex k): only these edges get
            the window (``ops.silhouette.silhouette_bits`` marks the silhouette of a connected mesh, so
            that its shared interior edges stay hard and open no seams); None: every edge (a soup).
    """
    if variant not in RASTER_VARIANTS:
        raise ValueError(f"variant must be one of {RASTER_VARIANTS}, got {variant!r}")
    if variant == "auto":
        variant = ("rows16" if K <= ROWS16_K_LIMIT else "rows") if device.is_cpu else "pixel"
    vs, width, height, K = check_raster_args(device, vs, mesh, width, height, K, near, far, sigma, variant)
    real = real_of(vs, "vs")
    q, alloc = device.queue, device.allocator
    npx = width * height
    device.check_alloc(npx * K * 8 * (2 if real == np.float64 else 1), f"fragment buffers ({width}x{height}, K={K})")
    b = bin_faces(device, vs, mesh, width, height, near, far, cull_backface, soft_edges, K)
    tiles_x, tiles_y = b.tiles_x, b.tiles_y

    # the kernels write each pixel's list (entry, depth) into K-strided scratch; then it is packed
    s_entry = device_empty(q, (height, width, K), np.int32, allocator=alloc)
    s_depth = device_empty(q, (height, width, K), real, allocator=alloc)
    count = device_empty(q, (height, width), np.int32, allocator=alloc)
    if variant == "rows16":
        kern, gsize, lsize = "raster_fwd_rows16", (tiles_x, tiles_y * TILE // 2), (1, ROWS16_LOCAL)
    elif variant == "rows":
        kern, gsize, lsize = "raster_fwd_rows", (tiles_x, tiles_y * TILE), (1, TILE)
    else:
        kern, gsize, lsize = "raster_fwd", (tiles_x * TILE, tiles_y * TILE), (TILE, TILE)
    launch(device, "raster", kern, gsize, lsize, defines={"TILE": TILE, "K_MAX": K}, real=real,
           tile_off=b.tile_off, entry_order=b.entry_order, entry_face=b.entry_face, entry_setup=b.entry_setup,
           entry_rows=b.entry_rows, width=width, height=height, tiles_x=tiles_x, K=K, far=far,
           frag_entry=s_entry, frag_depth=s_depth, frag_count=count)
    off, P, out = _packed_arrays(device, count, real, bool(sigma))
    win_ex = None
    if P:
        win_in_pack = bool(sigma) and WINDOW_IN_PACK
        launch(device, "raster", "pack_raster_fragments", *grid_1d(npx),
               defines={"TILE": TILE, "WINDOW": bool(sigma), "WINDOW_IN_PACK": win_in_pack},
               real=real, width=width, height=height, K=K, sigma=sigma or 0.0, count=count, off=off,
               s_entry=s_entry, s_depth=s_depth, entry_face=b.entry_face, entry_setup=b.entry_setup,
               **_pack_outputs(out))
        if sigma and not win_in_pack:  # the packing wrote each fragment's soft-edge distance; the exp in vector lanes
            win_ex = device_empty(q, max(P, 1), real, allocator=alloc)
            launch(device, "raster", "window_from_distance", *grid_1d(P), defines={"TILE": TILE, "WINDOW": True},
                   real=real, P=P, sigma=sigma, win=out[4], win_ex=win_ex)
            win_ex = device_head(win_ex, P)
    face, entry, bary, depth, win = (None if a is None else device_head(a, P) for a in out)
    return Fragments(width, height, K, tiles_x, tiles_y, b.num_entries, real, face, entry, bary, depth, count,
                     b.tile_off, b.face_off, b.face_entries, vs, mesh, win, sigma, b.entry_setup, b.entry_face,
                     soft_edges is not None, off, P, win_ex)


def pack_fragment_lists(device: Device, count: cla.Array, K: int, face, entry, bary, depth, win=None):
    """Pack K-strided per-pixel lists (``[H, W, K(, 2)]``, the first ``count`` slots valid) into the
    :class:`Fragments` layout. Returns ``(off [H*W+1], P, face [P], entry [P], bary [P, 2], depth [P],
    win [P] or None)``."""
    real = np.dtype(bary.dtype)
    npix = int(np.prod(count.shape))
    off, P, out = _packed_arrays(device, count, real, win is not None)
    if P:
        inputs = {"s_face": face, "s_entry": entry, "s_bary": bary, "s_depth": depth}
        if win is not None:
            inputs["s_win"] = win
        launch(device, "raster", "pack_fragments", (npix,), None, defines={"TILE": TILE, "WINDOW": win is not None},
               real=real, npix=npix, K=K, count=count, off=off, **inputs, **_pack_outputs(out))
    face, entry, bary, depth, win = (None if a is None else device_head(a, P) for a in out)
    return off, P, face, entry, bary, depth, win


def _pack_outputs(out) -> dict:
    """The output arguments of the pack kernels from :func:`_packed_arrays`' arrays (``win`` only with WINDOW)."""
    face, entry, bary, depth, win = out
    return {"face": face, "entry": entry, "bary": bary, "depth": depth, **({} if win is None else {"win": win})}


def _packed_arrays(device: Device, count: cla.Array, real, with_win: bool):
    """Offsets of the packed layout (prefix sum of ``count``), ``P``, and the arrays a pack kernel fills:
    ``(face [P'], entry [P'], bary [P', 2], depth [P'], win [P'] or None)``, ``P' = max(P, 1)``."""
    q, alloc = device.queue, device.allocator
    off, P = prefix_offsets(device, count.reshape(-1))
    n = max(P, 1)
    out = (device_empty(q, n, np.int32, allocator=alloc), device_empty(q, n, np.int32, allocator=alloc),
           device_empty(q, (n, 2), real, allocator=alloc), device_empty(q, n, real, allocator=alloc),
           device_empty(q, n, real, allocator=alloc) if with_win else None)
    return off, P, out


__all__ = ["K_LIMIT", "MOMENTS", "RASTER_VARIANTS", "ROWS16_K_LIMIT", "ROWS16_LOCAL", "SETUP", "TILE",
           "Binning", "Fragments", "bin_faces", "camera_params", "check_raster_args", "check_soft_edges",
           "corners_to_vertices", "frag_input", "fragments_backward", "gather_to_vertices", "pack_fragment_lists",
           "project", "project_backward", "rasterize", "raster_backward", "read_fragments",
           "valid_faces"]
