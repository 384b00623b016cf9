"""Refinement of the connected mesh (docs/ARCHITECTURE.md §9): selective subdivision where the gradients are
large, QEM simplification where they are small, with every per-vertex parameter and its Adam
moments carried across through an explicit vertex map.

**Subdivision** (:func:`subdivide_selected`) is *midpoint red-green refinement*, not Loop:

* the selected faces are split 1 → 4 at their edge midpoints ("red"); a face that would get two or
  three split edges is made red too (repeated until stable), and a face with exactly one split edge
  is bisected 1 → 2 ("green"). Every split edge is split on both of its faces, so the result has
  **no T-junctions** (a closed mesh stays closed);
* new vertices sit at the edge midpoints and take the mean of the two endpoints' values.

Why not Loop: ``trimesh.remesh.subdivide_loop`` refines the whole mesh, and Loop's smoothing moves
the old vertices too — applied to a selection it would shrink that region and crease its border;
in the middle of an optimisation it would also change the rendered image under the optimiser.
Midpoint refinement leaves the surface (and the image) exactly as it was and only adds the degrees
of freedom the gradients asked for; the optimiser and the Laplacian regulariser then smooth it.

**Simplification** (:func:`simplify`) is ``fast_simplification`` (quadric error metric) with the
collapse history (``return_collapses=True``) replayed by ``replay_simplification`` to get the map
old vertex → new vertex. A vertex that was never collapsed into another survives; each new vertex
has exactly one surviving old vertex, its *representative*, whose values (and Adam moments) it
takes; its position is the QEM-optimal one. Only the faces outside ``protect_mask`` are
simplified: they are cut out as a sub-mesh, simplified with ``preserve_border=True`` (edges at the
border to the protected faces never collapse, so the border vertices stay where they are) and put
back.

**On a scene** (:func:`subdivide_scene`, :func:`simplify_scene`, :func:`refine_scene`): every
per-vertex parameter (``V``, ``material``, ``alpha``, ``vertex_sh``) is rebuilt through the map and
:meth:`triplet_cl.optim.Adam.remap` carries the moments (kept / representative rows keep theirs,
new midpoint rows start at zero, as in density control).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ops.common import check_faces, check_real
from ..topology import mesh_edges, unique_ints

__all__ = ["RefineReport", "mesh_edges", "refine_scene", "select_by_gradient", "simplify", "simplify_scene",
           "subdivide_scene", "subdivide_selected"]


# ---------------------------------------------------------------------------------------------- helpers


def _check_attrs(attrs, n: int) -> dict:
    out = {}
    for name, a in (attrs or {}).items():
        a = np.asarray(a)
        if a.ndim < 1 or a.shape[0] != n:
            raise ValueError(f"attrs[{name!r}] must have {n} rows (one per vertex), got shape {list(a.shape)}")
        if a.dtype.kind != "f":
            raise ValueError(f"attrs[{name!r}] must be floating point, got dtype {a.dtype}")
        out[name] = a
    return out


def _check_mask(name: str, mask, m: int) -> np.ndarray:
    a = np.asarray(mask)
    if a.shape != (m,) or a.dtype != np.bool_:
        raise ValueError(f"{name} must be a bool array of shape [{m}] (one per face), got {a.dtype} {list(a.shape)}")
    return a


# ---------------------------------------------------------------------------------------------- selection


def select_by_gradient(face_grad, fraction_hi: float = 0.1, fraction_lo: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Faces to subdivide and faces to simplify, by rank of their accumulated gradient.

    Args:
        face_grad: ``[M]`` per-face gradient statistic (e.g. ``DensityStats.mean_grad()``; faces
            never seen have 0).
        fraction_hi: the top fraction to subdivide; fraction_lo: the bottom fraction to simplify
            (both in [0, 1], ``fraction_hi + fraction_lo ≤ 1``).

    Returns:
        ``(hi [M] bool, lo [M] bool)``, disjoint; ties are broken by face index (stable).
    """
    g = np.asarray(face_grad, np.float64)
    if g.ndim != 1:
        raise ValueError(f"face_grad must have shape [M], got {list(g.shape)}")
    if not np.isfinite(g).all():
        raise ValueError("face_grad must be finite")
    for name, f in (("fraction_hi", fraction_hi), ("fraction_lo", fraction_lo)):
        if not 0 <= f <= 1:
            raise ValueError(f"{name} must lie in [0, 1], got {f}")
    if fraction_hi + fraction_lo > 1:
        raise ValueError(f"fraction_hi + fraction_lo must be <= 1, got {fraction_hi} + {fraction_lo}")
    m = len(g)
    order = np.argsort(g, kind="stable")  # ascending
    n_hi, n_lo = int(round(fraction_hi * m)), int(round(fraction_lo * m))
    hi, lo = np.zeros(m, bool), np.zeros(m, bool)
    hi[order[m - n_hi:]] = True
    lo[order[:n_lo]] = True
    return hi, lo


# ---------------------------------------------------------------------------------------------- subdivision


def subdivide_selected(V, F, face_mask, attrs=None):
    """Midpoint red-green refinement of the selected faces (module docstring), crack-free.

    Args:
        V: ``[N, 3]``; F: ``[M, 3]``; face_mask: ``[M] bool`` faces to split 1 → 4.
        attrs: ``name -> [N, ...]`` per-vertex values (raw parameters or activated attributes).

    Returns:
        ``(V' [N', 3], F' [M', 3] int32, attrs' {name: [N', ...]}, index_map [N'] int64, parents [M'] int64)``:
        the first ``N`` vertices are the old ones unchanged (``index_map = arange(N)``), the new
        midpoints follow (``index_map = −1``); ``parents[f]`` is the old face that face ``f`` came
        from. Faces not refined come first in their old order, then the children.
    """
    Va = np.asarray(V)
    V = check_real("V", Va, (None, 3), Va.dtype if Va.dtype.kind == "f" else np.float64)
    n = len(V)
    F = check_faces("F", F, n).astype(np.int64)
    m = len(F)
    sel = _check_mask("face_mask", face_mask, m)
    attrs = _check_attrs(attrs, n)
    E, fe = mesh_edges(F) if m else (np.zeros((0, 2), np.int64), np.zeros((0, 3), np.int64))
    marked = np.zeros(len(E), bool)
    marked[fe[sel].reshape(-1)] = True
    while True:  # closure: a face with two or more split edges is split fully
        k = marked[fe].sum(axis=1)
        grow = (k >= 2) & (k < 3)
        if not grow.any():
            break
        marked[fe[grow].reshape(-1)] = True
    k = marked[fe].sum(axis=1)
    e_new = np.flatnonzero(marked)
    mid_of_edge = np.full(len(E), -1, np.int64)
    mid_of_edge[e_new] = n + np.arange(len(e_new))
    ends = E[e_new]
    V_new = np.concatenate([V, 0.5 * (V[ends[:, 0]] + V[ends[:, 1]]).astype(V.dtype)])
    attrs_new = {name: np.concatenate([a, (0.5 * (a[ends[:, 0]].astype(np.float64) + a[ends[:, 1]])).astype(a.dtype)])
                 for name, a in attrs.items()}

    keep = np.flatnonzero(k == 0)
    red = np.flatnonzero(k == 3)
    green = np.flatnonzero(k == 1)
    a, b, c = F[red, 0], F[red, 1], F[red, 2]
    mab, mbc, mca = (mid_of_edge[fe[red, i]] for i in range(3))
    red_children = np.stack([np.stack([a, mab, mca], 1), np.stack([mab, b, mbc], 1),
                             np.stack([mca, mbc, c], 1), np.stack([mab, mbc, mca], 1)], axis=1).reshape(-1, 3)
    # green: rotate each face so that its split edge runs from corner 0 to corner 1
    j = np.argmax(marked[fe[green]], axis=1)
    rot = (j[:, None] + np.arange(3)[None, :]) % 3
    G = np.take_along_axis(F[green], rot, axis=1)
    mg = mid_of_edge[np.take_along_axis(fe[green], j[:, None], axis=1)[:, 0]]
    green_children = np.stack([np.stack([G[:, 0], mg, G[:, 2]], 1), np.stack([mg, G[:, 1], G[:, 2]], 1)],
                              axis=1).reshape(-1, 3)
    F_new = np.concatenate([F[keep], red_children, green_children]).astype(np.int32)
    parents = np.concatenate([keep, np.repeat(red, 4), np.repeat(green, 2)]).astype(np.int64)
    index_map = np.concatenate([np.arange(n), np.full(len(e_new), -1)]).astype(np.int64)
    return V_new, F_new, attrs_new, index_map, parents


# ---------------------------------------------------------------------------------------------- simplification


def simplify(V, F, target_fraction: float | None = None, target_count: int | None = None, attrs=None,
             protect_mask=None, agg: float = 7.0):
    """QEM simplification (``fast_simplification``) of the faces outside ``protect_mask``.

    Args:
        V: ``[N, 3]``; F: ``[M, 3]``.
        target_fraction: fraction of the simplifiable faces to keep, in (0, 1]; or
        target_count: number of simplifiable faces to keep (give exactly one of the two).
        attrs: ``name -> [N, ...]`` per-vertex values, carried from each new vertex's representative.
        protect_mask: ``[M] bool`` faces to keep untouched (None: simplify the whole mesh); the
            border between both parts is preserved.
        agg: ``fast_simplification`` aggressiveness (0 … 10). Its result is not guaranteed
            manifold: measured on a 68k-face TSDF mesh of spot reduced to 20k, agg 7 gives 4
            pieces (not watertight), agg 3 a watertight mesh; but agg 3 stops far short of the
            target on small uniform meshes (an icosphere of 320 faces stays at 320 for a target
            of 100), so the default stays 7. Twin faces it leaves are dropped.

    Returns:
        ``(V' [N', 3], F' [M', 3] int32, attrs', vertex_map [N'] int64)``; ``vertex_map[j]`` is the old
        vertex whose values new vertex ``j`` carries (its representative; every entry ≥ 0).
        Vertices used by no face are dropped.
    """
    import fast_simplification as fs

    V = check_real("V", V, (None, 3), np.float64)
    n = len(V)
    F = check_faces("F", F, n).astype(np.int64)
    m = len(F)
    if m == 0:
        raise ValueError("cannot simplify a mesh with no faces")
    if (target_fraction is None) == (target_count is None):
        raise ValueError("give exactly one of target_fraction and target_count")
    attrs = _check_attrs(attrs, n)
    prot = np.zeros(m, bool) if protect_mask is None else _check_mask("protect_mask", protect_mask, m)
    region = np.flatnonzero(~prot)
    if target_fraction is not None:
        if not 0 < target_fraction <= 1:
            raise ValueError(f"target_fraction must lie in (0, 1], got {target_fraction}")
        target = int(round(target_fraction * len(region)))
    else:
        if not (isinstance(target_count, int | np.integer) and target_count >= 0):
            raise ValueError(f"target_count must be an integer >= 0, got {target_count!r}")
        target = int(target_count)

    pos_new = V.copy()
    if len(region) and target < len(region):
        Fr = F[region]
        sub_v = unique_ints(Fr)
        sub_of = np.full(n, -1, np.int64)
        sub_of[sub_v] = np.arange(len(sub_v))
        Fs = sub_of[Fr].astype(np.int32)
        pts, _, coll = fs.simplify(V[sub_v], Fs, target_count=max(target, 1), agg=agg, return_collapses=True,
                                   preserve_border=bool(prot.any()))
        _, Fs_new, mapping = fs.replay_simplification(V[sub_v].astype(np.float32), Fs, coll)
        mapping = np.asarray(mapping, np.int64)
        # new sub vertices get provisional ids; survivors (never collapsed) carry their positions
        survivor = np.ones(len(sub_v), bool)
        if len(coll):
            survivor[np.asarray(coll)[:, 1]] = False
        rep_sub = np.full(len(pts), -1, np.int64)
        rep_sub[mapping[survivor]] = np.flatnonzero(survivor)
        if (rep_sub < 0).any():  # should not happen: fast_simplification keeps one survivor per vertex
            raise RuntimeError("fast_simplification: a new vertex has no surviving source vertex")
        region_faces = sub_v[rep_sub[np.asarray(Fs_new, np.int64)]]  # faces in terms of representatives
        pos_new[sub_v[rep_sub]] = pts
        faces_rep = np.concatenate([F[prot], region_faces])
    else:
        faces_rep = F
    # fast_simplification can leave back-to-back twin faces (a fold: non-manifold edges); drop both
    _, inv, cnt = np.unique(np.sort(faces_rep, axis=1), axis=0, return_inverse=True, return_counts=True)
    faces_rep = faces_rep[cnt[inv.reshape(-1)] == 1]
    # compact: every vertex still used by a face (identified by its representative's old index)
    used = unique_ints(faces_rep)
    compact = np.full(n, -1, np.int64)
    compact[used] = np.arange(len(used))
    F_out = compact[faces_rep].astype(np.int32)
    V_out = pos_new[used]
    attrs_out = {name: a[used] for name, a in attrs.items()}
    return V_out, F_out, attrs_out, used.astype(np.int64)


# ---------------------------------------------------------------------------------------------- on a scene


@dataclass
class RefineReport:
    """What one refinement did: vertex and face counts before/after, faces subdivided / simplified."""

    vertices_before: int
    vertices_after: int
    faces_before: int
    faces_after: int
    subdivided: int = 0
    simplified: int = 0
    parents: np.ndarray | None = None  # [faces_after] old face of each new face (subdivision)


def _apply_mesh(scene, optimizer, V_new, F_new, index_map, new_data: dict) -> None:
    """Replace every per-vertex parameter of ``scene`` (``new_data``: ``id(param) -> [N', ...]``) and
    the faces; Adam groups holding them are remapped (``index_map``: old row or −1 per new row)."""
    from ..density import vertex_params
    from ..optim import owning_groups

    vparams = vertex_params(scene)
    done = set()
    for name, params in owning_groups(optimizer, vparams).items():
        optimizer.remap(name, index_map, [new_data[id(p)] for p in params])
        done |= {id(p) for p in params}
    for p in vparams:
        if id(p) not in done:
            p.data = np.ascontiguousarray(np.asarray(new_data[id(p)]).astype(p.data.dtype, copy=False))
            p.grad = None
    scene.F = np.ascontiguousarray(F_new, dtype=np.int32)


def _scene_attrs(scene) -> tuple[dict, dict]:
    """``({name: data}, {name: param})`` of the per-vertex parameters other than ``V``."""
    from ..density import vertex_params

    params = {p.name: p for p in vertex_params(scene) if p is not scene.V}
    return {k: np.asarray(p.data) for k, p in params.items()}, params


def _check_mesh_scene(scene) -> tuple[int, int]:
    n = np.asarray(scene.V.data).shape[0]
    F = check_faces("scene.F", scene.F, n)
    if len(F) == 0:
        raise ValueError("the scene has no faces to refine")
    return n, len(F)


def subdivide_scene(scene, optimizer, face_mask) -> RefineReport:
    """:func:`subdivide_selected` on a scene: positions, raw material/alpha/vertex SH of the new
    midpoints are the means of the edge endpoints; their Adam moments start at zero."""
    n, m = _check_mesh_scene(scene)
    attrs, params = _scene_attrs(scene)
    V2, F2, a2, index_map, parents = subdivide_selected(np.asarray(scene.V.data), scene.F, face_mask, attrs)
    new_data = {id(scene.V): V2, **{id(params[k]): v for k, v in a2.items()}}
    _apply_mesh(scene, optimizer, V2, F2, index_map, new_data)
    return RefineReport(n, len(V2), m, len(F2), subdivided=int(np.count_nonzero(face_mask)), parents=parents)


def simplify_scene(scene, optimizer, face_mask, keep_fraction: float = 0.5, agg: float = 7.0) -> RefineReport:
    """:func:`simplify` the faces of ``face_mask`` to ``keep_fraction`` of their number, the others
    protected; every new vertex carries its representative's raw parameters and Adam moments, and
    takes the QEM position."""
    n, m = _check_mesh_scene(scene)
    mask = _check_mask("face_mask", face_mask, m)
    if not mask.any():
        return RefineReport(n, n, m, m)
    attrs, params = _scene_attrs(scene)
    V2, F2, a2, vmap = simplify(np.asarray(scene.V.data), scene.F, target_fraction=keep_fraction, attrs=attrs,
                                protect_mask=~mask, agg=agg)
    new_data = {id(scene.V): V2.astype(scene.V.data.dtype), **{id(params[k]): v for k, v in a2.items()}}
    _apply_mesh(scene, optimizer, V2, F2, vmap, new_data)
    return RefineReport(n, len(V2), m, len(F2), simplified=int(mask.sum()))


def refine_scene(scene, optimizer, face_grad, fraction_hi: float = 0.1, fraction_lo: float = 0.3,
                 keep_fraction: float = 0.5, agg: float = 7.0) -> RefineReport:
    """One refinement step of the mesh stage: subdivide the ``fraction_hi`` faces of largest
    gradient, then simplify the ``fraction_lo`` faces of smallest gradient to ``keep_fraction`` of
    their number (the refined faces are protected). ``face_grad [M]`` as :func:`select_by_gradient`."""
    n, m = _check_mesh_scene(scene)
    g = np.asarray(face_grad)
    if g.shape != (m,):
        raise ValueError(f"face_grad must have shape [{m}] (one per face), got {list(g.shape)}")
    hi, lo = select_by_gradient(g, fraction_hi, fraction_lo)
    if hi.any():
        r1 = subdivide_scene(scene, optimizer, hi)
        lo = lo[r1.parents]  # the children of a low-gradient face (green neighbours) stay low
    else:
        r1 = RefineReport(n, n, m, m)
    r2 = simplify_scene(scene, optimizer, lo, keep_fraction, agg)
    return RefineReport(n, r2.vertices_after, m, r2.faces_after, subdivided=r1.subdivided, simplified=r2.simplified)
