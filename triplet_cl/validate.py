"""Up-front validation of the command line: every option and path is checked here, before any
work or output, and a problem is a :class:`~triplet_cl.errors.UsageError` naming the option (or the
file), what was expected and what was found. The CLI calls :func:`validate_args` first thing.

Also: :func:`resume_config` (which options may change on ``--resume``), output-folder checks
(``--out`` a file, read-only, inside a dataset, over files triplet did not make), the memory
estimate of ``--init-points`` and :func:`os_error_message` (one line for an expected OS error).
"""

from __future__ import annotations

import errno
import math
import os
from dataclasses import replace
from pathlib import Path

from .errors import RunError, UsageError, is_utf8, shown_text

K_LIMIT = 1024  # ops.raster.K_LIMIT (not imported: validation must not load the OpenCL layers)
TSDF_BYTES_PER_VOXEL = 64  # mesh.extract.tsdf_fusion: float64 grid, float32 centres, 2 float32 + 3 int32 sums
TEXTURE_BYTES_PER_TEXEL = 128  # mesh.bake while baking: measured peak 113 B / texel (export of a 15k-face mesh, 4096²)
HOST_BYTES_PER_INIT_POINT = 2048  # measured peak ≈ 510 B/point while initialising; ×4 for training copies
# device memory of one training render (ops/raster.py, ops/blend.py): per pixel and fragment slot the K-strided
# scratch (entry int32 + depth float32) and, at worst every slot filled, the packed lists (face, entry, bary×2,
# depth, window): 8 + 24 bytes; per face, its 3 vertices' projected position, attributes and their adjoints (3 +
# up to 70 channels of float32, ×2), rounded up
DEVICE_BYTES_PER_FRAGMENT = 32
DEVICE_BYTES_PER_FACE = 2048
# the smallest image side: the evaluation's SSIM has an 11x11 window with "valid" padding (losses.SSIM_RADIUS 5;
# not imported: validation must not load the OpenCL layers); it also keeps the warm-up's 1/4 renders >= 2 pixels
MIN_IMAGE_SIDE = 11

# option -> (args attribute, kind, low, high, what it is); None bound = unbounded
_INT_OPTIONS = {
    "--iterations": ("iterations", 1, 100_000_000),
    "--seed": ("seed", 0, 2**32 - 1),
    "--sh-degree": ("sh_degree", 0, 8),
    "--faces-per-pixel": ("faces_per_pixel", 1, K_LIMIT),
    "--init-points": ("init_points", 1, None),
    "--max-faces": ("max_faces", 100, None),  # DensityConfig.min_faces is 100
    "--checkpoint-every": ("checkpoint_every", 0, None),
    "--keep-checkpoints": ("keep_checkpoints", 0, None),
    "--shadow-every": ("shadow_every", 1, None),
    "--light-phase": ("light_phase", 0, None),
    "--mesh-resolution": ("mesh_resolution", 16, 1024),  # mesh.extract.tsdf_fusion's range; memory checked too
    "--mesh-faces": ("mesh_faces", 100, 50_000_000),
    "--mesh-rounds": ("mesh_rounds", 1, 100),
    "--mesh-iterations": ("mesh_iterations", 0, 10_000_000),
    "--remesh-every": ("remesh_every", 0, None),
    "--mesh-light-phase": ("mesh_light_phase", 0, None),
    "--mesh-metallic-trial": ("mesh_metallic_trial", 0, 10_000_000),
    "--mesh-supersample": ("mesh_supersample", 1, 4),
    "--mesh-eval-supersample": ("mesh_eval_supersample", 1, 8),
    "--texture-size": ("texture_size", 16, 16384),
    "--max-features": ("max_features", 64, 1_000_000),  # triplet colmap
    "--threads": ("threads", -1, 4096),  # triplet colmap (-1: all cores)
    "--env-degree": ("env_degree", 0, 8),  # relight / eval --relight: SH degree of projected environment maps
    "--mesh-env-degree": ("mesh_env_degree", 0, 8),  # MeshConfig.env_degree: the mesh's SH environment
    "--mesh-env-degree-metal": ("mesh_env_degree_metal", 0, 8),  # MeshConfig.env_degree_metal: a metal's
    "--mesh-env-occlusion": ("mesh_env_occlusion", 0, 4),  # MeshConfig.env_occlusion: its occluded bands' degree
}
_MESH_OPTIONS = ("--mesh-method", "--mesh-resolution", "--mesh-faces", "--mesh-rounds", "--mesh-iterations",
                 "--mesh-light-phase", "--mesh-metallic-trial", "--mesh-ao", "--mesh-bounce", "--mesh-light-fit",
                 "--remesh-every", "--mesh-supersample", "--mesh-eval-supersample", "--texture-size", "--formats",
                 "--bbox", "--mesh-crop", "--mesh-env-degree", "--mesh-env-degree-metal", "--mesh-env-occlusion",
                 "--mesh-metal-f0", "--mesh-pixel-filter", "--mesh-laplacian", "--mesh-creases")
OUTPUT_FORMATS = ("glb", "obj", "ply")


def _attr(option: str) -> str:
    return option.lstrip("-").replace("-", "_")


def check_int(option: str, value, low: int | None, high: int | None) -> None:
    if value is None:
        return
    if low is not None and value < low or high is not None and value > high:
        if high is None:
            rng = f"an integer >= {low}"
        elif low is None:
            rng = f"an integer <= {high}"
        else:
            rng = f"an integer in [{low}, {high}]"
        raise UsageError(option, f"expected {rng}, found {value}")


def parse_int_or_auto(option: str, value, low: int, high: int, what: str = "an integer") -> int | str:
    """``"auto"`` (any case) or an integer in [``low``, ``high``]; anything else a :class:`UsageError` naming
    ``option`` ("expected {what} in [low, high] or auto")."""
    t = str(value).strip().lower()
    if t == "auto":
        return "auto"
    try:
        n = int(t)
    except ValueError:
        raise UsageError(option, f"expected {what} in [{low}, {high}] or auto, found {value!r}") from None
    check_int(option, n, low, high)
    return n


def parse_downscale(option: str, value) -> int | str:
    """``--downscale``: ``"auto"`` or an integer factor in [1, 64]."""
    return parse_int_or_auto(option, value, 1, 64)


def parse_background_shell(option: str, value) -> int | str:
    """``--background-shell``: ``"auto"`` or a number of triangles in [0, 10 000 000]."""
    return parse_int_or_auto(option, value, 0, 10_000_000, "a number of triangles")


def parse_formats(option: str, text: str | None) -> tuple | None:
    """``"glb,obj"`` → ``("glb", "obj")``; unknown or empty names refused naming ``option``."""
    if text is None:
        return None
    fmts = tuple(x.strip().lower() for x in text.split(","))
    bad = [f for f in fmts if f not in OUTPUT_FORMATS]  # an empty item too ("glb," or "glb,,obj"), as --lights
    if bad or not fmts:
        raise UsageError(option, f"expected a comma-separated list of {', '.join(OUTPUT_FORMATS)}, found {text!r}")
    return tuple(dict.fromkeys(fmts))


def _check_options(args) -> None:
    for option, (attr, low, high) in _INT_OPTIONS.items():
        check_int(option, getattr(args, attr, None), low, high)
    # every command's --formats before any work (extract refused "glb," only after the device had started, export
    # took it); and the deprecated --format given beside it no longer silently wins
    if getattr(args, "formats", None) is not None:
        parse_formats("--formats", args.formats)
    alias = getattr(args, "_deprecated_alias", None)  # (the old spelling, its dest, the new spelling)
    if alias is not None and getattr(args, "_given_" + alias[1], False):
        raise UsageError(alias[0], f"is the deprecated spelling of {alias[2]}, which was given too: give {alias[2]} "
                                   "only")
    if getattr(args, "downscale", None) is not None:  # an integer factor or auto; the images must stay >= 11 px too
        args.downscale = parse_downscale("--downscale", args.downscale)  # (Trainer checks the dataset)
    if getattr(args, "background_shell", None) is not None:  # a number of triangles or auto (photos without alpha)
        args.background_shell = parse_background_shell("--background-shell", args.background_shell)
    dist = getattr(args, "light_distance", None)
    if dist is not None and not (math.isfinite(dist) and 0 < dist <= 1000):
        raise UsageError("--light-distance", f"expected a number of scene extents in (0, 1000], found {dist}")
    rmin = getattr(args, "light_min_distance", None)
    if rmin is not None and not (math.isfinite(rmin) and 0 <= rmin <= 1000):
        raise UsageError("--light-min-distance", f"expected a number of frame radii in [0, 1000], found {rmin}")
    sigma = getattr(args, "sigma", None)
    if sigma is not None and not (math.isfinite(sigma) and (sigma == 0 or 0.01 <= sigma <= 1000)):
        # (a battery's 1e-30 left the soup invisible to its gradients: nothing learned, exit 0)
        raise UsageError("--sigma", f"expected 0 (hard edges) or a sharpness in [0.01, 1000] (1/px), found {sigma}")
    ratio = getattr(args, "error_resplit_ratio", None)
    if ratio is not None and not (isinstance(ratio, str) and ratio.strip().lower() == "off"):
        try:
            value = float(ratio)
        except (TypeError, ValueError):
            value = math.nan
        if not (math.isfinite(value) and 0 < value <= 10):
            raise UsageError("--error-resplit-ratio", f"expected a number in (0, 10] (e.g. 0.9) or off, found {ratio}")
        args.error_resplit_ratio = value
    elif ratio is not None:
        args.error_resplit_ratio = "off"
    lights = getattr(args, "lights", None)
    if lights is not None:
        from .train import LIGHT_KINDS

        names = [x.strip() for x in lights.split(",") if x.strip()]
        bad = [x for x in names if x not in LIGHT_KINDS]
        if bad or not names:
            raise UsageError("--lights", f"lights must be a comma-separated mix of {', '.join(LIGHT_KINDS)}, found "
                                         f"{lights!r}")
        twice = sorted({x for x in names if names.count(x) > 1 and x != "point"})
        if twice:  # they start identical and get identical gradients: one light's worth, twice
            raise UsageError("--lights", f"{', '.join(twice)} given more than once ({lights!r}): only point lights "
                                         "may repeat (each starts at its own random position); the others would "
                                         "start identical and stay so")
    if getattr(args, "formats", None) is not None:
        parse_formats("--formats", args.formats)
    if getattr(args, "bbox", None) is not None:
        from .mesh.roi import parse_bbox

        try:
            parse_bbox(args.bbox)
        except ValueError as exc:
            raise UsageError("--bbox", str(exc)) from None
        if getattr(args, "mesh_crop", None) == "none":
            raise UsageError("--mesh-crop", f"none (keep everything) contradicts --bbox {args.bbox} (crop to that "
                                            "box): give one of them")
    f0 = getattr(args, "mesh_metal_f0", None)
    if f0 is not None and not (math.isfinite(f0) and 0 <= f0 <= 1):
        raise UsageError("--mesh-metal-f0", f"expected a metal's median F0 in [0, 1] (0: the F0 the soup left), "
                                            f"found {f0}")
    mr = getattr(args, "min_registered", None)
    if mr is not None and not (math.isfinite(mr) and 0 <= mr <= 1):
        raise UsageError("--min-registered", f"expected a fraction in [0, 1], found {mr}")
    init, max_faces = getattr(args, "init_points", None), getattr(args, "max_faces", None)
    if init is not None:
        budget = max_faces if max_faces is not None else 200_000
        if init > budget:
            raise UsageError("--init-points", f"{init} initial triangles exceed the face budget ({budget}, "
                                              "--max-faces): density control would prune them at once; give at "
                                              "most the budget, or raise --max-faces")
        check_memory_for_points(init)
    if max_faces is not None:
        check_memory_for_points(max_faces, "--max-faces")
    shell = getattr(args, "background_shell", None)
    if shell and shell != "auto":  # the shell's triangles join the initial soup: the same face budget and memory
        budget = max_faces if max_faces is not None else 200_000
        if shell > budget:
            raise UsageError("--background-shell", f"{shell} shell triangles exceed the face budget ({budget}, "
                                                   "--max-faces): density control would prune them at once; give "
                                                   "at most the budget (a few thousand take the sky), or raise "
                                                   "--max-faces")
        check_memory_for_points((init if init is not None else 20_000) + shell, "--background-shell")
    tex = getattr(args, "texture_size", None)
    if tex is not None and tex > 0:
        check_host_memory("--texture-size", f"baking a {tex}² texture", tex * tex * TEXTURE_BYTES_PER_TEXEL)
        if tex > MAX_VIEWER_TEXTURE:  # written without a word (battery 10)
            import warnings

            warnings.warn(f"--texture-size {tex}: many viewers (WebGL, mobile GPUs) load textures of at most "
                          f"{MAX_VIEWER_TEXTURE}², or fail; the asset is written as asked", stacklevel=2)
    res = getattr(args, "mesh_resolution", None)
    if res is not None:
        check_host_memory("--mesh-resolution", f"a {res}³ TSDF", res**3 * TSDF_BYTES_PER_VOXEL)


def check_host_memory(option: str, what: str, need: float) -> None:
    """Refuse ``option`` when ``what`` needs more than 80 % of the host memory available (unknown: accepted)."""
    avail = available_memory()
    if avail is not None and need > 0.8 * avail:
        raise UsageError(option, f"{what} would need about {need / 2**30:.1f} GiB of memory, more than 80 % of the "
                                 f"{avail / 2**30:.1f} GiB this machine has available")


def check_memory_for_points(n: int, option: str = "--init-points") -> None:
    """Refuse ``--init-points`` / ``--max-faces`` whose estimated host memory exceeds what is available."""
    check_host_memory(option, f"{n} triangles", n * HOST_BYTES_PER_INIT_POINT)


def device_budget(width: int, height: int, K: int, max_faces: int | None) -> tuple[int, int]:
    """``(total bytes, largest single buffer in bytes)`` a training render of ``width × height`` pixels with ``K``
    fragments per pixel and up to ``max_faces`` faces needs on the device, at worst (every fragment slot used)."""
    frags = int(width) * int(height) * int(K)
    faces = int(max_faces) if max_faces is not None else 0
    return frags * DEVICE_BYTES_PER_FRAGMENT + faces * DEVICE_BYTES_PER_FACE, frags * 8


def check_device_budget(info, renders, max_faces: int | None) -> None:
    """Refuse, before any work, a run whose renders cannot fit the device: ``info`` a
    :class:`~triplet_cl.device.DeviceInfo`; ``renders`` ``[(width, height, K, what)]`` the largest renders of the
    schedule (``what`` names the options that set them). Raises ``ValueError`` with the estimate, the device's
    limits and what to lower."""
    for width, height, K, what in renders:
        total, largest = device_budget(width, height, K, max_faces)
        fix = (f"lower {what}, reduce the images with --downscale, lower --max-faces, or choose a device with more "
               "memory (--device)")
        if largest > info.max_alloc_bytes:
            raise ValueError(f"a {width}x{height} render with K={K} fragments per pixel needs a buffer of "
                             f"{largest / 2**20:.0f} MiB, more than the largest allocation of {info.device_name!r} "
                             f"({info.max_alloc_bytes / 2**20:.0f} MiB): {fix}")
        if total > 0.9 * info.global_mem_bytes:
            faces = f" and {max_faces} faces" if max_faces is not None else ""
            raise ValueError(f"a {width}x{height} render with K={K} fragments per pixel{faces} needs up to "
                             f"{total / 2**30:.2f} GiB of device memory, more than 90 % of the "
                             f"{info.global_mem_bytes / 2**30:.2f} GiB {info.device_name!r} has: {fix}")


def check_image_sizes(ds, downscale: int = 1) -> None:
    """Every image of the dataset ``ds`` (after ``downscale``) is at least :data:`MIN_IMAGE_SIDE` pixels on each
    side: smaller ones used to train to the end and then fail in the evaluation's SSIM, after the run was written.
    A :class:`~triplet_cl.errors.UsageError` naming ``--downscale`` when it made them so small, else a
    :class:`~triplet_cl.errors.DatasetError` naming the image."""
    from .errors import DatasetError

    views = [(split, v) for split, vs in ds.splits.items() for v in vs]
    if not views:
        return
    split, small = min(views, key=lambda sv: min(sv[1].rgb.shape[:2]))
    h, w = small.rgb.shape[:2]
    if min(h, w) >= MIN_IMAGE_SIDE:
        return
    need = (f"images must be at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels (the {MIN_IMAGE_SIDE}x"
            f"{MIN_IMAGE_SIDE} window of the SSIM that evaluates the test views)")
    if downscale > 1 and ds.auto_downscale is not None:  # the factor "auto" chose, not one the user gave
        big = ds.auto_downscale
        raise UsageError("--downscale", f"auto chose {downscale} for {big[0]}x{big[1]}-pixel photos, which leaves "
                                        f"{w}x{h}-pixel {split} images ({small.name}); {need}: give --downscale 1 "
                                        "(or a smaller factor)")
    if downscale > 1:
        raise UsageError("--downscale", f"{downscale} leaves {w}x{h}-pixel {split} images ({small.name}); {need}: "
                                        "lower --downscale")
    raise DatasetError(small.path if small.path is not None else ds.root,
                       f"the {split} image {small.name} is {w}x{h} pixels; {need}")


MAX_CAMERA_COORD = 1e12  # a camera centre past this (a mistyped 1e300: the initial soup's range overflowed)
CAMERA_OUTLIER = 100.0  # a new run's training camera this many times farther from the cameras than 90 % of them


def check_training_views(ds, new_run: bool = True) -> None:
    """The training views can make a reconstruction, else a :class:`~triplet_cl.errors.DatasetError` naming the
    dataset: at least two views, their cameras not all at one place (no parallax: nothing to triangulate), and not
    every photo fully transparent (its alpha says there is no object) nor black wherever it shows something (every
    value exactly 0: no light reached the camera; a dark linear EXR of small radiances is a capture, not black)."""
    import numpy as np

    from .errors import DatasetError

    views = ds.train
    if len(views) < 2:
        n, every = len(ds.test), getattr(ds, "held_out", None)
        held = (f"; {n} more {'is' if n == 1 else 'are'} in the test split held out from them (every {every}th "
                "photo by name, the first among them: the capture has no test split of its own)") if n and every else ""
        raise DatasetError(ds.root, f"{len(views)} training view{'' if len(views) == 1 else 's'}{held}: a "
                                    "reconstruction needs photos from at least two places")
    c = ds.camera_centers("train")
    far = np.nonzero(~np.isfinite(c).all(axis=1) | (np.abs(c).max(axis=1) > MAX_CAMERA_COORD))[0]
    if len(far):
        raise DatasetError(ds.root, f"the training view {views[far[0]].name!r} has its camera at "
                                    f"{c[far[0]].tolist()}: expected coordinates within ±{MAX_CAMERA_COORD:g} (check "
                                    "its transform matrix's last column)")
    if new_run and len(c) >= 10:
        # each camera's distance to the cameras' coordinate-wise median, against the 90th percentile of those
        # distances: robust to a few wild frames (a least-squares look-at centre was pulled 25000 units by one camera
        # at 1e6) and to cameras that cluster (a video resting in one place: a median distance would be ~0)
        ref = np.median(c, axis=0)
        dist = np.linalg.norm(c - ref, axis=1)
        scale = float(np.percentile(dist, 90))
        out = np.nonzero(dist > CAMERA_OUTLIER * scale)[0] if scale > 0 else []
        if len(out):
            names = ", ".join(repr(views[i].name) for i in out[:3]) + (" ..." if len(out) > 3 else "")
            raise DatasetError(ds.root, f"the training camera(s) {names} stand {dist[out[0]] / scale:.3g}x farther "
                                        f"from the cameras' median position {np.round(ref, 6).tolist()} than 90 % of "
                                        f"the cameras (camera at {np.round(c[out[0]], 6).tolist()}): expected at most "
                                        f"{CAMERA_OUTLIER:g}x, a mistyped or wrongly scaled pose (the scene's extent "
                                        "and the initial soup follow the cameras); remove the frame or fix its "
                                        "transform matrix")
    spread = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max())
    if spread <= 1e-9 * max(1.0, float(np.abs(c).max())):
        raise DatasetError(ds.root, f"all {len(views)} training cameras are at the same position "
                                    f"{np.round(c[0], 6).tolist()}: a reconstruction needs photos from different "
                                    "places (check the transform matrices' last column)")
    if all(v.alpha is not None and not (v.alpha > 0).any() for v in views):
        raise DatasetError(ds.root, f"every one of the {len(views)} training photos is fully transparent (alpha 0 "
                                    "everywhere): there is no object to reconstruct")
    if all(float((v.rgb if v.alpha is None else v.rgb[v.alpha > 0]).max(initial=0.0)) <= 0.0 for v in views):
        raise DatasetError(ds.root, f"every one of the {len(views)} training photos is black where it shows anything "
                                    "(every colour value 0): there is nothing to reconstruct — check the exposure or "
                                    "the images' encoding")


def available_memory() -> int | None:
    """Available host memory in bytes (``MemAvailable`` of /proc/meminfo; None where unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


# ---- paths ---------------------------------------------------------------------------------------------
def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable_dir(path, option: str) -> None:
    """``path`` is (or can be created as) a writable folder: not a file, not under a file, not read-only."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise UsageError(option, f"{path} is a symbolic link that leads nowhere ({os.readlink(path)}): remove it or "
                                 "give another folder")
    for i, part in enumerate(path.parts):  # "new/../out": the OS cannot step out of a folder that is not there
        if part == ".." and not Path(*path.parts[:i]).is_dir():
            raise UsageError(option, f"{path}: '..' after {Path(*path.parts[:i])}, a folder that does not exist: "
                                     "give the path without it")
    if path.exists() and not path.is_dir():
        raise UsageError(option, f"{path} is a file, expected a folder")
    base = _nearest_existing(path)
    if not base.is_dir():
        raise UsageError(option, f"{path}: {base} is a file, so the folder cannot be created")
    if not os.access(base, os.W_OK | os.X_OK):
        ro = _read_only_fs(base)
        raise UsageError(option, f"{path}: {base} is not writable" + (" (read-only filesystem)" if ro else
                                                                       " (permission denied)"))
    if not path.exists():  # os.access says yes for root, and on /sys, /proc: try it (and take it back at once)
        made = []
        try:
            for p in reversed([q for q in (path.absolute(), *path.absolute().parents) if not q.exists()]):
                p.mkdir()
                made.append(p)
        except OSError as exc:
            raise UsageError(option, f"{path}: the folder cannot be created ({os_error_message(exc)})") from None
        finally:
            for p in reversed(made):
                try:
                    p.rmdir()
                except OSError:
                    pass


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def dataset_root_of(path) -> Path | None:
    """The dataset folder that contains ``path`` (a folder with transforms*.json or a COLMAP model)."""
    p = _nearest_existing(Path(path)).resolve()
    for folder in (p, *p.parents):
        if any((folder / n).is_file() for n in ("transforms_train.json", "transforms.json",
                                                 "transforms_test.json")):
            return folder
        for sub in ("sparse/0", "sparse", "."):
            d = folder / sub
            if (d / "cameras.txt").is_file() or (d / "cameras.bin").is_file():
                return folder
    return None


def check_not_in_dataset(path, option: str, dataset=None) -> None:
    """Never write into a dataset folder (its photos are the ground truth)."""
    p = Path(path).absolute()
    roots = [dataset_root_of(p)]
    if dataset is not None:
        roots.append(Path(dataset).resolve())
    for root in roots:
        if root is not None and (p.resolve() == root or root in p.resolve().parents):
            raise UsageError(option, f"{path} is inside the dataset folder {root}: triplet never writes into a "
                                     "dataset (it would replace the photos); choose another folder")


def check_not_run_internal(path, option: str) -> None:
    """Never write outputs into a run's ``checkpoints/`` folder (or below it): it is the run's own state,
    which ``--resume``, pruning and ``latest`` manage."""
    from .runs import CHECKPOINTS, is_run_dir

    p = Path(path).absolute().resolve()
    for folder in (p, *p.parents):
        if folder.name == CHECKPOINTS and is_run_dir(folder.parent):
            raise UsageError(option, f"{path} is inside the checkpoints folder of the run {folder.parent}: "
                                     "triplet writes nothing else there; choose another folder")


def check_not_other_run(path, run, option: str) -> None:
    """Outputs of a command on ``run`` go into that run or outside every run: never into another run's
    folder, whose own files (``lights.json``, ``mesh.*``, ``renders/``) they would replace."""
    from .runs import is_run_dir

    p = Path(path).absolute().resolve()
    mine = Path(run).absolute().resolve()
    for folder in (p, *p.parents):
        if folder == mine:
            return
        if is_run_dir(folder):
            raise UsageError(option, f"{path} is inside another run, {folder}: its own files (lights.json, mesh.*, "
                                     f"renders) would be replaced by those of {run}; choose a folder outside it")


def check_run_dir(run, option: str = "RUN", writable: bool = False, folders=()) -> dict:
    """A run directory with a readable config.json; ``writable``: results can be written into it, and into its own
    output ``folders`` that exist (:func:`check_run_folders_writable`)."""
    from .runs import read_run_config

    saved = read_run_config(run)
    if writable:
        check_writable_dir(run, option)
        check_run_folders_writable(run, option, folders)
    return saved


def check_run_folders_writable(run, option: str, folders=("checkpoints", "renders")) -> None:
    """The run's own ``folders`` a command writes into (``checkpoints``, ``renders``, ``relight``), where they exist,
    and the folders inside them, are writable: a read-only ``checkpoints/`` inside a writable run was met at the first
    checkpoint, after the training steps, the error naming a temporary file (battery 9)."""
    run = Path(run)
    for name in folders:
        top = run / name
        if not top.is_dir():
            continue
        for d in (top, *sorted(p for p in top.iterdir() if p.is_dir())):
            check_writable_dir(d, option)


def check_new_run_out(out, option: str, resume: bool, overwrite: bool, dataset=None) -> None:
    """``train --out``: refuse an existing run without --resume/--overwrite, a folder that is not a
    run, a file, a read-only place, a dataset folder, a new run inside another run, and ``--overwrite`` of a run
    that holds entries triplet did not write there or the dataset itself."""
    from .runs import is_run_dir

    out = Path(out)
    check_writable_dir(out, option)
    check_not_in_dataset(out, option, dataset)
    check_not_run_internal(out, option)
    for folder in ([] if resume else Path(out).absolute().resolve().parents):  # a run inside another run
        if is_run_dir(folder):
            raise UsageError(option, f"{out} is inside the run {folder}: a run goes in a folder of its own, outside "
                                     "every run (its --overwrite would otherwise delete the new one)")
    if resume and overwrite:
        raise UsageError("--overwrite", "cannot be combined with --resume")
    if resume:
        check_run_folders_writable(out, option)
        return
    from .runs import lock_run, stillborn_run_leftovers

    left = stillborn_run_leftovers(out)
    if left:  # a train killed while it created the run: what it left is triplet's, cleared for the new run
        lock_run(out, option)  # (not one that another train is creating right now)
        for p in left:
            if p.is_dir():
                p.rmdir()
            else:
                p.unlink()
    if out.is_dir() and any(out.iterdir()):
        if not is_run_dir(out):
            raise UsageError(option, f"{out} exists, is not empty and is not a triplet run: choose a new or empty "
                                     "folder (nothing there is touched)")
        if not overwrite:
            raise UsageError(option, f"{out} is an existing run: continue it with --resume, or replace it with "
                                     "--overwrite")
        from .runs import foreign_run_entries

        foreign = foreign_run_entries(out)
        if foreign:
            shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more" if len(foreign) > 4 else "")
            raise UsageError("--overwrite", f"{out} also holds {shown}, not written by triplet: --overwrite would "
                                            "delete them with the run; move them out first (nothing was touched)")
        if dataset is not None and Path(dataset).resolve().is_relative_to(out.resolve()):
            raise UsageError("--overwrite", f"the dataset {dataset} is inside the run {out} that --overwrite would "
                                            "delete")


def check_output_files(folder, names, option: str) -> None:
    """Refuse to replace files in ``folder`` that triplet did not make."""
    from .runs import foreign_files

    found = foreign_files(folder, names)
    if found:
        shown = ", ".join(found[:3]) + (f" and {len(found) - 3} more" if len(found) > 3 else "")
        raise UsageError(option, f"{folder} already holds {shown}, not written by triplet: choose another folder "
                                 "(triplet never overwrites files it did not make)")


def linked_within(run_dir, path) -> bool:
    """Whether ``path`` (inside ``run_dir``) or a folder between ``run_dir`` and it is a symbolic link."""
    run_dir, path = Path(run_dir), Path(path)
    try:
        rel = path.relative_to(run_dir)
    except ValueError:
        return False
    p = run_dir
    for part in rel.parts:
        p = p / part
        if p.is_symlink():
            return True
    return False


def check_render_out(trainer, split: str, out, option: str) -> None:
    """``render``: the split has views; ``out`` is not in the dataset and holds no file of the user."""
    from .errors import DatasetError

    views = trainer.ds[split]
    if not views:
        have = [s for s, v in trainer.ds.splits.items() if v]
        raise DatasetError(trainer.ds.root, f"the dataset has no {split!r} split (--split {split}); it has "
                                            f"{', '.join(have)}")
    check_not_in_dataset(out, option, trainer.ds.root)
    from .datasets.base import render_files

    names = render_files(views)
    taken = [n for n in names if (Path(out) / n).is_dir()]
    if taken:  # the run's own renders too: found only after rendering, under the temporary file's name
        raise UsageError(option, f"{Path(out) / taken[0]} is a folder where a render goes: move it away")
    own = trainer.run_dir / "renders" / split
    linked = linked_within(trainer.run_dir, own)
    if Path(out).resolve() != own.resolve() or linked:
        # a run's renders/SPLIT that is (or lies under) a link is the linked folder's, as --overwrite judges it:
        # `render RUN` replaced a user's r_0.png through such a link (battery 9)
        try:
            check_output_files(out, names, option)
        except UsageError:
            if not linked:
                raise
            from .runs import foreign_files

            found = foreign_files(out, names)
            raise UsageError(option, f"{own} leads (through a link) to {Path(out).resolve()}, which holds {found[0]}"
                                     f"{f' and {len(found) - 1} more' if len(found) > 1 else ''} with no record that "
                                     "triplet wrote them (a linked folder keeps a .triplet-output list once triplet "
                                     "writes there): move or delete them, or remove the link") from None
        from .runs import mark_output_dir

        mark_output_dir(out, names)  # the checks passed: these files are triplet's from now on


def mesh_output_names(formats) -> list[str]:
    """The files the mesh stage and ``export`` write into a folder for ``formats``."""
    names = ["lights.json", "envmap.exr"] + [f"mesh.{f}" for f in formats]
    if "obj" in formats:
        names += ["mesh.mtl", "mesh_basecolor.png", "mesh_roughness.png", "mesh_metallic.png", "mesh_specular.png"]
    return names


def check_mesh_outputs(run_dir, formats, test_views=None) -> None:
    """The mesh stage (``extract``, ``train --mesh-stage``) writes its result into the run: refuse before any work a
    folder or a special file where one of its files goes (a battery's ``mesh.glb`` folder failed only after the whole
    stage, naming a temporary file, with ``metrics.json`` already rewritten); with ``test_views`` (the views its test
    renders are of), also where those go (``renders/mesh/``)."""
    from .datasets.base import render_files

    run_dir = Path(run_dir)
    renders = [f"renders/mesh/{n}" for n in render_files(test_views)] if test_views else []
    check_output_slots(run_dir, ["mesh_stage.npz", "metrics.json", *mesh_output_names(formats), *renders],
                       "the mesh stage")
    from .runs import foreign_files

    found = foreign_files(run_dir, mesh_output_names(formats))
    if found:
        raise UsageError("RUN", f"{run_dir} holds {', '.join(found)}, not written by triplet: the mesh stage would "
                                "replace it; move it away first (nothing was touched)")


def check_output_slots(run_dir, names, who: str) -> None:
    """Before any work: each of ``names`` (paths inside ``run_dir`` that ``who`` writes) is a regular file or
    absent, and each folder on its way is a folder or absent (a battery's ``metrics.json`` folder was met only after
    a whole resumed training, the error naming a temporary file; a ``renders/mesh`` file after the whole mesh
    stage, as "File exists")."""
    run_dir = Path(run_dir)
    seen = set()
    for name in names:
        p = run_dir / name
        if (p.exists() or p.is_symlink()) and not p.is_file():
            what = "a folder" if p.is_dir() else "not a regular file"
            raise UsageError("RUN", f"{p} is {what}, where {who} writes its {name}: move it away")
        for q in list(Path(name).parents)[:-1]:
            d = run_dir / q
            if d in seen:
                continue
            seen.add(d)
            if (d.exists() or d.is_symlink()) and not d.is_dir():
                raise UsageError("RUN", f"{d} is a file, where {who} writes the folder {q}/: move it away")


def check_export_out(out, formats, option: str) -> None:
    """``export --out``: not a dataset folder, and no file there that triplet did not make."""
    check_not_in_dataset(out, option)
    names = mesh_output_names(formats)
    check_output_files(out, names, option)
    from .runs import is_run_dir, mark_output_dir

    if not is_run_dir(out):
        mark_output_dir(out, names)


# ---- the CLI entry -------------------------------------------------------------------------------------
MAX_VIEWER_TEXTURE = 8192  # the texture size WebGL 2 and most mobile GPUs guarantee (MAX_TEXTURE_SIZE)


def _check_utf8_paths(args) -> None:
    """Every string option is UTF-8: a path with other bytes (a Latin-1 folder name under a UTF-8 or C locale) reaches
    Python as surrogates, which OpenImageIO cannot take: `train` trained to the end and then failed writing its renders
    with a traceback (battery 10)."""
    positional = {"data": "DATA", "run": "RUN", "images": "IMAGES", "light_file": "--lights"}
    for dest, value in sorted(vars(args).items()):
        if not isinstance(value, str):
            continue
        if not is_utf8(value):
            raise UsageError(positional.get(dest, "--" + dest.replace("_", "-")),
                             f"{shown_text(value)} holds bytes that are not UTF-8 text (a name from another encoding): "
                             "the image library cannot open such a path; rename it in UTF-8")
        if dest == "out" and (value == "~" or value.startswith("~/")):  # quoted: the shell did not expand it, and a
            # folder named "~" was made in the current folder, printed as if it were the home folder (battery 10)
            raise UsageError("--out", f"{value} starts with '~', which the shell did not expand (quoted, or after "
                                      "'='): give the path unquoted or with $HOME, e.g. --out \"$HOME/...\"")


def validate_args(args) -> None:
    """Check every option of ``args`` (an argparse namespace of any command) before any work."""
    _check_utf8_paths(args)
    _check_options(args)
    _check_phases(args)
    dev = getattr(args, "device", None)
    if dev is not None and not str(dev).strip():  # ("" fell back to the default device, " " matched every name)
        raise UsageError("--device", f"expected P:D, a substring of a device's name, gpu or cpu (see `triplet "
                                     f"devices`), found {dev!r}; leave it out for the default device")
    cmd = getattr(args, "command", None)
    if cmd == "train":
        if not getattr(args, "mesh_stage", False):
            given = [o for o in _MESH_OPTIONS if getattr(args, _attr(o), None) is not None]
            if given:
                raise UsageError(given[0], "only applies with --mesh-stage (or use `triplet extract RUN`)")
        data = getattr(args, "data", None)
        if data is not None and getattr(args, "demo", False):
            raise UsageError("--demo", f"trains the dataset shipped with the package, and DATA {data} was given too: "
                                       "give one of them")
        if data is not None and not Path(data).exists():
            raise UsageError("DATA", f"{data}: dataset folder not found")
        out = getattr(args, "out", None) or ("runs/demo" if getattr(args, "demo", False) else None)
        if out:
            check_new_run_out(out, "--out", args.resume, getattr(args, "overwrite", False),
                              None if getattr(args, "demo", False) else data)
        # options that cannot act in the run asked for (a battery: each accepted and ignored, exit 0)
        if getattr(args, "shadows", None) == "off" and getattr(args, "shadow_every", None) is not None:
            raise UsageError("--shadow-every", "only applies with cast shadows (--shadows vertex)")
        if getattr(args, "light_phase", None) == 0 and getattr(args, "light_phase_lobes", None) is not None:
            raise UsageError("--light-phase-lobes", "only applies with a light phase (--light-phase > 0)")
        brdf = getattr(args, "brdf", None)
        if getattr(args, "blinn_phong_ka", None) is not None and brdf != "blinn-phong" and \
                not (brdf is None and getattr(args, "resume", False)):  # on --resume the run's BRDF decides
            raise UsageError("--blinn-phong-ka", f"only applies with --brdf blinn-phong (the BRDF is "
                                                 f"{brdf or 'cook-torrance, the default'})")
    elif cmd in ("render", "eval", "extract", "export", "relight"):
        if cmd == "eval" and not getattr(args, "relight", None):  # they only apply to the relit evaluation
            given = [o for o, a in (("--out", "out"), ("--renderer", "renderer"), ("--env-degree", "env_degree"),
                                    ("--shadows", "shadows")) if getattr(args, a, None) is not None]
            if given:
                raise UsageError(given[0], "only applies with --relight (the relit images, their renderer, shadows "
                                           "and the environment maps' SH degree); plain `eval` writes only "
                                           "metrics.json")
        writable = cmd in ("eval", "extract") or not getattr(args, "out", None)
        if cmd == "export":  # reads only mesh_stage.npz: a run directory, whatever its config.json holds
            if not (Path(args.run) / "config.json").is_file():
                from .runs import leftover_hint

                raise RunError(args.run, "is not a run directory (no config.json)" + leftover_hint(args.run))
            if writable:
                check_writable_dir(args.run, "RUN")
        else:
            saved = check_run_dir(args.run, "RUN", writable=writable,
                                  folders={"render": ("renders",), "extract": ("renders",),
                                           "relight": ("relight",)}.get(cmd, ()))
            check_run_dataset(args.run, saved["data"])  # read by every command but export: moved or deleted?
        if getattr(args, "out", None):
            rel = getattr(args, "relight", None) if cmd == "eval" else None
            if rel:  # the references are the user's: relit images never go among them
                refs = Path(rel)  # eval's --relight: the references' folder or its relight.json (no #set)
                refs = (refs.parent if refs.is_file() else refs).resolve()
                o = Path(args.out).resolve()
                if o == refs or refs in o.parents:
                    raise UsageError("--out", f"{args.out} is inside the relight references' folder {refs}: give a "
                                              "folder outside it")
            if cmd in ("render", "eval", "relight") and Path(args.out).resolve() == Path(args.run).resolve():
                raise UsageError("--out", f"{args.out} is the run folder itself: its images would lie among the run's "
                                          "own files; give a folder of their own (default: inside the run)")
            check_writable_dir(args.out, "--out")
            check_not_in_dataset(args.out, "--out")
            check_not_run_internal(args.out, "--out")
            check_not_other_run(args.out, args.run, "--out")
    elif cmd == "colmap":
        check_colmap_paths(args.images, args.out)


def _check_phases(args) -> None:
    """A light phase given longer than its run: the materials would never be fitted per vertex (an iteration count
    meant for a longer run). Equal is allowed: one material for the whole object, on purpose."""
    from .mesh.refine import MeshConfig
    from .train import DEMO_ITERATIONS, TrainConfig

    if getattr(args, "command", None) == "train" and not getattr(args, "resume", False):
        n = getattr(args, "light_phase", None)
        its = getattr(args, "iterations", None)
        if its is None:
            its = DEMO_ITERATIONS if getattr(args, "demo", False) else TrainConfig().iterations
        if n is not None and n > its:
            raise UsageError("--light-phase", f"{n} is longer than the run's {its} iterations: the materials would "
                                              f"never be fitted per vertex (give at most {its}; 0: no light phase)")
    n = getattr(args, "mesh_light_phase", None)
    its = getattr(args, "mesh_iterations", None)
    its = its if its is not None else MeshConfig().iterations
    if n is not None and n > its:
        raise UsageError("--mesh-light-phase", f"{n} is longer than a round's {its} refinement steps "
                                               "(--mesh-iterations): the mesh's materials would never be fitted per "
                                               f"vertex (give at most {its})")


def check_colmap_paths(images, out) -> None:
    """``colmap IMAGES --out DATA``: IMAGES a folder; DATA a new (or empty) writable folder outside IMAGES
    and outside any dataset (its work folder is made beside DATA, so that place must be clean too)."""
    images, out = Path(images), Path(out)
    if images.exists() and not images.is_dir():
        raise UsageError("IMAGES", f"{images} is a file, expected a folder of photos")
    if out.exists() and not out.is_dir():
        raise UsageError("--out", f"{out} is a file, expected a new folder")
    check_writable_dir(out, "--out")
    if images.is_dir():
        img = images.resolve()
        o = out.absolute().resolve()
        if o == img or img in o.parents:
            raise UsageError("--out", f"{out} is inside the photos folder {images}: choose a folder outside it "
                                      "(triplet never writes among the user's photos)")
    check_not_in_dataset(out, "--out")


class DeprecatedAlias:
    """An argparse action factory: ``--format`` kept as a deprecated spelling of ``new`` (warns)."""

    @staticmethod
    def action(new: str):
        import argparse
        import sys

        class _Alias(argparse.Action):
            def __call__(self, parser, namespace, values, option_string=None):
                print(f"triplet: warning: {option_string} is deprecated, use {new}", file=sys.stderr)
                setattr(namespace, self.dest, values)
                namespace._deprecated_alias = (option_string, self.dest, new)  # (both given: validate_args refuses)

        return _Alias

    @staticmethod
    def given():
        """The store action of the new spelling, noting that it was given (validate_args refuses both)."""
        import argparse

        class _Given(argparse.Action):
            def __call__(self, parser, namespace, values, option_string=None):
                setattr(namespace, self.dest, values)
                setattr(namespace, "_given_" + self.dest, True)

        return _Given


# ---- resume --------------------------------------------------------------------------------------------
def resume_config(args, saved_cfg, given_cfg):
    """The configuration of a resumed run and the notes on what changed.

    Options that fix what the checkpoint holds (seed, lights, BRDF, K, σ, ...) must be absent or
    equal to the saved value; ``--iterations``, ``--checkpoint-every`` and ``--keep-checkpoints``
    apply. Returns ``(cfg, notes)``."""
    from .train import RESUMABLE_FIELDS

    fixed = {"--seed": "seed", "--brdf": "brdf", "--lights": "lights", "--sh-degree": "sh_degree",
             "--faces-per-pixel": "faces_per_pixel", "--init-points": "init_points", "--background": "background",
             "--downscale": "downscale", "--sigma": "sigma", "--renderer": "renderer",
             "--background-shell": "background_shell", "--color": "color", "--shadows": "shadows",
             "--shadow-every": "shadow_every", "--light-phase": "material_tie_until",
             "--white-light": "white_light", "--light-phase-lobes": "light_phase_lobes",
             "--blinn-phong-ka": "blinn_phong_ka",
             "--light-distance": "light_distance", "--light-min-distance": "light_min_distance",
             "--sensor-clip": "sensor_clip"}
    for option, field in fixed.items():
        if getattr(args, _attr(option), None) is None:
            continue
        if option == "--background" and given_cfg.background == "auto":
            continue  # the run saved what "auto" resolved to when it started (white, or random with alpha)
        if option == "--background-shell" and given_cfg.background_shell == "auto":
            continue  # the run saved the number of triangles "auto" chose when it started
        if option == "--downscale" and given_cfg.downscale == "auto":
            continue  # the run saved the factor "auto" chose when it started
        if getattr(given_cfg, field) != getattr(saved_cfg, field):
            raise UsageError(option, f"cannot change on --resume (the run has {getattr(saved_cfg, field)!r}, "
                                     f"given {getattr(given_cfg, field)!r}); start a new run (another --out, or "
                                     "--overwrite) to change it")
    if getattr(args, "priors", None) is not None:
        from .priors import WEIGHT_FIELDS

        if any(getattr(given_cfg, k) != getattr(saved_cfg, k) for k in WEIGHT_FIELDS):
            had = {k: getattr(saved_cfg, k) for k in WEIGHT_FIELDS}
            raise UsageError("--priors", f"cannot change on --resume (the run has {had}, given --priors "
                                         f"{args.priors}); start a new run (another --out, or --overwrite)")
    if getattr(args, "error_resplit_ratio", None) is not None \
            and given_cfg.density.error_resplit_ratio != saved_cfg.density.error_resplit_ratio:
        had = saved_cfg.density.error_resplit_ratio
        had = "off" if had is None else had
        raise UsageError("--error-resplit-ratio", f"cannot change on --resume (the run has {had}, given "
                                                  f"{args.error_resplit_ratio}); start a new run (another --out, or "
                                                  "--overwrite) to change it")
    if getattr(args, "max_faces", None) is not None and given_cfg.density.max_faces != saved_cfg.density.max_faces:
        raise UsageError("--max-faces", f"cannot change on --resume (the run has {saved_cfg.density.max_faces}, "
                                        f"given {given_cfg.density.max_faces})")
    fmt = getattr(args, "data_format", None)
    if fmt not in (None, "auto"):
        raise UsageError("--data-format", "cannot change on --resume (the run's config.json fixes the dataset)")
    over, notes = {}, []
    for field in RESUMABLE_FIELDS:
        option = "--" + field.replace("_", "-")
        if getattr(args, field, None) is None:
            continue
        new, old = getattr(given_cfg, field), getattr(saved_cfg, field)
        over[field] = new
        if new != old:
            notes.append(f"{option} {new} (was {old})")
    return replace(saved_cfg, **over), notes


def resume_data(given, saved_data: str, run) -> tuple[str, list[str]]:
    """The dataset of a resumed run: the saved one; DATA given again must be the same folder, or
    replace a saved path that no longer exists (a moved dataset)."""
    if given is None:
        check_run_dataset(run, saved_data, resume=True)
        return saved_data, []
    if Path(saved_data).exists():
        if Path(given).resolve() != Path(saved_data).resolve():
            raise UsageError("DATA", f"{given} is not the run's dataset ({saved_data}, config.json of {run}); "
                                     "leave DATA out to resume, or start a new run for another dataset")
        return saved_data, []
    return str(given), [f"dataset {given} (config.json had {saved_data}, which no longer exists)"]


def check_run_dataset(run, data: str, resume: bool = False) -> None:
    """The dataset a run was trained on (``"data"`` of its config.json) still exists: render, eval, relight,
    extract and ``train --resume`` read it; a moved or deleted one is named with the run's config.json and
    what to do, before any work."""
    if Path(data).exists():
        return
    rel = "" if Path(data).is_absolute() else f" (a relative path, looked up from the current folder {Path.cwd()})"
    fix = ("give its new location as DATA (triplet train DATA --resume --out RUN)" if resume else
           "move it back, or write its new location into \"data\" of that file")
    raise RunError(Path(run) / "config.json", f"the run's dataset {data}{rel} does not exist: {fix}")


def check_resume_iterations(option: str, iterations: int, at: int) -> None:
    if iterations < at:
        raise UsageError(option, f"the run is already at iteration {at}; give --iterations >= {at}")


# ---- OS errors -----------------------------------------------------------------------------------------
_OS_HINTS = {
    errno.ENOSPC: "no space left on the device: free some space and run the command again",
    errno.EROFS: "read-only filesystem: choose a writable --out",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOTDIR: "a component of the path is a file, not a folder",
    errno.EISDIR: "is a folder, expected a file",
    errno.EDQUOT: "disk quota exceeded: free some space and resume",
    errno.ENOENT: "no such file or folder",
}


# `train`'s own advice for a full disk: its checkpoints are what fills it, and a run stopped before its first one has
# nothing to resume (battery 9: "resume" was advised, and --resume then refused)
_TRAIN_ENOSPC = ("no space left on the device: free some space (or keep fewer checkpoints: --keep-checkpoints), then "
                 "continue with --resume (a run stopped before its first checkpoint starts again with --overwrite)")


def os_error_message(exc: OSError, command: str | None = None) -> str:
    """One line for an expected OS error: the file and what went wrong (``command``: the ``triplet`` command that
    met it, for its own advice)."""
    what = _OS_HINTS.get(exc.errno, exc.strerror or str(exc))
    if exc.errno == errno.ENOSPC and command == "train":
        what = _TRAIN_ENOSPC
    name = exc.filename if exc.filename is not None else ""
    return f"{name}: {what}" if name else what


def device_memory_message(exc: BaseException) -> str | None:
    """One line for an OpenCL allocation failure (buffer too large, device or host out of memory);
    None for any other exception (a bug keeps its traceback)."""
    try:
        import pyopencl as cl
    except ImportError:  # pragma: no cover - pyopencl is a dependency
        return None
    if not isinstance(exc, cl.Error):
        return None
    codes = {cl.status_code.INVALID_BUFFER_SIZE, cl.status_code.MEM_OBJECT_ALLOCATION_FAILURE,
             cl.status_code.OUT_OF_RESOURCES, cl.status_code.OUT_OF_HOST_MEMORY}
    code = getattr(exc, "code", None)
    if code not in codes:
        return None
    return (f"the OpenCL device cannot allocate the buffers ({exc}): lower --faces-per-pixel or --max-faces, "
            "reduce the images with --downscale, or choose a device with more memory (--device)")
