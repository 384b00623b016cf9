"""Pinhole cameras and the one internal convention.

Internal convention (OpenCV / COLMAP style):

* ``w2c`` is the 4×4 world-to-camera matrix; camera space has **+X right, +Y down, +Z forward**
  (the camera looks down +Z; a point in front of the camera has ``z > 0``).
* Pixel coordinates: ``u = fx·x/z + cx``, ``v = fy·y/z + cy``; pixel ``(i, j)`` (column ``i``, row
  ``j``) covers ``[i, i+1) × [j, j+1)`` and its centre is ``(i + 0.5, j + 0.5)``. This is COLMAP's
  convention (the centre of the upper-left pixel is at (0.5, 0.5)) and NeRF's (``cx = W/2``).
  OpenCV puts the first pixel centre at (0, 0): :meth:`Camera.from_opencv` adds 0.5 to cx, cy.
* ``near``/``far`` bound the camera-space depth ``z``. A triangle with any vertex nearer than
  ``near`` is **culled** by the rasterizer (not clipped): the triplet soup consists of many small
  triangles, so culling the few that cross the near plane loses nothing visible and never draws
  one wrapped around through infinity.

Converters: :meth:`Camera.from_nerf` (Blender/NeRF camera-to-world, camera looks down −Z, +Y up),
:meth:`Camera.from_colmap` (quaternion + translation, world-to-camera, OpenCV axes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

# Blender/OpenGL camera axes (x right, y up, looking down -z) -> OpenCV axes (x right, y down, +z)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _check_pose(name: str, m) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape == (3, 4):
        a = np.vstack([a, [0.0, 0.0, 0.0, 1.0]])
    if a.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 (or 3x4) matrix, got shape {list(a.shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite, found NaN/Inf")
    r = a[:3, :3]
    if abs(abs(np.linalg.det(r)) - 1.0) > 1e-3:
        raise ValueError(f"{name}: the rotation part must be orthonormal (|det| = 1), got det {np.linalg.det(r):.4g}")
    return a


DEFAULT_NEAR, DEFAULT_FAR = 0.01, 1000.0  # world units at datasets.base.REFERENCE_EXTENT (datasets scale them)


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera in the internal convention (see module docstring).

    Attributes:
        fx, fy, cx, cy: intrinsics in pixels.
        width, height: image size in pixels.
        w2c: ``[4, 4]`` float64 world-to-camera matrix (OpenCV axes).
        near, far: depth range in camera-space units.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    w2c: np.ndarray = field(repr=False)
    near: float = DEFAULT_NEAR
    far: float = DEFAULT_FAR

    def __post_init__(self):
        object.__setattr__(self, "w2c", _check_pose("w2c", self.w2c))
        for n in ("fx", "fy", "cx", "cy", "near", "far"):
            v = float(getattr(self, n))
            if not math.isfinite(v):
                raise ValueError(f"camera {n} must be finite, got {v}")
            object.__setattr__(self, n, v)
        for n in ("width", "height"):  # a whole number of pixels (64.5 was truncated without a word)
            v = getattr(self, n)
            if isinstance(v, bool) or not (isinstance(v, int | np.integer)
                                           or (isinstance(v, float | np.floating) and float(v).is_integer())):
                raise ValueError(f"camera {n} must be a whole number of pixels, got {v!r}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"camera image size must be at least 1x1, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not 0 < self.near < self.far:
            raise ValueError(f"camera needs 0 < near < far, got near={self.near}, far={self.far}")

    # ---- constructors ---------------------------------------------------------------------
    @classmethod
    def from_nerf(cls, c2w, width: int, height: int, camera_angle_x: float | None = None,
                  fl_x: float | None = None, fl_y: float | None = None, cx: float | None = None,
                  cy: float | None = None, near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR) -> Camera:
        """From a NeRF/Blender camera-to-world matrix (camera looks down −Z, +Y up).

        Give either ``camera_angle_x`` (horizontal field of view, radians; NeRF-synthetic) or the
        focal lengths ``fl_x``/``fl_y`` (instant-ngp). ``cx``/``cy`` default to the image centre.
        """
        c2w_gl = _check_pose("c2w", c2w)
        if fl_x is None:
            if camera_angle_x is None:
                raise ValueError("from_nerf needs camera_angle_x or fl_x")
            fl_x = 0.5 * width / math.tan(0.5 * float(camera_angle_x))
        fl_y = fl_x if fl_y is None else fl_y
        c2w_cv = c2w_gl @ _GL_TO_CV
        return cls(fl_x, fl_y, width / 2.0 if cx is None else cx, height / 2.0 if cy is None else cy,
                   width, height, np.linalg.inv(c2w_cv), near, far)

    @classmethod
    def from_colmap(cls, qvec, tvec, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                    near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR) -> Camera:
        """From a COLMAP image pose (``qvec = [qw, qx, qy, qz]``, ``tvec``: world-to-camera)."""
        q = np.asarray(qvec, dtype=np.float64).reshape(-1)
        t = np.asarray(tvec, dtype=np.float64).reshape(-1)
        if q.shape != (4,) or t.shape != (3,):
            raise ValueError(f"COLMAP qvec must have 4 and tvec 3 entries, got {q.shape[0]} and {t.shape[0]}")
        n = np.linalg.norm(q)
        if not np.isfinite(n) or n < 1e-12:
            raise ValueError(f"COLMAP qvec must be a non-zero finite quaternion, got {q}")
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_rotmat(q / n)
        w2c[:3, 3] = t
        return cls(fx, fy, cx, cy, width, height, w2c, near, far)

    @classmethod
    def from_opencv(cls, K, w2c, width: int, height: int, near: float = DEFAULT_NEAR,
                    far: float = DEFAULT_FAR) -> Camera:
        """From an OpenCV intrinsic matrix ``K [3,3]`` (first pixel centre at 0,0) and ``w2c``."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape [3, 3], got {list(K.shape)}")
        return cls(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, width, height, w2c, near, far)

    @classmethod
    def look_at(cls, eye, target, up, fov_x_deg: float, width: int, height: int,
                near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR) -> Camera:
        """A camera at ``eye`` looking at ``target`` (``up`` appears upwards in the image)."""
        eye, target, up = (np.asarray(x, dtype=np.float64) for x in (eye, target, up))
        fov = float(fov_x_deg)
        if not (math.isfinite(fov) and 0 < fov < 180):
            raise ValueError(f"look_at: fov_x_deg must be a horizontal field of view in (0, 180) degrees, got "
                             f"{fov_x_deg!r}")
        for n, a in (("eye", eye), ("target", target), ("up", up)):
            if a.shape != (3,) or not np.isfinite(a).all():
                raise ValueError(f"look_at: {n} must be 3 finite numbers, got {a.tolist()!r}")
        z = target - eye
        if np.linalg.norm(z) < 1e-12:
            raise ValueError(f"look_at: eye and target are the same point {eye.tolist()}: no viewing direction")
        z /= np.linalg.norm(z)
        x = np.cross(z, up)  # image x to the right, y (= z × x) points down
        if np.linalg.norm(x) < 1e-12:
            raise ValueError("look_at: up is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        r = np.stack([x, y, z])
        w2c = np.eye(4)
        w2c[:3, :3] = r
        w2c[:3, 3] = -r @ eye
        f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return cls(f, f, width / 2.0, height / 2.0, width, height, w2c, near, far)

    # ---- derived ----------------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Camera centre in world space ``[3]``."""
        r, t = self.w2c[:3, :3], self.w2c[:3, 3]
        return -r.T @ t

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)

    @property
    def c2w_nerf(self) -> np.ndarray:
        """``[4, 4]`` camera-to-world in the NeRF/Blender convention (looks down −Z, +Y up): what :meth:`from_nerf`
        takes."""
        return self.c2w @ _GL_TO_CV

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.25 for ¼ resolution)."""
        if isinstance(factor, bool) or not (math.isfinite(float(factor)) and factor > 0):
            raise ValueError(f"scaled: factor must be a finite number > 0, got {factor!r}")
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy,
                       width=w, height=h)

    def block_averaged(self, f: int) -> Camera:
        """The camera of the image made of this one's ``f × f`` pixel blocks (the right and bottom remainder, fewer
        than ``f`` pixels, dropped): ``W // f × H // f`` pixels, intrinsics exactly ``1 / f`` (pixel-edge
        coordinates). :meth:`scaled` instead rescales to the rounded size, which for a size not divisible by ``f``
        moves the principal point by up to half a block against the blocks."""
        f = int(f)
        if f < 1 or self.width < f or self.height < f:
            raise ValueError(f"block size must be in [1, min(width, height)], got {f} for {self.width}x{self.height}")
        return replace(self, fx=self.fx / f, fy=self.fy / f, cx=self.cx / f, cy=self.cy / f,
                       width=self.width // f, height=self.height // f)

    def project_points(self, points: np.ndarray) -> np.ndarray:
        """Host-side projection ``[N,3] → [N,3]`` of (u, v, z) in float64 (reference / tools)."""
        p = np.asarray(points, dtype=np.float64) @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy, z], axis=1)


def quat_to_rotmat(q) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` → rotation matrix ``[3, 3]`` (COLMAP's convention)."""
    w, x, y, z = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
