"""Numpy reference of ``downsample.cl`` (the supersampled render's box and Gaussian pixel filters)."""

from __future__ import annotations

import numpy as np


def box_down(x: np.ndarray, f: int) -> np.ndarray:
    """``[H f, W f(, C)] → [H, W(, C)]``: the mean of each ``f × f`` block."""
    H, W = x.shape[0] // f, x.shape[1] // f
    return x.reshape((H, f, W, f) + x.shape[2:]).mean(axis=(1, 3))


def box_up(v_y: np.ndarray, f: int) -> np.ndarray:
    """The adjoint: each pixel's cotangent / f² over its block."""
    return np.repeat(np.repeat(v_y, f, axis=0), f, axis=1) / (f * f)


def _gauss_matrix(f: int, sigma: float, length: int) -> np.ndarray:
    """``[length, length f]``: row l holds the normalised weights of every supersample for output pixel l, straight
    from the definition (a Gaussian of ``sigma`` output pixels, truncated at 4 sigma and shifted to 0 there, between
    the centres; normalised over the supersamples inside the image)."""
    r = 4.0 * sigma
    d = (np.arange(length * f)[None, :] + 0.5) / f - (np.arange(length)[:, None] + 0.5)
    w = np.where(np.abs(d) < r, np.exp(-d * d / (2 * sigma * sigma)) - np.exp(-r * r / (2 * sigma * sigma)), 0.0)
    return w / w.sum(axis=1, keepdims=True)


def gauss_down(x: np.ndarray, f: int, sigma: float) -> np.ndarray:
    """``[H f, W f(, C)] → [H, W(, C)]``: the Gaussian pixel filter as two dense matrix products."""
    H, W = x.shape[0] // f, x.shape[1] // f
    return np.einsum("ir,jc,rc...->ij...", _gauss_matrix(f, sigma, H), _gauss_matrix(f, sigma, W), x)


def gauss_up(v_y: np.ndarray, f: int, sigma: float) -> np.ndarray:
    """The adjoint: the transposed products."""
    H, W = v_y.shape[:2]
    return np.einsum("ir,jc,ij...->rc...", _gauss_matrix(f, sigma, H), _gauss_matrix(f, sigma, W), v_y)
