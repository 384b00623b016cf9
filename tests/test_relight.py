"""Relighting: light-set files (every type, named sets, bad files), envmap → SH, the albedo metric, relit runs."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from triplet_cl.lights import DirectionalLight, PointLight, SHEnvironmentLight
from triplet_cl.relight import LightFileError, albedo_psnr, load_light_sets, project_equirect, rotation_y


def _write(tmp_path, doc, name="lights.json"):
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return p


def _write_hdr(path, img):
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, "float")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(img, np.float32))
    out.close()


def test_every_light_type_and_named_sets(tmp_path):
    env = tmp_path / "envmaps"
    env.mkdir()
    _write_hdr(env / "sky.exr", np.full((64, 128, 3), 0.5))
    doc = {"sets": {
        "a": {"lights": [{"type": "point", "position": [1, 2, 3], "intensity": 20.0},
                         {"type": "directional", "direction": [0, -2, 0], "irradiance": [1, 2, 3]}],
              "images": "a"},
        "b": {"lights": [{"type": "constant", "radiance": [0.1, 0.2, 0.3]},
                         {"type": "envmap", "filename": "sky.exr", "rotate_y_deg": 40, "scale": 2.0}]}}}
    sub = tmp_path / "scene" / "relight"
    sub.mkdir(parents=True)
    p = _write(sub, doc, "relight.json")
    sets = load_light_sets(p, env_degree=2)
    assert [s.name for s in sets] == ["a", "b"]
    pt, dl = sets[0].lights
    assert isinstance(pt, PointLight) and pt.falloff and np.allclose(pt.intensity, 20)
    assert np.allclose(pt.position, [1, 2, 3])
    assert isinstance(dl, DirectionalLight) and np.allclose(dl.direction, [0, 1, 0])  # towards the light
    assert np.allclose(dl.intensity, [1, 2, 3]) and sets[0].images == sub / "a"
    (sh,) = sets[1].lights  # the constant and the map share one SH environment
    assert isinstance(sh, SHEnvironmentLight) and sh.degree == 2
    # a uniform map of radiance 0.5 × scale 2 plus the constant: band 0 only, radiance 1 + c
    want = (np.array([0.1, 0.2, 0.3]) + 1.0) * math.sqrt(4 * math.pi)
    np.testing.assert_allclose(sh.coeffs[:, 0], want, rtol=1e-3)
    assert np.abs(sh.coeffs[:, 1:]).max() < 1e-3 * want.max()
    (only,) = load_light_sets(f"{p}#b", env_degree=2)
    assert only.name == "b" and only.images is None


def test_bare_list_and_a_runs_own_lights_json(tmp_path):
    p = _write(tmp_path, {"lights": [{"type": "constant", "radiance": 0.2}]}, "dim.json")
    (s,) = load_light_sets(p)
    assert s.name == "dim" and isinstance(s.lights[0], SHEnvironmentLight)
    from triplet_cl.lights import AmbientLight, light_to_json

    own = _write(tmp_path, {"lights": [light_to_json(PointLight([0, 1, 0], [2, 2, 2])),
                                       light_to_json(AmbientLight([0.1, 0.1, 0.1]))]}, "own.json")
    (s,) = load_light_sets(own)
    assert isinstance(s.lights[0], PointLight) and isinstance(s.lights[1], AmbientLight)


@pytest.mark.parametrize(("doc", "field", "what"), [
    ({"sets": {"a": {"lights": [{"type": "spot", "position": [0, 0, 0]}]}}}, "sets.a.lights[0].type",
     "expected one of"),
    ({"lights": [{"type": "point", "position": [0, 0], "intensity": 1}]}, "lights[0].position", "3 numbers"),
    ({"lights": [{"type": "point", "intensity": 1}]}, "lights[0].position", "missing"),
    ({"lights": [{"type": "directional", "direction": [0, 0, 0], "irradiance": 1}]}, "lights[0].direction", "zero"),
    ({"lights": [{"type": "constant", "radiance": -1}]}, "lights[0].radiance", ">= 0"),
    ({"lights": [{"type": "point", "position": [0, 0, 0], "intensity": 1, "power": 3}]}, "lights[0]", "unknown field"),
    ({"lights": [{"type": "envmap", "filename": "nowhere.hdr"}]}, "lights[0].filename", "tried"),
    ({"lights": [{"type": "envmap", "filename": "x.hdr", "scale": "big"}]}, "lights[0].scale", "finite number"),
    ({"lights": []}, "lights", "non-empty"),
    ({"sets": {}}, "sets", "non-empty"),
    ({"cameras": 1}, "", "\"sets\" object or a \"lights\" list"),
])
def test_bad_files_name_the_file_and_field(tmp_path, doc, field, what):
    p = _write(tmp_path, doc)
    with pytest.raises(LightFileError, match=what) as exc:
        load_light_sets(p)
    assert exc.value.field == field and str(p) in str(exc.value)


def test_missing_set_bad_json_missing_file(tmp_path):
    p = _write(tmp_path, {"sets": {"a": {"lights": [{"type": "constant", "radiance": 1}]}}})
    with pytest.raises(LightFileError, match="no set named 'zz'"):
        load_light_sets(f"{p}#zz")
    bad = tmp_path / "bad.json"
    bad.write_text("{ nope")
    with pytest.raises(LightFileError, match="not valid JSON"):
        load_light_sets(bad)
    with pytest.raises(LightFileError, match="does not exist"):
        load_light_sets(tmp_path / "none.json")


def test_envmap_rotation_and_projection():
    """A map bright in one pixel block: the SH of the rotated map is the SH of the rotated direction."""
    from triplet_cl.mesh.envmap import latlong_directions, sh_basis

    H = 64
    d = latlong_directions(H)
    target = np.array([1.0, 0.3, 0.2]) / np.linalg.norm([1.0, 0.3, 0.2])
    img = np.exp(40 * (d @ target - 1))[..., None] * np.ones(3)
    c0 = project_equirect(img, 0.0, 2)
    c1 = project_equirect(img, 90.0, 2)
    # band-0 energy unchanged; the lobe's direction turns with R_y(90°) (right-handed: +X → −Z)
    np.testing.assert_allclose(c1[:, 0], c0[:, 0], rtol=1e-6)
    rot = rotation_y(90) @ target
    assert np.allclose(rot, [target[2], target[1], -target[0]], atol=1e-12)
    lobe0, lobe1 = sh_basis(2, target), sh_basis(2, rot)
    np.testing.assert_allclose(c1[0, 1:4] / c1[0, 0], lobe1[1:4] / lobe1[0] * (c0[0, 1:4] / c0[0, 0])
                               / (lobe0[1:4] / lobe0[0]), rtol=1e-6, atol=1e-9)


def test_albedo_metric_on_a_known_scale(rng):
    from triplet_cl.ops.color import srgb_decode, srgb_encode

    gt = rng.uniform(0.2, 0.8, (3, 8, 9, 3))
    mask = rng.uniform(size=(3, 8, 9)) > 0.3
    scale = np.array([0.5, 0.8, 0.65])
    pred = srgb_encode(srgb_decode(gt) * scale)  # the right albedo under a per-channel light scale
    m = albedo_psnr(pred, gt, mask)
    np.testing.assert_allclose(m["scale"], 1 / scale, rtol=1e-9)
    assert m["psnr_scaled"] > 100 and m["psnr_raw"] < 20 and m["pixels"] == mask.sum()
    p = gt.copy()
    p[~mask] = 0  # what lies outside the ground truth's coverage does not count
    assert albedo_psnr(p, gt, mask)["psnr_raw"] == float("inf")
    with pytest.raises(ValueError, match="covers no pixel"):
        albedo_psnr(p, gt, np.zeros_like(mask))


# ---------------------------------------------------------------------------------------------- on a trained run


@pytest.fixture(scope="module")
def relit_run(tmp_path_factory):
    """A short soup run on the demo data; its own-light relight before the mesh stage, then a tiny mesh stage."""
    from triplet_cl.cli.main import demo_data_path
    from triplet_cl.cli.main import main as cli_main

    from tests.test_mesh_stage import tiny_mesh_cfg
    from tests.test_train import small_cfg
    from triplet_cl.mesh.refine import MeshStage
    from triplet_cl.train import Trainer

    run = tmp_path_factory.mktemp("relight") / "run"
    tr = Trainer(demo_data_path(), run, small_cfg(iterations=60, init_points=2000), quiet=True)
    tr.train()
    soup_out = run.parent / "soup_own"
    assert cli_main(["relight", str(run), "--lights", str(run / "lights.json"), "--out", str(soup_out)]) == 0
    MeshStage(tr, tiny_mesh_cfg(iterations=12, remesh_every=0)).run()
    return run, soup_out


def _read(p):
    from triplet_cl.datasets.images import read_image

    im = read_image(p)
    return im.rgb, im.alpha


def test_relight_under_its_own_lights_reproduces_the_test_renders(relit_run):
    from triplet_cl.cli.main import main as cli_main

    run, soup_out = relit_run
    assert json.loads((run / "config.json").read_text())["train"]["color"] == "linear"
    names = sorted(p.name for p in (run / "renders" / "test").glob("*.png"))
    assert names and names == sorted(p.name for p in soup_out.glob("*.png"))
    for n in names:  # soup: the same image, up to the 8-bit rounding of both files
        (a, aa), (b, ba) = _read(run / "renders" / "test" / n), _read(soup_out / n)
        assert np.abs(aa - ba).max() <= 1 / 255 + 1e-6
        cover = aa > 0.05
        assert np.abs(a - b)[cover].max() <= 2 / 255 + 1e-6, n
    mesh_out = run.parent / "mesh_own"  # the mesh (auto: the run has one) under the mesh stage's lights.json
    assert cli_main(["relight", str(run), "--lights", str(run / "lights.json"), "--out", str(mesh_out)]) == 0
    for n in names:
        (a, aa), (b, ba) = _read(run / "renders" / "mesh" / n), _read(mesh_out / n)
        assert np.abs(aa - ba).max() <= 1 / 255 + 1e-6
        assert np.abs(a - b)[aa > 0.05].max() <= 2 / 255 + 1e-6, n


def test_eval_relight_writes_its_section_and_keeps_the_others(relit_run, tmp_path, capsys):
    """A relight folder whose one set is the run's own (mesh) lights and images: near-perfect relit PSNR; the
    albedo folder is the base colour rendered by the run itself, scaled: raw PSNR drops, scaled PSNR does not."""
    import shutil

    from triplet_cl.cli.main import main as cli_main

    from triplet_cl.io import write_png
    from triplet_cl.ops.color import srgb_decode, srgb_encode

    run, _ = relit_run
    rdir = tmp_path / "relight"
    shutil.copytree(run / "renders" / "mesh", rdir / "own")
    own_lights = json.loads((run / "lights.json").read_text())["lights"]
    (rdir / "relight.json").write_text(json.dumps({"sets": {"own": {"lights": own_lights, "images": "own"}},
                                                   "albedo": "albedo"}))
    # the albedo reference: the run's own base colour × a per-channel scale (in linear values)
    from triplet_cl.relight import Relighter
    from triplet_cl.train import Trainer

    tr = Trainer(None, run, resume=True, quiet=True)
    rl = Relighter(tr)
    scale = np.array([0.6, 0.9, 0.75])
    for v in tr.ds["test"][: tr.cfg.max_test_views]:
        rgb, a = rl.render_albedo(v.camera)
        ref = srgb_encode(srgb_decode(np.clip(rgb, 0, 1)) * scale)
        write_png(rdir / "albedo" / f"{v.name.split('/')[-1]}.png", ref, np.clip(a, 0, 1))
    before = json.loads((run / "metrics.json").read_text())
    assert cli_main(["eval", str(run), "--relight", str(rdir)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    assert m["mesh"] == before["mesh"] and m["wall_time_s"] == before["wall_time_s"]  # other sections kept
    for stage in ("soup", "mesh"):
        assert set(m["relight"][stage]["sets"]) == {"own"}
    assert m["relight"]["mesh"]["sets"]["own"]["psnr"] > 45  # the mesh under its own lights: its own renders
    alb = m["relight"]["mesh"]["albedo"]
    assert alb["psnr_scaled"] > alb["psnr_raw"] + 5 and alb["psnr_scaled"] > 35
    np.testing.assert_allclose(alb["scale"], scale, rtol=0.05)
    # a bad light file: one clear error, exit status 2, metrics untouched
    (rdir / "relight.json").write_text(json.dumps({"sets": {"own": {"lights": [{"type": "point"}]}}}))
    capsys.readouterr()
    assert cli_main(["eval", str(run), "--relight", str(rdir)]) == 2
    err = capsys.readouterr().err
    assert "relight.json" in err and "sets.own.lights[0].position" in err
    assert json.loads((run / "metrics.json").read_text()) == m


def test_runs_before_the_linear_pipeline_stay_encoded():
    from triplet_cl.train import TrainConfig, color_transfer

    old = TrainConfig().to_dict()
    del old["color"]
    assert TrainConfig.from_dict(old).color == "encoded" and TrainConfig().color == "linear"
    assert color_transfer("encoded", "srgb") is None and color_transfer("linear", "srgb") == "srgb"
    assert color_transfer("linear", "linear") is None
    with pytest.raises(ValueError, match="color must be one of"):
        from dataclasses import replace

        replace(TrainConfig(), color="gamma").validate()


def test_a_linear_runs_exports_encode_the_albedo(relit_run):
    """The base-colour texture of a linear-pipeline run holds s(albedo) (glTF's sRGB convention), not the albedo."""
    import trimesh

    from triplet_cl.mesh.asset import MeshAsset
    from triplet_cl.mesh.refine import MESH_STATE, albedo_space, load_mesh_state, run_color
    from triplet_cl.ops.color import srgb_encode

    run, _ = relit_run
    assert run_color(run) == "linear" and albedo_space("linear") == "linear" and albedo_space("encoded") == "srgb"
    alb = MeshAsset.from_scene(load_mesh_state(run / MESH_STATE)).attributes["albedo"]
    g = list(trimesh.load(run / "mesh.glb", process=False).geometry.values())[0]
    tex = np.asarray(g.visual.material.baseColorTexture.convert("RGB"), np.float64) / 255
    enc, raw = np.median(srgb_encode(alb)), np.median(alb)
    assert abs(enc - raw) > 0.1  # the check can tell them apart
    assert abs(np.median(tex) - enc) < 0.25 * abs(enc - raw), (np.median(tex), enc, raw)


def test_blinn_phong_run_relights(tmp_path):
    """--brdf blinn-phong: `triplet relight` under the run's own lights gives its test renders back, and
    `eval --relight` with a Mitsuba-style set (point + constant) evaluates it; its albedo image is kd (the base
    colour)."""
    from triplet_cl.cli.main import demo_data_path
    from triplet_cl.cli.main import main as cli_main

    from tests.test_train import small_cfg
    from triplet_cl.relight import Relighter
    from triplet_cl.train import Trainer

    run = tmp_path / "bp"
    tr = Trainer(demo_data_path(), run, small_cfg(iterations=30, init_points=1500, brdf="blinn_phong"), quiet=True)
    tr.train()
    own = tmp_path / "own"
    assert cli_main(["relight", str(run), "--lights", str(run / "lights.json"), "--out", str(own)]) == 0
    names = sorted(p.name for p in (run / "renders" / "test").glob("*.png"))
    assert names and names == sorted(p.name for p in own.glob("*.png"))
    for n in names:
        (a, aa), (b, ba) = _read(run / "renders" / "test" / n), _read(own / n)
        assert np.abs(aa - ba).max() <= 1 / 255 + 1e-6
        assert np.abs(a - b)[aa > 0.05].max() <= 2 / 255 + 1e-6, n
    rdir = tmp_path / "relight"
    shutil.copytree(run / "renders" / "test", rdir / "set")
    shutil.copytree(run / "renders" / "test", rdir / "albedo")
    lights = [{"type": "point", "position": [2.0, 3.0, 2.5], "intensity": 30.0}, {"type": "constant", "radiance": 0.1}]
    (rdir / "relight.json").write_text(json.dumps({"sets": {"s": {"lights": lights, "images": "set"}},
                                                   "albedo": "albedo"}))
    assert cli_main(["eval", str(run), "--relight", str(rdir)]) == 0
    m = json.loads((run / "metrics.json").read_text())["relight"]["soup"]
    assert np.isfinite(m["sets"]["s"]["psnr"]) and np.isfinite(m["albedo"]["psnr_scaled"])
    tr2 = Trainer(None, run, resume=True, quiet=True)
    rl = Relighter(tr2)
    v = rl.views("test")[0]
    rgb, a = rl.render_albedo(v.camera)
    kd_scene = rl.albedo_scene()
    assert np.array_equal(np.asarray(kd_scene.material.data)[:, 7:10], np.asarray(tr2.scene.material.data)[:, 0:3])
    assert rgb.shape[:2] == a.shape and np.isfinite(rgb).all()


def test_a_light_set_with_an_unknown_key_is_refused(tmp_path):
    """A typo ("light" beside "lights") in a set was ignored (a battery); "_" keys are comments."""
    from triplet_cl.relight import LightFileError, load_light_sets

    p = tmp_path / "sets.json"
    pt = {"type": "point", "position": [0, 2, 3], "intensity": [5, 5, 5]}
    p.write_text(json.dumps({"sets": {"a": {"lights": [pt], "light": [pt]}}}))
    with pytest.raises(LightFileError, match=r"unknown key\(s\) \['light'\]"):
        load_light_sets(p)
    p.write_text(json.dumps({"sets": {"a": {"lights": [pt], "_note": "mine", "description": "x"}}}))
    assert len(load_light_sets(p)) == 1


def test_non_finite_relit_render_is_named_before_scoring():
    # session 62: on Intel's CPU runtime a soup relit under an SH environment came out NaN in some processes, and
    # `eval --relight` stopped with the loss's own "pred must be finite"; now the set and the view are named
    from triplet_cl.relight import check_finite_render

    check_finite_render(np.zeros((4, 4, 3), np.float32), "set 'a', view 'r_0'")  # finite: nothing to say
    img = np.zeros((4, 4, 3), np.float32)
    img[1, 2] = np.nan
    img[3, 3, 0] = np.inf
    with pytest.raises(ValueError, match=r"relit render of set 'env', view 'test/r_1' holds 4 NaN/Inf value\(s\)"):
        check_finite_render(img, "set 'env', view 'test/r_1'")
