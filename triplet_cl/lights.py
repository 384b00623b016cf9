"""Lights of the shading op: documented parameters, packing into the light table, gradients back.

Every light is a small dataclass of numpy arrays. Directions point **from the surface towards the
light** (like ``wi``); they need not be unit (the kernel normalises them, with the adjoint).

========================  ==================================================  =====================
light                     parameters (shape)                                  receive gradients
========================  ==================================================  =====================
``AmbientLight``          ``color`` (3) ambient radiance ``La``               ``color``
``DirectionalLight``      ``direction`` (3) towards the light,                ``direction``,
                          ``intensity`` (3) rgb radiance                      ``intensity``
``PointLight``            ``position`` (3), ``intensity`` (3),                ``position``,
                          ``falloff`` (bool): divide by ``|q - x|^2``         ``intensity``
``SHEnvironmentLight``    ``coeffs`` (3, (D+1)^2) rgb radiance SH, ``D <= 8``  ``coeffs`` (active
                          ``degree`` active degree ``<= D`` (band schedule)   bands; others 0)
``VertexSHLight``         none: the per-fragment ``vlight [P, 6]`` of         (``v_vlight`` of the
                          ``ops.vertex_sh`` (radiance rgb, direction wi)      shading op)
========================  ==================================================  =====================

The SH environment radiance is ``L(w) = sum_k coeffs[:, k] Y_k(w)`` with the real SH of
``kernels_cl/common/sh.h`` (a constant radiance ``c`` is ``coeffs[:, 0] = c * sqrt(4 pi)``).

Light table (one compiled kernel covers any mix):
    ``ints [L, 4] int32``: ``(type, offset, a, b)`` per light, ``offset`` into ``params``;
        ``a`` = falloff flag (point) or active degree (SH env); ``b`` = ``(D+1)^2`` (SH env).
    ``params [T]``: the lights' parameters, concatenated in the order of the table above
        (SH env: ``coeffs`` flattened channel-major, ``[3, (D+1)^2]``).
``unpack_gradients`` turns the ``[T]`` gradient of ``params`` into one dict per light.

One definition per light (the emitter-plugin idea of Mitsuba at this scale): each class, registered
with :func:`register_light`, owns its type id (``TYPE``), its C name (``DEFINE``: ``LIGHT_<DEFINE>``
in the kernels), its CLI kind (``KIND``), whether it casts ray-traced shadows (``CASTS_SHADOWS``),
its learnable parameters (``PARAMS``, packed in that order, shapes from the instance), the two
table integers (:meth:`Light.table_ints`), the parameters that get no gradient
(:meth:`Light.inactive_mask`), its JSON form, its glTF punctual form (:meth:`Light.gltf_punctual`)
and its initial value in training (:meth:`Light.initial`). The kernels get the ids and the
shadow-casting set as generated ``-D`` defines (:func:`kernel_defines`);
``kernels_cl/common/lights.h`` holds each light's incident radiance, its adjoint and its shadow ray.

Adding a light: its class here (``@register_light``), its branches in ``kernels_cl/common/lights.h``,
its reference in ``tests/reference/shade.py`` (and ``tests/reference/trace.py`` if it casts shadows).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

MAX_SH_DEGREE = 8

#: type id -> class, in id order (filled by :func:`register_light`)
LIGHT_TYPES: dict[int, type] = {}
#: class name (the ``"type"`` of ``lights.json``) -> class
LIGHT_CLASSES: dict[str, type] = {}
#: CLI / config kind (``"point"``, ...) -> class
LIGHT_KINDS: dict[str, type] = {}
_DEFINES: dict[str, int] = {}  # kernel_defines(), cleared by register_light


def register_light(cls):
    """Class decorator: add a light class to the registries (unique ``TYPE``, ``DEFINE``, ``KIND``)."""
    for attr in ("TYPE", "DEFINE", "KIND", "CASTS_SHADOWS", "PARAMS"):
        if attr not in vars(cls) and not hasattr(cls, attr):
            raise TypeError(f"light class {cls.__name__} must define {attr}")
    if cls.CASTS_SHADOWS and cls.SHADOW_RAY_PARAM not in cls.PARAMS:
        raise TypeError(f"light class {cls.__name__} casts shadows: SHADOW_RAY_PARAM must name one of {cls.PARAMS}")
    if cls.TYPE in LIGHT_TYPES or cls.KIND in LIGHT_KINDS or cls.__name__ in LIGHT_CLASSES:
        raise ValueError(f"light class {cls.__name__}: TYPE {cls.TYPE} / KIND {cls.KIND!r} already registered")
    if any(c.DEFINE == cls.DEFINE for c in LIGHT_TYPES.values()):
        raise ValueError(f"light class {cls.__name__}: DEFINE {cls.DEFINE!r} already registered")
    LIGHT_TYPES[cls.TYPE] = cls
    if not cls.INTERNAL:  # an internal light (computed by the renderer) is no CLI kind and no lights.json type
        LIGHT_CLASSES[cls.__name__] = cls
        LIGHT_KINDS[cls.KIND] = cls
    _DEFINES.clear()
    return cls


def is_light(obj) -> bool:
    """Whether ``obj`` is an instance of a registered light class (or of a subclass of one)."""
    return isinstance(obj, tuple(LIGHT_TYPES.values()))


def shadow_casting_types() -> tuple[int, ...]:
    """Type ids of the lights that cast ray-traced shadows (columns of ``vis`` in the shading op)."""
    return tuple(t for t, c in sorted(LIGHT_TYPES.items()) if c.CASTS_SHADOWS)


def kernel_defines() -> dict[str, int]:
    """The ``-D`` defines every kernel that reads a light table is built with: ``LIGHT_<DEFINE>`` =
    type id per light, ``LIGHT_SHADOW_MASK`` = bit ``1 << id`` set for the shadow casters.
    (Computed once per registry state; a copy is returned.)"""
    if not _DEFINES:
        _DEFINES.update({f"LIGHT_{c.DEFINE}": t for t, c in sorted(LIGHT_TYPES.items())})
        _DEFINES["LIGHT_SHADOW_MASK"] = sum(1 << t for t in shadow_casting_types())
    return dict(_DEFINES)


@dataclass(frozen=True)
class LightInit:
    """What the training set-up knows when it places the initial lights (:meth:`Light.initial`)."""

    center: np.ndarray  # [3] the point the cameras look at
    extent: float  # scene extent (world units)
    up: np.ndarray  # [3] unit mean camera up direction
    sh_degree: int  # max SH degree of SH lights
    rng: np.random.Generator
    index: int = 0  # this light's rank among the lights of its kind (initial_lights sets it)
    count: int = 1  # how many lights of this kind are placed
    distance: float = 0.6  # a point light starts this many extents from the centre (TrainConfig.light_distance)


def _vec3(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape [3], got {list(a.shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite")
    return a


class Light:
    """Base of the light classes (dataclasses): the generic packing, unpacking and JSON form.

    Class attributes a light defines: ``TYPE`` (int id in the light table), ``DEFINE`` (C name:
    ``LIGHT_<DEFINE>``), ``KIND`` (CLI name), ``CASTS_SHADOWS`` (bool) with ``SHADOW_RAY_PARAM`` (the
    3-vector parameter the shadow ray's adjoint belongs to, see ``lights.h``), ``PARAMS`` (names of
    its learnable array fields, packed in that order), ``NEEDS_VLIGHT`` (reads the per-fragment
    ``vlight``).
    """

    TYPE: ClassVar[int]
    DEFINE: ClassVar[str]
    KIND: ClassVar[str]
    CASTS_SHADOWS: ClassVar[bool] = False
    SHADOW_RAY_PARAM: ClassVar[str | None] = None
    PARAMS: ClassVar[tuple[str, ...]] = ()
    NEEDS_VLIGHT: ClassVar[bool] = False
    #: computed by the renderer, not learned nor written by a user: no CLI kind, no ``lights.json`` type
    INTERNAL: ClassVar[bool] = False
    #: the radiometric parameters (colours, intensities, SH radiance), whose learning rate may be made relative
    #: to their magnitude (:func:`relative_lr_scales`)
    RADIOMETRIC: ClassVar[tuple[str, ...]] = ()

    def param_shapes(self) -> dict[str, tuple[int, ...]]:
        """``{name: shape}`` of the learnable parameters, in packing order."""
        return {n: np.shape(getattr(self, n)) for n in self.PARAMS}

    @property
    def num_params(self) -> int:
        return sum(math.prod(s) for s in self.param_shapes().values())

    def flat_params(self) -> np.ndarray:
        """The parameters, concatenated (each flattened row-major): ``[num_params]`` float64."""
        if not self.PARAMS:
            return np.zeros(0)
        return np.concatenate([np.asarray(getattr(self, n), np.float64).reshape(-1) for n in self.PARAMS])

    def _split(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        out, off = {}, 0
        for n, shape in self.param_shapes().items():
            k = math.prod(shape)
            out[n] = np.asarray(flat[off:off + k]).reshape(shape).copy()
            off += k
        return out

    def table_ints(self) -> tuple[int, int]:
        """The light table's ``(a, b)`` integers of this light (see the module docstring)."""
        return 0, 0

    def param_offset(self, name: str) -> int:
        """Offset of parameter ``name`` in this light's packed parameters."""
        off = 0
        for n, shape in self.param_shapes().items():
            if n == name:
                return off
            off += math.prod(shape)
        raise KeyError(f"{type(self).__name__} has no parameter {name!r} (parameters: {self.PARAMS})")

    def inactive_mask(self) -> np.ndarray:
        """``[num_params]`` bool: parameters that get no gradient."""
        return np.zeros(self.num_params, bool)

    def sh_degree_needed(self) -> int:
        """Largest SH degree the kernels evaluate for this light (-1: none)."""
        return -1

    def with_params(self, flat: np.ndarray):
        """A copy of this light with its parameters read from ``flat [num_params]`` (other fields kept)."""
        return dataclasses.replace(self, **self._split(np.asarray(flat, np.float64)))

    def split_gradient(self, g: np.ndarray) -> dict[str, np.ndarray]:
        """``{parameter name: gradient}`` of this light from its slice ``g [num_params]`` of the packed gradient."""
        return self._split(g)

    def gltf_punctual(self):
        """``(glTF KHR_lights_punctual type, its 3-vector: position or direction, rgb intensity)``, or
        None when the light has no punctual glTF equivalent (``mesh.export.punctual_lights``)."""
        return None

    def to_json(self) -> dict:
        """``{"type": class name, field: value (lists)}`` (the format of ``lights.json``)."""
        d = {"type": type(self).__name__}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            d[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return d

    @classmethod
    def initial(cls, init: LightInit):
        """The method's initial light of this kind in training (placed from the cameras)."""
        raise NotImplementedError


def _ring_direction(init: LightInit) -> np.ndarray:
    """Unit direction ``k = init.index`` of ``n = init.count`` on a ring 31° above the horizon:
    ``normalize(0.6 up + cos(2πk/n) a + sin(2πk/n) b)``, ``a, b`` unit and orthogonal to ``up``."""
    up = init.up / max(np.linalg.norm(init.up), 1e-12)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    t = 2 * np.pi * init.index / init.count
    d = 0.6 * up + np.cos(t) * a + np.sin(t) * b
    return d / np.linalg.norm(d)


@register_light
@dataclass
class AmbientLight(Light):
    """Constant ambient radiance ``color`` (rgb); shading adds ``La * albedo * ao`` / ``La * ka``."""

    color: np.ndarray = field(default_factory=lambda: np.ones(3))

    TYPE: ClassVar[int] = 0
    DEFINE: ClassVar[str] = "AMBIENT"
    KIND: ClassVar[str] = "ambient"
    PARAMS: ClassVar[tuple[str, ...]] = ("color",)
    RADIOMETRIC: ClassVar[tuple[str, ...]] = ("color",)

    def __post_init__(self):
        self.color = _vec3("AmbientLight.color", self.color)

    @classmethod
    def initial(cls, init: LightInit) -> AmbientLight:
        """Dim ambient light (0.1)."""
        return cls(np.full(3, 0.1))


@register_light
@dataclass
class DirectionalLight(Light):
    """Distant light arriving from ``direction`` (surface → light) with rgb ``intensity``."""

    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))

    TYPE: ClassVar[int] = 1
    DEFINE: ClassVar[str] = "DIRECTIONAL"
    KIND: ClassVar[str] = "directional"
    CASTS_SHADOWS: ClassVar[bool] = True
    SHADOW_RAY_PARAM: ClassVar[str | None] = "direction"
    PARAMS: ClassVar[tuple[str, ...]] = ("direction", "intensity")
    RADIOMETRIC: ClassVar[tuple[str, ...]] = ("intensity",)

    def __post_init__(self):
        self.direction = _vec3("DirectionalLight.direction", self.direction)
        self.intensity = _vec3("DirectionalLight.intensity", self.intensity)

    def gltf_punctual(self):
        return "directional", self.direction, self.intensity

    @classmethod
    def initial(cls, init: LightInit) -> DirectionalLight:
        """One: from the cameras' mean up direction, intensity 1. Light ``k`` of ``n >= 2``: from the ring
        direction ``k`` of :meth:`PointLight.initial`, intensity 1 / n."""
        if init.count <= 1:
            return cls(init.up, np.full(3, 1.0))
        return cls(_ring_direction(init), np.full(3, 1.0 / init.count))


@register_light
@dataclass
class PointLight(Light):
    """Point light at ``position`` with rgb ``intensity``; ``falloff`` divides by the squared distance
    (clamped below at 1e-6). ``falloff`` is not differentiable."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))
    falloff: bool = True

    TYPE: ClassVar[int] = 2
    DEFINE: ClassVar[str] = "POINT"
    KIND: ClassVar[str] = "point"
    CASTS_SHADOWS: ClassVar[bool] = True
    SHADOW_RAY_PARAM: ClassVar[str | None] = "position"
    PARAMS: ClassVar[tuple[str, ...]] = ("position", "intensity")
    RADIOMETRIC: ClassVar[tuple[str, ...]] = ("intensity",)

    def __post_init__(self):
        self.position = _vec3("PointLight.position", self.position)
        self.intensity = _vec3("PointLight.intensity", self.intensity)
        self.falloff = bool(self.falloff)

    def table_ints(self) -> tuple[int, int]:
        return int(self.falloff), 0

    def gltf_punctual(self):
        """A point light without falloff has no glTF equivalent."""
        return ("point", self.position, self.intensity) if self.falloff else None

    @classmethod
    def initial(cls, init: LightInit) -> PointLight:
        """One point light: above the scene (``init.distance`` extents along up, jittered by 0.3 extent). Light
        ``k`` of ``n >= 2``: ``init.distance`` extents from the centre towards ``0.6 up + cos(2πk/n) a +
        sin(2πk/n) b`` (``a, b`` unit, orthogonal to ``up``: a ring tilted 31° above the horizon), jittered by
        0.05 extent. Intensity ``(distance · extent / 0.6)² / n``: the irradiance at the centre does not depend
        on the distance (extent² at the original 0.6 extents). Spread, because lights started at one place stay
        together: measured on the two-light synthetic scene (tests/test_recovery.py) both converged on the
        brighter light and the ambient light and the albedo took the other's share; spread, each found its
        light within 2°."""
        e, k = init.extent, init.distance
        intensity = e * e * (k / 0.6) ** 2  # exactly extent² at the default 0.6
        if init.count <= 1:
            return cls(init.center + k * e * init.up + 0.3 * e * init.rng.normal(size=3), np.full(3, intensity))
        pos = init.center + k * e * _ring_direction(init) + 0.05 * e * init.rng.normal(size=3)
        return cls(pos, np.full(3, intensity / init.count))


@register_light
@dataclass
class SHEnvironmentLight(Light):
    """Distant environment of radiance ``sum_k coeffs[:, k] Y_k(w)``: ``coeffs [3, (D+1)^2]``, D <= 8.

    ``degree`` (default ``D``) is the active degree of the band schedule; coefficients above it are
    ignored and get zero gradients. Diffuse: irradiance by the clamped-cosine SH convolution;
    glossy: radiance along the reflected view direction with bands attenuated by roughness (see
    ``kernels_cl/common/shade_brdf.h``).
    """

    coeffs: np.ndarray = field(default_factory=lambda: np.array([[np.sqrt(4 * np.pi)]] * 3))
    degree: int | None = None

    TYPE: ClassVar[int] = 3
    DEFINE: ClassVar[str] = "SH_ENV"
    KIND: ClassVar[str] = "sh-env"
    PARAMS: ClassVar[tuple[str, ...]] = ("coeffs",)
    RADIOMETRIC: ClassVar[tuple[str, ...]] = ("coeffs",)

    def __post_init__(self):
        c = np.asarray(self.coeffs, dtype=np.float64)
        if c.ndim != 2 or c.shape[0] != 3:
            raise ValueError(f"SHEnvironmentLight.coeffs must have shape [3, (D+1)^2], got {list(c.shape)}")
        D = int(round(np.sqrt(c.shape[1]))) - 1
        if (D + 1) ** 2 != c.shape[1] or D > MAX_SH_DEGREE:
            raise ValueError(
                f"SHEnvironmentLight.coeffs must have (D+1)^2 columns with D <= {MAX_SH_DEGREE}, got {c.shape[1]}"
            )
        if not np.isfinite(c).all():
            raise ValueError("SHEnvironmentLight.coeffs must be finite")
        self.coeffs = c
        if self.degree is None:
            self.degree = D
        if not 0 <= int(self.degree) <= D:
            raise ValueError(f"SHEnvironmentLight.degree must lie in [0, {D}], got {self.degree}")
        self.degree = int(self.degree)

    @property
    def stored_degree(self) -> int:
        return int(round(np.sqrt(self.coeffs.shape[1]))) - 1

    @classmethod
    def constant(cls, radiance, degree: int = 0) -> SHEnvironmentLight:
        """A uniform environment of rgb ``radiance`` stored with ``degree`` bands."""
        c = np.zeros((3, (degree + 1) ** 2))
        c[:, 0] = np.broadcast_to(np.asarray(radiance, float), 3) * np.sqrt(4 * np.pi)
        return cls(c, degree)

    def table_ints(self) -> tuple[int, int]:
        return self.degree, self.coeffs.shape[1]

    def inactive_mask(self) -> np.ndarray:
        """The bands above ``degree``."""
        mask = np.zeros(self.coeffs.shape, bool)
        mask[:, (self.degree + 1) ** 2:] = True
        return mask.reshape(-1)

    def sh_degree_needed(self) -> int:
        return self.degree

    @classmethod
    def initial(cls, init: LightInit) -> SHEnvironmentLight:
        """A constant environment of radiance 0.1 (the ambient light's) stored with ``sh_degree`` bands, active
        degree 0. Not 0.5: photos fix albedo × light, so the lights' overall scale stays near where it starts; at
        0.5 (irradiance 1.6 on top of the point light's) the albedo of spot ended 1.6–2.1× too dark on every
        point-lit capture (bench/results/light_models_pocl_2026-11-26.txt)."""
        coeffs = np.zeros((3, (init.sh_degree + 1) ** 2))
        coeffs[:, 0] = 0.1 / _Y00
        return cls(coeffs, 0)


@register_light
@dataclass
class VertexSHLight(Light):
    """The per-vertex SH light: the shading op reads ``vlight [P, 6]`` (radiance, direction wi)."""

    TYPE: ClassVar[int] = 4
    DEFINE: ClassVar[str] = "VERTEX_SH"
    KIND: ClassVar[str] = "vertex-sh"
    NEEDS_VLIGHT: ClassVar[bool] = True

    @classmethod
    def initial(cls, init: LightInit) -> VertexSHLight:
        return cls()


@register_light
@dataclass
class BounceLight(Light):
    """Light that reached a point after one diffuse bounce off the rest of the object (interreflection), as a
    uniform radiance per point: the shading op reads it from ``vlight [P, 6]`` (columns 0-2; 3-5 unused) and
    lights the point as the ambient light does (``ambient_term``). Internal: the renderer appends it to the
    lights when given the traced per-vertex radiance (``visibility.vertex_bounce``), a constant for the gradient
    (as the cached shadows); it has no parameters and is never learned, saved or asked for."""

    TYPE: ClassVar[int] = 5
    DEFINE: ClassVar[str] = "BOUNCE"
    KIND: ClassVar[str] = "bounce"
    NEEDS_VLIGHT: ClassVar[bool] = True
    INTERNAL: ClassVar[bool] = True

    @classmethod
    def initial(cls, init: LightInit) -> BounceLight:
        return cls()


_Y00 = 0.28209479177387814  # the constant real SH basis function
#: the type ids (also ``<Class>.TYPE``), kept as module names
AMBIENT, DIRECTIONAL, POINT, SH_ENV, VERTEX_SH, BOUNCE = (AmbientLight.TYPE, DirectionalLight.TYPE, PointLight.TYPE,
                                                          SHEnvironmentLight.TYPE, VertexSHLight.TYPE, BounceLight.TYPE)


@dataclass
class LightTable:
    """The packed light table (see the module docstring)."""

    ints: np.ndarray  # [L, 4] int32
    params: np.ndarray  # [T] float64
    env_degree: int  # largest active SH degree of the environment lights (-1: none)
    has_vertex_sh: bool
    inactive: np.ndarray  # [T] bool: parameters that get no gradient (inactive SH bands)
    #: ``[NV]`` offsets into ``params`` of each shadow caster's ``SHADOW_RAY_PARAM`` (light order)
    shadow_ray_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def shadowed(self) -> np.ndarray:
        """Indices (in light order) of the lights that cast ray-traced shadows: ``[NV]``."""
        casters = shadow_casting_types()  # (a few lights: a loop, not np.isin's ~0.5 ms, four times a step)
        return np.array([i for i, t in enumerate(self.ints[:, 0].tolist()) if t in casters], np.int64)

    @property
    def num_shadowed(self) -> int:
        return len(self.shadowed)


def _check_lights(lights) -> list:
    lights = list(lights)
    for i, lt in enumerate(lights):
        if not is_light(lt):
            raise ValueError(f"lights[{i}] must be one of the light classes of triplet_cl.lights "
                             f"({', '.join(LIGHT_CLASSES)}), got {type(lt)}")
    return lights


def pack_lights(lights) -> LightTable:
    """Pack a sequence of lights into a :class:`LightTable`."""
    lights = _check_lights(lights)
    ints = np.zeros((max(len(lights), 1), 4), np.int32)[: len(lights)]
    chunks, off, env_deg, has_vsh, inactive, ray_off = [], 0, -1, False, [], []
    for i, lt in enumerate(lights):
        flat = lt.flat_params()
        a, b = lt.table_ints()
        env_deg = max(env_deg, lt.sh_degree_needed())
        has_vsh = has_vsh or lt.NEEDS_VLIGHT
        ints[i] = (lt.TYPE, off, a, b)
        if lt.CASTS_SHADOWS:
            ray_off.append(off + lt.param_offset(lt.SHADOW_RAY_PARAM))
        chunks.append(flat)
        inactive.append(lt.inactive_mask())
        off += len(flat)
    params = np.concatenate(chunks) if chunks else np.zeros(0)
    inactive = np.concatenate(inactive) if inactive else np.zeros(0, bool)
    return LightTable(ints, params, env_deg, has_vsh, inactive, np.asarray(ray_off, np.int64))


def relative_lr_scales(lights, floor: float = 1e-3, position: float = 1.0, extent: float | None = None) -> np.ndarray:
    """``[T]`` learning-rate factors of the packed parameters: each radiometric parameter (``RADIOMETRIC``: a
    colour, an intensity, SH radiance) gets the largest magnitude of its current value (at least ``floor``),
    every other (positions, directions) 1. With them Adam moves every radiometric parameter by about the same
    fraction of its size per step: with one absolute rate (0.01), an ambient light of 0.1 moved by up to 10 %
    per step and a point light of intensity ~12 (extent²) by 0.08 %, so the ambient light and the albedo
    explained the shading long before the point light's intensity could (spot: ambient 0.39, truth 0.08;
    intensity 15, truth 30). ``position``: the factor of the point lights' positions
    (``TrainConfig.lr_light_position_scale``), a rate in world units at the dev scenes' size: with the scene's
    ``extent`` it is scaled by ``extent / datasets.base.REFERENCE_EXTENT`` (a capture in other units)."""
    if extent is not None:
        from .datasets.base import REFERENCE_EXTENT

        position = position * extent / REFERENCE_EXTENT
    out = []
    for lt in _check_lights(lights):
        for n, shape in lt.param_shapes().items():
            k = math.prod(shape)
            v = np.asarray(getattr(lt, n), np.float64)
            out.append(np.full(k, max(float(np.abs(v).max()) if v.size else 0.0, floor) if n in lt.RADIOMETRIC
                               else (position if n == "position" else 1.0)))
    return np.concatenate(out) if out else np.zeros(0)


def unpack_gradients(lights, v_params: np.ndarray) -> list[dict[str, np.ndarray]]:
    """Split the ``[T]`` gradient of the packed parameters into ``{param name: gradient}`` per light."""
    out, off = [], 0
    for lt in lights:
        n = lt.num_params
        out.append(lt.split_gradient(np.asarray(v_params[off:off + n])))
        off += n
    return out


def irradiance_rgb(light, center) -> np.ndarray | None:
    """``[3]`` the irradiance a surface at ``center`` facing the light receives from ``light`` (a point light
    ``I / d²``, a directional light its intensity, a uniform / SH environment ``π ×`` its mean radiance); None
    for a light without one colour for the whole scene (the per-vertex SH light)."""
    if isinstance(light, AmbientLight):
        return np.pi * np.asarray(light.color, np.float64)
    if isinstance(light, PointLight):
        i = np.asarray(light.intensity, np.float64)
        if not light.falloff:
            return i
        q = np.asarray(light.position, np.float64) - np.asarray(center, np.float64)
        return i / max(float(q @ q), 1e-6)
    if isinstance(light, DirectionalLight):
        return np.asarray(light.intensity, np.float64)
    if isinstance(light, SHEnvironmentLight):
        return np.pi * np.asarray(light.coeffs, np.float64)[:, 0] * _Y00  # band 0 × Y00: the mean radiance
    return None


def _map_radiometric(lights, params: np.ndarray, fn) -> np.ndarray:
    """A copy of the packed light ``params [T]`` with ``fn(value)`` applied to each radiometric parameter
    (``RADIOMETRIC``, in its own shape: ``[3]`` colours, ``[3, (D+1)²]`` SH radiance); positions and directions
    untouched."""
    params = np.asarray(params)
    out = params.astype(np.float64).copy()
    off = 0
    for lt in _check_lights(lights):
        for n, shape in lt.param_shapes().items():
            k = math.prod(shape)
            if n in lt.RADIOMETRIC:
                out[off:off + k] = np.broadcast_to(fn(out[off:off + k].reshape(shape)), shape).reshape(-1)
            off += k
    return out.astype(params.dtype)


def scale_lights(lights, params: np.ndarray, factor: float) -> np.ndarray:
    """The packed light ``params [T]`` with every radiometric parameter (colour, intensity, SH radiance) × ``factor``:
    the same lights ``factor`` times as bright, positions and directions untouched."""
    return _map_radiometric(lights, params, lambda v: v * float(factor))


def grey_lights(lights, params: np.ndarray) -> np.ndarray:
    """The packed light ``params [T]`` with every light's colour made grey (each radiometric parameter's channels
    replaced by their mean; SH radiance band by band): white lights of the same brightness."""
    return _map_radiometric(lights, params, lambda v: v.mean(axis=0, keepdims=True))


def white_balance(lights, params: np.ndarray, center) -> np.ndarray:
    """The packed light ``params [T]`` rescaled per colour channel so that the lights *together* are white at
    ``center``: the summed irradiance (:func:`irradiance_rgb`) gets equal channels at its mean, every radiometric
    parameter of channel ``k`` × ``mean(T) / T_k``. Each light's colour relative to the others' stays free (a
    warm sun under a blue sky), only the tint common to all of them goes: photos fix albedo × light per point,
    so that tint is the albedo's or the lights' alike, and an object's colour is the usual reading (white
    light). Returns ``params`` unchanged when a channel's total is not positive or a light has no one colour."""
    parts = [irradiance_rgb(lt, center) for lt in unpack_lights(lights, params)]
    if not parts or any(p is None for p in parts):
        return np.asarray(params)
    total = np.sum(parts, axis=0)
    if not np.all(np.isfinite(total)) or total.min() <= 0:
        return np.asarray(params)
    f = total.mean() / total
    return _map_radiometric(lights, params, lambda v: v * (f if v.ndim == 1 else f[:, None]))


def _nonnegative(v: np.ndarray) -> np.ndarray:
    if v.ndim == 1:
        return np.maximum(v, 0.0)
    v = v.copy()
    v[:, 0] = np.maximum(v[:, 0], 0.0)  # SH radiance: the mean (band 0) only; higher bands carry signed detail
    return v


def nonnegative_lights(lights, params: np.ndarray) -> np.ndarray:
    """The packed light ``params [T]`` with every colour / intensity clamped to ``>= 0`` (an SH environment's mean
    radiance, its band 0). A physical constraint, applied after every step whatever the white-light mode: measured
    on spot re-rendered under an HDR environment (``bench/make_scene.py --lights env``), the default point light's
    intensity went to −2.4 while the ambient light rose to 0.45 and the albedo fell to 6.9 dB (scaled)."""
    return _map_radiometric(lights, params, _nonnegative)


#: ``TrainConfig.white_light``: every light white / the lights together white / any tint
WHITE_LIGHT_MODES = ("each", "total", "off")


def hold_irradiance(lights, before, params, center) -> np.ndarray:
    """The packed light ``params`` with each point light's (with falloff) intensity × ``(d / d_before)²``, ``d`` its
    distance from ``center`` in ``params`` and ``d_before`` in ``before`` (the parameters before the optimiser
    step): moving a point light does not change the irradiance it gives the centre, which only its intensity's own
    gradient changes.

    Why: photos fix albedo × irradiance (the gauge), and the distance is what they constrain least (the falloff's
    variation across the object). A point light's position steps 10× its intensity's relative rate
    (``TrainConfig.lr_light_position_scale``), so the gauge drifted with the distance: spot_small's shape with a dark
    uniform albedo (the avocado's, bench/results/avocado_pocl_2026-11-27.txt) had its light walk from 2.4 to 5.6
    away at a constant intensity, the irradiance at the centre falling to 0.39 (truth 1.56) and the albedo rising to
    match: relight 25.45 / 22.82 / 19.29 dB; with this 35.44 / 33.32 / 29.70."""
    out = np.array(params, np.float64, copy=True)
    before = np.asarray(before, np.float64)
    c = np.asarray(center, np.float64)
    off = 0
    for lt in lights:
        if isinstance(lt, PointLight) and lt.falloff:
            d0 = float(np.sum((before[off:off + 3] - c) ** 2))
            d1 = float(np.sum((out[off:off + 3] - c) ** 2))
            if d0 > 0 and np.isfinite(d1):
                out[off + 3:off + 6] *= d1 / d0
        off += lt.num_params
    return out.astype(np.asarray(params).dtype, copy=False)


def lights_kept_out(lights, params, center, radius: float, before=None) -> np.ndarray:
    """The packed light ``params`` with every point light closer than ``radius`` to ``center`` moved out along its
    direction from the centre to ``radius`` (a light at the centre itself: along its direction in ``before``, or
    up ``+y``). ``radius`` 0: unchanged.

    Why: a point light inside or against the object lights nothing the photos show, and near a surface the inverse
    square makes its gradient spike. On spot_small's photos flattened on white (seed 0; the same with alpha is
    seed-dependent luck) one such spike at iteration 244 threw the soup's light from 1.5 to 0.5 away from the centre,
    inside the cow; :func:`hold_irradiance` scaled its intensity by the square of that (to 0.5, then 0 under the
    ``>= 0`` clamp), the ambient took the lighting and the light came back from below: test PSNR 30.40 dB against
    34.18 with the light kept at one frame radius (``TrainConfig.light_min_distance``)."""
    out = np.array(params, np.float64, copy=True)
    if not radius > 0:
        return out.astype(np.asarray(params).dtype, copy=False)
    c = np.asarray(center, np.float64)
    off = 0
    for lt in lights:
        if isinstance(lt, PointLight):
            v = out[off:off + 3] - c
            d = float(np.linalg.norm(v))
            if d < radius:
                if d <= 1e-12 * radius and before is not None:
                    v = np.asarray(before, np.float64)[off:off + 3] - c
                    d = float(np.linalg.norm(v))
                u = v / d if d > 1e-12 * radius else np.array([0.0, 1.0, 0.0])
                out[off:off + 3] = c + radius * u
        off += lt.num_params
    return out.astype(np.asarray(params).dtype, copy=False)


def balanced_lights(mode: str, lights, params, center, light_phase: bool = False, before=None,
                    min_distance: float = 0.0) -> np.ndarray:
    """The packed light ``params`` after the white-light rule ``mode`` (``TrainConfig.white_light``), applied after
    each optimiser step of the soup and mesh stages: "each" every light grey (:func:`grey_lights`); "total" the
    lights together white at ``center`` (:func:`white_balance`), each grey during the light phase; "off"
    any tint. In every mode the colours and intensities end clamped to ``>= 0`` (:func:`nonnegative_lights`).
    ``min_distance``: point lights kept at least this far from ``center`` (:func:`lights_kept_out`, first; 0: not
    applied); ``before``: the parameters before the step, for :func:`hold_irradiance` (then; None: not applied)."""
    if min_distance > 0:
        params = lights_kept_out(lights, params, center, min_distance, before=before)
    if before is not None:
        params = hold_irradiance(lights, before, params, center)
    if mode == "each" or (mode == "total" and light_phase):
        params = grey_lights(lights, params)
    if mode == "total":
        params = white_balance(lights, params, center)
    return nonnegative_lights(lights, params)


def unpack_lights(lights, params: np.ndarray) -> list:
    """The lights with their parameters read from the packed ``params [T]`` (other fields kept): the
    inverse of :func:`pack_lights` for a table built from ``lights``."""
    out, off = [], 0
    params = np.asarray(params, np.float64)
    for lt in lights:
        n = lt.num_params
        out.append(lt.with_params(params[off:off + n]))
        off += n
    return out


def light_to_json(light) -> dict:
    """``{"type": class name, field: value (lists)}`` of a light (the format of ``lights.json``)."""
    return light.to_json()


def lights_to_json(lights, check_finite: bool = True) -> dict:
    """``{"lights": [light_to_json(light), ...]}``: the document of ``lights.json``. Checks every
    light first: a registered light class, and (``check_finite``) finite values."""
    out = []
    for i, lt in enumerate(lights):
        if type(lt).__name__ not in LIGHT_CLASSES:  # its "type" must name a class lights_from_json knows
            raise ValueError(f"lights[{i}] must be a triplet_cl.lights object, got {type(lt).__name__}")
        for k, v in vars(lt).items() if check_finite else ():
            if isinstance(v, np.ndarray) and not np.isfinite(v).all():
                raise ValueError(f"lights[{i}] ({type(lt).__name__}).{k} must be finite, found NaN/Inf")
        out.append(light_to_json(lt))
    return {"lights": out}


def lights_from_json(items) -> list:
    """Lights from a list of :func:`light_to_json` dicts (or a ``{"lights": [...]}`` document)."""
    if isinstance(items, dict):
        items = items.get("lights", [])
    out = []
    for i, d in enumerate(items):
        d = dict(d)
        kind = d.pop("type", None)
        cls = LIGHT_CLASSES.get(kind)
        if cls is None:
            raise ValueError(f"lights[{i}].type must be one of {sorted(LIGHT_CLASSES)}, got {kind!r}")
        try:
            out.append(cls(**d))
        except TypeError as exc:
            raise ValueError(f"lights[{i}] ({kind}): {exc}") from None
    return out


def initial_lights(kinds, init: LightInit) -> list:
    """The method's initial lights for a sequence of CLI kinds (:data:`LIGHT_KINDS`), in that order."""
    bad = [k for k in kinds if k not in LIGHT_KINDS]
    if bad:
        raise ValueError(f"light kinds must be among {tuple(LIGHT_KINDS)}, got {bad}")
    kinds = list(kinds)
    out = []
    for i, k in enumerate(kinds):
        rank, count = kinds[:i].count(k), kinds.count(k)
        out.append(LIGHT_KINDS[k].initial(dataclasses.replace(init, index=rank, count=count)))
    return out
