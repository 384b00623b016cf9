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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

AMBIENT, DIRECTIONAL, POINT, SH_ENV, VERTEX_SH = 0, 1, 2, 3, 4
MAX_SH_DEGREE = 8


def _vec3(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape [3], got {list(a.shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite")
    return a


@dataclass
class AmbientLight:
    """Constant ambient radiance ``color`` (rgb); shading adds ``La * albedo * ao`` / ``La * ka``."""

    color: np.ndarray = field(default_factory=lambda: np.ones(3))

    TYPE = AMBIENT
    PARAMS = ("color",)

    def __post_init__(self):
        self.color = _vec3("AmbientLight.color", self.color)


@dataclass
class DirectionalLight:
    """Distant light arriving from ``direction`` (surface → light) with rgb ``intensity``."""

    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))

    TYPE = DIRECTIONAL
    PARAMS = ("direction", "intensity")

    def __post_init__(self):
        self.direction = _vec3("DirectionalLight.direction", self.direction)
        self.intensity = _vec3("DirectionalLight.intensity", self.intensity)


@dataclass
class PointLight:
    """Point light at ``position`` with rgb ``intensity``; ``falloff`` divides by the squared distance
    (clamped below at 1e-6). ``falloff`` is not differentiable."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    intensity: np.ndarray = field(default_factory=lambda: np.ones(3))
    falloff: bool = True

    TYPE = POINT
    PARAMS = ("position", "intensity")

    def __post_init__(self):
        self.position = _vec3("PointLight.position", self.position)
        self.intensity = _vec3("PointLight.intensity", self.intensity)
        self.falloff = bool(self.falloff)


@dataclass
class SHEnvironmentLight:
    """Distant environment of radiance ``sum_k coeffs[:, k] Y_k(w)``: ``coeffs [3, (D+1)^2]``, D <= 8.

    ``degree`` (default ``D``) is the active degree of the band schedule; coefficients above it are
    ignored and get zero gradients. Diffuse: irradiance by the clamped-cosine SH convolution;
    glossy: radiance along the reflected view direction with bands attenuated by roughness (see
    ``kernels_cl/common/shade_brdf.h``).
    """

    coeffs: np.ndarray = field(default_factory=lambda: np.array([[np.sqrt(4 * np.pi)]] * 3))
    degree: int | None = None

    TYPE = SH_ENV
    PARAMS = ("coeffs",)

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


@dataclass
class VertexSHLight:
    """The per-vertex SH light: the shading op reads ``vlight [P, 6]`` (radiance, direction wi)."""

    TYPE = VERTEX_SH
    PARAMS = ()


Light = AmbientLight | DirectionalLight | PointLight | SHEnvironmentLight | VertexSHLight


@dataclass
class LightTable:
    """The packed light table (see the module docstring)."""

    ints: np.ndarray  # [L, 4] int32
    params: np.ndarray  # [T] float64
    env_degree: int  # largest active SH degree of the environment lights (-1: none)
    has_vertex_sh: bool
    inactive: np.ndarray  # [T] bool: parameters that get no gradient (inactive SH bands)


def _flat(light) -> np.ndarray:
    if isinstance(light, SHEnvironmentLight):
        return light.coeffs.reshape(-1)
    if not light.PARAMS:
        return np.zeros(0)
    return np.concatenate([getattr(light, n) for n in light.PARAMS])


def pack_lights(lights) -> LightTable:
    """Pack a sequence of lights into a :class:`LightTable`."""
    lights = list(lights)
    ints = np.zeros((max(len(lights), 1), 4), np.int32)[: len(lights)]
    chunks, off, env_deg, has_vsh, inactive = [], 0, -1, False, []
    for i, lt in enumerate(lights):
        if not isinstance(lt, AmbientLight | DirectionalLight | PointLight | SHEnvironmentLight | VertexSHLight):
            raise ValueError(f"lights[{i}] must be one of the light classes of triplet_cl.lights, got {type(lt)}")
        flat = _flat(lt)
        a = b = 0
        mask = np.zeros(len(flat), bool)
        if isinstance(lt, PointLight):
            a = int(lt.falloff)
        elif isinstance(lt, SHEnvironmentLight):
            a, b = lt.degree, lt.coeffs.shape[1]
            env_deg = max(env_deg, lt.degree)
            mask = np.zeros(lt.coeffs.shape, bool)
            mask[:, (lt.degree + 1) ** 2:] = True
            mask = mask.reshape(-1)
        elif isinstance(lt, VertexSHLight):
            has_vsh = True
        ints[i] = (lt.TYPE, off, a, b)
        chunks.append(flat)
        inactive.append(mask)
        off += len(flat)
    params = np.concatenate(chunks) if chunks else np.zeros(0)
    inactive = np.concatenate(inactive) if inactive else np.zeros(0, bool)
    return LightTable(ints, params, env_deg, has_vsh, inactive)


def unpack_gradients(lights, v_params: np.ndarray) -> list[dict[str, np.ndarray]]:
    """Split the ``[T]`` gradient of the packed parameters into ``{param name: gradient}`` per light."""
    out, off = [], 0
    for lt in lights:
        d = {}
        if isinstance(lt, SHEnvironmentLight):
            n = lt.coeffs.size
            d["coeffs"] = np.asarray(v_params[off:off + n]).reshape(lt.coeffs.shape).copy()
            off += n
        else:
            for name in lt.PARAMS:
                d[name] = np.asarray(v_params[off:off + 3]).copy()
                off += 3
        out.append(d)
    return out


LIGHT_CLASSES = {c.__name__: c for c in (AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight,
                                          VertexSHLight)}


def light_to_json(light) -> dict:
    """``{"type": class name, field: value (lists)}`` of a light (the format of ``lights.json``)."""
    d = {"type": type(light).__name__}
    for k, v in vars(light).items():
        d[k] = v.tolist() if isinstance(v, np.ndarray) else v
    return d


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
