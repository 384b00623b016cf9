"""Activations of the raw parameters (docs/ARCHITECTURE.md §8) with their adjoints.

Each activation ``y = f(x)`` has a forward ``f(x)``, an adjoint ``f_bwd(..., v_y) -> v_x`` and a tape
:class:`~triplet_cl.autodiff.Function` (``Sigmoid()``, ``Softplus()``, ``Exp()``, ``Normalize()``).
All work on numpy arrays and on ``pyopencl.array.Array`` (device data stays on the device).

==========  ======================================  ===========================================
name        forward                                 adjoint
==========  ======================================  ===========================================
sigmoid     ``y = 1 / (1 + exp(-x))``               ``v_x = v_y * y * (1 - y)``
softplus    ``y = max(x, 0) + log1p(exp(-|x|))``    ``v_x = v_y * sigmoid(x)``
exp         ``y = exp(x)``                          ``v_x = v_y * y``
normalize   ``y = x / sqrt(|x|² + eps)`` (rows)     ``v_x = (v_y - y (y·v_y)) / sqrt(|x|² + eps)``
==========  ======================================  ===========================================

``normalize`` acts on the last axis of ``x [..., D]``; ``eps`` (default 1e-12) keeps it smooth at
zero (the adjoint above is exact for this smoothed form).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pyopencl.clmath as clmath
import scipy.special
from pyopencl.elementwise import ElementwiseKernel

from triplet_cl.autodiff import Function

NORMALIZE_EPS = 1e-12


def _is_dev(x) -> bool:
    return isinstance(x, cla.Array)


# ---- sigmoid ------------------------------------------------------------------------------------
def sigmoid(x):
    """``[...] -> [...]``: the logistic function (overflow-free on the host)."""
    if _is_dev(x):
        return 1.0 / (1.0 + clmath.exp(-x))
    return scipy.special.expit(x)


def sigmoid_bwd(y, v_y):
    """Adjoint of :func:`sigmoid` given its output ``y [...]`` and ``v_y [...]``: ``v_x [...]``."""
    return v_y * y * (1.0 - y)


# ---- softplus -----------------------------------------------------------------------------------
def softplus(x):
    """``[...] -> [...]``: ``log(1 + exp(x))`` computed without overflow."""
    if _is_dev(x):
        return 0.5 * (x + abs(x)) + clmath.log1p(clmath.exp(-abs(x)))  # max(x, 0) without fmax on ints
    return np.maximum(x, 0) + np.log1p(np.exp(-np.abs(x)))


def softplus_bwd(x, v_y):
    """Adjoint of :func:`softplus` given its input ``x [...]`` and ``v_y [...]``: ``v_x [...]``."""
    return v_y * sigmoid(x)


# ---- inverses (host, float64): raw values from activated ones ------------------------------------
def logit(p, eps: float | None = 1e-6):
    """Inverse of :func:`sigmoid`, ``[...] → [...]`` float64: ``log(p) − log1p(−p)``, with ``p``
    clipped to ``[eps, 1 − eps]`` first (``eps=None``: the caller has clipped it)."""
    p = np.asarray(p, np.float64)
    if eps is not None:
        p = np.clip(p, eps, 1 - eps)
    return np.log(p) - np.log1p(-p)


def inverse_softplus(y, floor: float = 1e-12, linear_above: float = 20.0):
    """Inverse of :func:`softplus`, ``[...] → [...]`` float64: ``log(expm1(y))`` on ``y`` clipped to
    ``[floor, linear_above]``, and ``y`` itself above ``linear_above`` (where they agree to rounding)."""
    y = np.asarray(y, np.float64)
    return np.where(y > linear_above, y, np.log(np.expm1(np.clip(y, floor, linear_above))))


# ---- exp ----------------------------------------------------------------------------------------
def exp(x):
    """``[...] -> [...]``: the exponential."""
    return clmath.exp(x) if _is_dev(x) else np.exp(x)


def exp_bwd(y, v_y):
    """Adjoint of :func:`exp` given its output ``y [...]`` and ``v_y [...]``: ``v_x [...]``."""
    return v_y * y


# ---- normalize ----------------------------------------------------------------------------------
_DEV_KERNELS: dict = {}


def _dev_kernel(ctx, dtype, which: str) -> ElementwiseKernel:
    """Row kernels on ``[N, D]`` device data (one work-item per row, D a kernel argument)."""
    key = (ctx, np.dtype(dtype), which)
    k = _DEV_KERNELS.get(key)
    if k is None:
        t = "double" if np.dtype(dtype) == np.float64 else "float"
        if which == "fwd":
            args = f"__global const {t}* x, __global {t}* y, const int d, const {t} eps"
            body = (f"{t} s = eps; for (int k = 0; k < d; ++k) s += x[i*d+k] * x[i*d+k];"
                    f"{t} inv = 1 / sqrt(s); for (int k = 0; k < d; ++k) y[i*d+k] = x[i*d+k] * inv;")
        else:
            args = f"__global const {t}* x, __global const {t}* v_y, __global {t}* v_x, const int d, const {t} eps"
            body = (f"{t} s = eps; for (int k = 0; k < d; ++k) s += x[i*d+k] * x[i*d+k];"
                    f"{t} inv = 1 / sqrt(s); {t} yv = 0;"
                    "for (int k = 0; k < d; ++k) yv += x[i*d+k] * inv * v_y[i*d+k];"
                    "for (int k = 0; k < d; ++k) v_x[i*d+k] = (v_y[i*d+k] - x[i*d+k] * inv * yv) * inv;")
        preamble = "#pragma OPENCL EXTENSION cl_khr_fp64 : enable\n" if t == "double" else ""
        k = ElementwiseKernel(ctx, args, body, f"normalize_rows_{which}", preamble=preamble)
        _DEV_KERNELS[key] = k
    return k


def normalize(x, eps: float = NORMALIZE_EPS):
    """``[..., D] -> [..., D]``: each row scaled to unit length, ``x / sqrt(|x|² + eps)``."""
    if _is_dev(x):
        d = x.shape[-1]
        y = cla.empty_like(x)
        _dev_kernel(x.context, x.dtype, "fwd")(x, y, np.int32(d), x.dtype.type(eps), range=slice(x.size // d))
        return y
    return x / np.sqrt(np.sum(x * x, axis=-1, keepdims=True) + eps)


def normalize_bwd(x, v_y, eps: float = NORMALIZE_EPS):
    """Adjoint of :func:`normalize` given its input ``x [..., D]`` and ``v_y [..., D]``: ``v_x``."""
    if _is_dev(x):
        d = x.shape[-1]
        v_x = cla.empty_like(x)
        _dev_kernel(x.context, x.dtype, "bwd")(x, v_y, v_x, np.int32(d), x.dtype.type(eps), range=slice(x.size // d))
        return v_x
    inv = 1.0 / np.sqrt(np.sum(x * x, axis=-1, keepdims=True) + eps)
    y = x * inv
    return (v_y - y * np.sum(y * v_y, axis=-1, keepdims=True)) * inv


# ---- tape functions -----------------------------------------------------------------------------
class Sigmoid(Function):
    """Tape op: ``y = sigmoid(x)``."""

    def forward(self, ctx, x):
        ctx.y = sigmoid(x)
        return ctx.y

    def backward(self, ctx, v_y):
        return sigmoid_bwd(ctx.y, v_y)


class Softplus(Function):
    """Tape op: ``y = softplus(x)``."""

    def forward(self, ctx, x):
        ctx.x = x
        return softplus(x)

    def backward(self, ctx, v_y):
        return softplus_bwd(ctx.x, v_y)


class Exp(Function):
    """Tape op: ``y = exp(x)``."""

    def forward(self, ctx, x):
        ctx.y = exp(x)
        return ctx.y

    def backward(self, ctx, v_y):
        return exp_bwd(ctx.y, v_y)


class Normalize(Function):
    """Tape op: ``y = normalize(x, eps)`` over the last axis."""

    def __init__(self, eps: float = NORMALIZE_EPS):
        self.eps = eps

    def forward(self, ctx, x):
        ctx.x = x
        return normalize(x, self.eps)

    def backward(self, ctx, v_y):
        return normalize_bwd(ctx.x, v_y, self.eps)
