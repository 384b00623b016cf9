"""The fused raster path for per-vertex attributes (``kernels_cl/blend.cl``).

``raster_blend`` computes in one kernel what :func:`~triplet_cl.ops.raster.rasterize` →
:func:`~triplet_cl.ops.interpolate.interpolate` → :func:`~triplet_cl.ops.composite.coverage` →
:func:`~triplet_cl.ops.composite.composite` compute when a fragment's colour and opacity are
interpolated per-vertex values, and ``raster_blend_backward`` its whole adjoint in one pass over
the tiles (then one pass over the faces, and for meshes with shared vertices a per-vertex gather).
No packed fragment array is written in between: on a CPU the generic chain spends most of its time
writing and re-reading per-fragment arrays.

Two kernel shapes with the same arithmetic: ``rows16`` (CPU: the 16 pixels of two tile rows in
vector lanes, per-entry data loaded as rows and transposed in registers; C ≤ 4) and ``pixel``
(GPU-shaped, scalar per pixel, any C ≤ 64). ``variant="auto"`` takes rows16 on CPUs where it applies.

Use it for unlit / emissive vertex colours, per-vertex radiance, depth or any feature image, and
the opaque K = 1 job; deferred shading (a BRDF evaluated per fragment) uses the generic chain.
Both give the same images and gradients (tests/test_blend.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .binning import TILE, Binning, bin_faces
from .common import c_max, check_real, const_array, device_empty, fragment_array, grid_1d, launch, real_of, to_device
from .fragment_bwd import MOMENTS, corners_to_vertices
from .mesh import DeviceMesh
from .raster import ROWS16_K_LIMIT, ROWS16_LOCAL, check_raster_args

BLEND_VARIANTS = ("auto", "pixel", "rows16")
C_LIMIT = 64  # feature channels
# the 16-lane kernels keep an entry's partial sums in two 16-wide vectors: 16 moments, then
# [3, C + 1] (C <= 4: RGB + opacity, depth, ...); more channels take the per-pixel kernels.
ROWS16_C_LIMIT = 4


@dataclass
class Blend:
    """The forward state of :func:`raster_blend` (device arrays) that its adjoint reads.

    ``image [H, W, C]``, ``trans [H, W]`` (transmittance behind the composited fragments: the
    accumulated alpha is ``1 − trans``), ``n_contrib [H, W]`` (fragments composited), ``count
    [H, W]`` (fragments found, ≤ K); scratch ``s_entry``/``s_T [T·4, K, 16]`` (tile, row pair,
    slot, lane: ``kernels_cl/blend.cl``): the (tile, face) entry and the transmittance in front of
    each composited fragment (:meth:`entries` gives the entries as ``[H, W, K]``).
    """

    width: int
    height: int
    K: int
    C: int
    sigma: float | None
    real: np.dtype
    image: cla.Array
    trans: cla.Array
    n_contrib: cla.Array
    count: cla.Array
    binning: Binning
    vs: cla.Array
    mesh: DeviceMesh
    attr: cla.Array
    bg: cla.Array
    s_entry: cla.Array
    s_T: cla.Array
    s_ex: cla.Array  # [T·4, K, 16] exp(−σ d) of each composited fragment's window (σ set; else 1 element)
    variant: str = "rows16"  # the kernel shape of the forward, reused by the backward
    face_attr: cla.Array | None = None  # rows16: [M, 16] corner attributes per face

    def _from_lanes(self, s: np.ndarray) -> np.ndarray:
        """Host ``[T·4, K, 16]`` (or ``[T·4, 16]``) scratch layout → ``[H, W, K]`` (``[H, W]``)."""
        bn = self.binning
        k = s.shape[1:-1]
        s = s.reshape((bn.tiles_y, bn.tiles_x, 4) + k + (2, 8))
        s = s.transpose((0, 2, 3 + len(k), 1, 4 + len(k)) + tuple(range(3, 3 + len(k))))
        return s.reshape((bn.tiles_y * TILE, bn.tiles_x * TILE) + k)[:self.height, :self.width]

    def _to_lanes(self, a: np.ndarray) -> np.ndarray:
        """Host ``[H, W]`` per pixel → the scratch's ``[T·4, 16]`` lanes (padding pixels: 0)."""
        bn = self.binning
        p = np.zeros((bn.tiles_y * TILE, bn.tiles_x * TILE), a.dtype)
        p[:self.height, :self.width] = a
        return p.reshape(bn.tiles_y, 4, 2, bn.tiles_x, 8).transpose(0, 3, 1, 2, 4).reshape(-1, 16)

    def entries(self) -> np.ndarray:
        """Host ``[H, W, K] int32``: the (tile, face) entry of each composited fragment, −1 beyond
        ``n_contrib`` (tests, tools)."""
        s = self._from_lanes(self.s_entry.get().reshape(-1, self.K, 16))
        used = np.arange(self.K) < self.n_contrib.get()[..., None]
        return np.where(used, s, -1).astype(np.int32)

    def entry_reaching(self, q: float) -> np.ndarray:
        """Host ``[H, W] int32``: the (tile, face) entry of the first composited fragment behind which
        the accumulated alpha ``1 − T`` reaches ``q`` (in (0, 1)), −1 where it never does. ``T`` only
        decreases front to back, so that fragment is the one after those with ``1 − T_j < q``."""
        K = self.K
        n = self._to_lanes(self.n_contrib.get())  # [T·4, 16]
        trans = self._to_lanes(self.trans.get()).astype(np.float64)
        j = np.arange(1, K)[None, :, None]
        with np.errstate(all="ignore"):  # slots beyond n_contrib were never written (any bits)
            T = self.s_T.get().reshape(-1, K, 16)[:, 1:].astype(np.float64)  # T_j in front of fragment j ≥ 1
            before = ((1.0 - T < q) & (j < n[:, None, :])).sum(axis=1)
        e = np.take_along_axis(self.s_entry.get().reshape(-1, K, 16), before[:, None, :], axis=1)[:, 0]
        hit = (n > 0) & (1.0 - trans >= q)
        return self._from_lanes(np.where(hit, e, -1).astype(np.int32))

    def depth_of(self, entry) -> np.ndarray:
        """Host ``[H, W]``: the camera-space depth of the fragment of (tile, face) entry ``entry
        [H, W]`` (from :meth:`entries`) at each pixel centre, as the list builders compute it
        (``1 / Σ_k b_k / z_k`` from the entry's set-up, in REAL); 0 where ``entry < 0``."""
        e = np.asarray(entry)
        r = self.real.type
        hit = e >= 0
        out = np.zeros(e.shape, self.real)
        if not hit.any():
            return out
        s = self.binning.entry_setup.get()[e[hit]]  # [P, SETUP] of the hit pixels only (the set-up of
        y, x = np.nonzero(hit)                      # an unused entry may hold anything, even overflow)
        dx = (x.astype(self.real) + r(0.5)) - s[:, 0]
        dy = (y.astype(self.real) + r(0.5)) - s[:, 1]
        b0 = r(1) + s[:, 2] * dx + s[:, 3] * dy
        b1 = s[:, 4] * dx + s[:, 5] * dy
        b2 = r(1) - b0 - b1
        with np.errstate(divide="ignore", invalid="ignore"):
            out[hit] = r(1) / (b0 * s[:, 6] + b1 * s[:, 7] + b2 * s[:, 8])
        return out

    @property
    def alpha(self) -> np.ndarray:
        """Host ``[H, W]`` accumulated alpha ``1 − trans``."""
        return 1.0 - self.trans.get()


def _device_attr(device: Device, attr, n: int, real) -> cla.Array:
    if isinstance(attr, cla.Array):
        if attr.ndim != 2 or attr.shape[0] != n:
            raise ValueError(f"attr must have shape [{n}, C + 1] (features, then opacity), got {list(attr.shape)}")
        if attr.dtype != real:
            raise ValueError(f"attr must have dtype {real} (as vs), got {attr.dtype}")
        if not attr.flags.c_contiguous:
            raise ValueError("attr must be C-contiguous")
        return attr
    return to_device(device.queue, check_real("attr", attr, (n, None), real))


def raster_blend(device: Device, vs, mesh: DeviceMesh, attr, width: int, height: int, K: int, bg=0.0,
                 sigma: float | None = None, soft_edges=None, t_min: float = 1e-4, near: float = 0.01,
                 far: float = 1000.0, cull_backface: bool = False, variant: str = "auto") -> Blend:
    """Per-vertex features and opacity, rasterized, interpolated and alpha-blended in one pass.

    Args:
        vs: ``[N, 3]`` projected vertices (u, v, z) from :func:`~triplet_cl.ops.raster.project`.
        mesh: the :class:`DeviceMesh`.
        attr: ``[N, C + 1]`` per vertex: C feature channels (1 ≤ C ≤ 64), then the opacity in
            [0, 1] (float32 or float64 as ``vs``; device arrays pass through).
        width, height, K: image size and fragments kept per pixel (1 ≤ K ≤ 1024).
        bg: ``[C]`` background (or a scalar).
        sigma, soft_edges: the soft-coverage window (see :func:`~triplet_cl.ops.raster.rasterize`);
            None: hard edges.
        t_min: compositing stops once the transmittance drops below it (0 disables).
        near, far, cull_backface: as :func:`~triplet_cl.ops.raster.rasterize`.
        variant: ``"rows16"`` (CPU-shaped: 16 pixels in vector lanes, K ≤ 256, C ≤ 4), ``"pixel"``
            (GPU-shaped: one work-item per pixel) or ``"auto"`` (rows16 on CPUs where it applies).

    Returns:
        :class:`Blend` (``.image [H, W, C]``, ``.trans [H, W]``, ...): the result of
        composite(interpolate(rasterize(...))) with the window of ``coverage``.
    """
    if variant not in BLEND_VARIANTS:
        raise ValueError(f"variant must be one of {BLEND_VARIANTS}, got {variant!r}")
    if not (0 <= t_min < 1):
        raise ValueError(f"t_min must be in [0, 1), got {t_min}")
    vs, width, height, K = check_raster_args(device, vs, mesh, width, height, K, near, far, sigma, variant)
    real = real_of(vs, "vs")
    a = _device_attr(device, attr, mesh.num_vertices, real)
    C = a.shape[1] - 1
    if not 1 <= C <= C_LIMIT:
        raise ValueError(f"attr must have C + 1 columns with 1 <= C <= {C_LIMIT} (features, then opacity), "
                         f"got {a.shape[1]} columns")
    if variant == "rows16" and C > ROWS16_C_LIMIT:
        raise ValueError(f"variant 'rows16' supports C <= {ROWS16_C_LIMIT} feature channels, got C={C}")
    if variant == "auto":
        variant = "rows16" if device.is_cpu and K <= ROWS16_K_LIMIT and C <= ROWS16_C_LIMIT else "pixel"
    b = np.asarray(bg, dtype=np.float64)
    if b.ndim > 1 or b.size not in (1, C):
        raise ValueError(f"bg must have shape [{C}] (or be a scalar), got {list(np.shape(bg))}")
    bgd = const_array(device, check_real("bg", np.broadcast_to(b, (C,)), (C,), real))
    q, alloc = device.queue, device.allocator
    tiles = -(-width // TILE) * -(-height // TILE)
    device.check_alloc(tiles * TILE * TILE * K * (4 + real.itemsize), f"fragment lists ({width}x{height}, K={K})")
    bn = bin_faces(device, vs, mesh, width, height, near, far, cull_backface, soft_edges, K)
    image = device_empty(q, (height, width, C), real, allocator=alloc)
    trans = device_empty(q, (height, width), real, allocator=alloc)
    n_contrib = device_empty(q, (height, width), np.int32, allocator=alloc)
    count = device_empty(q, (height, width), np.int32, allocator=alloc)
    s_entry = device_empty(q, (tiles * 4, K, 16), np.int32, allocator=alloc)
    s_T = device_empty(q, (tiles * 4, K, 16), real, allocator=alloc)
    s_ex = device_empty(q, (tiles * 4, K, 16) if sigma else (1,), real, allocator=alloc)
    if variant == "rows16":
        kern, gsize, lsize = "blend_fwd_rows16", (bn.tiles_x, bn.tiles_y * TILE // 2), (1, ROWS16_LOCAL)
        # the faces' corner attributes, read as rows by the 16-lane kernels
        M = mesh.num_faces
        face_attr = device_empty(q, (max(M, 1), 16), real, allocator=alloc)
        if M:
            launch(device, "blend", "blend_face_attr", *grid_1d(M), defines={"TILE": TILE}, real=real,
                   F=mesh.F, attr=a, C=C, num_faces=M, face_attr=face_attr)
        attr_args = {"face_attr": face_attr}
    else:
        kern, gsize, lsize = "blend_fwd", (bn.tiles_x * TILE, bn.tiles_y * TILE), (TILE, TILE)
        face_attr, attr_args = None, {"F": mesh.F, "attr": a}
    launch(device, "blend", kern, gsize, lsize, defines={"TILE": TILE, "K_MAX": K, "C_MAX": c_max(C)}, real=real,
           tile_off=bn.tile_off, entry_order=bn.entry_order, entry_face=bn.entry_face, entry_setup=bn.entry_setup,
           entry_rows=bn.entry_rows, bg=bgd, width=width, height=height, tiles_x=bn.tiles_x, K=K, far=far, C=C,
           sigma=sigma or 0.0, t_min=t_min, out=image, trans=trans, n_contrib=n_contrib, count=count,
           s_entry=s_entry, s_T=s_T, s_ex=s_ex, **attr_args)
    return Blend(width, height, K, C, sigma, real, image, trans, n_contrib, count, bn, vs, mesh, a, bgd,
                 s_entry, s_T, s_ex, variant, face_attr)


BWD_SCHEDULES = {"auto": 0, "rows": 1, "queue": 2}


def raster_blend_backward(device: Device, blend: Blend, v_image, v_alpha=None, schedule: str = "auto"):
    """Adjoint of :func:`raster_blend` for ``sum(image · v_image) + sum((1 − trans) · v_alpha)``.

    Args:
        blend: the :class:`Blend` of the forward pass.
        v_image: ``[H, W, C]`` adjoint of the image; v_alpha: optional ``[H, W]`` adjoint of the
            accumulated alpha.
        schedule: how the rows16 kernel walks a tile's pixels in its 16 lanes: ``"rows"`` (two
            tile rows at a time, all lanes at the same slot), ``"queue"`` (each lane takes the next
            pixel, longest lists first, when its own is done) or ``"auto"`` (per tile, the queue where
            it walks a fifth fewer slots). Same results up to rounding; ignored by ``pixel``.

    Returns:
        ``(v_attr [N, C + 1], v_vs [N, 3], v_sigma float)``: device arrays for the per-vertex
        features and opacity and the projected vertices (chain ``v_vs`` through
        :func:`~triplet_cl.ops.raster.project_backward`), and the window sharpness's adjoint (0
        without a window).
    """
    if schedule not in BWD_SCHEDULES:
        raise ValueError(f"schedule must be one of {tuple(BWD_SCHEDULES)}, got {schedule!r}")
    H, W, C, real = blend.height, blend.width, blend.C, blend.real
    q, alloc = device.queue, device.allocator
    g = fragment_array(q, "v_image", v_image, (H, W, C), real)
    va = fragment_array(q, "v_alpha", v_alpha, (H, W), real)
    bn = blend.binning
    T, E = bn.num_tiles, bn.num_entries
    CA = C + 1
    # per-entry records: the MOMENTS geometric moments, then [3, C + 1] (corner, attribute);
    # 32 per entry for the 16-lane kernel (its record is two transposed vectors: C <= 4)
    pstride = MOMENTS + 3 * CA
    if blend.variant == "rows16":
        assert pstride <= 32, "rows16 needs C <= 4"
        pstride = 32
    partial = device_empty(q, (max(E, 1), pstride), real, allocator=alloc)
    v_sig_tile = device_empty(q, T, real, allocator=alloc)
    kern = "blend_bwd_rows16" if blend.variant == "rows16" else "blend_bwd"
    # [M, 16] corner-attribute rows, or F and attr [N, C + 1]
    attr_args = {"face_attr": blend.face_attr} if blend.variant == "rows16" else {"F": blend.mesh.F, "attr": blend.attr}
    defines = {"TILE": TILE, "C_MAX": c_max(C)}
    if blend.variant == "rows16" and schedule != "auto":
        defines["BWD_SCHEDULE"] = BWD_SCHEDULES[schedule]
    launch(device, "blend", kern, (T,), (1,), defines={**defines, "V_ACC": va is not None}, real=real,
           tile_off=bn.tile_off, entry_face=bn.entry_face, entry_setup=bn.entry_setup, bg=blend.bg,
           n_contrib=blend.n_contrib, s_entry=blend.s_entry, s_T=blend.s_T, s_ex=blend.s_ex, v_out=g, C=C,
           K=blend.K, sigma=blend.sigma or 0.0, width=W, height=H, tiles_x=bn.tiles_x, num_tiles=T,
           pstride=pstride, partial=partial, v_sigma_tile=v_sig_tile, **attr_args,
           **({} if va is None else {"v_acc": va}))
    # per face: its entries' records summed, the moments turned into the screen-vertex adjoint
    # once, both per face corner; then per vertex
    mesh = blend.mesh
    M = mesh.num_faces
    v_attr_c = device_empty(q, (max(M, 1), 3, CA), real, allocator=alloc)[:M]
    v_vs_c = device_empty(q, (max(M, 1), 3, 3), real, allocator=alloc)[:M]
    if M:
        launch(device, "blend", "blend_face_grad", *grid_1d(M), defines=defines, real=real,
               face_off=bn.face_off, face_entries=bn.face_entries, partial=partial, pstride=pstride, vs=blend.vs,
               F=mesh.F, C=C, num_faces=M, v_attr_corner=v_attr_c, v_vs_corner=v_vs_c)
    v_attr, v_vs = corners_to_vertices(device, mesh, v_attr_c, v_vs_c)
    v_sigma = float(v_sig_tile.get().astype(np.float64).sum()) if blend.sigma else 0.0
    return v_attr, v_vs, v_sigma


__all__ = ["BLEND_VARIANTS", "BWD_SCHEDULES", "Blend", "raster_blend", "raster_blend_backward"]
