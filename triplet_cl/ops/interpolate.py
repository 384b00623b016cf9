"""Per-vertex attributes → fragments, and the adjoint (``kernels_cl/interpolate.cl``)."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import check_real, to_device
from .raster import TILE, Fragments, fragments_backward


def _attr(device: Device, attr, frags: Fragments) -> cla.Array:
    n = frags.mesh.num_vertices
    if isinstance(attr, cla.Array):
        if attr.ndim != 2 or attr.shape[0] != n:
            raise ValueError(f"attr must have shape [{n}, C], got {list(attr.shape)}")
        if attr.dtype != frags.real:
            raise ValueError(f"attr must have dtype {frags.real} (as the fragments), got {attr.dtype}")
        return attr
    return to_device(device.queue, check_real("attr", attr, (n, None), frags.real))


def interpolate(device: Device, attr, frags: Fragments) -> cla.Array:
    """Interpolate per-vertex attributes to every fragment.

    Args:
        attr: ``[N, C]`` per-vertex attributes (any C ≥ 1).
        frags: the :class:`~triplet_cl.ops.raster.Fragments` of the view.

    Returns:
        ``[H, W, K, C]`` device array. Like every per-fragment array, only the first
        ``frags.count[y, x]`` slots of a pixel are defined (the others are never read).
    """
    a = _attr(device, attr, frags)
    H, W, K = frags.shape
    C = a.shape[1]
    out = cla.empty(device.queue, (H, W, K, max(C, 1)), frags.real, allocator=device.allocator)
    if C:
        device.kernel("interpolate", "interpolate_fwd", {"TILE": TILE}, frags.real)(
            device.queue, (H * W,), None, a.data, frags.mesh.F.data, frags.face.data, frags.bary.data,
            frags.count.data, np.int32(H * W), np.int32(K), np.int32(C), out.data)
    return out[..., :C] if C != out.shape[3] else out


def interpolate_backward(device: Device, attr, frags: Fragments, v_out, v_bary_acc=None):
    """Adjoint of :func:`interpolate`.

    Args:
        attr: ``[N, C]`` the attributes of the forward pass.
        v_out: ``[H, W, K, C]`` adjoint of the interpolated attributes.
        v_bary_acc: optional ``[H, W, K, 2]`` barycentric adjoint of other interpolations of the
            view, added to this one's.

    Returns:
        ``(v_attr [N, C], v_bary [H, W, K, 2])`` device arrays; pass ``v_bary`` to
        :func:`~triplet_cl.ops.raster.raster_backward`. (A renderer that packs its attributes
        into one array calls :func:`~triplet_cl.ops.raster.fragments_backward` once instead.)
    """
    return fragments_backward(device, frags, attr=attr, v_attr_frag=v_out, v_bary=v_bary_acc, geometry=False)
