"""A strict checker for the GLB files we write: the rules of the glTF 2.0 specification that the
Khronos glTF-Validator checks for what our exporter emits, in Python, so that they are enforced on
every machine. (The validator itself, a JS tool, runs too where node and its npm package are
installed: ``tests/tools/gltf_validate.js``, ``test_glb_passes_the_khronos_validator``.)

``check_glb(path_or_bytes)`` returns ``(doc, bin)`` or raises ``GltfError`` listing every problem.

Checked:
- GLB container: magic ``glTF``, version 2, total length = file size, chunk 0 JSON (type
  ``0x4E4F534A``) and chunk 1 BIN (``0x004E4942``), chunk lengths multiples of 4.
- ``asset.version == "2.0"``; ``scene``/``scenes``/``nodes``/``meshes`` indices valid.
- buffers: one, no ``uri`` (the GLB-stored buffer), ``byteLength <= BIN length < byteLength + 4``.
- bufferViews: inside the buffer, 4-aligned offsets, ``target`` only 34962/34963, vertex-attribute
  views with 34962, index views with 34963, image views with none; ``byteStride`` 4..252, x4.
- accessors: componentType / type enums, ``count >= 1``, data inside its view, offset aligned to
  the component size; POSITION with ``min``/``max`` equal to the data's; float data finite;
  NORMAL unit length (|len - 1| <= 5e-4, the validator's threshold); TEXCOORD_0 float VEC2.
- primitives: mode 4 (triangles), attributes of one primitive with equal counts, indices SCALAR of
  an unsigned type, count a multiple of 3, every index < vertex count, no triangle with a repeated
  index (the validator only warns; we emit none), no primitive-restart value, material index valid.
- materials: texture indices valid, ``texCoord`` naming an existing TEXCOORD set, factors in
  range, ``alphaMode`` enum; colour space: an image used as base colour (sRGB) is not also used as
  linear data (metallic-roughness, occlusion, normal).
- textures / samplers / images: sampler filter and wrap enums, images in a bufferView with a
  ``mimeType`` of ``image/png`` or ``image/jpeg`` whose bytes carry the matching signature.
- nothing unused: every accessor, bufferView, image, texture, sampler and material is referenced
  (the validator reports unused objects as info; we hold ourselves to none).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np


class GltfError(AssertionError):
    """The GLB breaks one or more rules (all listed in the message)."""


_CTYPES = {5120: (np.int8, 1), 5121: (np.uint8, 1), 5122: (np.int16, 2), 5123: (np.uint16, 2),
           5125: (np.uint32, 4), 5126: (np.float32, 4)}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_MAG = {9728, 9729}
_MIN = {9728, 9729, 9984, 9985, 9986, 9987}
_WRAP = {33071, 33648, 10497}
_SIGS = {"image/png": b"\x89PNG\r\n\x1a\n", "image/jpeg": b"\xff\xd8\xff"}


def read_accessor(doc: dict, binary: bytes, i: int) -> np.ndarray:
    """The data of accessor ``i`` as ``[count, ncomp]`` (tightly packed views only)."""
    acc = doc["accessors"][i]
    view = doc["bufferViews"][acc["bufferView"]]
    dt, size = _CTYPES[acc["componentType"]]
    nc = _NCOMP[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(binary, dt, count=acc["count"] * nc, offset=start)
    return a.reshape(acc["count"], nc)


def check_glb(src) -> tuple[dict, bytes]:
    """Check a GLB (path or bytes); return ``(json document, BIN chunk)`` or raise :class:`GltfError`."""
    data = Path(src).read_bytes() if not isinstance(src, bytes | bytearray) else bytes(src)
    errors: list[str] = []

    def err(msg):
        errors.append(msg)

    if len(data) < 20:
        raise GltfError("GLB: file shorter than the 12-byte header and one chunk header")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF":
        raise GltfError(f"GLB: magic {magic!r} is not b'glTF'")
    if version != 2:
        err(f"GLB: version {version}, expected 2")
    if length != len(data):
        err(f"GLB: header length {length} != file size {len(data)}")
    jlen, jtype = struct.unpack_from("<II", data, 12)
    if jtype != 0x4E4F534A:
        raise GltfError(f"GLB: first chunk type {jtype:#x} is not JSON")
    if jlen % 4:
        err(f"GLB: JSON chunk length {jlen} not a multiple of 4")
    doc = json.loads(data[20:20 + jlen].decode("utf-8"))
    off = 20 + jlen
    binary = b""
    if off < len(data):
        blen, btype = struct.unpack_from("<II", data, off)
        if btype != 0x004E4942:
            err(f"GLB: second chunk type {btype:#x} is not BIN")
        if blen % 4:
            err(f"GLB: BIN chunk length {blen} not a multiple of 4")
        binary = data[off + 8:off + 8 + blen]
        if off + 8 + blen != len(data):
            err("GLB: trailing bytes after the BIN chunk")

    # asset / scene graph
    if doc.get("asset", {}).get("version") != "2.0":
        err(f"asset.version must be '2.0', got {doc.get('asset', {}).get('version')!r}")
    nodes, meshes = doc.get("nodes", []), doc.get("meshes", [])
    scenes = doc.get("scenes", [])
    if "scene" in doc and not 0 <= doc["scene"] < len(scenes):
        err(f"scene {doc['scene']} out of range")
    for s in scenes:
        for n in s.get("nodes", []):
            if not 0 <= n < len(nodes):
                err(f"scene node {n} out of range")
    for i, n in enumerate(nodes):
        if "mesh" in n and not 0 <= n["mesh"] < len(meshes):
            err(f"nodes[{i}].mesh out of range")

    # buffers and views
    buffers = doc.get("buffers", [])
    if len(buffers) != 1 or "uri" in buffers[0]:
        err(f"expected exactly one GLB-stored buffer without uri, got {buffers}")
    blen = buffers[0].get("byteLength", -1) if buffers else -1
    if not (blen <= len(binary) < blen + 4):
        err(f"buffers[0].byteLength {blen} does not match the BIN chunk ({len(binary)} bytes)")
    views = doc.get("bufferViews", [])
    for i, v in enumerate(views):
        o, n = v.get("byteOffset", 0), v.get("byteLength", 0)
        if v.get("buffer") != 0:
            err(f"bufferViews[{i}].buffer must be 0")
        if n < 1 or o < 0 or o + n > blen:
            err(f"bufferViews[{i}] [{o}, {o + n}) outside the buffer of {blen} bytes")
        if o % 4:
            err(f"bufferViews[{i}].byteOffset {o} not 4-aligned")
        if "target" in v and v["target"] not in (34962, 34963):
            err(f"bufferViews[{i}].target {v['target']} invalid")
        if "byteStride" in v and not (4 <= v["byteStride"] <= 252 and v["byteStride"] % 4 == 0):
            err(f"bufferViews[{i}].byteStride {v['byteStride']} invalid")

    # accessors
    accessors = doc.get("accessors", [])
    used_views: dict[int, str] = {}
    for i, a in enumerate(accessors):
        if a.get("componentType") not in _CTYPES:
            err(f"accessors[{i}].componentType {a.get('componentType')} invalid")
            continue
        if a.get("type") not in _NCOMP:
            err(f"accessors[{i}].type {a.get('type')!r} invalid")
            continue
        if a.get("count", 0) < 1:
            err(f"accessors[{i}].count must be >= 1")
        vi = a.get("bufferView")
        if vi is None or not 0 <= vi < len(views):
            err(f"accessors[{i}].bufferView out of range")
            continue
        size = _CTYPES[a["componentType"]][1]
        elem = size * _NCOMP[a["type"]]
        start = views[vi].get("byteOffset", 0) + a.get("byteOffset", 0)
        if start % size:
            err(f"accessors[{i}] offset {start} not aligned to its component size {size}")
        if a.get("byteOffset", 0) + a["count"] * elem > views[vi]["byteLength"]:
            err(f"accessors[{i}] data runs past its bufferView")
            continue
        if a["componentType"] == 5126 and not np.isfinite(read_accessor(doc, binary, i)).all():
            err(f"accessors[{i}] has non-finite floats")

    # meshes
    materials = doc.get("materials", [])
    used_acc, used_mat = set(), set()
    for mi, m in enumerate(meshes):
        for pi, p in enumerate(m.get("primitives", [])):
            where = f"meshes[{mi}].primitives[{pi}]"
            if p.get("mode", 4) != 4:
                err(f"{where}.mode {p.get('mode')} (we emit triangles only)")
            attrs = p.get("attributes", {})
            if "POSITION" not in attrs:
                err(f"{where} has no POSITION")
                continue
            counts = {k: accessors[v]["count"] for k, v in attrs.items() if 0 <= v < len(accessors)}
            if len(set(counts.values())) != 1 or len(counts) != len(attrs):
                err(f"{where} attribute counts differ or indices are invalid: {counts}")
            nvert = counts.get("POSITION", 0)
            for k, ai in attrs.items():
                used_acc.add(ai)
                vi = accessors[ai]["bufferView"]
                used_views[vi] = "vertex"
                if views[vi].get("target") != 34962:
                    err(f"{where}.{k}: bufferView {vi} must have target ARRAY_BUFFER (34962)")
            pa = accessors[attrs["POSITION"]]
            if pa["componentType"] != 5126 or pa["type"] != "VEC3":
                err(f"{where}.POSITION must be float VEC3")
            elif "min" not in pa or "max" not in pa:
                err(f"{where}.POSITION accessor needs min and max")
            else:
                pos = read_accessor(doc, binary, attrs["POSITION"])
                if not (np.array_equal(np.float32(pa["min"]), pos.min(0))
                        and np.array_equal(np.float32(pa["max"]), pos.max(0))):
                    err(f"{where}.POSITION min/max {pa['min']}/{pa['max']} differ from the data "
                        f"{pos.min(0).tolist()}/{pos.max(0).tolist()}")
            if "NORMAL" in attrs:
                na = accessors[attrs["NORMAL"]]
                if na["componentType"] != 5126 or na["type"] != "VEC3":
                    err(f"{where}.NORMAL must be float VEC3")
                else:
                    ln = np.linalg.norm(read_accessor(doc, binary, attrs["NORMAL"]).astype(np.float64), axis=1)
                    if np.abs(ln - 1).max() > 5e-4:
                        err(f"{where}.NORMAL not unit length (max |len-1| = {np.abs(ln - 1).max():.2e})")
            for k in attrs:
                if k.startswith("TEXCOORD_"):
                    ta = accessors[attrs[k]]
                    if ta["type"] != "VEC2" or ta["componentType"] not in (5126, 5121, 5123):
                        err(f"{where}.{k} must be VEC2 float (or normalized ubyte/ushort)")
            if "indices" in p:
                ii = p["indices"]
                used_acc.add(ii)
                ia = accessors[ii]
                vi = ia["bufferView"]
                used_views[vi] = "index"
                if views[vi].get("target") != 34963:
                    err(f"{where}.indices: bufferView {vi} must have target ELEMENT_ARRAY_BUFFER (34963)")
                if ia["type"] != "SCALAR" or ia["componentType"] not in (5121, 5123, 5125):
                    err(f"{where}.indices must be an unsigned SCALAR")
                elif ia["count"] % 3:
                    err(f"{where}.indices count {ia['count']} not a multiple of 3")
                else:
                    idx = read_accessor(doc, binary, ii)
                    if idx.size and int(idx.max()) >= nvert:
                        err(f"{where}.indices reach {int(idx.max())} >= vertex count {nvert}")
                    tri = idx.reshape(-1, 3)
                    ndeg = int(((tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])).sum())
                    if ndeg:
                        err(f"{where}: {ndeg} degenerate triangle(s) (a repeated index)")
                    if ia["componentType"] == 5123 and idx.size and int(idx.max()) == 65535:
                        err(f"{where}.indices use the primitive-restart value 65535")
            if "material" in p:
                if not 0 <= p["material"] < len(materials):
                    err(f"{where}.material out of range")
                used_mat.add(p["material"])
                tex_sets = {int(k.split("_")[1]) for k in attrs if k.startswith("TEXCOORD_")}
                for ref in _texture_refs(materials[p["material"]]):
                    if ref[1].get("texCoord", 0) not in tex_sets:
                        err(f"{where}: material texture {ref[0]} uses a missing TEXCOORD set")

    # materials, textures, samplers, images
    textures, images, samplers = doc.get("textures", []), doc.get("images", []), doc.get("samplers", [])
    srgb_imgs, linear_imgs, used_tex = set(), set(), set()
    for i, m in enumerate(materials):
        pbr = m.get("pbrMetallicRoughness", {})
        f = pbr.get("baseColorFactor", [1, 1, 1, 1])
        if len(f) != 4 or not all(0 <= x <= 1 for x in f):
            err(f"materials[{i}].baseColorFactor {f} invalid")
        for k in ("metallicFactor", "roughnessFactor"):
            if not 0 <= pbr.get(k, 1) <= 1:
                err(f"materials[{i}].{k} out of [0, 1]")
        if m.get("alphaMode", "OPAQUE") not in ("OPAQUE", "MASK", "BLEND"):
            err(f"materials[{i}].alphaMode {m.get('alphaMode')!r} invalid")
        for name, ref in _texture_refs(m):
            t = ref.get("index", -1)
            if not 0 <= t < len(textures):
                err(f"materials[{i}].{name}.index out of range")
                continue
            used_tex.add(t)
            src = textures[t].get("source")
            (srgb_imgs if name in ("baseColorTexture", "emissiveTexture") else linear_imgs).add(src)
    both = srgb_imgs & linear_imgs
    if both:
        err(f"images {sorted(both)} are used both as sRGB colour and as linear data")
    used_img, used_smp = set(), set()
    for i, t in enumerate(textures):
        if not 0 <= t.get("source", -1) < len(images):
            err(f"textures[{i}].source out of range")
        used_img.add(t.get("source"))
        if "sampler" in t:
            if not 0 <= t["sampler"] < len(samplers):
                err(f"textures[{i}].sampler out of range")
            used_smp.add(t["sampler"])
    for i, s in enumerate(samplers):
        if "magFilter" in s and s["magFilter"] not in _MAG:
            err(f"samplers[{i}].magFilter {s['magFilter']} invalid")
        if "minFilter" in s and s["minFilter"] not in _MIN:
            err(f"samplers[{i}].minFilter {s['minFilter']} invalid")
        for k in ("wrapS", "wrapT"):
            if k in s and s[k] not in _WRAP:
                err(f"samplers[{i}].{k} {s[k]} invalid")
    for i, im in enumerate(images):
        if "uri" in im or "bufferView" not in im:
            err(f"images[{i}] must be stored in a bufferView")
            continue
        mt = im.get("mimeType")
        if mt not in _SIGS:
            err(f"images[{i}].mimeType {mt!r} must be image/png or image/jpeg")
            continue
        v = views[im["bufferView"]]
        used_views[im["bufferView"]] = "image"
        if "target" in v:
            err(f"images[{i}]: its bufferView must not have a target")
        head = binary[v.get("byteOffset", 0):v.get("byteOffset", 0) + 8]
        if not head.startswith(_SIGS[mt]):
            err(f"images[{i}] bytes do not start with the {mt} signature")

    # nothing unused
    for kind, used, n in (("accessors", used_acc, len(accessors)), ("bufferViews", set(used_views), len(views)),
                          ("images", used_img, len(images)), ("textures", used_tex, len(textures)),
                          ("samplers", used_smp, len(samplers)), ("materials", used_mat, len(materials))):
        unused = sorted(set(range(n)) - used)
        if unused:
            err(f"unused {kind}: {unused}")
    if errors:
        raise GltfError("invalid GLB:\n  " + "\n  ".join(errors))
    return doc, binary


def _texture_refs(material: dict):
    pbr = material.get("pbrMetallicRoughness", {})
    for k in ("baseColorTexture", "metallicRoughnessTexture"):
        if k in pbr:
            yield k, pbr[k]
    for k in ("normalTexture", "occlusionTexture", "emissiveTexture"):
        if k in material:
            yield k, material[k]
