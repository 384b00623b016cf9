"""Projection, tile binning, K-nearest fragments, and the adjoint of the fragment geometry.

Kernels: ``kernels_cl/project.cl`` and ``kernels_cl/raster.cl`` (formulas at the top of each).

Design (chosen for CPUs through PoCL, correct on every OpenCL 1.2 device):

* faces are binned into 8×8-pixel tiles with int atomics (counts → prefix sums with
  ``pyopencl.scan`` → per-tile face lists), so each pixel tests only the faces of its tile;
* the forward pass keeps the K nearest fragments of each pixel sorted by (depth, face id) in
  private memory: one work-item per pixel in 8×8 work-groups on GPUs; on CPUs one work-item per two
  tile rows, the 16 pixels as vector lanes with a lane-wise insertion (``raster_fwd_rows16``:
  PoCL does not vectorise across work-items), identical results;
* the lists are then packed (:class:`Fragments`): every per-fragment array is ``[P, C]``, pixel
  after pixel, nearest first, so memory follows the fragments (not H·W·K) and per-fragment passes
  stream through memory;
* adjoints that land on vertices are never accumulated with float atomics (PoCL and many GPUs have
  none): a backward kernel runs one work-item per tile, owns the partial sums of that tile's
  (tile, face) entries, and a gather kernel sums the entries of every face corner of each vertex.
  Every sum happens in a fixed order, so gradients are bit-for-bit deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import InclusiveScanKernel

from ..camera import Camera
from ..device import Device
from .common import buf, check_real, check_shape, const_array, fragment_array, grid_1d, to_device
from .mesh import DeviceMesh

TILE = 8
K_LIMIT = 1024
SETUP = 12  # REALs of edge-function set-up per (tile, face) entry (raster.cl)
MOMENTS = 16  # REALs of geometric adjoint moments per entry (fragment_bwd.cl)


def _real_of(a) -> np.dtype:
    dt = np.dtype(a.dtype)
    if dt not in (np.float32, np.float64):
        raise ValueError(f"expected float32 or float64 data, got {dt}")
    return dt


def camera_params(camera: Camera, real=np.float32) -> np.ndarray:
    """The 16 numbers the kernels read: R (row-major), t, fx, fy, cx, cy."""
    w = camera.w2c
    return np.concatenate([w[:3, :3].reshape(-1), w[:3, 3], [camera.fx, camera.fy, camera.cx, camera.cy]]).astype(real)


def _cam_buffer(device: Device, camera: Camera, real) -> cla.Array:
    return const_array(device, camera_params(camera, real))


# ------------------------------------------------------------------------------------------------
# project
# ------------------------------------------------------------------------------------------------


def project(device: Device, V, camera: Camera) -> cla.Array:
    """Project world vertices to screen.

    Args:
        V: ``[N, 3]`` world positions (numpy or device array; float32 or float64 selects REAL).
        camera: the :class:`~triplet_cl.camera.Camera`.

    Returns:
        ``vs [N, 3]`` device array of (u, v, z): pixel coordinates and camera-space depth.
    """
    real = _real_of(V) if hasattr(V, "dtype") and np.dtype(V.dtype).kind == "f" else np.float32
    V = check_real("V", V, (None, 3), real)
    n = V.shape[0]
    Vd = to_device(device.queue, V)
    vs = cla.empty(device.queue, (max(n, 1), 3), real, allocator=device.allocator)[:n]
    if n:
        k = device.kernel("project", "project_fwd", real=real)
        k(device.queue, *grid_1d(n), Vd.data, _cam_buffer(device, camera, real).data, np.int32(n), vs.data)
    return vs


def project_backward(device: Device, V, camera: Camera, v_vs, pose_grad: bool = False):
    """Adjoint of :func:`project`.

    Args:
        V: ``[N, 3]`` world positions (as given to :func:`project`).
        v_vs: ``[N, 3]`` adjoint of (u, v, z).
        pose_grad: also return the adjoint of the world-to-camera matrix.

    Returns:
        ``v_V [N, 3]`` device array, and with ``pose_grad`` also ``v_w2c [4, 4]`` numpy (float64;
        only the top 3×4 block is non-zero).
    """
    real = _real_of(V)
    V = check_real("V", V, (None, 3), real)
    n = V.shape[0]
    check_shape("v_vs", v_vs, (n, 3))
    q = device.queue
    Vd, gd = to_device(q, V), to_device(q, np.asarray(v_vs, real) if not isinstance(v_vs, cla.Array) else v_vs)
    v_V = cla.empty(q, (max(n, 1), 3), real, allocator=device.allocator)[:n]
    v_pc = cla.empty(q, (max(n, 1), 3), real, allocator=device.allocator)[:n]
    if n:
        k = device.kernel("project", "project_bwd", real=real)
        k(q, *grid_1d(n), Vd.data, _cam_buffer(device, camera, real).data, gd.data, np.int32(n), v_V.data, v_pc.data)
    if not pose_grad:
        return v_V
    vp = v_pc.get().astype(np.float64)
    Vh = Vd.get().astype(np.float64)
    g = np.zeros((4, 4))
    g[:3, :3] = vp.T @ Vh
    g[:3, 3] = vp.sum(0)
    return v_V, g


# ------------------------------------------------------------------------------------------------
# binning + K-nearest fragments
# ------------------------------------------------------------------------------------------------


@dataclass
class Fragments:
    """The K nearest fragments of every pixel, packed, plus the binning the adjoint needs.

    Packed layout: pixel ``p = y * W + x`` has ``count[y, x]`` (≤ K) fragments, nearest first, at
    rows ``off[p] : off[p] + count[y, x]`` of every per-fragment array (``off`` the exclusive prefix
    sum of ``count``; ``P = off[H * W]`` fragments in all). Device arrays:
        face ``[P] int32``, bary ``[P, 2]`` perspective-correct (λ0, λ1; λ2 = 1 − λ0 − λ1),
        depth ``[P]`` camera-space depth, entry ``[P] int32`` (the (tile, face) entry of the
        fragment), count ``[H, W] int32``, off ``[H*W + 1] int32``; the binning: tile_off ``[T+1]``,
        face_off ``[M+1]``, face_entries ``[E]``, entry_setup ``[E, SETUP]``, entry_face ``[E]``.

    Every per-fragment array derived from them (interpolated attributes, windows, shaded colours,
    adjoints) is ``[P]`` or ``[P, C]`` in the same order. :meth:`to_hwk` / :meth:`from_hwk` convert
    host arrays to and from the padded ``[H, W, K, ...]`` view (tests, tools); :func:`read_fragments`
    gives host copies of the fragments in that view.
    """

    width: int
    height: int
    K: int
    tiles_x: int
    tiles_y: int
    num_entries: int
    real: np.dtype
    face: cla.Array
    entry: cla.Array
    bary: cla.Array
    depth: cla.Array
    count: cla.Array
    tile_off: cla.Array
    face_off: cla.Array
    face_entries: cla.Array
    vs: cla.Array
    mesh: DeviceMesh
    win: cla.Array | None = None  # [P] coverage window when rasterized with a sigma
    sigma: float | None = None
    entry_setup: cla.Array | None = None  # [E, SETUP] edge-function set-up of each entry (Binning)
    entry_face: cla.Array | None = None  # [E] face of each entry (Binning)
    soft_edges: bool = False  # the window covers only some edges (rasterize(soft_edges=...))
    off: cla.Array | None = None  # [H*W + 1] first row of each pixel's fragments
    P: int = 0  # number of fragments

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, K)``: the image and the most fragments a pixel may have."""
        return (self.height, self.width, self.K)

    def fshape(self, C: int | None = None) -> tuple[int, ...]:
        """Shape of a per-fragment array: ``(P,)`` or ``(P, C)``."""
        return (self.P,) if C is None else (self.P, C)

    def _slots(self) -> np.ndarray:
        """Host ``[P]``: the padded slot ``pixel * K + k`` of every packed row."""
        count = self.count.get().reshape(-1).astype(np.int64)
        off = self.off.get()[:-1].astype(np.int64)
        pix = np.repeat(np.arange(count.size), count)
        return pix * self.K + (np.arange(self.P) - off[pix])

    def to_hwk(self, x, fill=0) -> np.ndarray:
        """Host ``[P, ...]`` per-fragment values → ``[H, W, K, ...]`` (``fill`` in the empty slots)."""
        x = x.get() if isinstance(x, cla.Array) else np.asarray(x)
        if x.shape[0] != self.P:
            raise ValueError(f"expected a per-fragment array with {self.P} rows, got {list(x.shape)}")
        slot = self._slots()
        out = np.full((self.height * self.width * self.K,) + x.shape[1:], fill, dtype=x.dtype)
        out[slot] = x
        return out.reshape((self.height, self.width, self.K) + x.shape[1:])

    def from_hwk(self, x) -> np.ndarray:
        """Host ``[H, W, K, ...]`` padded values → ``[P, ...]`` (the valid slots, packed)."""
        x = np.asarray(x)
        if x.shape[:3] != self.shape:
            raise ValueError(f"expected an array of shape [{self.height}, {self.width}, {self.K}, ...], "
                             f"got {list(x.shape)}")
        slot = self._slots()
        return np.ascontiguousarray(x.reshape((-1,) + x.shape[3:])[slot])


def frag_input(device: Device, frags: Fragments, name: str, a, C: int | None = None, real=None) -> cla.Array | None:
    """A per-fragment input on the device: ``[P]`` / ``[P, C]`` (device or numpy), or a numpy array in the
    padded ``[H, W, K(, C)]`` view (packed here). ``None`` passes through. Shape and dtype are checked,
    values are not (a padded array may hold anything in its empty slots)."""
    if a is None:
        return None
    real = frags.real if real is None else np.dtype(real)
    shape = frags.fshape(C)
    if not isinstance(a, cla.Array):
        arr = np.asarray(a)
        if arr.ndim == len(shape) + 2 and arr.shape[:3] == frags.shape:
            a = frags.from_hwk(arr)
    return fragment_array(device.queue, name, a, shape, real)


def _scan_kernel(device: Device) -> InclusiveScanKernel:
    return device.cached(("scan", "int32-sum"), lambda: InclusiveScanKernel(device.ctx, np.int32, "a+b", neutral="0"))


SCAN_BLOCK = 4096  # counts per work-item of the CPU scan (kernels_cl/scan.cl) ...
SCAN_SERIAL = 1 << 18  # ... up to this many counts, one work-item


def _offsets(device: Device, counts: cla.Array, total: bool = True) -> tuple[cla.Array, int | None]:
    """Exclusive prefix sum as an ``[n+1]`` offsets array, and the total (one small blocking read
    back; ``total=False`` skips it and returns None). CPU devices: ``kernels_cl/scan.cl``; others:
    pyopencl's scan."""
    n = counts.shape[0]
    q, alloc = device.queue, device.allocator
    if n == 0:
        return cla.zeros(q, 1, np.int32, allocator=alloc), 0 if total else None
    if device.is_cpu:
        off = cla.empty(q, n + 1, np.int32, allocator=alloc)
        block = n if n <= SCAN_SERIAL else SCAN_BLOCK
        nb = -(-n // block)
        sums = cla.empty(q, nb, np.int32, allocator=alloc) if nb > 1 else off  # one block reads no sum
        args = (np.int32(n), np.int32(block), np.int32(nb))
        if nb > 1:
            device.kernel("scan", "scan_block_sums")(q, (nb,), (1,), counts.data, *args, sums.data)
            device.kernel("scan", "scan_block_offsets")(q, (1,), (1,), sums.data, np.int32(nb))
        device.kernel("scan", "scan_block_write")(q, (nb,), (1,), counts.data, *args, sums.data, off.data)
    else:
        off = cla.zeros(q, n + 1, np.int32, allocator=alloc)
        incl = cla.empty(q, n, np.int32, allocator=alloc)
        _scan_kernel(device)(counts, incl, queue=q)
        # off[1:] = incl  (a sliced array's .data would not carry the offset into the scan kernel)
        cl.enqueue_copy(q, off.data, incl.data, dst_offset=4, byte_count=4 * n)
    if not total:
        return off, None
    tail = np.empty(1, np.int32)
    cl.enqueue_copy(q, tail, off.data, src_offset=4 * n)
    return off, int(tail[0])


RASTER_VARIANTS = ("auto", "pixel", "rows", "rows16")
ROWS16_LOCAL = 4  # work-items (2-row pairs) per work-group of raster_fwd_rows16: one 8x8 tile
# raster_fwd_rows16 keeps its lists lane-wise (16 lanes x K slots x 12 bytes of private memory) and
# inserts back to front from the deepest hit lane (PoCL, 400², 100k faces: surface-like soup 2x
# faster than raster_fwd_rows at K = 1, 1.5x at K = 30; dense soup 1.4-1.6x at K = 60 and 150);
# above ROWS16_K_LIMIT the scalar rows kernel takes over (its lists are per pixel).
ROWS16_K_LIMIT = 256


@dataclass
class Binning:
    """Faces binned into ``TILE``×``TILE`` screen tiles: the (tile, face) "entries".

    Device arrays: ``tile_off [T+1]`` (entries of tile t: ``tile_off[t]:tile_off[t+1]``),
    ``entry_face [E]``, ``entry_setup [E, SETUP]`` (edge-function set-up, ``kernels_cl/raster.cl``),
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


def check_soft_edges(soft_edges, num_faces: int) -> np.ndarray | None:
    """Validate a per-face soft-edge bit mask ``[M]`` (bit k: edge k, opposite vertex k, has the window)."""
    if soft_edges is None:
        return None
    m = np.asarray(soft_edges)
    if m.dtype.kind not in "iu" or m.shape != (num_faces,):
        raise ValueError(f"soft_edges must be an integer array of shape [{num_faces}], got {m.dtype} {list(m.shape)}")
    if m.size and (m.min() < 0 or m.max() > 7):
        raise ValueError(f"soft_edges values must be 3-bit masks in [0, 7], found [{m.min()}, {m.max()}]")
    return np.ascontiguousarray(m, np.int32)


def bin_faces(device: Device, vs: cla.Array, mesh: DeviceMesh, width: int, height: int,
              near: float = 0.01, far: float = 1000.0, cull_backface: bool = False, soft_edges=None,
              K: int = 1) -> Binning:
    """Bin the faces of projected vertices ``vs [N, 3]`` into screen tiles (culling as :func:`rasterize`).

    Used by :func:`rasterize`, and by any renderer whose fragments need the atomics-free adjoint
    (:func:`fragments_backward` sums per (tile, face) entry). ``soft_edges``: see :func:`rasterize`.
    ``K``: the list length the entries will be rasterized with (it sets ``entry_order``: tiles whose
    lists fill up are visited nearest first).
    """
    real = _real_of(vs)
    q, alloc = device.queue, device.allocator
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    T = tiles_x * tiles_y
    M = mesh.num_faces
    defines = {"TILE": TILE}
    tile_count = cla.zeros(q, T, np.int32, allocator=alloc)
    face_ntiles = cla.empty(q, max(M, 1), np.int32, allocator=alloc)[:M]
    face_bbox = cla.empty(q, (max(M, 1), 4), np.int32, allocator=alloc)
    if M:
        device.kernel("raster", "bin_count", defines, real)(
            q, *grid_1d(M), vs.data, mesh.F.data, np.int32(M), np.int32(width), np.int32(height),
            np.int32(tiles_x), real.type(near), real.type(far), np.int32(bool(cull_backface)),
            face_ntiles.data, face_bbox.data, tile_count.data)
    tile_off, E = _offsets(device, tile_count)
    face_off, _ = _offsets(device, face_ntiles, total=False)  # the same total E: no second read back
    device.check_alloc(E * SETUP * real.itemsize, f"binned face list ({E} tile-face entries)")
    entry_face = cla.empty(q, max(E, 1), np.int32, allocator=alloc)
    # one spare row: the 16-lane kernels read each set-up 16 values wide (ops/blend.py)
    entry_setup = cla.empty(q, (max(E, 1) + 1, SETUP), real, allocator=alloc)
    face_entries = cla.empty(q, max(E, 1), np.int32, allocator=alloc)
    entry_rows = cla.empty(q, max(E, 1), np.int32, allocator=alloc)
    entry_order = cla.empty(q, max(E, 1), np.int32, allocator=alloc)
    soft = check_soft_edges(soft_edges, M)
    if E:
        tile_cursor = cla.zeros(q, T, np.int32, allocator=alloc)
        soft_d = to_device(q, soft) if soft is not None else None
        device.kernel("raster", "bin_fill", defines, real)(
            q, *grid_1d(M), vs.data, mesh.F.data, buf(soft_d, q), np.int32(soft is not None), np.int32(M),
            np.int32(tiles_x), np.int32(height), face_ntiles.data,
            face_bbox.data, face_off.data, tile_off.data, tile_cursor.data, entry_face.data,
            entry_setup.data, entry_rows.data, face_entries.data)
        device.kernel("raster", "bin_depth_order", defines, real)(
            q, *grid_1d(T), tile_off.data, entry_setup.data, entry_rows.data, np.int32(T), np.int32(K),
            entry_order.data)
    return Binning(width, height, tiles_x, tiles_y, E, tile_off, face_off, entry_face, entry_setup, face_entries,
                   entry_rows, entry_order)


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
        vs = to_device(device.queue, check_real("vs", vs, (mesh.num_vertices, 3), _real_of(np.asarray(vs))))
    check_shape("vs", vs, (mesh.num_vertices, 3))
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
            the window (``topology.silhouette_edges`` marks the silhouette of a connected mesh, so
            that its shared interior edges stay hard and open no seams); None: every edge (a soup).
    """
    if variant not in RASTER_VARIANTS:
        raise ValueError(f"variant must be one of {RASTER_VARIANTS}, got {variant!r}")
    if variant == "auto":
        variant = ("rows16" if K <= ROWS16_K_LIMIT else "rows") if device.is_cpu else "pixel"
    vs, width, height, K = check_raster_args(device, vs, mesh, width, height, K, near, far, sigma, variant)
    real = _real_of(vs)
    q, alloc = device.queue, device.allocator
    npx = width * height
    device.check_alloc(npx * K * 8 * (2 if real == np.float64 else 1), f"fragment buffers ({width}x{height}, K={K})")
    b = bin_faces(device, vs, mesh, width, height, near, far, cull_backface, soft_edges, K)
    tiles_x, tiles_y = b.tiles_x, b.tiles_y

    # the kernels write each pixel's list (entry, depth) into K-strided scratch; then it is packed
    s_entry = cla.empty(q, (height, width, K), np.int32, allocator=alloc)
    s_depth = cla.empty(q, (height, width, K), real, allocator=alloc)
    count = cla.empty(q, (height, width), np.int32, allocator=alloc)
    if variant == "rows16":
        kern, gsize, lsize = "raster_fwd_rows16", (tiles_x, tiles_y * TILE // 2), (1, ROWS16_LOCAL)
    elif variant == "rows":
        kern, gsize, lsize = "raster_fwd_rows", (tiles_x, tiles_y * TILE), (1, TILE)
    else:
        kern, gsize, lsize = "raster_fwd", (tiles_x * TILE, tiles_y * TILE), (TILE, TILE)
    device.kernel("raster", kern, {"TILE": TILE, "K_MAX": K}, real)(
        q, gsize, lsize, b.tile_off.data, b.entry_order.data, b.entry_face.data, b.entry_setup.data, b.entry_rows.data,
        np.int32(width), np.int32(height), np.int32(tiles_x), np.int32(K), real.type(far),
        s_entry.data, s_depth.data, count.data)
    off, P, out = _packed_arrays(device, count, real, bool(sigma))
    if P:
        device.kernel("raster", "pack_raster_fragments", {"TILE": TILE}, real)(
            q, (npx,), None, np.int32(width), np.int32(height), np.int32(K), real.type(sigma or 0.0), count.data,
            off.data, s_entry.data, s_depth.data, b.entry_face.data, b.entry_setup.data,
            *(buf(a, q) for a in out))
    face, entry, bary, depth, win = (None if a is None else a[:P] for a in out)
    return Fragments(width, height, K, tiles_x, tiles_y, b.num_entries, real, face, entry, bary, depth, count,
                     b.tile_off, b.face_off, b.face_entries, vs, mesh, win, sigma, b.entry_setup, b.entry_face,
                     soft_edges is not None, off, P)


def pack_fragment_lists(device: Device, count: cla.Array, K: int, face, entry, bary, depth, win=None):
    """Pack K-strided per-pixel lists (``[H, W, K(, 2)]``, the first ``count`` slots valid) into the
    :class:`Fragments` layout. Returns ``(off [H*W+1], P, face [P], entry [P], bary [P, 2], depth [P],
    win [P] or None)``."""
    q, real = device.queue, np.dtype(bary.dtype)
    npix = int(np.prod(count.shape))
    off, P, out = _packed_arrays(device, count, real, win is not None)
    if P:
        device.kernel("raster", "pack_fragments", {"TILE": TILE}, real)(
            q, (npix,), None, np.int32(npix), np.int32(K), count.data, off.data, face.data, entry.data, bary.data,
            depth.data, buf(win, q), np.int32(win is not None), *(buf(a, q) for a in out))
    face, entry, bary, depth, win = (None if a is None else a[:P] for a in out)
    return off, P, face, entry, bary, depth, win


def _packed_arrays(device: Device, count: cla.Array, real, with_win: bool):
    """Offsets of the packed layout (prefix sum of ``count``), ``P``, and the arrays a pack kernel fills:
    ``(face [P'], entry [P'], bary [P', 2], depth [P'], win [P'] or None)``, ``P' = max(P, 1)``."""
    q, alloc = device.queue, device.allocator
    off, P = _offsets(device, count.reshape(-1))
    n = max(P, 1)
    out = (cla.empty(q, n, np.int32, allocator=alloc), cla.empty(q, n, np.int32, allocator=alloc),
           cla.empty(q, (n, 2), real, allocator=alloc), cla.empty(q, n, real, allocator=alloc),
           cla.empty(q, n, real, allocator=alloc) if with_win else None)
    return off, P, out


def gather_to_vertices(device: Device, frags: Fragments, entry_hit: cla.Array, partial_a: cla.Array | None,
                       Ca: int, partial_b: cla.Array | None = None, Cb: int = 0, a_layout: tuple[int, int] | None = None,
                       b_layout: tuple[int, int] | None = None):
    """Sum per-entry partial adjoints ``[E, 3, Ca]`` (and ``[E, 3, Cb]``) to vertices ``[N, Ca]``
    (``[N, Cb]``) in one pass (deterministic, no atomics); entries with ``entry_hit [E] == 0`` (no
    fragments: their partials were never written) are skipped. ``a_layout = (stride, offset)``: entry
    e's ``[3, Ca]`` block of ``partial_a`` starts at ``e · stride + offset`` (default ``(3 Ca, 0)``), and
    likewise ``b_layout``.
    Returns ``(out_a, out_b)`` (None for an absent array)."""
    mesh = frags.mesh
    n = mesh.num_vertices
    q = device.queue
    out_a = cla.empty(q, (max(n, 1), max(Ca, 1)), frags.real, allocator=device.allocator)[:n, :Ca] if Ca else None
    out_b = cla.empty(q, (max(n, 1), max(Cb, 1)), frags.real, allocator=device.allocator)[:n, :Cb] if Cb else None
    if n and (Ca or Cb):
        device.kernel("raster", "gather_vertex", {"TILE": TILE}, frags.real)(
            q, *grid_1d(n), buf(partial_a, q), buf(partial_b, q), entry_hit.data, frags.face_off.data,
            frags.face_entries.data, mesh.csr_off.data, mesh.csr_corner.data, np.int32(n), np.int32(Ca),
            np.int32(Cb), *(np.int32(v) for v in (a_layout or (3 * Ca, 0))), *(np.int32(v) for v in (b_layout or (3 * Cb, 0))),
            buf(out_a, q), buf(out_b, q))
    return out_a, out_b


def corners_to_vertices(device: Device, mesh: DeviceMesh, corner_a: cla.Array, corner_b: cla.Array):
    """Per-face-corner adjoints ``[M, 3, Ca]`` and ``[M, 3, Cb]`` summed per vertex: ``([N, Ca], [N, Cb])``
    (deterministic, no atomics). A mesh whose corners are its vertices (a soup with face f on
    vertices 3f, 3f + 1, 3f + 2: ``mesh.corners_are_vertices``) returns the same data reshaped."""
    n, M = mesh.num_vertices, mesh.num_faces
    Ca, Cb = corner_a.shape[-1], corner_b.shape[-1]
    if mesh.corners_are_vertices:
        return corner_a.reshape(n, Ca), corner_b.reshape(n, Cb)
    q, real = device.queue, corner_a.dtype
    out_a = cla.empty(q, (max(n, 1), Ca), real, allocator=device.allocator)[:n]
    out_b = cla.empty(q, (max(n, 1), Cb), real, allocator=device.allocator)[:n]
    if n:
        if M == 0:
            out_a.fill(0)
            out_b.fill(0)
        else:
            device.kernel("raster", "gather_corner", {"TILE": TILE}, real)(
                q, *grid_1d(n), corner_a.data, corner_b.data, mesh.csr_off.data, mesh.csr_corner.data,
                np.int32(n), np.int32(Ca), np.int32(Cb), out_a.data, out_b.data)
    return out_a, out_b


def fragments_backward(device: Device, frags: Fragments, attr=None, v_attr_frag=None, v_bary=None,
                       v_depth=None, v_win=None, sigma: float = 0.0, geometry: bool = True):
    """The one backward pass over a view's fragments (``kernels_cl/fragment_bwd.cl``).

    Fuses the adjoints of :func:`~triplet_cl.ops.interpolate.interpolate` (one packed attribute
    array), of the perspective-correct barycentrics and depth, and of the coverage window.

    Args:
        frags: the :class:`Fragments` of the forward pass.
        attr: ``[N, C]`` per-vertex attributes that were interpolated, with ``v_attr_frag``
            ``[P, C]`` the adjoint of the interpolated values (or both None).
        v_bary: ``[P, 2]`` extra adjoint of (λ0, λ1) (λ2 = 1 − λ0 − λ1), or None.
        v_depth: ``[P]`` adjoint of the fragment depth, or None.
        v_win: ``[P]`` adjoint of the coverage window (``sigma`` its sharpness), or None.
        (Numpy inputs may also come in the padded ``[H, W, K, ...]`` view: :meth:`Fragments.from_hwk`.)
        geometry: carry the barycentric/depth/window adjoints on to the projected vertices;
            when False they are returned per fragment instead.

    Returns:
        ``geometry=True``: ``(v_attr [N, C] or None, v_vs [N, 3], v_sigma float)``;
        ``geometry=False``: ``(v_attr [N, C] or None, v_bary [P, 2])``. Device arrays.
    """
    H, W, K = frags.shape
    real = frags.real
    q, alloc = device.queue, device.allocator
    C = 0
    a = g = None
    if attr is not None:
        n = frags.mesh.num_vertices
        if isinstance(attr, cla.Array):
            if attr.ndim != 2 or attr.shape[0] != n:
                raise ValueError(f"attr must have shape [{n}, C], got {list(attr.shape)}")
            if attr.dtype != real:
                raise ValueError(f"attr must have dtype {real} (as the fragments), got {attr.dtype}")
            a = attr
        else:
            a = to_device(q, check_real("attr", attr, (n, None), real))
        C = a.shape[1]
        if v_attr_frag is None:
            raise ValueError("v_attr_frag is required with attr")
        g = frag_input(device, frags, "v_attr_frag", v_attr_frag, C)
    vb = frag_input(device, frags, "v_bary", v_bary, 2)
    vd = frag_input(device, frags, "v_depth", v_depth)
    vw = frag_input(device, frags, "v_win", v_win)
    T, E = frags.num_tiles, frags.num_entries
    if geometry and (frags.entry_setup is None or frags.entry_face is None):
        raise ValueError("the fragments carry no entry_setup/entry_face (Binning); the geometric adjoint needs them")
    hit = cla.empty(q, max(E, 1), np.int32, allocator=alloc)
    p_attr = cla.empty(q, (max(E, 1), 3, max(C, 1)), real, allocator=alloc) if C else None
    p_mom = cla.empty(q, (max(E, 1), MOMENTS), real, allocator=alloc) if geometry else None
    v_sig_tile = cla.empty(q, T, real, allocator=alloc) if geometry else None
    v_bary_out = None if geometry else cla.empty(q, (max(frags.P, 1), 2), real, allocator=alloc)[:frags.P]
    device.kernel("fragment_bwd", "fragment_bwd", {"TILE": TILE}, real)(
        q, (T,), (1,), buf(frags.entry_setup, q), frags.mesh.F.data, frags.tile_off.data, buf(frags.face, q),
        buf(frags.entry, q), buf(frags.bary, q), buf(frags.depth, q), frags.count.data, buf(a, q), buf(g, q),
        buf(vb, q), buf(vd, q), buf(vw, q),
        np.int32(C), np.int32(vb is not None), np.int32(vd is not None), np.int32(vw is not None),
        np.int32(bool(geometry)), real.type(sigma), np.int32(W), np.int32(H), np.int32(frags.tiles_x),
        np.int32(T), frags.off.data, hit.data, buf(p_attr, q), buf(p_mom, q), buf(v_sig_tile, q), buf(v_bary_out, q))
    p_geom = None
    if geometry:
        p_geom = cla.empty(q, (max(E, 1), 3, 3), real, allocator=alloc)
        if E:
            device.kernel("fragment_bwd", "entry_geom", {"TILE": TILE}, real)(
                q, *grid_1d(E), frags.vs.data, frags.mesh.F.data, frags.entry_face.data, p_mom.data, hit.data,
                np.int32(E), p_geom.data)
    v_attr, v_vs = gather_to_vertices(device, frags, hit, p_attr, C, p_geom, 3 if geometry else 0)
    if not geometry:
        return v_attr, v_bary_out
    v_sigma = float(v_sig_tile.get().astype(np.float64).sum()) if vw is not None else 0.0
    return v_attr, v_vs, v_sigma


def raster_backward(device: Device, frags: Fragments, v_bary=None, v_depth=None, v_win=None,
                    sigma: float = 0.0):
    """Adjoint of the fragment geometry (barycentrics, depth, coverage window) to projected vertices.

    Args:
        frags: the :class:`Fragments` of the forward pass.
        v_bary: ``[P, 2]`` adjoint of (λ0, λ1) (λ2 = 1 − λ0 − λ1), or None.
        v_depth: ``[P]`` adjoint of the fragment depth, or None.
        v_win: ``[P]`` adjoint of the coverage window, or None; ``sigma`` its sharpness.

    Returns:
        ``(v_vs [N, 3] device array, v_sigma float)``. :func:`fragments_backward` does this and the
        interpolation adjoint in one pass.
    """
    _, v_vs, v_sigma = fragments_backward(device, frags, v_bary=v_bary, v_depth=v_depth, v_win=v_win,
                                          sigma=sigma, geometry=True)
    return v_vs, v_sigma


def read_fragments(frags: Fragments) -> dict[str, np.ndarray]:
    """Host copies of the fragments in the padded ``[H, W, K, ...]`` view (tests, debugging, tools):
    face/entry −1 and zero barycentrics/depth in the empty slots; ``count [H, W]``."""
    out = {"face": frags.to_hwk(frags.face, -1), "bary": frags.to_hwk(frags.bary, 0),
           "depth": frags.to_hwk(frags.depth, 0), "entry": frags.to_hwk(frags.entry, -1), "count": frags.count.get()}
    return out


def valid_faces(frags: Fragments) -> np.ndarray:
    """``[H, W, K] int32`` face ids on the host, −1 beyond each pixel's count."""
    return frags.to_hwk(frags.face, -1)


__all__ = ["Binning", "Fragments", "TILE", "bin_faces", "camera_params", "check_raster_args", "check_soft_edges",
           "frag_input", "fragments_backward", "gather_to_vertices", "pack_fragment_lists", "project",
           "project_backward", "rasterize", "raster_backward", "read_fragments", "valid_faces"]
