"""Plain numpy references for the image losses (loops and a direct 2-D window, no scipy filters)."""

from __future__ import annotations

import numpy as np


def gaussian_window_2d(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """``[size, size]``: the outer product of 3DGS's normalised 1-D Gaussian."""
    k = np.arange(size) - size // 2
    g = np.exp(-(k**2) / (2 * sigma**2))
    g /= g.sum()
    return np.outer(g, g)


def filter_zero_pad(img: np.ndarray, window: np.ndarray) -> np.ndarray:
    """``[H, W, C]``: "same" correlation with zero padding, as conv2d(padding=size//2) in 3DGS."""
    h, w, _ = img.shape
    r = window.shape[0] // 2
    pad = np.pad(img, ((r, r), (r, r), (0, 0)))
    out = np.zeros_like(img, dtype=np.float64)
    for dy in range(window.shape[0]):
        for dx in range(window.shape[1]):
            out += window[dy, dx] * pad[dy:dy + h, dx:dx + w]
    return out


def ssim_3dgs(x: np.ndarray, y: np.ndarray, c1: float = 0.01**2, c2: float = 0.03**2) -> float:
    """3D Gaussian Splatting's ``ssim(img1, img2)`` (size_average=True) for ``[H, W, C]`` images."""
    win = gaussian_window_2d()
    mu1, mu2 = filter_zero_pad(x, win), filter_zero_pad(y, win)
    s11 = filter_zero_pad(x * x, win) - mu1**2
    s22 = filter_zero_pad(y * y, win) - mu2**2
    s12 = filter_zero_pad(x * y, win) - mu1 * mu2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    return float(m.mean())


def l1(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.abs(x - y).mean())


def image_tv_sum(img: np.ndarray, eps: float) -> float:
    """``Σ_c Σ_{i<H-1, j>=1} sqrt((x[i,j-1]-x[i,j])² + (x[i+1,j]-x[i,j])² + eps)`` by loops."""
    h, w, c = img.shape
    total = 0.0
    for ch in range(c):
        for i in range(h - 1):
            for j in range(1, w):
                dx = img[i, j - 1, ch] - img[i, j, ch]
                dy = img[i + 1, j, ch] - img[i, j, ch]
                total += np.sqrt(dx * dx + dy * dy + eps)
    return total
