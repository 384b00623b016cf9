"""Relighting: light-set files (every type, named sets, bad files), envmap → SH, the albedo metric, relit runs."""

from __future__ import annotations

import json
import math

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
