"""PBR asset export of a :class:`MeshAsset`: glTF 2.0 binary (GLB), OBJ + MTL, PLY, lights.

Entry points: :func:`export_asset` (everything into a folder), :func:`export_glb`,
:func:`export_obj`, :func:`export_ply`, :func:`~triplet_cl.mesh.envmap.export_envmap`,
:func:`lights_to_json` / :func:`lights_from_json`.

Textures (GLB and OBJ share one bake; see :mod:`triplet_cl.mesh.bake`): a ``xatlas`` UV atlas, each
face rasterised in texel space with barycentric interpolation of the vertex attributes, and empty
texels filled with the nearest chart texel so that bilinear filtering and mip-maps do not bleed.

Colour spaces. Runs of the linear pipeline (``TrainConfig.color = "linear"``, the default: shading in
linear radiance, the photos' sRGB transfer after compositing) learn ``albedo`` as linear
reflectance: ``albedo_space="linear"`` encodes it with the sRGB transfer function for the base-colour
textures (glTF's convention; the run's exports do this). ``albedo_space="srgb"`` (this function's
default, and the exports of runs trained before the linear pipeline, which fitted the photos'
encoded values directly) stores the values unchanged. Roughness, metallic and AO are linear data;
the PLY keeps the float attributes as trained.

Material mapping:
    Cook-Torrance: base colour = albedo; glTF metallic-roughness image (also the occlusion image,
        "ORM"): R = ao, G = roughness, B = metallic. Our GGX uses ``a = roughness^2`` like glTF.
    Blinn-Phong: base colour = kd; metallic = 0; roughness = ``(2 / (e + 2))^(1/4)`` with the
        shading exponent ``e = shininess + 1`` (the GGX ``a^2 = 2 / (e + 2)`` equivalence the SH
        environment shading already uses; ``a = roughness^2``); R (occlusion) = 1 and no occlusion
        texture; ks / ka are kept in the PLY and (ks) the OBJ ``map_Ks`` only.

Coordinates are written as they are (our world is Y up, as glTF's); normals are area-weighted
vertex normals of the connected mesh, smooth across UV seams.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io import atomic_write_bytes, write_json, write_soup_ply
from ..lights import light_to_json, lights_from_json, lights_to_json  # noqa: F401  (re-exports)
from ..materials import blinn_phong_roughness, get_brdf  # noqa: F401  (blinn_phong_roughness: re-export)
from .asset import ATTRIBUTES, MeshAsset
from .bake import UVAtlas, bake, rasterize_uv, uv_atlas, vertex_normals
from .envmap import environment_lights, export_envmap

FORMATS = ("glb", "obj", "ply")
GENERATOR = "triplet_cl"

# glTF enums
_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071


# ---- materials ---------------------------------------------------------------------------------
def srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (linear → encoded), on values clipped to [0, 1]."""
    from ..ops.color import srgb_encode as encode

    return encode(np.clip(np.asarray(x, np.float64), 0, 1))


def pbr_channels(asset: MeshAsset, albedo_space: str = "srgb") -> dict[str, np.ndarray]:
    """Per-vertex glTF material channels of ``asset``, all in [0, 1]:
    ``base [N, 3]`` (sRGB-encoded), ``roughness``, ``metallic``, ``ao`` ``[N]``, ``alpha [N]`` (1 if absent)."""
    if albedo_space not in ("srgb", "linear"):
        raise ValueError(f"albedo_space must be 'srgb' or 'linear', got {albedo_space!r}")
    a = asset.attributes
    base = np.clip(a["albedo"], 0, 1).astype(np.float64)
    if albedo_space == "linear":
        base = srgb_encode(base)
    n = asset.num_vertices
    rough, metal, ao = get_brdf(asset.brdf).pbr(a, n)  # the BRDF's glTF metallic-roughness mapping
    alpha = a.get("alpha", np.ones(n))
    return {"base": base, "roughness": np.clip(rough, 0, 1), "metallic": np.clip(metal, 0, 1),
            "ao": np.clip(ao, 0, 1), "alpha": np.clip(alpha, 0, 1)}


# an asset with a vertex this many times farther from the vertices' median than half of them is not exported (a
# battery's mesh_stage.npz with one vertex at 1e12 made xatlas's chart packing run for ever, deaf to SIGTERM and
# Ctrl-C); the mesh stage moves a vertex by a few extents at most. The median distance, not a high percentile: a
# small mesh's 99th percentile is its far vertex itself
MAX_VERTEX_SPREAD = 1e4


def check_asset(asset, what: str) -> MeshAsset:
    """An exportable :class:`MeshAsset` (faces, finite values, every attribute of its BRDF, no vertex far out), or a
    ``ValueError`` starting with ``what``."""
    if not isinstance(asset, MeshAsset):
        raise TypeError(f"{what}: expected a triplet_cl.mesh.MeshAsset, got {type(asset).__name__}")
    if asset.num_faces == 0:
        raise ValueError(f"{what}: the mesh has no faces (V has {asset.num_vertices} vertices, F is empty); "
                         "nothing to export")
    if not np.isfinite(asset.V).all():
        raise ValueError(f"{what}: vertex positions V must be finite, found "
                         f"{int((~np.isfinite(asset.V)).sum())} NaN/Inf value(s)")
    r = np.linalg.norm(asset.V - np.median(asset.V, axis=0), axis=1)
    bulk, i = float(np.median(r)), int(np.argmax(r))
    if r[i] > MAX_VERTEX_SPREAD * max(bulk, 1e-9 * max(float(np.abs(asset.V).max()), 1.0)):
        raise ValueError(f"{what}: vertex {i} lies {r[i]:.3g} from the mesh's centre, more than {MAX_VERTEX_SPREAD:g} "
                         f"times as far as half of its vertices ({bulk:.3g})")
    for name in ATTRIBUTES[asset.brdf]:
        if name not in asset.attributes:
            raise ValueError(f"{what}: a {asset.brdf} asset needs the per-vertex attribute {name!r}")
    for name, v in asset.attributes.items():
        if len(v) != asset.num_vertices:
            raise ValueError(f"{what}: attributes[{name!r}] has {len(v)} rows, expected {asset.num_vertices}")
        if not np.isfinite(v).all():
            raise ValueError(f"{what}: attributes[{name!r}] must be finite, found "
                             f"{int((~np.isfinite(v)).sum())} NaN/Inf value(s)")
    return asset


# ---- the shared bake ---------------------------------------------------------------------------
@dataclass
class BakedAsset:
    """Everything the GLB and OBJ writers need, computed once.

    Attributes:
        atlas: the :class:`~triplet_cl.mesh.bake.UVAtlas` (``N2`` atlas vertices).
        normals: ``[N, 3]`` unit vertex normals of the original vertices.
        base: ``[S, S, 3 or 4] uint8`` base colour (sRGB; RGBA when alpha is baked).
        orm: ``[S, S, 3] uint8`` R = occlusion, G = roughness, B = metallic (linear).
        specular: ``[S, S, 3] uint8`` Blinn-Phong ks (sRGB as the albedo), else ``None``.
        channels: the per-vertex :func:`pbr_channels`.
    """

    atlas: UVAtlas
    normals: np.ndarray
    base: np.ndarray
    orm: np.ndarray
    specular: np.ndarray | None
    channels: dict


def _u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def bake_asset(asset: MeshAsset, texture_size: int = 1024, albedo_space: str = "srgb", with_alpha: bool = False,
               padding: int | None = None, dilate: int | None = None) -> BakedAsset:
    """UV atlas + baked textures of ``asset`` (see the module docstring).

    Args:
        texture_size: width = height of every texture (>= 16). with_alpha: bake alpha into the base
            colour's A channel. padding: texels between charts; None: ``max(2, texture_size // 256)``
            (4 at 1024²). Measured with ``bench/gutter.py`` on a 50k-face marching-cubes Spot (695
            charts, 1024²): the fraction of chart texels whose mip-map block mixes in another chart's
            gutter at mip 2 / 3 / 4 is 0.2 / 4.8 / 24 % with padding 2, 0 / 2.4 / 20 % with 4 (8 %
            fewer texels for the charts), 0 / 0.4 / 14 % with 8 (30 % fewer); with the gutter filled per
            chart (``atlas.face_chart``, :func:`bake.gutter_sources`, the default now) 0 / 0.1 / 7.3 % with
            4. dilate: see :func:`bake.bake`.
    """
    check_asset(asset, "bake_asset")
    if int(texture_size) < 16 or int(texture_size) > 16384:
        raise ValueError(f"texture_size must lie in [16, 16384], got {texture_size}")
    s = int(texture_size)
    ch = pbr_channels(asset, albedo_space)
    atlas = uv_atlas(asset.V, asset.F, s, max(2, s // 256) if padding is None else int(padding))
    face_img, bary = rasterize_uv(atlas.uv, atlas.faces, s, s)
    cols = [ch["base"], ch["ao"][:, None], ch["roughness"][:, None], ch["metallic"][:, None]]
    if with_alpha:
        cols.append(ch["alpha"][:, None])
    spec = None
    spec_attr = get_brdf(asset.brdf).specular
    if spec_attr is not None:
        ks = np.clip(asset.attributes[spec_attr], 0, 1)
        cols.append(srgb_encode(ks) if albedo_space == "linear" else ks)
    values = np.concatenate(cols, 1)[atlas.vmap]  # per atlas vertex
    tex = bake(face_img, bary, atlas.faces, values, dilate=dilate, face_chart=atlas.face_chart)
    base = tex[..., :3] if not with_alpha else np.concatenate([tex[..., :3], tex[..., 6:7]], -1)
    if spec_attr is not None:
        spec = _u8(tex[..., -3:])
    return BakedAsset(atlas, vertex_normals(asset.V, asset.F), _u8(base), _u8(tex[..., 3:6]), spec, ch)


def png_bytes(img: np.ndarray, data: bool = False) -> bytes:
    """Encode ``img [H, W] or [H, W, C] uint8`` (C = 1..4) as PNG bytes through OpenImageIO.

    ``data=True`` (roughness, metallic, ORM maps: linear data, not colour): the colour-space chunks
    OpenImageIO writes (``sRGB``, ``gAMA``, ``cHRM``, ``iCCP``) are removed, so no viewer treats the
    values as sRGB colour."""
    import OpenImageIO as oiio

    img = np.ascontiguousarray(img, np.uint8)
    if img.ndim == 2:
        img = img[..., None]
    h, w, c = img.shape
    with tempfile.TemporaryDirectory(prefix="triplet_png_") as d:
        tmp = os.path.join(d, "image.png")
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise OSError(f"OpenImageIO cannot write PNG files: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        if c == 4:
            spec.attribute("oiio:UnassociatedAlpha", 1)
        if not out.open(tmp, spec) or not out.write_image(img):
            err = out.geterror()
            out.close()
            raise OSError(f"cannot encode a PNG: {err}")
        out.close()
        with open(tmp, "rb") as f:
            raw = f.read()
    return _strip_png_chunks(raw, (b"sRGB", b"gAMA", b"cHRM", b"iCCP")) if data else raw


def _strip_png_chunks(png: bytes, kinds) -> bytes:
    """``png`` without the chunks of the given types (each chunk carries its own CRC: the rest stays valid)."""
    out, i = [png[:8]], 8
    while i + 8 <= len(png):
        n = struct.unpack(">I", png[i:i + 4])[0]
        if png[i + 4:i + 8] not in kinds:
            out.append(png[i:i + 12 + n])
        i += 12 + n
    return b"".join(out)


# ---- GLB -------------------------------------------------------------------------------------
class _GlbBuilder:
    """Collects buffer views / accessors / images into one 4-aligned binary buffer."""

    def __init__(self):
        self.chunks: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        pad = (-self.size) % 4
        if pad:
            self.chunks.append(b"\0" * pad)
            self.size += pad
        v = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.views.append(v)
        self.chunks.append(data)
        self.size += len(data)
        return len(self.views) - 1

    def accessor(self, a: np.ndarray, ctype: int, gltf_type: str, target: int, minmax: bool = False) -> int:
        a = np.ascontiguousarray(a)
        acc = {"bufferView": self.view(a.tobytes(), target), "componentType": ctype, "count": int(len(a)),
               "type": gltf_type}
        if minmax:
            flat = a.reshape(len(a), -1)
            acc["min"] = [float(x) for x in flat.min(0)]
            acc["max"] = [float(x) for x in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def glb(self, doc: dict) -> bytes:
        binary = b"".join(self.chunks)
        binary += b"\0" * ((-len(binary)) % 4)
        doc["buffers"] = [{"byteLength": len(binary)}]
        doc["bufferViews"] = self.views
        doc["accessors"] = self.accessors
        js = json.dumps(doc, separators=(",", ":")).encode()
        js += b" " * ((-len(js)) % 4)
        total = 12 + 8 + len(js) + 8 + len(binary)
        return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
                + struct.pack("<I4s", len(binary), b"BIN\0") + binary)


def glb_bytes(asset: MeshAsset, baked: BakedAsset, alpha_mode: str = "OPAQUE", double_sided: bool = True,
              name: str = "mesh") -> bytes:
    """The GLB file of ``asset`` with its :class:`BakedAsset` textures (see :func:`export_glb`)."""
    at = baked.atlas
    b = _GlbBuilder()
    pos = np.ascontiguousarray(asset.V[at.vmap], np.float32)
    nrm = np.ascontiguousarray(baked.normals[at.vmap], np.float32)
    n2 = len(pos)
    idx_dtype, idx_ctype = (np.uint16, _USHORT) if n2 < 65535 else (np.uint32, _UINT)
    attributes = {
        "POSITION": b.accessor(pos, _FLOAT, "VEC3", _ARRAY_BUFFER, minmax=True),
        "NORMAL": b.accessor(nrm, _FLOAT, "VEC3", _ARRAY_BUFFER),
        "TEXCOORD_0": b.accessor(np.ascontiguousarray(at.uv, np.float32), _FLOAT, "VEC2", _ARRAY_BUFFER),
    }
    indices = b.accessor(_proper(at.faces).astype(idx_dtype).reshape(-1), idx_ctype, "SCALAR", _ELEMENT_ARRAY_BUFFER)
    images = [{"bufferView": b.view(png_bytes(baked.base)), "mimeType": "image/png", "name": "baseColor"},
              {"bufferView": b.view(png_bytes(baked.orm, data=True)), "mimeType": "image/png",
               "name": "occlusionRoughnessMetallic"}]
    material = {
        "name": "material",
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
                                 "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 1.0,
                                 "roughnessFactor": 1.0},
        "doubleSided": bool(double_sided),
        "alphaMode": alpha_mode,
        "extras": {"triplet_cl": {"brdf": asset.brdf,
                                  "orm": "R = occlusion, G = roughness, B = metallic"}},
    }
    brdf = get_brdf(asset.brdf)
    if brdf.gltf_occlusion:
        material["occlusionTexture"] = {"index": 1}
    material["extras"]["triplet_cl"].update(brdf.gltf_extras)
    light_defs, light_nodes = punctual_lights(asset.lights)
    doc = {
        "asset": {"version": "2.0", "generator": GENERATOR},
        "scene": 0,
        "scenes": [{"nodes": list(range(1 + len(light_nodes)))}],
        "nodes": [{"mesh": 0, "name": name}, *light_nodes],
        "meshes": [{"name": name, "primitives": [{"attributes": attributes, "indices": indices, "material": 0,
                                                  "mode": 4}]}],
        "materials": [material],
        "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR, "wrapS": _CLAMP_TO_EDGE,
                      "wrapT": _CLAMP_TO_EDGE}],
        "images": images,
        "textures": [{"sampler": 0, "source": 0}, {"sampler": 0, "source": 1}],
    }
    if light_defs:
        doc["extensionsUsed"] = ["KHR_lights_punctual"]
        doc["extensions"] = {"KHR_lights_punctual": {"lights": light_defs}}
    return b.glb(doc)


def punctual_lights(lights) -> tuple[list[dict], list[dict]]:
    """The point and directional lights as glTF ``KHR_lights_punctual`` lights and their nodes.

    Units: the renderer's Cook-Torrance BRDF carries the 1/π of a physical BRDF, so a point light's
    ``intensity`` (irradiance ``intensity · cos / d²``) is a luminous intensity (candela) and a
    directional light's an illuminance (lux), both on the scale where a pixel value of 1 is a
    radiance of 1 (cd/m²). glTF gets ``intensity = max(rgb)`` and ``color = rgb / max(rgb)``.
    A directional light shines along its node's −Z: the node's +Z is our ``direction`` (surface →
    light). Ambient and SH-environment lights are not punctual (see ``envmap.exr`` / ``lights.json``);
    a point light without falloff has no glTF equivalent and is left out."""
    defs, nodes = [], []
    for lt in lights:
        punctual = lt.gltf_punctual()  # (glTF type, position / direction, rgb intensity) or None
        if punctual is None:
            continue
        kind, where, intensity = punctual
        if kind == "point":
            extra = {"translation": [float(x) for x in where]}
        elif kind == "directional":
            extra = {"rotation": _rotation_z_to(np.asarray(where, np.float64))}
        else:
            raise ValueError(f"punctual_lights: glTF light type {kind!r} of {type(lt).__name__} is not supported")
        rgb = np.maximum(np.asarray(intensity, np.float64), 0.0)
        peak = float(rgb.max())
        color = (rgb / peak).tolist() if peak > 0 else [1.0, 1.0, 1.0]
        i = len(defs)
        defs.append({"type": kind, "name": f"{kind}_{i}", "color": color, "intensity": peak})
        nodes.append({"name": f"light_{i}", **extra, "extensions": {"KHR_lights_punctual": {"light": i}}})
    return defs, nodes


def _rotation_z_to(d: np.ndarray) -> list[float]:
    """Unit quaternion ``[x, y, z, w]`` rotating +Z onto ``d`` (normalised)."""
    n = float(np.linalg.norm(d))
    d = np.array([0.0, 0.0, 1.0]) if n < 1e-12 else d / n
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, d))
    if c < -1 + 1e-9:  # opposite: half a turn about x
        return [1.0, 0.0, 0.0, 0.0]
    axis = np.cross(z, d)
    q = np.array([*axis, 1.0 + c])
    return (q / np.linalg.norm(q)).tolist()


def _proper(faces: np.ndarray) -> np.ndarray:
    """The faces without a repeated corner index (glTF validators flag those triangles)."""
    f = np.asarray(faces)
    return f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]


def _alpha(alpha_mode: str) -> str:
    m = str(alpha_mode).upper()
    if m not in ("OPAQUE", "BLEND"):
        raise ValueError(f"alpha_mode must be 'opaque' or 'blend', got {alpha_mode!r}")
    return m


def export_glb(asset: MeshAsset, path, texture_size: int = 1024, *, albedo_space: str = "srgb",
               alpha_mode: str = "opaque", double_sided: bool = True, baked: BakedAsset | None = None) -> Path:
    """Write ``asset`` as a glTF 2.0 binary: one mesh with POSITION, NORMAL, TEXCOORD_0 and a
    metallic-roughness material with base-colour, metallic-roughness and occlusion textures (PNG,
    embedded), atomically. Faces with a repeated vertex index are left out (also from the OBJ).

    Args:
        asset: the :class:`MeshAsset` (``V [N, 3]``, ``F [M > 0, 3]``, activated attributes).
        path: output ``.glb``. texture_size: texture width = height.
        albedo_space: ``"srgb"`` (trained on sRGB photos, the default) or ``"linear"``.
        alpha_mode: ``"opaque"`` (alpha ignored) or ``"blend"`` (alpha baked into the base colour's A).
        double_sided: glTF ``doubleSided`` (default True: soup-extracted meshes are not always
            consistently oriented).
        baked: a :func:`bake_asset` result to reuse (its texture size and alpha win).
    Returns:
        ``path``.
    """
    check_asset(asset, "export_glb")
    mode = _alpha(alpha_mode)
    if baked is None:
        baked = bake_asset(asset, texture_size, albedo_space, with_alpha=mode == "BLEND")
    if mode == "BLEND" and baked.base.shape[-1] != 4:
        raise ValueError("export_glb: alpha_mode='blend' needs a bake with alpha (bake_asset(..., with_alpha=True))")
    data = glb_bytes(asset, baked, mode, double_sided, Path(path).stem)
    atomic_write_bytes(path, data)
    return Path(path)


# ---- OBJ ---------------------------------------------------------------------------------------
def export_obj(asset: MeshAsset, path, texture_size: int = 1024, *, albedo_space: str = "srgb",
               baked: BakedAsset | None = None) -> list[Path]:
    """Write ``asset`` as Wavefront OBJ + MTL + PNG textures beside it, each file atomically.

    ``<stem>.obj`` (``v`` original vertices, ``vt`` atlas UVs with ``v`` up as OBJ expects, ``vn``,
    ``f v/vt/vn``), ``<stem>.mtl`` with ``map_Kd <stem>_basecolor.png`` (sRGB), the PBR extension
    ``Pr``/``Pm`` (mean roughness / metallic) and ``map_Pr <stem>_roughness.png``,
    ``map_Pm <stem>_metallic.png`` (greyscale, linear); Blinn-Phong also ``Ks``, ``Ns`` and
    ``map_Ks <stem>_specular.png``. Returns the written paths (OBJ first).
    """
    check_asset(asset, "export_obj")
    path = Path(path)
    if baked is None:
        baked = bake_asset(asset, texture_size, albedo_space)
    stem, folder = path.stem, path.parent
    at, ch = baked.atlas, baked.channels
    tex = {f"{stem}_basecolor.png": png_bytes(baked.base[..., :3]),
           f"{stem}_roughness.png": png_bytes(baked.orm[..., 1], data=True),
           f"{stem}_metallic.png": png_bytes(baked.orm[..., 2], data=True)}
    mtl = ["# triplet_cl PBR material (Kd texture sRGB; Pr/Pm textures linear, greyscale)", "newmtl material",
           "Ka 1.000000 1.000000 1.000000", "Kd 1.000000 1.000000 1.000000"]
    brdf = get_brdf(asset.brdf)
    if brdf.specular is not None:
        tex[f"{stem}_specular.png"] = png_bytes(baked.specular)
        e = brdf.specular_exponent(asset.attributes)
        mtl += ["Ks 1.000000 1.000000 1.000000", f"Ns {e:.6f}", f"map_Ks {stem}_specular.png"]
    else:
        mtl += ["Ks 0.000000 0.000000 0.000000"]
    mtl += ["d 1.000000", "illum 2", f"map_Kd {stem}_basecolor.png",
            f"Pr {float(np.mean(ch['roughness'])):.6f}", f"Pm {float(np.mean(ch['metallic'])):.6f}",
            f"map_Pr {stem}_roughness.png", f"map_Pm {stem}_metallic.png", ""]
    V = np.asarray(asset.V, np.float64)
    uv = np.asarray(at.uv, np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # OBJ: v up
    faces = _proper(at.faces)
    fv = at.vmap[faces] + 1
    ft = faces.astype(np.int64) + 1
    f = np.stack([fv, ft, fv], -1).reshape(len(fv), 9)
    body = "".join([
        f"# triplet_cl mesh: {asset.num_vertices} vertices, {asset.num_faces} faces\n",
        f"mtllib {stem}.mtl\n",
        ("v %.7g %.7g %.7g\n" * len(V)) % tuple(V.ravel()),
        ("vt %.7g %.7g\n" * len(uv)) % tuple(uv.ravel()),
        ("vn %.6f %.6f %.6f\n" * len(V)) % tuple(baked.normals.astype(np.float64).ravel()),
        "usemtl material\n",
        ("f %d/%d/%d %d/%d/%d %d/%d/%d\n" * len(f)) % tuple(f.ravel().tolist()),
    ])
    written = []
    for name, data in tex.items():
        atomic_write_bytes(folder / name, data)
        written.append(folder / name)
    atomic_write_bytes(folder / f"{stem}.mtl", "\n".join(mtl).encode())
    atomic_write_bytes(path, body.encode())
    return [path, folder / f"{stem}.mtl", *written]


# ---- PLY ---------------------------------------------------------------------------------------
def export_ply(asset: MeshAsset, path, albedo_space: str = "srgb") -> Path:
    """Binary little-endian PLY of the connected mesh with per-vertex attributes, atomically.

    Vertex properties (float32 unless said): ``x y z``, ``nx ny nz`` (area-weighted unit normals),
    every attribute of the asset (``[N, k]`` as ``name_0 .. name_{k-1}``, e.g. ``albedo_0..2``,
    ``roughness``, ``metallic``, ``ao``, ``alpha``; Blinn-Phong ``ks_*``, ``shininess``, ``ka_*``),
    and ``red green blue`` uchar from the albedo (sRGB-encoded when ``albedo_space="linear"``, as the
    base-colour textures; the float ``albedo_*`` stay as trained); faces ``vertex_indices`` (uchar count, int).
    """
    check_asset(asset, "export_ply")
    n = vertex_normals(asset.V, asset.F)
    attrs = {"nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2], **asset.attributes}
    write_soup_ply(path, asset.V, asset.F, attrs, comment="triplet_cl connected triangle mesh",
                   albedo_space=albedo_space)
    return Path(path)


# ---- everything --------------------------------------------------------------------------------
def export_asset(asset: MeshAsset, out_dir, formats=FORMATS, texture_size: int = 1024, envmap_height: int = 256,
                 *, albedo_space: str = "srgb", alpha_mode: str = "opaque", double_sided: bool = True,
                 envmap: bool | None = None, require_lights: bool = True) -> dict[str, Path]:
    """Write the asset's files into ``out_dir``: ``mesh.glb``, ``mesh.obj`` (+ ``mesh.mtl``,
    ``mesh_*.png``), ``mesh.ply`` as ``formats`` asks, ``lights.json``, and ``envmap.exr`` when the
    asset has an SH environment light.

    Args:
        formats: any of ``"glb"``, ``"obj"``, ``"ply"`` (GLB and OBJ share one bake).
        texture_size, albedo_space, alpha_mode, double_sided: see :func:`export_glb`.
        envmap_height: lat-long height (width 2x). envmap: ``None`` writes it when there is an SH
            environment light; ``True`` requires one (``ValueError`` otherwise); ``False`` skips it.
        require_lights: refuse (``ValueError``) an asset without lights: a trained run always has
            some, so none means a broken hand-over; ``False`` writes an empty ``lights.json``.
    Returns:
        ``{"glb": path, "obj": path, "mtl": path, "ply": path, "lights": path, "envmap": path}`` for
        what was written (``"textures"``: list of the OBJ's PNGs).
    """
    formats = (formats,) if isinstance(formats, str) else tuple(formats)
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ValueError(f"formats must be a non-empty subset of {FORMATS}, got {list(formats)}")
    check_asset(asset, "export_asset")
    mode = _alpha(alpha_mode)
    if require_lights and not asset.lights:
        raise ValueError("export_asset: the asset has no lights (a trained run always has some; pass "
                         "require_lights=False to export the mesh with an empty lights.json)")
    has_env = bool(environment_lights(asset.lights))
    if envmap and not has_env:
        kinds = ", ".join(type(lt).__name__ for lt in asset.lights) or "none"
        raise ValueError(f"export_asset: an envmap was requested but the asset has no SHEnvironmentLight "
                         f"(lights: {kinds})")
    lights_doc = lights_to_json(asset.lights)  # validates the lights before anything is written
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    baked = None
    if "glb" in formats or "obj" in formats:
        baked = bake_asset(asset, texture_size, albedo_space, with_alpha=mode == "BLEND")
    if "glb" in formats:
        paths["glb"] = export_glb(asset, out_dir / "mesh.glb", alpha_mode=mode, double_sided=double_sided,
                                  baked=baked)
    if "obj" in formats:
        obj, mtl, *tex = export_obj(asset, out_dir / "mesh.obj", baked=baked)
        paths.update(obj=obj, mtl=mtl, textures=tex)
    if "ply" in formats:
        paths["ply"] = export_ply(asset, out_dir / "mesh.ply", albedo_space)
    write_json(out_dir / "lights.json", lights_doc)
    paths["lights"] = out_dir / "lights.json"
    if has_env and envmap is not False:
        paths["envmap"] = export_envmap(asset.lights, out_dir / "envmap.exr", envmap_height)
    return paths
