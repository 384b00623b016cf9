"""Physically based shading of fragments under a packed light table (``kernels_cl/shade.cl``).

The op works on a flat list of ``P`` fragments (the rasterizer's packed fragments), with
per-fragment attributes already interpolated by the rasterizer and materials already activated
by the parameter model:

* ``pos [P, 3]`` world position, ``nrm [P, 3]`` shading normal (any length; normalised inside),
* ``mat [P, C]`` activated material channels, layout per BRDF (``triplet_cl.materials``; e.g.
  Cook-Torrance C = 6: albedo r, g, b | roughness | metallic | ambient occlusion),
* ``face_id [P] int32``: ``-1`` marks an empty slot (colour 0, zero gradients),
* ``vlight [P, 6]`` (only with a :class:`~triplet_cl.lights.VertexSHLight`): per-fragment
  vertex-SH radiance (rgb) and direction ``wi`` (normalised inside),
* ``cam [3]`` camera centre; ``lights``: a sequence of :mod:`triplet_cl.lights` objects.

``two_sided`` (default True, right for triangle soups) flips a normal that faces away from the
camera. Output ``rgb [P, 3]``; the backward pass returns per-fragment adjoints and the gradient of
every light parameter (per-work-group partial sums, summed on the host: deterministic, no atomics).
Formulas: ``kernels_cl/common/shade_brdf.h`` and ``kernels_cl/shade.cl``.

On a CPU device the packed path (:func:`forward_packed`, :func:`backward_packed`: what ``render`` uses) runs the
Cook-Torrance BRDF under ambient, directional and point lights as ``kernels_cl/shade_lanes.cl``, eight fragments per
work-item in vector lanes (:func:`lanes_supported`); ``shade.cl`` stays the reference and serves everything else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..device import Device, get_device
from ..lights import (
    AmbientLight,
    BounceLight,
    DirectionalLight,
    LightTable,
    PointLight,
    SHEnvironmentLight,
    kernel_defines,
    pack_lights,
    unpack_gradients,
)
from ..materials import COOK_TORRANCE, DEFAULT_BRDF, get_brdf
from .common import check_real, check_shape, device_rows, empty, launch, round_up, to_device, to_host
from .vertex_sh import check_cam

LOCAL_SIZE = 64
RED_W = 16


def num_material_channels(brdf: str) -> int:
    """The material channel count ``C`` of ``brdf`` (``materials.BRDF.num_channels``)."""
    return get_brdf(brdf).num_channels


def env_occlusion_columns(table: LightTable, width: int) -> int:
    """The environment-occlusion columns of a ``vis`` of ``width`` columns: ``width`` less the shadow casters'
    (``table.num_shadowed``), which must be 0 or ``(d + 1)² − 1`` for a degree ``d`` ≥ 1 (the SH bands 1 .. d of
    :func:`~triplet_cl.visibility.vertex_occlusion`, shared by every SH environment light; unused without one)."""
    nv = table.num_shadowed
    n = int(width) - nv
    d = math.isqrt(n + 1) - 1 if n >= 0 else -1
    if n < 0 or (n and (d < 1 or (d + 1) ** 2 - 1 != n)):
        raise ValueError(f"vis must have {nv} columns (shadowed lights), then 0 or (d + 1)² − 1 environment-occlusion "
                         f"columns (3, 8, 15, ...), got {width}")
    return n


def _env_bucket(deg: int) -> int:
    """Compiled ENV_MAX_DEG for the largest active degree (-1: no env): few program variants (2, 4, 8)."""
    return 2 if deg <= 2 else (4 if deg <= 4 else 8)


def env_chunk(inp, local_mem_bytes: int, itemsize: int) -> int:
    """shade.cl's ``ENV_KC`` for ``shade_bwd``: the SH environment's coefficients per channel summed in one chunk
    through local memory, at most 32 (three chunks at degree 8), halved while the scratch (:func:`scratch_width`)
    would not fit the device's local memory (float64 at degree 8 needs 52 KB at 32)."""
    kc = min((_env_bucket(inp.table.env_degree) + 1) ** 2, 32)
    while kc > 4 and LOCAL_SIZE * scratch_width(kc) * itemsize > local_mem_bytes:
        kc //= 2
    return kc


def scratch_width(kc: int) -> int:
    """Local-memory values per work-item of ``shade_bwd``: ``RED_W`` for the lights' group sums, or the SH
    environment's row (shade.cl's ``ENV_SW``: gE, gG and, for ``kc`` coefficients, the diffuse factor, the band
    factor and Y(R)) when wider."""
    return max(RED_W, 3 * kc + 6)


@dataclass
class ShadeInputs:
    """Validated device-side inputs of one shading call."""

    pos: cla.Array  # [P, 3]
    nrm: cla.Array  # [P, 3]
    mat: cla.Array  # [P, C]
    face_id: cla.Array | None  # [P] int32 (None: every row is a fragment, the packed path)
    vlight: cla.Array | None  # [P, 6]
    cam: np.ndarray  # [3]
    table: LightTable
    lt_i: cla.Array  # [L, 4] int32
    lt_f: cla.Array  # [T]
    brdf: str
    two_sided: bool
    real: type
    # ray-traced terms (ops/trace.py), None in the raster path:
    #: [P, NV + NO] transmittance towards each point/directional light, then the environment's occlusion (NO columns)
    vis: cla.Array | None = None
    refl: cla.Array | None = None  # [P, 3] radiance along the mirror direction (reflection bounce)
    eye: cla.Array | None = None  # [P, 3] per-fragment viewpoint replacing cam
    #: the packed path (:func:`packed_inputs`): pos, nrm, mat (, vlight, vis) are the same ``[P, C]`` array of
    #: packed fragment attributes, ``{"POS" | "NRM" | "MAT" | "VL" | "VIS" | "ALPHA": (first column, width)}``
    blocks: dict | None = None
    #: :func:`_lanes_key` of these inputs, once computed (a forward and its backward ask for it several times)
    lanes_key: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def P(self) -> int:
        return self.pos.shape[0]

    @property
    def vis_width(self) -> int:
        """Columns of vis (shadowed lights, then the environment's occlusion)."""
        if self.vis is None:
            return 0
        return self.blocks["VIS"][1] if self.blocks is not None else self.vis.shape[1]

    @property
    def NV(self) -> int:
        """Columns of vis that are the shadowed lights' transmittance."""
        return 0 if self.vis is None else self.table.num_shadowed

    @property
    def env_occ(self) -> int:
        """Columns of vis that are the environment's occlusion (``ENV_OCC`` of ``shade.cl``)."""
        return self.vis_width - self.NV


@dataclass
class ShadeGrads:
    """Adjoints of :func:`shade` (numpy)."""

    v_pos: np.ndarray  # [P, 3]
    v_nrm: np.ndarray  # [P, 3]
    v_mat: np.ndarray  # [P, C]
    v_vlight: np.ndarray | None  # [P, 6] (None without vlight)
    v_light_params: np.ndarray  # [T] gradient of the packed light parameters
    v_lights: list[dict[str, np.ndarray]]  # per light: {parameter name: gradient}


@dataclass
class ShadeAdjoints:
    """Adjoints of one shading call (:func:`backward`): device arrays, ``v_light_params`` numpy.
    The optional inputs' adjoints are ``None`` where the input is absent."""

    v_pos: cla.Array  # [P, 3]
    v_nrm: cla.Array  # [P, 3]
    v_mat: cla.Array  # [P, C]
    v_vlight: cla.Array | None  # [P, 6]
    v_light_params: np.ndarray  # [T] gradient of the packed light parameters (inactive ones 0)
    v_vis: cla.Array | None = None  # [P, NV + NO]
    v_refl: cla.Array | None = None  # [P, 3]
    v_eye: cla.Array | None = None  # [P, 3]


def _optional(inp: ShadeInputs) -> dict[str, bool]:
    """Which optional inputs the call has: the ``HAS_*`` defines of ``shade.cl`` (and ``ALL_VALID`` without
    face ids)."""
    return {"HAS_VLIGHT": inp.vlight is not None, "HAS_VIS": inp.vis is not None and inp.vis_width > 0,
            "HAS_REFL": inp.refl is not None, "HAS_EYE": inp.eye is not None, "ALL_VALID": inp.face_id is None}


def _layout_defines(inp: ShadeInputs) -> dict:
    """The packed path's row layout (shade.cl ``X_LD`` / ``X_OFF``, ``ALPHA_COPY``); nothing otherwise."""
    if inp.blocks is None:
        return {}
    ld = inp.pos.shape[1]
    out = {}
    for key, (c0, _) in inp.blocks.items():
        out[f"{key}_LD"], out[f"{key}_OFF"] = ld, c0
    out["ALPHA_COPY"] = "ALPHA" in inp.blocks
    return out


def _table_defines(table: LightTable) -> dict:
    """``NUM_LIGHTS`` and ``LIGHT_TABLE`` (the rows of ``table.ints`` flattened): shade.cl compiles the light
    table's structure in (its loop over the lights unrolls, each light's branches fold); the parameters stay
    a buffer. One placeholder row without lights (a C array is never empty)."""
    rows = np.asarray(table.ints, np.int64).reshape(-1, 4)
    flat = rows.reshape(-1) if len(rows) else np.zeros(4, np.int64)
    return {"NUM_LIGHTS": len(rows), "LIGHT_TABLE": ",".join(str(int(v)) for v in flat)}


def _defines(inp: ShadeInputs) -> dict:
    """The build defines of a shading call (``HAS_*``: defined or not, see :func:`_optional`; the light
    table's structure: :func:`_table_defines`)."""
    occ = {"ENV_OCC": inp.env_occ} if inp.vis is not None and inp.env_occ else {}
    return {"ENV_MAX_DEG": _env_bucket(inp.table.env_degree), "RED_W": RED_W, **_optional(inp), **occ,
            **_layout_defines(inp), **_table_defines(inp.table), **get_brdf(inp.brdf).kernel_defines(),
            **kernel_defines()}


def _inputs(inp: ShadeInputs) -> dict:
    """The kernels' input arguments by name (the optional ones only when present)."""
    has = _optional(inp)
    args = dict(pos=inp.pos, nrm=inp.nrm, mat=inp.mat, P=inp.P, cx=inp.cam[0],
                cy=inp.cam[1], cz=inp.cam[2], two_sided=int(inp.two_sided), lt_f=inp.lt_f)
    if inp.face_id is not None:
        args["face_id"] = inp.face_id
    if has["HAS_VLIGHT"]:
        args["vlight"] = inp.vlight
    if has["HAS_VIS"]:
        args.update(NV=inp.NV, vis=inp.vis)
    if has["HAS_REFL"]:
        args["refl"] = inp.refl
    if has["HAS_EYE"]:
        args["eye"] = inp.eye
    return args


def forward(dev: Device, inp: ShadeInputs) -> cla.Array:
    """``rgb [P, 3]`` (device array) for validated device inputs."""
    rgb = empty(dev.queue, (inp.P, 3), inp.real)
    if inp.P:
        launch(dev, "shade", "shade_fwd", (round_up(inp.P, LOCAL_SIZE),), (LOCAL_SIZE,), defines=_defines(inp),
               real=inp.real, **_inputs(inp), rgb=rgb)
    return rgb


def backward(dev: Device, inp: ShadeInputs, v_rgb: cla.Array) -> ShadeAdjoints:
    """The adjoints (:class:`ShadeAdjoints`) of every input for the cotangent ``v_rgb [P, 3]``."""
    q, P, real = dev.queue, inp.P, inp.real
    C = inp.mat.shape[1]
    T = len(inp.table.params)
    has = _optional(inp)
    out = ShadeAdjoints(empty(q, (P, 3), real), empty(q, (P, 3), real), empty(q, (P, C), real),
                        empty(q, (P, 6), real) if inp.vlight is not None else None, np.zeros(T),
                        empty(q, inp.vis.shape, real) if inp.vis is not None else None,
                        empty(q, (P, 3), real) if inp.refl is not None else None,
                        empty(q, (P, 3), real) if inp.eye is not None else None)
    outs = dict(v_pos=out.v_pos, v_nrm=out.v_nrm, v_mat=out.v_mat)
    if has["HAS_VLIGHT"]:
        outs["v_vlight"] = out.v_vlight
    if has["HAS_VIS"]:
        outs["v_vis"] = out.v_vis
    if has["HAS_REFL"]:
        outs["v_refl"] = out.v_refl
    if has["HAS_EYE"]:
        outs["v_eye"] = out.v_eye
    out.v_light_params = _launch_backward(dev, inp, v_rgb, outs)
    return out


def _launch_backward(dev: Device, inp: ShadeInputs, v_rgb: cla.Array, outs: dict, extra: dict | None = None,
                     deferred: bool = False):
    """Run ``shade_bwd`` with the adjoint outputs ``outs`` (and ``extra`` arguments); returns the light
    parameters' gradient ``[T]`` (float64, the per-work-group partials summed on the host); ``deferred``: as an
    ``autodiff`` ``Deferred`` (the partials' download queued, the sum taken when it is resolved)."""
    q, P, real = dev.queue, inp.P, inp.real
    T = len(inp.table.params)
    v_params = np.zeros(T)
    groups = round_up(P, LOCAL_SIZE) // LOCAL_SIZE
    part = empty(q, (max(groups, 1), max(T, 1)), real)
    if P:
        dev.check_alloc(groups * max(T, 1) * np.dtype(real).itemsize, "shade light-gradient partials")
        item = np.dtype(real).itemsize
        kc = env_chunk(inp, dev.cached("local_mem_size", lambda: int(dev.cl_device.local_mem_size)), item)
        launch(dev, "shade", "shade_bwd", (groups * LOCAL_SIZE,), (LOCAL_SIZE,),
               defines={**_defines(inp), "ENV_KC": kc}, real=real,
               **_inputs(inp), **outs, **(extra or {}), T=T, v_rgb=v_rgb, v_light_part=part,
               scratch=cl.LocalMemory(LOCAL_SIZE * scratch_width(kc) * item))
        # only the active parameters: the kernel writes no partial for an inactive one (an SH environment's bands
        # above its active degree), whose column holds whatever the buffer held (a NaN there warned in the sum)
        # (an inactive parameter's gradient stays 0)
        active = np.ones(T, bool)
        active[inp.table.inactive] = False
        return _sum_partials(part, T, active, v_params, deferred)
    return v_params


# ---- the packed path -------------------------------------------------------------------------


def packed_inputs(dev: Device, fa: cla.Array, blocks: dict, cam, table: LightTable, lt_i: cla.Array,
                  lt_f: cla.Array, brdf: str, two_sided: bool, real) -> ShadeInputs:
    """Shading inputs that are column blocks of the packed fragment attributes ``fa [P, C]`` (every row a
    fragment): ``blocks`` maps ``"POS"``, ``"NRM"``, ``"MAT"`` (and ``"VL"``, ``"VIS"``, ``"ALPHA"``) to
    ``(first column, width)``. :func:`forward_packed` / :func:`backward_packed` read and write the blocks in
    place (no per-block copies: ``ops.columns.split_columns`` / ``merge_columns`` are what they replace)."""
    C = get_brdf(brdf).num_channels
    want = {"POS": 3, "NRM": 3, "MAT": C, "VL": 6, "ALPHA": 1}
    if fa.ndim != 2 or not fa.flags.c_contiguous or fa.dtype != np.dtype(real):
        raise ValueError(f"fa must be a C-contiguous [P, C] array of {np.dtype(real)}, got {list(fa.shape)} {fa.dtype}")
    for key, (c0, n) in blocks.items():
        if key not in want and key != "VIS":
            raise ValueError(f"unknown block {key!r}")
        if (key in want and n != want[key]) or c0 < 0 or c0 + n > fa.shape[1]:
            raise ValueError(f"block {key} = {(c0, n)} does not fit the {fa.shape[1]} columns (width {want.get(key)})")
    if any(k not in blocks for k in ("POS", "NRM", "MAT")) or (table.has_vertex_sh != ("VL" in blocks)):
        raise ValueError(f"blocks must hold POS, NRM, MAT (and VL with a VertexSHLight), got {sorted(blocks)}")
    if "VIS" in blocks:
        env_occlusion_columns(table, blocks["VIS"][1])
    return ShadeInputs(fa, fa, fa, None, fa if "VL" in blocks else None, check_cam(cam), table, lt_i, lt_f, brdf,
                       bool(two_sided), real, vis=fa if "VIS" in blocks else None, blocks=dict(blocks))


#: the light types ``shade_lanes.cl`` shades (by their ``lights.py`` class ``TYPE``)
LANES_LIGHT_TYPES = frozenset({AmbientLight.TYPE, DirectionalLight.TYPE, PointLight.TYPE, SHEnvironmentLight.TYPE,
                               BounceLight.TYPE})
#: the most light parameters ``shade_lanes.cl`` takes (each work-item keeps their sums in private memory: a point
#: light and an SH environment of degree 2 are 33; degree 8 alone is 243)
LANES_MAX_PARAMS = 64
LANES = 8  # fragments per work-item of shade_lanes.cl (its W)


def lanes_cover(inp: ShadeInputs) -> bool:
    """Whether ``shade_lanes.cl`` handles these inputs: packed rows, the Cook-Torrance BRDF under ambient, directional,
    point, SH environment and bounce lights (at most :data:`LANES_MAX_PARAMS` parameters), with at most the shadow
    casters' transmittance among the ray-traced terms (no vertex-SH light, environment occlusion, reflection bounce
    or per-fragment eye)."""
    return (inp.blocks is not None and inp.brdf == COOK_TORRANCE.name and inp.refl is None and inp.eye is None
            and ("VL" in inp.blocks) == inp.table.has_vertex_sh  # (the bounce reads its radiance there)
            and inp.env_occ == 0 and 0 < len(inp.table.params) <= LANES_MAX_PARAMS and len(inp.table.ints) > 0
            and set(np.asarray(inp.table.ints)[:, 0].tolist()) <= LANES_LIGHT_TYPES)


def lanes_supported(dev: Device, inp: ShadeInputs) -> bool:
    """Whether packed inputs take ``shade_lanes.cl`` (eight fragments per work-item in vector lanes) by default
    instead of ``shade.cl``: where it covers them (:func:`lanes_cover`) on a CPU device, where only that form
    vectorises (``bench/pocl_vectorize.py``), unless this device's build of that variant failed its check against
    ``shade.cl`` (:data:`LANES_CHECK_TOL`); a GPU keeps one fragment per work-item."""
    return dev.is_cpu and lanes_cover(inp) and _lanes_verdicts(dev).get(_lanes_key(inp)) is not False


#: the first forward and the first backward the default path runs through each compiled variant of ``shade_lanes.cl``
#: on a device are also run through ``shade.cl`` and compared, output by output (the RGB, each block of the rows'
#: adjoint, the light gradients): a difference above this fraction of the reference's largest value in that output
#: sends the variant to ``shade.cl`` for the rest of the process (with a warning), and the call returns shade.cl's
#: values. Why: Intel's CPU OpenCL runtime (session 62) builds the variant of a point light followed by an ambient
#: one (the default ``--lights point,ambient``) with albedo and metallic adjoints 1–30 % off, where PoCL's agrees with
#: shade.cl to rounding (float32: within ~5e-5 of the largest value, tests/test_shade_lanes.py). The check costs one
#: shade.cl pass per variant (a few per run), on the call's own inputs.
LANES_CHECK_TOL = 1e-3


def _lanes_key(inp: ShadeInputs) -> tuple:
    """The compiled variant of ``shade_lanes.cl`` that ``inp`` runs (its build defines and real), kept on ``inp``
    (~10 µs to form)."""
    if inp.lanes_key is None:
        inp.lanes_key = tuple(sorted((k, repr(v)) for k, v in _lanes_defines(inp).items())), np.dtype(inp.real).str
    return inp.lanes_key


def _lanes_verdicts(dev: Device) -> dict:
    """``{variant: "fwd" | True | False}`` on ``dev``: its forward checked against shade.cl, its backward too, or it
    failed the check (absent: not checked yet)."""
    return dev.cached("shade_lanes_verdicts", dict)


def _agree(got, want) -> bool:
    """``got`` within :data:`LANES_CHECK_TOL` of ``want``'s largest magnitude everywhere (both finite where ``want``
    is)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    if got.shape != want.shape:
        return False
    if not want.size:
        return True
    scale = float(np.nanmax(np.abs(want))) if np.isfinite(want).any() else 0.0
    with np.errstate(invalid="ignore"):
        d = np.abs(got - want)
    return bool(np.all(np.isfinite(d) | ~np.isfinite(want)) and np.nanmax(d, initial=0.0) <= LANES_CHECK_TOL * scale)


def _lanes_rejected(dev: Device, inp: ShadeInputs, what: str) -> None:
    import warnings

    _lanes_verdicts(dev)[_lanes_key(inp)] = False
    warnings.warn(f"shade_lanes.cl's {what} disagrees with shade.cl on {dev.name} (this light layout: "
                  f"{len(inp.table.ints)} lights, {np.dtype(inp.real).name}); shading with shade.cl instead",
                  RuntimeWarning, stacklevel=3)


def _lanes_defines(inp: ShadeInputs) -> dict:
    """The build defines of ``shade_lanes.cl`` for packed inputs: the row layout, ``HAS_VIS``, the light table
    and its parameter count, the light type ids."""
    d = {"RED_W": RED_W, **_layout_defines(inp), **_table_defines(inp.table),
         "NUM_PARAMS": len(inp.table.params), "ENV_MAX_DEG": _env_bucket(inp.table.env_degree), **kernel_defines()}
    if inp.vis is not None and inp.vis_width > 0:
        d["HAS_VIS"] = True
    return d


def _lanes_groups(P: int) -> int:
    """Work-groups of ``LOCAL_SIZE`` work-items, ``LANES`` fragments each, for ``P`` fragments."""
    return round_up(-(-P // LANES), LOCAL_SIZE) // LOCAL_SIZE


def _use_lanes(dev: Device, inp: ShadeInputs, lanes: bool | None) -> bool:
    """``lanes`` None: the default (:func:`lanes_supported`); True: ``shade_lanes.cl`` on any device (a GPU too: the
    tests' cross-check), which must cover the inputs; False: ``shade.cl``."""
    if lanes is None:
        return lanes_supported(dev, inp)
    if lanes and not lanes_cover(inp):
        raise ValueError("these shading inputs cannot take shade_lanes.cl (lanes_cover is False)")
    return bool(lanes)


def forward_packed(dev: Device, inp: ShadeInputs, lanes: bool | None = None) -> tuple[cla.Array, cla.Array | None]:
    """``(rgb [P, 3], alpha [P] or None)`` of packed inputs (:func:`packed_inputs`): the shading of
    :func:`forward`, and the alpha block copied out in the same pass (what the compositing reads).
    ``lanes``: ``shade_lanes.cl`` (True), ``shade.cl`` (False) or the default (None: :func:`lanes_supported`)."""
    P = inp.P
    rgb = device_rows(dev, (P, 3), inp.real)
    alpha = device_rows(dev, (P,), inp.real) if "ALPHA" in inp.blocks else None
    if P and _use_lanes(dev, inp, lanes):
        extra = dict(alpha=alpha) if alpha is not None else {}
        launch(dev, "shade_lanes", "shade_lanes_fwd", (_lanes_groups(P) * LOCAL_SIZE,), (LOCAL_SIZE,),
               defines=_lanes_defines(inp), real=inp.real, fa=inp.pos, P=P, cx=inp.cam[0], cy=inp.cam[1],
               cz=inp.cam[2], two_sided=int(inp.two_sided), lt_f=inp.lt_f, **extra, rgb=rgb)
        if lanes is None and _lanes_verdicts(dev).get(_lanes_key(inp)) is None:  # its first run here: checked
            ref = _shade_forward(dev, inp)
            if _agree(rgb.get(), ref[0].get()) and (alpha is None or np.array_equal(alpha.get(), ref[1].get())):
                _lanes_verdicts(dev)[_lanes_key(inp)] = "fwd"
            else:
                _lanes_rejected(dev, inp, "forward")
                return ref
    elif P:
        return _shade_forward(dev, inp)
    return rgb, alpha


def _shade_forward(dev: Device, inp: ShadeInputs) -> tuple[cla.Array, cla.Array | None]:
    """:func:`forward_packed` through ``shade.cl``."""
    P = inp.P
    rgb = device_rows(dev, (P, 3), inp.real)
    alpha = device_rows(dev, (P,), inp.real) if "ALPHA" in inp.blocks else None
    extra = dict(alpha_src=inp.pos, alpha=alpha) if alpha is not None else {}
    launch(dev, "shade", "shade_fwd", (round_up(P, LOCAL_SIZE),), (LOCAL_SIZE,), defines=_defines(inp),
           real=inp.real, **_inputs(inp), **extra, rgb=rgb)
    return rgb, alpha


def backward_packed(dev: Device, inp: ShadeInputs, v_rgb: cla.Array, v_alpha: cla.Array | None = None,
                    deferred: bool = False, lanes: bool | None = None):
    """``(v_fa [P, C], v_light_params [T] numpy)``: the adjoint of :func:`forward_packed`, written straight into
    the blocks of the attributes' adjoint (``v_alpha [P]`` into the alpha block; a column outside every block is
    not written). ``deferred``: ``v_light_params`` as an ``autodiff`` ``Deferred`` (no wait here)."""
    if "ALPHA" in inp.blocks and v_alpha is None:
        raise ValueError("v_alpha [P] is required with an ALPHA block")
    if _use_lanes(dev, inp, lanes):
        v_fa = device_rows(dev, inp.pos.shape, inp.real)
        if lanes is None and inp.P and _lanes_verdicts(dev).get(_lanes_key(inp)) is not True:  # checked once
            v_params = _launch_lanes_backward(dev, inp, v_rgb, v_alpha, v_fa, False)
            ref_fa, ref_params = _shade_backward(dev, inp, v_rgb, v_alpha, False)
            got, want = v_fa.get(), ref_fa.get()
            if all(_agree(got[:, c0:c0 + n], want[:, c0:c0 + n]) for c0, n in inp.blocks.values()) \
                    and _agree(v_params, ref_params):
                _lanes_verdicts(dev)[_lanes_key(inp)] = True
                return v_fa, v_params
            _lanes_rejected(dev, inp, "adjoint")
            return ref_fa, ref_params
        return v_fa, _launch_lanes_backward(dev, inp, v_rgb, v_alpha, v_fa, deferred)
    return _shade_backward(dev, inp, v_rgb, v_alpha, deferred)


def _shade_backward(dev: Device, inp: ShadeInputs, v_rgb: cla.Array, v_alpha, deferred: bool):
    """:func:`backward_packed` through ``shade.cl``."""
    v_fa = device_rows(dev, inp.pos.shape, inp.real)
    extra = dict(v_alpha=v_alpha, v_alpha_dst=v_fa) if "ALPHA" in inp.blocks else {}
    outs = dict(v_pos=v_fa, v_nrm=v_fa, v_mat=v_fa)
    if inp.vlight is not None:
        outs["v_vlight"] = v_fa
    if inp.vis is not None:
        outs["v_vis"] = v_fa
    return v_fa, _launch_backward(dev, inp, v_rgb, outs, extra, deferred=deferred)


def _sum_partials(part: cla.Array, T: int, active: np.ndarray, v_params: np.ndarray, deferred: bool):
    """The light parameters' gradient from the per-work-group partials ``part [groups, >= T]`` (float64 sums of
    the ``active`` columns; an inactive parameter's gradient stays 0), or as a ``Deferred``."""
    if deferred:
        from ..autodiff.arrays import Deferred, download_deferred

        dl = download_deferred(part)

        def total(dl=dl, v_params=v_params, active=active):
            v_params[active] = dl.resolve()[:, :T][:, active].sum(axis=0, dtype=np.float64)
            return v_params

        return Deferred(v_params.shape, total)
    v_params[active] = part.get()[:, :T][:, active].sum(axis=0, dtype=np.float64)
    return v_params


def _launch_lanes_backward(dev: Device, inp: ShadeInputs, v_rgb: cla.Array, v_alpha, v_fa: cla.Array,
                           deferred: bool):
    """``shade_lanes_bwd`` into ``v_fa``; returns the light parameters' gradient as :func:`_launch_backward`."""
    q, P, real = dev.queue, inp.P, inp.real
    T = len(inp.table.params)
    v_params = np.zeros(T)
    groups = _lanes_groups(P)
    part = empty(q, (max(groups, 1), T), real)
    if not P:
        return v_params
    dev.check_alloc(groups * T * np.dtype(real).itemsize, "shade light-gradient partials")
    extra = dict(v_alpha=v_alpha) if "ALPHA" in inp.blocks else {}
    launch(dev, "shade_lanes", "shade_lanes_bwd", (groups * LOCAL_SIZE,), (LOCAL_SIZE,),
           defines=_lanes_defines(inp), real=real, fa=inp.pos, P=P, cx=inp.cam[0], cy=inp.cam[1], cz=inp.cam[2],
           two_sided=int(inp.two_sided), lt_f=inp.lt_f, v_rgb=v_rgb, **extra, v_fa=v_fa, v_light_part=part,
           scratch=cl.LocalMemory(LOCAL_SIZE * RED_W * np.dtype(real).itemsize))
    active = np.ones(T, bool)
    active[inp.table.inactive] = False
    return _sum_partials(part, T, active, v_params, deferred)


# ---- validation ------------------------------------------------------------------------------


def prepare(pos, nrm, mat, face_id, cam, lights, *, brdf: str = DEFAULT_BRDF, vlight=None,
            two_sided: bool = True, device: Device | None = None, real=np.float32, vis=None, refl=None,
            eye=None) -> tuple[Device, ShadeInputs]:
    """Validate host (or device) inputs and upload them; returns ``(device, ShadeInputs)``.

    Ray-traced terms (optional): ``vis [P, NV (+ NO)]`` transmittance towards each point/directional
    light in light order (NV their number), then optionally the environment's occlusion (NO = (d + 1)² − 1
    columns: :func:`env_occlusion_columns`), ``refl [P, 3]`` radiance along the mirror direction,
    ``eye [P, 3]`` per-fragment viewpoint replacing ``cam``.
    """
    dev = device or get_device()
    C = get_brdf(brdf).num_channels
    pos = check_real("pos", pos, (None, 3), real)
    P = pos.shape[0]
    nrm = check_real("nrm", nrm, (P, 3), real)
    mat = check_real("mat", mat, (P, C), real)
    fid = face_id if isinstance(face_id, cla.Array) else np.asarray(face_id)
    if fid.dtype.kind not in "iu":
        raise ValueError(f"face_id must be an integer array, got dtype {fid.dtype}")
    check_shape("face_id", fid, (P,))
    if not isinstance(fid, cla.Array):
        if fid.size and int(fid.min()) < -1:
            raise ValueError(f"face_id must be >= -1 (-1 marks an empty slot), found {int(fid.min())}")
        fid = np.ascontiguousarray(fid, dtype=np.int32)
    elif fid.dtype != np.int32:
        raise ValueError(f"face_id must be a device array of dtype int32, got {fid.dtype}")
    cam = check_cam(cam)
    table = pack_lights(lights)
    if table.has_vertex_sh and vlight is None:
        raise ValueError("vlight [P, 6] is required with a VertexSHLight in lights")
    if vlight is not None:
        vlight = check_real("vlight", vlight, (P, 6), real)
    q = dev.queue

    def up(a):
        return to_device(q, a) if (isinstance(a, cla.Array) or a.size) else empty(q, a.shape, a.dtype)

    lt_i = table.ints if len(table.ints) else np.zeros((1, 4), np.int32)
    lt_f = table.params.astype(real) if len(table.params) else np.zeros(1, real)
    inp = ShadeInputs(up(pos), up(nrm), up(mat), up(fid), None if vlight is None else up(vlight), cam, table,
                      to_device(q, lt_i), to_device(q, lt_f), brdf, bool(two_sided), real)
    if vis is not None:
        width = vis.shape[1] if getattr(vis, "ndim", 0) == 2 else table.num_shadowed
        env_occlusion_columns(table, width)
        inp.vis = up(check_real("vis", vis, (P, width), real))
    if refl is not None:
        inp.refl = up(check_real("refl", refl, (P, 3), real))
    if eye is not None:
        inp.eye = up(check_real("eye", eye, (P, 3), real))
    return dev, inp


def shade(pos, nrm, mat, face_id, cam, lights, *, brdf: str = DEFAULT_BRDF, vlight=None, two_sided: bool = True,
          device: Device | None = None, real=np.float32) -> np.ndarray:
    """Shade ``P`` fragments.

    Args:
        pos: ``[P, 3]`` world positions.  nrm: ``[P, 3]`` normals (normalised inside).
        mat: ``[P, C]`` activated materials, ``C`` channels of ``brdf`` (``triplet_cl.materials``).
            face_id: ``[P]`` int, ``-1`` = empty slot.
        cam: ``[3]`` camera centre.  lights: sequence of :mod:`triplet_cl.lights` objects.
        brdf: a name of ``materials.BRDFS``.  vlight: ``[P, 6]`` for a VertexSHLight.
        two_sided: flip normals facing away from the camera.
    Returns:
        ``rgb [P, 3]`` (linear radiance, not clamped).
    """
    dev, inp = prepare(pos, nrm, mat, face_id, cam, lights, brdf=brdf, vlight=vlight, two_sided=two_sided,
                       device=device, real=real)
    return to_host(forward(dev, inp))


def shade_backward(pos, nrm, mat, face_id, cam, lights, v_rgb, *, brdf: str = DEFAULT_BRDF, vlight=None,
                   two_sided: bool = True, device: Device | None = None, real=np.float32) -> ShadeGrads:
    """Adjoint of :func:`shade` for the cotangent ``v_rgb [P, 3]``; returns :class:`ShadeGrads`."""
    dev, inp = prepare(pos, nrm, mat, face_id, cam, lights, brdf=brdf, vlight=vlight, two_sided=two_sided,
                       device=device, real=real)
    v_rgb = check_real("v_rgb", v_rgb, (inp.P, 3), real)
    v_rgb_d = to_device(dev.queue, v_rgb) if v_rgb.size else empty(dev.queue, (0, 3), real)
    g = backward(dev, inp, v_rgb_d)
    lights = list(lights)
    return ShadeGrads(to_host(g.v_pos), to_host(g.v_nrm), to_host(g.v_mat),
                      None if g.v_vlight is None else to_host(g.v_vlight), g.v_light_params,
                      unpack_gradients(lights, g.v_light_params))
