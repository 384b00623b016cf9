"""The photos' image formation after linear compositing (``kernels_cl/color.cl``).

Photos stored with 8/16 bits hold **straight-alpha, sRGB-encoded** colour, and the dataset loader
composites them over the background in that encoded space. The renderer shades and composites
linear radiance over a black background (premultiplied ``C [H, W, 3]``, accumulated alpha
``A [H, W]``); the model of a photo pixel is then

    out = A · s(C / max(A, eps)) + (1 − A) · bg

with ``s`` the sRGB transfer function (IEC 61966-2-1, extended by its power law above 1).
:func:`srgb_composite` / :func:`srgb_composite_backward` are the kernel pair (device arrays),
:class:`SRGBComposite` the tape :class:`~triplet_cl.autodiff.Function` of the render graph, and
:func:`srgb_encode` / :func:`srgb_decode` the plain transfer on the host (exports, metrics).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..autodiff import Function
from ..device import Device, get_device
from .common import check_real, device_empty, grid_1d, to_device

ALPHA_EPS = 1e-6  # below this accumulated alpha the straight colour is C / eps (no division by ~0)


def _bg3(bg) -> tuple[float, float, float]:
    b = np.broadcast_to(np.asarray(bg, np.float64), (3,))
    if not np.isfinite(b).all():
        raise ValueError(f"background must be 3 finite values, got {list(b)}")
    return float(b[0]), float(b[1]), float(b[2])


def _check_pair(C: cla.Array, A: cla.Array) -> int:
    if C.ndim < 1 or C.shape[-1] != 3:
        raise ValueError(f"C must have shape [..., 3], got {list(C.shape)}")
    if tuple(A.shape) != tuple(C.shape[:-1]):
        raise ValueError(f"A must have shape {list(C.shape[:-1])} (C's without the channel), got {list(A.shape)}")
    if C.dtype != A.dtype:
        raise ValueError(f"C and A must have the same dtype, got {C.dtype} and {A.dtype}")
    return int(np.prod(A.shape))


def _defines(clip: bool) -> dict | None:
    return {"SRGB_CLIP": True} if clip else None


def srgb_composite(dev: Device, C: cla.Array, A: cla.Array, bg, eps: float = ALPHA_EPS,
                   clip: bool = False, keep_root: bool = False):
    """``out [..., 3]`` (device) of linear premultiplied ``C [..., 3]`` and alpha ``A [...]`` over ``bg``; ``clip``:
    the encoded colour saturates at 1 (a photo's sensor / 8-bit range, ``color.cl``'s ``SRGB_CLIP``).
    ``keep_root``: returns ``(out, root)``, ``root [..., 3]`` the per-channel roots ``u^(1/2.4)`` that
    :func:`srgb_composite_backward` takes back (``color.cl``'s ``KEEP_ROOT``: no exp2/log2 in the adjoint)."""
    n = _check_pair(C, A)
    real = C.dtype
    out = device_empty(dev.queue, C.shape, real, allocator=dev.allocator)
    root = device_empty(dev.queue, C.shape, real, allocator=dev.allocator) if keep_root else None
    if n:
        t = real.type
        g, loc = grid_1d(3 * n)  # a work-item per channel value (color.cl)
        defines = {**(_defines(clip) or {}), "KEEP_ROOT": keep_root}
        dev.kernel("color", "srgb_composite_fwd", defines=defines, real=real)(
            dev.queue, g, loc, C.data, A.data, *(t(x) for x in _bg3(bg)), t(eps), np.int32(n),
            *((root.data,) if keep_root else ()), out.data)
    return (out, root) if keep_root else out


def srgb_composite_backward(dev: Device, C: cla.Array, A: cla.Array, bg, v_out: cla.Array,
                            eps: float = ALPHA_EPS, clip: bool = False,
                            root: cla.Array | None = None) -> tuple[cla.Array, cla.Array]:
    """``(v_C [..., 3], v_A [...])`` (device) of the cotangent ``v_out [..., 3]``; ``root``: the forward's roots
    (:func:`srgb_composite` with ``keep_root``), read instead of computed (the same result, bit for bit)."""
    n = _check_pair(C, A)
    if tuple(v_out.shape) != tuple(C.shape):
        raise ValueError(f"v_out must have shape {list(C.shape)}, got {list(v_out.shape)}")
    if root is not None and (tuple(root.shape) != tuple(C.shape) or root.dtype != C.dtype):
        raise ValueError(f"root must have shape {list(C.shape)} and dtype {C.dtype}, got {list(root.shape)} "
                         f"{root.dtype}")
    real = C.dtype
    v_C = device_empty(dev.queue, C.shape, real, allocator=dev.allocator)
    v_A = device_empty(dev.queue, A.shape, real, allocator=dev.allocator)
    if n:
        t = real.type
        g, loc = grid_1d(n)
        defines = {**(_defines(clip) or {}), "HAS_ROOT": root is not None}
        dev.kernel("color", "srgb_composite_bwd", defines=defines, real=real)(
            dev.queue, g, loc, C.data, A.data, *(t(x) for x in _bg3(bg)), t(eps), np.int32(n),
            v_out.astype(real).data, *((root.data,) if root is not None else ()), v_C.data, v_A.data)
    return v_C, v_A


def _device_pair(dev: Device, C, A, real):
    if isinstance(C, cla.Array) and isinstance(A, cla.Array):
        return C.astype(real) if C.dtype != real else C, A.astype(real) if A.dtype != real else A
    C = check_real("C", np.asarray(C.get() if isinstance(C, cla.Array) else C), (*np.shape(C)[:-1], 3), real)
    A = check_real("A", np.asarray(A.get() if isinstance(A, cla.Array) else A), np.shape(C)[:-1], real)
    return to_device(dev.queue, C), to_device(dev.queue, A)


def srgb_composite_host(C, A, bg, *, eps: float = ALPHA_EPS, device: Device | None = None,
                        real=np.float32, clip: bool = False) -> np.ndarray:
    """:func:`srgb_composite` of host arrays (validated), returned on the host."""
    dev = device or get_device()
    Cd, Ad = _device_pair(dev, C, A, np.dtype(real))
    return srgb_composite(dev, Cd, Ad, bg, eps, clip).get()


def srgb_composite_backward_host(C, A, bg, v_out, *, eps: float = ALPHA_EPS, device: Device | None = None,
                                 real=np.float32, clip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`srgb_composite_backward` of host arrays, returned on the host."""
    dev = device or get_device()
    Cd, Ad = _device_pair(dev, C, A, np.dtype(real))
    v = to_device(dev.queue, check_real("v_out", np.asarray(v_out), Cd.shape, np.dtype(real)))
    v_C, v_A = srgb_composite_backward(dev, Cd, Ad, bg, v, eps, clip)
    return v_C.get(), v_A.get()


class SRGBComposite(Function):
    """``(C [H, W, 3], A [H, W]) → out [H, W, 3]``: the photo model of the module docstring (device arrays)."""

    def __init__(self, device: Device, background, real=np.float32, eps: float = ALPHA_EPS, clip: bool = False):
        self.device, self.bg, self.real, self.eps, self.clip = device, _bg3(background), np.dtype(real), eps, clip

    def forward(self, ctx, C, A):
        Cd, Ad = _device_pair(self.device, C, A, self.real)
        ctx.C, ctx.A = Cd, Ad
        out, ctx.root = srgb_composite(self.device, Cd, Ad, self.bg, self.eps, self.clip, keep_root=True)
        return out

    def backward(self, ctx, v_out):
        if not isinstance(v_out, cla.Array):
            v_out = np.broadcast_to(np.asarray(v_out, self.real), ctx.C.shape)
            v_out = cla.to_device(self.device.queue, np.ascontiguousarray(v_out))
        return srgb_composite_backward(self.device, ctx.C, ctx.A, self.bg, v_out, self.eps, self.clip, root=ctx.root)


def srgb_encode(x) -> np.ndarray:
    """The sRGB transfer function on the host (linear → encoded; negative values stay linear)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def srgb_decode(y) -> np.ndarray:
    """The inverse of :func:`srgb_encode` (encoded → linear)."""
    y = np.asarray(y, np.float64)
    return np.where(y <= 0.04045, y / 12.92, np.power(np.maximum(y + 0.055, 0) / 1.055, 2.4))
