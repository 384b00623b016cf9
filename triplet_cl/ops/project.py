"""Projection of world vertices to the screen and its adjoint (``kernels_cl/project.cl``).

``vs = (u, v, z)``: pixel coordinates and camera-space depth; the adjoint optionally also gives the
gradient of the world-to-camera matrix (camera refinement).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..camera import Camera
from ..device import Device
from .common import check_real, check_shape, const_array, device_rows, grid_1d, real_of, to_device


def camera_params(camera: Camera, real=np.float32) -> np.ndarray:
    """The 16 numbers the kernels read: R (row-major), t, fx, fy, cx, cy."""
    w = camera.w2c
    return np.concatenate([w[:3, :3].reshape(-1), w[:3, 3], [camera.fx, camera.fy, camera.cx, camera.cy]]).astype(real)


def _cam_buffer(device: Device, camera: Camera, real) -> cla.Array:
    return const_array(device, camera_params(camera, real))


def project(device: Device, V, camera: Camera) -> cla.Array:
    """Project world vertices to screen.

    Args:
        V: ``[N, 3]`` world positions (numpy or device array; float32 or float64 selects REAL).
        camera: the :class:`~triplet_cl.camera.Camera`.

    Returns:
        ``vs [N, 3]`` device array of (u, v, z): pixel coordinates and camera-space depth.
    """
    real = real_of(V, "V") if hasattr(V, "dtype") and np.dtype(V.dtype).kind == "f" else np.float32
    V = check_real("V", V, (None, 3), real)
    n = V.shape[0]
    Vd = to_device(device.queue, V)
    vs = device_rows(device, (n, 3), real)
    if n:
        k = device.kernel("project", "project_fwd", real=real)
        k(device.queue, *grid_1d(n), Vd.data, _cam_buffer(device, camera, real).data, np.int32(n), vs.data)
    return vs


def project_backward(device: Device, V, camera: Camera, v_vs, pose_grad: bool = False):
    """Adjoint of :func:`project`.

    Args:
        V: ``[N, 3]`` world positions (as given to :func:`project`).
        v_vs: ``[N, 3]`` adjoint of (u, v, z).
        pose_grad: also return the adjoint of the world-to-camera matrix.

    Returns:
        ``v_V [N, 3]`` device array, and with ``pose_grad`` also ``v_w2c [4, 4]`` numpy (float64;
        only the top 3×4 block is non-zero).
    """
    real = real_of(V, "V")
    V = check_real("V", V, (None, 3), real)
    n = V.shape[0]
    check_shape("v_vs", v_vs, (n, 3))
    q = device.queue
    Vd, gd = to_device(q, V), to_device(q, np.asarray(v_vs, real) if not isinstance(v_vs, cla.Array) else v_vs)
    v_V = device_rows(device, (n, 3), real)
    v_pc = device_rows(device, (n, 3), real)
    if n:
        k = device.kernel("project", "project_bwd", real=real)
        k(q, *grid_1d(n), Vd.data, _cam_buffer(device, camera, real).data, gd.data, np.int32(n), v_V.data, v_pc.data)
    if not pose_grad:
        return v_V
    vp = v_pc.get().astype(np.float64)
    Vh = Vd.get().astype(np.float64)
    g = np.zeros((4, 4))
    g[:3, :3] = vp.T @ Vh
    g[:3, 3] = vp.sum(0)
    return v_V, g


__all__ = ["camera_params", "project", "project_backward"]
