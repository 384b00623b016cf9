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


class Compaction:
    """The valid fragment slots of a view as a dense list: ``pack`` / ``unpack`` between
    ``[H, W, K, C]`` (slots beyond a pixel's count ignored) and ``[Pv, n]``, ``Pv`` = Σ counts."""

    def __init__(self, device: Device, frags: Fragments):
        from .raster import _offsets

        self.device, self.frags = device, frags
        self.offsets, self.P = _offsets(device, frags.count.reshape(-1))

    def pack(self, x: cla.Array, c0: int, n: int) -> cla.Array:
        """``x[..., c0:c0+n]`` of the valid slots → ``[Pv, n]``."""
        d, fr = self.device, self.frags
        H, W, K = fr.shape
        out = cla.empty(d.queue, (max(self.P, 1), n), fr.real, allocator=d.allocator)
        d.kernel("columns", "pack_rows", real=fr.real)(
            d.queue, (H * W,), None, x.data, np.int32(x.shape[-1]), np.int32(c0), np.int32(n), self.offsets.data,
            fr.count.data, np.int32(H * W), np.int32(K), out.data)
        return out[: self.P] if self.P else out[:0]

    def unpack(self, src: cla.Array, dst: cla.Array, c0: int) -> None:
        """Write ``src [Pv, n]`` into ``dst[..., c0:c0+n]`` at the valid slots."""
        d, fr = self.device, self.frags
        H, W, K = fr.shape
        if self.P == 0:
            return
        d.kernel("columns", "unpack_rows", real=fr.real)(
            d.queue, (H * W,), None, src.data, np.int32(src.shape[-1]), self.offsets.data, fr.count.data,
            np.int32(H * W), np.int32(K), dst.data, np.int32(dst.shape[-1]), np.int32(c0))
