"""The pixel filters of a supersampled render and their adjoints (``downsample.cl``).

The mesh stage renders at ``f ×`` the camera's resolution and filters it down to the camera's pixels (linear
premultiplied radiance and alpha, before the photos' transfer function: as a camera integrates a pixel). On the
device, so that the supersampled image never comes to the host (it did, and numpy's mean over it cost ~10 ms of a
100 ms mesh step).

:func:`box_down` averages each ``f × f`` block. :func:`gauss_down` is a camera's reconstruction filter instead: each
pixel is the mean of the supersamples near its centre weighted by a Gaussian of standard deviation ``sigma`` pixels
truncated at ``4 sigma`` (Mitsuba 3's film default is ``sigma`` 0.5; Blender Cycles' 1.5-pixel Blackman-Harris is
close to it), normalised by the weights of the supersamples inside the image, as a film divides by its weights;
separable, one pass per axis (:func:`filter_weights` gives the weights).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_empty, grid_1d, launch


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
        raise ValueError(f"the pixel filter's factor must be an integer >= 1, got {f!r}")
    if x.ndim not in (2, 3) or x.shape[0] % f or x.shape[1] % f:
        raise ValueError(f"x must be [H*f, W*f(, C)] with f = {f}, got {list(x.shape)}")
    return x.shape[0] // f, x.shape[1] // f, (x.shape[2] if x.ndim == 3 else 1)


def _adjoint_shape(v_y: cla.Array, f: int) -> tuple[int, int, int]:
    """``(H, W, C)`` of an adjoint's ``v_y [H, W(, C)]``, with the factor checked."""
    if not isinstance(f, (int, np.integer)) or f < 1:
        raise ValueError(f"the pixel filter's factor must be an integer >= 1, got {f!r}")
    if v_y.ndim not in (2, 3):
        raise ValueError(f"v_y must be [H, W(, C)], got {list(v_y.shape)}")
    return v_y.shape[0], v_y.shape[1], (v_y.shape[2] if v_y.ndim == 3 else 1)


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
    H, W, C = _adjoint_shape(v_y, f)
    v_x = device_empty(device.queue, (H * f, W * f) + tuple(v_y.shape[2:]), real, allocator=device.allocator)
    if H * W * C:
        device.kernel("downsample", "box_up", real=real)(device.queue, *grid_1d(H * W * f * f), v_y.data,
                                                        np.int32(H), np.int32(W), np.int32(f), np.int32(C), v_x.data)
    return v_x


#: the Gaussian's standard deviation, in pixels: from MIN_SIGMA every pixel's window holds a supersample at any factor
#: (4 sigma reaches past the 0.5 / f between a pixel's centre and its nearest supersample for every f >= 1)
MIN_SIGMA, MAX_SIGMA = 0.1, 4.0


def check_pixel_sigma(name: str, sigma, allow_box: bool = True) -> float:
    """``sigma`` as a float when it is 0 (the box; with ``allow_box``) or a standard deviation in
    [``MIN_SIGMA``, ``MAX_SIGMA``] pixels; else a ``ValueError`` naming ``name`` (every boundary that takes a pixel
    filter — the render settings, the mesh config, the command line — checks it here)."""
    try:
        v = float(sigma)
    except (TypeError, ValueError):
        v = float("nan")
    if not ((allow_box and v == 0) or MIN_SIGMA <= v <= MAX_SIGMA):  # NaN fails too
        box = "0 (the box) or " if allow_box else ""
        raise ValueError(f"{name} must be {box}a standard deviation in [{MIN_SIGMA}, {MAX_SIGMA}] pixels, "
                         f"got {sigma!r}")
    return v


def filter_weights(f: int, sigma: float, length: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The Gaussian pixel filter along one axis of ``length`` output pixels, each ``f`` supersamples wide:
    ``(wt [f + 2 R], inv_norm [length], R)``, float64. ``wt[t - l f + R]`` is the weight of supersample ``t`` for output
    ``l``, ``exp(−d² / 2σ²) − exp(−r² / 2σ²)`` for ``|d| < r = 4σ`` (``d``: the distance between their centres in
    output pixels), and ``inv_norm[l]`` one over the sum of the weights of ``l``'s supersamples inside
    ``[0, length f)``; ``R = ceil(r f)`` supersamples on each side of an output's own ``f``."""
    if not isinstance(f, (int, np.integer)) or f < 1:
        raise ValueError(f"the pixel filter's factor must be an integer >= 1, got {f!r}")
    sigma = check_pixel_sigma("the pixel filter's sigma", sigma, allow_box=False)
    radius = 4.0 * sigma
    R = int(np.ceil(radius * f))
    j = np.arange(f + 2 * R)  # t − l f + R
    d = (j - R + 0.5) / f - 0.5
    two_var = 2.0 * sigma * sigma
    wt = np.where(np.abs(d) < radius, np.exp(-d * d / two_var) - np.exp(-radius * radius / two_var), 0.0)
    l = np.arange(length)
    t = l[:, None] * f - R + j[None, :]
    norm = (wt[None, :] * ((t >= 0) & (t < length * f))).sum(axis=1)
    if not (norm > 0).all():  # no supersample within the radius of some pixel's centre (cannot happen above MIN_SIGMA)
        raise ValueError(f"the pixel filter of sigma {sigma} reaches no supersample of a pixel at factor {f}")
    return wt, 1.0 / norm, R


def _gauss_launch(device: Device, kernel: str, x: cla.Array, out_shape: tuple, f: int, sigma: float, length: int,
                  **sizes) -> cla.Array:
    """One pass of the Gaussian filter (``kernels_cl/downsample.cl`` ``kernel``, built for ``F = f``) into a new
    array of ``out_shape``; ``length`` output pixels along the filtered axis."""
    real = np.dtype(x.dtype)
    wt, inv_norm, R = _device_weights(device, f, sigma, length, real)
    y = device_empty(device.queue, out_shape, real, allocator=device.allocator)
    n = int(np.prod(out_shape)) // max(sizes.get("C", 1), 1)
    if n and sizes.get("C", 1) and sizes.get("K", 1):
        launch(device, "downsample", kernel, *grid_1d(n), defines={"F": int(f)}, real=real, src=x, wt=wt,
               inv_norm=inv_norm, R=R, dst=y, **sizes)
    return y


def _device_weights(device: Device, f: int, sigma: float, length: int, real) -> tuple[cla.Array, cla.Array, int]:
    """:func:`filter_weights` on the device, kept by the device (``Device.cached``) per (f, sigma, length, dtype): a
    mesh stage filters the same sizes every step, and an upload per call is a blocking write that waits for the
    queue."""
    def make():
        wt, inv_norm, R = filter_weights(f, sigma, length)
        return cla.to_device(device.queue, wt.astype(real)), cla.to_device(device.queue, inv_norm.astype(real)), R

    return device.cached(("gauss_weights", int(f), float(sigma), int(length), np.dtype(real).str), make)


def gauss_down(device: Device, x: cla.Array, f: int, sigma: float) -> cla.Array:
    """``[H f, W f(, C)] → [H, W(, C)]``: the Gaussian pixel filter (module docstring; device arrays, float32 or
    float64, C ≤ 4). With ``f = 1`` it blurs the image by the filter."""
    _real("x", x)
    H, W, C = _shape(x, f)
    if C > 4:
        raise ValueError(f"the Gaussian pixel filter takes at most 4 channels, got {C}")
    tmp = _gauss_launch(device, "gauss_rows_down", x, (H * f, W, C), f, sigma, W, O=H * f, L=W, C=C)
    y = _gauss_launch(device, "gauss_cols_down", tmp, (H, W * C), f, sigma, H, L=H, K=W * C)
    return y.reshape((H, W) + tuple(x.shape[2:]))


def gauss_up(device: Device, v_y: cla.Array, f: int, sigma: float) -> cla.Array:
    """The adjoint of :func:`gauss_down`: ``[H, W(, C)] → [H f, W f(, C)]``."""
    _real("v_y", v_y)
    H, W, C = _adjoint_shape(v_y, f)
    if C > 4:
        raise ValueError(f"the Gaussian pixel filter takes at most 4 channels, got {C}")
    v_tmp = _gauss_launch(device, "gauss_cols_up", v_y, (H * f, W * C), f, sigma, H, L=H, K=W * C)
    v_x = _gauss_launch(device, "gauss_rows_up", v_tmp, (H * f, W * f, C), f, sigma, W, O=H * f, L=W, C=C)
    return v_x.reshape((H * f, W * f) + tuple(v_y.shape[2:]))


def _rgba_args(name: str, rgb: cla.Array, a: cla.Array | None) -> np.dtype:
    """The dtype of a radiance ``rgb [h, w, 3]`` and its alpha ``a [h, w]`` (None: no alpha, the adjoint's zero)."""
    real = _real(name, rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{name} must be [H, W, 3], got {list(rgb.shape)}")
    if a is not None:
        if _real(f"{name}'s alpha", a) != real or a.shape != rgb.shape[:2]:
            raise ValueError(f"{name}'s alpha must be [{rgb.shape[0]}, {rgb.shape[1]}] {real.name}, got "
                             f"{list(a.shape)} {a.dtype}")
    return real


def _blocks8(n: int) -> int:
    """The blocks of eight outputs of a row of ``n`` (the row passes' work-items: ``gauss4_rows_*8``)."""
    return (int(n) + 7) // 8


def _gauss4(device: Device, kernel: str, n: int, f: int, sigma: float, length: int, real, has_va: bool = False,
            **args) -> None:
    """One ``gauss4_*`` pass over ``n`` work-items, the weights of ``length`` outputs along its axis."""
    wt, inv_norm, R = _device_weights(device, f, sigma, length, real)
    if n:
        defines = {"F": int(f), "GR": int(R), "NTAP": int(f + 2 * R)}
        if has_va:
            defines["HAS_VA"] = 1
        launch(device, "downsample", kernel, *grid_1d(n), defines=defines, real=real, wt=wt, inv_norm=inv_norm, **args)


def gauss_down_rgba(device: Device, rgb: cla.Array, a: cla.Array, f: int, sigma: float) -> tuple[cla.Array, cla.Array]:
    """:func:`gauss_down` of a render's radiance ``rgb [H f, W f, 3]`` and alpha ``a [H f, W f]`` together: one
    four-channel pass per axis (``downsample.cl`` ``gauss4_*``) instead of two filters; ``([H, W, 3], [H, W])``, the
    same values."""
    real = _rgba_args("rgb", rgb, a)
    H, W, _ = _shape(rgb, f)
    O = H * f
    tmp = device_empty(device.queue, (O, W, 4), real, allocator=device.allocator)
    _gauss4(device, "gauss4_rows_down8", O * _blocks8(W), f, sigma, W, real, rgb=rgb, a=a, O=O, L=W, dst=tmp)
    y = device_empty(device.queue, (H, W, 3), real, allocator=device.allocator)
    ya = device_empty(device.queue, (H, W), real, allocator=device.allocator)
    _gauss4(device, "gauss4_cols_down", H * W, f, sigma, H, real, src=tmp, L=H, W=W, rgb=y, a=ya)
    return y, ya


def gauss_up_rgba(device: Device, v_rgb: cla.Array, v_a: cla.Array | None, f: int,
                  sigma: float) -> tuple[cla.Array, cla.Array]:
    """The adjoint of :func:`gauss_down_rgba`: ``(v_rgb [H, W, 3], v_a [H, W] or None = 0) → ([H f, W f, 3],
    [H f, W f])``."""
    real = _rgba_args("v_rgb", v_rgb, v_a)
    H, W, _ = _adjoint_shape(v_rgb, f)
    O = H * f
    tmp = device_empty(device.queue, (O, W, 4), real, allocator=device.allocator)
    va = {} if v_a is None else {"v_a": v_a}
    _gauss4(device, "gauss4_cols_upF", H * W, f, sigma, H, real, has_va=v_a is not None, v_rgb=v_rgb, L=H, W=W,
            dst=tmp, **va)
    vx = device_empty(device.queue, (O, W * f, 3), real, allocator=device.allocator)
    vxa = device_empty(device.queue, (O, W * f), real, allocator=device.allocator)
    _gauss4(device, "gauss4_rows_up8", O * _blocks8(W), f, sigma, W, real, src=tmp, O=O, L=W, v_rgb=vx, v_a=vxa)
    return vx, vxa
