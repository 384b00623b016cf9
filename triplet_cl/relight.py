"""Relighting a trained run: light sets (files), environment maps → SH, relit renders and their metrics.

Light-set files (``triplet relight --lights FILE``, ``triplet eval --relight DIR``):

* the format of ``scenes/*/relight/relight.json``: ``{"sets": {name: {"lights": [...], "images": folder}},
  "albedo": folder, "conventions": "..."}``; ``FILE#name`` picks one set (without ``#name`` every set);
* a bare ``{"lights": [...]}`` (one set, named after the file);
* a run's own ``lights.json`` (items whose ``type`` is a class name of :mod:`triplet_cl.lights`).

Light items in Mitsuba 3's units and axes (the renderer of the photos; our shading is physical, the
diffuse lobe ``albedo/π · N·L · Li``, so they map one to one):

=============  ===================================================  ===============================
type           fields                                               becomes
=============  ===================================================  ===============================
``point``      ``position`` [3], ``intensity`` (W/sr, 1 or 3)      ``PointLight`` (falloff 1/d²)
``directional````direction`` [3] (where the light travels),         ``DirectionalLight(-direction,
               ``irradiance`` (W/m², 1 or 3)                        irradiance)`` (ours: towards it)
``constant``   ``radiance`` (1 or 3)                                SH environment, band 0
``envmap``     ``filename`` (equirectangular HDR/EXR),              SH environment of degree
               ``rotate_y_deg`` (about +Y, right-handed),           ``env_degree`` (projection)
               ``scale``
=============  ===================================================  ===============================

Every ``constant`` and ``envmap`` of a set is summed into **one** :class:`SHEnvironmentLight` (a
constant environment gives the glossy term too, which ``AmbientLight`` would not: relighting spot_small's
ground-truth mesh and material, point_left / sun_and_sky 31.26 / 31.11 dB against 30.68 / 29.76 dB). Envmap files are
looked up relative to the light file's folder, then in an ``envmaps/`` folder beside it or beside
any folder above it (``shared/data/envmaps`` for the dataset's sets).

Equirectangular axes (Mitsuba's envmap emitter, as :mod:`triplet_cl.mesh.envmap`): a pixel
``(u, v)`` shows the radiance arriving from ``d = (sin θ sin φ, cos θ, −sin θ cos φ)``, ``θ = π v``,
``φ = 2π u``; the emitter's rotation ``R = R_y(rotate_y_deg)`` moves it to the world direction
``R d``, so ``c_k = scale · Σ_pixels L(d) Y_k(R d) dΩ``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .datasets.base import render_files
from .io import strict_json_object
from .lights import LIGHT_CLASSES, DirectionalLight, PointLight, SHEnvironmentLight, VertexSHLight, lights_from_json
from .materials import colour_display_raw
from .mesh.envmap import project_envmap, rotation_y  # noqa: F401  (rotation_y: re-exported)

# SH degree of projected environment maps, chosen by accuracy (README "Relighting"). On the dataset's sky
# (overcast_soil_puresky, rotated 130°): irradiance error against the brute-force integral (300 random normals)
# 27 % / 4.3 % / 0.35 % / 0.08 % / 0.02 % at degree 0 / 1 / 2 / 4 / 8; the glossy term of roughness 0.25 differs from
# degree 8's by 12 % at degree 2 and 8.5 % at 4. Relighting spot_small's ground-truth mesh and material
# (env_rotated, 4 test views, raster): 28.09 / 31.70 / 32.13 / 32.05 / 32.15 dB. Degree 8 is the most accurate
# on both counts and the best relit; its cost (a 5 s projection of a 1k map, cached per process) is paid once.
ENV_DEGREE = 8

MITSUBA_TYPES = ("point", "directional", "constant", "envmap")


class LightFileError(ValueError):
    """A light-set file that cannot be used: names the file and the field."""

    def __init__(self, path, field_name: str, message: str):
        self.path, self.field = Path(path), field_name
        super().__init__(f"{path}: {field_name}: {message}" if field_name else f"{path}: {message}")


@dataclass
class LightSet:
    """One named set of lights (our light objects) and, when the file says, the folder of its reference images."""

    name: str
    lights: list
    images: Path | None = None
    source: Path | None = None
    items: list = field(default_factory=list)  # the file's items, as read


# ---------------------------------------------------------------------------------------------- parsing


def split_spec(spec) -> tuple[Path, str | None]:
    """``"FILE#name"`` → ``(FILE, name)``; ``"FILE"`` → ``(FILE, None)``. A file whose own name holds a ``#`` (it
    exists as spelled) is that file (battery 9: ``studio#1.json`` was read as the set ``1.json`` of ``studio``)."""
    s = str(spec)
    if "#" in s and not Path(s).exists():
        path, name = s.rsplit("#", 1)
        if not name:
            raise LightFileError(Path(path), "", f"{s!r} ends with '#' but names no set (FILE#name picks one set, "
                                                 "FILE alone every set)")
        return Path(path), name
    return Path(s), None


def _read_json(path: Path) -> dict:
    if path.is_dir():
        hint = f" (did you mean {path / 'relight.json'}?)" if (path / "relight.json").is_file() else ""
        raise LightFileError(path, "", f"is a folder, expected a light file{hint}")
    if not path.is_file():
        raise LightFileError(path, "", "the light file does not exist")
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"), object_pairs_hook=strict_json_object)
    except (OSError, UnicodeDecodeError) as exc:
        raise LightFileError(path, "", f"cannot read it ({exc})") from None
    except json.JSONDecodeError as exc:
        raise LightFileError(path, "", f"not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    except (RecursionError, ValueError) as exc:  # nested too deep; an integer past Python's 4300 digits
        raise LightFileError(path, "", "unreadable JSON (" + ("nested too deeply" if isinstance(exc, RecursionError)
                                                                else str(exc)) + ")") from None
    if not isinstance(doc, dict):
        raise LightFileError(path, "", "expected a JSON object with \"sets\" or \"lights\", found "
                             f"{type(doc).__name__}")
    return doc


SET_KEYS = frozenset({"lights", "images", "description"})  # a light set's keys (those starting with _: comments)


def load_light_sets(spec, env_degree: int | None = None) -> list[LightSet]:
    """The light sets of ``spec`` (``FILE`` or ``FILE#name``; see the module docstring), validated;
    environment maps projected onto SH of ``env_degree`` (default :data:`ENV_DEGREE`)."""
    env_degree = ENV_DEGREE if env_degree is None else int(env_degree)
    if not 0 <= env_degree <= 8:
        raise ValueError(f"the environment SH degree must be in [0, 8], got {env_degree}")
    path, name = split_spec(spec)
    doc = _read_json(path)
    if "sets" in doc and "lights" in doc:  # the top-level list was ignored (battery 9)
        raise LightFileError(path, "", "holds both \"sets\" and a top-level \"lights\" list: expected one of them "
                                       "(put those lights into a set of their own)")
    if "sets" in doc:
        sets = doc["sets"]
        if not isinstance(sets, dict) or not sets:
            raise LightFileError(path, "sets", "expected a non-empty object {name: {\"lights\": [...]}}")
        if name is not None and name not in sets:
            raise LightFileError(path, "sets", f"no set named {name!r} (the file has {sorted(sets)})")
        names = [name] if name is not None else list(sets)
        out = []
        for n in names:
            _check_set_name(path, n)
            entry = sets[n]
            where = f"sets.{n}"
            if not isinstance(entry, dict) or "lights" not in entry:
                raise LightFileError(path, where, "expected an object with a \"lights\" list")
            stray = sorted(k for k in entry if k not in SET_KEYS and not str(k).startswith("_"))
            if stray:  # a typo ("light" beside "lights") was ignored (a battery)
                raise LightFileError(path, where, f"unknown key(s) {stray}: a set holds {sorted(SET_KEYS)} (keys "
                                                  "starting with _ are comments)")
            images = entry.get("images")
            if images is not None and not isinstance(images, str):
                raise LightFileError(path, f"{where}.images", f"expected a folder name, found {images!r}")
            lights = parse_lights(entry["lights"], path, f"{where}.lights", env_degree)
            out.append(LightSet(n, lights, path.parent / images if images else None, path, list(entry["lights"])))
        return out
    if "lights" in doc:
        if name is not None:
            raise LightFileError(path, "", f"#{name} names a set, but the file holds one bare \"lights\" list")
        return [LightSet(path.stem, parse_lights(doc["lights"], path, "lights", env_degree), None, path,
                         list(doc["lights"]) if isinstance(doc["lights"], list) else [])]
    raise LightFileError(path, "", f"expected a \"sets\" object or a \"lights\" list, found keys {sorted(doc)}")


def _unit(path, where: str, v) -> np.ndarray:
    """``v`` (finite, checked before) as a unit vector; scaled by its largest component first, so that a tiny but
    non-zero direction (``[1e-200, 0, 0]``, whose squared norm underflows: refused as "the zero vector", battery 9)
    keeps its direction."""
    v = np.asarray(v, np.float64)
    m = float(np.abs(v).max()) if v.size else 0.0
    if m == 0.0:
        raise LightFileError(path, where, "must not be the zero vector")
    v = v / m
    return v / np.linalg.norm(v)


def _check_set_name(path, name: str) -> None:
    """A set's name is the folder its renders go to (``OUT/NAME``): a plain folder name, else a
    :class:`LightFileError` (a name with ``/``, ``..`` or an absolute path wrote the renders over the user's files
    outside ``--out``)."""
    bad = (not name or name != name.strip() or name.startswith(".") or any(c in name for c in '/\\:*?"<>|\0')
           or Path(name).is_absolute() or len(name.encode("utf-8")) > 100)
    if bad:
        raise LightFileError(path, "sets", f"the set name {name!r} is not a plain folder name (its renders go to a "
                                           "folder of that name): expected no path separator nor any of :*?\"<>|, "
                                           "not starting with '.' or a space, at most 100 bytes")


MAX_LIGHT_VALUE = 1e30  # a light file's numbers: float32 renders overflow past ~1e38 (a 1e308 intensity rendered inf)
NON_NEGATIVE_PARAMS = ("intensity", "color")  # our lights.json form's powers (lights.py PARAMS)


def _vec(path, where: str, v, n_ok=(3,), positive=False) -> np.ndarray:
    if isinstance(v, bool) or (isinstance(v, list) and any(isinstance(x, bool) for x in v)):
        want = " or ".join(f"{k} number{'s' if k > 1 else ''}" for k in n_ok)
        raise LightFileError(path, where, f"expected {want}, found {v!r}")
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = None
    except OverflowError:  # an integer beyond any float
        raise LightFileError(path, where, "must be finite, found a number too large for a float") from None
    if a is None or a.ndim > 1 or (a.ndim == 1 and len(a) not in n_ok) or (a.ndim == 0 and 1 not in n_ok):
        want = " or ".join(f"{k} number{'s' if k > 1 else ''}" for k in n_ok)
        raise LightFileError(path, where, f"expected {want}, found {v!r}")
    if not np.isfinite(a).all():
        raise LightFileError(path, where, f"must be finite, found {v!r}")
    if np.abs(a).max() > MAX_LIGHT_VALUE:
        raise LightFileError(path, where, f"must be at most {MAX_LIGHT_VALUE:g} in size (the renders overflow), "
                                          f"found {v!r}")
    if positive and (a < 0).any():
        raise LightFileError(path, where, f"must be >= 0, found {v!r}")
    return np.broadcast_to(a, (3,)).astype(np.float64)


def _need(path, where: str, item: dict, key: str):
    if key not in item:
        raise LightFileError(path, f"{where}.{key}", f"missing (a {item.get('type')} light needs {key!r})")
    return item[key]


def parse_lights(items, path, where: str = "lights", env_degree: int = ENV_DEGREE) -> list:
    """Our light objects of a list of light items (Mitsuba-unit items or our ``lights.json`` items)."""
    if not isinstance(items, list) or not items:
        raise LightFileError(path, where, f"expected a non-empty list of lights, found {items!r}")
    out, env = [], None
    ours = []
    for i, it in enumerate(items):
        w = f"{where}[{i}]"
        if not isinstance(it, dict):
            raise LightFileError(path, w, f"expected an object with a \"type\", found {it!r}")
        kind = it.get("type")
        if "type" not in it:
            raise LightFileError(path, f"{w}.type", f"missing: every light needs a \"type\", one of "
                                 f"{list(MITSUBA_TYPES)} (or a class of triplet_cl.lights: {sorted(LIGHT_CLASSES)})")
        if not isinstance(kind, str):  # a list or an object is not a light type (nor hashable: a lookup would raise)
            raise LightFileError(path, f"{w}.type", f"expected one of {list(MITSUBA_TYPES)} (or a class of "
                                 f"triplet_cl.lights: {sorted(LIGHT_CLASSES)}), found {kind!r}")
        if kind in LIGHT_CLASSES:  # our lights.json form: every parameter given, finite
            for p in LIGHT_CLASSES[kind].PARAMS:
                if p not in it:
                    need = list(LIGHT_CLASSES[kind].PARAMS)
                    raise LightFileError(path, f"{w}.{p}", f"missing (a {kind} needs {need})")
                try:
                    a = np.asarray(it[p], np.float64)
                except (TypeError, ValueError):
                    a = None
                if a is None or a.size == 0 or not np.isfinite(a).all() or np.asarray(it[p]).dtype == bool:
                    raise LightFileError(path, f"{w}.{p}", f"expected finite numbers, found {it[p]!r}")
                if np.abs(a).max() > MAX_LIGHT_VALUE:
                    raise LightFileError(path, f"{w}.{p}", f"must be at most {MAX_LIGHT_VALUE:g} in size (the renders "
                                                           f"overflow), found {it[p]!r}")
                if p in NON_NEGATIVE_PARAMS and (a < 0).any():  # a light's power; SH coefficients may be negative
                    raise LightFileError(path, f"{w}.{p}", f"must be >= 0, found {it[p]!r}")
            if "falloff" in it and not isinstance(it["falloff"], bool):
                raise LightFileError(path, f"{w}.falloff", f"expected true or false, found {it['falloff']!r}")
            if "direction" in LIGHT_CLASSES[kind].PARAMS:
                it = {**it, "direction": _unit(path, f"{w}.direction", it["direction"]).tolist()}
            fields = [f.name for f in dataclasses.fields(LIGHT_CLASSES[kind])]  # lights.json's keys (to_json)
            unknown = set(it) - {"type", *fields}
            if unknown:
                raise LightFileError(path, w, f"unknown field(s) {sorted(unknown)} for a {kind} (expected {fields})")
            ours.append(it)
            continue
        extra = set(it) - {"type", *_FIELDS.get(kind, ())}
        if kind not in MITSUBA_TYPES:
            raise LightFileError(path, f"{w}.type", f"expected one of {list(MITSUBA_TYPES)} (or a class of "
                                 f"triplet_cl.lights: {sorted(LIGHT_CLASSES)}), found {kind!r}")
        if extra:
            raise LightFileError(path, w, f"unknown field(s) {sorted(extra)} for a {kind} light "
                                 f"(expected {list(_FIELDS[kind])})")
        if kind == "point":
            out.append(PointLight(_vec(path, f"{w}.position", _need(path, w, it, "position")),
                                  _vec(path, f"{w}.intensity", _need(path, w, it, "intensity"), (1, 3), True)))
        elif kind == "directional":
            d = _unit(path, f"{w}.direction", _vec(path, f"{w}.direction", _need(path, w, it, "direction")))
            out.append(DirectionalLight(-d,
                                        _vec(path, f"{w}.irradiance", _need(path, w, it, "irradiance"), (1, 3), True)))
        else:
            if kind == "constant":
                c = np.zeros((3, 1))
                rad = _vec(path, f"{w}.radiance", _need(path, w, it, "radiance"), (1, 3), True)
                c[:, 0] = rad * math.sqrt(4 * math.pi)
            else:
                c = envmap_item_sh(it, path, w, env_degree)
            env = c if env is None else _add_sh(env, c)
    if ours:
        try:
            out += lights_from_json(ours)
        except ValueError as exc:
            raise LightFileError(path, where, str(exc)) from None
    if env is not None:
        out.append(SHEnvironmentLight(env))
    return out


_FIELDS = {"point": ("position", "intensity"), "directional": ("direction", "irradiance"),
           "constant": ("radiance",), "envmap": ("filename", "rotate_y_deg", "scale")}


def _add_sh(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(a.shape[1], b.shape[1])
    out = np.zeros((3, n))
    out[:, : a.shape[1]] += a
    out[:, : b.shape[1]] += b
    return out


def envmap_item_sh(item: dict, path, where: str, degree: int) -> np.ndarray:
    """SH coefficients ``[3, (degree+1)^2]`` of an ``envmap`` item of the light file ``path``."""
    name = _need(path, where, item, "filename")
    if not isinstance(name, str) or not name:
        raise LightFileError(path, f"{where}.filename", f"expected a file name, found {name!r}")
    rot = item.get("rotate_y_deg", 0.0)
    scale = item.get("scale", 1.0)
    for k, v in (("rotate_y_deg", rot), ("scale", scale)):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise LightFileError(path, f"{where}.{k}", f"expected a finite number, found {v!r}")
    if scale < 0:
        raise LightFileError(path, f"{where}.scale", f"must be >= 0, found {scale!r}")
    if scale > MAX_LIGHT_VALUE:
        raise LightFileError(path, f"{where}.scale", f"must be at most {MAX_LIGHT_VALUE:g} (the renders overflow), "
                             f"found {scale!r}")
    file = find_envmap(name, Path(path).parent, path, f"{where}.filename")
    from .datasets.images import read_image
    from .errors import DatasetError

    key = (str(file.resolve()), file.stat().st_mtime_ns, float(rot), degree)
    if key not in _PROJECTIONS:
        try:
            img = read_image(file, unpremultiply=False)  # an RGBA map's stored colour is its radiance
        except DatasetError as exc:
            raise LightFileError(path, f"{where}.filename", str(exc)) from None
        if img.color_space != "linear":
            raise LightFileError(path, f"{where}.filename", f"{file} is not a linear HDR/EXR image (found an "
                                 "8/16-bit file, whose values are display-encoded, not radiance)")
        if abs(img.width / img.height - 2.0) > 0.1 or img.height < 2:  # a cube map, a crop, a thumbnail strip
            need = ("twice as wide as it is high" if abs(img.width / img.height - 2.0) > 0.1
                    else "at least 2 pixels high")
            raise LightFileError(path, f"{where}.filename", f"{file} is {img.width}x{img.height}: an "
                                 f"equirectangular environment map is {need}")
        peak = float(np.abs(img.rgb).max()) if img.rgb.size else 0.0
        if peak > MAX_LIGHT_VALUE:
            raise LightFileError(path, f"{where}.filename", f"{file} holds a value of {peak:.3g}: radiance must be at "
                                 f"most {MAX_LIGHT_VALUE:g} (the renders overflow)")
        _PROJECTIONS[key] = project_equirect(img.rgb, float(rot), degree)
    coeffs = float(scale) * _PROJECTIONS[key]
    if not np.isfinite(coeffs).all() or np.abs(coeffs).max(initial=0.0) > MAX_LIGHT_VALUE:
        raise LightFileError(path, f"{where}.scale", f"{scale!r} times the map's radiance overflows (at most "
                             f"{MAX_LIGHT_VALUE:g})")
    return coeffs


_PROJECTIONS: dict = {}  # (file, mtime, rotation, degree) → SH coefficients: one projection per process


def find_envmap(name: str, base: Path, path=None, where: str = "filename") -> Path:
    """The environment map ``name``: absolute, relative to ``base``, or in an ``envmaps/`` folder in ``base`` or
    beside any folder above it. Raises :class:`LightFileError` listing the paths tried."""
    p = Path(name)
    tried = []
    cands = [p] if p.is_absolute() else [base / p] + [d / "envmaps" / p.name for d in [base, *base.resolve().parents]]
    for c in cands:
        tried.append(str(c))
        if c.is_file():
            return c
    folders = [c for c in cands if c.is_dir()]
    if folders:  # ("not found" for a folder of that name, battery 8)
        raise LightFileError(path or base, where, f"environment map {name!r}: {folders[0]} is a folder, not an image "
                                                  "(EXR, HDR or PNG)")
    raise LightFileError(path or base, where, f"environment map {name!r} not found; tried: {', '.join(tried)}")


def project_equirect(img, rotate_y_deg: float = 0.0, degree: int = ENV_DEGREE) -> np.ndarray:
    """:func:`~triplet_cl.mesh.envmap.project_envmap` of an equirectangular radiance map ``[H, W, 3]``
    rotated by ``R_y(rotate_y_deg)``, with the degree checked: ``[3, (degree+1)^2]``."""
    if not 0 <= degree <= 8:
        raise ValueError(f"env SH degree must be in [0, 8], got {degree}")
    return project_envmap(img, degree, rotate_y_deg)


# ---------------------------------------------------------------------------------------------- rendering


class Relighter:
    """Renders a trained run (its refined mesh when it has one, else the soup) under other lights.

    The run's colour pipeline is respected: a run of the linear pipeline renders linear radiance and encodes it
    as the photos are; a run saved before it (no ``color`` in its config) rendered encoded values and is
    rendered the same way (lights in linear units then do not mean what they say: that is what it learned).
    """

    def __init__(self, trainer, stage: str = "auto", renderer: str | None = None, shadows: str | None = None):
        from .mesh.refine import MESH_STATE, MeshStage, load_mesh_state
        from .visibility import SHADOW_MODES

        if shadows is not None and shadows not in SHADOW_MODES:
            raise ValueError(f"shadows must be one of {SHADOW_MODES}, got {shadows!r}")
        self.tr = trainer
        if trainer.cfg.color == "encoded":  # relit and scored without a word (battery 9)
            import warnings

            from .datasets.base import DatasetWarning

            warnings.warn(DatasetWarning(f"{trainer.run_dir} was trained with --color encoded (shaded in the photos' "
                                         "sRGB-encoded values): its lights and albedo are not physical quantities, so "
                                         "its relit images (and their scores) do not follow the new lights' units; "
                                         "train with --color linear (the default) to relight"), stacklevel=2)
        # cast shadows of the relit lights with the raster renderer (visibility.py), traced once per light set;
        # default: as the run was trained (its albedo fitted with shadows, or with the photos' shadows in it)
        self.shadows = shadows or ("vertex" if trainer.shadows_active() else "off")
        self._vis: dict = {}
        has_mesh = (trainer.run_dir / MESH_STATE).is_file()
        if stage == "auto":
            stage = "mesh" if has_mesh else "soup"
        if stage not in ("soup", "mesh"):
            raise ValueError(f"stage must be 'auto', 'soup' or 'mesh', got {stage!r}")
        if stage == "mesh" and not has_mesh:
            raise FileNotFoundError(f"{trainer.run_dir} has no refined mesh ({MESH_STATE}); run `triplet extract` "
                                    "or relight the soup (--stage soup)")
        self.stage_name = stage
        self.renderer = renderer or (trainer.cfg.renderer if stage == "soup" else "raster")
        if stage == "mesh":
            self.base = load_mesh_state(trainer.run_dir / MESH_STATE)  # first: a damaged file is named there
            self.mesh_stage = MeshStage(trainer, _mesh_config(trainer.run_dir / MESH_STATE), quiet=True)
            self.mesh_stage.renderer = self.renderer
        else:
            self.mesh_stage = None
            self.base = trainer.scene

    def views(self, split: str = "test") -> list:
        ds = self.tr.ds
        if split not in ("train", "val", "test"):
            raise ValueError(f"split must be train, val or test, got {split!r}")
        views = ds[split]
        if not views:
            raise ValueError(f"--split {split}: the run's dataset {self.tr.data} has no {split!r} views")
        if split == "test" and self.tr.cfg.max_test_views:
            views = views[: self.tr.cfg.max_test_views]
        return views

    def with_lights(self, lights, albedo: bool = False):
        """The base scene with ``lights`` (raw parameters shared); ``albedo``: lit so that it shows its base
        colour (ambient 1, ambient occlusion 1)."""
        from .lights import AmbientLight
        from .scene import Scene

        s = self.base
        mat = np.asarray(s.material.data)
        brdf = s.brdf
        if albedo:
            # Blinn-Phong's ambient term shows the base colour whatever a BRDF's environment weights are (Blinn-Phong's
            # kd and Cook-Torrance's albedo are columns 0-2 under the same sigmoid)
            mat, brdf = colour_display_raw(mat[:, 0:3]), "blinn_phong"
            lights = [AmbientLight(np.ones(3))]
        keep_vsh = any(isinstance(lt, VertexSHLight) for lt in lights)
        return Scene.from_arrays(s.V.data, s.F, material=mat, alpha=s.alpha.data, lights=lights,
                                 vertex_sh=s.vertex_sh.data if keep_vsh and s.vertex_sh is not None else None,
                                 brdf=brdf, dtype=np.asarray(s.V.data).dtype)

    def render(self, scene, camera, background, renderer: str | None = None,
               bounce: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """``(image [H, W, 3] over background, in the photos' encoding, alpha [H, W])`` of ``scene`` (with
        ``renderer``, default the relighter's). A mesh trained with the traced interreflection
        (``MeshConfig.bounce``) is relit with it, the bounce of ``scene``'s lights, unless ``bounce`` is False."""
        from .render import RenderSettings, render

        renderer = renderer or self.renderer
        if self.mesh_stage is not None:
            self.mesh_stage.renderer = renderer
            vis = self.visibility(scene) if self.shadows == "vertex" and renderer == "raster" else None
            bnc = self.bounce(scene, vis) if bounce else None
            _, img, alpha = self.mesh_stage.render(scene, camera, background, self.mesh_stage.cfg.eval_supersample,
                                                   vis=vis, bounce=bnc)
            return np.asarray(img), np.asarray(alpha)
        tc = self.tr.cfg
        sh = scene.vertex_sh is not None
        vis = None
        if self.shadows == "vertex" and renderer == "raster":
            vis = self.visibility(scene)
        st = RenderSettings(K=tc.faces_per_pixel, sigma=tc.sigma, background=tuple(float(x) for x in background),
                            renderer=renderer, transfer=self.tr.transfer,
                            sh_degree=min(tc.sh_degree, self.tr.it // max(tc.sh_band_every, 1)) if sh else None)
        r = render(scene, camera, st, self.tr.device, vis=vis)
        return r.image, r.alpha

    def visibility(self, scene) -> np.ndarray:
        """``[N, NV]`` per-vertex visibility of ``scene`` towards its own lights (traced once per scene)."""
        from .visibility import vertex_visibility

        key = id(scene)
        if key not in self._vis or self._vis[key][0] is not scene:
            eps = self.tr.cfg.shadow_eps if self.mesh_stage is None else self.mesh_stage.cfg.shadow_eps
            self._vis[key] = (scene, vertex_visibility(scene, self.tr.device, ray_eps=eps))
        return self._vis[key][1]

    def bounce(self, scene, vis):
        """``[N, 3]`` the traced interreflection of ``scene``'s lights (``MeshStage.bounce``; traced once per scene),
        or None (the soup, a mesh trained without it, another renderer)."""
        ms = self.mesh_stage
        if ms is None or not ms.bounce_active(scene):  # depends on the renderer of the call: decided per call
            return None
        key = ("bounce", id(scene))
        if key not in self._vis or self._vis[key][0] is not scene:
            self._vis[key] = (scene, ms.bounce(scene, vis))
        return self._vis[key][1]

    @property
    def shadows_used(self) -> str:
        """The cast shadows of the relit images: "vertex" (cached, raster), "traced" (raytrace / hybrid) or "off"."""
        if self.renderer != "raster":
            return "traced"
        return "vertex" if self.shadows == "vertex" else "off"

    def render_albedo(self, camera) -> tuple[np.ndarray, np.ndarray]:
        """``(straight base colour [H, W, 3] sRGB-encoded, alpha [H, W])`` through ``camera`` (rasterized: no
        shadow or reflection bounce may add to it)."""
        img, alpha = self.render(self.albedo_scene(), camera, np.zeros(3), "raster", bounce=False)
        rgb = np.where(alpha[..., None] > 1e-4, img / np.maximum(alpha[..., None], 1e-4), 0.0)
        if self.tr.transfer is None and self.tr.cfg.color == "linear":  # linear dataset: encode for comparison
            from .ops.color import srgb_encode

            rgb = srgb_encode(np.clip(rgb, 0, None))
        return rgb, alpha

    def albedo_scene(self):
        if getattr(self, "_albedo_scene", None) is None:
            self._albedo_scene = self.with_lights([], albedo=True)
        return self._albedo_scene


def _mesh_config(path):
    """The :class:`MeshConfig` the refined mesh was trained with (saved in its state)."""
    import zipfile

    from .errors import RunError
    from .mesh.refine import MeshConfig

    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
        return MeshConfig.from_dict(meta["mesh"]) if "mesh" in meta else MeshConfig()
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise RunError(path, f"damaged mesh-stage result ({type(exc).__name__}: {exc}): run `triplet extract` "
                             "again") from None


def check_finite_render(img: np.ndarray, what: str) -> None:
    """Refuse a relit render with NaN/Inf in it, naming the set and view, before anything is scored or written (the
    losses' own input check said only "pred must be finite"; a PNG of NaN is garbage): finite materials and lights
    can still shade to NaN, e.g. a run trained with wrong gradients (bench/results/intel_lanes_check_2026-11-29.txt)."""
    bad = int(np.size(img) - np.count_nonzero(np.isfinite(img)))
    if bad:
        raise ValueError(f"the relit render of {what} holds {bad} NaN/Inf value(s): the run's materials and lights do "
                         "not shade to finite colours under these lights; nothing was scored or written for it")


def straight(img: np.ndarray, alpha: np.ndarray, background) -> np.ndarray:
    """Un-composite ``background`` from an image: the straight colour of an RGBA PNG."""
    a = np.clip(alpha, 0, 1)[..., None]
    bg = np.asarray(background, np.float64)
    return np.where(a > 1e-4, (img - bg * (1 - a)) / np.maximum(a, 1e-4), 0.0)


def relight_run(relighter: Relighter, light_set: LightSet, out_dir, split: str = "test") -> list[Path]:
    """Render every view of ``split`` under ``light_set`` as straight-alpha RGBA PNGs in ``out_dir``."""
    from .io import write_png

    scene = relighter.with_lights(light_set.lights)
    bg = np.ones(3)
    out = []
    views = relighter.views(split)
    from .runs import view_progress

    for v, fname in view_progress(zip(views, render_files(views), strict=True), f"relight {light_set.name}"):
        img, alpha = relighter.render(scene, v.camera, bg)
        check_finite_render(img, f"set {light_set.name!r}, view {v.name!r}")
        p = Path(out_dir) / fname
        write_png(p, np.clip(straight(img, alpha, bg), 0, 1), np.clip(alpha, 0, 1))
        out.append(p)
    return out


# ---------------------------------------------------------------------------------------------- metrics


def albedo_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    """Albedo PSNR over the ground truth's covered pixels ``mask [H, W]`` (or stacks ``[N, H, W]``) of sRGB-encoded
    ``pred`` against ``gt``: raw, and after one per-channel scale fitted (least squares on the linear values of
    every covered pixel: the NeRFactor / TensoIR protocol for the albedo–light scale ambiguity)."""
    from .ops.color import srgb_decode, srgb_encode

    m = np.asarray(mask, bool)
    p, g = np.asarray(pred, np.float64)[m], np.asarray(gt, np.float64)[m]
    if not len(p):
        raise ValueError("the ground-truth albedo covers no pixel")
    pl, gl = srgb_decode(np.clip(p, 0, 1)), srgb_decode(np.clip(g, 0, 1))
    scale = (pl * gl).sum(0) / np.maximum((pl * pl).sum(0), 1e-12)
    scaled = srgb_encode(np.clip(pl * scale, 0, 1))

    def _psnr(a):
        mse = float(np.mean((np.clip(a, 0, 1) - g) ** 2))
        return 10 * math.log10(1 / mse) if mse > 0 else float("inf")

    return {"psnr_raw": _psnr(p), "psnr_scaled": _psnr(scaled), "scale": scale.tolist(), "pixels": int(m.sum())}


def check_vertex_sh(sets, has_vertex_sh: bool) -> None:
    """A set with a ``VertexSHLight`` needs a run trained with the vertex-SH light (its per-vertex coefficients)."""
    for ls in sets:
        if not has_vertex_sh and any(isinstance(lt, VertexSHLight) for lt in ls.lights):
            raise LightFileError(ls.source or ls.name, "", f"set {ls.name!r} has a VertexSHLight, but the run was "
                                 "trained without one (--lights vertex-sh): it has no per-vertex SH to relight with")


def _frame_key(file_path: str) -> str:
    """A transforms frame's image name as the views are named (an image extension the loader knows dropped, dots
    kept)."""
    from .datasets.images import IMAGE_EXTENSIONS

    p = Path(file_path)
    return p.stem if p.suffix.lower() in IMAGE_EXTENSIONS else p.name


def check_reference_cameras(spec: Path, doc: dict, view_names, cameras, tol: float = 1e-4) -> None:
    """``"cameras"`` of a relight.json (a transforms JSON beside it, the cameras its references were rendered from):
    it names a file that has a frame for each test view (by the image's name), whose pose is the view's camera in
    the run (within ``tol`` × the camera's distance from the origin). A battery found the key ignored: references of
    other cameras were scored against the run's test views without a word."""
    from .datasets.nerf import _camera_maker, _check_intrinsics, _matrix, frame_intrinsics, has_focal, read_json
    from .errors import DatasetError

    ref = doc.get("cameras")
    if ref is None:
        return
    if not isinstance(ref, str) or not ref:
        raise LightFileError(spec, "cameras", f"expected the name of a transforms JSON file, found {ref!r}")
    path = spec.parent / ref
    if not path.is_file():
        raise LightFileError(spec, "cameras", f"{path}: " + ("a folder, not a transforms JSON file" if path.is_dir()
                                                             else "file not found"))
    try:
        data = read_json(path)
        frames = data.get("frames") if isinstance(data, dict) else None
        if not isinstance(frames, list):
            raise DatasetError(path, "expected an object with a list 'frames'")
        poses, lenses = {}, {}
        top = {k: v for k, v in data.items() if k != "frames"}
        _check_intrinsics(path, "", top)
        for i, fr in enumerate(frames):
            if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str) or "transform_matrix" not in fr:
                raise DatasetError(path, f"frames[{i}]: expected an object with file_path and transform_matrix")
            key = _frame_key(fr["file_path"])
            if key in poses:
                raise DatasetError(path, f"frames[{i}]: a second frame named {key!r} (the references are matched to "
                                         "the test views by their images' names)")
            poses[key] = _matrix(path, f"frames[{i}]: ", fr["transform_matrix"])
            intr = frame_intrinsics(path, f"frames[{i}]: ", top, fr)
            if has_focal(intr):  # (a file without a focal length: the poses only)
                lenses[key] = (_camera_maker(path, f"frames[{i}]: ", poses[key], intr), intr.get("w"), intr.get("h"))
    except DatasetError as exc:
        raise LightFileError(spec, "cameras", str(exc)) from None
    for name, cam in zip(view_names, cameras, strict=True):
        key = Path(name).name  # the reference images' own key (check_references: NAME.png)
        if key not in poses:
            raise LightFileError(spec, "cameras", f"{path} has no frame for the test view {name}")
        mine = cam.c2w_nerf[:3]
        scale = max(1.0, float(np.linalg.norm(cam.center)))
        if not np.allclose(poses[key][:3], mine, rtol=0, atol=tol * scale):
            raise LightFileError(spec, "cameras", f"{path}: the pose of {key} is not the run's test camera {name} "
                                                  "(the references were rendered from other cameras than the run's "
                                                  "test views)")
        if key not in lenses:
            continue
        make, w, h = lenses[key]
        try:  # the reference camera at its own size when the file gives it (the loader's intrinsics and checks)
            ref_cam = make(int(round(float(w))) if w is not None else cam.width,
                           int(round(float(h))) if h is not None else cam.height)
        except DatasetError as exc:
            raise LightFileError(spec, "cameras", str(exc)) from None
        fov, theirs = (2 * np.arctan(0.5 * c.width / c.fx) for c in (ref_cam, cam))
        # (a field of view: any image size; 1 %: a --downscale that crops a row or column moves it by up to (f - 1) / W)
        if abs(fov - theirs) > 1e-2 * theirs:
            raise LightFileError(spec, "cameras", f"{path}: the field of view of {key} ({np.degrees(fov):.3f}°) "
                                                  f"is not the run's test camera {name}'s ({np.degrees(theirs):.3f}°): "
                                                  "the references were rendered through another lens")


def read_reference(path, width: int, height: int):
    """A reference image for a view of ``width × height``: as stored, or — when it is an integer multiple ``n`` of
    the view's size as ``--downscale n`` leaves it (``W // n``, ``H // n``) — downscaled by ``n`` as the dataset's
    photos were (:func:`~triplet_cl.datasets.images.downscale_image`): a run trained with ``--downscale 2`` was
    refused against the scene's full-size references (battery 9). Any other size is returned as read (the callers
    name the mismatch)."""
    from .datasets.images import image_size, read_image

    W, H = image_size(path)
    n = max(1, W // max(int(width), 1))  # the largest n with W // n >= width: if any factor fits, this one does
    return read_image(path, downscale=n if n > 1 and (W // n, H // n) == (int(width), int(height)) else 1)


def check_references(relight_dir, view_names, env_degree: int | None = None, sizes=None,
                     writes_out: bool = False, cameras=None) -> None:
    """Every reference image ``evaluate_relight`` will read exists (each set's ``images`` folder and the
    ``albedo`` folder, one PNG per test view) and, with ``sizes`` (``(width, height)`` per view), reads as an image of
    its view's size; the albedo's covers some pixel; with ``writes_out`` (``eval --out``), no set is named ``albedo``
    beside an albedo folder (their renders would share ``OUT/STAGE/albedo``); with ``cameras`` (the views'), the
    file's ``"cameras"`` agree with them (:func:`check_reference_cameras`). Checked before any rendering, one error
    naming the file."""
    from .errors import DatasetError

    rdir = Path(relight_dir)
    spec = rdir / "relight.json" if rdir.is_dir() else rdir
    doc = _read_json(spec)
    if cameras is not None:
        check_reference_cameras(spec, doc, view_names, cameras)
    folders = []
    alb = doc.get("albedo")
    for ls in load_light_sets(spec, env_degree):
        if ls.images is None:
            raise LightFileError(spec, f"sets.{ls.name}.images", "missing: the folder of the set's reference images")
        if writes_out and alb is not None and ls.name == "albedo":
            raise LightFileError(spec, "sets.albedo", "a set may not be named 'albedo' in a file with an albedo "
                                                      "folder: its relit renders and the albedo renders would share "
                                                      "one folder; rename the set")
        folders.append((f"sets.{ls.name}.images", ls.images))
    if alb is not None:
        if not isinstance(alb, str):
            raise LightFileError(spec, "albedo", f"expected a folder name, found {alb!r}")
        folders.append(("albedo", spec.parent / alb))
    for where, folder in folders:
        if not folder.is_dir():
            raise LightFileError(spec, where, f"{folder}: " + ("a file, not a folder" if folder.exists()
                                                               else "folder not found"))
        missing = [n for n in view_names if not (folder / f"{Path(n).name}.png").is_file()]
        dirs = [n for n in missing if (folder / f"{Path(n).name}.png").is_dir()]
        if dirs:  # (battery 11: named as missing)
            raise LightFileError(spec, where, f"{folder / (Path(dirs[0]).name + '.png')}: a folder, not the image of "
                                              f"the test view {dirs[0]}")
        if missing:
            raise LightFileError(spec, where, f"{folder}: no image for the test view(s) "
                                              f"{', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} "
                                              f"(expected {Path(missing[0]).name}.png: 8- or 16-bit PNG, straight "
                                              "alpha)")
        if sizes is None:
            continue
        covered = False
        no_alpha, empty = [], []
        for n, (w, h) in zip(view_names, sizes, strict=True):
            p = folder / f"{Path(n).name}.png"
            try:
                im = read_reference(p, w, h)
            except DatasetError as exc:
                raise LightFileError(spec, where, str(exc)) from None
            if im.rgb.shape[:2] != (h, w):
                raise LightFileError(spec, where, f"{p} is {im.rgb.shape[1]}x{im.rgb.shape[0]}, its view {w}x{h} "
                                                  "(an integer multiple is read as a --downscale of it)")
            covered = covered or im.alpha is None or bool((im.alpha > 0.5).any())
            if im.alpha is None:
                no_alpha.append(p.name)
            elif not (im.alpha > 0.5).any():
                empty.append(p.name)
        if where == "albedo" and not covered:
            raise LightFileError(spec, where, f"{folder}: every image is transparent (alpha 0): the albedo covers no "
                                              "pixel to compare with")
        _warn_references(spec, where, folder, no_alpha, empty, len(view_names))


def _warn_references(spec, where: str, folder, no_alpha, empty, n: int) -> None:
    """References that cannot be what the scores assume (battery 8: scored without a word, 1.04 dB and 24.80 dB):
    without an alpha channel (their background then counts as the object, composited over white) or with no
    opaque pixel (the score is then the render's background against white)."""
    import warnings

    from .datasets.base import DatasetWarning

    for names, what in ((no_alpha, "have no alpha channel: their background is scored as part of the object"),
                        (empty, "are fully transparent: they show no object to compare with")):
        if names:
            warnings.warn(DatasetWarning(f"{spec}: {where}: {len(names)} of the {n} references in {folder} {what} "
                                         f"(e.g. {names[0]})"), stacklevel=3)


def evaluate_relight(relighter: Relighter, relight_dir, env_degree: int | None = None, out_dir=None) -> dict:
    """Per light set of ``relight_dir/relight.json``: PSNR / SSIM of the relit test views against the set's images
    (both composited over white, as the novel-view metrics); albedo PSNR (raw / scaled, :func:`albedo_psnr`) of
    the rendered base colour against the file's ``albedo`` folder. ``out_dir``: also write the relit PNGs there."""
    from .errors import DatasetError
    from .io import write_png
    from .losses import ssim
    from .runs import view_progress
    from .train import psnr

    rdir = Path(relight_dir)
    spec = rdir / "relight.json" if rdir.is_dir() else rdir
    doc = _read_json(spec)
    env_degree = ENV_DEGREE if env_degree is None else int(env_degree)
    sets = load_light_sets(spec, env_degree)
    views = relighter.views("test")
    check_reference_cameras(spec, doc, [v.name for v in views], [v.camera for v in views])
    bg = np.ones(3, np.float32)

    def ref(folder: Path, v):
        p = folder / f"{Path(v.name).name}.png"
        try:
            im = read_reference(p, v.camera.width, v.camera.height)
        except DatasetError as exc:
            raise LightFileError(spec, "images", str(exc)) from None
        if im.rgb.shape[:2] != (v.camera.height, v.camera.width):
            raise LightFileError(spec, "images", f"{p} is {im.rgb.shape[1]}x{im.rgb.shape[0]}, the view "
                                 f"{v.camera.width}x{v.camera.height}")
        a = np.ones(im.rgb.shape[:2], np.float32) if im.alpha is None else im.alpha
        return im.rgb, a

    out: dict = {"dir": str(rdir), "stage": relighter.stage_name, "renderer": relighter.renderer,
                 "shadows": relighter.shadows_used,
                 "env_sh_degree": env_degree, "sets": {}}
    for ls in sets:
        if ls.images is None:
            raise LightFileError(spec, f"sets.{ls.name}.images", "missing: the folder of the set's reference images")
        scene = relighter.with_lights(ls.lights)
        per = []
        for v, fname in view_progress(zip(views, render_files(views), strict=True), f"relight {ls.name}"):
            rgb, a = ref(ls.images, v)
            target = rgb * a[..., None] + bg * (1 - a[..., None])
            img, alpha = relighter.render(scene, v.camera, bg)
            check_finite_render(img, f"set {ls.name!r}, view {v.name!r}")
            img = np.clip(img, 0, 1)
            per.append({"name": v.name, "psnr": psnr(img, target),
                        "ssim": float(ssim(img.astype(np.float64), target.astype(np.float64), padding="valid"))})
            if out_dir is not None:
                write_png(Path(out_dir) / ls.name / fname, np.clip(straight(img, alpha, bg), 0, 1),
                          np.clip(alpha, 0, 1))
        out["sets"][ls.name] = {"psnr": float(np.mean([p["psnr"] for p in per])),
                                "ssim": float(np.mean([p["ssim"] for p in per])), "views": per}
    alb = doc.get("albedo")
    if alb is not None:
        if not isinstance(alb, str):
            raise LightFileError(spec, "albedo", f"expected a folder name, found {alb!r}")
        preds, gts, masks = [], [], []
        for v, fname in view_progress(zip(views, render_files(views), strict=True), "albedo"):
            rgb, a = ref(spec.parent / alb, v)
            pred, pa = relighter.render_albedo(v.camera)
            check_finite_render(pred, f"the albedo, view {v.name!r}")
            preds.append(pred)
            gts.append(rgb)
            masks.append(a > 0.5)
            if out_dir is not None:
                write_png(Path(out_dir) / "albedo" / fname, np.clip(pred, 0, 1),
                          np.clip(pa, 0, 1))
        out["albedo"] = albedo_psnr(np.stack(preds), np.stack(gts), np.stack(masks))
    return out
