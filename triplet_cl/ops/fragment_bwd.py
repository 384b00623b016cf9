"""The adjoint of the fragments (``kernels_cl/fragment_bwd.cl``): one backward pass over a view's
fragments for the interpolated attributes, the perspective-correct barycentrics, the depth and the
coverage window, and the per-vertex gathers of per-entry and per-corner adjoints.

Adjoints that land on vertices are never accumulated with float atomics (PoCL and many GPUs have
none): ``fragment_bwd`` runs one work-item per tile, owns the partial sums of that tile's (tile,
face) entries (:mod:`~triplet_cl.ops.binning`), and ``gather_vertex`` sums the entries of every face
corner of each vertex. Every sum happens in a fixed order, so gradients are bit-for-bit
deterministic.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .binning import TILE
from .common import check_real, device_empty, device_rows, grid_1d, launch, to_device
from .fragments import Fragments, frag_input
from .mesh import DeviceMesh

MOMENTS = 16  # REALs of geometric adjoint moments per entry (fragment_bwd.cl)


def gather_to_vertices(device: Device, frags: Fragments, entry_hit: cla.Array, partial_a: cla.Array | None,
                       Ca: int, partial_b: cla.Array | None = None, Cb: int = 0,
                       a_layout: tuple[int, int] | None = None, b_layout: tuple[int, int] | None = None):
    """Sum per-entry partial adjoints ``[E, 3, Ca]`` (and ``[E, 3, Cb]``) to vertices ``[N, Ca]``
    (``[N, Cb]``) in one pass (deterministic, no atomics); entries with ``entry_hit [E] == 0`` (no
    fragments: their partials were never written) are skipped. ``a_layout = (stride, offset)``: entry
    e's ``[3, Ca]`` block of ``partial_a`` starts at ``e · stride + offset`` (default ``(3 Ca, 0)``), and
    likewise ``b_layout``.
    Returns ``(out_a, out_b)`` (None for an absent array)."""
    mesh = frags.mesh
    n = mesh.num_vertices
    q = device.queue
    out_a = device_empty(q, (max(n, 1), max(Ca, 1)), frags.real, allocator=device.allocator)[:n, :Ca] if Ca else None
    out_b = device_empty(q, (max(n, 1), max(Cb, 1)), frags.real, allocator=device.allocator)[:n, :Cb] if Cb else None
    if n and (Ca or Cb):
        (a_stride, a_off), (b_stride, b_off) = a_layout or (3 * Ca, 0), b_layout or (3 * Cb, 0)
        launch(device, "fragment_bwd", "gather_vertex", *grid_1d(n), defines={"TILE": TILE}, real=frags.real,
               partial_a=partial_a, partial_b=partial_b, entry_hit=entry_hit, face_off=frags.face_off,
               face_entries=frags.face_entries, csr_off=mesh.csr_off, csr_corner=mesh.csr_corner, n=n, Ca=Ca, Cb=Cb,
               a_stride=a_stride, a_off=a_off, b_stride=b_stride, b_off=b_off, out_a=out_a, out_b=out_b)
    return out_a, out_b


def corners_to_vertices(device: Device, mesh: DeviceMesh, corner_a: cla.Array, corner_b: cla.Array):
    """Per-face-corner adjoints ``[M, 3, Ca]`` and ``[M, 3, Cb]`` summed per vertex: ``([N, Ca], [N, Cb])``
    (deterministic, no atomics). A mesh whose corners are its vertices (a soup with face f on
    vertices 3f, 3f + 1, 3f + 2: ``mesh.corners_are_vertices``) returns the same data reshaped."""
    n, M = mesh.num_vertices, mesh.num_faces
    Ca, Cb = corner_a.shape[-1], corner_b.shape[-1]
    if mesh.corners_are_vertices:
        return corner_a.reshape(n, Ca), corner_b.reshape(n, Cb)
    real = corner_a.dtype
    out_a = device_rows(device, (n, Ca), real)
    out_b = device_rows(device, (n, Cb), real)
    if n:
        if M == 0:
            out_a.fill(0)
            out_b.fill(0)
        else:
            launch(device, "fragment_bwd", "gather_corner", *grid_1d(n), defines={"TILE": TILE}, real=real,
                   corner_a=corner_a, corner_b=corner_b, csr_off=mesh.csr_off, csr_corner=mesh.csr_corner, n=n,
                   Ca=Ca, Cb=Cb, out_a=out_a, out_b=out_b)
    return out_a, out_b


#: the attribute channels one at a time in ``fragment_bwd`` (the reference the vector chunks are tested against
#: bit for bit: ``tests/test_raster.py``); False, the default: eight, four and two at a time
SCALAR_CHANNELS = False
#: read the window's exp from the forward (``Fragments.win_ex``) where it is there; False: take it again in
#: ``fragment_bwd`` (the reference the stored one is tested against, ``tests/test_raster.py``)
USE_WIN_EX = True


def fragments_backward(device: Device, frags: Fragments, attr=None, v_attr_frag=None, v_bary=None,
                       v_depth=None, v_win=None, sigma: float = 0.0, geometry: bool = True,
                       want_sigma: bool = True):
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
        want_sigma: sum ``v_sigma`` (a read-back, so the host waits for the whole pass here); False
            returns 0.0 in its place and the host goes on queueing (the training loop does not use it).

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
    hit = device_empty(q, max(E, 1), np.int32, allocator=alloc)
    # the optional inputs and outputs are compile-time defines; their parameters exist only then
    opt = {}
    if C:
        opt.update(attr=a, v_out=g, C=C, partial_attr=device_empty(q, (max(E, 1), 3, C), real, allocator=alloc))
    if vb is not None:
        opt["v_bary_in"] = vb
    if vd is not None:
        opt["v_depth"] = vd
    if vw is not None:
        opt["v_win"] = vw
    # the forward's exp of the window (Fragments.win_ex), where the window is the rasterizer's own (its sigma)
    win_ex = vw is not None and geometry and frags.win_ex is not None and sigma == frags.sigma and USE_WIN_EX
    if win_ex:
        opt["win_ex"] = frags.win_ex
    if geometry:
        opt.update(partial_mom=device_empty(q, (max(E, 1), MOMENTS), real, allocator=alloc),
                   v_sigma_tile=device_empty(q, T, real, allocator=alloc))
    else:
        opt["v_bary_out"] = device_empty(q, (max(frags.P, 1), 2), real, allocator=alloc)[:frags.P]
    defines = {"TILE": TILE, "ATTR": bool(C), "V_BARY_IN": vb is not None, "V_DEPTH": vd is not None,
               "V_WIN": vw is not None, "WIN_EX": win_ex, "GEOMETRY": bool(geometry),
               "SCALAR_CHANNELS": SCALAR_CHANNELS}
    launch(device, "fragment_bwd", "fragment_bwd", (T,), (1,), defines=defines, real=real,
           entry_setup=frags.entry_setup, F=frags.mesh.F, tile_off=frags.tile_off, frag_face=frags.face,
           frag_entry=frags.entry, frag_bary=frags.bary, frag_depth=frags.depth, frag_count=frags.count,
           frag_off=frags.off, sigma=sigma, width=W, height=H, tiles_x=frags.tiles_x, num_tiles=T, entry_hit=hit,
           **opt)
    p_attr = opt.get("partial_attr")
    p_geom = None
    if geometry:
        p_geom = device_empty(q, (max(E, 1), 3, 3), real, allocator=alloc)
        if E:
            launch(device, "fragment_bwd", "entry_geom", *grid_1d(E), defines={"TILE": TILE}, real=real,
                   vs=frags.vs, F=frags.mesh.F, entry_face=frags.entry_face, partial_mom=opt["partial_mom"],
                   entry_hit=hit, num_entries=E, partial_geom=p_geom)
    v_attr, v_vs = gather_to_vertices(device, frags, hit, p_attr, C, p_geom, 3 if geometry else 0)
    if not geometry:
        return v_attr, opt["v_bary_out"]
    v_sigma = float(opt["v_sigma_tile"].get().astype(np.float64).sum()) if vw is not None and want_sigma else 0.0
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


__all__ = ["MOMENTS", "corners_to_vertices", "fragments_backward", "gather_to_vertices", "raster_backward"]
