"""Reference real spherical harmonics (numpy) and the scipy-based definition they are tested against.

Convention (kernels_cl/common/sh.h): k = l*l + l + m;  Y_{l,0} = Y_l^0, Y_{l,m} = sqrt2 Re Y_l^m (m > 0),
Y_{l,m} = sqrt2 Im Y_l^|m| (m < 0), with scipy's complex Y_l^m (Condon-Shortley phase included).
"""

from __future__ import annotations

from math import factorial, pi, sqrt

import numpy as np

BAND_A = np.array([
    pi, 2 * pi / 3, pi / 4, 0.0, -pi / 24, 0.0, pi / 64, 0.0, -pi / 128
])  # Ramamoorthi-Hanrahan clamped-cosine band factors (A_8 = -pi/128)


def num_coeffs(deg: int) -> int:
    return (deg + 1) ** 2


def band_of(nk: int) -> np.ndarray:
    """``l`` of each coefficient index ``k < nk``."""
    return np.floor(np.sqrt(np.arange(nk))).astype(int)


def sh_eval(deg: int, d):
    """Polynomial recurrence (same algorithm as sh.h) on ``d [..., 3]`` → ``[..., (deg+1)^2]``.

    Works with complex inputs (complex-step differentiation).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.zeros(d.shape[:-1] + (num_coeffs(deg),), dtype=np.result_type(d, np.float64))
    C, S, qmm = np.ones_like(x), np.zeros_like(x), 1.0
    for m in range(deg + 1):
        if m > 0:
            C, S = x * C - y * S, x * S + y * C
            qmm *= -(2 * m - 1)
        q1 = q2 = 0.0
        for l in range(m, deg + 1):
            if l == m:
                q = qmm * np.ones_like(z)
            elif l == m + 1:
                q = (2 * m + 1) * z * qmm
            else:
                q = ((2 * l - 1) * z * q1 - (l + m - 1) * q2) / (l - m)
            K = sqrt((2 * l + 1) / (4 * pi) * factorial(l - m) / factorial(l + m))
            c = l * l + l
            if m == 0:
                out[..., c] = K * q
            else:
                out[..., c + m] = sqrt(2) * K * q * C
                out[..., c - m] = sqrt(2) * K * q * S
            q2, q1 = q1, q
    return out


def sh_scipy(deg: int, d):
    """The definition, through ``scipy.special.sph_harm_y`` (unit ``d [..., 3]``)."""
    from scipy.special import sph_harm_y

    d = np.asarray(d, np.float64)
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    phi = np.arctan2(d[..., 1], d[..., 0])
    out = np.zeros(d.shape[:-1] + (num_coeffs(deg),))
    for l in range(deg + 1):
        for m in range(-l, l + 1):
            k = l * l + l + m
            if m == 0:
                out[..., k] = sph_harm_y(l, 0, theta, phi).real
            elif m > 0:
                out[..., k] = sqrt(2) * sph_harm_y(l, m, theta, phi).real
            else:
                out[..., k] = sqrt(2) * sph_harm_y(l, -m, theta, phi).imag
    return out


def vertex_sh(V, coeffs, cam, degree: int):
    """Reference implementation of vertex_sh: ``[N, 6]`` (radiance relu(sum Y c + 0.5), direction)."""
    w = cam - V
    l2 = np.sum(w * w, axis=-1, keepdims=True)
    d = w / np.sqrt(np.where(l2.real > 1e-20, l2, 1e-20))
    nk = (degree + 1) ** 2
    Y = sh_eval(degree, d)
    s = np.einsum("nk,njk->nj", Y, coeffs[:, :, :nk])
    rad = s[:, :3] + 0.5
    return np.concatenate([np.where(rad.real > 0, rad, 0), s[:, 3:]], axis=1)
