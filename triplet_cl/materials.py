"""The material models: one descriptor per BRDF, read by every layer that knows material channels.

A :class:`BRDF` names its per-vertex material channels (the columns of ``Scene.material`` and of the
shading op's ``mat``), their activations (raw → activated: sigmoid, or softplus for an unbounded
channel such as the Blinn-Phong shininess), their initial (activated) values, how the channels group
into the mesh asset's attributes, how those map onto glTF metallic-roughness and OBJ/MTL, and the
kernel define that selects the BRDF in ``kernels_cl/common/shade_brdf.h``.

========================  =====  ===============================================================
BRDF                      C      channels (activation; initial value)
========================  =====  ===============================================================
``"cook_torrance"``       6      albedo r, g, b (sigmoid; 0.5) | roughness (sigmoid; 0.5) |
                                 metallic (sigmoid; 0.1) | ambient occlusion (sigmoid; 0.99)
``"blinn_phong"``         10     kd r, g, b (sigmoid; 0.5) | ks r, g, b (sigmoid; 0.7) |
                                 shininess (softplus; 64) | ka r, g, b (sigmoid; 0.2)
========================  =====  ===============================================================

Adding a BRDF: its descriptor here (:data:`BRDFS`), its ``#elif BRDF == BRDF_<NAME>`` block in
``shade_brdf.h`` (``brdf_direct``, ``ambient_term``, ``env_bands``, ``env_scales`` and their
adjoints) and its reference in ``tests/reference/shade.py``; the CLI (``--brdf``) reads ``cli`` here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

ACTIVATIONS = ("sigmoid", "softplus")


@dataclass(frozen=True)
class Channel:
    """One material channel: its name, activation and initial activated value."""

    name: str
    activation: str  # "sigmoid" | "softplus"
    init: float


@dataclass(frozen=True)
class Attribute:
    """A group of consecutive channels that the mesh asset and the exports carry as one attribute
    (``width`` 1: an ``[N]`` array, else ``[N, width]``)."""

    name: str
    start: int
    width: int

    @property
    def columns(self) -> slice:
        return slice(self.start, self.start + self.width)


@dataclass(frozen=True)
class BRDF:
    """The descriptor of one BRDF (see the module docstring).

    Attributes:
        name: the identifier (``Scene.brdf``, ``config.json``, glTF extras); cli: the CLI spelling.
        kernel_id: value of the ``BRDF`` define (``BRDF_<NAME>`` in the kernels).
        channels: the material channels, in column order.
        attributes: the mesh asset's per-vertex attributes (groups of channels).
        pbr: ``(attributes dict, N) -> (roughness [N], metallic [N], ao [N])``: the glTF
            metallic-roughness values of the activated attributes (before clipping to [0, 1]).
        specular: the attribute exported as a specular colour texture (OBJ ``map_Ks``), or None.
        specular_exponent: ``attributes -> OBJ Ns`` (mean Phong exponent), with ``specular``.
        gltf_occlusion: whether the glTF material has an occlusion texture (the ORM image's R).
        gltf_extras: notes written into the glTF material's ``extras.triplet_cl``.
    """

    name: str
    cli: str
    kernel_id: int
    channels: tuple[Channel, ...]
    attributes: tuple[Attribute, ...]
    pbr: Callable
    specular: str | None = None
    specular_exponent: Callable | None = None
    gltf_occlusion: bool = False
    gltf_extras: dict = field(default_factory=dict)

    def __post_init__(self):
        bad = [c.name for c in self.channels if c.activation not in ACTIVATIONS]
        if bad:
            raise ValueError(f"BRDF {self.name}: channels {bad} have an activation not in {ACTIVATIONS}")

    @property
    def num_channels(self) -> int:
        return len(self.channels)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    def column(self, name: str) -> int | None:
        """The material column of channel ``name`` (``"metallic"``, ``"ao"``, …), or None when this BRDF has none."""
        names = self.channel_names
        return names.index(name) if name in names else None

    @property
    def softplus_columns(self) -> list[int]:
        """Columns activated by softplus (the others: sigmoid)."""
        return [i for i, c in enumerate(self.channels) if c.activation == "softplus"]

    @property
    def lobe_columns(self) -> list[int]:
        """The columns that shape the specular lobe and its weight: Cook-Torrance roughness and metallic,
        Blinn-Phong shininess (``TrainConfig.lr_lobe_scale`` scales their learning rate)."""
        return [i for i, c in enumerate(self.channels) if c.name in ("roughness", "metallic", "shininess")]

    @property
    def attribute_widths(self) -> dict[str, int]:
        """``{attribute name: width}`` in channel order."""
        return {a.name: a.width for a in self.attributes}

    def kernel_defines(self) -> dict[str, int]:
        """``-D`` defines of the shading kernels: ``BRDF_<NAME>`` ids of every BRDF, ``BRDF`` (this
        one) and ``NMAT`` (its channel count)."""
        out = {f"BRDF_{b.name.upper()}": b.kernel_id for b in BRDFS.values()}
        out.update(BRDF=self.kernel_id, NMAT=self.num_channels)
        return out

    def initial_raw(self, n: int) -> np.ndarray:
        """``[n, C]`` float64 raw channels of the initial (activated) values."""
        from .activations import inverse_softplus, logit  # lazily: the CLI reads this module at start-up

        raw = logit(np.array([c.init if c.activation == "sigmoid" else 0.5 for c in self.channels]))
        for j in self.softplus_columns:
            raw[j] = inverse_softplus(self.channels[j].init)
        return np.tile(raw, (n, 1))

    def activate(self, raw) -> np.ndarray:
        """``[N, C]`` raw → activated channels (host, float64)."""
        from .activations import sigmoid, softplus

        raw = np.asarray(raw, np.float64)
        act = sigmoid(raw)
        for j in self.softplus_columns:
            act[:, j] = softplus(raw[:, j])
        return act

    def split(self, act: np.ndarray, attributes=None) -> dict[str, np.ndarray]:
        """``{attribute: act[:, columns]}`` (``[N]`` for width-1 attributes) of activated channels."""
        names = attributes if attributes is not None else [a.name for a in self.attributes]
        out = {}
        for a in self.attributes:
            if a.name in names:
                out[a.name] = act[:, a.start] if a.width == 1 else act[:, a.columns]
        return out

    @property
    def bounded_attributes(self) -> list[str]:
        """The attributes whose channels are all sigmoid-activated (values in [0, 1])."""
        return [a.name for a in self.attributes
                if all(c.activation == "sigmoid" for c in self.channels[a.columns])]


def _rgb(prefix: str, act: str, init: float) -> tuple[Channel, ...]:
    return tuple(Channel(f"{prefix}_{c}", act, init) for c in "rgb")


def blinn_phong_roughness(shininess: np.ndarray) -> np.ndarray:
    """glTF (perceptual) roughness of a Blinn-Phong ``shininess`` ``s`` (exponent ``e = s + 1``):
    ``(2 / (e + 2))^(1/4)``, in (0, 0.9036]."""
    e = np.maximum(np.asarray(shininess, np.float64), 0) + 1
    return (2.0 / (e + 2.0)) ** 0.25


COOK_TORRANCE = BRDF(
    name="cook_torrance", cli="cook-torrance", kernel_id=0,
    channels=(*_rgb("albedo", "sigmoid", 0.5), Channel("roughness", "sigmoid", 0.5),
              Channel("metallic", "sigmoid", 0.1), Channel("ao", "sigmoid", 0.99)),
    attributes=(Attribute("albedo", 0, 3), Attribute("roughness", 3, 1), Attribute("metallic", 4, 1),
                Attribute("ao", 5, 1)),
    pbr=lambda a, n: (a["roughness"], a["metallic"], a["ao"]),
    gltf_occlusion=True,
)

BLINN_PHONG = BRDF(
    name="blinn_phong", cli="blinn-phong", kernel_id=1,
    channels=(*_rgb("kd", "sigmoid", 0.5), *_rgb("ks", "sigmoid", 0.7), Channel("shininess", "softplus", 64.0),
              *_rgb("ka", "sigmoid", 0.2)),
    attributes=(Attribute("albedo", 0, 3), Attribute("ks", 3, 3), Attribute("shininess", 6, 1),
                Attribute("ka", 7, 3)),
    pbr=lambda a, n: (blinn_phong_roughness(a["shininess"]), np.zeros(n), np.ones(n)),
    specular="ks",
    specular_exponent=lambda a: float(np.mean(np.maximum(a["shininess"], 0) + 1)),
    gltf_extras={"roughness": "(2 / (shininess + 3))^(1/4)"},
)

def ambient_pairs(brdf: BRDF | str) -> tuple[list[int], list[int]]:
    """``(diffuse columns, ambient columns)`` of a BRDF with its own ambient reflectance (Blinn-Phong's ``ka`` beside
    ``kd``), or two empty lists (Cook-Torrance lights its ambient term with the albedo itself)."""
    b = get_brdf(brdf) if isinstance(brdf, str) else brdf
    names = list(b.channel_names)
    if not all(f"ka_{c}" in names and f"kd_{c}" in names for c in "rgb"):
        return [], []
    return [names.index(f"kd_{c}") for c in "rgb"], [names.index(f"ka_{c}") for c in "rgb"]


def tie_ambient_gradient(param, pairs) -> None:
    """``ka ≡ kd`` (same activation, same raw value): the ambient columns' gradient added to the diffuse columns'
    and zeroed, so the optimizer steps the one shared reflectance (:func:`copy_ambient` after the step)."""
    kd, ka = pairs
    g = param.grad
    if not kd or g is None or not len(g):
        return
    g[:, kd] += g[:, ka]
    g[:, ka] = 0.0


def copy_ambient(param, pairs) -> None:
    """The ambient columns set to the diffuse columns' raw values (``ka ≡ kd``)."""
    kd, ka = pairs
    if kd:
        param.data[:, ka] = param.data[:, kd]


def colour_display_raw(raw_rgb: np.ndarray) -> np.ndarray:
    """A Blinn-Phong raw material ``[N, 10]`` that an ambient light of radiance 1 shows as ``sigmoid(raw_rgb)``
    exactly (its ambient term is ``La ka``; kd = ka = ``raw_rgb``, ks 0): a base colour rendered with no BRDF's
    environment weights in it (the albedo images of ``eval --relight``, test and bench captures)."""
    raw_rgb = np.asarray(raw_rgb)
    n = len(raw_rgb)
    return np.concatenate([raw_rgb, np.full((n, 3), -30.0), np.zeros((n, 1)), raw_rgb], axis=1)


#: every BRDF by name
BRDFS: dict[str, BRDF] = {b.name: b for b in (COOK_TORRANCE, BLINN_PHONG)}
DEFAULT_BRDF = COOK_TORRANCE.name


def highlight_vertices(V, normals, light_position, cameras, cos_half: float = 0.97,
                       cos_view: float = 0.1) -> np.ndarray:
    """``[N] bool``: the vertices some camera sees near the mirror direction of a point light at
    ``light_position`` (the half vector within ``acos(cos_half)`` of the normal, the camera in front): where a
    highlight can tell the specular lobe (roughness, metallic) from the diffuse one. Diagnostics and tests."""
    V = np.asarray(V, np.float64)
    n = np.asarray(normals, np.float64)
    ldir = np.asarray(light_position, np.float64) - V
    ldir /= np.linalg.norm(ldir, axis=1, keepdims=True)
    out = np.zeros(len(V), bool)
    for c in cameras:
        eye = -c.w2c[:3, :3].T @ c.w2c[:3, 3]
        vdir = (eye - V) / np.linalg.norm(eye - V, axis=1, keepdims=True)
        h = ldir + vdir
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        out |= (np.sum(n * h, axis=1) > cos_half) & (np.sum(n * vdir, axis=1) > cos_view)
    return out


def get_brdf(name: str) -> BRDF:
    """The descriptor of ``name``; ``ValueError`` naming the choices otherwise."""
    b = BRDFS.get(name) if isinstance(name, str) else None
    if b is None:
        raise ValueError(f"brdf must be one of {sorted(BRDFS)}, got {name!r}")
    return b


def brdf_from_cli(name: str) -> str:
    """The BRDF name for its CLI spelling (``"cook-torrance"`` → ``"cook_torrance"``)."""
    for b in BRDFS.values():
        if name in (b.cli, b.name):
            return b.name
    raise ValueError(f"--brdf must be one of {[b.cli for b in BRDFS.values()]}, got {name!r}")
