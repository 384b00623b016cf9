"""Numerical derivatives shared by the gradient tests."""

from __future__ import annotations

import numpy as np


def cs_grad(f, x, h=1e-30):
    """Gradient of the real scalar ``f`` at ``x`` by complex steps (exact to rounding)."""
    g = np.zeros(x.shape)
    for i in np.ndindex(x.shape):
        xc = x.astype(np.complex128)
        xc[i] += 1j * h
        g[i] = f(xc).imag / h
    return g


def fd_grad(f, x, h=1e-6):
    """Gradient of the scalar ``f`` at ``x`` by central differences."""
    g = np.zeros(x.shape)
    for i in np.ndindex(x.shape):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        g[i] = (f(xp) - f(xm)) / (2 * h)
    return g
