"""UV atlas (xatlas) and texture baking of per-vertex attributes, on the host in numpy.

Texture coordinates follow glTF: ``(u, v)`` in [0, 1], ``u`` along the image width, ``v`` *down*
the image (row ``i`` covers ``v`` in ``[i/H, (i+1)/H)``); texel ``(i, j)`` has its centre at
``uv = ((j + 0.5)/W, (i + 0.5)/H)``.

Baking: every face is rasterised in texel space (a texel belongs to the face that contains its
centre, barycentric ``w`` of the centre; texels that only overlap a face get its clamped
barycentrics, so that every face, however small, owns a texel: :func:`rasterize_uv`), and each
attribute is ``sum_k w_k a[corner k]`` there. Texels that no face reaches (the gutter) are then filled with
the value of the *nearest* reached texel (``scipy.ndimage.distance_transform_edt``), out to
``dilate`` texels or everywhere: bilinear
filtering and mip-maps near chart borders then average values of the same chart instead of the
background. Given the faces' charts (:attr:`UVAtlas.face_chart`), the gutter is filled **per chart**
(:func:`gutter_sources`): a gutter texel not next to a chart whose mip-map block (2×2 … 32×32, coarsest first) holds
covered texels of one chart only is given to that chart and takes the value of that chart's nearest
texel, so that the block averages one chart's values; the other gutter texels take the nearest chart's
(measured with ``bench/gutter.py``, see ``bench/results/gutter_2026-11-24.txt``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class UVAtlas:
    """A UV atlas of a mesh ``V [N, 3]``, ``F [M, 3]``.

    Attributes:
        vmap: ``[N2] int64`` original vertex of each atlas vertex (vertices are split at seams).
        faces: ``[M, 3] int32`` faces into the atlas vertices (same order as ``F``).
        uv: ``[N2, 2] float32`` texture coordinates in [0, 1] (glTF convention, ``v`` down).
        charts: number of charts; utilization: fraction of the atlas the charts cover.
        face_chart: ``[M] int64`` the chart of each face (:func:`chart_of_faces`), or None.
    """

    vmap: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    charts: int
    utilization: float
    face_chart: np.ndarray | None = None


def chart_of_faces(faces: np.ndarray, pos: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Charts of an atlas: connected components of its faces ``[M, 3]`` (into the atlas vertices) through
    shared corners, a corner being one 3D position ``pos`` at one UV position ``uv`` (xatlas splits
    vertices at seams and joins colocated ones of a chart). Returns ``[M] int64`` labels."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return np.zeros(0, np.int64)
    key = np.column_stack([np.round(np.asarray(pos, np.float64) * 2**20).astype(np.int64),
                           np.round(np.asarray(uv, np.float64) * 2**20).astype(np.int64)])
    _, corner = np.unique(key, axis=0, return_inverse=True)
    f = corner.reshape(-1)[faces]
    rows = np.repeat(np.arange(len(f)), 3)
    g = coo_matrix((np.ones(rows.size), (rows, f.ravel())), shape=(len(f), int(corner.max()) + 1)).tocsr()
    _, lab = connected_components(g @ g.T, directed=False)
    return lab.astype(np.int64)


def gutter_sources(face_img: np.ndarray, face_chart: np.ndarray | None = None, levels: int = 5):
    """For every texel, the covered texel whose value it takes: ``(iy, ix, dist)`` ``[H, W]`` (a covered
    texel takes its own; ``dist``: distance to the nearest covered texel of any chart).

    Without ``face_chart``: the nearest covered texel. With it (module docstring): each gutter texel is
    first given a chart — a texel next to a chart (8-neighbourhood, what bilinear filtering reads) the
    nearest; then for ``L = levels … 1``, a ``2^L × 2^L`` block whose covered texels all belong to one chart
    gives its still unassigned gutter texels to that chart; the rest go to the nearest chart — and then
    takes the value of the nearest covered texel of that chart."""
    from scipy.ndimage import distance_transform_edt

    covered = face_img >= 0
    dist, (iy, ix) = distance_transform_edt(~covered, return_indices=True)
    if face_chart is None or covered.all():
        return iy, ix, dist
    h, w = face_img.shape
    own = np.full((h, w), -1, np.int64)
    own[covered] = np.asarray(face_chart, np.int64)[face_img[covered]]
    assigned = own.copy()
    near = ~covered & (dist < 1.5)  # next to a chart (8-neighbourhood): bilinear filtering reads it, the nearest
    assigned[near] = own[iy[near], ix[near]]  # chart's value keeps a chart's border clean at full resolution
    big = np.iinfo(np.int64).max
    for lv in range(int(levels), 0, -1):
        b = 2**lv
        H, W = -(-h // b) * b, -(-w // b) * b
        o = np.full((H, W), -1, np.int64)
        o[:h, :w] = own
        blk = o.reshape(H // b, b, W // b, b)
        mx = blk.max(axis=(1, 3))
        mn = np.where(blk >= 0, blk, big).min(axis=(1, 3))
        single = np.where((mx >= 0) & (mn == mx), mx, -1)  # [H/b, W/b] the one chart, or -1
        cand = np.repeat(np.repeat(single, b, 0), b, 1)[:h, :w]
        take = (assigned < 0) & (cand >= 0)
        assigned[take] = cand[take]
    rest = assigned < 0
    assigned[rest] = own[iy[rest], ix[rest]]
    # the nearest covered texel of the assigned chart, where it is not the nearest of all
    from scipy.ndimage import find_objects

    wrong = ~covered & (own[iy, ix] != assigned)
    label = np.where(covered, own, np.where(wrong, assigned, -1)) + 1  # the chart's texels and its wrong gutter
    boxes = find_objects(label.astype(np.int32))
    for c in np.unique(assigned[wrong]):
        box = boxes[int(c)]
        tgt = wrong[box] & (assigned[box] == c)
        _, (sy, sx) = distance_transform_edt(own[box] != c, return_indices=True)
        iy[box][tgt] = sy[tgt] + box[0].start
        ix[box][tgt] = sx[tgt] + box[1].start
    return iy, ix, dist


def spatial_pieces(V: np.ndarray, F: np.ndarray, piece_faces: int) -> list[np.ndarray]:
    """Split the faces into pieces of about ``piece_faces`` faces: the cells of a regular grid over
    the face centroids' bounding box (``g^3`` cells, ``g = ceil((M / piece_faces)^(1/3))``).
    Returns the face indices of each non-empty cell."""
    M = len(F)
    g = max(1, int(np.ceil((M / max(int(piece_faces), 1)) ** (1 / 3))))
    if g == 1:
        return [np.arange(M)]
    c = np.asarray(V, np.float64)[np.asarray(F)].mean(1)
    lo, hi = c.min(0), c.max(0)
    cell = np.minimum(((c - lo) / np.maximum(hi - lo, 1e-30) * g).astype(np.int64), g - 1)
    key = (cell[:, 0] * g + cell[:, 1]) * g + cell[:, 2]
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    return np.split(order, bounds)


def uv_atlas(V: np.ndarray, F: np.ndarray, texture_size: int = 1024, padding: int = 2,
             piece_faces: int | None = 3000) -> UVAtlas:
    """Charts and packs a UV atlas with ``xatlas`` for a ``texture_size`` square texture.

    xatlas' chart computation grows faster than linearly with the faces of one mesh (measured on a
    124k-face marching-cubes mesh: 83 s as one mesh, 16 s as 50 pieces, on 2 busy cores), so the
    mesh is first cut into spatial pieces of about ``piece_faces`` faces (:func:`spatial_pieces`),
    charted independently (in parallel by xatlas) and packed into one atlas. The cuts add chart
    borders (about +9 % charts there); ``piece_faces=None`` charts the mesh whole.

    Args:
        V: ``[N, 3]`` positions. F: ``[M, 3]`` faces (M > 0).
        texture_size: the texture's width = height in texels (sets xatlas' texel density).
        padding: texels between charts. piece_faces: see above.
    Returns:
        :class:`UVAtlas` with one atlas page (the texel density is lowered until the charts fit one);
        ``faces`` in the order of ``F``.
    """
    import xatlas

    V = np.ascontiguousarray(V, np.float32)
    F = np.ascontiguousarray(F, np.uint32)
    if len(F) == 0:
        raise ValueError("uv_atlas: the mesh has no faces")
    pieces = [np.arange(len(F))] if piece_faces is None else spatial_pieces(V, F, piece_faces)
    # xatlas' tolerances are absolute: a mesh a thousandth the dev scenes' size (a capture in other units) came back
    # with no atlas at all. Far from unit size, the positions it sees are scaled by a power of two (exact) to a
    # bounding-box diagonal in [1, 2); the charts and UVs do not depend on the scale.
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) if len(V) else 1.0
    Vx = V
    if np.isfinite(diag) and diag > 0 and not 1 / 16 <= diag <= 16:
        Vx = np.ascontiguousarray(V * np.float32(2.0 ** -np.floor(np.log2(diag))), np.float32)
    local = []
    for idx in pieces:
        used, inv = np.unique(F[idx], return_inverse=True)
        local.append((idx, used, np.ascontiguousarray(inv.reshape(-1, 3), np.uint32)))
    texels_per_unit = 0.0
    for _ in range(8):
        atlas = xatlas.Atlas()
        for _, used, f in local:
            atlas.add_mesh(Vx[used], f)
        pack = xatlas.PackOptions()
        pack.resolution = int(texture_size)
        pack.padding = int(padding)
        pack.bilinear = True
        pack.texels_per_unit = float(texels_per_unit)
        atlas.generate(xatlas.ChartOptions(), pack)
        if atlas.atlas_count <= 1:
            break
        # more than one page: lower the density so that everything fits one texture
        texels_per_unit = float(atlas.texels_per_unit) * 0.9 / np.sqrt(atlas.atlas_count)
    else:
        raise RuntimeError(f"xatlas could not pack the charts into one {texture_size}² atlas")
    vmaps, uvs, faces, offset = [], [], np.empty((len(F), 3), np.int32), 0
    for i, (idx, used, _) in enumerate(local):
        vm, fi, uv = atlas[i]
        vmaps.append(used[vm])
        uvs.append(uv)
        faces[idx] = fi.astype(np.int64) + offset
        offset += len(vm)
    util = atlas.utilization
    vmap = np.concatenate(vmaps).astype(np.int64)
    uv = np.clip(np.concatenate(uvs), 0, 1).astype(np.float32)
    return UVAtlas(vmap, faces, uv, int(atlas.chart_count), float(np.ravel(util)[0]) if np.ndim(util) else float(util),
                   chart_of_faces(faces, V[vmap], uv))


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, width: int, height: int,
                 max_candidates: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise triangles in texture space: the face of each texel and its barycentrics.

    Two layers, the first winning: (1) the face containing the texel's **centre** (barycentrics
    of the centre, exact); (2) *conservative* coverage: a face whose triangle, grown by half a
    texel, contains the centre (the texel square overlaps the edge slabs), with the centre's
    barycentrics clamped to the triangle (negative weights set to 0, renormalised). Layer (2) gives
    every face at least one texel, however small or thin, and the texels along chart borders the
    values of their own chart rather than the nearest-texel fill of :func:`bake`.

    Args:
        uv: ``[N, 2]`` texture coordinates in [0, 1] (glTF convention). faces: ``[M, 3]`` into ``uv``.
        width, height: texture size. max_candidates: texels tested per chunk (memory bound).
    Returns:
        ``face [H, W] int32`` (-1 where no face reaches the texel) and ``bary [H, W, 3] float32``.
        Within a layer, where faces overlap (shared edges in an atlas) the later face wins.
    """
    uv = np.asarray(uv, np.float64)
    faces = np.asarray(faces, np.int64)
    face_img = np.full((2, height, width), -1, np.int32)  # layer 0: centre inside; 1: conservative
    bary_img = np.zeros((2, height, width, 3), np.float32)
    p = uv[faces] * np.array([width, height])  # [M, 3, 2] texel units; centres at j + 0.5
    a, e1, e2 = p[:, 0], p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    # half-texel support of the edge opposite each vertex, in barycentric units times |det|:
    # the centre is within the grown triangle iff w_i |det| >= -(|dx_i| + |dy_i|) / 2 for all i
    opp = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], 1)  # [M, 3, 2]
    slack = 0.5 * np.abs(opp).sum(-1) / np.maximum(np.abs(det), 1e-300)[:, None]  # [M, 3]
    lo = np.maximum(np.floor(p.min(1)).astype(np.int64), 0)  # texels whose square meets the bbox
    hi = np.minimum(np.ceil(p.max(1)).astype(np.int64) - 1, [width - 1, height - 1])
    n = np.maximum(hi - lo + 1, 0)
    count = n[:, 0] * n[:, 1]
    ok = (np.abs(det) > 1e-12) & (count > 0)
    ids = np.flatnonzero(ok)
    if len(ids) == 0:
        return face_img[0], bary_img[0]
    csum = np.cumsum(count[ids])
    start = 0
    eps = 1e-7
    while start < len(ids):
        base = csum[start - 1] if start else 0
        stop = max(int(np.searchsorted(csum, base + max_candidates, side="right")), start + 1)
        fid = np.repeat(ids[start:stop], count[ids[start:stop]])
        first = np.repeat(csum[start:stop] - count[ids[start:stop]] - base, count[ids[start:stop]])
        k = np.arange(len(fid)) - first
        nx = n[fid, 0]
        jx = lo[fid, 0] + k % nx
        jy = lo[fid, 1] + k // nx
        q = np.stack([jx + 0.5, jy + 0.5], -1) - a[fid]
        w1 = (q[:, 0] * e2[fid, 1] - q[:, 1] * e2[fid, 0]) / det[fid]
        w2 = (e1[fid, 0] * q[:, 1] - e1[fid, 1] * q[:, 0]) / det[fid]
        w = np.stack([1.0 - w1 - w2, w1, w2], -1)
        inside = (w >= -eps).all(1)
        grown = (w >= -slack[fid]).all(1) & ~inside
        wc = np.maximum(w[grown], 0)
        for layer, m, ww in ((1, grown, wc / wc.sum(1, keepdims=True)), (0, inside, w[inside])):
            face_img[layer, jy[m], jx[m]] = fid[m]
            bary_img[layer, jy[m], jx[m]] = ww
        start = stop
    use = face_img[0] >= 0
    return np.where(use, face_img[0], face_img[1]), np.where(use[..., None], bary_img[0], bary_img[1])


def bake(face_img: np.ndarray, bary_img: np.ndarray, faces: np.ndarray, values: np.ndarray,
         dilate: int | None = None, fill=None, face_chart: np.ndarray | None = None) -> np.ndarray:
    """Bake per-vertex ``values`` into a texture from a UV rasterisation (:func:`rasterize_uv`).

    Args:
        face_img: ``[H, W]`` face per texel (-1: empty). bary_img: ``[H, W, 3]`` barycentrics.
        faces: ``[M, 3]`` faces into the rows of ``values``. values: ``[N, C]`` per-vertex values.
        dilate: fill empty texels within this many texels of a covered one with the nearest covered
            value; ``None`` fills every empty texel that way (best for mip-maps).
        fill: ``[C]`` value of the texels left empty (default: the mean of the covered texels).
        face_chart: ``[M]`` chart of each face (:attr:`UVAtlas.face_chart`): fill the gutter per chart
            (:func:`gutter_sources`); None: from the nearest covered texel.
    Returns:
        ``[H, W, C] float32``.
    """
    values = np.asarray(values, np.float32)
    values = values.reshape(len(values), -1)
    h, w = face_img.shape
    out = np.zeros((h, w, values.shape[1]), np.float32)
    covered = face_img >= 0
    if not covered.any():
        out[:] = 0 if fill is None else np.asarray(fill, np.float32)
        return out
    f = np.asarray(faces)[face_img[covered]]  # [T, 3]
    out[covered] = np.einsum("tk,tkc->tc", bary_img[covered], values[f])
    if covered.all():
        return out
    iy, ix, dist = gutter_sources(face_img, face_chart)
    grow = ~covered if dilate is None else (~covered) & (dist <= float(dilate))
    out[grow] = out[iy[grow], ix[grow]]
    rest = ~covered & ~grow
    if rest.any():
        out[rest] = out[covered].mean(0) if fill is None else np.asarray(fill, np.float32)
    return out


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[N, 3] float32`` (sum of the adjacent faces' cross products,
    normalised; a vertex with no face or a zero sum gets ``(0, 1, 0)``, so every normal is unit)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # 2 * area * unit normal
    n = np.zeros_like(V)
    for c in range(3):
        n[:, c] = np.bincount(F.ravel(), weights=np.repeat(fn[:, c], 3), minlength=len(V))
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    good = ln[:, 0] > 1e-20
    n[good] /= ln[good]
    n[~good] = (0.0, 1.0, 0.0)
    return n.astype(np.float32)
