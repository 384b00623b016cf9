"""The lights read from the extracted mesh's shading (issue 18): how many point lights, from where, how bright.

Why: the soup learns its lights by gradient steps from one initial guess, with a per-vertex albedo that can paint
in whatever the lights miss. On a capture lit by two point lights it kept one light overhead and an ambient 8× the
truth, and the second light's shading went into the albedo (albedo 14 dB). Once the mesh is extracted, its normals
are clean and a global fit is cheap, so the lights are fitted again from scratch:

1. **What each vertex shows** (:func:`vertex_radiance`): the median of the linear photo values at the vertex over
   the training views that see it (facing the camera, not occluded: the shadow-ray visibility towards the camera
   centre, inside the photo's alpha). The median drops the views where a highlight sits on it.
2. **Light atoms**: ``atoms`` point lights spread evenly over a sphere around the object
   (:func:`~triplet_cl.visibility.sphere_directions`, ``distance`` extents from the centre), each with its cast
   shadows (:func:`~triplet_cl.visibility.vertex_visibility`), and one constant ambient term. Vertex ``v``'s
   irradiance is linear in the atoms' non-negative weights ``w``:
   ``E_v = sum_k w_k B_vk``, ``B_vk = vis_vk max(0, n_v · l_vk) d² / r_vk²``, ``B_v,ambient = 1``.
3. **The fit** (:func:`fit_weights`): the albedo that a lighting implies is ``radiance / irradiance``; a surface's
   albedo is piecewise constant and its shading is not, so the weights minimise the total variation of the implied
   log albedo over the mesh's edges, ``sum_(u,v) rho(log(c_u / E_u) - log(c_v / E_v))`` (``rho`` the Charbonnier
   ``sqrt(x² + eps²)``, luminance), by L-BFGS-B with ``w >= 0``. Scale-free: only the weights' ratios matter.
4. **Lights from atoms** (:func:`cluster_atoms`): the strongest atom and its neighbours within ``cluster_angle``
   become one point light (their weighted mean direction), repeated while a cluster holds ``min_share`` of the
   direct weight, at most ``max_lights``; the lights' relative weights are fitted again by (3) with their own
   shadows. What is spread out (an environment, a sky) ends in the ambient term.
5. **Ambient, scale and distance** (:func:`robust_log_fit`): the TV always wants more ambient (more ambient flattens
   every shading error the normals and the photos' interreflection leave), so the ambient's share and the overall
   scale come from a robust one-albedo fit, at the distance (the same for every light) where that fit is best.

Measured on the 96² re-renders of spot_small (``bench/results/light_fit_pocl_2026-11-26.txt``): two point lights
found 0.3-0.4 units from the truth's positions (directions 0.7° and 2.0° off), one light on spot_small, the sun's
direction on the sun-and-sky capture.

A metal shows no diffuse shading to read (the fit above put 73 % of the weight in the ambient term), but its
highlights move with the view: :func:`fit_metal_lights` reads the lights from every view of a sample of vertices
(:func:`vertex_observations`), each divided by the specular lobe of candidate lights (:func:`specular_atom_matrix`),
which must give each vertex one F0 (:func:`view_consistency`). :class:`~triplet_cl.mesh.refine.MeshStage` uses it
when its metallic trial chose a metal.

This is a diagnostic-free product path: nothing here reads ``ground_truth.json``.
"""

from __future__ import annotations

import time

import numpy as np

from ..visibility import sphere_directions

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _bilinear(img: np.ndarray, xi, yi, fx, fy) -> np.ndarray:
    """``img [H, W, C]`` at the points with integer corners ``(xi, yi)`` and fractions ``fx, fy [n, 1]``."""
    return (img[yi, xi] * (1 - fx) * (1 - fy) + img[yi, xi + 1] * fx * (1 - fy)
            + img[yi + 1, xi] * (1 - fx) * fy + img[yi + 1, xi + 1] * fx * fy)


def vertex_observations(V: np.ndarray, normals: np.ndarray, views, seen: np.ndarray, min_cos: float = 0.3,
                        min_alpha: float = 0.9) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every view's photo value at every vertex that view sees: facing it (``n · to camera > min_cos``: grazing
    views sample the outline), not occluded (``seen``), inside the image and the photo's alpha (outline pixels mix
    in the background).

    Args:
        V, normals: ``[N, 3]`` positions and unit vertex normals.
        views: ``[(camera, rgb, alpha)]``, ``rgb`` ``[H, W, 3]`` linear radiance, ``alpha`` ``[H, W]`` or None.
        seen: ``[N, len(views)]`` visibility of each vertex from each camera centre (1: unoccluded).

    Returns:
        ``(vertex [M], view [M], radiance [M, 3], to_camera [M, 3])``, view by view, each view's in vertex order.
    """
    V = np.asarray(V, np.float64)
    out = ([], [], [], [])
    for j, (cam, rgb, alpha) in enumerate(views):
        h, w = rgb.shape[:2]
        rgb = np.asarray(rgb, np.float32).reshape(h, w, -1)
        uv = cam.project_points(V)
        x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # pixel centres at +0.5
        to_cam = np.asarray(cam.center, np.float64) - V
        to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
        ok = ((seen[:, j] > 0.5) & (uv[:, 2] > 0) & (x >= 0) & (y >= 0) & (x < w - 1) & (y < h - 1)
              & ((normals * to_cam).sum(1) > min_cos))
        idx = np.flatnonzero(ok)
        xi, yi = np.floor(x[idx]).astype(np.int64), np.floor(y[idx]).astype(np.int64)
        fx, fy = (x[idx] - xi)[:, None], (y[idx] - yi)[:, None]
        val = _bilinear(rgb, xi, yi, fx, fy)
        if alpha is not None:
            cover = _bilinear(np.asarray(alpha, np.float32).reshape(h, w, 1), xi, yi, fx, fy)[:, 0]
            keep = cover >= min_alpha
            idx, val = idx[keep], val[keep]
        for lst, a in zip(out, (idx, np.full(len(idx), j), val, to_cam[idx]), strict=True):
            lst.append(a)
    if not out[0]:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    return tuple(np.concatenate(a) for a in out)


def vertex_radiance(V: np.ndarray, normals: np.ndarray, views, seen: np.ndarray, min_cos: float = 0.3,
                    min_alpha: float = 0.9, chunk: int = 16384) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex median of the photos' linear radiance over the views that see the vertex
    (:func:`vertex_observations`; the median drops the views where a highlight sits on it).

    Args:
        V, normals, views, seen, min_cos, min_alpha: as :func:`vertex_observations`.
        chunk: vertices per pass (the samples of a pass, ``chunk × views × 3`` floats, are held at once).

    Returns:
        ``(c [N, 3], count [N])``: the median (NaN where no view sees the vertex) and the number of views used.
    """
    V = np.asarray(V, np.float64)
    c = np.full((len(V), 3), np.nan)
    count = np.zeros(len(V), np.int64)
    for lo in range(0, len(V), chunk):
        n = len(V[lo:lo + chunk])
        vi, vj, val, _ = vertex_observations(V[lo:lo + chunk], normals[lo:lo + chunk], views, seen[lo:lo + chunk],
                                             min_cos, min_alpha)
        obs = np.full((n, len(views), 3), np.nan, np.float32)
        obs[vi, vj] = val
        k = np.isfinite(obs[..., 0]).sum(axis=1)
        has = np.flatnonzero(k > 0)
        count[lo:lo + chunk] = k
        c[lo + has] = np.nanmedian(obs[has], axis=1)
    return c, count


def atom_matrix(V: np.ndarray, normals: np.ndarray, positions: np.ndarray, vis: np.ndarray,
                distance: float) -> np.ndarray:
    """``[N, K]`` irradiance at each vertex of a point light of intensity ``distance²`` at each of ``positions``
    (so about 1 at the object's centre): ``vis max(0, n · l) distance² / r²``."""
    L = positions[None, :, :] - V[:, None, :]
    r2 = np.maximum((L * L).sum(axis=2), 1e-12)
    cos = (normals[:, None, :] * L).sum(axis=2) / np.sqrt(r2)
    return vis * np.maximum(cos, 0.0) * (distance * distance) / r2


def observed_edges(F: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``[E, 2]`` unique undirected edges of the faces ``F`` (:func:`~triplet_cl.regularizers.mesh_edges`) whose two
    vertices are both in ``keep``."""
    from ..regularizers import mesh_edges

    E = mesh_edges(F)
    return E[keep[E[:, 0]] & keep[E[:, 1]]]


def implied_albedo_tv(w: np.ndarray, B: np.ndarray, log_c: np.ndarray, edges: np.ndarray,
                      eps: float = 0.02) -> tuple[float, np.ndarray]:
    """The Charbonnier total variation of ``log_c - log(B w)`` over ``edges`` (mean per edge) and its gradient in
    ``w``."""
    e = B @ w + 1e-9
    la = log_c - np.log(e)
    d = la[edges[:, 0]] - la[edges[:, 1]]
    s = np.sqrt(d * d + eps * eps)
    g = d / s
    g_la = np.bincount(edges[:, 0], g, minlength=len(e)) - np.bincount(edges[:, 1], g, minlength=len(e))
    n = max(len(edges), 1)
    return float(s.sum() / n), (B.T @ (-g_la / e)) / n


def fit_weights(B: np.ndarray, log_c: np.ndarray, edges: np.ndarray, w0: np.ndarray | None = None,
                max_iter: int = 500) -> tuple[np.ndarray, float]:
    """Non-negative weights of the columns of ``B`` that minimise :func:`implied_albedo_tv`, normalised to sum 1;
    returns ``(w, tv)``."""
    from scipy.optimize import minimize

    k = B.shape[1]
    w0 = np.full(k, 1.0 / k) if w0 is None else np.maximum(np.asarray(w0, np.float64), 1e-6)
    res = minimize(implied_albedo_tv, w0, args=(B, log_c, edges), jac=True, method="L-BFGS-B",
                   bounds=[(0.0, None)] * k, options={"maxiter": max_iter})
    w = np.maximum(res.x, 0.0)
    w = w / max(w.sum(), 1e-300)
    return w, implied_albedo_tv(w, B, log_c, edges)[0]


def cluster_atoms(dirs: np.ndarray, w: np.ndarray, angle_deg: float = 40.0, min_share: float = 0.15,
                  max_lights: int = 3) -> list[tuple[np.ndarray, float]]:
    """Greedy clusters of the weighted directions: the atoms within ``angle_deg`` of the heaviest atom left (moved
    to their weighted mean direction, three times), while a cluster holds at least ``min_share`` of the total
    weight (the first one always), at most ``max_lights``. Returns ``[(unit direction, weight)]``."""
    left = np.asarray(w, np.float64).copy()
    total = max(left.sum(), 1e-300)
    cos_min = np.cos(np.radians(angle_deg))
    out = []
    while len(out) < max_lights and left.max() > 0:
        d = dirs[int(np.argmax(left))]
        for _ in range(3):  # mean shift: the seed atom may sit on the cluster's rim
            near = (dirs @ d >= cos_min) & (left > 0)
            m = (left[near, None] * dirs[near]).sum(axis=0)
            d = m / max(np.linalg.norm(m), 1e-12)
        near = (dirs @ d >= cos_min) & (left > 0)
        weight = float(left[near].sum())
        if out and weight < min_share * total:
            break
        out.append((d, weight))
        left[near] = 0.0
    return out


def _clustered(dirs, w_atoms, cluster_angle, min_share, max_lights, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The point lights' directions ``[L, 3]`` from the atoms' weights (the ambient's last) by :func:`cluster_atoms`,
    and their weights followed by the ambient's, to start their own fit; ValueError when no atom has weight."""
    clusters = cluster_atoms(dirs, w_atoms[:-1], cluster_angle, min_share, max_lights)
    if not clusters:
        raise ValueError(f"{what} no direction to place a point light in (every atom's weight is 0)")
    return np.array([d for d, _ in clusters]), np.array([wt for _, wt in clusters] + [w_atoms[-1]])


def robust_log_fit(B: np.ndarray, log_c: np.ndarray, w0: np.ndarray, eps: float = 0.05,
                   max_iter: int = 500) -> tuple[np.ndarray, float]:
    """Non-negative weights ``w`` of the columns of ``B`` that minimise the mean Charbonnier distance between
    ``log_c`` and ``log(B w)``: the lighting under which one albedo (``w``'s scale) explains the most vertices,
    the rest (texture, highlights) costing each about its absolute log error. Returns ``(w, objective)``."""
    from scipy.optimize import minimize

    def f(w):
        e = B @ w + 1e-9
        r = log_c - np.log(e)
        s = np.sqrt(r * r + eps * eps)
        return float(s.mean()), (B.T @ (-(r / s) / e)) / len(r)

    res = minimize(f, np.maximum(np.asarray(w0, np.float64), 1e-9), jac=True, method="L-BFGS-B",
                   bounds=[(0.0, None)] * B.shape[1], options={"maxiter": max_iter})
    w = np.maximum(res.x, 0.0)
    return w, f(w)[0]


def fit_lights(V, F, normals, c, count, visibility, *, center, extent: float, distance: float = 3.0,
               distances=(2.0, 3.0, 4.5, 7.0), atoms: int = 128, min_views: int = 2, max_lights: int = 3,
               cluster_angle: float = 40.0, min_share: float = 0.15, current=None) -> dict:
    """Point lights and an ambient term fitted to the mesh's shading.

    Two criteria, each for what it measures without bias (spot_small's mesh, bench/results/light_fit_pocl_2026-
    11-26.txt): the implied albedo's total variation finds the lights' directions and number (step 3 of the
    module), but its minimum sits at 2.5× the true ambient (more ambient flattens every shading error the mesh's
    normals and the photos' interreflection leave); the robust one-albedo fit (:func:`robust_log_fit`) puts the
    ambient at the truth's share (0.17 for 0.16 on spot_small, 0.09 for 0.07 with two lights), and picks a
    distance the TV put 1.3-1.6× too far. So: atoms ``distance`` extents away → TV weights → clusters
    (directions) → for each of ``distances`` (extents from the centre, the same for every light) the TV's relative
    weights of the lights, then the robust fit of their scale and the ambient's → the distance whose robust fit is
    best.

    Args:
        V, F, normals: the mesh; c, count: :func:`vertex_radiance`'s output.
        visibility: ``visibility(positions [K, 3], rows) -> [len(rows), K]``, the transmittance of the vertices
            ``rows`` towards point lights at ``positions`` (the mesh's cast shadows); asked only for the observed
            vertices (only their rows enter the fit: the rays of the others were a third of the stage's light fit).
        center, extent: the object's centre and radius.
        current: ``(positions [P, 3], intensities [P], ambient irradiance)`` of the lights before (luminance, in
            the renderer's units): their robust fit, only their overall scale free, is reported as
            ``objective_current`` (None for lights that light no observed vertex).

    Returns:
        ``{"positions" [L, 3], "intensities" [L], "ambient" (irradiance), "irradiance" [N] (NaN where
        unobserved), "observed" [N], "objective", "objective_current", "distance" (extents), "tv", "weights"
        (per light, then the ambient), "vertices", "seconds"}``; lights and irradiance share one
        arbitrary scale (the photos fix only albedo × light).
    """
    t = time.perf_counter()
    V = np.asarray(V, np.float64)
    center = np.asarray(center, np.float64)
    good = (count >= min_views) & np.isfinite(c).all(axis=1)
    lum = np.where(good, np.nan_to_num(c) @ LUMA, 1.0)
    good &= lum > 1e-4
    if good.sum() < 16:
        raise ValueError(f"too few vertices seen by {min_views}+ views to fit lights ({int(good.sum())})")
    log_c = np.log(np.maximum(lum, 1e-4))
    edges = observed_edges(F, good)
    if len(edges) == 0:
        raise ValueError("no mesh edge between observed vertices to fit lights")
    sub = np.flatnonzero(good)
    remap = np.full(len(V), -1)
    remap[sub] = np.arange(len(sub))
    e_sub, lc = remap[edges], log_c[sub]
    V_sub, n_sub = V[sub], np.asarray(normals, np.float64)[sub]

    def design(P, d):  # [S, L + 1] over the observed vertices: the point lights at P (about 1 at the centre), ambient
        return np.concatenate([atom_matrix(V_sub, n_sub, P, visibility(P, sub), d), np.ones((len(sub), 1))], axis=1)

    dirs = sphere_directions(atoms)
    B = design(center + distance * extent * dirs, distance * extent)
    w_atoms, tv = fit_weights(B, lc, e_sub)
    L, w_tv = _clustered(dirs, w_atoms, cluster_angle, min_share, max_lights, "the shading shows")
    best = None
    for k in distances:
        BL = design(center + k * extent * L, k * extent)
        w, tv_k = fit_weights(BL, lc, e_sub, w0=w_tv)  # the lights' relative weights by the TV
        # the ambient's share by the robust one-albedo fit: two unknowns, the direct light's scale and the ambient
        direct = BL[:, :-1] @ w[:-1]
        B2 = np.stack([direct, np.ones(len(sub))], axis=1)
        w0 = np.array([1.0, w[-1]])
        w2, obj_k = robust_log_fit(B2, lc, w0 * np.exp(np.median(lc - np.log(B2 @ w0))))
        if best is None or obj_k < best[0]:  # the distance by the robust fit too (the TV's chose 1.3-1.6x too far)
            best = (obj_k, k, np.append(w[:-1] * w2[0], w2[1]), BL, tv_k)
    obj, k, w, BL, tv = best
    E = np.full(len(V), np.nan)
    E[sub] = BL @ w
    obj_current = None
    if current is not None:
        cp, ci, ca = current
        cp = np.asarray(cp, np.float64).reshape(-1, 3)
        Bc = atom_matrix(V_sub, n_sub, cp, visibility(cp, sub), 1.0) @ np.asarray(ci, np.float64) + float(ca)
        if np.any(Bc > 0):  # else they light no observed vertex and explain nothing (None)
            _, obj_current = robust_log_fit(Bc[:, None], lc, np.exp([np.median(lc - np.log(Bc + 1e-9))]))
    return {"positions": center + k * extent * L, "intensities": w[:-1] * (k * extent) ** 2, "ambient": float(w[-1]),
            "irradiance": E, "observed": good, "objective": obj,
            "objective_current": obj_current, "distance": k, "tv": tv, "weights": w.tolist(),
            "vertices": int(good.sum()), "seconds": time.perf_counter() - t}


def lobe_geometry(P: np.ndarray, normals: np.ndarray, to_cam: np.ndarray, positions: np.ndarray, vis: np.ndarray,
                  distance: float, f0: np.ndarray | None = None,
                  chunk: int = 2048) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`specular_atom_matrix` needs of each observation ``P`` (seen along ``to_cam``) and each point light
    at ``positions`` whatever the roughness: ``(n·l, n·v, n·h, vis d² / r² F / F0)``, each ``[M, K]`` (``n·v``
    ``[M, 1]``), ``chunk`` observations at a time (the ``[chunk, K, 3]`` temporaries). ``F / F0`` is Schlick's
    Fresnel over F0, ``1 + (1 / f0 - 1) (1 - h·v)^5``, with each observation's estimate ``f0 [M]`` (1 without)."""
    m, k = len(P), len(positions)
    nl, nh, fall = np.empty((m, k)), np.empty((m, k)), np.empty((m, k))
    nv = np.maximum((normals * to_cam).sum(axis=1), 0.0)[:, None]
    for lo in range(0, m, chunk):
        sl = slice(lo, lo + chunk)
        n, v = normals[sl], to_cam[sl]
        L = positions[None, :, :] - P[sl, None, :]
        r2 = np.maximum((L * L).sum(axis=2), 1e-12)
        L /= np.sqrt(r2)[..., None]
        nl[sl] = np.maximum((n[:, None, :] * L).sum(axis=2), 0.0)
        H = L + v[:, None, :]
        H /= np.maximum(np.linalg.norm(H, axis=2, keepdims=True), 1e-12)
        nh[sl] = np.clip((n[:, None, :] * H).sum(axis=2), 0.0, 1.0)
        fall[sl] = vis[sl] * (distance * distance) / r2
        if f0 is not None:  # the brighter reflection at grazing angles, which F = F0 would leave to the ambient term
            hv = np.clip((H * v[:, None, :]).sum(axis=2), 0.0, 1.0)
            fall[sl] *= 1.0 + (1.0 / f0[sl, None] - 1.0) * (1.0 - hv) ** 5
    return nl, nv, nh, fall


def specular_atom_matrix(P: np.ndarray, normals: np.ndarray, to_cam: np.ndarray, positions: np.ndarray,
                         vis: np.ndarray, roughness: float, distance: float, geometry=None,
                         f0: np.ndarray | None = None) -> np.ndarray:
    """``[M, K]`` radiance over F0 of a metal seen along ``to_cam`` at each observation ``P``, lit by a point light
    of intensity ``distance²`` at each of ``positions``: the Cook-Torrance specular lobe of ``shade.cl`` (GGX,
    Smith's exact masking, ``a = roughness²``) over F0, ``vis D (F / F0) G / (4 nv nl) nl d² / r²`` (``F / F0`` with the
    estimate ``f0 [M]``, 1 without: :func:`lobe_geometry`). ``geometry``: :func:`lobe_geometry` of the same
    arguments, computed once for several roughnesses."""
    nl, nv, nh, fall = (lobe_geometry(P, normals, to_cam, positions, vis, distance, f0) if geometry is None
                        else geometry)
    a2 = roughness ** 4
    D = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2 + 1e-6)
    # Smith's exact masking: G / (4 nv nl) = 1 / ((nv + sqrt(a2 + (1 - a2) nv²)) (nl + sqrt(a2 + (1 - a2) nl²)))
    qv = nv + np.sqrt(a2 + (1.0 - a2) * nv * nv + 1e-12)
    ql = nl + np.sqrt(a2 + (1.0 - a2) * nl * nl + 1e-12)
    return fall * D / (qv * ql + 1e-6) * nl


def view_consistency(w: np.ndarray, B: np.ndarray, log_c: np.ndarray, group: np.ndarray, n_groups: int,
                     eps: float = 0.05) -> tuple[float, np.ndarray]:
    """The mean Charbonnier spread of the implied log F0, ``log_c - log(B w)``, around each vertex's own mean over
    the views that see it (``group`` [M]: the vertex of each observation), and its gradient in ``w``. Scale-free:
    each vertex's F0 is free, only how the lighting changes from view to view is judged."""
    e = B @ w + 1e-9
    r = log_c - np.log(e)
    size = np.maximum(np.bincount(group, minlength=n_groups), 1)
    d = r - (np.bincount(group, r, n_groups) / size)[group]
    s = np.sqrt(d * d + eps * eps)
    g = d / s
    g = g - (np.bincount(group, g, n_groups) / size)[group]  # through each vertex's mean
    return float(s.mean()), (B.T @ (-g / e)) / len(r)


def _fit_consistency(B, log_c, group, n_groups, w0=None, max_iter: int = 500):
    from scipy.optimize import minimize

    k = B.shape[1]
    w0 = np.full(k, 1.0 / k) if w0 is None else np.maximum(np.asarray(w0, np.float64), 1e-9)
    res = minimize(view_consistency, w0, args=(B, log_c, group, n_groups), jac=True, method="L-BFGS-B",
                   bounds=[(0.0, None)] * k, options={"maxiter": max_iter})
    w = np.maximum(res.x, 0.0)
    w = w / max(w.sum(), 1e-300)
    return w, view_consistency(w, B, log_c, group, n_groups)[0]


def fit_metal_lights(V, normals, observations, visibility, *, center, extent: float, distance: float = 3.0,
                     distances=(2.0, 3.0, 4.5, 7.0), roughness=(0.2, 0.35, 0.5, 0.7), atoms: int = 512,
                     min_views: int = 3, max_lights: int = 3, cluster_angle: float = 40.0, min_share: float = 0.15,
                     max_observations: int = 20000, max_iter: int = 150, f0: np.ndarray | None = None,
                     current=None) -> dict:
    """Point lights and an ambient term fitted to a metal's highlights.

    A metal shows no diffuse shading (:func:`fit_lights` reads nothing from it), but its highlights move with the
    view: a vertex's photo values over the views that see it, divided by the specular lobe of the right lights,
    give the same F0 in every view. So the atoms (:func:`specular_atom_matrix`, ``atoms`` directions ``distance``
    extents away, and an ambient column of ``F0 La``) are weighted by :func:`view_consistency` at each roughness of
    ``roughness`` (the best one kept), clustered into point lights (:func:`cluster_atoms`), and those lights' weights
    fitted again at each of ``distances`` (the best kept).

    Args:
        V, normals: ``[N, 3]`` the vertices observed (a sample of the mesh's).
        observations: :func:`vertex_observations` of those vertices.
        visibility: ``visibility(positions [K, 3]) -> [N, K]``, the vertices' transmittance towards point lights.
        center, extent: the object's centre and radius.
        current: ``(positions [P, 3], intensities [P], ambient radiance AO × La)`` of the lights before (luminance):
            their :func:`view_consistency` at the best roughness for them, as ``objective_current``.
        max_observations: a random subset of the vertices, with all their views, when there are more observations
            (the matrices hold observations × atoms; 18k on a 96² capture of 40 views found two lights within 3°).
        max_iter: L-BFGS-B iterations per fit (150: the same lights as 500 at a third of the time).
        f0: ``[N]`` each vertex's F0 as the mesh has it (luminance), for Schlick's Fresnel over F0 in the atoms and
            the ambient column (None: F = F0).

    Returns:
        ``{"positions", "intensities", "ambient" (radiance), "roughness", "objective", "objective_current",
        "distance", "weights", "vertices", "observations", "implied" [N] (each vertex's median implied F0,
        luminance, NaN where unobserved), "seconds"}``: lights and F0 share one arbitrary scale.
    """
    t = time.perf_counter()
    V, normals = np.asarray(V, np.float64), np.asarray(normals, np.float64)
    center = np.asarray(center, np.float64)
    vi, _, val, to_cam = observations
    lum = np.asarray(val, np.float64) @ LUMA
    ok = lum > 1e-4
    vi, lum, to_cam = vi[ok], lum[ok], to_cam[ok]
    per_vertex = np.bincount(vi, minlength=len(V))
    good = per_vertex >= min_views
    if per_vertex[good].sum() > max_observations:  # a random subset of the vertices, every view of each kept
        order = np.random.default_rng(0).permutation(np.flatnonzero(good))
        keep = order[:max(int(np.searchsorted(np.cumsum(per_vertex[order]), max_observations)), 16)]
        good = np.zeros(len(V), bool)
        good[keep] = True
    ok = good[vi]
    vi, log_c, to_cam = vi[ok], np.log(lum[ok]), to_cam[ok]
    if good.sum() < 16:
        raise ValueError(f"too few vertices seen by {min_views}+ views to fit lights ({int(good.sum())})")
    remap = np.cumsum(good) - 1
    group, n_groups = remap[vi], int(good.sum())
    P, nrm = V[vi], normals[vi]
    f0_obs = None if f0 is None else np.clip(np.asarray(f0, np.float64)[vi], 0.02, 1.0)
    grazing = (1.0 - np.maximum((nrm * to_cam).sum(axis=1), 0.0)) ** 5

    def ambient_column(r):  # the ambient term's Fresnel over F0: 1 + (1 / f0 - 1) (1 - r) (1 - n·v)^5 (shade.cl's Fe)
        return np.ones(len(P)) if f0_obs is None else 1.0 + (1.0 / f0_obs - 1.0) * (1.0 - r) * grazing

    def design(pos, d, r, geometry=None):  # [M, L + 1]: the point lights at pos (about 1 at the centre), the ambient
        if geometry is None:
            geometry = lobe_geometry(P, nrm, to_cam, pos, visibility(pos)[vi], d, f0_obs)
        return np.concatenate([specular_atom_matrix(P, nrm, to_cam, pos, None, r, d, geometry),
                               ambient_column(r)[:, None]], axis=1)

    dirs = sphere_directions(atoms)
    pos = center + distance * extent * dirs
    geometry = lobe_geometry(P, nrm, to_cam, pos, visibility(pos)[vi], distance * extent, f0_obs)
    found = None
    for r in roughness:
        w, obj = _fit_consistency(design(pos, distance * extent, r, geometry), log_c, group, n_groups,
                                  max_iter=max_iter)
        if found is None or obj < found[0]:
            found = (obj, r, w)
    _, r, w_atoms = found
    del geometry
    L, w0 = _clustered(dirs, w_atoms, cluster_angle, min_share, max_lights, "the highlights show")
    best = None
    for k in distances:
        BL = design(center + k * extent * L, k * extent, r)
        w, obj = _fit_consistency(BL, log_c, group, n_groups, w0=w0, max_iter=max_iter)
        if best is None or obj < best[0]:
            best = (obj, k, w, BL)
    obj, k, w, BL = best
    implied = np.full(len(V), np.nan)  # each vertex's F0 under the fit (one scale): the median over its views
    ratio = np.exp(log_c) / np.maximum(BL @ w, 1e-12)
    order = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[order], np.arange(n_groups + 1))
    implied[np.flatnonzero(good)] = [np.median(ratio[order[a:b]]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    obj_current = None
    if current is not None:
        cp, ci, ca = current
        cp = np.asarray(cp, np.float64).reshape(-1, 3)
        geometry = lobe_geometry(P, nrm, to_cam, cp, visibility(cp)[vi], 1.0, f0_obs)
        for rc in roughness:
            Bc = (specular_atom_matrix(P, nrm, to_cam, cp, None, rc, 1.0, geometry) @ np.asarray(ci, np.float64)
                  + float(ca) * ambient_column(rc))[:, None]
            if np.any(Bc > 0):
                o = view_consistency(np.ones(1), Bc, log_c, group, n_groups)[0]
                obj_current = o if obj_current is None else min(obj_current, o)
    return {"positions": center + k * extent * L, "intensities": w[:-1] * (k * extent) ** 2, "ambient": float(w[-1]),
            "roughness": float(r), "objective": float(obj), "objective_current": obj_current, "distance": k,
            "weights": w.tolist(), "vertices": n_groups, "observations": int(len(vi)), "implied": implied,
            "seconds": time.perf_counter() - t}
