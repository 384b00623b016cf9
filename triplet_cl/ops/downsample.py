"""The box filter of a supersampled render and its adjoint (``downsample.cl``).

The mesh stage renders at ``f ×`` the camera's resolution and averages each ``f × f`` block (linear premultiplied
radiance and alpha, before the photos' transfer function: as a camera integrates a pixel). On the device, so that the
supersampled image never comes to the host (it did, and numpy's mean over it cost ~10 ms of a 100 ms mesh step).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_empty, grid_1d


def _real(name: str, a) -> np.dtype:
    if not isinstance(a, cla.Array):
        raise ValueError(f"{name} must be a device array, got {type(a).__name__}")
    if a.dtype not in (np.float32, np.float64):
        raise ValueError(f"{name} must be float32 or float64, got {a.dtype}")
    if not a.flags.c_contiguous:
        raise ValueError(f"{name} must be C-contiguous")
    return np.dtype(a.dtype)


def _shape(x: cla.Array, f: int) -> tuple[int, int, int]:
    if not isinstance(f, (int, np.integer)) or f < 1:
        raise ValueError(f"the box filter's factor must be an integer >= 1, got {f!r}")
    if x.ndim not in (2, 3) or x.shape[0] % f or x.shape[1] % f:
        raise ValueError(f"x must be [H*f, W*f(, C)] with f = {f}, got {list(x.shape)}")
    return x.shape[0] // f, x.shape[1] // f, (x.shape[2] if x.ndim == 3 else 1)


def box_down(device: Device, x: cla.Array, f: int) -> cla.Array:
    """``[H f, W f(, C)] → [H, W(, C)]``: the mean of each ``f × f`` block (device arrays, float32 or float64)."""
    real = _real("x", x)
    H, W, C = _shape(x, f)
    y = device_empty(device.queue, (H, W) + tuple(x.shape[2:]), real, allocator=device.allocator)
    if H * W * C:
        device.kernel("downsample", "box_down", real=real)(device.queue, *grid_1d(H * W), x.data, np.int32(H),
                                                          np.int32(W), np.int32(f), np.int32(C), y.data)
    return y


def box_up(device: Device, v_y: cla.Array, f: int) -> cla.Array:
    """The adjoint of :func:`box_down`: ``[H, W(, C)] → [H f, W f(, C)]``, each pixel's cotangent / f² spread over
    its block."""
    real = _real("v_y", v_y)
    if not isinstance(f, (int, np.integer)) or f < 1:
        raise ValueError(f"the box filter's factor must be an integer >= 1, got {f!r}")
    if v_y.ndim not in (2, 3):
        raise ValueError(f"v_y must be [H, W(, C)], got {list(v_y.shape)}")
    H, W = v_y.shape[:2]
    C = v_y.shape[2] if v_y.ndim == 3 else 1
    v_x = device_empty(device.queue, (H * f, W * f) + tuple(v_y.shape[2:]), real, allocator=device.allocator)
    if H * W * C:
        device.kernel("downsample", "box_up", real=real)(device.queue, *grid_1d(H * W * f * f), v_y.data,
                                                        np.int32(H), np.int32(W), np.int32(f), np.int32(C), v_x.data)
    return v_x
