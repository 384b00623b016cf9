"""Run directories: reading ``config.json`` and checkpoints defensively, pruning checkpoints,
removing temp files of killed writes, and knowing which output files triplet made.

Every problem is a :class:`~triplet_cl.errors.RunError` that names the file, what was expected and
what was found — never a ``KeyError`` / ``BadZipFile`` / ``EOFError`` traceback.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np

from .errors import RunError

CONFIG = "config.json"
CHECKPOINTS = "checkpoints"
RUN_OUTPUT_FOLDERS = ("renders", "relight")  # a run's own output folders (render, the mesh stage, relight)
OUTPUT_MARKER = ".triplet-output"  # manifest of the files triplet wrote into a render/export folder
_CKPT_RE = re.compile(r"^ckpt_(\d+)\.npz$")
# temp files of io.atomic_write_bytes / write_png (".<name>.<random>.tmp" / ".<stem>.<random>.png")
_TEMP_RE = re.compile(r"^\..+\.[A-Za-z0-9_]{6,}\.(tmp|png|exr)$")


def view_progress(items, desc: str, quiet: bool = False):
    """``items`` (views) with a progress bar on stderr when it is a terminal (``render``, ``eval``, ``relight`` were
    silent until the end: 40 views at 96² ray-traced took 21 s without a word, battery 9); nothing when ``quiet``
    or when stderr is not a terminal (logs and pipes stay clean)."""
    from tqdm import tqdm

    items = list(items)
    return tqdm(items, total=len(items), desc=desc, unit="view", leave=False, dynamic_ncols=True,
                disable=True if quiet else None)


def is_run_dir(path) -> bool:
    """A folder with a ``config.json`` that triplet wrote (an object with ``"train"``)."""
    p = Path(path) / CONFIG
    if not p.is_file():
        return False
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return True  # a damaged run is still a run: refuse to overwrite it, read_run_config names the problem
    return isinstance(d, dict) and "train" in d


def overwritten_leftovers(run_dir) -> list[Path]:
    """Old runs an interrupted ``--overwrite`` left beside ``run_dir`` (:func:`replacing_run` moves the old run into
    ``.NAME.overwritten.XXXX/NAME`` and puts it back on an error, but a killed process cannot): newest first."""
    run = Path(run_dir)
    try:
        found = [h / run.name for h in run.resolve().parent.glob(f".{run.name}.overwritten.*")
                 if (h / run.name / CONFIG).is_file()]
    except OSError:
        return []
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


def leftover_hint(run_dir) -> str:
    """``"; ..."``: where an interrupted ``--overwrite`` left the previous run and how to put it back, or ``""``."""
    left = overwritten_leftovers(run_dir)
    if not left:
        return ""
    import shlex

    return (f"; an interrupted --overwrite left the previous run in {left[0]}: put it back with `rm -r "
            f"{shlex.quote(str(run_dir))} && mv {shlex.quote(str(left[0]))} {shlex.quote(str(run_dir))}` (or delete "
            f"{left[0].parent} if it is not wanted)")


def read_run_config(run_dir) -> dict:
    """``config.json`` of a run as ``{"data": str, "format": str, "train": dict, ...}``, checked."""
    path = Path(run_dir) / CONFIG
    if not Path(run_dir).is_dir():
        raise RunError(run_dir, "is not a run directory (" + ("it is a file, not a folder)" if Path(run_dir).exists()
                                                              else "the folder does not exist)")
                       + leftover_hint(run_dir))
    if not path.is_file():
        raise RunError(run_dir, f"is not a run directory (no {CONFIG})" + leftover_hint(run_dir))
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RunError(path, f"cannot read the file: {exc}") from None
    if not text.strip():
        raise RunError(path, "the file is empty (expected the run's configuration as a JSON object)")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RunError(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg} "
                             "(truncated or edited by hand?)") from None
    except (RecursionError, ValueError) as exc:  # nested too deep; an integer past Python's 4300 digits
        why = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise RunError(path, f"unreadable JSON ({why}; edited by hand?)") from None
    if not isinstance(d, dict):
        raise RunError(path, f"expected a JSON object at the top level, found {type(d).__name__}")
    for key, typ in (("data", str), ("train", dict)):
        if key not in d:
            raise RunError(path, f"missing key {key!r}")
        if not isinstance(d[key], typ):
            raise RunError(path, f"{key!r} must be a {'string' if typ is str else 'JSON object'}, "
                                 f"found {type(d[key]).__name__}")
    if "format" in d and not isinstance(d["format"], str):
        raise RunError(path, f"'format' must be a string, found {type(d['format']).__name__}")
    from .datasets import FORMATS

    if d.get("format", "auto") not in ("auto", *FORMATS):
        raise RunError(path, f"'format' must be one of {', '.join(('auto', *FORMATS))}, found {d['format']!r}")
    return d


def config_from_saved(run_dir, saved: dict):
    """The :class:`~triplet_cl.train.TrainConfig` of ``saved["train"]``, every field type-checked."""
    from dataclasses import MISSING, fields

    from .density import DensityConfig
    from .train import TrainConfig

    path = Path(run_dir) / CONFIG
    t = saved["train"]

    def check(cls, d: dict, prefix: str):
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise RunError(path, f"unknown fields {[prefix + u for u in unknown]} in 'train'")
        for name, f in known.items():
            if name not in d:
                continue
            default = f.default if f.default is not MISSING else (f.default_factory() if f.default_factory
                                                                  is not MISSING else None)
            v = d[name]
            if v is None:
                ok = "None" in str(f.type)
            elif cls is TrainConfig and name in ("downscale", "background_shell"):  # what "auto" chose (or "auto")
                ok, default = (isinstance(v, int) and not isinstance(v, bool)) or v == "auto", 1
            elif default is None:
                ok = isinstance(v, (int, float)) and not isinstance(v, bool)
            elif isinstance(default, bool):
                ok = isinstance(v, bool)
            elif isinstance(default, int):
                ok = isinstance(v, int) and not isinstance(v, bool)
            elif isinstance(default, float):
                ok = isinstance(v, (int, float)) and not isinstance(v, bool)
            elif isinstance(default, str):
                ok = isinstance(v, str)
            elif isinstance(default, tuple):
                ok = isinstance(v, list)
            elif isinstance(default, DensityConfig):
                ok = isinstance(v, dict)
                if ok:
                    check(DensityConfig, v, prefix + name + ".")
            else:
                ok = True
            if not ok:
                raise RunError(path, f"'train'.{prefix}{name} has the wrong type: expected "
                                     f"{type(default).__name__}, found {type(v).__name__} ({v!r})")

    check(TrainConfig, t, "")
    if t.get("brdf") == "blinn_phong" and "lr_lights_mode" not in t:  # saved before issue 18's changes
        import warnings

        warnings.warn(f"{path}: this Blinn-Phong run was trained before its diffuse lobe became kd/pi (issue 18): its "
                      "kd was learned as albedo/pi, so under point / directional lights it now renders pi times darker "
                      "than it was trained (the environment term is unchanged); train it again", stacklevel=2)
    try:
        cfg = TrainConfig.from_dict(t)
        cfg.validate()
    except (TypeError, ValueError) as exc:
        raise RunError(path, f"invalid configuration: {exc}") from None
    return cfg


def read_metrics(run_dir, command: str = "eval") -> dict:
    """``metrics.json`` of a run as a dict (``{}`` when there is none), for a command that merges its section
    into it; a damaged file is a :class:`RunError` naming it (callers read it before any work)."""
    path = Path(run_dir) / "metrics.json"
    if not path.is_file():
        return {}
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as exc:  # JSON, UTF-8 and digit-limit errors are ValueErrors
        exc = "nested too deeply" if isinstance(exc, RecursionError) else exc
        raise RunError(path, f"damaged ({exc}); its other sections (\"mesh\", \"relight\", timings) cannot be "
                             f"kept: delete it to have {command} write a new one") from None
    if not isinstance(d, dict):
        raise RunError(path, f"damaged (expected a JSON object, found {type(d).__name__}); delete it to have "
                             f"{command} write a new one")
    return d


# ---- checkpoints ---------------------------------------------------------------------------------------
def read_checkpoint(path) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a checkpoint ``.npz``; a truncated, empty or foreign file is a RunError."""
    path = Path(path)
    if not path.is_file():
        raise RunError(path, "checkpoint not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise RunError(path, "not a checkpoint (expected an .npz archive, found a single array)")
            a = {k: z[k] for k in z.files}
    except RunError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        size = path.stat().st_size if path.exists() else 0
        what = "empty" if size == 0 else "truncated or not a triplet checkpoint"
        raise RunError(path, f"cannot read the checkpoint ({what}: {type(exc).__name__}: {exc}); resume from an "
                             "earlier checkpoint by editing checkpoints/latest, or start again with --overwrite"
                       ) from None
    if "meta" not in a:
        raise RunError(path, f"not a triplet checkpoint (no 'meta' entry; entries: {sorted(a)[:8]})")
    try:
        meta = json.loads(bytes(a.pop("meta")).decode())
    except (UnicodeDecodeError, ValueError) as exc:
        raise RunError(path, f"damaged checkpoint metadata: {exc}") from None
    if not isinstance(meta, dict):
        raise RunError(path, "damaged checkpoint metadata (not a JSON object)")
    missing = [k for k in ("V", "F", "material", "alpha") if k not in a] + \
              [k for k in ("it", "t", "order", "rng", "opt_hyper") if k not in meta]
    if missing:
        raise RunError(path, f"not a complete triplet checkpoint: missing {missing}")
    return a, meta


def list_checkpoints(run_dir) -> list[Path]:
    """The run's ``ckpt_*.npz``, oldest first."""
    folder = Path(run_dir) / CHECKPOINTS
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _CKPT_RE.match(p.name))]
    return [p for _, p in sorted(found)]


def prune_checkpoints(run_dir, keep: int, protect: Path | None = None) -> list[Path]:
    """Delete all but the newest ``keep`` checkpoints (0: keep all); never ``protect``."""
    if not keep or keep <= 0:
        return []
    removed = []
    for p in list_checkpoints(run_dir)[:-keep]:
        if protect is not None and p.name == Path(protect).name:
            continue
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def remove_stale_temp_files(folder, min_age_s: float = 120.0) -> list[Path]:
    """Remove temp files left in ``folder`` by writes that were killed (``kill -9`` mid-write).

    Only files older than ``min_age_s``: a write in flight in another process (an ``extract`` or
    ``render`` of the same run) is seconds old and is left alone."""
    import time

    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    now = time.time()
    for p in folder.iterdir():
        if p.is_file() and _TEMP_RE.match(p.name) and now - p.stat().st_mtime > min_age_s:
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


# ---- outputs the user made -----------------------------------------------------------------------------
def _manifest(folder: Path) -> set[str]:
    try:
        names = json.loads((folder / OUTPUT_MARKER).read_text(encoding="utf-8")).get("files", [])
        return {str(n) for n in names}
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return set()


def mark_output_dir(folder, names) -> None:
    """Record in ``folder/.triplet-output`` the file ``names`` triplet is about to write there (they may
    be replaced by triplet later; every other file of the folder stays the user's)."""
    from .io import write_json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    known = _manifest(folder) | {str(n) for n in names}
    write_json(folder / OUTPUT_MARKER, {"written_by": "triplet_cl", "files": sorted(known)})


def foreign_files(folder, names) -> list[str]:
    """Of ``names`` (files triplet would write into ``folder``), those that exist and that triplet
    did not make: not listed in the folder's ``.triplet-output`` manifest, and the folder is neither a run
    directory nor one of a run's own output folders (``RUN/renders/...``, ``RUN/relight/...``); in the run directory
    itself, the mesh files without triplet's signature (:func:`made_by_triplet`: a battery found ``extract`` and
    ``export`` replacing the user's ``mesh.obj`` there). Any other folder
    inside a run is the user's like any folder (a battery found ``render RUN --out RUN/my_stuff`` replacing the
    user's ``r_0.png`` there)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    resolved = folder.resolve()
    for root in [resolved, *list(resolved.parents)[:3]]:
        if is_run_dir(root):
            rel = resolved.relative_to(root).parts
            if not rel:  # the run itself: its files may be replaced, unless they are mesh files the user made
                return [n for n in names if made_by_triplet(resolved / n) is False]
            if rel[0] in RUN_OUTPUT_FOLDERS:  # where the run's commands write by default
                return []
            break
    mine = _manifest(folder)
    return [n for n in names if (folder / n).exists() and n not in mine]


# the mesh files whose writers sign them (the OBJ's / MTL's first comment, the PLY header's comment, the glTF's
# asset.generator all say "triplet_cl"): a file of that name without the signature is the user's
_SIGNED_SUFFIXES = frozenset({".obj", ".mtl", ".ply", ".glb", ".gltf"})
_SIGNATURE = b"triplet_cl"


_MAGIC = {".png": b"\x89PNG\r\n\x1a\n", ".exr": b"\x76\x2f\x31\x01"}  # the first bytes of every such file


def made_by_triplet(path) -> bool | None:
    """Whether the existing file ``path`` is one triplet wrote: for a signed kind (OBJ, MTL, PLY, glTF / GLB) its
    first 64 kB hold the signature; a PNG or EXR that is not one at all (its magic bytes) is not; None for a file of
    another kind or a real image (no way to tell) or no regular file."""
    p = Path(path)
    if p.suffix.lower() in _MAGIC and p.is_file():  # an image triplet writes (textures, envmap.exr): unsigned, but a
        # file that is not of that kind at all is not ours (battery 8: extract replaced the user's text file there)
        try:
            with open(p, "rb") as f:
                return None if f.read(len(_MAGIC[p.suffix.lower()])) == _MAGIC[p.suffix.lower()] else False
        except OSError:
            return False
    if p.suffix.lower() not in _SIGNED_SUFFIXES or not p.is_file():
        return None
    try:
        with open(p, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    return _SIGNATURE in head


# what triplet writes into a run folder (train, extract, export, eval, relight, render): ``--overwrite`` replaces a run
# only when it holds nothing else (a battery found the user's notes and a dataset copy inside a run deleted with it)
RUN_ENTRIES = frozenset({CONFIG, CHECKPOINTS, *RUN_OUTPUT_FOLDERS, "train.log", "metrics.json", "lights.json",
                         "triplets.ply", "mesh_stage.npz", "envmap.exr", OUTPUT_MARKER,
                         ".DS_Store", "Thumbs.db", "desktop.ini"})  # (and the file browsers' own)
_RUN_MESH_RE = re.compile(r"^mesh(_[a-z0-9]+)?\.(glb|gltf|obj|mtl|ply|png|bin)$")


_JUNK = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
_IMAGE_SUFFIXES = frozenset({".png", ".exr"})  # what triplet writes into renders/ and relight/


def _foreign_in_outputs(folder: Path, rel: str) -> list[str]:
    """Files under a run's own output folder (``renders/``, ``relight/``) that triplet did not write: not an image of
    the kinds it writes, not listed in their folder's manifest, not its temp files (paths relative to the run)."""
    out = []
    mine = _manifest(folder)
    for e in sorted(folder.iterdir(), key=lambda e: e.name):
        name = f"{rel}/{e.name}"
        if e.is_dir() and not e.is_symlink():
            out += _foreign_in_outputs(e, name)
        elif not (e.name in mine or e.name in _JUNK or e.name == OUTPUT_MARKER or _TEMP_RE.match(e.name)
                  or (e.is_file() and e.suffix.lower() in _IMAGE_SUFFIXES)):
            out.append(name)
    return out


_LOG_LINE_RE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} ")  # train.log's format (asctime first)


def _is_triplet_log(path: Path) -> bool:
    """Whether ``path`` reads as triplet's ``train.log``: every line in its ``asctime`` format (an empty one too)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = [ln for ln in f.read(1 << 20).splitlines() if ln.strip()]
    except OSError:
        return False
    return all(_LOG_LINE_RE.match(ln) for ln in lines)


def stillborn_run_leftovers(folder) -> list[Path] | None:
    """The files a ``train`` killed while creating its run left in ``folder`` (its ``train.log``, the temporary file
    of its ``config.json``, an empty ``checkpoints/``), when the folder holds nothing else and no ``config.json``;
    else None. A battery's SIGKILL there left a folder that no command would take: "not a triplet run" for a new
    run and for ``--overwrite``, "no config.json" for ``--resume``."""
    folder = Path(folder)
    if not folder.is_dir() or (folder / CONFIG).exists():
        return None
    found = []
    for e in folder.iterdir():
        if e.name == "train.log" and e.is_file() and not e.is_symlink():
            if not _is_triplet_log(e):  # a train.log of the user's: the folder is theirs
                return None
            found.append(e)
        elif _TEMP_RE.match(e.name) and e.is_file() and not e.is_symlink():
            found.append(e)
        elif e.name == CHECKPOINTS and e.is_dir() and not e.is_symlink() and not any(e.iterdir()):
            found.append(e)
        else:
            return None
    return found or None


def foreign_run_entries(run) -> list[str]:
    """The entries of the run folder ``run`` that triplet does not write there (sorted paths relative to the run):
    other names at its top level, mesh files without triplet's signature (:func:`made_by_triplet`), and inside its
    own folders other files than its checkpoints (``checkpoints/``) and images (``renders/``, ``relight/``): a
    battery found ``--overwrite`` deleting the user's notes kept in ``renders/test/`` and ``checkpoints/``."""
    run = Path(run)
    out = []
    for e in sorted(run.iterdir(), key=lambda e: e.name):
        if e.name not in RUN_ENTRIES and not _RUN_MESH_RE.match(e.name) and not _TEMP_RE.match(e.name):
            out.append(e.name)
        elif _RUN_MESH_RE.match(e.name) and made_by_triplet(e) is False:
            out.append(e.name)
        elif e.name == CHECKPOINTS and e.is_dir() and not e.is_symlink():
            out += [f"{CHECKPOINTS}/{c.name}" for c in sorted(e.iterdir(), key=lambda c: c.name)
                    if not (c.is_file() and (_CKPT_RE.match(c.name) or c.name == "latest"))
                    and c.name not in _JUNK and not _TEMP_RE.match(c.name)]
        elif e.name in RUN_OUTPUT_FOLDERS and e.is_dir() and not e.is_symlink():
            out += _foreign_in_outputs(e, e.name)
    return out


@contextlib.contextmanager
def replacing_run(out, overwrite: bool):
    """``--overwrite``: move the old run aside (into a new hidden folder beside it: never a folder of the user's),
    delete it when the block succeeds, put it back if not. ``out`` is resolved first (``--out .``, a link to a run:
    the run itself is replaced)."""
    out = Path(out).resolve()
    if not (overwrite and out.is_dir()):
        yield
        return
    import tempfile

    holder = Path(tempfile.mkdtemp(prefix=f".{out.name}.overwritten.", dir=out.parent))
    aside = holder / out.name
    os.replace(out, aside)
    try:
        yield
    except BaseException:
        if out.exists():
            shutil.rmtree(out, ignore_errors=True)
        os.replace(aside, out)
        shutil.rmtree(holder, ignore_errors=True)
        raise
    shutil.rmtree(holder, ignore_errors=True)


_HELD_LOCKS: list = []  # this process's run locks ((st_dev, st_ino), folder descriptor), held until its command ends


def lock_run(run, option: str = "--out") -> None:
    """Take the run's lock (an exclusive ``flock`` on the run folder itself: no file is written; kept until the
    process ends, and the kernel drops it when the process dies, so a killed run leaves no stale lock), or refuse
    with a :class:`UsageError` when another process holds it. A battery found ``train --resume`` and ``train
    --overwrite`` accepted on a run that another process was still training: both wrote the folder, and the first
    one's results were silently replaced. Taken by ``train`` (every mode), ``extract`` and ``export`` into the run;
    idempotent in one process; no-op where ``fcntl`` is missing, the folder cannot be opened or the file system has no
    ``flock``."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        return
    from .errors import UsageError

    try:
        fd = os.open(run, os.O_RDONLY)
    except OSError:  # (the commands' own checks name a missing or unreadable run)
        return
    st = os.fstat(fd)
    if any(k == (st.st_dev, st.st_ino) for k, _ in _HELD_LOCKS):  # this process holds it already
        os.close(fd)
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise UsageError(option, f"{run} is being written by another triplet process (training or its mesh stage): "
                                 "wait for it to finish, or stop it first (nothing was touched)") from None
    except OSError:  # a file system without flock (some FUSE mounts): no lock rather than no run
        os.close(fd)
        return
    _HELD_LOCKS.append(((st.st_dev, st.st_ino), fd))


def release_run_locks() -> None:
    """Drop this process's run locks (the end of a command; the CLI's ``main`` in one process runs several)."""
    while _HELD_LOCKS:
        with contextlib.suppress(OSError):
            os.close(_HELD_LOCKS.pop()[1])
