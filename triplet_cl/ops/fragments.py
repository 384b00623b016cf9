"""The packed K-nearest fragments of a view (:class:`Fragments`): the data every per-fragment op
reads (interpolate, coverage, composite, shading, columns) and the fragment adjoint
(:mod:`~triplet_cl.ops.fragment_bwd`) walks. Made by :func:`~triplet_cl.ops.raster.rasterize` and
the ray tracer (``ops/trace.py``); no kernel of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import fragment_array
from .mesh import DeviceMesh


@dataclass
class Fragments:
    """The K nearest fragments of every pixel, packed, plus the binning the adjoint needs.

    Packed layout: pixel ``p = y * W + x`` has ``count[y, x]`` (≤ K) fragments, nearest first, at
    rows ``off[p] : off[p] + count[y, x]`` of every per-fragment array (``off`` the exclusive prefix
    sum of ``count``; ``P = off[H * W]`` fragments in all). Device arrays:
        face ``[P] int32``, bary ``[P, 2]`` perspective-correct (λ0, λ1; λ2 = 1 − λ0 − λ1),
        depth ``[P]`` camera-space depth, entry ``[P] int32`` (the (tile, face) entry of the
        fragment), count ``[H, W] int32``, off ``[H*W + 1] int32``; the binning: tile_off ``[T+1]``,
        face_off ``[M+1]``, face_entries ``[E]``, entry_setup ``[E, SETUP]``, entry_face ``[E]``.

    Every per-fragment array derived from them (interpolated attributes, windows, shaded colours,
    adjoints) is ``[P]`` or ``[P, C]`` in the same order. :meth:`to_hwk` / :meth:`from_hwk` convert
    host arrays to and from the padded ``[H, W, K, ...]`` view (tests, tools); :func:`read_fragments`
    gives host copies of the fragments in that view.
    """

    width: int
    height: int
    K: int
    tiles_x: int
    tiles_y: int
    num_entries: int
    real: np.dtype
    face: cla.Array
    entry: cla.Array
    bary: cla.Array
    depth: cla.Array
    count: cla.Array
    tile_off: cla.Array
    face_off: cla.Array
    face_entries: cla.Array
    vs: cla.Array
    mesh: DeviceMesh
    win: cla.Array | None = None  # [P] coverage window when rasterized with a sigma
    sigma: float | None = None
    entry_setup: cla.Array | None = None  # [E, SETUP] edge-function set-up of each entry (Binning)
    entry_face: cla.Array | None = None  # [E] face of each entry (Binning)
    soft_edges: bool = False  # the window covers only some edges (rasterize(soft_edges=...))
    off: cla.Array | None = None  # [H*W + 1] first row of each pixel's fragments
    P: int = 0  # number of fragments
    # [P] exp(-sigma d) of each window (win = 1 - win_ex) where the rasterizer computed it in its own pass: the adjoint
    # reads it instead of taking the exp again (fragment_bwd.cl WIN_EX); None: the adjoint computes it
    win_ex: cla.Array | None = None

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, K)``: the image and the most fragments a pixel may have."""
        return (self.height, self.width, self.K)

    def fshape(self, C: int | None = None) -> tuple[int, ...]:
        """Shape of a per-fragment array: ``(P,)`` or ``(P, C)``."""
        return (self.P,) if C is None else (self.P, C)

    def _slots(self) -> np.ndarray:
        """Host ``[P]``: the padded slot ``pixel * K + k`` of every packed row."""
        count = self.count.get().reshape(-1).astype(np.int64)
        off = self.off.get()[:-1].astype(np.int64)
        pix = np.repeat(np.arange(count.size), count)
        return pix * self.K + (np.arange(self.P) - off[pix])

    def to_hwk(self, x, fill=0) -> np.ndarray:
        """Host ``[P, ...]`` per-fragment values → ``[H, W, K, ...]`` (``fill`` in the empty slots)."""
        x = x.get() if isinstance(x, cla.Array) else np.asarray(x)
        if x.shape[0] != self.P:
            raise ValueError(f"expected a per-fragment array with {self.P} rows, got {list(x.shape)}")
        slot = self._slots()
        out = np.full((self.height * self.width * self.K,) + x.shape[1:], fill, dtype=x.dtype)
        out[slot] = x
        return out.reshape((self.height, self.width, self.K) + x.shape[1:])

    def from_hwk(self, x) -> np.ndarray:
        """Host ``[H, W, K, ...]`` padded values → ``[P, ...]`` (the valid slots, packed)."""
        x = np.asarray(x)
        if x.shape[:3] != self.shape:
            raise ValueError(f"expected an array of shape [{self.height}, {self.width}, {self.K}, ...], "
                             f"got {list(x.shape)}")
        slot = self._slots()
        return np.ascontiguousarray(x.reshape((-1,) + x.shape[3:])[slot])


def frag_input(device: Device, frags: Fragments, name: str, a, C: int | None = None, real=None) -> cla.Array | None:
    """A per-fragment input on the device: ``[P]`` / ``[P, C]`` (device or numpy), or a numpy array in the
    padded ``[H, W, K(, C)]`` view (packed here). ``None`` passes through. Shape and dtype are checked,
    values are not (a padded array may hold anything in its empty slots)."""
    if a is None:
        return None
    real = frags.real if real is None else np.dtype(real)
    shape = frags.fshape(C)
    if not isinstance(a, cla.Array):
        arr = np.asarray(a)
        if arr.ndim == len(shape) + 2 and arr.shape[:3] == frags.shape:
            a = frags.from_hwk(arr)
    return fragment_array(device.queue, name, a, shape, real)


def read_fragments(frags: Fragments) -> dict[str, np.ndarray]:
    """Host copies of the fragments in the padded ``[H, W, K, ...]`` view (tests, debugging, tools):
    face/entry −1 and zero barycentrics/depth in the empty slots; ``count [H, W]``."""
    out = {"face": frags.to_hwk(frags.face, -1), "bary": frags.to_hwk(frags.bary, 0),
           "depth": frags.to_hwk(frags.depth, 0), "entry": frags.to_hwk(frags.entry, -1), "count": frags.count.get()}
    return out


def valid_faces(frags: Fragments) -> np.ndarray:
    """``[H, W, K] int32`` face ids on the host, −1 beyond each pixel's count."""
    return frags.to_hwk(frags.face, -1)


__all__ = ["Fragments", "frag_input", "read_fragments", "valid_faces"]
