"""The fragments that compositing reaches, before shading (``kernels_cl/prune.cl``).

Compositing (``composite.cl``) stops at the first fragment that brings a pixel's transmittance below ``t_min``; the
fragments behind it are still interpolated, shaded and taken through the adjoints, all for a weight of exactly zero.
:func:`prune_fragments` drops them once the opacity and the coverage window are known (after interpolation), with a
margin (it keeps fragments down to ``t_min / 2``), so that the composite and every adjoint of the kept list equal the
full list's. For an opaque mesh (alpha ``1 - 1e-5``) that is the front fragment of every covered pixel; the mesh
stage's renders had two (the front and the back face of the object). The binning is unchanged: an entry whose
fragments were all dropped simply has none (``fragment_bwd`` skips it).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import buf, device_empty, grid_1d
from .fragments import Fragments
from .scan import prefix_offsets

PRUNE_MARGIN = 0.5  # keep fragments down to T < PRUNE_MARGIN × t_min (rounding against composite.cl's T)


def prune_fragments(device: Device, frags: Fragments, fa: cla.Array, alpha_col: int, win: cla.Array | None,
                    t_min: float) -> tuple[Fragments, cla.Array, cla.Array | None]:
    """``(frags, fa [P2, C], win [P2])`` without the fragments behind each pixel's ``t_min`` cut-off.

    Args:
        frags: the view's fragments; fa: ``[P, C]`` their interpolated attributes, the opacity in column
            ``alpha_col``; win: ``[P]`` their coverage windows (None: 1); t_min: the compositing's cut-off (> 0).
    """
    P, C = fa.shape
    if P != frags.P:
        raise ValueError(f"fa must have one row per fragment ({frags.P}), got {P}")
    if not 0 <= alpha_col < C:
        raise ValueError(f"alpha_col must be in [0, {C - 1}], got {alpha_col}")
    if not (np.isfinite(t_min) and t_min > 0):
        raise ValueError(f"t_min must be a positive number, got {t_min!r}")
    if win is not None and win.shape != (P,):
        raise ValueError(f"win must have shape [{P}], got {list(win.shape)}")
    q, alloc, real = device.queue, device.allocator, frags.real
    npix = frags.width * frags.height
    if P == 0 or npix == 0:
        return frags, fa, win
    has_win = np.int32(win is not None)
    win_b = buf(win, q) if win is not None else buf(fa, q)  # unread without a window
    count2 = device_empty(q, max(npix, 1), np.int32, allocator=alloc)[:npix]
    device.kernel("prune", "prune_count", real=real)(
        q, *grid_1d(npix), buf(fa, q), np.int32(C), np.int32(alpha_col), win_b, has_win, frags.count.data,
        frags.off.data, np.int32(npix), real.type(PRUNE_MARGIN * t_min), count2.data)
    off2, P2 = prefix_offsets(device, count2)
    if P2 == P:  # nothing to drop
        return frags, fa, win
    rows = max(P2, 1)
    face2 = device_empty(q, rows, np.int32, allocator=alloc)[:P2]
    entry2 = device_empty(q, rows, np.int32, allocator=alloc)[:P2]
    bary2 = device_empty(q, (rows, 2), real, allocator=alloc)[:P2]
    depth2 = device_empty(q, rows, real, allocator=alloc)[:P2]
    win2 = device_empty(q, rows, real, allocator=alloc)[:P2] if win is not None else None
    fa2 = device_empty(q, (rows, C), real, allocator=alloc)[:P2]
    device.kernel("prune", "prune_pack", real=real)(
        q, *grid_1d(npix), count2.data, frags.off.data, off2.data, np.int32(npix), np.int32(C), has_win,
        buf(frags.face, q), buf(frags.entry, q), buf(frags.bary, q), buf(frags.depth, q), win_b, buf(fa, q),
        buf(face2, q), buf(entry2, q), buf(bary2, q), buf(depth2, q), buf(win2, q) if win2 is not None else buf(fa2, q),
        buf(fa2, q))
    count2 = count2.reshape(frags.count.shape)
    out = replace(frags, face=face2, entry=entry2, bary=bary2, depth=depth2, count=count2, off=off2, P=P2,
                  win=win2 if frags.win is not None else None, win_ex=None)  # (the adjoint takes the window's exp
    # again: where pruning runs, the mesh stage's, only silhouette fragments have one)
    return out, fa2, win2


__all__ = ["PRUNE_MARGIN", "prune_fragments"]
