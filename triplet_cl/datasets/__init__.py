"""Multi-view datasets: NeRF-synthetic, instant-ngp and COLMAP, into one :class:`Dataset` model.

>>> ds = load_dataset("scenes/spot", downscale=2, background="white")   # doctest: +SKIP
>>> view = ds.train[0]; view.camera, view.rgb.shape, view.alpha.shape    # doctest: +SKIP

Images are kept as stored (sRGB values in [0, 1] for 8/16-bit files, linear for EXR/HDR;
``Dataset.color_space``), with straight alpha kept apart so that the training loop composites the
background it wants (:func:`resolve_background`, :func:`composite_background`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DatasetError
from .base import (
    BACKGROUNDS,
    Dataset,
    DatasetWarning,
    View,
    composite_background,
    drop_opaque_alpha,
    holdout_split,
    resolve_background,
)
from .colmap import find_model, load_colmap, read_model
from .images import AUTO_MAX_SIDE, AutoDownscale, auto_factor, downscale_camera, downscale_image, read_image
from .nerf import load_nerf
from .ngp import load_ngp

FORMATS = ("nerf", "ngp", "colmap")
NERF_SPLIT_FILES = ("transforms_train.json", "transforms_val.json", "transforms_test.json")

__all__ = [
    "AUTO_MAX_SIDE",
    "BACKGROUNDS",
    "FORMATS",
    "AutoDownscale",
    "Dataset",
    "DatasetError",
    "DatasetWarning",
    "View",
    "composite_background",
    "auto_factor",
    "detect_format",
    "downscale_camera",
    "downscale_image",
    "find_model",
    "holdout_split",
    "load_colmap",
    "load_dataset",
    "load_nerf",
    "load_ngp",
    "read_image",
    "read_model",
    "resolve_background",
]


def detect_format(path) -> str:
    """``"nerf"`` (``transforms_train.json``), ``"ngp"`` (``transforms.json``, or a ``.json`` file
    given directly) or ``"colmap"`` (a sparse model in ``sparse/0/``, ``sparse/`` or the folder)."""
    path = Path(path)
    if path.is_file() and path.name.lower() in NERF_SPLIT_FILES:
        raise DatasetError(path, f"a NeRF-synthetic split file, not a dataset: give its folder {path.parent} "
                                 "(triplet reads transforms_train/_val/_test.json there together)")
    if path.is_file() and path.suffix.lower() == ".json":
        return "ngp"
    if not path.is_dir():
        raise DatasetError(path, "is a file, not a dataset folder" if path.exists() else "dataset folder not found")
    for name in ("transforms_train.json", "transforms.json"):
        if (path / name).exists() and not (path / name).is_file():
            raise DatasetError(path / name, "is a folder (or not a regular file); expected the JSON file")
        if (path / name).is_symlink() and not (path / name).exists():
            raise DatasetError(path / name, "is a link to nothing (a dangling or looping symbolic link: an unfetched "
                                            "large file?); expected the JSON file")
    if (path / "transforms_train.json").is_file():
        return "nerf"
    if (path / "transforms.json").is_file():
        return "ngp"
    if find_model(path) is not None:
        return "colmap"
    photos = _photo_folder(path)
    if photos is not None:
        raise DatasetError(path, f"a folder of photos without cameras ({photos}): solve the cameras first with "
                                 f"`triplet colmap {photos} --out DATA`, then `triplet train DATA --out RUN`")
    raise DatasetError(path, "cannot tell the dataset format: found neither transforms_train.json (NeRF-synthetic), "
                             "transforms.json (instant-ngp) nor a COLMAP model (cameras + images .bin/.txt in "
                             "sparse/0/, sparse/ or the folder itself)")


def _photo_folder(path: Path) -> Path | None:
    """``path`` or ``path/images`` when it directly holds photos (a capture without cameras)."""
    from .sfm import SFM_EXTENSIONS

    for folder in (path, path / "images"):
        if folder.is_dir() and any(p.suffix.lower() in SFM_EXTENSIONS for p in folder.iterdir() if p.is_file()):
            return folder
    return None


def load_dataset(path, format: str = "auto", downscale: int | str = 1, background="white",
                 split_holdout: int | None = 8) -> Dataset:
    """Load a dataset folder.

    Args:
        path: the dataset folder (or an instant-ngp ``transforms.json``).
        format: ``"auto"`` (:func:`detect_format`), ``"nerf"``, ``"ngp"`` or ``"colmap"``.
        downscale: integer factor; images are area-averaged (``N×N`` blocks) and intrinsics divided.
            ``"auto"``: the smallest factor that brings the first training image's longer side to at most
            :data:`~triplet_cl.datasets.images.AUTO_MAX_SIDE` (1600) pixels (1 for smaller photos); the factor chosen
            is the dataset's ``downscale``, the size it was chosen from its ``auto_downscale``.
        background: ``"white"``, ``"black"``, ``"random"`` or an RGB colour — recorded on the
            dataset as the default for :meth:`Dataset.targets` and the training loop (images keep
            their alpha; nothing is composited at load time).
        split_holdout: without a test split (COLMAP, instant-ngp, NeRF without
            ``transforms_test.json``) every ``split_holdout``-th view by name (index % N == 0) is a
            test view; 0/None keeps all views for training.
    """
    auto = None
    if isinstance(downscale, np.integer):
        downscale = int(downscale)
    if isinstance(downscale, str) and downscale == "auto":
        auto = downscale = AutoDownscale()
    elif isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise ValueError(f"downscale must be a positive integer or 'auto', got {downscale!r}")
    if split_holdout is not None and (isinstance(split_holdout, bool) or not isinstance(split_holdout, int)
                                      or split_holdout < 0 or split_holdout == 1):
        raise ValueError(f"split_holdout must be 0/None (no hold-out) or an integer >= 2, got {split_holdout!r}")
    resolve_background(background)  # validate early
    fmt = detect_format(path) if format == "auto" else format
    if fmt == "nerf":
        ds = load_nerf(path, downscale, split_holdout)
    elif fmt == "ngp":
        ds = load_ngp(path, downscale, split_holdout)
    elif fmt == "colmap":
        ds = load_colmap(path, downscale, split_holdout)
    else:
        raise ValueError(f"format must be 'auto' or one of {FORMATS}, got {format!r}")
    drop_opaque_alpha(ds)  # an RGBA export of ordinary photos: alpha 255 everywhere masks nothing
    ds.background = background
    if auto is not None:  # the factor the first image chose (1 for a dataset without images)
        ds.downscale = auto.factor or 1
        ds.auto_downscale = auto.size
    return ds
