"""Device copy of a mesh's topology, built once per topology and reused every iteration."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..device import Device
from ..topology import vertex_corner_csr
from .common import check_faces


class DeviceMesh:
    """Faces ``[M, 3]`` on the device plus the vertex → face-corner CSR table of the adjoint gather.

    Args:
        device: the :class:`~triplet_cl.device.Device`.
        faces: ``[M, 3]`` integer vertex indices (validated against ``num_vertices``).
        num_vertices: ``N``.

    Rebuild it whenever the topology changes (density control, mesh phase); vertex positions and
    attributes are passed separately to every op.
    """

    def __init__(self, device: Device, faces, num_vertices: int):
        if int(num_vertices) < 0:
            raise ValueError(f"num_vertices must be >= 0, got {num_vertices}")
        self.device = device
        self.num_vertices = int(num_vertices)
        self.faces = check_faces("faces", faces, self.num_vertices)
        self.num_faces = int(self.faces.shape[0])
        q = device.queue
        self.F = cla.to_device(q, self.faces if self.num_faces else np.zeros((1, 3), np.int32))
        off, corners = vertex_corner_csr(self.faces, self.num_vertices)
        self.csr_off = cla.to_device(q, off)
        self.csr_corner = cla.to_device(q, corners if corners.size else np.zeros(1, np.int32))
        # a soup whose face f has the vertices 3f, 3f + 1, 3f + 2 (the training loop's layout):
        # per-face-corner adjoints are then the per-vertex adjoints, no gather needed
        self.corners_are_vertices = bool(self.num_vertices == 3 * self.num_faces and np.array_equal(
            self.faces.reshape(-1), np.arange(3 * self.num_faces)))

    @property
    def edge_neighbors(self) -> np.ndarray:
        """``[M, 3]`` the face across each edge (``topology.face_edge_neighbors``), computed once."""
        if getattr(self, "_edge_neighbors", None) is None:
            from ..topology import face_edge_neighbors

            self._edge_neighbors = face_edge_neighbors(self.faces)
        return self._edge_neighbors

    @property
    def device_edge_neighbors(self) -> cla.Array:
        """:attr:`edge_neighbors` on the device (``[M, 3] int32``; one row for an empty mesh), copied once."""
        if getattr(self, "_edge_neighbors_dev", None) is None:
            nb = np.ascontiguousarray(self.edge_neighbors, np.int32)
            self._edge_neighbors_dev = cla.to_device(self.device.queue, nb if len(nb) else np.zeros((1, 3), np.int32))
        return self._edge_neighbors_dev

    def __repr__(self) -> str:
        return f"DeviceMesh(N={self.num_vertices}, M={self.num_faces})"
