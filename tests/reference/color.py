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
