"""Split and pack channel blocks of per-fragment arrays on the device (``kernels_cl/columns.cl``)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import buf
from .raster import Fragments


def copy_columns(device: Device, frags: Fragments, src: cla.Array | None, cs0: int, dst: cla.Array, cd0: int,
                 n: int, accumulate: bool = False) -> None:
    """``dst[..., cd0:cd0+n] (+)= src[..., cs0:cs0+n]`` over the valid fragment slots (zeros when
    ``src`` is None). Both arrays are ``[H, W, K, C]`` device arrays of the fragments' dtype."""
    H, W, K = frags.shape
    Cd = dst.shape[-1]
    Cs = src.shape[-1] if src is not None else 1
    if dst.shape[:3] != (H, W, K) or (src is not None and src.shape[:3] != (H, W, K)):
        raise ValueError("copy_columns: arrays must be [H, W, K, C] of the fragments")
    if cd0 + n > Cd or (src is not None and cs0 + n > Cs):
        raise ValueError("copy_columns: channel range out of bounds")
    device.kernel("columns", "copy_columns", real=frags.real)(
        device.queue, (H * W,), None, buf(src, device.queue), np.int32(Cs), np.int32(cs0), dst.data, np.int32(Cd),
        np.int32(cd0), np.int32(n), frags.count.data, np.int32(H * W), np.int32(K), np.int32(src is not None),
        np.int32(bool(accumulate)))


def split(device: Device, frags: Fragments, x: cla.Array, sizes: list[int]) -> list[cla.Array]:
    """Split ``[H, W, K, C]`` into blocks of ``sizes`` channels (each ``[H, W, K, s]``)."""
    out, c0 = [], 0
    for s in sizes:
        y = cla.empty(device.queue, x.shape[:3] + (s,), x.dtype, allocator=device.allocator)
        copy_columns(device, frags, x, c0, y, 0, s)
        out.append(y)
        c0 += s
    return out


def pack(device: Device, frags: Fragments, blocks: list[cla.Array | None], sizes: list[int]) -> cla.Array:
    """Inverse of :func:`split`; ``None`` blocks become zeros."""
    H, W, K = frags.shape
    y = cla.empty(device.queue, (H, W, K, sum(sizes)), frags.real, allocator=device.allocator)
    c0 = 0
    for b, s in zip(blocks, sizes, strict=True):
        copy_columns(device, frags, None if b is None else b.reshape(H, W, K, s), 0, y, c0, s)
        c0 += s
    return y
