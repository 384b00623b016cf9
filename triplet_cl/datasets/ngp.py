"""instant-ngp datasets: one ``transforms.json`` (``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` or
``camera_angle_x``, globally or per frame; OpenGL camera-to-world ``transform_matrix``).

Frames whose image is missing are skipped with one warning that counts them; non-zero distortion
coefficients (``k1``, ``k2``, ``k3``, ``k4``, ``p1``, ``p2``) and fisheye models are refused. There is no
split in the file: the LLFF hold-out (every ``split_holdout``-th view by name) becomes the test
split. instant-ngp's own ``scale``/``offset``/``aabb_scale`` are viewer settings and are ignored.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DatasetError
from .base import Dataset, holdout_split, merge_color_spaces
from .nerf import load_transforms_split


def load_ngp(path, downscale: int = 1, split_holdout: int | None = 8) -> Dataset:
    """Load ``path/transforms.json`` (or ``path`` itself when it is a JSON file)."""
    path = Path(path)
    json_path = path if path.suffix.lower() == ".json" else path / "transforms.json"
    if not json_path.parent.is_dir():
        raise DatasetError(json_path.parent, "dataset folder not found")
    if not json_path.is_file():
        raise DatasetError(json_path, "file not found (an instant-ngp dataset needs it)")
    views, spaces = load_transforms_split(json_path, "train", downscale)
    splits = holdout_split(views, split_holdout)
    return Dataset(json_path.parent, "ngp", splits, color_space=merge_color_spaces(json_path.parent, spaces),
                   downscale=downscale, held_out=split_holdout or None)
