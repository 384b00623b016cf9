"""COLMAP sparse models (text and binary) and the datasets built on them.

A model folder holds ``cameras``, ``images`` and (optionally) ``points3D``, each as ``.bin`` or
``.txt``. It is looked for at ``<root>/sparse/0/``, ``<root>/sparse/`` and ``<root>`` itself; the
images at ``<root>/images/`` (for a model folder given directly: its own ``images/``, its parent's
or its grandparent's). COLMAP's pixel convention (upper-left pixel centre at (0.5, 0.5)) and axes
(OpenCV) are ours, so intrinsics and poses are used as they are.

Camera models PINHOLE and SIMPLE_PINHOLE are used as they are (so are distorting models whose
distortion coefficients are all exactly zero). A scene with distorting cameras (SIMPLE_RADIAL,
RADIAL, OPENCV, the fisheyes, ...: COLMAP's defaults for phone photos) is undistorted to PINHOLE once
with pycolmap into a cache (:func:`triplet_cl.datasets.sfm.undistorted_model`: ``$TRIPLET_CACHE``, else
``$XDG_CACHE_HOME/triplet_cl/`` = ``~/.cache/triplet_cl/``; never the dataset folder) and that copy is loaded.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import DatasetError
from .base import Dataset, holdout_split, merge_color_spaces, warn_missing
from .images import load_views

# COLMAP's model ids: (name, number of parameters)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: i for i, (name, _) in CAMERA_MODELS.items()}
# models with the pinhole part first and only distortion after it (usable when that is all zero)
_PINHOLE_PREFIX = {"SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4, "FULL_OPENCV": 4}


class ColmapCamera:
    __slots__ = ("id", "model", "width", "height", "params")

    def __init__(self, id: int, model: str, width: int, height: int, params):
        self.id, self.model, self.width, self.height = int(id), model, int(width), int(height)
        self.params = np.asarray(params, dtype=np.float64)


class ColmapImage:
    __slots__ = ("id", "qvec", "tvec", "camera_id", "name")

    def __init__(self, id: int, qvec, tvec, camera_id: int, name: str):
        self.id, self.camera_id, self.name = int(id), int(camera_id), name
        self.qvec = np.asarray(qvec, dtype=np.float64)
        self.tvec = np.asarray(tvec, dtype=np.float64)


# ---- text -----------------------------------------------------------------------------------------
def _text_lines(path: Path):
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read the file: {exc}") from exc
    return [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines()) if not ln.lstrip().startswith("#")]


def _floats(path: Path, lineno: int, items, what: str):
    try:
        v = [float(x) for x in items]
    except ValueError:
        raise DatasetError(path, f"line {lineno}: {what} must be numbers, found {' '.join(items)!r}") from None
    if not np.isfinite(v).all():
        raise DatasetError(path, f"line {lineno}: {what} hold NaN or Inf values")
    return v


def _int(path: Path, lineno: int, item: str, what: str) -> int:
    try:
        return int(item)
    except ValueError:
        raise DatasetError(path, f"line {lineno}: {what} must be an integer, found {item!r}") from None


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cams = {}
    for lineno, ln in _text_lines(path):
        if not ln:
            continue
        el = ln.split()
        if len(el) < 4:
            raise DatasetError(path, f"line {lineno}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', found {ln!r}")
        cid = _int(path, lineno, el[0], "CAMERA_ID")
        model = el[1]
        if model not in MODEL_IDS:
            raise DatasetError(path, f"line {lineno}: unknown camera model {model!r}")
        nparams = CAMERA_MODELS[MODEL_IDS[model]][1]
        if len(el) != 4 + nparams:
            raise DatasetError(path, f"line {lineno}: camera model {model} takes {nparams} parameters, "
                                     f"found {len(el) - 4}")
        w, h = _int(path, lineno, el[2], "WIDTH"), _int(path, lineno, el[3], "HEIGHT")
        cams[cid] = ColmapCamera(cid, model, w, h, _floats(path, lineno, el[4:], "camera parameters"))
    return cams


def _check_unique(path: Path, images: dict, names: dict, iid: int, name: str, where: str = "") -> None:
    """An image id or name met twice: one photo dropped, or one photo trained under two poses (a battery).
    ``names``: the names read so far, with their ids (updated)."""
    if iid in images:
        raise DatasetError(path, f"{where}IMAGE_ID {iid} appears twice ({images[iid].name!r} and {name!r}): expected "
                                 "one entry per image")
    if name in names:
        raise DatasetError(path, f"{where}the image {name!r} appears twice (IMAGE_ID {names[name]} and {iid}): "
                                 "expected one pose per photo")
    names[name] = iid


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    """``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then one line of 2D points (maybe empty)."""
    images, names = {}, {}
    lines = _text_lines(path)
    i = 0
    while i < len(lines):
        lineno, ln = lines[i]
        i += 1
        if not ln:
            continue
        el = ln.split(maxsplit=9)
        if len(el) < 10:
            raise DatasetError(path, f"line {lineno}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
                                     f"found {ln!r}")
        iid = _int(path, lineno, el[0], "IMAGE_ID")
        pose = _floats(path, lineno, el[1:8], "QW QX QY QZ TX TY TZ")
        _check_unique(path, images, names, iid, el[9].strip(), f"line {lineno}: ")
        images[iid] = ColmapImage(iid, pose[:4], pose[4:], _int(path, lineno, el[8], "CAMERA_ID"), el[9].strip())
        # the POINTS2D line (possibly empty) — unless the file was written one line per image (some tools
        # omit it): then the next line is already the next image
        if i < len(lines) and not _is_image_line(lines[i][1]):
            i += 1
    return images


def _is_image_line(ln: str) -> bool:
    """``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` with a unit quaternion — never a POINTS2D line
    (``X Y POINT3D_ID`` triples: its first token is a float pixel coordinate and the would-be
    quaternion is not of unit length)."""
    el = ln.split(maxsplit=9)
    if len(el) < 10:
        return False
    try:
        int(el[0]), int(el[8])
        q = np.array([float(x) for x in el[1:5]])
        [float(x) for x in el[5:8]]
    except ValueError:
        return False
    return bool(abs(np.linalg.norm(q) - 1.0) < 1e-2)


def read_points3d_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    for lineno, ln in _text_lines(path):
        if not ln:
            continue
        el = ln.split()
        if len(el) < 8:
            raise DatasetError(path, f"line {lineno}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...', found {ln!r}")
        v = _floats(path, lineno, el[1:7], "X Y Z R G B")
        xyz.append(v[:3])
        rgb.append(v[3:6])
    return (np.asarray(xyz, np.float32).reshape(-1, 3), (np.asarray(rgb, np.float32) / 255.0).reshape(-1, 3))


# ---- binary ----------------------------------------------------------------------------------------
class _Reader:
    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except OSError as exc:
            raise DatasetError(path, f"cannot read the file: {exc}") from exc
        self.pos = 0

    def unpack(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.buf):
            raise DatasetError(self.path, f"truncated binary file (needed {size} bytes at offset {self.pos}, "
                                          f"the file has {len(self.buf)})")
        v = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return v

    def skip(self, n: int):
        if self.pos + n > len(self.buf):
            raise DatasetError(self.path, f"truncated binary file (needed {n} bytes at offset {self.pos}, "
                                          f"the file has {len(self.buf)})")
        self.pos += n

    def cstring(self) -> str:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(self.path, f"truncated binary file (unterminated image name at offset {self.pos})")
        s = self.buf[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s

    def done(self):
        if self.pos != len(self.buf):
            raise DatasetError(self.path, f"{len(self.buf) - self.pos} unexpected bytes after the last record")


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    (n,) = r.unpack("Q")
    cams = {}
    for _ in range(n):
        cid, model_id, w, h = r.unpack("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DatasetError(path, f"camera {cid}: unknown camera model id {model_id}")
        model, nparams = CAMERA_MODELS[model_id]
        params = r.unpack("d" * nparams)
        if not np.isfinite(params).all():
            raise DatasetError(path, f"camera {cid}: parameters hold NaN or Inf values")
        cams[cid] = ColmapCamera(cid, model, w, h, params)
    r.done()
    return cams


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    (n,) = r.unpack("Q")
    images, names = {}, {}
    for _ in range(n):
        v = r.unpack("idddddddi")
        iid, pose, cid = v[0], v[1:8], v[8]
        name = r.cstring()
        if not np.isfinite(pose).all():
            raise DatasetError(path, f"image {iid} ({name}): pose holds NaN or Inf values")
        (npts,) = r.unpack("Q")
        r.skip(24 * npts)  # x, y (double), point3D_id (int64)
        _check_unique(path, images, names, iid, name)
        images[iid] = ColmapImage(iid, pose[:4], pose[4:], cid, name)
    r.done()
    return images


def read_points3d_binary(path: Path) -> tuple[np.ndarray, np.ndarray]:
    r = _Reader(path)
    (n,) = r.unpack("Q")
    xyz = np.empty((n, 3), np.float64) if n < 1 << 31 else None
    if xyz is None:
        raise DatasetError(path, f"implausible point count {n}")
    rgb = np.empty((n, 3), np.float32)
    for k in range(n):
        v = r.unpack("QdddBBBdQ")
        xyz[k] = v[1:4]
        rgb[k] = v[4:7]
        r.skip(8 * v[8])  # track: (image_id int32, point2D_idx int32)
    r.done()
    if not np.isfinite(xyz).all():
        raise DatasetError(path, "point coordinates hold NaN or Inf values")
    return xyz.astype(np.float32), rgb / 255.0


# ---- model folder ------------------------------------------------------------------------------------
def _model_file(folder: Path, stem: str) -> Path | None:
    for ext in (".bin", ".txt"):
        p = folder / (stem + ext)
        if p.is_file():
            return p
    return None


def is_model_folder(folder: Path) -> bool:
    return _model_file(folder, "cameras") is not None and _model_file(folder, "images") is not None


def find_model(root: Path) -> Path | None:
    """The sparse model folder of a scene: ``root/sparse/0``, ``root/sparse`` or ``root``."""
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if cand.is_dir() and is_model_folder(cand):
            return cand
    return None


def read_model(folder: Path):
    """``(cameras, images, points, colors)`` of a model folder (``.bin`` preferred over ``.txt``);
    points/colors are ``None`` without a ``points3D`` file."""
    folder = Path(folder)
    cam_path, img_path = _model_file(folder, "cameras"), _model_file(folder, "images")
    if cam_path is None:
        raise DatasetError(folder / "cameras.bin", "file not found (nor cameras.txt): not a COLMAP model folder")
    if img_path is None:
        raise DatasetError(folder / "images.bin", "file not found (nor images.txt): not a COLMAP model folder")
    cams = read_cameras_binary(cam_path) if cam_path.suffix == ".bin" else read_cameras_text(cam_path)
    imgs = read_images_binary(img_path) if img_path.suffix == ".bin" else read_images_text(img_path)
    pts_path = _model_file(folder, "points3D")
    points = colors = None
    if pts_path is not None:
        points, colors = (read_points3d_binary(pts_path) if pts_path.suffix == ".bin"
                          else read_points3d_text(pts_path))
    return cams, imgs, points, colors, cam_path, img_path


def is_pinhole(cam: ColmapCamera) -> bool:
    """PINHOLE / SIMPLE_PINHOLE, or a distorting model whose distortion is all zero."""
    if cam.model in ("PINHOLE", "SIMPLE_PINHOLE"):
        return True
    return cam.model in _PINHOLE_PREFIX and not np.any(cam.params[_PINHOLE_PREFIX[cam.model]:])


def pinhole_intrinsics(cam: ColmapCamera, path: Path) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of a PINHOLE / SIMPLE_PINHOLE camera (or a distorting model whose
    distortion is all zero); :class:`DatasetError` naming the model otherwise."""
    p = cam.params
    model = cam.model
    if model in _PINHOLE_PREFIX and not np.any(p[_PINHOLE_PREFIX[model]:]):
        model = "SIMPLE_PINHOLE" if _PINHOLE_PREFIX[model] == 3 else "PINHOLE"
    if model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    if model == "PINHOLE":
        return p[0], p[1], p[2], p[3]
    raise DatasetError(path, f"camera {cam.id} uses the {cam.model} camera model, which is not supported here (only "
                             "PINHOLE and SIMPLE_PINHOLE are; load_colmap undistorts other models first)")


def _images_folder(root: Path, model: Path, images: str | Path | None) -> Path:
    if images is not None:
        p = Path(images)
        p = p if p.is_absolute() else root / p
        if not p.is_dir():
            raise DatasetError(p, "images folder not found")
        return p
    cands = [root / "images"] if model != root else []
    cands += [model / "images", model.parent / "images", model.parent.parent / "images"]
    for c in cands:
        if c.is_dir():
            return c
    raise DatasetError(root / "images", "images folder not found (looked next to the sparse model: "
                                        + ", ".join(str(c) for c in dict.fromkeys(cands)) + ")")


def load_colmap(root, downscale: int = 1, split_holdout: int | None = 8, images: str | Path | None = None,
                progress=None, _undistorted: bool = False) -> Dataset:
    """A COLMAP scene: the sparse model (see :func:`find_model`) and its images folder.

    Views are sorted by image name; every ``split_holdout``-th one is the test split (LLFF).
    ``images`` overrides the images folder (relative to ``root``). Distorting cameras: the scene
    is undistorted once into a cache and the copy loaded (module docstring); ``progress`` is called
    with a line when that happens (default: a :class:`DatasetWarning`-free print to stderr).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "is a file, not a dataset folder" if root.exists() else "dataset folder not found")
    model = find_model(root)
    if model is None:
        raise DatasetError(root, "no COLMAP model found (looked for cameras/images .bin or .txt in sparse/0/, "
                                 "sparse/ and the folder itself)")
    cams, imgs, points, colors, cam_path, img_path = read_model(model)
    if not imgs:
        raise DatasetError(img_path, "no images in the model")
    img_dir = _images_folder(root, model, images)
    if not all(is_pinhole(c) for c in cams.values()) and _undistorted:
        bad = next(c for c in cams.values() if not is_pinhole(c))
        raise DatasetError(cam_path, f"camera {bad.id}: pycolmap's undistortion left the {bad.model} model with "
                                     f"parameters {bad.params.tolist()} as it was (not a pinhole camera); this "
                                     "camera cannot be used")
    if not all(is_pinhole(c) for c in cams.values()):
        from .sfm import undistorted_model

        present = {k: im for k, im in imgs.items() if (img_dir / im.name).is_file()}
        if not present:
            raise DatasetError(img_dir, f"no images left: none of the {len(imgs)} image files of {img_path.name} "
                                        "exists")
        warn_missing(img_dir, sorted(im.name for im in imgs.values() if not (img_dir / im.name).is_file()),
                     len(imgs), f"images of {img_path.name}")
        say = progress if progress is not None else (lambda s: print(s, file=sys.stderr))
        for im in present.values():
            if im.camera_id not in cams:
                raise DatasetError(img_path, f"image {im.id} ({im.name}) refers to camera {im.camera_id}, which "
                                             f"{cam_path.name} does not define")
        cached = undistorted_model(root, model, img_dir, cams, present, progress=say)
        ds = load_colmap(cached, downscale, split_holdout, _undistorted=True)
        ds.root = root
        return ds
    records, missing = [], []
    for im in sorted(imgs.values(), key=lambda m: m.name):
        if im.camera_id not in cams:
            raise DatasetError(img_path, f"image {im.id} ({im.name}) refers to camera {im.camera_id}, which "
                                         f"{cam_path.name} does not define")
        cam = cams[im.camera_id]
        fx, fy, cx, cy = pinhole_intrinsics(cam, cam_path)
        image_file = img_dir / im.name
        if not image_file.is_file():
            missing.append(im.name)
            continue

        def make(width, height, im=im, cam=cam, fx=fx, fy=fy, cx=cx, cy=cy, image_file=image_file) -> Camera:
            if (width, height) != (cam.width, cam.height):
                raise DatasetError(image_file, f"image is {width}x{height} but camera {cam.id} of "
                                               f"{cam_path.name} is {cam.width}x{cam.height}")
            try:
                return Camera.from_colmap(im.qvec, im.tvec, fx, fy, cx, cy, width, height)
            except ValueError as exc:
                raise DatasetError(img_path, f"image {im.id} ({im.name}): {exc}") from None

        records.append((Path(im.name).with_suffix("").as_posix(), image_file, make))
    warn_missing(img_dir, missing, len(imgs), f"images of {img_path.name}")
    if not records:
        raise DatasetError(img_dir, f"no images left: none of the {len(imgs)} image files of {img_path.name} exists")
    views, spaces = load_views(records, downscale, "train", stored_pixel_poses=True)  # COLMAP reads stored pixels
    return Dataset(root, "colmap", holdout_split(views, split_holdout), points=points, colors=colors,
                   color_space=merge_color_spaces(root, spaces), downscale=downscale, held_out=split_holdout or None)
