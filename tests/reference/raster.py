"""Reference implementation (numpy, float64) of projection, K-nearest rasterization, interpolation,
soft coverage and compositing — brute force over all faces, no tiles. For small test scenes only.
"""

from __future__ import annotations

import numpy as np


def project_ref(V, cam16):
    """``[N,3]`` world → ``[N,3]`` (u, v, z); ``cam16`` = R (9, row-major), t (3), fx, fy, cx, cy."""
    V = np.asarray(V, np.float64)
    c = np.asarray(cam16, np.float64)
    R, t = c[:9].reshape(3, 3), c[9:12]
    pc = V @ R.T + t
    return np.stack([c[12] * pc[:, 0] / pc[:, 2] + c[14], c[13] * pc[:, 1] / pc[:, 2] + c[15], pc[:, 2]], 1)


def _cross(x, y):
    return x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]


def screen_bary(p, a0, a1, a2):
    """Screen barycentrics of points ``p [...,2]`` in triangles ``a_i [...,2]`` (broadcasting)."""
    A = _cross(a1 - a0, a2 - a0)
    b0 = _cross(a1 - p, a2 - p) / A
    b1 = _cross(a2 - p, a0 - p) / A
    b2 = _cross(a0 - p, a1 - p) / A
    return b0, b1, b2, A


def pixel_centres(W, H):
    ys, xs = np.mgrid[0:H, 0:W]
    return np.stack([xs + 0.5, ys + 0.5], -1).astype(np.float64)  # [H, W, 2]


def raster_ref(vs, F, W, H, K, near=0.01, far=1000.0, cull_back=False):
    """K nearest fragments by (depth, face id): face [H,W,K] (−1 empty), bary [H,W,K,2], depth, count."""
    vs = np.asarray(vs, np.float64)
    F = np.asarray(F, np.int64)
    p = pixel_centres(W, H)[:, :, None, :]  # [H,W,1,2]
    face = -np.ones((H, W, K), np.int64)
    bary = np.zeros((H, W, K, 2))
    depth = np.zeros((H, W, K))
    count = np.zeros((H, W), np.int64)
    if len(F) == 0:
        return face, bary, depth, count
    a = vs[F]  # [M,3,3]
    z = a[:, :, 2]
    b0, b1, b2, A = screen_bary(p, a[None, None, :, 0, :2], a[None, None, :, 1, :2], a[None, None, :, 2, :2])
    A = A.reshape(-1)
    valid = (z >= near).all(1) & ~(z > far).all(1) & (np.abs(A) > 1e-10)
    if cull_back:
        valid &= A <= 0
    inside = (b0 >= 0) & (b1 >= 0) & (b2 >= 0) & valid[None, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        w0, w1, w2 = b0 / z[:, 0], b1 / z[:, 1], b2 / z[:, 2]
        s = w0 + w1 + w2
        zp = 1.0 / s
    inside &= zp <= far
    M = len(F)
    for y in range(H):
        for x in range(W):
            idx = np.nonzero(inside[y, x])[0]
            if idx.size == 0:
                continue
            order = np.lexsort((idx, zp[y, x, idx]))[:K]
            sel = idx[order]
            n = len(sel)
            count[y, x] = n
            face[y, x, :n] = sel
            depth[y, x, :n] = zp[y, x, sel]
            bary[y, x, :n, 0] = w0[y, x, sel] / s[y, x, sel]
            bary[y, x, :n, 1] = w1[y, x, sel] / s[y, x, sel]
    assert face.max() < M
    return face, bary, depth, count


def interpolate_ref(attr, F, face, bary):
    attr = np.asarray(attr, np.float64)
    F = np.asarray(F, np.int64)
    valid = face >= 0
    f = np.where(valid, face, 0)
    l0, l1 = bary[..., 0], bary[..., 1]
    l2 = 1 - l0 - l1
    out = (l0[..., None] * attr[F[f, 0]] + l1[..., None] * attr[F[f, 1]] + l2[..., None] * attr[F[f, 2]])
    return np.where(valid[..., None], out, 0.0)


def interpolate_vjp_ref(attr, F, face, bary, v_out):
    """(v_attr [N,C], v_bary [H,W,K,2]) of ``sum(interpolate_ref(...) * v_out)``."""
    attr = np.asarray(attr, np.float64)
    F = np.asarray(F, np.int64)
    valid = face >= 0
    f = np.where(valid, face, 0)
    l0, l1 = bary[..., 0], bary[..., 1]
    lam = np.stack([l0, l1, 1 - l0 - l1], -1)
    g = np.where(valid[..., None], v_out, 0.0)
    v_attr = np.zeros_like(attr)
    for i in range(3):
        np.add.at(v_attr, F[f[valid], i], lam[valid][:, i, None] * g[valid])
    a0, a1, a2 = attr[F[f, 0]], attr[F[f, 1]], attr[F[f, 2]]
    v_bary = np.stack([(g * (a0 - a2)).sum(-1), (g * (a1 - a2)).sum(-1)], -1)
    return v_attr, np.where(valid[..., None], v_bary, 0.0)


def fragment_geometry_ref(vs, F, face, sigma=None, soft_edges=None):
    """Recompute (λ0, λ1, depth, window) of given fragments from ``vs`` — differentiable reference
    of what the kernels derive from projected vertices (used for finite-difference VJPs).
    ``soft_edges [M]``: 3-bit masks, only edges k with bit k set enter the window's minimum."""
    vs = np.asarray(vs, np.float64)
    F = np.asarray(F, np.int64)
    H, W, K = face.shape
    valid = face >= 0
    f = np.where(valid, face, 0)
    a = vs[F[f]]  # [H,W,K,3,3]
    p = pixel_centres(W, H)[:, :, None, :]
    b0, b1, b2, A = screen_bary(p, a[..., 0, :2], a[..., 1, :2], a[..., 2, :2])
    w0, w1, w2 = b0 / a[..., 0, 2], b1 / a[..., 1, 2], b2 / a[..., 2, 2]
    s = w0 + w1 + w2
    lam0, lam1, zp = w0 / s, w1 / s, 1 / s
    out = {"bary": np.where(valid[..., None], np.stack([lam0, lam1], -1), 0.0), "depth": np.where(valid, zp, 0.0)}
    if sigma is not None:
        sg = np.where(A >= 0, 1.0, -1.0)
        a0, a1, a2 = a[..., 0, :2], a[..., 1, :2], a[..., 2, :2]
        d0 = sg * _cross(a1 - p, a2 - p) / np.linalg.norm(a2 - a1, axis=-1)
        d1 = sg * _cross(a2 - p, a0 - p) / np.linalg.norm(a0 - a2, axis=-1)
        d2 = sg * _cross(a0 - p, a1 - p) / np.linalg.norm(a1 - a0, axis=-1)
        if soft_edges is not None:
            bits = np.asarray(soft_edges)[f]
            d0, d1, d2 = (np.where(bits & (1 << k), d, np.inf) for k, d in enumerate((d0, d1, d2)))
        d = np.maximum(np.minimum(np.minimum(d0, d1), d2), 0.0)
        out["win"] = np.where(valid, 1 - np.exp(-sigma * d), 0.0)
    return out


def composite_ref(feat, alpha, count, bg, t_min=0.0):
    """Front-to-back blending: image [H,W,C], trans [H,W], n_contrib [H,W]."""
    H, W, K, C = feat.shape
    img = np.zeros((H, W, C))
    trans = np.ones((H, W))
    ncon = np.zeros((H, W), np.int64)
    for y in range(H):
        for x in range(W):
            T = 1.0
            n = 0
            for i in range(count[y, x]):
                a = alpha[y, x, i]
                img[y, x] += feat[y, x, i] * a * T
                T *= 1 - a
                n = i + 1
                if T < t_min:
                    break
            img[y, x] += np.asarray(bg) * T
            trans[y, x] = T
            ncon[y, x] = n
    return img, trans, ncon


def composite_vjp_ref(feat, alpha, count, bg, v_img, v_acc=None, t_min=0.0):
    """(v_feat, v_alpha) of ``sum(img * v_img) + sum((1 - trans) * v_acc)`` by the product rule,
    written independently of the kernel's back-to-front recursion (O(K²) per pixel)."""
    H, W, K, C = feat.shape
    _, _, ncon = composite_ref(feat, alpha, count, bg, t_min)
    v_feat = np.zeros_like(feat, dtype=np.float64)
    v_alpha = np.zeros_like(alpha, dtype=np.float64)
    for y in range(H):
        for x in range(W):
            n = ncon[y, x]
            a = alpha[y, x, :n]
            f = feat[y, x, :n]
            T = np.concatenate([[1.0], np.cumprod(1 - a)])
            for i in range(n):
                v_feat[y, x, i] = v_img[y, x] * a[i] * T[i]
                # d img / d a_i = f_i T_i - sum_{j>i} f_j a_j T_j / (1 - a_i) - bg T_n / (1 - a_i), product form:
                rest = np.prod(np.delete(1 - a, i))
                d = f[i] * T[i]
                for j in range(i + 1, n):
                    Tj_wo = np.prod(np.delete(1 - a[:j], i))
                    d = d - f[j] * a[j] * Tj_wo
                d = d - np.asarray(bg) * rest
                v_alpha[y, x, i] = (v_img[y, x] * d).sum()
                if v_acc is not None:
                    v_alpha[y, x, i] += v_acc[y, x] * rest
    return v_feat, v_alpha
