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


def sampled_fd(param, loss, rng, n, eps=1e-6):
    """Central differences of ``loss() -> (value, same_fragments)`` at ``n`` random entries of ``param.data``
    (perturbed in place and restored): ``(indices, numerical, ok)``, ``ok`` false where a perturbation changed
    which fragments a pixel holds (the render is then not differentiable there)."""
    flat = param.data.reshape(-1)
    idx = rng.choice(flat.size, size=min(flat.size, n), replace=False)
    num, ok = [], []
    for i in idx:
        old = flat[i]
        flat[i] = old + eps
        lp, sp = loss()
        flat[i] = old - eps
        lm, sm = loss()
        flat[i] = old
        num.append((lp - lm) / (2 * eps))
        ok.append(sp and sm)
    return idx, np.asarray(num), np.asarray(ok)
