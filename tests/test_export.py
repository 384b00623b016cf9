"""PBR asset export: UV rasterisation and baking, GLB (strict checker + trimesh + pygltflib + gltfpack),
OBJ + MTL, PLY round trip, the lat-long SH environment map, lights.json, and clear errors."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess

import numpy as np
import pytest
import trimesh

from tests.reference.sh import sh_scipy
from tests.tools.gltf_check import GltfError, check_glb, read_accessor
from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight
from triplet_cl.mesh import MeshAsset
from triplet_cl.mesh.bake import bake, rasterize_uv, uv_atlas, vertex_normals
from triplet_cl.mesh.envmap import (
    eval_environment,
    export_envmap,
    latlong_directions,
    latlong_uv,
    project_envmap,
    read_envmap_sh,
    render_envmap,
    sh_basis,
)
from triplet_cl.mesh.export import (
    blinn_phong_roughness,
    export_asset,
    export_glb,
    export_obj,
    export_ply,
    lights_from_json,
    lights_to_json,
    srgb_encode,
)

TEX = 128
# four separate cubes, each with constant material values
REGIONS = {
    "albedo": np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.2, 0.3, 0.9], [0.7, 0.7, 0.1]]),
    "roughness": np.array([0.2, 0.4, 0.6, 0.8]),
    "metallic": np.array([0.0, 0.33, 0.66, 1.0]),
    "ao": np.array([1.0, 0.8, 0.6, 0.4]),
}
OFFSETS = np.array([-4.5, -1.5, 1.5, 4.5])


def _lights(rng):
    coeffs = rng.normal(scale=0.3, size=(3, 9))
    coeffs[:, 0] += 2.0
    return [PointLight([0, 3, 1], [2, 2, 2]), AmbientLight([0.1, 0.1, 0.1]), SHEnvironmentLight(coeffs)]


def _region_asset(rng, lights=True) -> MeshAsset:
    Vs, Fs, region = [], [], []
    for r, x in enumerate(OFFSETS):
        box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
        Fs.append(box.faces + sum(len(v) for v in Vs))
        Vs.append(box.vertices + (x, 0, 0))
        region.append(np.full(len(box.vertices), r))
    region = np.concatenate(region)
    attrs = {k: v[region] for k, v in REGIONS.items()}
    attrs["alpha"] = np.ones(len(region))
    return MeshAsset(np.concatenate(Vs), np.concatenate(Fs), attrs, "cook_torrance", _lights(rng) if lights else [])


def _region_of(points):
    return np.argmin(np.abs(points[:, :1] - OFFSETS[None]), axis=1)


def _sphere_asset(rng, brdf="cook_torrance") -> MeshAsset:
    m = trimesh.creation.icosphere(subdivisions=3)
    V = m.vertices
    n = len(V)
    if brdf == "cook_torrance":
        attrs = {"albedo": 0.5 + 0.4 * V, "roughness": 0.5 + 0.4 * V[:, 1], "metallic": 0.5 - 0.4 * V[:, 2],
                 "ao": 0.75 + 0.2 * V[:, 0], "alpha": 0.6 + 0.3 * V[:, 2]}
    else:
        attrs = {"albedo": 0.5 + 0.4 * V, "ks": np.full((n, 3), 0.3), "shininess": 10 + 20 * (V[:, 1] + 1),
                 "ka": np.full((n, 3), 0.2)}
    return MeshAsset(V, m.faces, attrs, brdf, _lights(rng))


def _bilinear(img, uv_up):
    """Sample ``img [H, W, C]`` at trimesh-convention UVs (v up) with bilinear filtering, clamped."""
    img = np.asarray(img, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    h, w = img.shape[:2]
    x = np.clip(uv_up[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv_up[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def _loaded_geometry(path):
    scene = trimesh.load(path, process=False)
    geoms = list(scene.geometry.values()) if isinstance(scene, trimesh.Scene) else [scene]
    assert len(geoms) == 1
    return geoms[0]


def _centroid_uvs(g):
    """Face centroids (3D) and their UVs (trimesh convention) of a loaded textured mesh."""
    uv = np.asarray(g.visual.uv, np.float64)
    return g.vertices[g.faces].mean(1), uv[g.faces].mean(1)


# ---- baking ------------------------------------------------------------------------------------
def test_rasterize_and_bake_reproduce_a_linear_function():
    # two triangles covering the unit square: every texel centre is covered and a function linear in
    # uv bakes exactly (barycentric interpolation is exact for linear functions)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    face, bary = rasterize_uv(uv, F, 40, 24)
    assert (face >= 0).all()
    vals = np.stack([0.2 + 0.5 * uv[:, 0], 0.9 - 0.6 * uv[:, 1]], 1)
    tex = bake(face, bary, F, vals)
    jj, ii = np.meshgrid((np.arange(40) + 0.5) / 40, (np.arange(24) + 0.5) / 24)
    np.testing.assert_allclose(tex[..., 0], 0.2 + 0.5 * jj, atol=1e-5)
    np.testing.assert_allclose(tex[..., 1], 0.9 - 0.6 * ii, atol=1e-5)
    # a small triangle in one corner: texels whose centre is inside get the exact interpolation, the
    # texels it only overlaps its clamped values, the rest the value of a nearest reached texel
    uv2 = np.array([[0.05, 0.05], [0.5, 0.05], [0.05, 0.5]], np.float32)
    F2, vals2 = np.array([[0, 1, 2]]), np.array([[1.0], [2.0], [3.0]])
    face2, bary2 = rasterize_uv(uv2, F2, 32, 32)
    cx, cy = np.meshgrid((np.arange(32) + 0.5) / 32, (np.arange(32) + 0.5) / 32)
    w1, w2 = (cx - 0.05) / 0.45, (cy - 0.05) / 0.45
    centre_in = (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
    reached = face2 >= 0
    assert 80 < centre_in.sum() < 140  # area (0.45^2 / 2) * 32^2 ~ 104 texels
    assert reached[centre_in].all() and 0 < (reached & ~centre_in).sum() < 60  # a one-texel rim
    tex2 = bake(face2, bary2, F2, vals2)[..., 0]
    np.testing.assert_allclose(tex2[centre_in], (1 + w1 + 2 * w2)[centre_in], atol=1e-5)
    assert (tex2 >= 1 - 1e-6).all() and (tex2 <= 3 + 1e-6).all()
    cov = np.argwhere(reached)
    for i, j in np.argwhere(~reached):  # each empty texel holds the value of one of its nearest reached texels
        d2 = ((cov - (i, j)) ** 2).sum(1)
        assert np.isclose(tex2[i, j], tex2[tuple(cov[d2 == d2.min()].T)]).any()
    limited = bake(face2, bary2, F2, vals2, dilate=2, fill=[-1.0])
    assert limited[31, 31, 0] == -1.0
    ring = (~reached) & (limited[..., 0] != -1.0)
    assert ring.any() and np.allclose(limited[ring, 0], tex2[ring])
    np.testing.assert_array_equal(limited[reached, 0], tex2[reached])


def test_rasterize_gives_every_face_a_texel():
    # 200 slivers and specks far smaller than a texel, between the texel centres: each owns a texel
    rng = np.random.default_rng(12)
    n = 200
    cell = rng.choice(64 * 64, size=n, replace=False)
    corner = np.stack([cell % 64, cell // 64], 1) + 0.55  # just past a texel centre
    tri = corner[:, None] + rng.uniform(0, 0.3, size=(n, 3, 2))
    uv = (tri / 64).reshape(-1, 2)
    face, bary = rasterize_uv(uv, np.arange(3 * n).reshape(n, 3), 64, 64)
    assert set(np.unique(face[face >= 0])) == set(range(n))
    assert np.allclose(bary[face >= 0].sum(-1), 1) and (bary >= 0).all()


@pytest.mark.parametrize("piece_faces", [None, 150])
def test_uv_atlas_pieces_keep_faces_and_do_not_overlap(piece_faces):
    m = trimesh.creation.icosphere(subdivisions=3)  # 1280 faces: 9 pieces of ~150
    at = uv_atlas(m.vertices, m.faces, 256, piece_faces=piece_faces)
    np.testing.assert_array_equal(at.vmap[at.faces], m.faces)  # same faces, same order
    assert at.uv.min() >= 0 and at.uv.max() <= 1
    # no two UV triangles overlap: random points lie in at most one (up to shared edges)
    tri = at.uv[at.faces].astype(np.float64)  # [M, 3, 2]
    pts = np.random.default_rng(13).random((4000, 2))
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    q = pts[:, None] - a[None]
    w1 = (q[..., 0] * e2[:, 1] - q[..., 1] * e2[:, 0]) / det
    w2 = (e1[:, 0] * q[..., 1] - e1[:, 1] * q[..., 0]) / det
    inside = (w1 > 1e-6) & (w2 > 1e-6) & (w1 + w2 < 1 - 1e-6)
    assert inside.sum(1).max() == 1
    assert inside.any(1).mean() > 0.3  # the charts cover a good part of the atlas


def test_vertex_normals_area_weighted_and_unit():
    m = trimesh.creation.icosphere(subdivisions=2)
    n = vertex_normals(m.vertices, m.faces)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-6)
    assert (np.sum(n * m.vertices, 1) > 0.99).all()  # close to the sphere's radial direction
    # an isolated vertex (no face) still gets a unit normal
    n2 = vertex_normals(np.vstack([m.vertices, [[5, 5, 5]]]), m.faces)
    assert np.isclose(np.linalg.norm(n2[-1]), 1)


# ---- GLB ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def region_glb(tmp_path_factory):
    rng = np.random.default_rng(0)
    asset = _region_asset(rng)
    path = export_glb(asset, tmp_path_factory.mktemp("glb") / "mesh.glb", texture_size=TEX)
    return asset, path


def test_glb_passes_the_checker(region_glb):
    asset, path = region_glb
    doc, binary = check_glb(path)
    prim = doc["meshes"][0]["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "TEXCOORD_0"}
    mat = doc["materials"][0]
    pbr = mat["pbrMetallicRoughness"]
    assert doc["textures"][pbr["baseColorTexture"]["index"]]["source"] == 0
    assert mat["occlusionTexture"]["index"] == pbr["metallicRoughnessTexture"]["index"]  # one ORM image
    pos = read_accessor(doc, binary, prim["attributes"]["POSITION"])
    assert {tuple(p) for p in pos} == {tuple(p) for p in asset.V}  # only split at seams, nothing moved
    assert read_accessor(doc, binary, prim["indices"]).size == 3 * asset.num_faces


def test_glb_textures_hold_the_regions_values(region_glb):
    _, path = region_glb
    g = _loaded_geometry(path)
    mat = g.visual.material
    base = np.asarray(mat.baseColorTexture)
    orm = np.asarray(mat.metallicRoughnessTexture)
    occ = np.asarray(mat.occlusionTexture)
    assert base.shape == (TEX, TEX, 3) and orm.shape == (TEX, TEX, 3)
    np.testing.assert_array_equal(orm, occ)
    cent, cuv = _centroid_uvs(g)
    r = _region_of(cent)
    assert set(r) == {0, 1, 2, 3}
    tol = 0.6 / 255
    np.testing.assert_allclose(_bilinear(base, cuv) / 255, REGIONS["albedo"][r], atol=tol)
    got = _bilinear(orm, cuv) / 255
    np.testing.assert_allclose(got[:, 0], REGIONS["ao"][r], atol=tol)  # R = occlusion
    np.testing.assert_allclose(got[:, 1], REGIONS["roughness"][r], atol=tol)  # G = roughness
    np.testing.assert_allclose(got[:, 2], REGIONS["metallic"][r], atol=tol)  # B = metallic
    # at the chart corners too: the dilation keeps bilinear filtering inside the chart's values
    rv = _region_of(g.vertices)
    np.testing.assert_allclose(_bilinear(base, np.asarray(g.visual.uv)) / 255, REGIONS["albedo"][rv], atol=tol)


def test_glb_smooth_attributes_and_blend_alpha(tmp_path):
    rng = np.random.default_rng(1)
    asset = _sphere_asset(rng)
    path = export_glb(asset, tmp_path / "s.glb", texture_size=256, alpha_mode="blend")
    doc, _ = check_glb(path)
    assert doc["materials"][0]["alphaMode"] == "BLEND"
    g = _loaded_geometry(path)
    base = np.asarray(g.visual.material.baseColorTexture)
    assert base.shape == (256, 256, 4)
    cent, cuv = _centroid_uvs(g)
    # the loaded vertices are the asset's (split at seams): interpolate the known linear fields
    exp_rgb = 0.5 + 0.4 * cent
    exp_a = 0.6 + 0.3 * cent[:, 2]
    got = _bilinear(base, cuv) / 255
    assert np.abs(got[:, :3] - exp_rgb).max() < 0.02
    assert np.abs(got[:, 3] - exp_a).max() < 0.02
    orm = _bilinear(np.asarray(g.visual.material.metallicRoughnessTexture), cuv) / 255
    assert np.abs(orm[:, 1] - (0.5 + 0.4 * cent[:, 1])).max() < 0.02
    assert np.abs(orm[:, 2] - (0.5 - 0.4 * cent[:, 2])).max() < 0.02
    # normals: area-weighted, close to radial on the sphere
    assert (np.sum(g.vertex_normals * g.vertices, 1) > 0.98).all()


def test_glb_blinn_phong_and_linear_albedo(tmp_path):
    rng = np.random.default_rng(2)
    asset = _sphere_asset(rng, "blinn_phong")
    path = export_glb(asset, tmp_path / "bp.glb", texture_size=128, albedo_space="linear")
    doc, _ = check_glb(path)
    assert "occlusionTexture" not in doc["materials"][0]
    g = _loaded_geometry(path)
    cent, cuv = _centroid_uvs(g)
    orm = _bilinear(np.asarray(g.visual.material.metallicRoughnessTexture), cuv) / 255
    rough = blinn_phong_roughness(10 + 20 * (cent[:, 1] + 1))
    assert np.abs(orm[:, 1] - rough).max() < 0.02 and np.abs(orm[:, 2]).max() < 1e-9
    base = _bilinear(np.asarray(g.visual.material.baseColorTexture), cuv) / 255
    assert np.abs(base - srgb_encode(0.5 + 0.4 * cent)).max() < 0.03
    # OBJ: ks as map_Ks, the mean exponent as Ns; PLY keeps the Blinn-Phong attributes
    paths = export_asset(asset, tmp_path / "bp", formats=("obj", "ply"), texture_size=64)
    mtl = paths["mtl"].read_text()
    assert "map_Ks mesh_specular.png" in mtl and (tmp_path / "bp" / "mesh_specular.png").is_file()
    ns = float(next(line.split()[1] for line in mtl.splitlines() if line.startswith("Ns ")))
    assert np.isclose(ns, np.mean(asset.attributes["shininess"] + 1), rtol=1e-5)
    raw = trimesh.load(paths["ply"], process=False).metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_array_equal(raw["shininess"], asset.attributes["shininess"])
    np.testing.assert_array_equal(raw["ks_2"], asset.attributes["ks"][:, 2])
    # the formula: exponent e = s + 1, a^2 = 2 / (e + 2), roughness = sqrt(a)
    s = np.array([0.0, 7.0, 1000.0])
    np.testing.assert_allclose(blinn_phong_roughness(s) ** 4, 2 / (s + 3))


def test_glb_and_obj_leave_out_index_degenerate_faces(tmp_path):
    rng = np.random.default_rng(9)
    a = _region_asset(rng)
    bad = MeshAsset(a.V, np.vstack([a.F, [[0, 0, 1]], [[2, 3, 2]]]), a.attributes, lights=a.lights)
    doc, binary = check_glb(export_glb(bad, tmp_path / "d.glb", texture_size=64))
    assert read_accessor(doc, binary, doc["meshes"][0]["primitives"][0]["indices"]).size == 3 * a.num_faces
    obj = export_obj(bad, tmp_path / "d.obj", texture_size=64)[0]
    assert sum(line.startswith("f ") for line in obj.read_text().splitlines()) == a.num_faces


def test_glb_second_parser_pygltflib(region_glb):
    pygltflib = pytest.importorskip("pygltflib", reason="pygltflib not installed (pip install pygltflib)")
    asset, path = region_glb
    g = pygltflib.GLTF2().load_binary(str(path))
    blob = g.binary_blob()
    prim = g.meshes[0].primitives[0]
    acc = g.accessors[prim.attributes.POSITION]
    view = g.bufferViews[acc.bufferView]
    pos = np.frombuffer(blob, np.float32, acc.count * 3, view.byteOffset + (acc.byteOffset or 0)).reshape(-1, 3)
    np.testing.assert_allclose(acc.min, pos.min(0))
    np.testing.assert_allclose(acc.max, pos.max(0))
    assert [im.mimeType for im in g.images] == ["image/png", "image/png"]
    assert g.materials[0].pbrMetallicRoughness.metallicRoughnessTexture.index == 1
    assert g.asset.version == "2.0"


def test_glb_third_parser_gltfpack(region_glb, tmp_path):
    exe = shutil.which("gltfpack")
    if exe is None:
        pytest.skip("gltfpack not installed (apt-get install gltfpack)")
    asset, path = region_glb
    # -noq: no KHR_mesh_quantization, so that our checker (core glTF only) can read the output too
    res = subprocess.run([exe, "-i", str(path), "-o", str(tmp_path / "packed.glb"), "-noq", "-v"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert f"input: 1 mesh primitives ({asset.num_faces} triangles" in res.stdout
    doc, _ = check_glb(path)
    png_bytes = sum(doc["bufferViews"][im["bufferView"]]["byteLength"] for im in doc["images"])
    assert f"image {png_bytes} bytes" in res.stdout  # both embedded PNGs were read and carried over
    check_glb(tmp_path / "packed.glb")  # and our checker accepts a third party's GLB


def _khronos_validate(paths) -> list[dict]:
    """Reports of the Khronos glTF-Validator (tests/tools/gltf_validate.js) or a pytest skip when
    node or the npm package is missing (NODE_PATH, or ~/.cache/triplet_cl/node/node_modules)."""
    import os
    from pathlib import Path

    node = shutil.which("node")
    if node is None:
        pytest.skip("node not installed: the Khronos glTF-Validator needs it")
    env = dict(os.environ)
    env["NODE_PATH"] = os.pathsep.join(filter(None, [env.get("NODE_PATH"),
                                                     str(Path.home() / ".cache/triplet_cl/node/node_modules")]))
    script = Path(__file__).parent / "tools" / "gltf_validate.js"
    res = subprocess.run([node, str(script), *map(str, paths)], capture_output=True, text=True, env=env,
                         timeout=120)
    if res.returncode == 2:
        pytest.skip("Khronos glTF-Validator not installed: npm install --prefix ~/.cache/triplet_cl/node "
                    "gltf-validator")
    return [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{")]


def test_glb_passes_the_khronos_validator(region_glb, tmp_path):
    rng = np.random.default_rng(14)
    blend = export_glb(_sphere_asset(rng), tmp_path / "blend.glb", texture_size=64, alpha_mode="blend")
    bp = export_glb(_sphere_asset(rng, "blinn_phong"), tmp_path / "bp.glb", texture_size=64)
    broken = tmp_path / "broken.glb"  # and the harness does see errors
    broken.write_bytes(_replace_json(region_glb[1].read_bytes(),
                                     lambda d: d["accessors"][0].__setitem__("max", [9.0, 9.0, 9.0])))
    reports = _khronos_validate([region_glb[1], blend, bp, broken])
    assert len(reports) == 4
    for r in reports[:3]:
        assert (r["errors"], r["warnings"], r["infos"], r["hints"]) == (0, 0, 0, 0), r
    assert reports[3]["errors"] > 0 and any("ACCESSOR_MAX_MISMATCH" in m for m in reports[3]["messages"])


def _replace_json(glb: bytes, edit) -> bytes:
    jlen = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20:20 + jlen])
    edit(doc)
    js = json.dumps(doc).encode()
    js += b" " * ((-len(js)) % 4)
    rest = glb[20 + jlen:]
    head = struct.pack("<4sII", b"glTF", 2, 20 + len(js) + len(rest)) + struct.pack("<I4s", len(js), b"JSON")
    return head + js + rest


@pytest.mark.parametrize("edit,msg", [
    (lambda d: d["accessors"][0].__setitem__("max", [9.0, 9.0, 9.0]), "min/max"),
    (lambda d: d["accessors"][0].pop("min"), "needs min and max"),
    (lambda d: d["asset"].__setitem__("version", "1.0"), "asset.version"),
    (lambda d: d["samplers"][0].__setitem__("minFilter", 1234), "minFilter"),
    (lambda d: d["images"][0].__setitem__("mimeType", "image/bmp"), "mimeType"),
    (lambda d: d["bufferViews"][0].pop("target"), "ARRAY_BUFFER"),
    (lambda d: d["materials"][0]["pbrMetallicRoughness"]["metallicRoughnessTexture"].__setitem__("index", 0),
     "sRGB colour and as linear"),
    (lambda d: d["accessors"][3].__setitem__("count", 10), "multiple of 3"),
])
def test_checker_catches_broken_files(region_glb, edit, msg):
    data = region_glb[1].read_bytes()
    with pytest.raises(GltfError, match=msg):
        check_glb(_replace_json(data, edit))


# ---- OBJ / PLY ---------------------------------------------------------------------------------
def test_obj_mtl_textures_reload(tmp_path):
    rng = np.random.default_rng(3)
    asset = _region_asset(rng)
    obj, mtl, *tex = export_obj(asset, tmp_path / "mesh.obj", texture_size=TEX)
    text = mtl.read_text()
    for key in ("map_Kd mesh_basecolor.png", "map_Pr mesh_roughness.png", "map_Pm mesh_metallic.png", "\nPr ",
                "\nPm "):
        assert key in text
    assert all(p.is_file() for p in tex)
    g = trimesh.load(obj, process=False)
    assert len(g.faces) == asset.num_faces
    img = np.asarray(g.visual.material.image)
    assert img.shape[:2] == (TEX, TEX)
    cent, cuv = _centroid_uvs(g)
    r = _region_of(cent)
    np.testing.assert_allclose(_bilinear(img[..., :3], cuv) / 255, REGIONS["albedo"][r], atol=0.6 / 255)
    from PIL import Image

    rough = np.asarray(Image.open(tmp_path / "mesh_roughness.png"))
    metal = np.asarray(Image.open(tmp_path / "mesh_metallic.png"))
    assert rough.ndim == 2  # greyscale
    np.testing.assert_allclose(_bilinear(rough, cuv)[:, 0] / 255, REGIONS["roughness"][r], atol=0.6 / 255)
    np.testing.assert_allclose(_bilinear(metal, cuv)[:, 0] / 255, REGIONS["metallic"][r], atol=0.6 / 255)
    # v lines are the original vertices, in order
    v = np.array([line.split()[1:] for line in obj.read_text().splitlines() if line.startswith("v ")], float)
    np.testing.assert_allclose(v, asset.V, rtol=1e-6)


def test_ply_round_trips_attributes(tmp_path):
    rng = np.random.default_rng(4)
    asset = _sphere_asset(rng)
    path = export_ply(asset, tmp_path / "mesh.ply")
    m = trimesh.load(path, process=False)
    np.testing.assert_array_equal(np.asarray(m.vertices, np.float32), asset.V)
    np.testing.assert_array_equal(m.faces, asset.F)
    raw = m.metadata["_ply_raw"]["vertex"]["data"]
    for name, a in asset.attributes.items():
        a = a.reshape(len(a), -1)
        cols = [name] if a.shape[1] == 1 else [f"{name}_{i}" for i in range(a.shape[1])]
        np.testing.assert_array_equal(np.stack([raw[c] for c in cols], 1), a)
    rgb = np.stack([raw[c] for c in ("red", "green", "blue")], 1)
    np.testing.assert_array_equal(rgb, (asset.attributes["albedo"] * 255 + 0.5).astype(np.uint8))
    n = np.stack([raw[c] for c in ("nx", "ny", "nz")], 1)
    np.testing.assert_allclose(n, vertex_normals(asset.V, asset.F))


# ---- environment map ---------------------------------------------------------------------------
def test_sh_basis_matches_scipy_definition():
    rng = np.random.default_rng(5)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(sh_basis(8, d), sh_scipy(8, d), atol=1e-10)


def test_latlong_convention():
    d = latlong_directions(8)
    assert d.shape == (8, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1)
    assert d[0, :, 1].min() > 0.9 and d[-1, :, 1].max() < -0.9  # top row +Y, bottom row -Y
    # u: -Z at the left edge, +X a quarter across, +Z in the centre, -X at three quarters
    np.testing.assert_allclose(latlong_uv([[0, 0, -1], [1, 0, 0], [0, 0, 1], [-1, 0, 0]])[:, 0],
                               [0.0, 0.25, 0.5, 0.75], atol=1e-12)
    np.testing.assert_allclose(latlong_uv([[1, 0, 0], [0, 1, 0], [0, -1, 0]])[:, 1], [0.5, 0.0, 1.0])
    h = 16
    uv = latlong_uv(latlong_directions(h))
    jj, ii = np.meshgrid((np.arange(2 * h) + 0.5) / (2 * h), (np.arange(h) + 0.5) / h)
    np.testing.assert_allclose(uv[..., 0], jj, atol=1e-12)
    np.testing.assert_allclose(uv[..., 1], ii, atol=1e-12)


@pytest.mark.parametrize("dtype,rtol", [("float", 1e-6), ("half", 1e-3)])
def test_envmap_pixels_equal_sh_evaluation(tmp_path, dtype, rtol):
    import OpenImageIO as oiio

    rng = np.random.default_rng(6)
    coeffs = rng.normal(scale=0.2, size=(3, 16))
    coeffs[:, 0] = [3.0, 2.5, 2.0]
    lights = [PointLight(), SHEnvironmentLight(coeffs, degree=2), SHEnvironmentLight.constant([0.1, 0.2, 0.3])]
    path = export_envmap(lights, tmp_path / "env.exr", height=32, dtype=dtype)
    img = oiio.ImageInput.open(str(path))
    assert img.spec().width == 64 and img.spec().height == 32 and img.spec().nchannels == 3
    pix = img.read_image("float")
    img.close()
    # independent: scipy SH of the pixel-centre directions, active bands only, both lights summed
    d = latlong_directions(32)
    want = sh_scipy(2, d) @ coeffs[:, :9].T + np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(pix, np.maximum(want, 0), rtol=rtol, atol=1e-6)
    np.testing.assert_allclose(eval_environment(lights, d), want, atol=1e-10)
    # a pure +Y lobe (Y_{1,-1} = -c y): brightest on the top row, as the convention says
    lobe = np.zeros((3, 4))
    lobe[:, 0], lobe[:, 1] = 2.0, -1.0
    top = eval_environment([SHEnvironmentLight(lobe)], latlong_directions(8))[..., 0]
    assert top[0].mean() > top[-1].mean()


def test_envmap_convention_matches_mitsuba(tmp_path):
    # the test scenes were rendered by Mitsuba 3's envmap emitter: our EXR, loaded by it, gives back
    # our SH radiance in the same world directions (bilinear lookup: small error away from the poles)
    mi = pytest.importorskip("mitsuba", reason="mitsuba not installed")
    import drjit as dr

    mi.set_variant("scalar_rgb")
    c = np.zeros((3, 4))
    c[:, 0] = 3.0
    c[0, 3], c[1, 1], c[2, 2] = -2.0, -2.0, 2.0  # red towards +X, green towards +Y, blue towards +Z
    lt = SHEnvironmentLight(c)
    path = export_envmap([lt], tmp_path / "env.exr", height=128, dtype="float")
    emitter = mi.load_dict({"type": "envmap", "filename": str(path)})
    rng = np.random.default_rng(11)
    dirs = np.vstack([np.eye(3), -np.eye(3), rng.normal(size=(20, 3))])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for d in dirs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*(-d))  # wi points back along the ray that left towards d
        got = np.array(emitter.eval(si), np.float64).ravel()
        np.testing.assert_allclose(got, np.maximum(eval_environment([lt], d), 0), atol=0.02)


def test_project_envmap_inverts_render_envmap(tmp_path):
    rng = np.random.default_rng(10)
    coeffs = rng.normal(scale=0.3, size=(3, 16))
    coeffs[:, 0] = 4.0  # positive everywhere: nothing clamped
    lt = SHEnvironmentLight(coeffs)
    img = render_envmap([lt], height=64)
    assert img.min() > 0
    np.testing.assert_allclose(project_envmap(img, 3), coeffs, atol=2e-3)
    # through a file, and a higher requested degree finds (almost) nothing above the band limit
    export_envmap([lt], tmp_path / "e.exr", height=64, dtype="float")
    c5 = read_envmap_sh(tmp_path / "e.exr", 5)
    np.testing.assert_allclose(c5[:, :16], coeffs, atol=2e-3)
    assert np.abs(c5[:, 16:]).max() < 2e-3


@pytest.mark.parametrize("name", ["overcast_soil_puresky_1k.hdr"])
def test_project_shared_envmap(shared_data, name):
    # the ground-truth map of the bob_env scene: its SH projection re-rendered is its low-pass
    # version, whose mean radiance equals the map's mean over the sphere (the DC term)
    from triplet_cl.datasets.images import read_image

    img = read_image(shared_data / "envmaps" / name, downscale=4).rgb.astype(np.float64)
    c = project_envmap(img, 2)
    h = img.shape[0]
    sin_t = np.sin(np.pi * (np.arange(h) + 0.5) / h)[:, None, None]
    mean = (img * sin_t).sum((0, 1)) / (sin_t.sum() * img.shape[1])
    np.testing.assert_allclose(c[:, 0] / np.sqrt(4 * np.pi), mean, rtol=1e-3)
    up = eval_environment([SHEnvironmentLight(c)], [[0, 1, 0]])[0]
    down = eval_environment([SHEnvironmentLight(c)], [[0, -1, 0]])[0]
    assert up.sum() > down.sum()  # a sky above soil: brighter from +Y, the convention's up


# ---- everything, lights, errors ----------------------------------------------------------------
def test_export_asset_writes_all_files(tmp_path):
    rng = np.random.default_rng(7)
    asset = _region_asset(rng)
    paths = export_asset(asset, tmp_path / "out", texture_size=64, envmap_height=16)
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == ["envmap.exr", "lights.json", "mesh.glb", "mesh.mtl", "mesh.obj", "mesh.ply",
                     "mesh_basecolor.png", "mesh_metallic.png", "mesh_roughness.png"]
    assert set(paths) == {"glb", "obj", "mtl", "textures", "ply", "lights", "envmap"}
    check_glb(paths["glb"])
    back = lights_from_json(json.loads(paths["lights"].read_text()))
    assert [type(x) for x in back] == [type(x) for x in asset.lights]
    np.testing.assert_array_equal(back[2].coeffs, asset.lights[2].coeffs)
    np.testing.assert_array_equal(back[0].position, asset.lights[0].position)
    assert lights_to_json(back) == lights_to_json(asset.lights)
    # only the PLY, no envmap without an SH environment light
    asset2 = MeshAsset(asset.V, asset.F, asset.attributes, lights=[DirectionalLight()])
    p2 = export_asset(asset2, tmp_path / "ply_only", formats="ply")
    assert set(p2) == {"ply", "lights"}


def test_clear_errors_and_nothing_written(tmp_path):
    rng = np.random.default_rng(8)
    good = _region_asset(rng)
    empty = MeshAsset(good.V, np.zeros((0, 3), np.int32), good.attributes, lights=good.lights)
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="no faces"):
        export_asset(empty, out)
    with pytest.raises(ValueError, match="no faces"):
        export_glb(empty, out / "mesh.glb")
    with pytest.raises(ValueError, match="no faces"):
        export_ply(empty, out / "mesh.ply")
    far = good.V.copy()
    far[3] = 1e12  # xatlas's chart packing ran for ever on such a vertex
    with pytest.raises(ValueError, match="vertex 3 lies 1.73e\\+12"):
        export_asset(MeshAsset(far, good.F, good.attributes, lights=good.lights), out)
    with pytest.raises(ValueError, match="has no lights"):
        export_asset(_region_asset(rng, lights=False), out)
    with pytest.raises(ValueError, match="no SHEnvironmentLight"):
        export_asset(MeshAsset(good.V, good.F, good.attributes, lights=[PointLight()]), out, envmap=True)
    with pytest.raises(ValueError, match="no SHEnvironmentLight"):
        export_envmap([PointLight(), AmbientLight()], out / "env.exr")
    with pytest.raises(ValueError, match="formats must be"):
        export_asset(good, out, formats=("glb", "fbx"))
    with pytest.raises(ValueError, match="alpha_mode"):
        export_asset(good, out, alpha_mode="mask")
    bad = _region_asset(rng)
    bad.attributes["roughness"][3] = np.nan  # mutated after construction
    with pytest.raises(ValueError, match=r"attributes\['roughness'\] must be finite"):
        export_asset(bad, out)
    nan_light = _region_asset(rng)
    nan_light.lights[0].position[1] = np.inf
    with pytest.raises(ValueError, match=r"lights\[0\] \(PointLight\).position must be finite"):
        export_asset(nan_light, out)
    with pytest.raises(TypeError, match="MeshAsset"):
        export_ply({"V": good.V}, out / "x.ply")
    with pytest.raises(ValueError, match="lights\\[0\\].type"):
        lights_from_json({"lights": [{"type": "Sun"}]})
    assert not out.exists() or not any(out.iterdir())  # every failure came before any write


def test_gutter_is_filled_per_chart_for_mip_maps():
    """Issue 21 (Eevee speckles): chart A covers columns 0-2, chart B columns 9-15 of a 16² texture. The
    nearest-texel fill gives columns 6-7 to B, so the 8×8 mip block over columns 0-7 averages B's value into
    A's texels; the per-chart fill gives them to A (the block holds A's texels only), and every texel next to
    a chart (what bilinear filtering reads) still takes that chart's value."""
    from triplet_cl.mesh.bake import bake, gutter_sources

    face_img = np.full((16, 16), -1, np.int32)
    face_img[:, :3] = 0
    face_img[:, 9:] = 1
    bary = np.full((16, 16, 3), 1 / 3, np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    values = np.array([0, 0, 0, 1, 1, 1], np.float32)[:, None]
    near = bake(face_img, bary, faces, values)[..., 0]
    per = bake(face_img, bary, faces, values, face_chart=np.array([0, 1]))[..., 0]
    np.testing.assert_array_equal(near[:, 6:9], 1)
    np.testing.assert_array_equal(per[:, :8], 0)  # columns 3-7: A's mip block
    np.testing.assert_array_equal(per[:, 8], 1)  # column 8 is next to B (bilinear footprint): B's
    np.testing.assert_array_equal(near[:, :6], 0)
    mip3 = per.reshape(2, 8, 2, 8).mean(axis=(1, 3))
    assert (mip3[:, 0] == 0).all() and (near.reshape(2, 8, 2, 8).mean(axis=(1, 3))[:, 0] > 0).all()
    iy, ix, dist = gutter_sources(face_img, np.array([0, 1]))
    assert (face_img[iy, ix] >= 0).all() and dist[0, 8] == 1
