"""The region of interest of a capture with a background: which part of the trained scene is *the object*.

Photos of an object on a table (or the ground) under a sky have no alpha: the soup is trained with
the background as part of the scene, and the mesh exported must be the object alone. The region is
an oriented box (:class:`ROI`); the TSDF fusion treats every voxel outside it as empty, so the
extracted surface is closed where the box cuts it (under the object's feet).

:func:`auto_roi` finds it from the cameras and the sparse SfM points:

1. the **look-at point** ``c``: the point nearest to every camera's optical axis (least squares) —
   an object-centric capture looks at its object;
2. **up**: the mean of the cameras' up vectors (photos are taken upright);
3. the **ground**: the dominant plane of the sparse points (RANSAC, inlier band 0.5 % of the mean
   camera distance) whose normal lies within 30° of up and which passes below ``c``; none → no
   ground cut;
4. the **object**: the sparse points above the ground (by more than 3 % of the camera distance: the
   ground's own points scatter a little above it) within a horizontal radius of ``0.5 ×`` the
   cameras' mean horizontal distance from ``c``; the
   box spans their 2nd–98th percentiles along up and two horizontal axes, padded by 25 % (at least
   2 % of the camera distance); its bottom is the ground plane plus a small gap (1 % of the camera
   distance: the soup's ground has some thickness).

``--bbox XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`` (world units of the dataset) replaces it with that
axis-aligned box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ROI:
    """An oriented box: ``center [3]``, ``axes [3, 3]`` (rows: unit axes), ``half [3]`` half-sizes along them."""

    center: np.ndarray
    axes: np.ndarray
    half: np.ndarray
    source: str = "bbox"  # "bbox" (given) or "auto"
    ground: tuple | None = None  # (normal [3], offset): the ground plane n·x = offset, when one was found

    @classmethod
    def from_bbox(cls, bbox) -> ROI:
        b = np.asarray(bbox, np.float64).reshape(-1)
        if b.shape != (6,) or not np.isfinite(b).all() or not (b[3:] > b[:3]).all():
            raise ValueError(f"bbox must be XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX with each max > min, got {list(bbox)}")
        return cls(0.5 * (b[:3] + b[3:]), np.eye(3), 0.5 * (b[3:] - b[:3]), "bbox")

    def local(self, X: np.ndarray) -> np.ndarray:
        return (np.asarray(X, np.float64) - self.center) @ self.axes.T

    def contains(self, X: np.ndarray) -> np.ndarray:
        return (np.abs(self.local(X)) <= self.half).all(axis=-1)

    def corners(self) -> np.ndarray:
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return self.center + (s * self.half) @ self.axes

    def aabb(self) -> np.ndarray:
        c = self.corners()
        return np.stack([c.min(0), c.max(0)])

    def to_dict(self) -> dict:
        d = {"center": self.center.tolist(), "axes": self.axes.tolist(), "half": self.half.tolist(),
             "source": self.source}
        if self.ground is not None:
            d["ground"] = {"normal": np.asarray(self.ground[0]).tolist(), "offset": float(self.ground[1])}
        return d


def cameras_seeing(roi: ROI, cameras, samples: int = 9) -> int:
    """How many of ``cameras`` see some of the box: a ``samples³`` grid of its points (corners included) in front of
    the camera and inside its image. A ``--bbox`` no training camera sees crops the mesh to nothing, found only
    after the whole training."""
    t = np.linspace(-1.0, 1.0, samples)
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    X = roi.center + (g * roi.half) @ roi.axes
    n = 0
    for cam in cameras:
        if roi.contains(cam.center[None])[0]:  # a camera inside the box sees into it, whatever the grid
            n += 1
            continue
        Xc = X @ cam.w2c[:3, :3].T + cam.w2c[:3, 3]
        z = Xc[:, 2]
        front = z > cam.near
        u = cam.fx * Xc[front, 0] / z[front] + cam.cx
        v = cam.fy * Xc[front, 1] / z[front] + cam.cy
        n += bool(((u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)).any())
    return n


def parse_bbox(text: str) -> tuple:
    """``"XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX"`` → 6 floats; :class:`ValueError` saying what is expected."""
    try:
        b = tuple(float(x) for x in str(text).split(","))
    except ValueError:
        b = ()
    if len(b) != 6 or not all(np.isfinite(b)) or not all(b[i + 3] > b[i] for i in range(3)):
        raise ValueError(f"expected XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX (6 numbers, each max > min), found {text!r}")
    return b


def look_at_point(cameras) -> np.ndarray:
    """The point nearest to every camera's optical axis; the mean centre when the axes are parallel."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.w2c[2, :3]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    if np.linalg.cond(A) > 1e8:
        return np.mean([c.center for c in cameras], axis=0)
    return np.linalg.solve(A, b)


def mean_up(cameras) -> np.ndarray:
    up = -np.mean([c.w2c[1, :3] for c in cameras], axis=0)  # image y points down
    return up / (np.linalg.norm(up) + 1e-12)


def ground_plane(points: np.ndarray, up: np.ndarray, below: np.ndarray, band: float, iterations: int = 2000,
                 max_tilt_deg: float = 30.0, seed: int = 0):
    """RANSAC: the plane ``n·x = d`` (``n`` towards ``up``) with the most points within ``band``, among planes
    tilted less than ``max_tilt_deg`` from ``up`` that pass below ``below``; ``None`` without one holding at
    least 20 % of the points."""
    P = np.asarray(points, np.float64)
    if len(P) < 10:
        return None
    rng = np.random.default_rng(seed)
    best, best_n = None, 0
    cos_max = np.cos(np.radians(max_tilt_deg))
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        if n @ up < 0:
            n = -n
        if n @ up < cos_max:
            continue
        d = n @ a
        if n @ below <= d:
            continue
        cnt = int((np.abs(P @ n - d) < band).sum())
        if cnt > best_n:
            best, best_n = (n, d), cnt
    if best is None or best_n < 0.2 * len(P):
        return None
    n, d = best  # refine on the inliers (least squares)
    inl = P[np.abs(P @ n - d) < band]
    cen = inl.mean(0)
    _, _, Vt = np.linalg.svd(inl - cen)
    n2 = Vt[2] if Vt[2] @ n > 0 else -Vt[2]
    return n2, float(n2 @ cen)


def auto_roi(cameras, points) -> ROI | None:
    """The object's box from the cameras and the sparse points (module docstring); ``None`` without points."""
    cameras = list(cameras)
    if points is None or len(points) < 10 or not cameras:
        return None
    P = np.asarray(points, np.float64)
    c = look_at_point(cameras)
    up = mean_up(cameras)
    centres = np.array([cam.center for cam in cameras])
    dist = float(np.linalg.norm(centres - c, axis=1).mean())
    plane = ground_plane(P, up, c, band=0.005 * dist)
    n = plane[0] if plane is not None else up
    # horizontal axes: any orthonormal pair perpendicular to n
    x = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    axes = np.stack([x, y, n])
    rel = P - c
    horiz = rel - np.outer(rel @ n, n)
    cam_rel = centres - c
    cam_horiz = float(np.linalg.norm(cam_rel - np.outer(cam_rel @ n, n), axis=1).mean())
    keep = np.linalg.norm(horiz, axis=1) < 0.5 * cam_horiz
    floor = None
    if plane is not None:
        floor = plane[1] + 0.01 * dist  # the soup's ground has some thickness
        keep &= P @ n > plane[1] + 0.03 * dist
    obj = P[keep]
    if len(obj) < 5:
        return None
    L = (obj - c) @ axes.T
    lo, hi = np.percentile(L, 2, axis=0), np.percentile(L, 98, axis=0)
    pad = np.maximum(0.25 * (hi - lo), 0.02 * dist)
    lo, hi = lo - pad, hi + pad
    if floor is not None:
        lo[2] = floor - float(c @ n)  # the box's bottom: just above the ground
        hi[2] = max(hi[2], lo[2] + 0.02 * dist)
    mid = 0.5 * (lo + hi)
    return ROI(c + mid @ axes, axes, 0.5 * (hi - lo), "auto", plane)
