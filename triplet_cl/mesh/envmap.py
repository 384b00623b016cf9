"""The SH environment light as an image: numpy SH evaluation and a lat-long (equirectangular) EXR.

Real spherical harmonics, same convention as ``kernels_cl/common/sh.h`` (index ``k = l*l + l + m``;
``Y_{l,m} = sqrt2 Re Y_l^m`` for ``m > 0``, ``sqrt2 Im Y_l^|m|`` for ``m < 0``, Condon-Shortley phase
included), evaluated with the same polynomial recurrence in the unit direction ``(x, y, z)``.

Lat-long convention (Y up, as glTF and Mitsuba 3, whose envmap emitter rendered the test scenes):
a pixel at row ``i``, column ``j`` of an ``H x 2H`` image has ``u = (j + 0.5) / W``,
``v = (i + 0.5) / H``, polar angle ``theta = pi v`` from ``+Y`` and azimuth ``phi = 2 pi u``; it shows
the radiance arriving from the world direction

    d = (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi))

so the top row is ``+Y`` (up), the left/right edges ``-Z``, a quarter across ``+X``, the centre
column ``+Z``. :func:`latlong_uv` is the inverse mapping.
"""

from __future__ import annotations

import os
import tempfile
from math import factorial, pi, sqrt
from pathlib import Path

import numpy as np

from ..lights import SHEnvironmentLight


def sh_basis(degree: int, dirs) -> np.ndarray:
    """Real SH ``Y_k(d)`` for ``k < (degree+1)^2``.

    Args:
        degree: largest band ``l`` (0..8 in the kernels; any here).
        dirs: ``[..., 3]`` unit directions.
    Returns:
        ``[..., (degree+1)^2] float64``.
    """
    d = np.asarray(dirs, np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"sh_basis: dirs must have shape [..., 3], got {list(d.shape)}")
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + ((degree + 1) ** 2,))
    cm, sm, qmm = np.ones_like(x), np.zeros_like(x), 1.0  # (x + iy)^m and Q_m^m
    for m in range(degree + 1):
        if m > 0:
            cm, sm = x * cm - y * sm, x * sm + y * cm
            qmm *= -(2 * m - 1)
        q_prev2 = q_prev = None
        for l in range(m, degree + 1):
            if l == m:
                q = np.full_like(z, qmm)
            elif l == m + 1:
                q = (2 * m + 1) * z * qmm
            else:
                q = ((2 * l - 1) * z * q_prev - (l + m - 1) * q_prev2) / (l - m)
            k = sqrt((2 * l + 1) / (4 * pi) * factorial(l - m) / factorial(l + m))
            c = l * l + l
            if m == 0:
                out[..., c] = k * q
            else:
                out[..., c + m] = sqrt(2) * k * q * cm
                out[..., c - m] = sqrt(2) * k * q * sm
            q_prev2, q_prev = q_prev, q
    return out


def environment_lights(lights) -> list[SHEnvironmentLight]:
    """The :class:`SHEnvironmentLight` objects among ``lights``."""
    return [lt for lt in lights if isinstance(lt, SHEnvironmentLight)]


def eval_environment(lights, dirs) -> np.ndarray:
    """Radiance of the SH environment light(s) arriving from unit directions ``dirs [..., 3]``.

    ``L(d) = sum over SH environment lights of sum_{k < (degree+1)^2} coeffs[:, k] Y_k(d)`` (only the
    active bands, as the shading kernel; other light types are ignored). Returns ``[..., 3] float64``
    (unclamped: a low-order SH can go negative). Raises ``ValueError`` when there is no SH
    environment light.
    """
    envs = environment_lights(_as_list(lights))
    if not envs:
        raise ValueError(f"no SHEnvironmentLight among the lights (found {_kinds(lights)})")
    d = np.asarray(dirs, np.float64)
    out = np.zeros(d.shape[:-1] + (3,))
    for lt in envs:
        nk = (lt.degree + 1) ** 2
        out += sh_basis(lt.degree, d) @ lt.coeffs[:, :nk].T
    return out


def latlong_directions(height: int) -> np.ndarray:
    """World directions of the pixel centres of an ``height x 2*height`` lat-long image:
    ``[H, 2H, 3] float64`` (see the module docstring for the convention)."""
    h, w = int(height), 2 * int(height)
    theta = pi * (np.arange(h) + 0.5) / h
    phi = 2 * pi * (np.arange(w) + 0.5) / w
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.sin(phi), ct, -st * np.cos(phi)), axis=-1)


def latlong_uv(dirs) -> np.ndarray:
    """Inverse of the lat-long mapping: ``[..., 3]`` directions → ``[..., 2]`` ``(u, v)`` in [0, 1]
    (``u`` along the width, ``v`` down the height)."""
    d = np.asarray(dirs, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.mod(np.arctan2(d[..., 0], -d[..., 2]) / (2 * pi), 1.0)
    v = np.arccos(np.clip(d[..., 1], -1, 1)) / pi
    return np.stack([u, v], -1)


def render_envmap(lights, height: int = 256, clamp_negative: bool = True) -> np.ndarray:
    """The lat-long image ``[H, 2H, 3] float32`` of the SH environment light(s) (linear radiance)."""
    if int(height) < 1:
        raise ValueError(f"envmap height must be >= 1, got {height}")
    img = eval_environment(lights, latlong_directions(height))
    if clamp_negative:
        img = np.maximum(img, 0.0)
    return img.astype(np.float32)


def rotation_y(deg: float) -> np.ndarray:
    """Right-handed rotation by ``deg`` degrees about +Y (column vectors), ``[3, 3]``."""
    t = np.radians(deg)
    c, s = float(np.cos(t)), float(np.sin(t))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def project_envmap(img, degree: int = 2, rotate_y_deg: float = 0.0) -> np.ndarray:
    """SH coefficients of a lat-long radiance map (the inverse of :func:`render_envmap` up to the
    band limit): ``c_k = sum_pixels L(d) Y_k(R d) dOmega`` with the pixel solid angle
    ``dOmega = (2 pi / W)(pi / H) sin(theta)`` (midpoint rule) and ``R = R_y(rotate_y_deg)`` (the map
    rotated about +Y, as Mitsuba's ``to_world``).

    Args:
        img: ``[H, W, 3]`` linear radiance in this module's lat-long convention (any ``W``).
        degree: largest SH band of the result.
        rotate_y_deg: rotation of the map about +Y, degrees (right-handed).
    Returns:
        ``coeffs [3, (degree+1)^2] float64``, ready for :class:`SHEnvironmentLight`.
    """
    img = np.asarray(img, np.float64)
    if img.ndim != 3 or img.shape[2] < 3:
        raise ValueError(f"project_envmap: img must have shape [H, W, 3], got {list(img.shape)}")
    h, w = img.shape[:2]
    theta = pi * (np.arange(h) + 0.5) / h
    phi = 2 * pi * (np.arange(w) + 0.5) / w
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack(np.broadcast_arrays(st * np.sin(phi), ct, -st * np.cos(phi)), axis=-1)
    if rotate_y_deg:
        d = d @ rotation_y(rotate_y_deg).T
    dw = (2 * pi / w) * (pi / h) * np.sin(theta)  # [H]
    out = np.zeros((3, (degree + 1) ** 2))
    for i0 in range(0, h, 64):  # rows in blocks: the basis is [64, W, K] at a time, not [H, W, K]
        Y = sh_basis(degree, d[i0:i0 + 64])
        out += np.einsum("hwk,hwc,h->ck", Y, img[i0:i0 + 64, :, :3], dw[i0:i0 + 64])
    return out


def read_envmap_sh(path, degree: int = 2) -> np.ndarray:
    """:func:`project_envmap` of a lat-long image file (EXR / HDR, read with OpenImageIO):
    ``coeffs [3, (degree+1)^2]``, e.g. to compare a trained SH environment with a ground-truth map."""
    from ..datasets.images import read_image

    return project_envmap(read_image(path, unpremultiply=False).rgb, degree)  # (any alpha: radiance as stored)


def export_envmap(lights, path, height: int = 256, dtype: str = "half", clamp_negative: bool = True) -> Path:
    """Write the SH environment light(s) as a lat-long RGB OpenEXR (linear radiance), atomically.

    Args:
        lights: a sequence of :mod:`triplet_cl.lights` objects (or a ``MeshAsset``'s ``lights``); the
            :class:`SHEnvironmentLight` ones are summed, the others ignored.
        path: output ``.exr`` path. height: image height ``H`` (width ``2H``).
        dtype: ``"half"`` or ``"float"`` channels. clamp_negative: clamp negative SH radiance to 0.
    Returns:
        ``path``. Raises ``ValueError`` when ``lights`` holds no SH environment light.
    """
    if dtype not in ("half", "float"):
        raise ValueError(f"export_envmap: dtype must be 'half' or 'float', got {dtype!r}")
    if environment_lights(_as_list(lights)) == []:
        raise ValueError(f"export_envmap: no SHEnvironmentLight to write (lights: {_kinds(lights)})")
    img = render_envmap(lights, height, clamp_negative)
    write_exr(path, img, dtype)
    return Path(path)


def write_exr(path, img: np.ndarray, dtype: str = "half") -> None:
    """Atomic OpenEXR write of ``img [H, W, C] float`` (C = 1, 3 or 4) through OpenImageIO."""
    import OpenImageIO as oiio

    img = np.ascontiguousarray(img, np.float32)
    if img.ndim != 3:
        raise ValueError(f"write_exr: img must have shape [H, W, C], got {list(img.shape)}")
    h, w, c = img.shape
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".exr", dir=path.parent)
    try:  # from the file's creation on: a signal between it and the write took the temporary file with it (a battery)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would make the result private
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise OSError(f"OpenImageIO cannot write EXR files: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, oiio.HALF if dtype == "half" else oiio.FLOAT)
        spec.attribute("compression", "zip")
        if not out.open(tmp, spec) or not out.write_image(img):
            err = out.geterror()
            out.close()
            raise OSError(f"cannot write {path}: {err}")
        out.close()
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _as_list(lights) -> list:
    return list(getattr(lights, "lights", lights) or [])


def _kinds(lights) -> str:
    ls = _as_list(lights)
    return ", ".join(type(lt).__name__ for lt in ls) if ls else "none"
