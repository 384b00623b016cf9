"""numpy reference of ``kernels_cl/color.cl``: the sRGB transfer and encoded-space compositing."""

from __future__ import annotations

import numpy as np

KNEE = 0.0031308


def srgb_encode(u):
    """The sRGB transfer function (linear → encoded), extended linearly below 0 and as the power law above 1.
    Works on complex input (complex-step derivatives)."""
    u = np.asarray(u)
    lo = np.real(u) <= KNEE
    safe = np.where(lo, 1.0, u)
    return np.where(lo, 12.92 * u, 1.055 * safe ** (1 / 2.4) - 0.055)


def srgb_composite(C, A, bg, eps=1e-6, clip=False):
    """``A·s(C/max(A, eps)) + (1 − A)·bg``: ``C [H, W, 3]`` linear premultiplied, ``A [H, W]``; ``clip``: ``s``
    saturates at 1 for ``u >= 1`` (the camera's clip, ``SRGB_CLIP``)."""
    C, A = np.asarray(C), np.asarray(A)
    ad = np.where(np.real(A) >= eps, A, eps)
    u = C / ad[..., None]
    s = srgb_encode(u)
    if clip:
        s = np.where(np.real(u) >= 1.0, 1.0 + 0.0 * u, s)
    return A[..., None] * s + (1 - A[..., None]) * np.asarray(bg, float)


def srgb_slope(u):
    """s'(u) of the unclipped transfer (12.92 up to the knee, 1.055/2.4 · u^(1/2.4 − 1) above)."""
    u = np.asarray(u, np.float64)
    lo = u <= KNEE
    safe = np.where(lo, 1.0, u)
    return np.where(lo, 12.92, 1.055 / 2.4 * safe ** (1 / 2.4 - 1))


def srgb_composite_clip_adjoint(C, A, bg, v, eps=1e-6):
    """The adjoint of the clipped photo model (``SRGB_CLIP``) as ``color.cl`` defines it (one-sided straight-through):
    the unclipped slope ``s'(u)`` with the forward's clipped value ``min(s(u), 1)``, and above the clip only the
    cotangent's positive part (what lowers the value) through the slope, ``g = max(v, 0)`` there (else ``g = v``):
    ``v_C = g A s'(u) / a'``, ``v_A = Σ_c v (min(s(u), 1) − bg) − g [A ≥ eps] s'(u) u``."""
    C, A, v = np.asarray(C, np.float64), np.asarray(A, np.float64), np.asarray(v, np.float64)
    ad = np.where(A >= eps, A, eps)
    u = C / ad[..., None]
    ds = srgb_slope(u)
    s = np.where(u >= 1.0, 1.0, srgb_encode(u))
    g = np.where(u >= 1.0, np.maximum(v, 0.0), v)
    v_C = g * (A / ad)[..., None] * ds
    v_A = np.sum(v * (s - np.asarray(bg, float)) - g * (A >= eps)[..., None] * ds * u, axis=-1)
    return v_C, v_A
