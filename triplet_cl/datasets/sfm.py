"""Cameras from a folder of photos (structure from motion with pycolmap) and undistortion of COLMAP models.

:func:`run_sfm` — ``triplet colmap IMAGES_DIR --out DATA``: SIFT features, exhaustive matching and
COLMAP's incremental mapper (pycolmap, CPU), then undistortion to PINHOLE cameras. ``DATA`` is a
standard COLMAP folder that :func:`~triplet_cl.datasets.load_dataset` reads::

    DATA/images/            the undistorted photos (what training reads)
    DATA/sparse/0/          cameras.bin (PINHOLE), images.bin, points3D.bin
    DATA/distorted/sparse/0 the model as solved (one SIMPLE_RADIAL camera by default)
    DATA/sfm.json           counts, timings, the solved camera, the unregistered photos

Everything is written into a temporary folder beside ``DATA`` and renamed at the end: an existing
``DATA`` is never touched (the command refuses it).

:func:`undistorted_model` — a COLMAP scene whose cameras distort (SIMPLE_RADIAL, RADIAL, OPENCV, the
fisheyes, …: COLMAP's defaults for phone photos) is undistorted once with pycolmap into a cache (see
:func:`cache_root`) and that PINHOLE copy is loaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import DatasetError, is_utf8, shown_text
from .images import IMAGE_EXTENSIONS

# the formats COLMAP's image reader (FreeImage) takes among ours
SFM_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")
REGISTER_HELP = ("what helps: more photos with more overlap (every part of the object in 3 or more photos, "
                 "10-20 degrees apart), a textured, static scene (no plain white object on a plain table, nothing "
                 "moving), sharp and evenly exposed photos, the same zoom for all")


def _pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise DatasetError("pycolmap", f"the pycolmap module is needed for structure from motion and undistortion "
                                       f"({exc}); install it with `pip install pycolmap`") from exc
    return pycolmap


def _quiet_colmap(pycolmap, verbose: bool, level: int = 3) -> None:
    """COLMAP logs every step to stderr (glog): only ``level`` and up unless ``verbose`` (3, fatal: structure from
    motion, whose failures, e.g. "Failed to create any sparse model", come with our own message saying what failed and
    what helps; 2, errors too: the undistortion of a dataset, where COLMAP reports and goes on)."""
    pycolmap.logging.minloglevel = 0 if verbose else level
    pycolmap.logging.stderrthreshold = 0 if verbose else level


# ---------------------------------------------------------------------------------------------- inputs


def list_photos(folder) -> list[Path]:
    """The image files directly inside ``folder`` (sorted by name); :class:`DatasetError` when the
    folder does not exist or holds none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "images folder not found")
    # "._IMG_0001.JPG" is the resource fork a Mac leaves beside each photo on FAT / exFAT / network drives (no image:
    # the whole folder was refused, battery 10); other hidden files are no photos either
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SFM_EXTENSIONS
                    and not p.name.startswith("."))
    bad = [p.name for p in photos if not is_utf8(p.name)]
    if bad:
        raise DatasetError(folder, f"{len(bad)} photo name(s) hold bytes that are not UTF-8 text (e.g. "
                                   f"{shown_text(bad[0])}): the image library cannot open them; rename them in UTF-8")
    if not photos:
        others = sorted(p.name for p in folder.iterdir())[:3]
        found = f"found {', '.join(others)}{', ...' if len(others) == 3 else ''}" if others else "the folder is empty"
        raise DatasetError(folder, f"no images (expected {', '.join(SFM_EXTENSIONS)} files directly in the "
                                   f"folder; {found})")
    _warn_left_out(folder)
    return photos


def _warn_left_out(folder: Path) -> None:
    """One :class:`DatasetWarning` each for photos that are not used although they look meant: links to a photo that
    lead nowhere, and photos in subfolders beside the folder's own (both were left out without a word, battery 10)."""
    import warnings

    from .base import DatasetWarning

    entries = sorted(folder.iterdir(), key=lambda e: e.name)
    dead = [e.name for e in entries if e.is_symlink() and not e.exists() and e.suffix.lower() in SFM_EXTENSIONS]
    if dead:
        warnings.warn(DatasetWarning(f"{folder}: {len(dead)} photo link(s) lead nowhere and are left out (e.g. "
                                     f"{shown_text(dead[0])})"), stacklevel=3)
    nested = [e.name for e in entries if e.is_dir() and not e.name.startswith(".") and _has_photos(e)]
    if nested:
        shown = ", ".join(map(shown_text, nested[:3]))
        warnings.warn(DatasetWarning(f"{folder}: the photos in the subfolder(s) {shown}"
                                     f"{' ...' if len(nested) > 3 else ''} are not used (only the folder's own photos "
                                     "are): move them up to use them"), stacklevel=3)


def _has_photos(folder: Path) -> bool:
    return folder.is_dir() and any(p.is_file() and p.suffix.lower() in SFM_EXTENSIONS and not p.name.startswith(".")
                                   for p in folder.iterdir())


def photo_headers(photos) -> dict[Path, tuple[int, int, int]]:
    """``{path: (width, height, EXIF orientation)}`` read from the files' headers (OpenImageIO), each file opened
    once."""
    import OpenImageIO as oiio

    out = {}
    for p in photos:
        inp = oiio.ImageInput.open(str(p))
        if inp is None:
            raise DatasetError(p, f"cannot read the image: {oiio.geterror() or 'unknown format'}")
        try:
            spec = inp.spec()
            out[p] = (int(spec.width), int(spec.height), int(spec.get_int_attribute("Orientation", 1)))
        finally:
            inp.close()
    return out


def photo_sizes(photos) -> dict[Path, tuple[int, int]]:
    """``{path: (width, height)}`` read from the files' headers (:func:`photo_headers`)."""
    return {p: (w, h) for p, (w, h, _) in photo_headers(photos).items()}


def warn_exif_orientation(headers: dict) -> int:
    """A :class:`DatasetWarning` when photos carry an EXIF orientation other than 1 (a phone's portrait shot: viewers
    show the stored pixels turned): COLMAP solves on the stored pixels and ``train`` reads the same pixels, so the
    cameras fit them, but the whole capture is then worked as stored, not as viewers show it (battery 10: solved
    without a word). ``headers``: :func:`photo_headers`'s. Returns how many photos carry one."""
    from .images import EXIF_ORIENTATIONS

    photos = list(headers)
    turned = [(p.name, o) for p, (_, _, o) in headers.items() if o in EXIF_ORIENTATIONS]
    if turned:
        import warnings

        from .base import DatasetWarning

        name, o = turned[0]
        warnings.warn(DatasetWarning(
            f"{len(turned)} of the {len(photos)} photos carry an EXIF orientation ({name}: {o}, shown "
            f"{EXIF_ORIENTATIONS[o]} by image viewers): structure from motion solves on the pixels as stored, and "
            "`triplet train` reads the same pixels, so the cameras fit them; the renders and the mesh are those of the "
            "stored pixels. To work with the photos as viewers show them, rotate the files themselves first (e.g. "
            "exiftran -ai or mogrify -auto-orient)"), stacklevel=3)
    return len(turned)


def check_one_size(sizes: dict[Path, tuple[int, int]], folder) -> tuple[int, int]:
    """The one size of the photos; :class:`DatasetError` listing the sizes found when they differ
    (one camera model is solved for all photos: one camera, one zoom, one orientation)."""
    count = Counter(sizes.values())
    if len(count) > 1:
        parts = []
        for (w, h), n in count.most_common():
            example = next(p.name for p, s in sizes.items() if s == (w, h))
            parts.append(f"{n} are {w}x{h} (e.g. {example})")
        raise DatasetError(folder, "the photos have different sizes: " + ", ".join(parts) + "; the photos must come "
                                   "from one camera at one size and orientation (rotate/resize them to one size, or "
                                   "keep only the photos of one size)")
    return next(iter(count))


# ---------------------------------------------------------------------------------------------- SfM


def run_sfm(images_dir, out_dir, *, camera_model: str = "SIMPLE_RADIAL", max_features: int = 1024,
            min_registered: float = 0.5, num_threads: int = -1, verbose: bool = False,
            progress: Callable[[str], None] | None = None) -> dict:
    """Solve the cameras of the photos in ``images_dir`` and write an undistorted COLMAP folder at
    ``out_dir`` (module docstring).

    Args:
        camera_model: COLMAP model of the one camera shared by all photos (SIMPLE_RADIAL: focal,
            principal point and one radial coefficient, COLMAP's default for phone photos).
        max_features: SIFT features per photo.
        min_registered: fail (:class:`DatasetError`) when fewer than this fraction of the photos
            register (at least 3 must, whatever the fraction).
        num_threads: threads of COLMAP's steps (-1: all cores).
        verbose: show COLMAP's own log.
        progress: called with one line per step (default: nothing).

    Returns:
        the summary also written to ``out_dir/sfm.json``.
    """
    say = progress or (lambda s: None)
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    if not 0 <= min_registered <= 1:
        raise ValueError(f"min_registered must lie in [0, 1], got {min_registered}")
    if max_features < 64:
        raise ValueError(f"max_features must be >= 64, got {max_features}")
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise DatasetError(out_dir, "already exists and is not empty; choose a new --out folder (nothing is "
                                    "overwritten)")
    if images_dir.is_dir() and not _has_photos(images_dir) and _has_photos(images_dir / "images"):
        images_dir = images_dir / "images"  # a capture folder with its photos in images/
    photos = list_photos(images_dir)
    if len(photos) < 3:
        raise DatasetError(images_dir, f"only {len(photos)} image(s); structure from motion needs at least 3 "
                                       "overlapping photos (20 or more around an object)")
    headers = photo_headers(photos)
    width, height = check_one_size({p: (w, h) for p, (w, h, _) in headers.items()}, images_dir)
    warn_exif_orientation(headers)
    warn_duplicate_photos(photos)
    pycolmap = _pycolmap()
    _quiet_colmap(pycolmap, verbose)
    made = [p for p in (out_dir.parent, *out_dir.parent.parents) if not p.exists()]  # removed again on a failure
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_dead_work_dirs(out_dir)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        (work / WORK_PID).write_text(str(os.getpid()))
        summary = _solve(pycolmap, photos, images_dir, work, camera_model, max_features, min_registered,
                         num_threads, say)
        summary.update({"images_dir": str(images_dir.resolve()), "width": width, "height": height})
        (work / "sfm.json").write_text(json.dumps(summary, indent=1) + "\n")
        (work / WORK_PID).unlink()
        work.chmod(0o777 & ~_umask())  # mkdtemp made it 0700: the dataset gets the user's usual mode (battery 9)
        if out_dir.exists():  # an empty folder (checked above)
            out_dir.rmdir()
        os.replace(work, out_dir)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        for p in made:  # the parents this call created (innermost first), if nothing else went there (battery 8)
            try:
                p.rmdir()
            except OSError:
                break
        raise
    return summary


def warn_duplicate_photos(photos) -> None:
    """A :class:`DatasetWarning` naming photos that are byte-for-byte copies of others: each copy registers at its
    original's pose and adds no view (battery 8: half the photos duplicated, all registered, nothing said)."""
    import warnings

    from .base import DatasetWarning

    seen, copies = {}, []
    for p in photos:
        h = hashlib.sha256(Path(p).read_bytes()).hexdigest()
        if h in seen:
            copies.append((Path(p).name, seen[h]))
        else:
            seen[h] = Path(p).name
    if copies:
        shown = ", ".join(f"{a} = {b}" for a, b in copies[:3]) + (", ..." if len(copies) > 3 else "")
        what = "is a byte-for-byte copy of another" if len(copies) == 1 else "are byte-for-byte copies of others"
        warnings.warn(DatasetWarning(f"{len(copies)} of the {len(photos)} photos {what} ({shown}): a copy adds no "
                                     "view of the object; remove the copies"), stacklevel=2)


WORK_PID = ".pid"  # the process writing a work folder (a folder whose process is gone is removed)


def remove_dead_work_dirs(out_dir) -> list[Path]:
    """Remove the work folders ``.<DATA>.tmp-*`` beside ``out_dir`` left by a ``triplet colmap`` that was
    killed (SIGKILL, power loss: SIGTERM and Ctrl-C clean up themselves): those whose recorded process no
    longer runs. A folder of a process still running (another ``colmap`` with the same ``--out``) stays."""
    out_dir = Path(out_dir)
    removed = []
    if not out_dir.parent.is_dir():
        return removed
    for p in out_dir.parent.glob(f".{out_dir.name}.tmp-*"):
        try:
            pid = int((p / WORK_PID).read_text().strip())
        except (OSError, ValueError):
            continue  # not ours, or being created this instant
        try:
            os.kill(pid, 0)
            continue  # still running
        except ProcessLookupError:
            pass
        except OSError:  # exists but belongs to someone else
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
    return removed


def _umask() -> int:
    """The process's umask, read from /proc where it can be (setting it to read it leaves a window for threads)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


HEARTBEAT_S = 20.0  # seconds between the progress lines of a long COLMAP call


@contextlib.contextmanager
def _heartbeat(say, what: str, done=None, total: int | None = None, every: float | None = None):
    """A progress line every ``every`` seconds while a COLMAP call that reports nothing runs (14 photos of 4000x3000
    were 240 s of silence in feature extraction, battery 10): the time so far and, with ``done``, how many of
    ``total`` items are finished."""
    stop = threading.Event()
    t0 = time.perf_counter()
    every = HEARTBEAT_S if every is None else every

    def beat():
        while not stop.wait(every):
            k = done() if done is not None else None
            count = f", {k} of {total} photos" if k is not None and total else ""
            try:
                say(f"  {what}: {time.perf_counter() - t0:.0f} s{count}")
            except (OSError, ValueError):  # stdout gone (a closed pipe): the main thread reports it, once
                return

    th = threading.Thread(target=beat, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join()


def _rows(db: Path, table: str, most: int | None = None) -> int | None:
    """Rows of ``table`` in the COLMAP database while COLMAP writes it, at most ``most`` (None when it cannot be read
    just then): a progress count only. Opened ``immutable``: SQLite then takes no lock at all. A reader's shared lock
    made COLMAP's next write fail with "database is locked", which COLMAP does not retry: a photo's features were
    lost (15 of 16 photos registered) or the process aborted (std::terminate), the test's 0.05 s heartbeat catching
    it about one run in two here. Without locks a read may see a write half done: a count off for a moment, or an
    error (None)."""
    import sqlite3

    try:
        # (as_uri escapes a '?' or '#' in the path: unescaped, SQLite opened, and made, the path cut there read-write)
        con = sqlite3.connect(Path(db).absolute().as_uri() + "?mode=ro&immutable=1", uri=True, timeout=0.1)
        try:
            k = int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
        finally:
            con.close()
    except (sqlite3.Error, TypeError, ValueError):
        return None
    return max(0, k if most is None else min(k, most))


def _solve(pycolmap, photos, images_dir: Path, work: Path, camera_model: str, max_features: int,
           min_registered: float, num_threads: int, say) -> dict:
    n = len(photos)
    names = [p.name for p in photos]
    db = work / "database.db"
    times = {}
    cpu0 = time.process_time()

    t = time.perf_counter()
    say(f"features: SIFT on {n} photos ...")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.sift.max_num_features = max_features
    with _heartbeat(say, "features", lambda: _rows(db, "keypoints", n), n):
        pycolmap.extract_features(db, images_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    times["features_s"] = time.perf_counter() - t

    t = time.perf_counter()
    say(f"matching: {n * (n - 1) // 2} pairs (exhaustive) ...")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    with _heartbeat(say, "matching"):
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    times["matching_s"] = time.perf_counter() - t

    t = time.perf_counter()
    say("mapping: incremental reconstruction ...")
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = num_threads
    registered = [0]

    def next_image():  # called per registration attempt, retries and later models included: a step count, not
        registered[0] += 1  # the photos registered ("registered 25 of 16 photos", battery 9)
        say(f"  mapping step {registered[0]} ({n} photos)")

    models = work / "distorted" / "sparse"
    models.mkdir(parents=True)
    recs = pycolmap.incremental_mapping(db, images_dir, models, options=mapping, next_image_callback=next_image)
    times["mapping_s"] = time.perf_counter() - t
    best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
    n_reg = best.num_reg_images() if best is not None else 0
    need = max(3, int(-(-min_registered * n // 1)))
    if n_reg < need:
        what = "no photo registered" if n_reg == 0 else f"only {n_reg} of {n} photos registered"
        raise DatasetError(images_dir, f"structure from motion failed: {what} (at least {need} needed; "
                                       f"{len(recs)} separate model(s) found); {REGISTER_HELP}")
    # keep only the largest model, as sparse/0
    for p in models.iterdir():
        shutil.rmtree(p)
    (models / "0").mkdir()
    best.write(models / "0")
    reg_names = {best.images[i].name for i in best.reg_image_ids()}
    missing = [nm for nm in names if nm not in reg_names]
    if missing:
        shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
        say(f"warning: {len(missing)} of {n} photos did not register and are left out ({shown}); {REGISTER_HELP}")

    t = time.perf_counter()
    say(f"undistortion: {n_reg} photos to PINHOLE ...")
    undistort_model(pycolmap, models / "0", images_dir, work)
    _undistort_alpha(pycolmap, models / "0", images_dir, work, sorted(reg_names))  # (photos cut out: their alpha)
    times["undistortion_s"] = time.perf_counter() - t
    db.unlink(missing_ok=True)
    cam = next(iter(best.cameras.values()))
    return {
        "photos": n, "registered": n_reg, "unregistered": missing, "models": len(recs),
        "points": best.num_points3D(), "mean_reprojection_error_px": float(best.compute_mean_reprojection_error()),
        "camera": {"model": cam.model.name, "width": cam.width, "height": cam.height,
                   "params": [float(x) for x in cam.params]},
        **times, "total_s": sum(times.values()), "cpu_s": time.process_time() - cpu0,
    }


# ---------------------------------------------------------------------------------------------- undistortion


def undistort_model(pycolmap, model_dir: Path, images_dir: Path, out: Path, image_names=()) -> None:
    """pycolmap's undistorter: ``out/images/`` (PINHOLE photos, cropped to valid pixels) and
    ``out/sparse/0/`` (the model with PINHOLE cameras); its other outputs are removed."""
    tmp = out / ".undistort"
    options = pycolmap.UndistortCameraOptions()
    options.blank_pixels = 0.0  # crop to the region every pixel of which is valid
    pycolmap.undistort_images(tmp, model_dir, images_dir, image_names=list(image_names), output_type="COLMAP",
                              undistort_options=options)
    (out / "sparse").mkdir(parents=True, exist_ok=True)
    os.replace(tmp / "images", out / "images")
    sparse = tmp / "sparse"
    if not (sparse / "cameras.bin").is_file() and (sparse / "0").is_dir():
        sparse = sparse / "0"
    os.replace(sparse, out / "sparse" / "0")
    shutil.rmtree(tmp, ignore_errors=True)


def _undistort_alpha(pycolmap, model_dir: Path, images_dir: Path, out: Path, names) -> None:
    """The photos' alpha through the same undistortion: pycolmap writes colour only (a battery's RGBA photos came out
    opaque, the black under alpha 0 trained as part of the object). Each photo with an alpha channel has it written
    as a grey image of the same name, undistorted with the same model (the same warp and crop), and put back as the
    fourth channel of its undistorted PNG (saved as PNG, whatever pycolmap's extension)."""
    from ..io import write_png
    from .images import read_image

    with_alpha = []
    for n in names:
        if Path(n).suffix.lower() in (".jpg", ".jpeg"):  # no alpha channel there: not decoded for nothing
            continue
        im = read_image(images_dir / n)
        if im.alpha is not None:
            if Path(n).suffix.lower() != ".png":
                raise DatasetError(images_dir / n, "has an alpha channel and the camera model a distortion: its "
                                                   "undistorted copy keeps the alpha only as a PNG; convert the "
                                                   "photos with alpha to PNG (or undistort them yourself)")
            with_alpha.append((n, im.alpha))
    if not with_alpha:
        return
    src, dst = out / ".alpha_src", out / ".alpha_out"
    for n, a in with_alpha:
        write_png(src / n, np.repeat(a[..., None], 3, axis=2))
    dst.mkdir(parents=True)
    undistort_model(pycolmap, model_dir, src, dst, [n for n, _ in with_alpha])
    for n, _ in with_alpha:
        rgb = read_image(out / "images" / n)
        alpha = read_image(dst / "images" / n).rgb[..., 0]
        if alpha.shape != rgb.rgb.shape[:2]:
            raise DatasetError(images_dir / n, f"its undistorted alpha is {alpha.shape[1]}x{alpha.shape[0]}, its "
                                               f"colour {rgb.rgb.shape[1]}x{rgb.rgb.shape[0]}")
        (out / "images" / n).unlink()
        write_png(out / "images" / n, rgb.rgb, alpha)
    shutil.rmtree(src, ignore_errors=True)
    shutil.rmtree(dst, ignore_errors=True)


def cache_root(root: Path | None = None) -> Path:
    """Where undistorted copies go: ``$TRIPLET_CACHE``, else the user's cache folder
    ``$XDG_CACHE_HOME/triplet_cl/`` (``~/.cache/triplet_cl/``) — never the dataset folder ``root``
    (triplet writes nothing into a dataset). ``root`` is unused (kept for callers of the old signature)."""
    env = os.environ.get("TRIPLET_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "triplet_cl"


LEGACY_CACHE = ".triplet_cache"  # ROOT/.triplet_cache/: where versions before 2026-11-24 put the copies


CACHE_VERSION = b"alpha"  # copies made before the photos' alpha was undistorted too are not reused


def _model_key(model_dir: Path, images_dir: Path, names, version: bytes = CACHE_VERSION) -> str:
    h = hashlib.sha256(version)
    for stem in ("cameras", "images", "points3D"):
        for ext in (".bin", ".txt"):
            p = model_dir / (stem + ext)
            if p.is_file():
                h.update(p.name.encode())
                h.update(p.read_bytes())
    for name in sorted(names):
        p = images_dir / name
        st = p.stat() if p.is_file() else None
        h.update(f"{name}:{st.st_size if st else -1}:{st.st_mtime_ns if st else -1}".encode())
    return h.hexdigest()[:16]


def undistorted_model(root: Path, model_dir: Path, images_dir: Path, cameras: dict, images: dict,
                      progress=None) -> Path:
    """A PINHOLE copy of a distorted COLMAP scene, made once (pycolmap) and cached by the content of
    the model files and the images' sizes/times: the cached scene folder (``images/``, ``sparse/0``).

    ``cameras`` / ``images``: the model as read (:func:`~triplet_cl.datasets.colmap.read_model`),
    the images restricted to those whose file exists. pycolmap is given a clean text copy of them
    without the 2D-3D tracks (it refuses models whose tracks are inconsistent, and undistortion does
    not need them); the sparse points are world coordinates, unchanged by undistortion, so the
    model's ``points3D`` file is copied as it is.
    """
    say = progress or (lambda s: None)
    names = [im.name for im in images.values()]
    key = _model_key(model_dir, images_dir, names)
    # made by an older version (before the cache moved out of the dataset, and before the alpha: its key unsalted):
    # read, never written
    legacy = Path(root) / LEGACY_CACHE / f"undistorted-{_model_key(model_dir, images_dir, names, b'')}"
    if (legacy / "sparse" / "0").is_dir() and (legacy / "images").is_dir():
        return legacy
    base = cache_root(root)
    if root is not None and base.resolve().is_relative_to(Path(root).resolve()):
        src = "$TRIPLET_CACHE" if os.environ.get("TRIPLET_CACHE") else "the user's cache folder"
        raise DatasetError(base, f"the undistortion cache ({src}) is inside the dataset folder {root}: triplet "
                                 "writes nothing into a dataset; set $TRIPLET_CACHE to a folder outside it")
    dest = base / f"undistorted-{key}"
    if (dest / "sparse" / "0").is_dir() and (dest / "images").is_dir():
        return dest
    pycolmap = _pycolmap()
    _quiet_colmap(pycolmap, False, level=2)
    try:
        base.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".undistorted-{key}.tmp-", dir=base))
    except OSError as exc:
        raise DatasetError(base, f"cannot create the undistortion cache: {exc} (set $TRIPLET_CACHE to a writable "
                                 "folder)") from exc
    try:
        src = _write_text_model(work / ".model", cameras, images)
        say(f"undistorting the {len(names)} images of {model_dir} (camera model "
            f"{', '.join(sorted({c.model for c in cameras.values()}))}) into {dest} (once) ...")
        try:
            undistort_model(pycolmap, src, images_dir, work, names)
            _undistort_alpha(pycolmap, src, images_dir, work, names)
        except DatasetError:
            raise
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError
            raise DatasetError(model_dir, f"pycolmap could not undistort the model: {exc}") from exc
        shutil.rmtree(src, ignore_errors=True)
        sparse = work / "sparse" / "0"
        for ext in (".bin", ".txt"):
            (sparse / f"points3D{ext}").unlink(missing_ok=True)
        for ext in (".bin", ".txt"):
            if (model_dir / f"points3D{ext}").is_file():
                shutil.copyfile(model_dir / f"points3D{ext}", sparse / f"points3D{ext}")
                break
        try:
            os.replace(work, dest)
        except OSError:  # made meanwhile by another process
            if not (dest / "sparse" / "0").is_dir():
                raise
            shutil.rmtree(work, ignore_errors=True)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return dest


def _write_text_model(folder: Path, cameras: dict, images: dict) -> Path:
    """``cameras.txt``, ``images.txt`` (no 2D points) and an empty ``points3D.txt``."""
    folder.mkdir(parents=True)
    used = {im.camera_id for im in images.values()}
    lines = [f"{c.id} {c.model} {c.width} {c.height} " + " ".join(repr(float(p)) for p in c.params)
             for c in cameras.values() if c.id in used]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = []
    for im in images.values():
        pose = " ".join(repr(float(v)) for v in (*im.qvec, *im.tvec))
        lines += [f"{im.id} {pose} {im.camera_id} {im.name}", ""]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("")
    return folder


__all__ = ["CAMERA_MODELS", "IMAGE_EXTENSIONS", "REGISTER_HELP", "SFM_EXTENSIONS", "cache_root", "check_one_size",
           "list_photos", "photo_headers", "photo_sizes", "remove_dead_work_dirs", "run_sfm", "undistort_model",
           "undistorted_model"]
