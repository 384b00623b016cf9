"""Numpy reference of ``downsample.cl`` (the supersampled render's box filter)."""

from __future__ import annotations

import numpy as np


def box_down(x: np.ndarray, f: int) -> np.ndarray:
    """``[H f, W f(, C)] → [H, W(, C)]``: the mean of each ``f × f`` block."""
    H, W = x.shape[0] // f, x.shape[1] // f
    return x.reshape((H, f, W, f) + x.shape[2:]).mean(axis=(1, 3))


def box_up(v_y: np.ndarray, f: int) -> np.ndarray:
    """The adjoint: each pixel's cotangent / f² over its block."""
    return np.repeat(np.repeat(v_y, f, axis=0), f, axis=1) / (f * f)
