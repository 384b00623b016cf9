"""Density control's per-view visibility from the packed fragments, on the device
(``kernels_cl/face_visibility.cl``): which faces have a fragment (:func:`visible_mask`) and the
nearest (sufficiently opaque) face of every pixel (:func:`front_face_map`).

:func:`triplet_cl.density.visible_faces` and :func:`triplet_cl.density.front_faces` compute the same
on the host from downloaded ``[P]`` face ids (and, for the alpha-aware nearest face, a sort over the
fragments); they are the reference these kernels are tested against (``tests/test_density.py``).
Here only ``[M]`` bytes or ``[H, W]`` ints come down. Integer work only: the results are exact.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_empty, grid_1d, launch


def visible_mask(dev: Device, face: cla.Array, num_faces: int) -> np.ndarray:
    """Host ``[M] bool``: faces ``0 <= f < num_faces`` with at least one entry in the device face ids
    ``face`` (``[P] int32``, −1 = empty)."""
    if face.dtype != np.int32:
        raise ValueError(f"face must be a device array of dtype int32, got {face.dtype}")
    m = int(num_faces)
    if m < 0:
        raise ValueError(f"num_faces must be >= 0, got {num_faces}")
    vis = cla.zeros(dev.queue, max(m, 1), np.uint8, allocator=dev.allocator)
    P = int(face.size)
    if P and m:
        launch(dev, "face_visibility", "visible_mark", *grid_1d(P), face=face, P=P, M=m, vis=vis)
    return vis.get()[:m].astype(bool)


def front_face_map(dev: Device, frags, face_ok: np.ndarray | None = None) -> np.ndarray:
    """Host ``[H, W] int64``: the first packed fragment's face of every pixel of ``frags``
    (:class:`~triplet_cl.ops.fragments.Fragments`), or with ``face_ok`` (``[M] bool``) the first face
    whose ``face_ok`` is set; −1 where none."""
    H, W = int(frags.height), int(frags.width)
    npix = H * W
    front = device_empty(dev.queue, max(npix, 1), np.int32, allocator=dev.allocator)
    if npix:
        face = frags.face if frags.P else cla.zeros(dev.queue, 1, np.int32, allocator=dev.allocator)
        args = dict(count=frags.count, off=frags.off, face=face, npix=npix, front=front)
        defines = None
        if face_ok is not None:
            ok = np.ascontiguousarray(np.asarray(face_ok, bool).reshape(-1), np.uint8)
            args["face_ok"] = cla.to_device(dev.queue, ok if ok.size else np.zeros(1, np.uint8))
            defines = {"FACE_OK": 1}
        launch(dev, "face_visibility", "front_face", *grid_1d(npix), defines=defines, **args)
    return front.get()[:npix].astype(np.int64).reshape(H, W)
