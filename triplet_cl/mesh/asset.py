"""The hand-over object of the mesh phase: a connected triangle mesh with activated per-vertex PBR
attributes and the scene's lights."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..materials import BRDFS, DEFAULT_BRDF, get_brdf
from ..ops.common import check_faces, check_real

#: per-vertex attributes each BRDF carries, with their widths (``materials.BRDF.attributes``;
#: activated values, in [0, 1] for sigmoid channels); ``alpha`` [N] is optional for all.
ATTRIBUTES = {name: b.attribute_widths for name, b in BRDFS.items()}


@dataclass
class MeshAsset:
    """A connected mesh with PBR attributes.

    Attributes:
        V: ``[N, 3] float32`` world positions; F: ``[M, 3] int32`` faces (counter-clockwise seen
            from outside where the orientation is known).
        attributes: ``name -> [N] or [N, k] float32`` activated per-vertex values; the names of
            :data:`ATTRIBUTES` for ``brdf`` are required, ``alpha`` is optional.
        brdf: a name of ``materials.BRDFS``.
        lights: :mod:`triplet_cl.lights` objects with their trained parameters.
    """

    V: np.ndarray
    F: np.ndarray
    attributes: dict = field(default_factory=dict)
    brdf: str = DEFAULT_BRDF
    lights: list = field(default_factory=list)

    def __post_init__(self):
        self.V = check_real("V", self.V, (None, 3), np.float32)
        self.F = check_faces("F", self.F, len(self.V))
        if self.brdf not in ATTRIBUTES:
            raise ValueError(f"brdf must be one of {sorted(ATTRIBUTES)}, got {self.brdf!r}")
        n = len(self.V)
        out = {}
        for name, a in self.attributes.items():
            a = np.asarray(a)
            width = ATTRIBUTES[self.brdf].get(name, 1)
            shape = (n,) if width == 1 and a.ndim == 1 else (n, width)
            out[name] = check_real(f"attributes[{name!r}]", a, shape, np.float32)
        missing = [k for k in ATTRIBUTES[self.brdf] if k not in out]
        if missing:
            raise ValueError(f"a {self.brdf} MeshAsset needs per-vertex {missing}; got {sorted(out)}")
        self.attributes = out

    @property
    def num_vertices(self) -> int:
        return len(self.V)

    @property
    def num_faces(self) -> int:
        return len(self.F)

    @classmethod
    def from_scene(cls, scene) -> MeshAsset:
        """Activated attributes of a :class:`~triplet_cl.scene.Scene` (soup or mesh), same V and F."""
        from ..activations import sigmoid

        brdf = get_brdf(scene.brdf)
        attrs = {"alpha": sigmoid(np.asarray(scene.alpha.data, np.float64))[:, 0]}
        attrs.update(brdf.split(brdf.activate(scene.material.data)))
        return cls(scene.V.data, scene.F, attrs, scene.brdf, scene.current_lights())
