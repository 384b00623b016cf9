"""The scene model: a triangle soup (or mesh) with raw per-vertex parameters, and learnable lights.

Parameters are stored raw and activated in the render graph (docs/ARCHITECTURE.md §8):

| parameter | shape | activation | meaning |
|---|---|---|---|
| ``V`` | ``[N, 3]`` | — | vertex positions (world) |
| ``material`` | ``[N, Cm]`` | per channel (``materials.BRDF.channels``) | the BRDF's channels |
| ``alpha`` | ``[N, 1]`` | sigmoid | opacity |
| ``vertex_sh`` | ``[N, 6, (D+1)²]`` | — | per-vertex SH light (optional) |
| ``light_params`` | ``[T]`` | — | every light's parameters, packed (``lights.pack_lights``) |

``F [M, 3]`` is the topology (not optimised). Every array parameter is an
:class:`~triplet_cl.autodiff.Param` so that the tape fills ``.grad`` and Adam updates ``.data``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .activations import inverse_softplus, logit  # noqa: F401  (re-exported: their home is activations)
from .autodiff import Param
from .lights import Light, pack_lights, unpack_lights
from .materials import DEFAULT_BRDF, get_brdf
from .ops.common import check_faces, check_real


def default_material_raw(n: int, brdf: str) -> np.ndarray:
    """The method's initial materials, raw ``[n, Cm]``: the BRDF descriptor's initial values
    (``materials.BRDF.initial_raw``; e.g. albedo 0.5, roughness 0.5, metallic 0.1, AO 0.99)."""
    return get_brdf(brdf).initial_raw(n)


@dataclass
class Scene:
    """A triangle soup / mesh with raw parameters and lights (see the module docstring)."""

    V: Param
    F: np.ndarray
    material: Param
    alpha: Param
    lights: list = field(default_factory=list)
    light_params: Param | None = None
    vertex_sh: Param | None = None
    brdf: str = DEFAULT_BRDF

    @classmethod
    def from_arrays(cls, V, F, *, material=None, alpha=None, lights=None, vertex_sh=None,
                    brdf: str = DEFAULT_BRDF, alpha_init: float = 0.1, dtype=np.float32) -> Scene:
        """Build a scene; omitted parameters get the method's initial values.

        Args:
            V: ``[N, 3]`` positions; F: ``[M, 3]`` faces.
            material: raw ``[N, Cm]`` (default: :func:`default_material_raw`).
            alpha: raw ``[N, 1]`` (default: ``logit(alpha_init)``).
            lights: list of :mod:`triplet_cl.lights` objects (their parameters become
                ``light_params``); vertex_sh: ``[N, 6, (D+1)²]`` coefficients for a VertexSHLight.
        """
        V = check_real("V", V, (None, 3), dtype)
        n = V.shape[0]
        F = check_faces("F", F, n)
        cm = get_brdf(brdf).num_channels
        mat = default_material_raw(n, brdf) if material is None else material
        mat = check_real("material", mat, (n, cm), dtype)
        al = np.full((n, 1), logit(alpha_init)) if alpha is None else alpha
        al = check_real("alpha", al, (n, 1), dtype)
        if isinstance(lights, Light):  # one light given alone
            lights = [lights]
        lights = list(lights or [])
        table = pack_lights(lights)
        lp = Param(table.params.astype(dtype), "light_params") if len(table.params) else None
        vsh = None
        if vertex_sh is not None:
            vsh_a = np.asarray(vertex_sh)
            if vsh_a.ndim != 3 or vsh_a.shape[:2] != (n, 6):
                raise ValueError(f"vertex_sh must have shape [{n}, 6, (D+1)^2], got {list(vsh_a.shape)}")
            vsh = Param(check_real("vertex_sh", vsh_a, vsh_a.shape, dtype), "vertex_sh")
        if table.has_vertex_sh and vsh is None:
            raise ValueError("a VertexSHLight needs vertex_sh coefficients [N, 6, (D+1)^2]")
        return cls(Param(V, "V"), F, Param(mat, "material"), Param(al, "alpha"), lights, lp, vsh, brdf)

    @property
    def params(self) -> list[Param]:
        """Every optimisable parameter."""
        return [p for p in (self.V, self.material, self.alpha, self.light_params, self.vertex_sh) if p is not None]

    def zero_grad(self) -> None:
        for p in self.params:
            p.zero_grad()

    def current_lights(self) -> list:
        """The lights with their current (optimised) parameters written back."""
        lp = np.zeros(0) if self.light_params is None else np.asarray(self.light_params.data, np.float64)
        return unpack_lights(self.lights, lp)
