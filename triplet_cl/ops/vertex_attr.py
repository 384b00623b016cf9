"""The per-vertex attribute array the rasterizer interpolates, built on the device
(``kernels_cl/vertex_attr.cl``): ``pos | nrm | mat | alpha [| vlight]`` from the vertex positions,
a normal array (per vertex, or per face of a soup in the training layout), the raw material
channels (sigmoid, or softplus where the BRDF says so) and the raw alpha (sigmoid), and its adjoint.

:class:`triplet_cl.render.VertexAttributes` is the op on the tape; the host chain ``Normals →
MaterialActivation → SigmoidHost → Concat`` computes the same array and is its reference
(``tests/test_render.py``). On a CPU device the host chain spends most of its time in numpy
passes and host ↔ device copies of ``[N, C]`` arrays; here one kernel writes the array where the
rasterizer reads it and one kernel takes its adjoint apart.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from .common import device_rows, grid_1d, launch

VA_LANES = 8  # vertices per work-item of vertex_attr_fwd (vertex_attr.cl: its activations as REAL8 lanes)


def attr_defines(nmat: int, softplus_cols, face_nrm: bool, has_vlight: bool, nconst: int = 0) -> dict:
    """The build defines of ``vertex_attr.cl`` (softplus channels as a bit mask; ``nconst`` constant
    columns after the others)."""
    mask = 0
    for j in softplus_cols:
        if not 0 <= j < nmat:
            raise ValueError(f"softplus column {j} outside the {nmat} material channels")
        mask |= 1 << int(j)
    if nmat > 30:
        raise ValueError(f"at most 30 material channels (a 32-bit mask), got {nmat}")
    return {"NMAT": int(nmat), "SOFTPLUS_MASK": mask, "FACE_NRM": bool(face_nrm), "HAS_VLIGHT": bool(has_vlight),
            "HAS_CONST": nconst > 0, "NCONST": int(nconst)}


def num_channels(nmat: int, has_vlight: bool, nconst: int = 0) -> int:
    """``C`` of the attribute array: 3 + 3 + nmat + 1 (+ 6) (+ nconst)."""
    return 7 + int(nmat) + (6 if has_vlight else 0) + int(nconst)


def vertex_attr(dev: Device, V: cla.Array, nrm: cla.Array, mat_raw: cla.Array, alpha_raw: cla.Array,
                vlight: cla.Array | None, softplus_cols, face_nrm: bool, real=np.float32,
                const: cla.Array | None = None) -> cla.Array:
    """``attr [N, C]`` (device) from device arrays ``V [N, 3]``, ``nrm [N, 3]`` (``face_nrm``: ``[N / 3, 3]``,
    vertex i on face i // 3), ``mat_raw [N, Cm]``, ``alpha_raw [N]``, optionally ``vlight [N, 6]`` and
    ``const [N, k]`` (constant columns copied last, e.g. a cached visibility; no adjoint)."""
    N, nmat = V.shape[0], mat_raw.shape[1]
    if N == 0:
        raise ValueError("vertex_attr needs at least one vertex")
    rows = N // 3 if face_nrm else N
    if (face_nrm and N % 3) or nrm.shape != (rows, 3) or mat_raw.shape[0] != N or alpha_raw.size != N \
            or (vlight is not None and vlight.shape != (N, 6)) or (const is not None and (const.ndim != 2 or
                                                                  const.shape[0] != N or const.shape[1] < 1)):
        raise ValueError(f"vertex_attr: inconsistent shapes V {list(V.shape)}, nrm {list(nrm.shape)}, "
                         f"mat_raw {list(mat_raw.shape)}, alpha_raw {list(alpha_raw.shape)}")
    nconst = 0 if const is None else const.shape[1]
    attr = device_rows(dev, (N, num_channels(nmat, vlight is not None, nconst)), real)
    args = dict(V=V, nrm=nrm, mat_raw=mat_raw, alpha_raw=alpha_raw, N=N, attr=attr)
    if vlight is not None:
        args["vlight"] = vlight
    if const is not None:
        args["cst"] = const
    defines = attr_defines(nmat, softplus_cols, face_nrm, vlight is not None, nconst)
    launch(dev, "vertex_attr", "vertex_attr_fwd", *grid_1d(-(-N // VA_LANES)), defines=defines, real=real, **args)
    return attr


def vertex_attr_backward(dev: Device, mat_raw: cla.Array, attr: cla.Array, v_attr: cla.Array, softplus_cols,
                         has_vlight: bool, real=np.float32, nconst: int = 0):
    """Adjoint of :func:`vertex_attr` for ``v_attr [N, C]`` (device): ``(v_pos [N, 3], v_nrm [N, 3],
    v_mat_raw [N, Cm], v_alpha_raw [N], v_vlight [N, 6] or None)``, device arrays (``v_nrm`` per
    vertex: :func:`face_sum3` gives the per-face adjoint of a soup's face normals); the ``nconst``
    constant columns have none. ``attr [N, C]`` is the forward's output (:func:`vertex_attr` of the
    same ``mat_raw``): the sigmoids' derivatives come from its values."""
    N, nmat = mat_raw.shape
    C = num_channels(nmat, has_vlight, nconst)
    for name, a in (("v_attr", v_attr), ("attr", attr)):
        if a.shape != (N, C) or a.dtype != np.dtype(real):
            raise ValueError(f"{name} must be [{N}, {C}] {np.dtype(real)}, got {list(a.shape)} {a.dtype}")
    if not v_attr.flags.c_contiguous:
        v_attr = v_attr.copy()
    if not attr.flags.c_contiguous:
        attr = attr.copy()
    out = dict(v_pos=device_rows(dev, (N, 3), real), v_nrm=device_rows(dev, (N, 3), real),
               v_mat_raw=device_rows(dev, (N, nmat), real), v_alpha_raw=device_rows(dev, (N,), real))
    if has_vlight:
        out["v_vlight"] = device_rows(dev, (N, 6), real)
    launch(dev, "vertex_attr", "vertex_attr_bwd", *grid_1d(N), defines=attr_defines(nmat, softplus_cols, False,
                                                                                      has_vlight, nconst),
           real=real, mat_raw=mat_raw, attr=attr, v_attr=v_attr, N=N, **out)
    return out["v_pos"], out["v_nrm"], out["v_mat_raw"], out["v_alpha_raw"], out.get("v_vlight")


def face_sum3(dev: Device, x: cla.Array, real=np.float32) -> cla.Array:
    """``[M, 3]``: ``x[3f] + x[3f + 1] + x[3f + 2]`` of a per-corner ``x [3M, 3]`` (device)."""
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] % 3:
        raise ValueError(f"face_sum3: x must be [3M, 3], got {list(x.shape)}")
    M = x.shape[0] // 3
    out = device_rows(dev, (M, 3), real)
    if M:
        launch(dev, "vertex_attr", "face_sum3", *grid_1d(M), defines={"NMAT": 1}, real=real, x=x, M=M, out=out)
    return out


__all__ = ["attr_defines", "face_sum3", "num_channels", "vertex_attr", "vertex_attr_backward"]
