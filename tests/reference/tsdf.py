"""Reference for ``kernels_cl/tsdf.cl`` (``triplet_cl.ops.tsdf``): TSDF fusion's per-voxel votes in numpy,
vectorised over the voxels of one view at a time (what ``tsdf_fusion`` ran on the host before the kernel), in
float32 with every dot product written out left to right as the kernel evaluates it."""

from __future__ import annotations

import numpy as np

from triplet_cl.ops.tsdf import FusionView


def project_voxels(X: np.ndarray, row: np.ndarray, width: int, height: int):
    """Voxel centres ``X [P, 3] float32`` seen by the camera of ``row`` (:meth:`FusionView.camera_row`):
    ``(idx [Q] voxels in front of the camera and inside the image, pix [Q] flat pixel index (nearest pixel),
    z [Q] camera depth, uv [Q, 2] continuous image position (pixel centres at j + 0.5))``."""
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    zc = x * row[6] + y * row[7] + z * row[8] + row[11]
    idx = np.flatnonzero(zc > row[16])
    x, y, z, zc = x[idx], y[idx], z[idx], zc[idx]
    uc = (x * row[0] + y * row[1] + z * row[2] + row[9]) / zc * row[12] + row[14]
    vc = (x * row[3] + y * row[4] + z * row[5] + row[10]) / zc * row[13] + row[15]
    u, v = np.floor(uc), np.floor(vc)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    pix = v[ok].astype(np.int64) * width + u[ok].astype(np.int64)
    return idx[ok], pix, zc[ok], np.stack([uc[ok], vc[ok]], 1)


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``img [H, W] float32`` bilinearly interpolated at ``uv [Q, 2]`` (pixel centres at ``j + 0.5``, clamped)."""
    H, W = img.shape
    one, half = np.float32(1), np.float32(0.5)
    x = np.clip(uv[:, 0] - half, np.float32(0), np.float32(W - 1))
    y = np.clip(uv[:, 1] - half, np.float32(0), np.float32(H - 1))
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2 if H > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = x - x0.astype(np.float32), y - y0.astype(np.float32)
    top = img[y0, x0] * (one - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (one - fx) + img[y1, x1] * fx
    return top * (one - fy) + bot * fy


def fuse_votes(axes, views: list[FusionView], alpha_threshold: float, tau: float) -> dict[str, np.ndarray]:
    """The seven per-voxel sums of ``TsdfVotes`` (its ``NAMES``) over the grid ``axes`` after ``views``."""
    gx, gy, gz = (np.asarray(a, np.float32) for a in axes)
    X = np.stack(np.meshgrid(gx, gy, gz, indexing="ij"), axis=-1).reshape(-1, 3)
    n = len(X)
    num, wsum, hull_sdf = np.zeros(n, np.float32), np.zeros(n, np.float32), np.full(n, -np.inf, np.float32)
    seen, hidden, hull_out, hull_exact = (np.zeros(n, np.int32) for _ in range(4))
    thr, inv_tau, one = np.float32(alpha_threshold), np.float32(1.0 / tau), np.float32(1)
    for view in views:
        cam = view.camera
        row = view.camera_row(tau)
        idx, pix, z, uv = project_voxels(X, row, cam.width, cam.height)
        seen[idx] += 1
        if view.photo_bg is not None:
            hull_out[idx[np.asarray(view.photo_bg).reshape(-1)[pix]]] += 1
        if view.sd is not None:
            sd = bilinear(np.asarray(view.sd, np.float32), uv) * z * row[17]
            out = sd > 0
            hull_exact[idx[out]] += 1
            hull_sdf[idx[out]] = np.maximum(hull_sdf[idx[out]], np.minimum(sd[out], one))
        a = np.asarray(view.acc, np.float32).reshape(-1)[pix]
        surf = a >= thr
        s = (np.asarray(view.depth, np.float32).reshape(-1)[pix] - z) * inv_tau
        behind = surf & (s < -1)
        hidden[idx[behind]] += 1
        use = np.asarray(view.free).reshape(-1)[pix] | (surf & ~behind)
        w = np.where(surf, a, one)[use]
        ii = idx[use]
        num[ii] += w * np.where(surf[use], np.minimum(s[use], one), one)
        wsum[ii] += w
    return {"num": num, "wsum": wsum, "seen": seen, "hidden": hidden, "hull_out": hull_out,
            "hull_exact": hull_exact, "hull_sdf": hull_sdf}
