"""NeRF-synthetic ("Blender") datasets and the ``transforms*.json`` parser shared with instant-ngp.

A ``transforms_{train,val,test}.json`` holds ``camera_angle_x`` (horizontal field of view in
radians) and ``frames``: each a ``file_path`` (relative to the JSON's folder, with or without an
extension) and a ``transform_matrix`` (4×4 camera-to-world, Blender/OpenGL axes: the camera looks
down −Z with +Y up). The same parser reads instant-ngp's keys (``fl_x``, ``fl_y``, ``cx``, ``cy``,
``w``, ``h``, ``camera_angle_y``; globally or per frame) and refuses lens distortion.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import DatasetError
from ..io import strict_json_object
from .base import Dataset, holdout_split, merge_color_spaces, warn_missing
from .images import find_image, load_views, not_a_file

_INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
MIN_FOV = 1e-3  # radians: no lens sees less (a 2000 mm lens on full frame: 0.018)
FOCAL_AGREEMENT = 0.01  # fl_x and camera_angle_x both given: the relative difference of their focal lengths allowed
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_FISHEYE_MODELS = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "FOV",
                   "EQUIRECTANGULAR")


def read_json(path: Path) -> dict:
    """Parse a JSON file; :class:`DatasetError` with line/column on a syntax error."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a BOM (Windows editors) is no error
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read the file: {exc}") from exc
    try:
        data = json.loads(text, object_pairs_hook=strict_json_object)
    except json.JSONDecodeError as exc:
        raise DatasetError(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from exc
    except (RecursionError, ValueError) as exc:  # nested too deep; an integer past Python's 4300 digits
        raise DatasetError(path, f"unreadable JSON ({'nested too deeply' if isinstance(exc, RecursionError) else exc})"
                           ) from None
    if not isinstance(data, dict):
        raise DatasetError(path, f"expected a JSON object at the top level, found {type(data).__name__}")
    return data


def _number(path: Path, where: str, key: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(path, f"{where}{key} must be a number, found {value!r}")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond any float
        v = math.inf
    if not math.isfinite(v):
        raise DatasetError(path, f"{where}{key} must be finite, found {v}")
    if positive and v <= 0:
        raise DatasetError(path, f"{where}{key} must be positive, found {v}")
    return v


def _numbers_only(value) -> bool:
    """``value`` is a number (not a boolean) or nested lists of them: no strings, which numpy would convert."""
    if isinstance(value, list):
        return all(_numbers_only(x) for x in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _matrix(path: Path, where: str, value) -> np.ndarray:
    if not _numbers_only(value):
        raise DatasetError(path, f"{where}transform_matrix must be a 4x4 matrix of numbers (no strings or booleans), "
                                 f"found {str(value)[:80]}")
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(path, f"{where}transform_matrix must be a 4x4 matrix of numbers") from None
    except OverflowError:
        raise DatasetError(path, f"{where}transform_matrix holds a number too large for a float") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise DatasetError(path, f"{where}transform_matrix must be 4x4 (or 3x4), found shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise DatasetError(path, f"{where}transform_matrix holds NaN or Inf values")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(r) <= 0:
        raise DatasetError(path, f"{where}transform_matrix is not a rigid camera-to-world transform: its rotation "
                                 f"part is not orthonormal with determinant +1 (max |RᵀR − I| = {err:.3g}, det "
                                 f"{np.linalg.det(r):.4g}; scaled, sheared or mirrored cameras are not supported)")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DatasetError(path, f"{where}transform_matrix is not a rigid camera-to-world transform: its bottom row "
                                 f"is {m[3].tolist()}, expected [0, 0, 0, 1]")
    return m


def _check_distortion(path: Path, where: str, intr: dict) -> None:
    model = intr.get("camera_model")
    fish = intr.get("is_fisheye")
    if fish is not None and fish not in (True, False, 0, 1):  # a string "false" was read as true (a battery)
        raise DatasetError(path, f"{where}is_fisheye: expected true or false, found {fish!r}")
    if model is not None and not isinstance(model, str):
        raise DatasetError(path, f"{where}camera_model: expected a name such as \"OPENCV\", found {model!r}")
    if fish or (isinstance(model, str) and model.upper() in _FISHEYE_MODELS):
        raise DatasetError(path, f"{where}fisheye camera ({model or 'is_fisheye'}) is not supported: undistort the "
                                 "images to a pinhole camera first (e.g. `colmap image_undistorter`)")
    bad = []
    for k in _DISTORTION_KEYS:
        if k in intr:
            v = _number(path, where, k, intr[k])
            if v != 0.0:
                bad.append(f"{k}={v:g}")
    if bad:
        raise DatasetError(path, f"{where}lens distortion is not supported ({', '.join(bad)}): undistort the images "
                                 "first (e.g. `colmap image_undistorter`) and write their pinhole intrinsics "
                                 "without distortion coefficients")


def _check_intrinsics(path: Path, where: str, intr: dict) -> None:
    for k in _INTRINSIC_KEYS:
        if k in intr:
            _number(path, where, k, intr[k], positive=k not in ("cx", "cy"))
    for k in ("camera_angle_x", "camera_angle_y"):
        if k in intr and not float(intr[k]) < math.pi:
            v = float(intr[k])
            raise DatasetError(path, f"{where}{k} = {v:g} is not a field of view in radians (expected 0 < {k} < π)"
                                     + (f"; if it is in degrees, write {math.radians(v):.6g}" if v < 180 else ""))
        if k in intr and float(intr[k]) < MIN_FOV:
            raise DatasetError(path, f"{where}{k} = {float(intr[k]):g} is not a camera's field of view (expected at "
                                     f"least {MIN_FOV} radians, {math.degrees(MIN_FOV):.2g}°: a 2000 mm lens on a "
                                     "full-frame camera still sees 1°)")
    _check_distortion(path, where, intr)


FOCAL_KEYS = ("fl_x", "camera_angle_x", "fl_y", "camera_angle_y")
# a principal point farther than this share of the image's side from its centre warns: lenses put it within a few
# percent of the centre, and intrinsics written for images of another size (twice the size: cx, cy at a quarter of
# the image, exactly 0.25 off; half the size: three quarters) land at 0.25 or beyond (battery 9: trained without a
# word). A crop of a photo can be that far off too: hence a warning, not a refusal
OFF_CENTRE = 0.2


def has_focal(intr: dict) -> bool:
    """``intr`` gives a focal length: ``fl_x`` / ``camera_angle_x``, or only the vertical one (square pixels)."""
    return any(k in intr for k in FOCAL_KEYS)


def _camera_maker(path: Path, where: str, c2w: np.ndarray, intr: dict, notes: list | None = None):
    """A ``make_camera(width, height)`` for :func:`load_views`, checked against the JSON. With only the vertical
    focal length (``fl_y`` or ``camera_angle_y`` with the image height), the pixels are square: ``fl_x = fl_y``, as
    instant-ngp reads it. ``notes``: a list that gets ``(where, cx, cy, width, height, sized)`` for a principal point
    farther than :data:`OFF_CENTRE` from the image centre (``sized``: the intrinsics gave ``w`` and ``h``), for the
    caller's one warning (:func:`warn_off_centre`)."""
    if not has_focal(intr):
        raise DatasetError(path, "missing key 'camera_angle_x' (or 'fl_x'; or 'camera_angle_y' / 'fl_y' for square "
                                 f"pixels), at the top level or in {where.rstrip(': ')}: the focal length is unknown")

    def make(width: int, height: int, path=path, where=where) -> Camera:
        for k, size in (("w", width), ("h", height)):
            if k in intr and int(round(float(intr[k]))) != size:
                raise DatasetError(path, f"{where}{k}={intr[k]:g} but the image is {width}x{height}")
        for fk, ak, size in (("fl_x", "camera_angle_x", width), ("fl_y", "camera_angle_y", height)):
            if fk in intr and ak in intr:  # both given (instant-ngp writes both): they must be one camera
                f_angle = 0.5 * size / math.tan(0.5 * float(intr[ak]))
                if abs(float(intr[fk]) - f_angle) > FOCAL_AGREEMENT * f_angle:
                    raise DatasetError(path, f"{where}{fk} = {float(intr[fk]):g} pixels and {ak} = {float(intr[ak]):g} "
                                             f"rad (a focal length of {f_angle:.4g} pixels on the {size}-pixel side) "
                                             "disagree: give one, or both for the same camera")
        fl_y = intr.get("fl_y")
        if fl_y is None and "camera_angle_y" in intr:
            fl_y = 0.5 * height / math.tan(0.5 * float(intr["camera_angle_y"]))
        fl_x = intr.get("fl_x")
        if fl_x is None and "camera_angle_x" in intr:
            fl_x = 0.5 * width / math.tan(0.5 * float(intr["camera_angle_x"]))
        if fl_x is None:  # only the vertical focal length: square pixels (instant-ngp's reading)
            fl_x = fl_y
        for k, f, size in (("fl_x", fl_x, width), ("fl_y", intr.get("fl_y"), height)):
            if f is not None and 2.0 * math.atan(0.5 * size / float(f)) < MIN_FOV:
                raise DatasetError(path, f"{where}{k} = {float(f):g} pixels on a {size}-pixel side is a field of view "
                                         f"under {MIN_FOV} radians: not a camera's focal length")
        for k, size in (("cx", width), ("cy", height)):
            if k in intr and not -size <= float(intr[k]) <= 2 * size:
                raise DatasetError(path, f"{where}{k} = {float(intr[k]):g} puts the principal point more than an image "
                                         f"away from the {width}x{height} image (expected {-size} to {2 * size})")
        if notes is not None and ("cx" in intr or "cy" in intr):
            cx, cy = float(intr.get("cx", 0.5 * width)), float(intr.get("cy", 0.5 * height))
            if abs(cx - 0.5 * width) > OFF_CENTRE * width or abs(cy - 0.5 * height) > OFF_CENTRE * height:
                notes.append((where, cx, cy, width, height, "w" in intr and "h" in intr))
        try:
            return Camera.from_nerf(c2w, width, height, fl_x=float(fl_x), fl_y=None if fl_y is None else float(fl_y),
                                    cx=intr.get("cx"), cy=intr.get("cy"))
        except ValueError as exc:
            raise DatasetError(path, f"{where}{exc}") from None

    return make


def frame_intrinsics(path: Path, where: str, top: dict, frame: dict) -> dict:
    """A frame's intrinsics: the file's ``top`` keys (checked by the caller) overridden by the frame's own (checked
    here); a frame's own focal length overrides the file's in either form (``fl_x`` or ``camera_angle_x``)."""
    own = {k: v for k, v in frame.items() if k not in ("file_path", "transform_matrix")}
    _check_intrinsics(path, where, own)
    intr = {**top, **own}
    for fk, ak in (("fl_x", "camera_angle_x"), ("fl_y", "camera_angle_y")):
        if (fk in own) != (ak in own):
            intr.pop(ak if fk in own else fk, None)
    return intr


def warn_off_centre(json_path: Path, notes: list, total: int) -> None:
    """One :class:`DatasetWarning` for the frames whose principal point :func:`_camera_maker` found far from the image
    centre (``notes``), naming the first one's values and image size and the likely cause."""
    if not notes:
        return
    import warnings

    from .base import DatasetWarning

    where, cx, cy, w, h, sized = notes[0]
    cause = ("check cx / cy (a crop of the photos?)" if sized else
             "the intrinsics were likely written for images of another size (e.g. the photos resized after the "
             "poses were solved): give w and h with them, so that a size mismatch is refused, or fix fl_x / fl_y / "
             "cx / cy for these images")
    warnings.warn(f"{json_path}: {len(notes)} of {total} frames put the principal point far from the image centre "
                  f"({where.rstrip(': ')}: cx = {cx:g}, cy = {cy:g} on a {w}x{h} image, whose centre is {w / 2:g}, "
                  f"{h / 2:g}): {cause}", DatasetWarning, stacklevel=3)


def transforms_records(json_path: Path, data: dict | None = None, notes: list | None = None):
    """Parse a ``transforms*.json`` → ``(records, missing)`` for :func:`load_views`.

    ``records`` are ``(name, image_path, make_camera)``; frames whose image file does not exist
    are left out and their ``file_path`` returned in ``missing``. ``notes``: see :func:`_camera_maker`.
    """
    json_path = Path(json_path)
    root = json_path.parent
    data = read_json(json_path) if data is None else data
    if "frames" not in data:
        raise DatasetError(json_path, "missing key 'frames'")
    frames = data["frames"]
    if not isinstance(frames, list):
        raise DatasetError(json_path, f"'frames' must be a list, found {type(frames).__name__}")
    if not frames:
        raise DatasetError(json_path, "no frames ('frames' is empty)")
    top = {k: v for k, v in data.items() if k != "frames"}
    _check_intrinsics(json_path, "", top)
    records, missing, names = [], [], {}
    for i, fr in enumerate(frames):
        where = f"frames[{i}]: "
        if not isinstance(fr, dict):
            raise DatasetError(json_path, f"{where}each frame must be a JSON object, found {type(fr).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise DatasetError(json_path, f"{where}missing key '{key}'")
        fp = fr["file_path"]
        if not isinstance(fp, str) or not fp:
            raise DatasetError(json_path, f"{where}file_path must be a non-empty string, found {fp!r}")
        c2w = _matrix(json_path, where, fr["transform_matrix"])
        intr = frame_intrinsics(json_path, where, top, fr)
        make = _camera_maker(json_path, where, c2w, intr, notes)
        image = find_image(root / fp)
        if image is None:
            there = not_a_file(root / fp)
            if there:  # something is there, but no photo: say what, rather than "missing"
                raise DatasetError(there[0], f"{there[1]}, not an image file ({json_path.name}, {where.rstrip(': ')})")
            missing.append(fp)
            continue
        try:
            name = image.resolve().relative_to(root.resolve()).with_suffix("").as_posix()
        except ValueError:
            name = Path(fp).with_suffix("").as_posix()
        if name in names:
            raise DatasetError(json_path, f"{where}file_path {fp!r} names the same image as frames[{names[name]}] "
                                          f"({name}): each frame must be its own photo")
        names[name] = i
        records.append((name, image, make))
    return records, missing


def load_transforms_split(json_path: Path, split: str, downscale: int = 1):
    """Views of one ``transforms*.json``; frames with a missing image are skipped with one
    :class:`DatasetWarning` that counts them. Returns ``(views, color_spaces)``."""
    notes: list = []
    data = read_json(json_path)
    records, missing = transforms_records(json_path, data, notes=notes)
    warn_missing(json_path, missing, len(missing) + len(records), "frames")
    if not records:
        raise DatasetError(json_path, f"no frames left: none of the {len(missing)} image files exists")
    out = load_views(records, downscale, split)
    warn_off_centre(json_path, notes, len(records))
    warn_masks(json_path, data["frames"])
    return out


def warn_masks(json_path: Path, frames: list) -> None:
    """One :class:`DatasetWarning` when frames carry nerfstudio's ``mask_path`` (battery 9: ignored without a word).

    The masks are not applied, by choice: nerfstudio's mask marks the pixels to leave out of the loss (a passer-by, the
    capture rig), not the object's coverage. Read as alpha, those pixels would be trained as transparent, the scene
    behind a passer-by taught to vanish, and triplet has no per-pixel loss weight to leave them out instead."""
    n = sum(isinstance(f, dict) and "mask_path" in f for f in frames)
    if n:
        import warnings

        from .base import DatasetWarning

        warnings.warn(f"{json_path}: {n} of {len(frames)} frames have a 'mask_path' (nerfstudio masks): the masks are "
                      "not used (a nerfstudio mask marks pixels to leave out of the loss, which triplet cannot do), "
                      "the masked pixels are trained as the photos show them; to leave out a background, give the "
                      "photos an alpha channel", DatasetWarning, stacklevel=3)


def warn_shared_frames(root: Path, splits: dict) -> None:
    """One :class:`DatasetWarning` per split (val, test) whose frames name training images (the same file): they are
    scored as novel views though trained on (battery 9: without a word)."""
    import warnings

    from .base import DatasetWarning

    trained = {}
    for v in splits.get("train", []):
        trained.setdefault(Path(v.path).resolve(), v.name)
    for s in ("val", "test"):
        shared = [(v.name, trained[p]) for v in splits.get(s, []) if (p := Path(v.path).resolve()) in trained]
        if shared:
            name, was = shared[0]
            same = name if name == was else f"{name}, the training frame {was}"
            warnings.warn(f"{root}: {len(shared)} of the {len(splits[s])} {s} frames "
                          f"{'is a training image' if len(shared) == 1 else 'are training images'} too, the same file "
                          f"(e.g. {same}): scored as novel views though trained on, the {s} metrics overstate; give "
                          f"the {s} split images of its own", DatasetWarning, stacklevel=3)


def load_nerf(root, downscale: int = 1, split_holdout: int | None = 8) -> Dataset:
    """A NeRF-synthetic folder: ``transforms_train.json`` (required), ``transforms_val.json`` and
    ``transforms_test.json`` (optional; without a test file, the LLFF hold-out of
    :func:`~triplet_cl.datasets.base.holdout_split` makes one from the training frames)."""
    root = Path(root)
    if root.is_file():
        raise DatasetError(root, f"is a file; expected the dataset folder (the one holding transforms_train.json, "
                                 f"e.g. {root.parent})")
    if not root.is_dir():
        raise DatasetError(root, "dataset folder not found")
    if not (root / "transforms_train.json").is_file():
        raise DatasetError(root / "transforms_train.json", "file not found (a NeRF-synthetic dataset needs it)")
    splits, spaces = {}, set()
    for s in ("train", "val", "test"):
        p = root / f"transforms_{s}.json"
        if p.exists() and not p.is_file():  # a folder there was passed over: the hold-out replaced the test split
            raise DatasetError(p, "is a folder (or not a regular file); expected the split's JSON file")
        if p.is_symlink() and not p.exists():  # a dangling link (an unfetched git-annex / LFS file) or a loop
            raise DatasetError(p, "is a link to nothing (a dangling or looping symbolic link: an unfetched large "
                                  "file?); expected the split's JSON file")
        if p.is_file():
            splits[s], sp = load_transforms_split(p, s, downscale)
            spaces |= sp
    warn_shared_frames(root, splits)
    held_out = None
    if "test" not in splits:
        held = holdout_split(splits["train"], split_holdout)
        splits["train"], splits["test"] = held["train"], held["test"]
        held_out = split_holdout or None
    return Dataset(root, "nerf", splits, color_space=merge_color_spaces(root, spaces), downscale=downscale,
                   held_out=held_out)
