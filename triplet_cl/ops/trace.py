"""Ray tracing over a :class:`~triplet_cl.ops.bvh.BVH` (``kernels_cl/trace.cl``, formulas at its top).

* :func:`trace_primary` — the K nearest hits of every pixel's camera ray, returned as
  :class:`~triplet_cl.ops.raster.Fragments` (same order, same pixel-centre convention, same culling),
  so interpolation, shading, compositing and :func:`~triplet_cl.ops.raster.fragments_backward` serve
  both renderers. The adjoint needs the rasterizer's tile binning: :func:`~triplet_cl.ops.raster.bin_faces`
  (reused, not duplicated); each hit is kept only if its face is binned into the pixel's tile, which
  also gives the rasterizer's culling.
* :func:`shadow_forward` / :func:`shadow_backward` — transmittance ``T = Π(1 − α)`` of each shaded
  point towards each point / directional light, and its adjoint to the occluders' vertex alphas and
  positions, the shaded point and the light position/direction.
* :func:`bounce` / :func:`gather_hits` — the nearest hit along each fragment's mirror direction and
  the hit surface's interpolated attributes; :func:`scatter_hits` is the adjoint of the latter.

Adjoints that land on vertices are written as per-hit records and summed per vertex on the host
with ``np.bincount`` (fixed order: deterministic; no float atomics).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ..camera import Camera
from ..device import Device
from ..lights import LightTable, kernel_defines
from .bvh import BVH
from .common import check_real, device_empty, launch, round_up, to_device
from .raster import TILE, Fragments, bin_faces, camera_params, pack_fragment_lists
from .scan import prefix_offsets

LOCAL = 64


def _run(device: Device, name: str, real, gsize, lsize, defines: dict | None = None, /, **args):
    """Launch kernel ``name`` of ``trace.cl`` (built with the light defines of ``lights.kernel_defines``
    and ``defines``), its arguments bound by name (:func:`~triplet_cl.ops.common.launch`)."""
    return launch(device, "trace", name, gsize, lsize, defines={**kernel_defines(), **(defines or {})}, real=real,
                  **args)


def _check_bvh(bvh: BVH, V) -> None:
    if not isinstance(bvh, BVH):
        raise ValueError(f"bvh must be a BVH (ops.bvh.build_bvh), got {type(bvh).__name__}")
    if V.dtype != bvh.real:
        raise ValueError(f"V must have the BVH's dtype {bvh.real}, got {V.dtype}")


def trace_primary(device: Device, bvh: BVH, V, vs, camera: Camera, K: int, cull_backface: bool = False) -> Fragments:
    """The K nearest ray hits of every pixel, as rasterizer :class:`Fragments`.

    Args:
        bvh: the hierarchy, refitted to ``V``.
        V: ``[N, 3]`` world positions (device array or numpy, the BVH's dtype).
        vs: ``[N, 3]`` projected vertices of ``V`` (:func:`~triplet_cl.ops.raster.project`; the
            binning and the adjoint use them).
        camera: the pinhole camera; K: hits kept per pixel.

    Returns:
        :class:`Fragments` (``face``, ``bary``, ``depth`` = camera depth, ``count``, and the binning).
    """
    mesh = bvh.mesh
    Vd = V if isinstance(V, cla.Array) else to_device(device.queue,
                                                      check_real("V", V, (mesh.num_vertices, 3), bvh.real))
    _check_bvh(bvh, Vd)
    W, H = camera.width, camera.height
    binning = bin_faces(device, vs, mesh, W, H, camera.near, camera.far, cull_backface)
    K = int(K)
    q, alloc, real = device.queue, device.allocator, bvh.real
    face = device_empty(q, (H, W, K), np.int32, allocator=alloc)
    entry = device_empty(q, (H, W, K), np.int32, allocator=alloc)
    bary = device_empty(q, (H, W, K, 2), real, allocator=alloc)
    depth = device_empty(q, (H, W, K), real, allocator=alloc)
    count = device_empty(q, (H, W), np.int32, allocator=alloc)
    c = camera.center
    cam = cla.to_device(q, camera_params(camera, real))
    _run(device, "trace_primary", real, (round_up(W, TILE), round_up(H, TILE)), (TILE, TILE),
         {"TILE": TILE, "K_MAX": K}, nodes=bvh.nodes, prim=bvh.prim, P=bvh.num_leaves, M=mesh.num_faces, V=Vd,
         F=mesh.F, cam=cam, ox=c[0], oy=c[1], oz=c[2], width=W, height=H, tiles_x=binning.tiles_x, K=K,
         far=camera.far, tile_off=binning.tile_off, face_off=binning.face_off, face_entries=binning.face_entries,
         frag_face=face, frag_entry=entry, frag_bary=bary, frag_depth=depth, frag_count=count)
    off, P, face, entry, bary, depth, _ = pack_fragment_lists(device, count, K, face, entry, bary, depth)
    return Fragments(W, H, K, binning.tiles_x, binning.tiles_y, binning.num_entries, np.dtype(real), face, entry,
                     bary, depth, count, binning.tile_off, binning.face_off, binning.face_entries, vs, mesh,
                     entry_setup=binning.entry_setup, entry_face=binning.entry_face, off=off, P=P)


def num_shadowed_lights(table: LightTable) -> int:
    """How many lights of a packed table cast ray-traced shadows (``CASTS_SHADOWS`` in lights.py)."""
    return table.num_shadowed


@dataclass
class ShadowState:
    """What :func:`shadow_forward` keeps for its adjoint."""

    vis: cla.Array  # [P, NV] transmittance
    nhit: cla.Array  # [P, NV] int32 hits per ray
    NV: int
    args: dict  # kernel arguments (by name) shared by the forward and the backward
    defines: dict  # HAS_NRM


@dataclass
class ShadowGrads:
    """Adjoints of :func:`shadow_forward` (:func:`shadow_backward`)."""

    v_alpha: np.ndarray  # [N] occluders' vertex alphas
    v_V: np.ndarray  # [N, 3] occluders' vertex positions
    v_pos: cla.Array  # [P, 3] the shading points (device)
    v_light: np.ndarray  # [P, NV, 3] each shadow caster's ray parameter (position / direction), per point


def shadow_forward(device: Device, bvh: BVH, V: cla.Array, attr: cla.Array, alpha_col: int, pos: cla.Array,
                   face: cla.Array, lt_i: cla.Array, lt_f: cla.Array, table: LightTable, eps: float,
                   nrm: cla.Array | None = None, cam_center=None, two_sided: bool = True,
                   early_out: bool = False) -> ShadowState:
    """Transmittance from ``P`` points towards each point / directional light.

    Args:
        V: ``[N, 3]`` positions (device, the BVH's dtype, the BVH refitted to them).
        attr: ``[N, C]`` per-vertex attributes (device); column ``alpha_col`` is the activated alpha.
        pos: ``[P, 3]`` shading points; face: ``[P] int32`` their own faces (skipped; −1: no ray).
        lt_i, lt_f: the packed light table on the device (``lights.pack_lights``); table: the same on the host.
        eps: world-space offset of the ray start against self-intersection.
        nrm, cam_center, two_sided: with ``nrm [P, 3]`` the shading normals (flipped towards
            ``cam_center`` when ``two_sided``, as shade.cl), rays towards lights behind a point
            (N·L ≤ 0, which contribute nothing) are skipped: T = 1, no hits.
        early_out: a ray's walk stops once its T is below 1e-4 (``trace.cl``'s ``T_EARLY``: T is then within
            1e-4 of the full product); :func:`shadow_backward` then walks the same hits (the adjoint of the
            truncated product: occluders beyond the stop get no gradient).

    Returns:
        :class:`ShadowState` with ``vis [P, NV]`` (NV = :func:`num_shadowed_lights`, in light order).
    """
    _check_bvh(bvh, V)
    q, real = device.queue, bvh.real
    P = pos.shape[0]
    NV = num_shadowed_lights(table)
    C = attr.shape[1]
    if not 0 <= alpha_col < C:
        raise ValueError(f"alpha_col must be in [0, {C - 1}], got {alpha_col}")
    vis = device_empty(q, (max(P, 1), max(NV, 1)), real, allocator=device.allocator)[:P, :NV]
    nhit = cla.zeros(q, (max(P, 1) * max(NV, 1),), np.int32, allocator=device.allocator)
    c = np.zeros(3) if cam_center is None else np.asarray(cam_center, np.float64)
    args = dict(nodes=bvh.nodes, prim=bvh.prim, P=bvh.num_leaves, M=bvh.mesh.num_faces, V=V, F=bvh.mesh.F,
                attr=attr, C=C, ca=alpha_col, pos=pos, face=face, Pf=P, lt_i=lt_i, lt_f=lt_f, L=len(table.ints),
                NV=NV, eps=eps)
    if nrm is not None:
        args.update(nrm=nrm, cx=c[0], cy=c[1], cz=c[2], two_sided=int(bool(two_sided)))
    defines = {"HAS_NRM": nrm is not None, "EARLY_OUT": bool(early_out)}
    if P and NV:
        _run(device, "trace_shadow_fwd", real, (round_up(P, LOCAL),), (LOCAL,), defines, **args, vis=vis.base_data,
             nhit=nhit)
    return ShadowState(vis, nhit[: P * NV], NV, args, defines)


def shadow_backward(device: Device, bvh: BVH, st: ShadowState, v_vis) -> ShadowGrads:
    """Adjoint of :func:`shadow_forward` for ``v_vis [P, NV]``.

    Returns:
        :class:`ShadowGrads`: adjoints of the vertex alphas and positions of the occluders, of the
        shading points and of each light's position (point) or direction (directional), per shading point.
    """
    q, real = device.queue, bvh.real
    P, NV = st.vis.shape
    n = bvh.mesh.num_vertices
    v_pos = cla.zeros(q, (max(P, 1), 3), real, allocator=device.allocator)[:P]
    if P == 0 or NV == 0:
        return ShadowGrads(np.zeros(n), np.zeros((n, 3)), v_pos, np.zeros((P, NV, 3)))
    off, R = prefix_offsets(device, st.nhit)
    v_vis = v_vis if isinstance(v_vis, cla.Array) else to_device(q, np.ascontiguousarray(v_vis, real))
    rec_face = device_empty(q, max(R, 1), np.int32, allocator=device.allocator)
    rec_w = device_empty(q, (max(R, 1), 12), real, allocator=device.allocator)
    v_light = device_empty(q, (P, NV, 3), real, allocator=device.allocator)
    _run(device, "trace_shadow_bwd", real, (round_up(P, LOCAL),), (LOCAL,), st.defines, **st.args,
         vis=st.vis.base_data, v_vis=v_vis, rec_off=off, rec_face=rec_face, rec_w=rec_w, v_x=v_pos.base_data,
         v_light=v_light)
    F = bvh.mesh.faces
    if R:
        fc = rec_face.get()[:R]
        w = rec_w.get()[:R].astype(np.float64)
        verts = F[fc].reshape(-1)  # [R * 3] corner vertices
        v_alpha = np.bincount(verts, weights=w[:, :3].reshape(-1), minlength=n)
        wp = w[:, 3:].reshape(-1, 3)
        v_V = np.stack([np.bincount(verts, weights=wp[:, c], minlength=n) for c in range(3)], axis=1)
    else:
        v_alpha, v_V = np.zeros(n), np.zeros((n, 3))
    return ShadowGrads(v_alpha, v_V, v_pos, v_light.get().astype(np.float64))


def bounce(device: Device, bvh: BVH, V: cla.Array, pos: cla.Array, nrm: cla.Array, face: cla.Array, cam_center,
           two_sided: bool, eps: float):
    """Nearest hit along each point's mirror direction (about its normal, seen from ``cam_center``).

    Args:
        pos, nrm: ``[P, 3]`` shading points and normals (device); face: ``[P] int32`` own faces (−1: none).

    Returns:
        ``(hit_face [P] int32, hit_bary [P, 2])`` device arrays (−1 / zeros where nothing is hit).
    """
    _check_bvh(bvh, V)
    q, real = device.queue, bvh.real
    P = pos.shape[0]
    hf = device_empty(q, max(P, 1), np.int32, allocator=device.allocator)
    hb = device_empty(q, (max(P, 1), 2), real, allocator=device.allocator)
    c = np.asarray(cam_center, np.float64)
    if P:
        _run(device, "trace_bounce", real, (round_up(P, LOCAL),), (LOCAL,), nodes=bvh.nodes, prim=bvh.prim,
             P=bvh.num_leaves, M=bvh.mesh.num_faces, V=V, F=bvh.mesh.F, pos=pos, nrm=nrm, face=face, Pf=P,
             cx=c[0], cy=c[1], cz=c[2], two_sided=int(bool(two_sided)), eps=eps, hit_face=hf, hit_bary=hb)
    return hf[:P], hb[:P]


def bounce_backward(device: Device, V: cla.Array, attr: cla.Array, pos: cla.Array, nrm: cla.Array,
                    hit_face: cla.Array, hit_bary: cla.Array, v_h, v_eye: cla.Array, mesh, cam_center,
                    two_sided: bool):
    """Adjoint of the bounce geometry: how the hit point moves with the reflecting point, its normal and
    the hit face's vertices (the hit face itself is discrete).

    Args:
        V: ``[N, 3]``, attr: ``[N, C]`` (device) as gathered by :func:`gather_hits`; pos, nrm: ``[P, 3]``
            reflecting points and normals; hit_face/hit_bary: from :func:`bounce`.
        v_h: ``[P, C]`` adjoint of every gathered attribute column at the hits; v_eye: ``[P, 3]``
            adjoint of the hit shading's viewpoint (the reflecting point).
        mesh: the :class:`~triplet_cl.ops.mesh.DeviceMesh` (faces on the device and the host).

    Returns:
        ``(v_pos [P, 3] device, v_nrm [P, 3] device, v_V [N, 3] numpy)``.
    """
    q, real = device.queue, V.dtype
    P = pos.shape[0]
    C = attr.shape[1]
    v_h = v_h if isinstance(v_h, cla.Array) else cla.to_device(q, np.ascontiguousarray(v_h, real))
    vp = device_empty(q, (max(P, 1), 3), real, allocator=device.allocator)
    vn = device_empty(q, (max(P, 1), 3), real, allocator=device.allocator)
    rec = device_empty(q, (max(P, 1), 3, 3), real, allocator=device.allocator)
    c = np.asarray(cam_center, np.float64)
    n = V.shape[0]
    if P == 0:
        return vp[:0], vn[:0], np.zeros((n, 3))
    _run(device, "bounce_bwd", real, (round_up(P, LOCAL),), (LOCAL,), V=V, F=mesh.F, attr=attr, C=C, pos=pos,
         nrm=nrm, hit_face=hit_face, hit_bary=hit_bary, v_h=v_h, v_eye=v_eye, Pf=P, cx=c[0], cy=c[1], cz=c[2],
         two_sided=int(bool(two_sided)), v_pos=vp, v_nrm=vn, rec_pos=rec)
    hf = hit_face.get()
    ok = hf >= 0
    verts = mesh.faces[hf[ok]].reshape(-1)
    w = rec.get()[:P][ok].reshape(-1, 3).astype(np.float64)
    v_V = np.stack([np.bincount(verts, weights=w[:, k], minlength=n) for k in range(3)], axis=1)
    return vp[:P], vn[:P], v_V


def trace_rays(device: Device, bvh: BVH, V: cla.Array, origin, direction, own, eps: float):
    """Nearest hit along each ray ``origin + t direction`` (``t > eps``, the face ``own`` skipped; ``own < 0``: no
    ray). ``origin``, ``direction``: ``[R, 3]``; ``own``: ``[R]`` int32 (host or device arrays).

    Returns:
        ``(hit_face [R] int32, hit_bary [R, 2])`` device arrays (−1 / zeros where nothing is hit).
    """
    _check_bvh(bvh, V)
    q, real = device.queue, bvh.real
    o = to_device(q, check_real("origin", origin, (None, 3), real))
    R = o.shape[0]
    dr = to_device(q, check_real("direction", direction, (R, 3), real))
    ow = own if isinstance(own, cla.Array) else cla.to_device(q, np.ascontiguousarray(own, np.int32))
    if ow.shape != (R,) or ow.dtype != np.int32:
        raise ValueError(f"own must be [{R}] int32 (one face per ray), got {list(ow.shape)} {ow.dtype}")
    hf = device_empty(q, max(R, 1), np.int32, allocator=device.allocator)
    hb = device_empty(q, (max(R, 1), 2), real, allocator=device.allocator)
    if R:
        _run(device, "trace_rays", real, (round_up(R, LOCAL),), (LOCAL,), nodes=bvh.nodes, prim=bvh.prim,
             P=bvh.num_leaves, M=bvh.mesh.num_faces, V=V, F=bvh.mesh.F, origin=o, dir=dr, own=ow, R=R, eps=eps,
             hit_face=hf, hit_bary=hb)
    return hf[:R], hb[:R]


def gather_hits(device: Device, attr: cla.Array, c0: int, n: int, F: cla.Array, hit_face: cla.Array,
                hit_bary: cla.Array) -> cla.Array:
    """``attr[:, c0:c0+n]`` interpolated at each hit: ``[P, n]`` device array (zeros without a hit)."""
    q = device.queue
    P = hit_face.shape[0]
    real = attr.dtype
    out = device_empty(q, (max(P, 1), n), real, allocator=device.allocator)
    if P:
        _run(device, "gather_hits", real, (round_up(P, LOCAL),), (LOCAL,), attr=attr, C=attr.shape[1], c0=c0, n=n,
             F=F, hit_face=hit_face, hit_bary=hit_bary, Pf=P, out=out)
    return out[:P]


def scatter_hits(faces: np.ndarray, num_vertices: int, hit_face: np.ndarray, hit_bary: np.ndarray,
                 v_out: np.ndarray) -> np.ndarray:
    """Adjoint of :func:`gather_hits` (host): ``v_out [P, n]`` → ``v_attr [N, n]`` (float64)."""
    ok = hit_face >= 0
    f, b, g = hit_face[ok], hit_bary[ok].astype(np.float64), np.asarray(v_out, np.float64)[ok]
    lam = np.stack([b[:, 0], b[:, 1], 1.0 - b[:, 0] - b[:, 1]], axis=1)  # [P', 3]
    verts = faces[f].reshape(-1)
    out = np.zeros((num_vertices, g.shape[1]))
    for c in range(g.shape[1]):
        out[:, c] = np.bincount(verts, weights=(lam * g[:, c:c + 1]).reshape(-1), minlength=num_vertices)
    return out


def ray_mask(device: Device, frags: Fragments, offsets: cla.Array, face: cla.Array, alpha: cla.Array,
             win: cla.Array | None, t_min: float) -> cla.Array:
    """``[P] int32``: the compacted face ids, −1 for fragments behind a transmittance below ``t_min``
    (``Π (1 − α·win)`` of the fragments in front; compositing gives them no weight, so they need no
    shadow or bounce ray). ``alpha``, ``win``: ``[P]`` (or ``[P, 1]``) compacted per-fragment values."""
    H, W, K = frags.shape
    P = face.shape[0]
    out = device_empty(device.queue, max(P, 1), np.int32, allocator=device.allocator)
    if P:
        extra = {} if win is None else {"win": win}
        _run(device, "ray_mask", frags.real, (H * W,), None, {"HAS_WIN": win is not None}, face=face,
             alpha=alpha, **extra, frag_count=frags.count, offsets=offsets, npix=H * W, t_min=t_min, out=out)
    return out[:P]


__all__ = ["ShadowGrads", "ShadowState", "bounce", "bounce_backward", "gather_hits", "num_shadowed_lights", "ray_mask",
           "scatter_hits", "shadow_backward", "shadow_forward", "trace_primary"]
