"""Numpy references of the ray-tracing kernels (brute force over all triangles, float64)."""

from __future__ import annotations

import numpy as np

AMAX = 1.0 - 1e-6


def ray_tri(o, d, v0, v1, v2, tmin=0.0, tmax=np.inf):
    """Möller–Trumbore for one ray ``o, d [3]`` against triangles ``v0, v1, v2 [M, 3]``.

    Returns ``(hit [M] bool, t [M], u [M], v [M])`` (edges inclusive, ``tmin < t <= tmax``)."""
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d[None], e2)
    det = (e1 * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o[None] - v0
        u = (s * p).sum(-1) * inv
        q = np.cross(s, e1)
        v = (d[None] * q).sum(-1) * inv
        t = (e2 * q).sum(-1) * inv
    hit = (det != 0) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > tmin) & (t <= tmax)
    return hit, t, u, v


def camera_ray(camera, x, y):
    """World-space ray of pixel (x, y) through its centre; ``d`` has camera-space z = 1."""
    R = camera.w2c[:3, :3]
    dc = np.array([(x + 0.5 - camera.cx) / camera.fx, (y + 0.5 - camera.cy) / camera.fy, 1.0])
    return camera.center, R.T @ dc


def primary_ref(V, F, camera, K, allowed=None):
    """Brute-force K nearest hits per pixel sorted by (t, face): dict of face/bary/depth/count
    (−1 / 0 in empty slots). ``allowed(x, y, f)`` optionally filters faces (the rasterizer's binning)."""
    W, H = camera.width, camera.height
    face = -np.ones((H, W, K), np.int64)
    bary = np.zeros((H, W, K, 2))
    depth = np.zeros((H, W, K))
    count = np.zeros((H, W), np.int64)
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    for y in range(H):
        for x in range(W):
            o, d = camera_ray(camera, x, y)
            hit, t, u, v = ray_tri(o, d, v0, v1, v2, 0.0, camera.far)
            ids = np.nonzero(hit)[0]
            if allowed is not None:
                ids = np.array([f for f in ids if allowed(x, y, f)], np.int64)
            order = sorted(ids, key=lambda f: (t[f], f))[:K]
            count[y, x] = len(order)
            for k, f in enumerate(order):
                face[y, x, k] = f
                bary[y, x, k] = (1 - u[f] - v[f], u[f])
                depth[y, x, k] = t[f]
    return {"face": face, "bary": bary, "depth": depth, "count": count}


def bvh_bounds_ref(V, F, prim, P):
    """Node bounds ``[2P - 1, 6]`` of the implicit heap-ordered tree of bvh.cl for face order ``prim``."""
    M = len(F)
    nodes = np.zeros((2 * P - 1, 6))
    for j in range(P):
        s0, s1 = j * M // P, (j + 1) * M // P
        if s1 > s0:
            pts = V[F[prim[s0:s1]]].reshape(-1, 3)
            lo, hi = pts.min(0), pts.max(0)
            pad = 1e-6 * (np.abs(lo) + np.abs(hi)) + 1e-30
            nodes[P - 1 + j] = np.concatenate([lo - pad, hi + pad])
        else:
            nodes[P - 1 + j] = [1e30] * 3 + [-1e30] * 3
    for n in range(P - 2, -1, -1):
        a, b = nodes[2 * n + 1], nodes[2 * n + 2]
        nodes[n] = np.concatenate([np.minimum(a[:3], b[:3]), np.maximum(a[3:], b[3:])])
    return nodes


def transmittance_ref(V, F, alpha_v, pos, own, lights, eps):
    """``(T [P, NV], hits [P, NV])``: T = Π over the triangles crossed (own face skipped) of
    ``1 − clamp(α at the hit)``. ``lights``: list of ("point", position) or ("dir", direction)."""
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    P = len(pos)
    T = np.ones((P, len(lights)))
    n = np.zeros((P, len(lights)), np.int64)
    for j, (kind, a) in enumerate(lights):
        a = np.asarray(a, np.float64)
        for p in range(P):
            x = pos[p]
            d = a - x if kind == "point" else a
            tmin = eps / max(np.linalg.norm(d), 1e-30)
            tmax = 1.0 - tmin if kind == "point" else 1e30
            hit, _, u, v = ray_tri(x, d, v0, v1, v2, tmin, tmax)
            if 0 <= own[p] < len(F):
                hit[own[p]] = False
            n[p, j] = hit.sum()
            for f in np.nonzero(hit)[0]:
                al = (1 - u[f] - v[f]) * alpha_v[F[f, 0]] + u[f] * alpha_v[F[f, 1]] + v[f] * alpha_v[F[f, 2]]
                T[p, j] *= 1.0 - np.clip(al, 0.0, AMAX)
    return T, n


def nearest_ref(V, F, origin, direction, own, eps):
    """Nearest hit of each ray ``origin + t direction`` (``t > eps``, face ``own`` skipped, ``own < 0``: no ray):
    ``(face [R], bary [R, 2])``, ties to the lower face id."""
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    R = len(origin)
    face = -np.ones(R, np.int64)
    bary = np.zeros((R, 2))
    for p in range(R):
        if own[p] < 0:
            continue
        hit, t, u, v = ray_tri(origin[p], direction[p], v0, v1, v2, eps, np.inf)
        hit[own[p]] = False
        ids = np.nonzero(hit)[0]
        if len(ids):
            f = min(ids, key=lambda i: (t[i], i))
            face[p] = f
            bary[p] = (1 - u[f] - v[f], u[f])
    return face, bary


def bounce_ref(V, F, pos, nrm, own, cam, eps, two_sided=True):
    """Nearest hit along the mirror direction: ``(face [P], bary [P, 2])``."""
    dirs = np.zeros_like(pos)
    for p in range(len(pos)):
        Vd = cam - pos[p]
        Vd = Vd / np.linalg.norm(Vd)
        N = nrm[p] / np.linalg.norm(nrm[p])
        if two_sided and N @ Vd < 0:
            N = -N
        dirs[p] = 2 * (N @ Vd) * N - Vd
    return nearest_ref(V, F, pos, dirs, own, eps)
