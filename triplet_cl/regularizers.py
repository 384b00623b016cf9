"""Mesh regularisers with adjoints for the connected-mesh phase (docs/ARCHITECTURE.md §9), host-side.

``V [N, 3]`` vertex positions, ``F [M, 3]`` int faces, ``X [N, C]`` per-vertex attributes.
Each energy is a tape :class:`~triplet_cl.autodiff.Function` built once per topology (the
connectivity is precomputed in the constructor) and a functional form. ``reduction="mean"``
(default) divides the sum by the number of terms named below, ``"sum"`` keeps the sum.

=======================  =========================================================  ==============
energy                   definition                                                  mean over
=======================  =========================================================  ==============
face-normal consistency  ``Σ_{(a,b) edge-adjacent} 1 − n_a·n_b``, ``n = normalize(   P face pairs
                         (v1−v0)×(v2−v0))``; gradient wrt ``V``
uniform Laplacian        ``Σ_i |δ_i|²``, ``δ_i = Σ_{j∈N(i)} (x_j − x_i) / |N(i)|``    N vertices
                         (``δ = L X`` with ``L = D⁻¹A − I``; ``δ_i = 0`` for isolated
                         vertices); gradient ``2 Lᵀ L X``; any ``X [N, D]`` (positions)
rest Laplacian           ``Σ_i |δ_i − δ⁰_i|²``, ``δ⁰ = L X₀`` of a rest shape ``X₀``;    N vertices
                         gradient ``2 Lᵀ (L X − L X₀)``
graph TV on materials    ``Σ_i Σ_{j∈N(i)} sqrt(w_ij)·|x_i − x_j|₁`` (each undirected    2·E·C terms
                         edge counted twice, as the double sum says); gradient
                         ``sign(x_i − x_j)`` (0 at ties); weights below
=======================  =========================================================  ==============

GTV weights ``w_ij``: ``"uniform"`` (1) or ``"inverse_length"``: ``w_ij = ℓ̄ / |v_i − v_j|`` with
``ℓ̄`` the mean edge length (scale-free; shorter edges — finer detail — are tied more strongly);
or an explicit ``[E]`` array aligned with :func:`mesh_edges`. Weights are constants (no gradient
flows to the positions through them).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from triplet_cl.autodiff import Function
from triplet_cl.ops.common import check_faces
from triplet_cl.topology import edge_adjacent_faces
from triplet_cl.topology import mesh_edges as _edges_and_faces

from .losses import reduction_scale as _scale

FACE_NORMAL_EPS = 1e-30  # smooths normalize() only for (near-)degenerate faces


def _check_attr(name: str, a, num_rows: int | None = None, cols: int | None = None) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind != "f":
        raise ValueError(f"{name} must be a floating-point array, got dtype {a.dtype}")
    if a.ndim != 2 or (cols is not None and a.shape[1] != cols) or (num_rows is not None and a.shape[0] != num_rows):
        want = f"[{num_rows if num_rows is not None else 'N'}, {cols if cols is not None else 'C'}]"
        raise ValueError(f"{name} must have shape {want}, got {list(a.shape)}")
    if a.size and not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite, found {int((~np.isfinite(a)).sum())} NaN/Inf value(s)")
    return a


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """``F [M, 3] -> [E, 2] int64``: the unique undirected edges, each as ``(i, j)`` with ``i < j``,
    sorted lexicographically (the edges of :func:`triplet_cl.topology.mesh_edges`)."""
    return _edges_and_faces(faces)[0]


def _scatter_rows(num_rows: int, index: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros((num_rows, values.shape[1]), dtype=values.dtype)
    np.add.at(out, index, values)
    return out


class RowScatter:
    """``out[index[k]] += values[k]`` into ``num_rows`` rows (``_scatter_rows``) for an ``index`` fixed at
    construction, as a sparse product: the ``[num_rows, K]`` 0/1 matrix (CSR, kept per dtype) times ``values``.
    Bit for bit ``np.add.at``'s result (each row sums its entries in index order, in the values' dtype, from 0;
    × 1 is exact) at a fraction of its time: the mesh stage's regularisers scattered 180k rows three times a step
    with ``np.add.at``, 15 ms of a ~100 ms step."""

    def __init__(self, num_rows: int, index: np.ndarray):
        self.num_rows = int(num_rows)
        self.index = np.asarray(index, np.int64)
        self._mats: dict = {}

    def __call__(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values)
        if values.ndim != 2 or values.shape[0] != len(self.index):
            raise ValueError(f"values must have shape [{len(self.index)}, C], got {list(values.shape)}")
        m = self._mats.get(values.dtype.str)
        if m is None:
            k = len(self.index)
            m = self._mats[values.dtype.str] = sp.csr_matrix(
                (np.ones(k, values.dtype), (self.index, np.arange(k))), shape=(self.num_rows, k))
        return np.asarray(m @ values).astype(values.dtype, copy=False)


# ---- face-normal consistency --------------------------------------------------------------------
class FaceNormalConsistency(Function):
    """Tape op ``V [N,3] -> Σ_pairs ρ(1 − n_a·n_b)`` for the edge-adjacent face pairs of ``faces``.

    ``kappa`` None: ``ρ(x) = x``. A number ``κ > 0``: ``ρ(x) = κ·log(1 + x/κ) + x⁵/5``, slope
    ``1 / (1 + x/κ) + x⁴``: small bends are smoothed as by the plain term (slope 1 at ``x = 0``), bends of
    ~25–75° are pulled weakly (κ = 0.05: slope 0.27 at 30°, 0.15 at 45–60°, 0.37 at 75°), a right angle about as
    hard as by the plain term (1.05) and a fold past it harder (1.9 at 100°, 5.1 at 120°): the log alone lets noise
    fold faces over and keep them folded. ``kappa`` may be changed between calls (the mesh stage anneals it); a
    call's backward uses the κ of its forward."""

    def __init__(self, faces, num_vertices: int | None = None, reduction: str = "mean", kappa: float | None = None):
        if kappa is not None and not kappa > 0:
            raise ValueError(f"kappa must be None or > 0, got {kappa}")
        self.kappa = None if kappa is None else float(kappa)
        f = np.asarray(faces)
        n = int(f.max()) + 1 if num_vertices is None and f.size else int(num_vertices or 0)
        self.faces = check_faces("faces", f, n).astype(np.int64)
        self.pairs = edge_adjacent_faces(self.faces)  # [P, 2]
        self.scale = _scale(reduction, len(self.pairs))
        # the faces' corners and the pairs' faces as contiguous index columns: every array below is a column of one
        # component (gathers of 1-D arrays, sums of three columns) instead of [K, 3] rows (fancy row gathers, numpy's
        # slow reductions over a last axis of 3): 17.7 -> 5.9 ms a call on spot's 61k-face mesh, the same bits
        self._corners = [np.ascontiguousarray(self.faces[:, i]) for i in range(3)]
        self._a, self._b = np.ascontiguousarray(self.pairs[:, 0]), np.ascontiguousarray(self.pairs[:, 1])
        self._to_faces = RowScatter(len(self.faces), np.concatenate([self._a, self._b]))
        self._to_vertices = RowScatter(n, self.faces.reshape(-1))

    def forward(self, ctx, vertices):
        v = _check_attr("vertices", vertices, cols=3)
        if self.faces.size and self.faces.max() >= len(v):
            raise ValueError(f"vertices has {len(v)} rows but faces index up to {int(self.faces.max())}")
        f0, f1, f2 = self._corners
        vc = [np.ascontiguousarray(v[:, j]) for j in range(3)]
        p0 = [x[f0] for x in vc]
        e1 = [x[f1] - q for x, q in zip(vc, p0, strict=True)]  # tri[:, 1] - tri[:, 0], per component
        e2 = [x[f2] - q for x, q in zip(vc, p0, strict=True)]
        c = _cross_cols(e1, e2)
        ss = _sum3([q * q for q in c])  # np.sum(c * c, axis=-1): ((c0² + c1²) + c2²)
        r = np.sqrt(ss + FACE_NORMAL_EPS)
        n = [q / r for q in c]  # normalize(c, FACE_NORMAL_EPS)
        a, b = self._a, self._b
        x = 1.0 - _sum3([q[a] * q[b] for q in n])
        k = self.kappa
        ctx.save(len(v), e1, e2, c, ss, n, x, k)
        if k is not None:
            return np.asarray(np.sum(k * np.log1p(x / k) + x**5 / 5) * self.scale)
        return np.asarray(np.sum(x) * self.scale)

    def backward(self, ctx, v_out):
        num_v, e1, e2, c, ss, n, x, k = ctx.saved
        a, b = self._a, self._b
        s = -float(v_out) * self.scale
        if k is not None:  # ρ'(x) per pair
            s = s * (1.0 / (1.0 + x / k) + x**4)
        v_n = self._to_faces(np.stack([np.concatenate([s * q[b], s * q[a]]) for q in n], axis=1))
        v_n = [np.ascontiguousarray(v_n[:, j]) for j in range(3)]
        # normalize_bwd(c, v_n, FACE_NORMAL_EPS): inv = 1 / sqrt(|c|² + eps), y = c inv, (v_n − y (y·v_n)) inv
        inv = 1.0 / np.sqrt(ss + FACE_NORMAL_EPS)
        y = [q * inv for q in c]
        yv = _sum3([p * q for p, q in zip(y, v_n, strict=True)])
        v_c = [(q - p * yv) * inv for p, q in zip(y, v_n, strict=True)]
        v_e1, v_e2 = _cross_cols(e2, v_c), _cross_cols(v_c, e1)  # adjoints of c = e1 × e2
        # the corners' rows in the order of faces.reshape(-1): [M, 3 corners, 3 components]
        corner = np.stack([np.stack([-(p + q), p, q], axis=1) for p, q in zip(v_e1, v_e2, strict=True)], axis=2)
        if num_v != self._to_vertices.num_rows:
            return _scatter_rows(num_v, self.faces.reshape(-1), corner.reshape(-1, 3))
        return self._to_vertices(corner.reshape(-1, 3))


def _sum3(cols):
    """``np.sum(stack(cols, -1), axis=-1)`` for three columns, in numpy's order for a last axis of 3: ``(c0 + c1) + c2``
    (checked bit for bit against it, ``tests/test_regularizers.py``)."""
    return (cols[0] + cols[1]) + cols[2]


def _cross_cols(p, q):
    """``np.cross`` of two vectors given as columns: numpy's own operations (``p1 q2 − p2 q1``, ``p2 q0 − p0 q2``,
    ``p0 q1 − p1 q0``)."""
    return [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]]


def face_normal_consistency(vertices, faces, reduction: str = "mean", kappa: float | None = None):
    """``Σ_{edge-adjacent faces} ρ(1 − cos(n_a, n_b))`` of a mesh ``V [N,3]``, ``F [M,3]``
    (:class:`FaceNormalConsistency`)."""
    return FaceNormalConsistency(faces, len(np.asarray(getattr(vertices, "data", vertices))), reduction,
                                 kappa)(vertices)


# ---- uniform Laplacian --------------------------------------------------------------------------
def uniform_laplacian_matrix(faces, num_vertices: int) -> sp.csr_matrix:
    """``[N, N]`` sparse ``L = D⁻¹A − I`` (A: 1-ring adjacency, D: valence; rows of isolated
    vertices are zero), so ``(L X)_i = mean_{j∈N(i)} x_j − x_i``."""
    e = mesh_edges(check_faces("faces", faces, num_vertices))
    i = np.concatenate([e[:, 0], e[:, 1]])
    j = np.concatenate([e[:, 1], e[:, 0]])
    adj = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(num_vertices, num_vertices))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    has_ring = (deg > 0).astype(np.float64)
    return (sp.diags(inv) @ adj - sp.diags(has_ring)).tocsr()


class UniformLaplacian(Function):
    """Tape op ``X [N,D] -> Σ_i |(L X)_i|²`` with the uniform Laplacian of ``faces``."""

    def __init__(self, faces, num_vertices: int, reduction: str = "mean"):
        self.num_vertices = int(num_vertices)
        self.lap = uniform_laplacian_matrix(faces, self.num_vertices)
        self.lap_t = self.lap.T.tocsr()
        self.scale = _scale(reduction, self.num_vertices)

    def forward(self, ctx, x):
        x = _check_attr("x", x, num_rows=self.num_vertices)
        delta = self.lap @ x
        ctx.delta = delta
        return np.asarray(np.sum(delta * delta) * self.scale)

    def backward(self, ctx, v_out):
        return (self.lap_t @ ctx.delta) * (2.0 * float(v_out) * self.scale)


class RestLaplacian(UniformLaplacian):
    """Tape op ``X [N,D] -> Σ_i |(L X)_i − (L X₀)_i|²``: the uniform Laplacian of the displacement from
    a rest shape ``X₀`` (the differential coordinates of ``X₀`` are kept, not flattened). Zero, with zero
    gradient, at ``X = X₀``: it damps the noise an optimisation grows without pulling the rest shape's
    curved parts (a thin rod's ring, a fin's edge) towards their neighbours' mean as the plain Laplacian
    does (that pull shrinks a rod a few voxels thick to nothing within tens of Adam steps)."""

    def __init__(self, faces, num_vertices: int, rest, reduction: str = "mean"):
        super().__init__(faces, num_vertices, reduction)
        rest = _check_attr("rest", np.asarray(rest, dtype=np.float64), num_rows=self.num_vertices)
        self.rest_delta = self.lap @ rest

    def forward(self, ctx, x):
        x = _check_attr("x", x, num_rows=self.num_vertices)
        if x.shape[1] != self.rest_delta.shape[1]:
            raise ValueError(f"x has {x.shape[1]} columns but the rest shape has {self.rest_delta.shape[1]}")
        delta = self.lap @ x - self.rest_delta
        ctx.delta = delta
        return np.asarray(np.sum(delta * delta) * self.scale)


def rest_laplacian(x, faces, rest, reduction: str = "mean"):
    """:class:`RestLaplacian` energy of per-vertex ``x [N, D]`` against the rest values ``rest [N, D]``."""
    return RestLaplacian(faces, len(np.asarray(getattr(x, "data", x))), rest, reduction)(x)


def uniform_laplacian(x, faces, reduction: str = "mean"):
    """Uniform Laplacian energy of per-vertex ``x [N, D]`` over the mesh ``faces [M, 3]``."""
    return UniformLaplacian(faces, len(np.asarray(getattr(x, "data", x))), reduction)(x)


# ---- graph total variation ----------------------------------------------------------------------
def gtv_edge_weights(vertices, edges: np.ndarray, kind: str = "inverse_length") -> np.ndarray:
    """``[E]`` weights ``w_ij`` for :class:`MaterialGTV`: ``"uniform"`` (ones) or
    ``"inverse_length"`` (``mean edge length / |v_i − v_j|``, degenerate edges get the largest
    finite weight)."""
    if kind == "uniform":
        return np.ones(len(edges))
    if kind != "inverse_length":
        raise ValueError(f"kind must be 'uniform' or 'inverse_length', got {kind!r}")
    v = _check_attr("vertices", vertices, cols=3)
    length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    mean = float(length.mean()) if len(length) else 1.0
    w = np.divide(mean, length, out=np.zeros_like(length), where=length > 0)
    if (length <= 0).any():
        w[length <= 0] = w.max() if (length > 0).any() else 1.0
    return w


class MaterialGTV(Function):
    """Tape op ``X [N,C] -> Σ_i Σ_{j∈N(i)} sqrt(w_ij)·|x_i − x_j|₁`` over the 1-rings of ``faces``.

    ``weights``: None (uniform) or ``[E]`` aligned with ``mesh_edges(faces)`` (see
    :func:`gtv_edge_weights`).
    """

    def __init__(self, faces, num_vertices: int, weights=None, reduction: str = "mean"):
        self.num_vertices = int(num_vertices)
        self.edges = mesh_edges(check_faces("faces", faces, self.num_vertices))
        w = np.ones(len(self.edges)) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != (len(self.edges),) or (w < 0).any() or not np.isfinite(w).all():
            raise ValueError(f"weights must be finite, >= 0, with shape [{len(self.edges)}] (one per mesh edge), "
                             f"got shape {list(w.shape)}")
        self.sqrt_w = 2.0 * np.sqrt(w)[:, None]  # both directions of the double sum
        self._e0, self._e1 = np.ascontiguousarray(self.edges[:, 0]), np.ascontiguousarray(self.edges[:, 1])
        self.reduction = reduction
        self._scatters: dict = {}  # per dtype, _signed_scatter's matrix

    def forward(self, ctx, x):
        x = _check_attr("x", x, num_rows=self.num_vertices)
        ctx.scale = _scale(self.reduction, 2 * len(self.edges) * x.shape[1])
        # np.take: the rows x[i] of a fancy index, ~5x faster for [E, C] rows (1.9 -> 0.5 ms on spot's 91k edges)
        ctx.diff = np.take(x, self._e0, axis=0) - np.take(x, self._e1, axis=0)
        return np.asarray(np.sum(self.sqrt_w * np.abs(ctx.diff)) * ctx.scale)

    def backward(self, ctx, v_out):
        g = self.sqrt_w * np.sign(ctx.diff) * (float(v_out) * ctx.scale)
        return self._signed_scatter(g)

    def _signed_scatter(self, g: np.ndarray) -> np.ndarray:
        """``RowScatter(concat([e0, e1]))(concat([g, -g]))`` without the ``[2E, C]`` concatenation: a ``[N, E]`` matrix
        of ±1 whose rows hold their entries in that concatenation's order (edges as ``e0`` first, then as ``e1``; built
        as CSR arrays, so scipy keeps the order), so each row sums the same terms in the same order from 0 (× ±1 is
        exact): bit for bit, ~1 ms less a call on spot's mesh."""
        m = self._scatters.get(g.dtype.str)
        if m is None:
            E, n = len(self.edges), self.num_vertices
            pos = np.concatenate([self._e0, self._e1])  # the row of each position of the concatenation
            order = np.argsort(pos, kind="stable")  # by row, then by position (stable)
            indptr = np.concatenate([[0], np.cumsum(np.bincount(pos, minlength=n))]).astype(np.int64)
            data = np.where(order < E, 1.0, -1.0).astype(g.dtype)
            m = self._scatters[g.dtype.str] = sp.csr_matrix((data, (order % E).astype(np.int64), indptr),
                                                            shape=(n, E))
        return np.asarray(m @ g).astype(g.dtype, copy=False)


def material_gtv(x, faces, weights=None, reduction: str = "mean"):
    """Graph total variation of per-vertex materials ``x [N, C]`` over the mesh ``faces [M, 3]``."""
    return MaterialGTV(faces, len(np.asarray(getattr(x, "data", x))), weights, reduction)(x)
