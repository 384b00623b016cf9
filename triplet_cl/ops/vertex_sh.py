"""The per-vertex SH light of the Triplet method (``kernels_cl/vertex_sh.cl``) and the raw SH basis.

Per vertex ``i`` with coefficients ``coeffs [N, 6, (D+1)^2]`` (channels 0-2: incoming radiance,
3-5: incoming light direction, pointing from the surface towards the light), evaluated along the
view direction ``d = normalize(cam - V_i)`` with the real SH of ``kernels_cl/common/sh.h``::

    s_j = sum_{k < (deg+1)^2} Y_k(d) coeffs[i, j, k]
    out[i, 0:3] = relu(s_{0:3} + 0.5)        radiance
    out[i, 3:6] = s_{3:6}                    direction wi (normalised later, per fragment, by shade)

``deg`` (the active degree of the band schedule) is a run-time argument ``<= D``; the program is
compiled once per storage degree ``D``. Init of the method (docs/ARCHITECTURE.md §8): radiance DC
``0.5 / Y_00 = 0.5 sqrt(4 pi)`` (radiance 1), direction DC ``0.1 * randn``, higher bands 0.

The output ``[N, 6]`` is interpolated to fragments by the rasterizer's interpolate op and passed to
``triplet_cl.ops.shade`` as ``vlight``.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device, get_device
from .common import check_real, empty, to_device, to_host
from .common import run_1d as _run

MAX_DEGREE = 8


def _degree_of(nk: int, name: str) -> int:
    d = int(round(np.sqrt(nk))) - 1
    if (d + 1) ** 2 != nk or d < 0 or d > MAX_DEGREE:
        raise ValueError(f"{name} must have (D+1)^2 coefficients with D <= {MAX_DEGREE}, got {nk}")
    return d


def check_cam(cam) -> np.ndarray:
    """Validate a camera centre ``[3]`` (integers accepted) and return it as float64."""
    a = np.asarray(cam)
    if a.dtype.kind in "iu":
        a = a.astype(np.float64)
    return check_real("cam", a, (3,), np.float64)


def _cam_args(cam, real):
    t = np.dtype(real).type
    return t(cam[0]), t(cam[1]), t(cam[2])


# ---- device-level pair -----------------------------------------------------------------------


def forward(dev: Device, V: cla.Array, coeffs: cla.Array, cam: np.ndarray, degree: int, real=np.float32) -> cla.Array:
    """``[N, 6]`` vertex-SH light of device arrays ``V [N, 3]``, ``coeffs [N, 6, (D+1)^2]``."""
    N, D = V.shape[0], _degree_of(coeffs.shape[2], "coeffs")
    out = empty(dev.queue, (N, 6), real)
    k = dev.kernel("vertex_sh", "vertex_sh_fwd", {"VSH_MAX_DEG": D}, real)
    _run(dev, k, N, V.data, coeffs.data, *_cam_args(cam, real), np.int32(N), np.int32(degree), out.data)
    return out


def backward(dev: Device, V: cla.Array, coeffs: cla.Array, cam: np.ndarray, degree: int, v_out: cla.Array,
             real=np.float32) -> tuple[cla.Array, cla.Array]:
    """``(v_coeffs [N, 6, (D+1)^2], v_V [N, 3])`` from ``v_out [N, 6]``."""
    N, D = V.shape[0], _degree_of(coeffs.shape[2], "coeffs")
    v_coeffs = empty(dev.queue, coeffs.shape, real)
    v_V = empty(dev.queue, (N, 3), real)
    k = dev.kernel("vertex_sh", "vertex_sh_bwd", {"VSH_MAX_DEG": D}, real)
    _run(dev, k, N, V.data, coeffs.data, *_cam_args(cam, real), np.int32(N), np.int32(degree), v_out.data,
         v_coeffs.data, v_V.data)
    return v_coeffs, v_V


# ---- validating public functions -------------------------------------------------------------


def _prep(V, coeffs, cam, degree, real):
    V = check_real("V", V, (None, 3), real)
    coeffs = check_real("coeffs", coeffs, (V.shape[0], 6, None), real)
    D = _degree_of(coeffs.shape[2], "coeffs")
    cam = check_cam(cam)
    degree = D if degree is None else int(degree)
    if not 0 <= degree <= D:
        raise ValueError(f"degree must lie in [0, {D}] (the stored degree of coeffs), got {degree}")
    return V, coeffs, cam, degree


def vertex_sh(V, coeffs, cam, degree: int | None = None, *, device: Device | None = None,
              real=np.float32) -> np.ndarray:
    """Per-vertex SH light.

    Args:
        V: ``[N, 3]`` vertex positions.
        coeffs: ``[N, 6, (D+1)^2]`` SH coefficients, ``D <= 8`` (radiance rgb, direction xyz).
        cam: ``[3]`` camera centre.
        degree: active degree ``<= D`` (default ``D``).
    Returns:
        ``[N, 6]``: radiance ``relu(sum Y c[0:3] + 0.5)`` and direction ``sum Y c[3:6]``.
    """
    dev = device or get_device()
    V, coeffs, cam, degree = _prep(V, coeffs, cam, degree, real)
    if V.shape[0] == 0:
        return np.zeros((0, 6), real)
    q = dev.queue
    return to_host(forward(dev, to_device(q, V), to_device(q, coeffs), cam, degree, real))


def vertex_sh_backward(V, coeffs, cam, v_out, degree: int | None = None, *, device: Device | None = None,
                       real=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Adjoint of :func:`vertex_sh`: ``v_out [N, 6]`` → ``(v_coeffs [N, 6, (D+1)^2], v_V [N, 3])``."""
    dev = device or get_device()
    V, coeffs, cam, degree = _prep(V, coeffs, cam, degree, real)
    v_out = check_real("v_out", v_out, (V.shape[0], 6), real)
    if V.shape[0] == 0:
        return np.zeros(coeffs.shape, real), np.zeros((0, 3), real)
    q = dev.queue
    v_c, v_V = backward(dev, to_device(q, V), to_device(q, coeffs), cam, degree, to_device(q, v_out), real)
    return to_host(v_c), to_host(v_V)


def sh_basis(dirs, degree: int, *, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Real SH basis ``[n, (degree+1)^2]`` of directions ``dirs [n, 3]`` (unit for true SH values)."""
    dev = device or get_device()
    dirs = check_real("dirs", dirs, (None, 3), real)
    if not 0 <= int(degree) <= MAX_DEGREE:
        raise ValueError(f"degree must lie in [0, {MAX_DEGREE}], got {degree}")
    n, nk = dirs.shape[0], (int(degree) + 1) ** 2
    if n == 0:
        return np.zeros((0, nk), real)
    out = empty(dev.queue, (n, nk), real)
    k = dev.kernel("vertex_sh", "sh_basis_fwd", real=real)
    _run(dev, k, n, to_device(dev.queue, dirs).data, np.int32(n), np.int32(degree), out.data)
    return to_host(out)


def sh_basis_backward(dirs, degree: int, v_Y, *, device: Device | None = None, real=np.float32) -> np.ndarray:
    """Adjoint of :func:`sh_basis` (of the SH polynomial): ``v_Y [n, (degree+1)^2]`` → ``v_dirs [n, 3]``."""
    dev = device or get_device()
    dirs = check_real("dirs", dirs, (None, 3), real)
    if not 0 <= int(degree) <= MAX_DEGREE:
        raise ValueError(f"degree must lie in [0, {MAX_DEGREE}], got {degree}")
    n, nk = dirs.shape[0], (int(degree) + 1) ** 2
    v_Y = check_real("v_Y", v_Y, (n, nk), real)
    if n == 0:
        return np.zeros((0, 3), real)
    q = dev.queue
    out = empty(q, (n, 3), real)
    k = dev.kernel("vertex_sh", "sh_basis_bwd", real=real)
    _run(dev, k, n, to_device(q, dirs).data, np.int32(n), np.int32(degree), to_device(q, v_Y).data, out.data)
    return to_host(out)
