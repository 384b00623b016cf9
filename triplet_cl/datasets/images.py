"""Image reading through OpenImageIO, with straight alpha and area downscaling.

* PNG/TIFF/… with alpha are read with ``oiio:UnassociatedAlpha = 1`` so the colour comes back as
  stored (straight), not premultiplied by OIIO.
* OpenEXR stores colour premultiplied by alpha (associated), whatever that attribute says, and so does a TIFF
  that OIIO does not report as unassociated: their colour is divided by alpha where alpha > 0 (0 where it is 0),
  so every format comes back straight (:func:`read_image`'s ``unpremultiply``; an environment map keeps its
  stored colour).
* A multi-layer EXR (Blender's ``ViewLayer.Combined.R``, ``ViewLayer.AO.R``, ...) gives its photo by channel
  name (:func:`exr_channels`), not by position.
* Integer files (8/16-bit PNG, JPEG, …) come back as float32 in [0, 1] (sRGB-encoded values, as
  stored); float files (EXR, HDR) as float32 linear values. Nothing is converted.
* ``downscale = N`` averages N×N blocks (area filter). Rows/columns beyond a multiple of N are
  cropped off the right/bottom edge, so the pixel grid stays aligned and the intrinsics simply
  divide by N (:func:`downscale_camera`). With alpha the colour is averaged **premultiplied** and
  then un-premultiplied, so that compositing commutes with downscaling:
  ``composite(down(rgb, a), bg) == down(composite(rgb, a, bg))`` for any background.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..camera import Camera
from ..errors import DatasetError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".tif", ".tiff", ".webp", ".bmp")
_FLOAT_TYPES = ("half", "float", "double")


class Image(NamedTuple):
    """What :func:`read_image` returns: pixels after the downscale, the file's own size."""

    rgb: np.ndarray  # [h, w, 3] float32
    alpha: np.ndarray | None  # [h, w] float32
    color_space: str  # "srgb" or "linear"
    width: int  # of the file, before any downscale
    height: int
    orientation: int = 1  # the file's EXIF Orientation tag (1: as stored); the pixels are returned as stored


# EXIF Orientation values and how an image viewer shows the stored pixels (5-8 swap width and height)
EXIF_ORIENTATIONS = {2: "mirrored", 3: "rotated 180°", 4: "flipped upside down", 5: "transposed",
                     6: "rotated 90° clockwise", 7: "transversed", 8: "rotated 90° counter-clockwise"}


# downscale "auto": the smallest integer factor that brings the training photos' longer side to at most this many
# pixels (3D Gaussian Splatting's rule for large inputs: 1.6K). NeRF-synthetic's 800² and every dev scene load as they
# are; a phone's 4000x3000 photos train at 1333x1000 instead of being refused by the device budget (or taking hours)
AUTO_MAX_SIDE = 1600


def auto_factor(width: int, height: int, max_side: int = AUTO_MAX_SIDE) -> int:
    """The smallest integer ``f >= 1`` with ``max(width, height) / f <= max_side``."""
    return max(1, -(-max(int(width), int(height)) // int(max_side)))


def image_size(path) -> tuple[int, int]:
    """``(width, height)`` of an image file from its header (no pixels read); :class:`DatasetError` naming the file
    when it is missing or unreadable."""
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "image file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DatasetError(path, f"cannot read the image: {_one_line(oiio.geterror() or 'unknown format')}")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


class AutoDownscale:
    """``load_dataset(downscale="auto")``: the factor is :func:`auto_factor` of the first image :func:`load_views`
    reads (the first split's; every image of a split has one size), then used for every split. ``factor`` and
    ``size`` (that image's) stay None until then."""

    def __init__(self, max_side: int | None = None):
        self.max_side = int(AUTO_MAX_SIDE if max_side is None else max_side)
        self.factor: int | None = None
        self.size: tuple[int, int] | None = None

    def resolve(self, path, split: str = "train") -> int:
        """The factor, chosen from ``path`` (a split's first image) on the first call; a later split whose first
        image would have chosen a larger one loads at this factor with a :class:`DatasetWarning`."""
        if self.factor is None:
            self.size = image_size(path)
            self.factor = auto_factor(*self.size, self.max_side)
            return self.factor
        w, h = image_size(path)
        if auto_factor(w, h, self.max_side) > self.factor:
            import warnings

            from .base import DatasetWarning

            warnings.warn(f"{Path(path).parent}: the {split} images are {w}x{h}, larger than the {self.size[0]}x"
                          f"{self.size[1]} images that chose downscale {self.factor} (auto): they load at "
                          f"{w // self.factor}x{h // self.factor}; give --downscale to choose the factor",
                          DatasetWarning, stacklevel=3)
        return self.factor


NEGATIVE_TOLERANCE = 0.01  # linear images: values below -1 % of the brightest are an error, the rest clipped


def _oiio():
    try:
        import OpenImageIO as oiio
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise DatasetError("OpenImageIO", f"the OpenImageIO Python module is needed to read images ({exc})") from exc
    return oiio


_stderr_lock = threading.Lock()
_stderr_depth = 0


@contextlib.contextmanager
def _library_stderr():
    """The C libraries' own lines on stderr (libpng's "libpng error: ..." before a truncated PNG's exception) held
    back while images are read: passed on as they were when the reads succeed, dropped when one fails (its
    :class:`DatasetError` carries the library's message already, so the user sees one line). Re-entrant: the
    outermost call redirects the process's file descriptor 2, nested and worker-thread reads go through it."""
    global _stderr_depth
    with _stderr_lock:
        outer = _stderr_depth == 0
        _stderr_depth += 1
    saved = None
    if outer:
        with contextlib.suppress(OSError):  # no stderr at all (closed: `2>&-`, a daemon): nothing to hold back
            saved = os.dup(2)
    if saved is None:  # nested, or nothing to redirect
        try:
            yield
        finally:
            with _stderr_lock:
                _stderr_depth -= 1
        return
    failed = False
    with tempfile.TemporaryFile() as tmp:
        if sys.stderr is not None:
            sys.stderr.flush()
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        except BaseException:
            failed = True
            raise
        finally:
            if sys.stderr is not None:
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            with _stderr_lock:
                _stderr_depth -= 1
            if not failed:
                tmp.seek(0)
                held = tmp.read()
                if held:
                    os.write(2, held)


def exr_channels(path, names) -> tuple[list[int], int] | None:
    """The channels of an EXR's photo by name: ``([r, g, b], a)`` (``a`` -1 without alpha), or None for an EXR whose
    channels carry neither R/G/B names nor layers (the caller then goes by position).

    Plain ``R``, ``G``, ``B`` (and ``A``) when present; else the one layer (the name's prefix before its last ``.``,
    e.g. ``ViewLayer.Combined``) holding R, G and B; else, among several, the one named ``Combined`` (Blender's
    rendered image; ``ViewLayer.AO`` or ``ViewLayer.Normal`` sort before it, and taking the first three channels
    trained on the AO pass). :class:`DatasetError` naming the layers when none of these decides."""
    names = [str(n) for n in names]
    layers: dict[str, dict[str, int]] = {}
    for i, n in enumerate(names):
        prefix, _, last = n.rpartition(".")
        layers.setdefault(prefix, {}).setdefault(last.upper(), i)
    rgb_layers = [k for k, ch in layers.items() if all(c in ch for c in "RGB")]
    if "" in rgb_layers:
        chosen = ""
    elif len(rgb_layers) == 1:
        chosen = rgb_layers[0]
    else:
        combined = [k for k in rgb_layers if k.rpartition(".")[2].lower() == "combined"]
        if len(combined) == 1:
            chosen = combined[0]
        elif set(layers) == {""}:  # no layers, and no channel named R, G, B (X, Y, Z): by position, as before
            return None
        else:
            found = ", ".join(k or "(no layer)" for k in layers)
            raise DatasetError(path, "a multi-layer EXR without a single colour layer to read as the photo: found "
                                     f"the layers {found}, " + (f"{len(rgb_layers)} of them with R, G, B"
                                                                if rgb_layers else "none with R, G, B channels")
                                     + "; expected plain R, G, B channels, one layer with them, or one named "
                                       "'Combined': save the rendered image alone (or its Combined pass)")
    ch = layers[chosen]
    return [ch["R"], ch["G"], ch["B"]], ch.get("A", -1)


def read_image(path, downscale: int = 1, unpremultiply: bool = True) -> Image:
    """Read one image → :class:`Image` ``(rgb [h,w,3] float32, alpha [h,w] float32 or None,
    color_space, width, height)`` where ``h, w = H // downscale, W // downscale``.

    ``color_space`` is ``"linear"`` for float files (EXR, HDR) and ``"srgb"`` otherwise. One
    channel is grey, two are grey + alpha, three RGB, four RGBA; with more, the first three are
    colour and the spec's alpha channel (if any) is alpha — an EXR's by name (:func:`exr_channels`).
    Colour stored premultiplied (OpenEXR's convention; an associated-alpha TIFF) is divided by alpha
    where alpha > 0 and 0 where it is 0, so that ``rgb`` is straight for every format; ``unpremultiply``
    False keeps it as stored (an environment map: its stored colour is the radiance). Raises
    :class:`DatasetError` naming the file when it is missing, unreadable, or holds NaN/Inf.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "image file not found")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _library_stderr():
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            raise DatasetError(path, f"cannot read the image: {_one_line(oiio.geterror() or 'unknown format')}")
        try:
            spec = inp.spec()
            fmt = inp.format_name()
            orientation = int(spec.get_int_attribute("Orientation", 1))
            # colour stored premultiplied: an EXR by the format's convention, whatever the attribute says; a TIFF
            # unless OIIO reports its alpha unassociated (1: kept as stored, as for PNG, WebP, TGA). Other formats
            # with alpha store it straight (or one bit, GIF's) and are left alone
            associated = fmt == "openexr" or (
                fmt == "tiff" and spec.get_int_attribute("oiio:UnassociatedAlpha", 0) != 1)
            px = inp.read_image(0, 0, 0, spec.nchannels, "float")
            err = inp.geterror()
        finally:
            inp.close()
        if px is None or err:  # a truncated JPEG comes back filled in, with an error message
            raise DatasetError(path, f"cannot read the image: {_one_line(err or oiio.geterror() or 'read failed')}")
    window = (spec.x, spec.y, spec.width, spec.height)
    # EXR only: a PNG's oFFs offset (a crop without +repage) shows as a data window too, on a complete image
    if fmt == "openexr" and spec.full_width > 0 and spec.full_height > 0 and window != (
            spec.full_x, spec.full_y, spec.full_width, spec.full_height):
        # an EXR whose pixels cover part of its frame: the camera's intrinsics are the frame's, the pixels are not
        raise DatasetError(path, f"the image's data window ({spec.width}x{spec.height} at {spec.x},{spec.y}) is not "
                                 f"its display window ({spec.full_width}x{spec.full_height} at {spec.full_x},"
                                 f"{spec.full_y}): crop or pad it to the full frame")
    px = np.asarray(px, dtype=np.float32)
    if px.ndim == 2:
        px = px[:, :, None]
    if px.ndim != 3 or px.shape[0] < 1 or px.shape[1] < 1:
        raise DatasetError(path, f"unexpected pixel array of shape {list(px.shape)}")
    nc = px.shape[2]
    alpha = None
    if nc == 1:
        rgb = np.repeat(px, 3, axis=2)
    elif nc == 2:
        rgb, alpha = np.repeat(px[:, :, :1], 3, axis=2), px[:, :, 1]
    else:
        picked = exr_channels(path, spec.channelnames) if fmt == "openexr" else None
        if picked is not None:
            rgb, a_ch = px[:, :, picked[0]], picked[1]
        else:
            rgb = px[:, :, :3]
            # the header's alpha channel, where it names one the pixels have (a GIF's names channel 4 of 4)
            a_ch = spec.alpha_channel if 3 <= spec.alpha_channel < nc else (3 if nc == 4 else -1)
        if a_ch >= 0:
            alpha = px[:, :, a_ch]
    if not np.isfinite(rgb).all() or (alpha is not None and not np.isfinite(alpha).all()):
        raise DatasetError(path, "the image holds NaN or Inf values")
    color_space = "linear" if str(spec.format) in _FLOAT_TYPES else "srgb"
    if color_space == "linear":  # radiance is >= 0: a filter's ringing (a few 1e-3 below 0) is clipped, not more
        low = float(rgb.min()) if rgb.size else 0.0
        if low < -NEGATIVE_TOLERANCE * max(1.0, float(np.abs(rgb).max())):
            raise DatasetError(path, f"the image holds negative radiance (down to {low:.4g}): linear images must be "
                                     ">= 0 (a reconstruction filter's ringing of a few thousandths is clipped)")
        rgb = np.maximum(rgb, 0.0)
    if alpha is not None:
        alpha = np.clip(alpha, 0.0, 1.0)
        if unpremultiply and associated:  # straight colour, as the other formats give it (0 where alpha is 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                rgb = np.where(alpha[:, :, None] > 0, rgb / np.maximum(alpha, 1e-12)[:, :, None], 0.0)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    alpha = None if alpha is None else np.ascontiguousarray(alpha, dtype=np.float32)
    height, width = rgb.shape[:2]
    if downscale != 1:
        if height < downscale or width < downscale:
            raise DatasetError(path, f"image of {width}x{height} is smaller than downscale={downscale}")
        rgb, alpha = downscale_image(rgb, alpha, downscale)
    return Image(rgb, alpha, color_space, width, height, orientation if orientation in EXIF_ORIENTATIONS else 1)


def _one_line(message: str) -> str:
    """OpenImageIO's error text on one line (a truncated PNG gives three: the read error, libpng's, "PNG library
    error"), repeats dropped, so that the CLI's error stays one line."""
    parts = [p.strip() for p in str(message).splitlines() if p.strip()]
    return "; ".join(dict.fromkeys(parts)) or "read failed"


def _block_mean(a: np.ndarray, n: int) -> np.ndarray:
    h, w = a.shape[0] // n, a.shape[1] // n
    a = a[: h * n, : w * n]
    return a.reshape(h, n, w, n, *a.shape[2:]).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def downscale_image(rgb: np.ndarray, alpha: np.ndarray | None, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Average ``n × n`` blocks (cropping the remainder off the right/bottom edge).

    With alpha the colour is averaged premultiplied and then un-premultiplied (colour 0 where the
    averaged alpha is 0), so compositing over any background commutes with the downscale.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"downscale must be a positive integer, got {n}")
    if n == 1:
        return rgb, alpha
    if alpha is None:
        return _block_mean(rgb, n), None
    a = _block_mean(alpha, n)
    pre = _block_mean(rgb * alpha[:, :, None], n)
    with np.errstate(divide="ignore", invalid="ignore"):
        straight = np.where(a[:, :, None] > 0, pre / np.maximum(a, 1e-12)[:, :, None], 0.0)
    return np.ascontiguousarray(straight, dtype=np.float32), a


def downscale_camera(camera: Camera, n: int) -> Camera:
    """The camera of an image downscaled by :func:`downscale_image` (size ``W // n × H // n``)."""
    if n == 1:
        return camera
    return replace(camera, fx=camera.fx / n, fy=camera.fy / n, cx=camera.cx / n, cy=camera.cy / n,
                   width=camera.width // n, height=camera.height // n)


def find_image(base: Path) -> Path | None:
    """``base`` itself when it exists, else ``base`` + a known image extension (NeRF-synthetic's
    ``file_path`` often has none), else ``None``."""
    if base.is_file():
        return base
    for ext in IMAGE_EXTENSIONS:
        for e in (ext, ext.upper()):
            p = base.with_name(base.name + e)
            if p.is_file():
                return p
    return None


def not_a_file(base: Path) -> tuple[Path, str] | None:
    """What lies at ``base`` (or ``base`` + a known image extension) where :func:`find_image` found no file:
    ``(path, "a folder")``, ``(path, "not a regular file ...")`` (a device or a pipe), or None when nothing is there
    — a symbolic link that leads nowhere counts as missing (an unfetched file of a git-annex / DVC checkout: the
    frame is skipped with a warning, as COLMAP's loader does)."""
    for p in [base] + [base.with_name(base.name + e) for ext in IMAGE_EXTENSIONS for e in (ext, ext.upper())]:
        if p.is_dir():
            return p, "a folder"
        if p.exists():  # neither a file nor a folder: /dev/zero, a pipe, a socket
            return p, "not a regular file (a device, pipe or socket)"
    return None


def read_images(paths: list[Path], downscale: int = 1, workers: int | None = None):
    """:func:`read_image` over many files, in a thread pool (OpenImageIO decodes without the GIL)."""
    if not paths:
        return []
    workers = workers or min(8, os.cpu_count() or 1, len(paths))
    if workers <= 1 or len(paths) < 4:
        return [read_image(p, downscale) for p in paths]
    with _library_stderr(), ThreadPoolExecutor(max_workers=workers) as pool:  # (the workers' lines held with ours)
        return list(pool.map(lambda p: read_image(p, downscale), paths))


def load_views(records, downscale: int = 1, split: str = "train", stored_pixel_poses: bool = False):
    """Read the images of one split and build its views.

    ``records`` are ``(name, image_path, make_camera)`` with ``make_camera(width, height)`` →
    the full-resolution :class:`Camera` for an image of that size (it raises
    :class:`DatasetError` naming the metadata file on a bad camera). Every image of a split must
    have the same size. Returns ``(views, color_spaces)``.
    """
    from .base import View

    records = list(records)
    if isinstance(downscale, AutoDownscale):
        downscale = downscale.resolve(records[0][1], split) if records else (downscale.factor or 1)
    images = read_images([r[1] for r in records], downscale)
    views, spaces = [], set()
    first = None
    for (name, path, make_camera), img in zip(records, images, strict=True):
        if first is None:
            first = (path, img.width, img.height, img.orientation)
        elif (img.width, img.height) != first[1:3]:
            shown = ""
            sideways = [(who, o, w, h) for who, o, w, h in (("its", img.orientation, img.width, img.height),
                                                            (f"{first[0].name}'s", first[3], first[1], first[2]))
                        if o >= 5]  # a phone photo stored sideways: viewers show it at the other size
            if sideways:
                who, o, w, h = sideways[0]
                shown = (f" ({who} EXIF orientation {o} has viewers show it {EXIF_ORIENTATIONS[o]}, at {h}x{w}; "
                         "triplet reads the pixels as stored, as COLMAP and instant-ngp do: rotate the file itself)")
            raise DatasetError(path, f"image is {img.width}x{img.height} but {first[0].name} in the same {split} "
                                     f"split is {first[1]}x{first[2]}: every image of a split must have one size"
                                     + shown)
        cam = downscale_camera(make_camera(img.width, img.height), downscale)
        views.append(View(name, cam, img.rgb, img.alpha, path))
        spaces.add(img.color_space)
    turned = [(Path(r[1]).name, img.orientation) for r, img in zip(records, images, strict=True)
              if img.orientation != 1]
    if turned:  # the cameras must be those of the stored pixels: say so where a viewer shows something else
        import warnings

        from .base import DatasetWarning

        name, o = turned[0]
        head = (f"{Path(records[0][1]).parent}: {len(turned)} of {len(records)} {split} images carry an EXIF "
                f"orientation ({name}: {o}, shown {EXIF_ORIENTATIONS[o]} by image viewers); triplet reads the "
                "pixels as stored, as COLMAP and instant-ngp do")
        if stored_pixel_poses:  # COLMAP solved on the same stored pixels: nothing to do (battery 10)
            tail = (": COLMAP's cameras were solved on those pixels and fit them; the renders and the mesh are those "
                    "of the stored pixels, not of the photos as viewers show them")
        else:
            tail = (", so the cameras must be those of the stored pixels: if the poses were made for the photos as "
                    "viewers show them, rotate the files themselves (e.g. exiftran -ai or mogrify -auto-orient)")
        warnings.warn(head + tail, DatasetWarning, stacklevel=2)
    bare = [v for v in views if v.alpha is None]
    if bare and len(bare) < len(views):  # a mix: those views' background would be trained as the object
        import warnings

        from .base import DatasetWarning

        shown = ", ".join(Path(v.path).name for v in bare[:3]) + (", ..." if len(bare) > 3 else "")
        warnings.warn(f"{Path(bare[0].path).parent}: {len(bare)} of {len(views)} {split} images have no alpha channel "
                      f"({shown}) while the others have: their background is taken as part of the object (give every "
                      "image alpha, or none)", DatasetWarning, stacklevel=2)
    # images that show nothing: transparent everywhere, or black and opaque everywhere (battery 11: trained on and
    # scored without a word; a transparent test image raised the mean PSNR 12.2 -> 14.0 dB)
    empty = [v for v in views if v.alpha is not None and v.alpha.size and float(np.max(v.alpha)) <= 0.0]
    black = [v for v in views if (v.alpha is None or float(np.min(v.alpha)) >= 1.0) and v.rgb.size
             and float(np.max(v.rgb)) <= 0.0]
    for found, what in ((empty, "fully transparent (alpha 0 in every pixel: no object)"),
                        (black, "black and opaque in every pixel")):
        if found and len(found) < len(views):  # (every image so: the training views' check refuses it, named)
            import warnings

            from .base import DatasetWarning

            shown = ", ".join(Path(v.path).name for v in found[:3]) + (", ..." if len(found) > 3 else "")
            warnings.warn(f"{Path(found[0].path).parent}: {len(found)} of {len(views)} {split} images are {what} "
                          f"({shown}): a blank or failed render? they are {'scored' if split == 'test' else 'trained'} "
                          "as they are; remove them from the split if they are not meant", DatasetWarning,
                          stacklevel=2)
    return views, spaces
