"""The light registry of triplet_cl.lights: one definition per light (ids, kinds, shadows, packing,
reconstruction, JSON form, initial values) and the defines the kernels are built with."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from triplet_cl import lights as L
from triplet_cl.lights import (
    LIGHT_CLASSES,
    LIGHT_KINDS,
    LIGHT_TYPES,
    AmbientLight,
    DirectionalLight,
    LightInit,
    PointLight,
    SHEnvironmentLight,
    VertexSHLight,
    initial_lights,
    kernel_defines,
    light_to_json,
    lights_from_json,
    lights_to_json,
    pack_lights,
    unpack_gradients,
    unpack_lights,
)


def _init(seed=0):
    return LightInit(np.array([0.1, 0.2, 0.3]), 2.0, np.array([0.0, 1.0, 0.0]), 2, np.random.default_rng(seed))


def _mix():
    rng = np.random.default_rng(1)
    return [PointLight([1, 2, 3], [2, 1, 1], falloff=False), AmbientLight([0.1, 0.2, 0.3]),
            SHEnvironmentLight(rng.normal(size=(3, 9)), 1), DirectionalLight([0, 1, 0.5], [1, 2, 3]), VertexSHLight()]


def test_registry_is_consistent():
    assert set(LIGHT_CLASSES) == {"AmbientLight", "DirectionalLight", "PointLight", "SHEnvironmentLight",
                                  "VertexSHLight"}
    assert {c.TYPE for c in LIGHT_TYPES.values()} == set(LIGHT_TYPES) == {0, 1, 2, 3, 4, 5}
    assert {c.KIND for c in LIGHT_KINDS.values()} == {"point", "directional", "ambient", "sh-env", "vertex-sh"}
    # the bounce light is the renderer's (traced interreflection): in the kernels' table, no CLI kind, no json type
    assert LIGHT_TYPES[5] is L.BounceLight and L.BounceLight.INTERNAL and "bounce" not in LIGHT_KINDS
    d = kernel_defines()
    for t, c in LIGHT_TYPES.items():
        assert d[f"LIGHT_{c.DEFINE}"] == t
        assert bool(d["LIGHT_SHADOW_MASK"] >> t & 1) == c.CASTS_SHADOWS
    assert L.shadow_casting_types() == (DirectionalLight.TYPE, PointLight.TYPE)
    # the historical module names of the ids still hold
    assert (L.AMBIENT, L.DIRECTIONAL, L.POINT, L.SH_ENV, L.VERTEX_SH, L.BOUNCE) == (0, 1, 2, 3, 4, 5)


def test_register_refuses_duplicates():
    with pytest.raises(ValueError, match="already registered"):
        @L.register_light
        @dataclass
        class Twin(L.Light):
            TYPE: ClassVar[int] = PointLight.TYPE
            DEFINE: ClassVar[str] = "TWIN"
            KIND: ClassVar[str] = "twin"
    assert "Twin" not in LIGHT_CLASSES and "twin" not in LIGHT_KINDS
    with pytest.raises(TypeError, match="SHADOW_RAY_PARAM"):
        @L.register_light
        @dataclass
        class Shadowy(L.Light):
            TYPE: ClassVar[int] = 99
            DEFINE: ClassVar[str] = "SHADOWY"
            KIND: ClassVar[str] = "shadowy"
            CASTS_SHADOWS: ClassVar[bool] = True
    assert "Shadowy" not in LIGHT_CLASSES


def test_pack_unpack_round_trip():
    lights = _mix()
    t = pack_lights(lights)
    assert t.ints[:, 0].tolist() == [2, 0, 3, 1, 4]
    assert t.ints[:, 1].tolist() == [0, 6, 9, 36, 42] and len(t.params) == 42
    assert t.ints[0, 2] == 0 and tuple(t.ints[2, 2:]) == (1, 9)
    assert t.env_degree == 1 and t.has_vertex_sh
    assert t.shadowed.tolist() == [0, 3] and t.num_shadowed == 2
    assert t.shadow_ray_offsets.tolist() == [0, 36]  # position (point), direction (directional)
    assert lights[3].param_offset("intensity") == 3
    assert t.inactive.sum() == 3 * 5 and not t.inactive[:9].any()
    back = unpack_lights(lights, t.params)
    assert [type(a) for a in back] == [type(b) for b in lights]
    assert back[0].falloff is False and back[2].degree == 1
    assert np.array_equal(pack_lights(back).params, t.params)
    scaled = unpack_lights(lights, 2 * t.params)
    assert np.array_equal(scaled[2].coeffs, 2 * lights[2].coeffs)
    g = unpack_gradients(lights, np.arange(42.0))
    assert list(g[3]) == ["direction", "intensity"] and np.array_equal(g[3]["intensity"], [39.0, 40.0, 41.0])
    assert g[2]["coeffs"].shape == (3, 9) and g[4] == {}
    with pytest.raises(ValueError, match="light classes"):
        pack_lights([object()])


def test_json_round_trip_and_checks():
    lights = _mix()
    doc = lights_to_json(lights)
    assert doc["lights"][0] == light_to_json(lights[0]) == {"type": "PointLight", "position": [1.0, 2.0, 3.0],
                                                            "intensity": [2.0, 1.0, 1.0], "falloff": False}
    back = lights_from_json(json.loads(json.dumps(doc)))
    assert np.array_equal(pack_lights(back).params, pack_lights(lights).params)
    assert back[2].degree == 1
    bad = PointLight()
    bad.position = np.array([np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="must be finite"):
        lights_to_json([bad])
    assert lights_to_json([bad], check_finite=False)["lights"][0]["position"][1] == 0.0
    with pytest.raises(ValueError, match="type must be one of"):
        lights_from_json([{"type": "SpotLight"}])


def test_initial_lights_per_kind():
    init = _init()
    out = initial_lights(["point", "directional", "ambient", "sh-env", "vertex-sh"], init)
    assert [type(x) for x in out] == [PointLight, DirectionalLight, AmbientLight, SHEnvironmentLight, VertexSHLight]
    rng = np.random.default_rng(0)
    assert np.array_equal(out[0].position, init.center + 0.6 * 2.0 * init.up + 0.3 * 2.0 * rng.normal(size=3))
    assert np.array_equal(out[0].intensity, [4.0] * 3)
    assert out[3].coeffs.shape == (3, 9) and out[3].degree == 0
    assert np.allclose(out[3].coeffs[:, 0] * 0.28209479177387814, 0.1)  # the ambient light's (was 0.5)
    with pytest.raises(ValueError, match="light kinds"):
        initial_lights(["spot"], _init())


def test_several_lights_of_a_kind_start_spread():
    """Two or more point / directional lights start on a ring around the up axis (distinct directions, 0.6 extent
    from the centre, intensity shared), so that each can find its own light; one light keeps its old place."""
    init = _init()
    pts = initial_lights(["point", "ambient", "point", "point"], init)
    pts = [p for p in pts if isinstance(p, PointLight)]
    dirs = [(p.position - init.center) / np.linalg.norm(p.position - init.center) for p in pts]
    for i in range(3):
        assert np.linalg.norm(pts[i].position - init.center) == pytest.approx(0.6 * 2.0, rel=0.2)
        assert np.allclose(pts[i].intensity, 4.0 / 3)
        assert dirs[i] @ init.up > 0.3  # above the horizon
        for j in range(i):
            assert np.degrees(np.arccos(dirs[i] @ dirs[j])) > 60
    d2 = initial_lights(["directional", "directional"], init)
    assert np.degrees(np.arccos(d2[0].direction @ d2[1].direction)) > 60
    assert np.allclose(d2[0].intensity, 0.5) and np.isclose(np.linalg.norm(d2[0].direction), 1)
    assert np.array_equal(initial_lights(["directional"], init)[0].direction, init.up)


def test_relative_lr_scales_follow_the_radiometric_parameters():
    """Colours / intensities / SH radiance: their magnitude (at least 1e-3); positions and directions: 1."""
    from triplet_cl.lights import relative_lr_scales

    lights = [PointLight([1, 2, 3], [12.0, 10.0, 11.0]), AmbientLight([0.1, 0.05, 0.0]),
              DirectionalLight([0, 1, 0], [0.0, 0.0, 0.0]), SHEnvironmentLight.constant([0.5] * 3, 1)]
    s = relative_lr_scales(lights)
    assert len(s) == pack_lights(lights).params.size
    np.testing.assert_allclose(s[:6], [1, 1, 1, 12, 12, 12])
    np.testing.assert_allclose(s[6:9], 0.1)
    np.testing.assert_allclose(s[9:15], [1, 1, 1, 1e-3, 1e-3, 1e-3])
    np.testing.assert_allclose(s[15:], 0.5 * np.sqrt(4 * np.pi))
    # the point lights' positions by their own factor (TrainConfig.lr_light_position_scale); directions keep 1
    s10 = relative_lr_scales(lights, position=10.0)
    np.testing.assert_allclose(s10[:3], 10.0)
    np.testing.assert_array_equal(s10[3:], s[3:])
    # in world units at the dev scenes' extent: a scene twice as large steps its lights' positions twice as far
    from triplet_cl.datasets.base import REFERENCE_EXTENT

    s20 = relative_lr_scales(lights, position=10.0, extent=2 * REFERENCE_EXTENT)
    np.testing.assert_allclose(s20[:3], 20.0)
    np.testing.assert_array_equal(s20[3:], s[3:])


def test_training_steps_the_light_position_by_its_own_rate(tmp_path):
    """``TrainConfig.lr_light_position_scale`` reaches the optimizer: the point light's position rows of the light
    group's learning-rate factors are ``lr_light_position_scale`` (10 by default; 1 in a config from before), a rate in
    world units at the reference extent scaled by the scene's (``datasets.base.REFERENCE_EXTENT``)."""
    from triplet_cl.cli.main import demo_data_path

    from triplet_cl.train import TrainConfig, Trainer

    cfg = TrainConfig(iterations=2, init_points=300, checkpoint_every=0, max_test_views=1)
    assert cfg.lr_light_position_scale == 10.0
    tr = Trainer(demo_data_path(), tmp_path / "run", cfg, quiet=True)
    sc = tr.opt.group("lights").lr_scale[0]
    from triplet_cl.datasets.base import REFERENCE_EXTENT

    assert 0.99 < tr.extent / REFERENCE_EXTENT < 1.02  # the demo is at the reference scale
    np.testing.assert_allclose(sc[:3], 10.0 * tr.extent / REFERENCE_EXTENT)  # PointLight: position, then intensity
    old = cfg.to_dict()
    del old["lr_light_position_scale"]
    assert TrainConfig.from_dict(old).lr_light_position_scale == 1.0
    with pytest.raises(ValueError, match="lr_light_position_scale"):
        TrainConfig(lr_light_position_scale=float("nan")).validate()


def test_gltf_punctual_form():
    p, d = PointLight([1, 2, 3], [2, 1, 1]), DirectionalLight([0, 0, 2], [1, 1, 1])
    assert p.gltf_punctual()[0] == "point" and np.array_equal(p.gltf_punctual()[1], [1, 2, 3])
    assert d.gltf_punctual()[0] == "directional" and np.array_equal(d.gltf_punctual()[2], [1, 1, 1])
    assert PointLight(falloff=False).gltf_punctual() is None and AmbientLight().gltf_punctual() is None
    assert SHEnvironmentLight().gltf_punctual() is None and VertexSHLight().gltf_punctual() is None


def test_train_uses_the_registry():
    from triplet_cl.train import LIGHT_KINDS as TRAIN_KINDS

    assert set(TRAIN_KINDS) == set(LIGHT_KINDS)


def test_scene_current_lights_reads_the_packed_parameters():
    from triplet_cl.scene import Scene

    V = np.random.default_rng(0).normal(size=(6, 3))
    lights = _mix()
    s = Scene.from_arrays(V, np.arange(6).reshape(2, 3), lights=lights, vertex_sh=np.zeros((6, 6, 1)),
                          dtype=np.float64)
    s.light_params.data = s.light_params.data * 3
    cur = s.current_lights()
    assert np.array_equal(pack_lights(cur).params, 3 * pack_lights(lights).params)
    assert cur[0].falloff is False and isinstance(cur[4], VertexSHLight)


def test_white_balance_makes_the_lights_white_together_and_keeps_their_relative_colours():
    """``white_balance``: the summed irradiance at the centre gets equal channels at its mean; each light keeps its
    colour relative to the others (a warm point light under a blue sky stays warmer than the sky)."""
    from triplet_cl.lights import irradiance_rgb, pack_lights, unpack_lights, white_balance

    c = np.array([0.1, -0.2, 0.3])
    lights = [PointLight(np.array([1.0, 2.0, 3.0]), np.array([20.0, 17.0, 12.0])),
              AmbientLight(np.array([0.05, 0.08, 0.12])),
              DirectionalLight(np.array([0, 1.0, 0]), np.array([1.0, 0.9, 0.7])),
              SHEnvironmentLight(np.array([[1.0, 0.2, 0.1, 0.0], [0.8, 0.1, 0.1, 0.0], [0.6, 0.0, 0.3, 0.1]]))]
    p = pack_lights(lights).params
    q = white_balance(lights, p, c)
    before = [irradiance_rgb(lt, c) for lt in unpack_lights(lights, p)]
    after = [irradiance_rgb(lt, c) for lt in unpack_lights(lights, q)]
    total = np.sum(after, axis=0)
    np.testing.assert_allclose(total, np.full(3, np.sum(before, axis=0).mean()), rtol=1e-10)
    f = after[0] / before[0]
    for b, a in zip(before, after, strict=True):
        np.testing.assert_allclose(a / b, f, rtol=1e-10)  # one factor per channel for every light
    pos = lambda ls: np.asarray(ls[0].position)  # noqa: E731
    np.testing.assert_array_equal(pos(unpack_lights(lights, q)), pos(lights))  # geometry untouched
    sh_b, sh_a = unpack_lights(lights, p)[3].coeffs, unpack_lights(lights, q)[3].coeffs
    np.testing.assert_allclose(sh_a, sh_b * f[:, None], rtol=1e-10)  # every band of a channel alike
    np.testing.assert_allclose(white_balance(lights, q, c), q, rtol=1e-10)  # a projection


def test_white_balance_leaves_what_it_cannot_balance():
    from triplet_cl.lights import pack_lights, white_balance

    dark = [AmbientLight(np.array([0.1, 0.0, 0.1]))]  # a channel without light: nothing to scale it by
    p = pack_lights(dark).params
    np.testing.assert_array_equal(white_balance(dark, p, np.zeros(3)), p)


def test_grey_lights_keeps_each_lights_brightness():
    from triplet_cl.lights import grey_lights, pack_lights, unpack_lights

    lights = [PointLight(np.array([1.0, 2.0, 3.0]), np.array([20.0, 17.0, 11.0])),
              AmbientLight(np.array([0.05, 0.08, 0.14]))]
    q = unpack_lights(lights, grey_lights(lights, pack_lights(lights).params))
    np.testing.assert_allclose(q[0].intensity, np.full(3, 16.0))
    np.testing.assert_allclose(q[1].color, np.full(3, 0.09))
    np.testing.assert_array_equal(q[0].position, lights[0].position)


def test_scale_lights_scales_every_radiometric_parameter_and_nothing_else():
    """``scale_lights`` (the mesh stage's metal gauge): colours, intensities and every SH band × the factor,
    positions and directions untouched."""
    from triplet_cl.lights import SHEnvironmentLight, scale_lights

    rng = np.random.default_rng(3)
    lights = [PointLight(np.array([1.0, 2.0, 3.0]), np.array([20.0, 17.0, 11.0])),
              DirectionalLight(np.array([0.0, 1.0, 0.5]), np.array([2.0, 2.5, 3.0])),
              AmbientLight(np.array([0.05, 0.08, 0.14])), SHEnvironmentLight(rng.normal(size=(3, 9)), 2)]
    q = unpack_lights(lights, scale_lights(lights, pack_lights(lights).params, 0.25))
    np.testing.assert_allclose(q[0].intensity, lights[0].intensity * 0.25, rtol=1e-6)
    np.testing.assert_array_equal(q[0].position, lights[0].position)
    np.testing.assert_allclose(q[1].intensity, lights[1].intensity * 0.25, rtol=1e-6)
    np.testing.assert_allclose(q[1].direction, lights[1].direction, rtol=1e-6)
    np.testing.assert_allclose(q[2].color, lights[2].color * 0.25, rtol=1e-6)
    np.testing.assert_allclose(q[3].coeffs, lights[3].coeffs * 0.25, rtol=1e-5)
    assert q[3].degree == 2


def test_point_light_distance_keeps_the_irradiance_at_the_centre():
    """``LightInit.distance`` (``--light-distance``) moves the point lights out along their directions and scales
    the intensity so that ``I / d²`` at the centre is the same as at the default 0.6 extent."""
    import dataclasses

    from triplet_cl.lights import irradiance_rgb

    for kinds in (["point"], ["point", "point"]):
        near = initial_lights(kinds, _init())
        far = initial_lights(kinds, dataclasses.replace(_init(), distance=1.8))
        for a, b in zip(near, far, strict=True):
            c = _init().center
            da, db = a.position - c, b.position - c
            assert np.linalg.norm(db) > 2 * np.linalg.norm(da)
            if len(kinds) == 2:  # ring lights: the same direction (up to the jitter)
                assert da @ db / np.linalg.norm(da) / np.linalg.norm(db) > 0.99
            ea = a.intensity / (0.6 * 2.0) ** 2
            eb = b.intensity / (1.8 * 2.0) ** 2
            np.testing.assert_allclose(ea, eb, rtol=1e-12)
            assert irradiance_rgb(b, c) is not None


def test_hold_irradiance_keeps_each_point_light_s_irradiance_at_the_centre():
    """``lights.hold_irradiance``: a point light (with falloff) that moved keeps ``I / d²`` at the centre (its
    intensity × (d / d_before)²); ambient, directional and falloff-free point lights, and lights that did not move,
    are untouched; the offsets follow the packed table (two point lights after an ambient one)."""
    from triplet_cl.lights import balanced_lights, hold_irradiance

    c = np.array([0.1, -0.2, 0.3])
    lights = [AmbientLight(np.full(3, 0.1)), PointLight(np.array([2.0, 0.0, 0.0]), np.full(3, 4.0)),
              DirectionalLight(np.array([0.0, -1.0, 0.0]), np.full(3, 2.0)),
              PointLight(np.array([0.0, 3.0, 0.0]), np.array([9.0, 8.0, 7.0])),
              PointLight(np.array([0.0, 0.0, 5.0]), np.full(3, 5.0), falloff=False)]
    before = pack_lights(lights).params.astype(np.float64)
    moved = [lights[0], PointLight(np.array([3.0, 0.5, 0.0]), np.full(3, 4.4)), lights[2],
             PointLight(np.array([0.0, 3.0, 0.0]), np.array([9.0, 8.0, 7.0])),
             PointLight(np.array([0.0, 0.0, 7.0]), np.full(3, 5.0), falloff=False)]
    after = pack_lights(moved).params.astype(np.float64)
    out = L.unpack_lights(moved, hold_irradiance(moved, before, after, c))
    d0, d1 = np.sum((lights[1].position - c) ** 2), np.sum((moved[1].position - c) ** 2)
    np.testing.assert_allclose(out[1].intensity / d1, 4.4 / d0, rtol=1e-12)  # the step's own intensity change stays
    np.testing.assert_allclose(out[1].position, moved[1].position)
    np.testing.assert_array_equal(out[3].intensity, [9.0, 8.0, 7.0])  # did not move
    np.testing.assert_array_equal(out[4].intensity, np.full(3, 5.0))  # no falloff: no irradiance to keep
    np.testing.assert_array_equal(out[0].color, lights[0].color)
    np.testing.assert_array_equal(out[2].intensity, lights[2].intensity)
    # balanced_lights applies it first when given the parameters before the step, and not without them
    np.testing.assert_allclose(balanced_lights("off", moved, after, c, before=before),
                               hold_irradiance(moved, before, after, c))
    np.testing.assert_array_equal(balanced_lights("off", moved, after, c), after)


def test_training_steps_keep_the_point_light_s_irradiance_but_for_its_intensity_step(tmp_path):
    """``TrainConfig.hold_irradiance`` (default): after each soup step the point light's intensity is what the
    optimiser made it × (d / d_before)², d its distance from the look-at centre, so moving it changes nothing at the
    centre (the gauge the photos do not fix stayed with the distance they constrain least: an avocado-shaped dark
    object's light walked out to 5.6 at a constant intensity, its irradiance a quarter of the truth's). A config
    from before has it off."""
    from triplet_cl.cli.main import demo_data_path

    from triplet_cl.train import TrainConfig, Trainer

    cfg = TrainConfig(iterations=5, init_points=300, checkpoint_every=0, max_test_views=1)
    assert cfg.hold_irradiance is True
    tr = Trainer(demo_data_path(), tmp_path / "run", cfg, quiet=True)
    c = tr.priors.center
    raw = {}
    step = tr.opt.step

    def spy():  # the parameters before and after the optimiser's own update
        raw["before"] = np.array(tr.scene.light_params.data, np.float64)
        step()
        raw["after"] = np.array(tr.scene.light_params.data, np.float64)

    tr.opt.step = spy
    for _ in range(3):
        tr.step()
        b, a = raw["before"], raw["after"]
        p = np.array(tr.scene.light_params.data, np.float64)
        d0, d1 = np.sum((b[:3] - c) ** 2), np.sum((a[:3] - c) ** 2)
        assert abs(d1 / d0 - 1) > 1e-6  # the light moved
        np.testing.assert_allclose(p[3:6], np.mean(a[3:6]) * d1 / d0, rtol=1e-5)  # grey ("each"), then held
    old = cfg.to_dict()
    del old["hold_irradiance"]
    assert TrainConfig.from_dict(old).hold_irradiance is False
    with pytest.raises(ValueError, match="hold_irradiance"):
        TrainConfig(hold_irradiance=1).validate()


def test_lights_kept_out_moves_point_lights_out_to_the_radius():
    """``lights.lights_kept_out``: a point light (with or without falloff) closer than the radius to the centre moves
    out along its own direction to the radius; one farther, and other light types, are untouched; one at the centre
    itself goes along its direction before the step (or up without one); radius 0 changes nothing."""
    from triplet_cl.lights import lights_kept_out

    c = np.array([0.1, -0.2, 0.3])
    lights = [AmbientLight(np.full(3, 0.1)), PointLight(c + np.array([0.3, 0.4, 0.0]), np.full(3, 4.0)),
              DirectionalLight(np.array([0.0, -0.1, 0.0]), np.full(3, 2.0)),
              PointLight(c + np.array([0.0, 3.0, 0.0]), np.array([9.0, 8.0, 7.0])),
              PointLight(c + np.array([0.0, 0.0, -0.2]), np.full(3, 5.0), falloff=False),
              PointLight(c.copy(), np.full(3, 1.0))]
    p = pack_lights(lights).params.astype(np.float64)
    before = p.copy()
    before[-6:-3] = c + np.array([-2.0, 0.0, 0.0])  # the last light came to the centre from -x
    out = L.unpack_lights(lights, lights_kept_out(lights, p, c, 2.0, before=before))
    np.testing.assert_allclose(out[1].position, c + 2.0 * np.array([0.6, 0.8, 0.0]), rtol=1e-12)
    np.testing.assert_array_equal(out[1].intensity, lights[1].intensity)  # only the position (hold_irradiance: after)
    np.testing.assert_array_equal(out[3].position, lights[3].position)  # 3 > 2: untouched
    np.testing.assert_allclose(out[4].position, c + np.array([0.0, 0.0, -2.0]), rtol=1e-12)
    np.testing.assert_allclose(out[5].position, c + np.array([-2.0, 0.0, 0.0]), rtol=1e-12)
    np.testing.assert_array_equal(out[2].direction, lights[2].direction)
    np.testing.assert_array_equal(out[0].color, lights[0].color)
    up = L.unpack_lights(lights, lights_kept_out(lights, p, c, 2.0))[5]
    np.testing.assert_allclose(up.position, c + np.array([0.0, 2.0, 0.0]), rtol=1e-12)
    np.testing.assert_array_equal(lights_kept_out(lights, p, c, 0.0), p)


def test_balanced_lights_keeps_out_before_holding_the_irradiance():
    """``balanced_lights(min_distance=R)``: the light is kept out first, so the irradiance hold scales its intensity
    by the distance it ends at (a step from 3 to 0.5, kept at 1.5: intensity × (1.5 / 3)²)."""
    from triplet_cl.lights import balanced_lights

    c = np.zeros(3)
    lights = [PointLight(np.array([0.0, 0.5, 0.0]), np.full(3, 8.0))]
    before = np.array([0.0, 3.0, 0.0, 8.0, 8.0, 8.0])
    after = pack_lights(lights).params.astype(np.float64)
    out = balanced_lights("off", lights, after, c, before=before, min_distance=1.5)
    np.testing.assert_allclose(out, [0.0, 1.5, 0.0, 2.0, 2.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(balanced_lights("off", lights, after, c, before=before),
                               [0.0, 0.5, 0.0, 8.0 / 36, 8.0 / 36, 8.0 / 36], rtol=1e-12)


def test_training_keeps_the_point_light_out_of_the_object(tmp_path):
    """``TrainConfig.light_min_distance`` (default 1 frame radius): a soup step that would take the point light
    inside that radius leaves it on it (spot_small's photos flattened on white: a gradient spike threw the light
    inside the cow and it ended below it, 30.40 dB against 34.18). Saved configs from before have it off; a negative
    or non-finite value is refused."""
    from triplet_cl.cli.main import demo_data_path

    from triplet_cl.train import TrainConfig, Trainer, frame_radius

    cfg = TrainConfig(iterations=5, init_points=300, checkpoint_every=0, max_test_views=1)
    assert cfg.light_min_distance == 1.0
    tr = Trainer(demo_data_path(), tmp_path / "run", cfg, quiet=True)
    c, R = tr.priors.center, frame_radius(tr.ds)
    assert tr.light_min_radius == pytest.approx(R) and R > 0
    lp = tr.scene.light_params.data
    lp[:3] = c + np.array([0.0, 0.1 * R, 0.0])  # inside (as after a jump)
    tr.step()
    assert np.linalg.norm(lp[:3] - c) == pytest.approx(R, rel=1e-5)
    assert (lp[3:6] > 0).all()
    old = cfg.to_dict()
    del old["light_min_distance"]
    assert TrainConfig.from_dict(old).light_min_distance == 0.0
    for bad in (-1.0, float("nan"), True, 1001.0):
        with pytest.raises(ValueError, match="light_min_distance"):
            TrainConfig(light_min_distance=bad).validate()


def test_initial_point_light_starts_outside_the_keep_out_radius(monkeypatch):
    """``train.initial_lights``: a point light whose start falls within ``light_keep_out_radius`` (a short
    ``--light-distance``, or ~4 % of the jittered starts) starts on it, its intensity × (R / d_start)²: the irradiance
    at the centre it was placed to give; with the rule off it starts where it was placed. The radius is the frame
    radius × ``light_min_distance``, at most the cameras' mean distance (a lens wider than 90°)."""
    from dataclasses import replace

    from triplet_cl.cli.main import demo_data_path

    from triplet_cl import train as train_mod
    from triplet_cl.datasets import load_dataset
    from triplet_cl.train import TrainConfig, frame_radius, initial_lights, light_keep_out_radius, look_at_center

    ds = load_dataset(demo_data_path())
    c, R = look_at_center(ds), frame_radius(ds)
    cfg = replace(TrainConfig(), light_distance=0.05)
    seed = next(s for s in range(200)  # a start within R (the jitter, 0.3 extent, is most of the offset here)
                if np.linalg.norm(initial_lights(replace(cfg, light_min_distance=0.0), ds,
                                                 np.random.default_rng(s))[0].position - c) < R)
    off = initial_lights(replace(cfg, light_min_distance=0.0), ds, np.random.default_rng(seed))
    on = initial_lights(cfg, ds, np.random.default_rng(seed))
    d0, d1 = np.linalg.norm(off[0].position - c), np.linalg.norm(on[0].position - c)
    assert d0 < R and d1 == pytest.approx(R, rel=1e-9)
    np.testing.assert_allclose((on[0].position - c) / d1, (off[0].position - c) / d0, rtol=1e-9)
    np.testing.assert_allclose(on[0].intensity / d1**2, off[0].intensity / d0**2, rtol=1e-9)
    np.testing.assert_array_equal(on[1].color, off[1].color)  # the ambient light is not moved
    far = initial_lights(replace(cfg, light_distance=0.6), ds, np.random.default_rng(0))  # placed outside: as is
    np.testing.assert_array_equal(far[0].position, initial_lights(replace(cfg, light_distance=0.6,
                                                                            light_min_distance=0.0), ds,
                                                                    np.random.default_rng(0))[0].position)
    assert light_keep_out_radius(replace(cfg, light_min_distance=2.0), ds) == pytest.approx(2 * R)
    assert light_keep_out_radius(replace(cfg, light_min_distance=0.0), ds) == 0.0
    dist = float(np.mean([np.linalg.norm(v.camera.center - c) for v in ds.train]))
    monkeypatch.setattr(train_mod, "frame_radius", lambda ds: 10.0 * dist)  # a fisheye's frame radius
    assert light_keep_out_radius(cfg, ds) == pytest.approx(dist)
