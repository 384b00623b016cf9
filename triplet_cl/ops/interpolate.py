"""Per-vertex attributes → fragments, and the adjoint (``kernels_cl/interpolate.cl``)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .binning import TILE
from .common import buf, check_contiguous, check_real, device_rows, grid_1d, to_device
from .fragment_bwd import fragments_backward
from .fragments import Fragments


def _attr(device: Device, attr, frags: Fragments) -> cla.Array:
    n = frags.mesh.num_vertices
    if isinstance(attr, cla.Array):
        if attr.ndim != 2 or attr.shape[0] != n:
            raise ValueError(f"attr must have shape [{n}, C], got {list(attr.shape)}")
        if attr.dtype != frags.real:
            raise ValueError(f"attr must have dtype {frags.real} (as the fragments), got {attr.dtype}")
        check_contiguous("attr", attr)
        return attr
    return to_device(device.queue, check_real("attr", attr, (n, None), frags.real))


def interpolate(device: Device, attr, frags: Fragments) -> cla.Array:
    """Interpolate per-vertex attributes to every fragment.

    Args:
        attr: ``[N, C]`` per-vertex attributes (any C ≥ 1).
        frags: the :class:`~triplet_cl.ops.raster.Fragments` of the view.

    Returns:
        ``[P, C]`` device array, in the fragments' packed order (:class:`~triplet_cl.ops.raster.Fragments`).
    """
    a = _attr(device, attr, frags)
    C, P = a.shape[1], frags.P
    out = device_rows(device, (P, max(C, 1)), frags.real)
    if C and P:
        device.kernel("interpolate", "interpolate_fwd", {"TILE": TILE}, frags.real)(
            device.queue, *grid_1d(P), a.data, frags.mesh.F.data, buf(frags.face, device.queue),
            buf(frags.bary, device.queue), np.int32(P), np.int32(C), buf(out, device.queue))
    return out[:, :C] if C != out.shape[1] else out


def interpolate_backward(device: Device, attr, frags: Fragments, v_out, v_bary_acc=None):
    """Adjoint of :func:`interpolate`.

    Args:
        attr: ``[N, C]`` the attributes of the forward pass.
        v_out: ``[P, C]`` adjoint of the interpolated attributes.
        v_bary_acc: optional ``[P, 2]`` barycentric adjoint of other interpolations of the
            view, added to this one's.

    Returns:
        ``(v_attr [N, C], v_bary [P, 2])`` device arrays; pass ``v_bary`` to
        :func:`~triplet_cl.ops.raster.raster_backward`. (A renderer that packs its attributes
        into one array calls :func:`~triplet_cl.ops.raster.fragments_backward` once instead.)
    """
    return fragments_backward(device, frags, attr=attr, v_attr_frag=v_out, v_bary=v_bary_acc, geometry=False)
