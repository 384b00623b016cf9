"""Soft coverage window and front-to-back alpha compositing (``coverage.cl``, ``composite.cl``)."""

from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import buf, c_max, check_real, const_array, device_empty, device_rows, fragment_array
from .fragments import Fragments, frag_input


def coverage(device: Device, frags: Fragments, sigma: float) -> cla.Array:
    """Soft edge window per fragment: ``1 − exp(−σ·d)``, d the pixel distance to the nearest edge.

    Args:
        frags: the fragments of the view; ``sigma`` > 0 the sharpness in 1/pixels (σ → ∞: hard edge).

    Returns:
        ``win [P]`` device array (per fragment, packed order). Its adjoint is part of
        :func:`~triplet_cl.ops.raster.raster_backward` (``v_win``, ``sigma``).
    """
    if not (isinstance(sigma, int | float) and math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a finite positive number, got {sigma!r}")
    if frags.win is not None and frags.sigma == sigma:
        return frags.win  # computed by the rasterizer in the same pass
    if frags.soft_edges:
        raise ValueError("fragments rasterized with soft_edges carry their window only for the sigma given to "
                         f"rasterize ({frags.sigma}); got sigma={sigma}")
    H, W, K = frags.shape
    q = device.queue
    win = device_empty(q, max(frags.P, 1), frags.real, allocator=device.allocator)[: frags.P]
    device.kernel("coverage", "coverage_fwd", real=frags.real)(
        q, (H * W,), None, frags.vs.data, frags.mesh.F.data, buf(frags.face, q), frags.count.data,
        np.int32(W), np.int32(H), frags.off.data, frags.real.type(sigma), buf(win, q))
    return win


def composite(device: Device, frags: Fragments, feat, alpha, bg, win=None, t_min: float = 1e-4):
    """Front-to-back alpha blending of the K fragments of each pixel over a background.

    Args:
        feat: ``[P, C]`` per-fragment features (colour, and e.g. depth / normal channels), in the
            fragments' packed order (numpy also as the padded ``[H, W, K, C]`` view).
        alpha: ``[P]`` per-fragment opacity in [0, 1].
        bg: ``[C]`` background (use 0 for channels such as depth).
        win: optional ``[P]`` coverage window multiplying ``alpha``.
        t_min: compositing stops once the transmittance drops below it (0 disables).

    Returns:
        ``(image [H, W, C], trans [H, W], n_contrib [H, W] int32)`` device arrays;
        accumulated alpha is ``1 − trans``.
    """
    H, W, K = frags.shape
    real = frags.real
    if not hasattr(feat, "shape") or len(feat.shape) not in (2, 4):
        raise ValueError(f"feat must have shape [P, C] (P = {frags.P}), got {list(getattr(feat, 'shape', []))}")
    C = int(feat.shape[-1])
    if not 1 <= C <= 64:
        raise ValueError(f"feat must have between 1 and 64 channels, got {C}")
    f = frag_input(device, frags, "feat", feat, C)
    a = frag_input(device, frags, "alpha", alpha)
    w = frag_input(device, frags, "win", win)
    b = np.broadcast_to(np.asarray(bg, dtype=np.float64), (C,)) if np.ndim(bg) <= 1 else None
    if b is None:
        raise ValueError(f"bg must have shape [{C}] (or be a scalar), got {list(np.shape(bg))}")
    bgd = const_array(device, check_real("bg", b, (C,), real))
    if not (0 <= t_min < 1):
        raise ValueError(f"t_min must be in [0, 1), got {t_min}")
    q, alloc = device.queue, device.allocator
    npix = H * W
    out = device_empty(q, (H, W, C), real, allocator=alloc)
    trans = device_empty(q, (H, W), real, allocator=alloc)
    ncon = device_empty(q, (H, W), np.int32, allocator=alloc)
    device.kernel("composite", "composite_fwd", _defines(C), real)(
        q, (npix,), None, buf(f, q), buf(a, q), buf(w, q), frags.count.data, bgd.data, np.int32(npix), frags.off.data,
        np.int32(C), np.int32(w is not None), real.type(t_min), out.data, trans.data, ncon.data)
    return out, trans, ncon


#: the channel count compiled into the composite kernels (unrolled channel loops, the pixel's sums in registers: the
#: same bits as the runtime loops, ``tests/test_raster.py``); False: the runtime count (the reference)
COMPILED_CHANNELS = True


def _defines(C: int) -> dict:
    return {"C_MAX": c_max(C), "NC": C} if COMPILED_CHANNELS else {"C_MAX": c_max(C)}


def composite_backward(device: Device, frags: Fragments, feat, alpha, bg, n_contrib, trans, v_image,
                       v_acc=None, win=None, bg_grad: bool = False):
    """Adjoint of :func:`composite`.

    Args:
        feat, alpha, bg, win: the inputs of the forward pass; ``n_contrib``, ``trans`` its outputs.
        v_image: ``[H, W, C]`` adjoint of the image; v_acc: optional ``[H, W]`` adjoint of the
            accumulated alpha ``1 − trans``.
        bg_grad: also return the background's adjoint (a host reduction over the image).

    Returns:
        ``(v_feat [P, C], v_alpha [P], v_win [P] or None, v_bg [C] numpy or None)``.
    """
    H, W, K = frags.shape
    real = frags.real
    C = int(feat.shape[-1])
    f = frag_input(device, frags, "feat", feat, C)
    a = frag_input(device, frags, "alpha", alpha)
    w = frag_input(device, frags, "win", win)
    g = fragment_array(device.queue, "v_image", v_image, (H, W, C), real)
    va = None if v_acc is None else fragment_array(device.queue, "v_acc", v_acc, (H, W), real)
    b = np.broadcast_to(np.asarray(bg, dtype=np.float64), (C,))
    bgd = const_array(device, b.astype(real))
    q = device.queue
    P = frags.P
    v_feat = device_rows(device, (P, C), real)
    v_alpha = device_rows(device, P, real)
    v_win = device_rows(device, P, real) if w is not None else None
    device.kernel("composite", "composite_bwd", _defines(C), real)(
        q, (H * W,), None, buf(f, q), buf(a, q), buf(w, q), n_contrib.data, frags.count.data, bgd.data, g.data,
        buf(va, q), np.int32(H * W), frags.off.data, np.int32(C), np.int32(w is not None), np.int32(va is not None),
        buf(v_feat, q), buf(v_alpha, q), buf(v_win, q))
    # v_bg_c = sum over pixels of v_image_c * T_n  (small host reduction, only when asked)
    v_bg = None
    if bg_grad:
        v_bg = (g.get().astype(np.float64) * trans.get().astype(np.float64)[..., None]).reshape(-1, C).sum(0)
    return v_feat, v_alpha, v_win, v_bg
