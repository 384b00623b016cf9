"""Split and pack channel blocks of per-fragment arrays on the device (``kernels_cl/columns.cl``)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import buf, device_empty, grid_1d
from .fragments import Fragments


def copy_columns(device: Device, frags: Fragments, src: cla.Array | None, cs0: int, dst: cla.Array, cd0: int,
                 n: int, accumulate: bool = False) -> None:
    """``dst[:, cd0:cd0+n] (+)= src[:, cs0:cs0+n]`` over the fragments (zeros when ``src`` is None).
    Both arrays are ``[P, C]`` device arrays of the fragments' dtype (``P = frags.P``)."""
    P = frags.P
    Cd = dst.shape[-1]
    Cs = src.shape[-1] if src is not None else 1
    if dst.shape[0] != P or dst.ndim != 2 or (src is not None and (src.shape[0] != P or src.ndim != 2)):
        raise ValueError(f"copy_columns: arrays must be [P, C] with P = {P} fragments, got "
                         f"{list(dst.shape)} and {None if src is None else list(src.shape)}")
    if cd0 + n > Cd or (src is not None and cs0 + n > Cs):
        raise ValueError("copy_columns: channel range out of bounds")
    if P == 0 or n == 0:
        return
    device.kernel("columns", "copy_columns", real=frags.real)(
        device.queue, *grid_1d(P), buf(src, device.queue), np.int32(Cs), np.int32(cs0), buf(dst, device.queue),
        np.int32(Cd), np.int32(cd0), np.int32(n), np.int32(P), np.int32(src is not None), np.int32(bool(accumulate)))


SPLIT_BLOCKS = 8  # channel blocks per split_columns / merge_columns launch (columns.cl)


def _block_args(device: Device, arrays, cols, ns) -> list:
    args = []
    for k in range(SPLIT_BLOCKS):
        if k < len(arrays):
            args += [buf(arrays[k], device.queue), np.int32(cols[k]), np.int32(ns[k])]
        else:
            args += [buf(None, device.queue), np.int32(0), np.int32(0)]
    return args


def split_columns(device: Device, frags: Fragments, src: cla.Array, blocks) -> list[cla.Array]:
    """``[src[:, c0:c0+n] for (c0, n) in blocks]`` as new dense ``[P, n]`` arrays, in one pass over
    the fragments (at most ``SPLIT_BLOCKS`` blocks; what ``copy_columns`` does once per block)."""
    P, real = frags.P, frags.real
    blocks = [(int(c0), int(n)) for c0, n in blocks]
    if len(blocks) > SPLIT_BLOCKS:
        raise ValueError(f"split_columns: at most {SPLIT_BLOCKS} blocks, got {len(blocks)}")
    Cs = src.shape[-1] if src.ndim == 2 else 1
    if src.shape[0] != P or any(c0 < 0 or n < 1 or c0 + n > Cs for c0, n in blocks):
        raise ValueError(f"split_columns: src must be [P = {P}, C] and every block inside its {Cs} channels, "
                         f"got {list(src.shape)} and {blocks}")
    outs = [device_empty(device.queue, (max(P, 1), n), real, allocator=device.allocator)[:P] for _, n in blocks]
    if P and blocks:
        device.kernel("columns", "split_columns", real=real)(
            device.queue, *grid_1d(P), buf(src, device.queue), np.int32(Cs), np.int32(P),
            *_block_args(device, outs, [c0 for c0, _ in blocks], [n for _, n in blocks]))
    return outs


def merge_columns(device: Device, frags: Fragments, parts, dst: cla.Array) -> None:
    """``dst[:, c0:c0+n] = s`` for every ``(s [P, n], c0)`` of ``parts`` in one pass over the
    fragments (at most ``SPLIT_BLOCKS``; the inverse of :func:`split_columns`)."""
    P = frags.P
    parts = [(s if s.ndim == 2 else s.reshape(P, 1), int(c0)) for s, c0 in parts]
    if len(parts) > SPLIT_BLOCKS:
        raise ValueError(f"merge_columns: at most {SPLIT_BLOCKS} blocks, got {len(parts)}")
    Cd = dst.shape[-1]
    if dst.ndim != 2 or dst.shape[0] != P or any(s.shape[0] != P or c0 < 0 or c0 + s.shape[1] > Cd
                                                 for s, c0 in parts):
        raise ValueError(f"merge_columns: arrays must be [P = {P}, C] and every block inside dst's {Cd} channels")
    if P and parts:
        device.kernel("columns", "merge_columns", real=frags.real)(
            device.queue, *grid_1d(P), buf(dst, device.queue), np.int32(Cd), np.int32(P),
            *_block_args(device, [s for s, _ in parts], [c0 for _, c0 in parts], [s.shape[1] for s, _ in parts]))


class Compaction:
    """Channel blocks of a view's per-fragment arrays as their own dense arrays: ``pack`` /
    ``unpack`` between ``[P, C]`` and ``[P, n]`` (``P = frags.P``; the fragments are packed
    already, so this moves columns only). ``offsets`` is the fragments' ``off``."""

    def __init__(self, device: Device, frags: Fragments):
        self.device, self.frags = device, frags
        self.offsets, self.P = frags.off, frags.P

    def _rows(self, x: cla.Array) -> cla.Array:
        """``x`` as ``[P, C]`` (``[P]`` → ``[P, 1]``; explicit sizes: P may be 0)."""
        return x if x.ndim == 2 else x.reshape(self.P, 1)

    def pack(self, x: cla.Array, c0: int, n: int) -> cla.Array:
        """``x[:, c0:c0+n]`` → a new ``[P, n]`` array."""
        d, fr = self.device, self.frags
        out = device_empty(d.queue, (max(self.P, 1), n), fr.real, allocator=d.allocator)[: self.P]
        copy_columns(d, fr, self._rows(x), c0, out, 0, n)
        return out

    def unpack(self, src: cla.Array, dst: cla.Array, c0: int) -> None:
        """Write ``src [P, n]`` into ``dst[:, c0:c0+n]``."""
        src = self._rows(src)
        copy_columns(self.device, self.frags, src, 0, self._rows(dst), c0, src.shape[1])
