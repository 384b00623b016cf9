"""The dataset model shared by every loader: views, splits, scene bounds and backgrounds.

Images are kept **as stored**: 8/16-bit files (PNG, JPEG) are sRGB-encoded values in [0, 1],
float files (EXR, HDR) are linear; :attr:`Dataset.color_space` says which ("srgb" or
"linear"). Training compares in that same space: the linear pipeline (``TrainConfig.color``) renders
linear radiance and, for "srgb" datasets, applies the sRGB transfer and the encoded-space compositing
of the targets (``ops/color.py``) before the loss; runs before it fitted the encoded values directly.

Straight (unassociated) alpha is kept apart from the colour: ``View.rgb`` is the un-premultiplied
colour and ``View.alpha`` the coverage, so the training loop can composite a different background
every iteration (:func:`resolve_background` + :func:`composite_background`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import DEFAULT_FAR, DEFAULT_NEAR, Camera
from ..errors import DatasetError

SPLITS = ("train", "val", "test")
BACKGROUNDS = ("white", "black", "random")


def render_files(views) -> list[str]:
    """The file name of each view's render (and relit image): its image's file name with ``.png``, or, where two of
    ``views`` share that name (a rig's ``cam0/0001`` and ``cam1/0001``), its path inside the dataset with ``__`` for
    ``/`` — one render never replaces another."""
    names = [str(v.name if hasattr(v, "name") else v) for v in views]
    base = [Path(n).name for n in names]
    shared = {b for b in base if base.count(b) > 1}
    return [f"{n.replace('/', '__') if b in shared else b}.png" for n, b in zip(names, base, strict=True)]


class DatasetWarning(UserWarning):
    """Something in a dataset was skipped (e.g. frames whose image file is missing)."""

# The scene extent (:meth:`Dataset.scene_extent`) at which the defaults given in world units were measured: every dev
# scene's cameras sit 3.2 from the object (extent 3.91-3.94). The cameras' near / far and the point lights' position
# learning rate (lights.relative_lr_scales) are scaled by extent / REFERENCE_EXTENT, so a capture in other units (a
# COLMAP reconstruction's arbitrary scale, a benchmark object ten times larger) trains as the same capture at the
# reference scale would (the object's own size, train.frame_radius, scales the random start and the mesh stage's
# Laplacian). Measured on spot_small scaled by 0.1 before this: soup 34.0 -> 31.9 dB (the light moving 10x too fast);
# by 1000 or 0.001: nothing drawn (bench/results/scale_units_pocl_2026-11-27.txt).
REFERENCE_EXTENT = 3.9


@dataclass(frozen=True, eq=False)
class View:
    """One photograph: its camera, its pixels and where it came from.

    Attributes:
        name: the image's name inside the dataset (relative path without extension for NeRF/ngp,
            the image name for COLMAP).
        camera: the :class:`~triplet_cl.camera.Camera` (internal OpenCV convention), matching the
            image size after any downscale.
        rgb: ``[H, W, 3]`` float32 colour, as stored (see the module docstring), un-premultiplied.
        alpha: ``[H, W]`` float32 coverage in [0, 1], or ``None`` for images without alpha.
        path: the image file.
    """

    name: str
    camera: Camera
    rgb: np.ndarray = field(repr=False)
    alpha: np.ndarray | None = field(repr=False, default=None)
    path: Path | None = None

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    def target(self, background="white") -> np.ndarray:
        """The image composited over ``background`` (a name or an RGB colour; see
        :func:`composite_background`), ``[H, W, 3]`` float32."""
        return composite_background(self.rgb, self.alpha, background)


@dataclass(eq=False)
class Dataset:
    """A multi-view dataset: views per split, plus the sparse points COLMAP reconstructed.

    Attributes:
        root: the folder it was loaded from.
        format: ``"nerf"``, ``"ngp"`` or ``"colmap"``.
        splits: ``{"train": [...], "val": [...], "test": [...]}`` (every key present, maybe empty).
        points: ``[P, 3]`` float32 sparse points (COLMAP), or ``None``.
        colors: ``[P, 3]`` float32 point colours in [0, 1] (COLMAP), or ``None``.
        color_space: ``"srgb"`` (8/16-bit images, values as stored) or ``"linear"`` (EXR/HDR).
        background: the background asked for at load time (``"white"``, ``"black"``, ``"random"``
            or an RGB colour) — the default for :meth:`targets` and for the training loop.
        downscale: the integer factor the images and intrinsics were reduced by.
        auto_downscale: with ``load_dataset(downscale="auto")``, the ``(width, height)`` of the image that chose
            the factor (None otherwise).
        held_out: N when the test split is the loader's hold-out (every N-th view by name, :func:`holdout_split`),
            None when the capture brought its own (or nothing was held out).
    """

    root: Path
    format: str
    splits: dict[str, list[View]]
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    color_space: str = "srgb"
    background: object = "white"
    downscale: int = 1
    auto_downscale: tuple[int, int] | None = None
    held_out: int | None = None

    def __post_init__(self):
        for s in SPLITS:
            self.splits.setdefault(s, [])
        # the cameras' depth range in the scene's units: the default (0.01, 1000) is world units at the reference
        # extent, so a capture in millimetres is not culled beyond 1000 nor one a hundredth the size before 0.01;
        # never narrower than the default (a forward-facing capture's cameras span little of what they see)
        if not self.train or any(v.camera is None for vs in self.splits.values() for v in vs):  # (test doubles)
            return
        with np.errstate(over="ignore", invalid="ignore"):  # absurd poses are refused later, with their names
            f = self.scene_extent() / REFERENCE_EXTENT
        if not (np.isfinite(f) and f > 0) or f == 1.0:
            return
        near, far = DEFAULT_NEAR * min(f, 1.0), DEFAULT_FAR * max(f, 1.0)
        for vs in self.splits.values():
            for i, v in enumerate(vs):
                if (v.camera.near, v.camera.far) == (DEFAULT_NEAR, DEFAULT_FAR):
                    vs[i] = dataclasses.replace(v, camera=dataclasses.replace(v.camera, near=near, far=far))

    # ---- access ---------------------------------------------------------------------------
    @property
    def train(self) -> list[View]:
        return self.splits["train"]

    @property
    def val(self) -> list[View]:
        return self.splits["val"]

    @property
    def test(self) -> list[View]:
        return self.splits["test"]

    def __getitem__(self, split: str) -> list[View]:
        if split not in self.splits:
            raise KeyError(f"no split {split!r}; the splits are {sorted(self.splits)}")
        return self.splits[split]

    def __len__(self) -> int:
        return sum(len(v) for v in self.splits.values())

    def cameras(self, split: str = "train") -> list[Camera]:
        return [v.camera for v in self[split]]

    @property
    def has_alpha(self) -> bool:
        return any(v.alpha is not None for vs in self.splits.values() for v in vs)

    def targets(self, split: str = "train", background=None, rng: np.random.Generator | None = None):
        """``[N, H, W, 3]`` float32 targets of a split composited over ``background`` (default: the
        dataset's). ``"random"`` draws one colour for the whole batch from ``rng``."""
        views = self[split]
        if not views:
            return np.zeros((0, 0, 0, 3), np.float32)
        bg = resolve_background(self.background if background is None else background, rng)
        return np.stack([v.target(bg) for v in views])

    # ---- scene bounds ---------------------------------------------------------------------
    def camera_centers(self, split: str = "train") -> np.ndarray:
        """``[N, 3]`` camera centres in world space."""
        views = self[split] or self.train
        return np.array([v.camera.center for v in views], dtype=np.float64).reshape(-1, 3)

    def scene_center(self, split: str = "train") -> np.ndarray:
        """The mean of the camera centres ``[3]`` (3DGS's ``getNerfppNorm`` translate, negated)."""
        c = self.camera_centers(split)
        return c.mean(axis=0) if len(c) else np.zeros(3)

    def scene_extent(self, split: str = "train") -> float:
        """1.1 × the largest distance of a camera centre from :meth:`scene_center` (3DGS's
        ``getNerfppNorm`` radius); 1.0 for a single camera."""
        c = self.camera_centers(split)
        if len(c) == 0:
            return 1.0
        r = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max()) * 1.1
        return r if r > 0 else 1.0

    def summary(self) -> str:
        parts = [f"{s}: {len(self.splits[s])}" for s in SPLITS if self.splits[s]]
        v = next((vs[0] for vs in self.splits.values() if vs), None)
        size = f", {v.width}x{v.height}" if v is not None else ""
        pts = f", {len(self.points)} points" if self.points is not None else ""
        return f"{self.format} dataset {self.root} ({', '.join(parts)}{size}, {self.color_space}{pts})"


# ---- backgrounds -------------------------------------------------------------------------------
def resolve_background(background, rng: np.random.Generator | None = None) -> np.ndarray:
    """A background spec → an RGB colour ``[3]`` float32.

    ``"white"`` → (1, 1, 1), ``"black"`` → (0, 0, 0), ``"random"`` → a uniform random colour
    drawn from ``rng`` (a ``numpy.random.Generator``; a fresh one when ``None``), a number → grey,
    three numbers → that colour. The training loop calls this once per iteration and gives the
    same colour to the renderer and to :func:`composite_background`.
    """
    if isinstance(background, str):
        b = background.lower()
        if b == "white":
            return np.ones(3, np.float32)
        if b == "black":
            return np.zeros(3, np.float32)
        if b == "random":
            rng = np.random.default_rng() if rng is None else rng
            return rng.random(3).astype(np.float32)
        raise ValueError(f"background must be one of {BACKGROUNDS} or an RGB colour, got {background!r}")
    c = np.asarray(background, dtype=np.float32).reshape(-1)
    if c.shape == (1,):
        c = np.repeat(c, 3)
    if c.shape != (3,) or not np.isfinite(c).all():
        raise ValueError(f"background colour must be 3 finite numbers, got {background!r}")
    return c


def composite_background(rgb: np.ndarray, alpha: np.ndarray | None, background) -> np.ndarray:
    """``rgb · alpha + background · (1 − alpha)`` → ``[H, W, 3]`` float32 (straight alpha in).

    ``background`` is ``"white"``, ``"black"`` or an RGB colour (``[3]``) — or a per-pixel image
    ``[H, W, 3]``. ``"random"`` is refused here: draw the colour with :func:`resolve_background`
    so that the renderer can use the same one. Without alpha the image is returned unchanged.
    """
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must have shape [H, W, 3], got {list(rgb.shape)}")
    if alpha is None:
        return rgb
    a = np.asarray(alpha, dtype=np.float32)
    if a.shape != rgb.shape[:2]:
        raise ValueError(f"alpha must have shape {list(rgb.shape[:2])}, got {list(a.shape)}")
    if isinstance(background, str) and background.lower() == "random":
        raise ValueError("composite_background needs a colour: draw it with resolve_background('random', rng) "
                         "and give the same colour to the renderer")
    if isinstance(background, str):
        bg = resolve_background(background)
    else:
        bg = np.asarray(background, dtype=np.float32)
        if bg.shape != rgb.shape:
            bg = resolve_background(bg)
    a = a[..., None]
    return (rgb * a + bg * (1.0 - a)).astype(np.float32, copy=False)


def merge_color_spaces(root, spaces: set[str]) -> str:
    """The one colour space of a dataset's images; :class:`DatasetError` when they mix."""
    if len(spaces) > 1:
        raise DatasetError(root, "the dataset mixes 8/16-bit (sRGB) and float (linear) images; "
                                 "convert them to one kind")
    return next(iter(spaces), "srgb")


def warn_missing(where, missing: Sequence[str], total: int, what: str) -> None:
    """One :class:`DatasetWarning` counting the ``missing`` image files of ``total`` ``what``s."""
    if missing:
        import warnings

        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        hint = ""
        if any("\\" in str(m) for m in missing):  # a Windows path: the backslash is part of a name here
            hint = "; their paths hold backslashes (Windows separators): write them with / instead"
        warnings.warn(f"{where}: skipped {len(missing)} of {total} {what} whose image file is missing ({shown}){hint}",
                      DatasetWarning, stacklevel=4)


# an alpha channel at or above this everywhere (255 in 8 bits, 65535 in 16) masks nothing
OPAQUE_ALPHA = 1.0 - 0.5 / 65535.0


def drop_opaque_alpha(ds: Dataset) -> bool:
    """Images whose alpha channel is fully opaque in every pixel of every image that has one (an RGBA export of
    ordinary photos) carry no object mask: their alpha is dropped (``View.alpha`` None), so the capture is trained
    as photos with their background in the picture (the automatic background and shell, the mesh's crop) instead of
    as an object cut out over white, and a :class:`DatasetWarning` says so. A dataset where any image is transparent
    anywhere keeps every alpha. Returns whether it dropped them."""
    views = [v for vs in ds.splits.values() for v in vs]
    with_alpha = [v for v in views if v.alpha is not None]
    if not with_alpha or any(float(np.min(v.alpha)) < OPAQUE_ALPHA for v in with_alpha if v.alpha.size):
        return False
    ds.splits = {k: [dataclasses.replace(v, alpha=None) for v in vs] for k, vs in ds.splits.items()}
    import warnings

    warnings.warn(f"{ds.root}: the alpha channel of every image ({len(with_alpha)} with one) is fully opaque, so it "
                  "masks nothing: the photos are trained as photos with their background (no alpha); cut the "
                  "object out (transparent background) to train it over a plain background instead",
                  DatasetWarning, stacklevel=3)
    return True


# ---- splits -------------------------------------------------------------------------------------
def holdout_split(views: Sequence[View], every: int | None) -> dict[str, list[View]]:
    """LLFF-style hold-out: views sorted by name, every ``every``-th one (index % every == 0) goes
    to ``test``, the rest to ``train``. ``every`` of 0/None keeps everything for training."""
    views = sorted(views, key=lambda v: v.name)
    if not every or every < 1:
        return {"train": list(views), "val": [], "test": []}
    if every == 1:
        raise ValueError("split_holdout=1 would leave no training view; use 0 to disable the hold-out")
    return {
        "train": [v for i, v in enumerate(views) if i % every != 0],
        "val": [],
        "test": [v for i, v in enumerate(views) if i % every == 0],
    }
