"""Decomposition regression: a small synthetic scene rendered by our own renderer (a sphere, a known point
light, a known orange albedo, no ambient light); optimising lights and materials on it (geometry fixed) must
recover what the photos determine, so a regression in the decomposition fails a test, not only a benchmark.

1. Lights and materials jointly, from the training's initial values (albedo 0.5, roughness 0.9, metallic
   0.1, a point light above the object, ambient 0.1), the training loss (L1 + SSIM) and the default
   priors (the light terms): the light's direction, the albedo's colour (its per-channel ratios) and its
   level, and no negative light. Measured (600 steps): direction 3.0° off, colour (0.489, 0.316, 0.195)
   against (0.48, 0.32, 0.20), albedo (0.59, 0.38, 0.23) against (0.6, 0.4, 0.25), ambient 0.011 (truth 0).
   Without the priors: direction 0.7°, but the light takes the colour: albedo colour (0.42, 0.34, 0.24),
   albedo (0.89, 0.73, 0.50); with the material priors too (`--priors all`): direction 1.5°, albedo
   (0.51, 0.33, 0.21), ambient 0.05.
2. The light alone, materials known: its direction from the object and its irradiance at the centre.
3. Two point lights (issue 18): the truth lit by two white point lights on opposite sides (irradiance at the
   centre 0.85 and 0.65), fitted with ``--lights point,point,ambient`` as training places them
   (``initial_lights``: spread on a ring, scene extent 3) and the chroma and metallic priors (0.01 each), light
   learning rate 0.05, 1200 steps. Measured: directions 0.9° and 0.5° off, irradiance ratio of the two 0.88 of the
   truth's, albedo colour (0.475, 0.321, 0.204) against (0.480, 0.320, 0.200), ambient 0.054, metallic 0.009.
   With learning rate 0.02 the second light was still 11.6° off after 1200 steps; without the priors metallic
   rose to 0.34 and the lights took the colour (albedo colour (0.35, 0.34, 0.30)); with both lights started at one
   place (the single light's placement) both converged on the brighter light (115° off the other).
4. Sun and sky: a white directional light and a near-white constant environment (SH band 0), fitted with
   ``--lights directional,ambient`` the same way: direction 1.0° off, ambient 0.150 against the sky's 0.127,
   albedo colour (0.455, 0.312, 0.234) (the sky's blue tint goes partly into the albedo), level 0.95-1.17 of the
   truth per channel.
5. The light phase (``TrainConfig.material_tie_until``): a spotted sphere (cream, near-black patches) under a point
   light and a dim ambient, every material channel one value for the first third of the fit: the ambient's share
   and the albedo (scaled per channel) recovered, and better than without the phase.
"""

from __future__ import annotations

import numpy as np
import pytest

from triplet_cl.camera import Camera
from triplet_cl.lights import (
    AmbientLight,
    DirectionalLight,
    LightInit,
    PointLight,
    SHEnvironmentLight,
    initial_lights,
)
from triplet_cl.losses import photometric_loss_and_grad
from triplet_cl.materials import get_brdf, highlight_vertices
from triplet_cl.optim import Adam
from triplet_cl.priors import LIGHT_WEIGHTS, Priors
from triplet_cl.render import RenderSettings, render
from triplet_cl.scene import Scene, logit
from triplet_cl.train import TrainConfig, tie_rows

trimesh = pytest.importorskip("trimesh")

RES = 32
TRUE_ALBEDO = np.array([0.6, 0.4, 0.25])
TRUE_POS = np.array([1.2, 2.0, 1.5])
TRUE_I = 6.0
START_POS = np.array([-0.3, 2.5, 0.4])  # above the object, as training places it (PointLight.initial)
SETTINGS = RenderSettings(K=8, sigma=None, background=(0.0, 0.0, 0.0))


def _soup():
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.8)
    V = np.asarray(m.vertices)[np.asarray(m.faces)].reshape(-1, 3)
    return V, np.arange(len(V)).reshape(-1, 3)


def _cameras():
    cams = []
    for k in range(8):
        t = 2 * np.pi * k / 8
        eye = [3.0 * np.sin(t), 1.0 + 0.8 * np.cos(3 * t), 3.0 * np.cos(t)]
        cams.append(Camera.look_at(eye, [0, 0, 0], [0, 1, 0], 45, RES, RES))
    return cams


def _scene(V, F, albedo, rough, metal, lights):
    n = len(V)
    act = np.tile(np.r_[albedo, rough, metal, 0.99], (n, 1))
    return Scene.from_arrays(V, F, material=logit(act), alpha=np.full((n, 1), logit(0.999)), lights=lights)


def _fit(scene, targets, cams, iterations, groups, priors=None, tie_until=0, lobes="tied", track=None):
    opt = Adam()
    for name, lr in groups.items():
        opt.add_group(name, [getattr(scene, name)], lr=lr, betas=(0.9, 0.999))
    rng = np.random.default_rng(0)
    for it in range(iterations):
        i = int(rng.integers(len(cams)))
        r = render(scene, cams[i], SETTINGS)
        r.backward(photometric_loss_and_grad(r.image, targets[i], lam=0.2)[1])  # the training loss
        if priors is not None:
            priors.apply(scene, it)
        held = None
        if it < tie_until:  # the light phase of training (TrainConfig.material_tie_until)
            lobe = get_brdf(scene.brdf).lobe_columns
            if lobes == "held":  # TrainConfig.light_phase_lobes: values put back, per-vertex Adam moments
                held = np.array(scene.material.data[:, lobe])
                tie_rows(scene.material, [c for c in range(scene.material.data.shape[1]) if c not in lobe])
            else:
                tie_rows(scene.material)
        opt.step()
        opt.zero_grad()
        if held is not None:
            scene.material.data[:, lobe] = held
        if priors is not None:
            priors.project(scene)
        if track is not None:
            track(scene)
    seen = np.concatenate([render(scene, c, SETTINGS).image.reshape(-1, 3) for c in cams])
    return float(np.sqrt(np.mean((seen - np.concatenate([t.reshape(-1, 3) for t in targets])) ** 2)))


@pytest.fixture(scope="module")
def synthetic():
    V, F = _soup()
    cams = _cameras()
    truth = _scene(V, F, TRUE_ALBEDO, 0.4, 0.0, [PointLight(TRUE_POS, np.full(3, TRUE_I))])
    targets = [render(truth, c, SETTINGS).image.copy() for c in cams]
    assert all(t.max() > 0.2 for t in targets)  # lit views
    return V, F, cams, targets


@pytest.mark.slow
def test_joint_recovery_of_light_direction_albedo_colour_and_level(synthetic):
    V, F, cams, targets = synthetic
    ini = get_brdf("cook_torrance").channels
    scene = _scene(V, F, [ini[0].init] * 3, ini[3].init, ini[4].init,
                   [PointLight(START_POS, np.full(3, 2.0)), AmbientLight(np.full(3, 0.1))])
    # 1500 steps: the fit wanders on the way (measured every 150 steps with Mitsuba's direct BSDF, session 38: the
    # ambient 0.016-0.076, the direction 2.8-5.8°, the level below 0.85 x until step 1050; from step 1200 on the
    # level 1.01-1.05 x, the direction 3.3-5.1°, the ambient falling to 0.008 at 1500. The shading before passed at
    # 600 and failed from 900: ambient 0.15, direction 5.7-6.5°, level 0.5-1.33 x)
    # Judged on the mean state of the last 300 steps: Adam's steps keep the lights and materials swinging from step
    # 300 on (the ambient between ~0.01 and ~0.1, a metallic tied near 0.55 on this faceted sphere: session 46, with a
    # metal's environment weights from its lobe, the ambient 0.084 and the albedo's red share 0.501 at step 1500
    # itself, 0.022 and 0.49 on average over steps 1200-1500)
    n = V / np.linalg.norm(V, axis=1, keepdims=True)
    to_light = TRUE_POS - V
    # the albedo is observable where the true light reaches (the far side is black: no information)
    lit = np.sum(n * to_light, axis=1) / np.linalg.norm(to_light, axis=1) > 0.3
    brdf = get_brdf("cook_torrance")
    states = []

    def track(s):
        pt, amb = s.current_lights()
        act = brdf.activate(np.asarray(s.material.data, np.float64))
        states.append((amb.color.max(), act[lit, :3].mean(axis=0), np.asarray(pt.position, np.float64),
                       # the level the photos fix: the diffuse albedo (1 - metallic) albedo times the light's
                       # irradiance at the centre (its distance and intensity trade, and so do metallic and albedo —
                       # metallic ends ~0.5 on this faceted sphere in either shading: the albedo alone wanders, 0.78
                       # -> 0.35 of the truth's 0.6 between steps 150 and 1200)
                       ((1 - act[lit, 4:5]) * act[lit, :3]).mean(axis=0) * pt.intensity.mean()
                       / (pt.position @ pt.position), min(amb.color.min(), pt.intensity.min())))

    err = _fit(scene, targets, cams, 1500, {"material": 0.05, "light_params": 0.02},
               Priors(TrainConfig(prior_from=0, **LIGHT_WEIGHTS), np.zeros(3)), track=track)
    assert err < 0.01, f"the fit itself failed (RMSE {err:.4f})"
    last = states[-300:]
    assert min(x[4] for x in last) >= 0, "a negative light"
    # The ambient is judged on the last 750 steps against its start. Under one light a constant ambient is exactly
    # absorbed by the per-vertex albedo (ρ' = ρ·E/(E + a) at each vertex), so only the 0.02 ambient prior pulls it
    # down, and its level is a random walk of Adam's steps around ~0.03 (0.01-0.19 over 150-step windows). Session 57
    # measured 10 view orders with the code of two commits: the mean of the last 300 steps ranged 0.014-0.137 and
    # the former bound 0.04 on it passed about half the orders on either commit (seed 0 passed on one, failed on the
    # other; the fits themselves, RMSE 0.003-0.01, and the direction, level and colour below are unaffected); the
    # mean of the last 750 steps, recorded in 8 of those runs, stayed within 0.024-0.072
    # (bench/results/recovery_ambient_pocl_2026-11-28.txt)
    ambient = np.mean([x[0] for x in states[-750:]])
    assert ambient < 0.1, f"ambient light {ambient:.3f} (started at 0.1, truth 0)"
    pos = np.mean([x[2] for x in last], axis=0)
    ang = np.degrees(np.arccos(np.clip(pos @ TRUE_POS / np.linalg.norm(pos) / np.linalg.norm(TRUE_POS), -1, 1)))
    assert ang < 5.0, f"light direction off by {ang:.1f} deg ({pos})"
    albedo = np.mean([x[1] for x in last], axis=0)
    np.testing.assert_allclose(albedo / albedo.sum(), TRUE_ALBEDO / TRUE_ALBEDO.sum(), atol=0.02)
    level = np.mean([x[3] for x in last], axis=0)
    np.testing.assert_allclose(level, TRUE_ALBEDO * TRUE_I / (TRUE_POS @ TRUE_POS), rtol=0.15)


@pytest.mark.slow
def test_light_recovery_with_known_materials(synthetic):
    V, F, cams, targets = synthetic
    scene = _scene(V, F, TRUE_ALBEDO, 0.4, 0.0, [PointLight(START_POS, np.full(3, 2.0))])
    err = _fit(scene, targets, cams, 300, {"light_params": 0.02})
    assert err < 0.01, f"the fit itself failed (RMSE {err:.4f})"
    (pt,) = scene.current_lights()
    cos = pt.position @ TRUE_POS / np.linalg.norm(pt.position) / np.linalg.norm(TRUE_POS)
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert ang < 5.0, f"light direction off by {ang:.1f} deg ({pt.position})"
    irr = pt.intensity.mean() / (pt.position @ pt.position)  # irradiance at the centre (the object's scale)
    assert irr == pytest.approx(TRUE_I / (TRUE_POS @ TRUE_POS), rel=0.2)


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


LR_LIGHTS = 0.05


def _fit_from_training_init(V, F, cams, truth_lights, kinds, iterations=1200):
    """Render the truth (albedo TRUE_ALBEDO, roughness 0.4, metallic 0), then fit lights and materials from the
    training's initial values (lights placed by ``initial_lights``) with the chroma and metallic priors."""
    truth = _scene(V, F, TRUE_ALBEDO, 0.4, 0.0, truth_lights)
    targets = [render(truth, c, SETTINGS).image.copy() for c in cams]
    ini = get_brdf("cook_torrance").channels
    lights = initial_lights(kinds, LightInit(np.zeros(3), 3.0, np.array([0.0, 1.0, 0.0]), 2, np.random.default_rng(0)))
    scene = _scene(V, F, [ini[0].init] * 3, ini[3].init, ini[4].init, lights)
    err = _fit(scene, targets, cams, iterations, {"material": 0.05, "light_params": LR_LIGHTS},
               Priors(TrainConfig(prior_from=0, prior_chroma=0.01, prior_metallic=0.01), np.zeros(3)))
    act = get_brdf("cook_torrance").activate(np.asarray(scene.material.data, np.float64))
    return err, scene.current_lights(), act


@pytest.mark.slow
def test_two_point_lights_are_recovered_with_the_albedo():
    V, F = _soup()
    P = [np.array([1.6, 1.8, 1.2]), np.array([-1.8, 0.6, -1.0])]
    I = [6.0, 3.0]
    err, lights, act = _fit_from_training_init(V, F, _cameras(), [PointLight(P[0], np.full(3, I[0])),
                                                                 PointLight(P[1], np.full(3, I[1]))],
                                               ["point", "point", "ambient"])
    assert err < 0.01, f"the fit itself failed (RMSE {err:.4f})"
    pts = [lt for lt in lights if isinstance(lt, PointLight)]
    (amb,) = [lt for lt in lights if isinstance(lt, AmbientLight)]
    matched = [min(pts, key=lambda p: _angle(p.position, q)) for q in P]
    assert matched[0] is not matched[1], "both lights converged on one"
    for p, q in zip(matched, P, strict=False):
        assert _angle(p.position, q) < 5.0, f"light at {p.position}: {_angle(p.position, q):.1f} deg off {q}"
    irr = [p.intensity.mean() / (p.position @ p.position) for p in matched]  # irradiance at the centre
    true_irr = [i / (q @ q) for i, q in zip(I, P, strict=False)]
    assert irr[0] / irr[1] == pytest.approx(true_irr[0] / true_irr[1], rel=0.2)
    assert amb.color.max() < 0.08, f"ambient light {amb.color} (truth 0)"
    # both sides are lit; the albedo's level trades against the lights' (only the product is seen): its colour
    albedo = act[:, :3].mean(axis=0)
    np.testing.assert_allclose(albedo / albedo.sum(), TRUE_ALBEDO / TRUE_ALBEDO.sum(), atol=0.02)
    assert act[:, 4].mean() < 0.05  # metallic (truth 0)


@pytest.mark.slow
def test_sun_and_sky_are_recovered_with_the_albedo():
    V, F = _soup()
    sun, sky = np.array([0.5, 0.8, 0.3]), np.array([0.12, 0.12, 0.14])
    err, lights, act = _fit_from_training_init(V, F, _cameras(), [DirectionalLight(sun, np.full(3, 1.5)),
                                                                 SHEnvironmentLight.constant(sky, 2)],
                                               ["directional", "ambient"])
    assert err < 0.01, f"the fit itself failed (RMSE {err:.4f})"
    d, amb = lights
    assert _angle(d.direction, sun) < 5.0, f"sun direction {d.direction}: {_angle(d.direction, sun):.1f} deg off"
    assert amb.color.mean() == pytest.approx(sky.mean(), rel=0.3)
    albedo = act[:, :3].mean(axis=0)
    np.testing.assert_allclose(albedo / albedo.sum(), TRUE_ALBEDO / TRUE_ALBEDO.sum(), atol=0.05)
    np.testing.assert_allclose(albedo, TRUE_ALBEDO, rtol=0.25)


# ---- roughness and metallic (issue 18, item 3; bench/diag_brdf.py is the diagnostic these come from) -------------
HL_RES = 48
HL_LIGHT = np.array([1.2, 2.0, 1.5])


def _hl_sphere():
    """A sphere soup (icosphere 3, radius 0.8) and 8 cameras around it at ``HL_RES``²."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    V = np.asarray(m.vertices)[np.asarray(m.faces)].reshape(-1, 3)
    cams = []
    for k in range(8):
        t = 2 * np.pi * k / 8
        cams.append(Camera.look_at([3.0 * np.sin(t), 1.0 + 0.8 * np.cos(3 * t), 3.0 * np.cos(t)], [0, 0, 0],
                                   [0, 1, 0], 45, HL_RES, HL_RES))
    return V, np.arange(len(V)).reshape(-1, 3), cams


def _brdf_fit(albedo, rough, metal, ambient, iterations=1000):
    """Render a sphere soup (icosphere 3, 48², 8 views) with a known material under a known point light + ambient;
    fit the materials alone (lights known) from training's initial values, training's loss, Adam betas and
    material learning rate (times ``TrainConfig.lr_lobe_scale`` on the lobe columns), decayed to 0.002 so that the
    end point is the fit's, not Adam's jitter. Returns the activated materials, the vertices facing the light and
    those in a highlight in at least one view (half vector within ~14° of the normal)."""
    from triplet_cl.optim import ExponentialDecay

    V, F, cams = _hl_sphere()

    def lights():
        return [PointLight(HL_LIGHT, np.full(3, 6.0)), AmbientLight(np.full(3, ambient))]

    truth = _scene(V, F, albedo, rough, metal, lights())
    targets = [render(truth, c, SETTINGS).image.copy() for c in cams]
    brdf = get_brdf("cook_torrance")
    ini = {c.name: c.init for c in brdf.channels}
    scene = _scene(V, F, [ini["albedo_r"]] * 3, ini["roughness"], ini["metallic"], lights())
    cfg = TrainConfig()
    scale = np.ones((1, brdf.num_channels))
    scale[0, brdf.lobe_columns] = cfg.lr_lobe_scale
    opt = Adam()
    opt.add_group("material", [scene.material], lr=ExponentialDecay(cfg.lr_material, 0.002, iterations),
                  lr_scale=[scale], betas=tuple(cfg.betas))
    rng = np.random.default_rng(0)
    for _ in range(iterations):
        i = int(rng.integers(len(cams)))
        r = render(scene, cams[i], SETTINGS)
        r.backward(photometric_loss_and_grad(r.image, targets[i], lam=cfg.ssim_lambda)[1])
        opt.step()
        opt.zero_grad()
    act = brdf.activate(np.asarray(scene.material.data, np.float64))
    n = V / np.linalg.norm(V, axis=1, keepdims=True)
    ldir = (HL_LIGHT - V) / np.linalg.norm(HL_LIGHT - V, axis=1, keepdims=True)
    seen = np.sum(n * ldir, axis=1) > 0.2
    hl = highlight_vertices(V, n, HL_LIGHT, cams)
    assert hl.sum() > 100
    return act, seen, hl


@pytest.mark.slow
def test_dielectric_roughness_and_zero_metallic_are_recovered():
    """Orange dielectric, roughness 0.3, metallic 0. Measured (2026-11-24): roughness 0.354 over the lit vertices
    (0.438 over the highlit ones), metallic 0.081; with the initial roughness 0.9 of before: roughness 0.86, metallic
    0.129 (the rough lobe passing for diffuse light where no highlight is seen)."""
    act, seen, hl = _brdf_fit([0.6, 0.4, 0.25], 0.3, 0.0, 0.03)
    assert abs(act[seen, 3].mean() - 0.3) < 0.1, f"roughness {act[seen, 3].mean():.3f} (truth 0.3)"
    assert act[seen, 4].mean() < 0.12, f"metallic {act[seen, 4].mean():.3f} (truth 0)"


@pytest.mark.slow
def test_gold_metallic_and_roughness_are_recovered_where_a_highlight_is_seen():
    """Gold (albedo (1, 0.78, 0.34), metallic 1, roughness 0.35). Where a highlight is seen the data fix the metal:
    measured metallic 0.77, roughness 0.40 there; elsewhere (no highlight in any view) metallic and albedo trade along
    a valley ((1 − m)·albedo diffuse vs the ambient's albedo) and metallic stays ~0.5 (mean 0.56 over the lit
    vertices): the known limit, README "Roughness and metallic"."""
    act, seen, hl = _brdf_fit([1.0, 0.78, 0.34], 0.35, 1.0, 0.05)
    assert act[hl, 4].mean() > 0.7, f"metallic {act[hl, 4].mean():.3f} where highlit (truth 1)"
    assert abs(act[hl, 3].mean() - 0.35) < 0.1, f"roughness {act[hl, 3].mean():.3f} where highlit (truth 0.35)"
    assert act[seen, 4].mean() > 0.4  # the metal is not pushed to a dielectric elsewhere either


def _spotted(V, F, dark_above=0.5, colours=((0.05, 0.05, 0.05), (0.85, 0.75, 0.7))):
    """A sphere soup with a cow-like albedo: cream with dark patches (per face), and its vertex albedo; a lower
    ``dark_above`` makes the dark part larger (``-0.3``: most of the sphere, as gadget's black tracks and frame)."""
    c = V[F].mean(axis=1)
    dark = (np.sin(4 * c[:, 0]) * np.cos(3 * c[:, 1]) + 0.4 * np.sin(5 * c[:, 2])) > dark_above
    face_albedo = np.where(dark[:, None], colours[0], colours[1])
    return np.repeat(face_albedo, 3, axis=0), dark


def _fit_spotted(tie_until, lobes=None, **spots):
    V, F = _soup()
    cams = _cameras()
    albedo, _ = _spotted(V, F, **spots)
    true_amb = 0.04
    truth = Scene.from_arrays(V, F, material=logit(np.c_[albedo, np.tile([0.4, 1e-3, 0.999], (len(V), 1))]),
                              alpha=np.full((len(V), 1), logit(0.999)),
                              lights=[PointLight(TRUE_POS, np.full(3, TRUE_I)), AmbientLight(np.full(3, true_amb))])
    targets = [render(truth, c, SETTINGS).image.copy() for c in cams]
    start = [PointLight(START_POS, np.full(3, 9.0)), AmbientLight(np.full(3, 0.1))]
    ini = {c.name: c.init for c in get_brdf("cook_torrance").channels}  # training's initial values
    scene = _scene(V, F, np.full(3, ini["albedo_r"]), ini["roughness"], ini["metallic"], start)
    err = _fit(scene, targets, cams, 900, {"material": 0.05, "light_params": 0.02}, tie_until=tie_until,
               lobes=lobes or TrainConfig().light_phase_lobes)
    assert err < 0.02, f"the fit itself failed (RMSE {err:.4f})"
    pt, amb = scene.current_lights()
    act = get_brdf("cook_torrance").activate(np.asarray(scene.material.data, np.float64))
    # what the photos can fix: the ambient's share of the light at the centre (the albedo × light scale is free)
    e_pt = pt.intensity.mean() / np.sum(pt.position ** 2) / np.pi
    share = amb.color.mean() / e_pt / (true_amb / (TRUE_I / np.sum(TRUE_POS ** 2) / np.pi))
    scale = (act[:, :3] * albedo).sum(0) / (act[:, :3] ** 2).sum(0)  # per channel, as the albedo PSNR
    alb_err = float(np.median(np.abs(act[:, :3] * scale - albedo)))
    return share, alb_err, _angle(pt.position, TRUE_POS), act[:, 3:5]


@pytest.mark.slow
def test_light_phase_recovers_the_ambient_share_and_the_albedo():
    """The light phase (issue 18): photos of a Lambertian object fix albedo × irradiance per point, so with free
    per-vertex albedo from the first step the lights stay about where the first steps leave them. A spotted sphere
    (cream with near-black patches) lit by a point light and a dim ambient (0.04), fitted from training's initial
    values (ambient 0.1, albedo 0.5, roughness 0.5, metallic 0.1), 900 steps. Measured: materials tied for the
    first 300 steps, roughness and metallic held there (the default ``TrainConfig.light_phase_lobes``): ambient
    share 1.47 × the truth's, scaled albedo error median 0.085, direction 0.4°; never tied: 1.77 ×, 0.161, 6.7°
    (lobes tied too: 1.38 ×, 0.067, 2.9°). With the shading before session 38 (Lambert diffuse, Schlick-GGX
    masking) the same fits measured 1.28 ×, 0.064, 0.6° (never tied 1.65 ×, 0.142, 8.0°): the path tracer's Disney
    diffuse, whose view-dependent (1 - Fi/2) and retro-reflection terms the one tied albedo of the light phase
    cannot place either, leaves the phase's estimate less good on this spotted sphere, while on the real captures
    the lights came closer to the truth (spot from scratch: irradiance at the centre 1.59 for the truth's 1.56,
    ambient 0.092 for 0.08; before 1.72 and 0.102).
    (The dark sphere below is the case the held lobes are for.)"""
    share, alb, ang, _ = _fit_spotted(300)
    assert 0.7 < share < 1.6, f"ambient share {share:.2f} x the truth's"
    assert alb < 0.1, f"scaled albedo error median {alb:.3f}"
    assert ang < 5.0, f"light direction {ang:.1f} deg off"
    share0, alb0, ang0, _ = _fit_spotted(0)
    assert alb < 0.75 * alb0 and abs(share - 1) < abs(share0 - 1), (
        f"the light phase should beat none: albedo {alb:.3f} vs {alb0:.3f}, share {share:.2f} vs {share0:.2f}")


@pytest.mark.slow
def test_light_phase_keeps_a_dark_object_dielectric():
    """``TrainConfig.light_phase_lobes`` (issue 18, the metallic flip): during the light phase one roughness and one
    metallic for the whole object followed the mean of their gradients at Adam's full step, and on a mostly dark
    object (gadget's black frame and tracks) that mean says "darker": metallic rose for all (gadget's soup 0.1 ->
    0.64 in 100 steps; the mesh came out metallic 1.00, truth 0). A sphere mostly near-black (0.03) with orange
    patches, a dielectric (metallic 0.001, roughness 0.4), fitted as the light-phase test above. Measured: lobes
    held in the phase (the default) metallic mean 0.13, scaled albedo error median 0.012, ambient share 1.44 ×,
    direction 0.2°; lobes tied: metallic 0.51, 0.032, 1.92 ×, 1.6°; frozen (no gradient in the phase, fresh Adam
    moments after it): 0.24, 0.019, 1.71 ×, 1.1°."""
    spots = {"dark_above": -0.3, "colours": ((0.03, 0.03, 0.03), (0.8, 0.3, 0.1))}
    share, alb, ang, lobes = _fit_spotted(300, "held", **spots)
    share_t, alb_t, ang_t, lobes_t = _fit_spotted(300, "tied", **spots)
    metal, metal_t = lobes[:, 1].mean(), lobes_t[:, 1].mean()
    assert metal < 0.25 and metal < metal_t - 0.2, f"metallic {metal:.3f} held vs {metal_t:.3f} tied (truth 0)"
    assert alb < 0.02 and alb < alb_t, f"scaled albedo error median {alb:.3f} held vs {alb_t:.3f} tied"
    assert share < share_t and ang < 2.0, f"ambient share {share:.2f} vs {share_t:.2f} tied, direction {ang:.1f} deg"


def _metallic_trial(albedo, rough, metal, steps=120):
    """The mesh stage's metal-or-dielectric trial (``mesh.refine.metallic_trial``) on a sphere (icosphere 3, 48²,
    8 views) rendered by our renderer with a known material under a point light and an ambient light. Its start is
    what the soup hands the mesh stage: a near-dielectric fit (training's initial values, metallic 0.1 and roughness
    0.5 held, the albedo per vertex, 150 steps), roughness and AO then one value (their mean)."""
    from triplet_cl.mesh.refine import metallic_trial

    V, F, cams = _hl_sphere()

    def lights():
        return [PointLight(HL_LIGHT, np.full(3, 6.0)), AmbientLight(np.full(3, 0.05))]

    albedo = np.asarray(albedo, np.float64)
    truth = _scene(V, F, albedo if albedo.ndim == 1 else np.zeros(3), rough, metal, lights())
    if albedo.ndim == 2:
        truth.material.data[:, :3] = logit(albedo)
    targets = [render(truth, c, SETTINGS).image.copy() for c in cams]
    brdf = get_brdf("cook_torrance")
    ini = {c.name: c.init for c in brdf.channels}
    scene = _scene(V, F, [ini["albedo_r"]] * 3, ini["roughness"], ini["metallic"], lights())
    cfg = TrainConfig()
    rng = np.random.default_rng(0)
    opt = Adam()
    opt.add_group("material", [scene.material], lr=cfg.lr_material, betas=tuple(cfg.betas))
    lobe = brdf.lobe_columns
    for _ in range(150):  # the soup: a dielectric-looking start (lobes held as in the light phase)
        i = int(rng.integers(len(cams)))
        r = render(scene, cams[i], SETTINGS)
        r.backward(photometric_loss_and_grad(r.image, targets[i], lam=cfg.ssim_lambda)[1])
        scene.material.grad[:, lobe] = 0.0
        opt.step()
        opt.zero_grad()
    tied = [3, 4, 5]
    scene.material.data[:, tied] = np.asarray(scene.material.data)[:, tied].mean(axis=0, keepdims=True)
    views = rng.integers(len(cams), size=steps)

    def loss_and_backward(k):
        r = render(scene, cams[views[k]], SETTINGS)
        loss, v = photometric_loss_and_grad(r.image, targets[views[k]], lam=cfg.ssim_lambda)
        r.backward(v)
        return float(loss)

    before = np.array(scene.material.data)
    out = metallic_trial(scene, tied, 4, loss_and_backward, steps, lr_material=cfg.lr_material, rough_col=3)
    after = np.asarray(scene.material.data)
    np.testing.assert_array_equal(np.delete(after, 4, axis=1), np.delete(before, 4, axis=1))  # put back
    assert np.ptp(after[:, 4]) == 0 and len(out["curves"]["0.01"]) == steps
    rough_metal = 1 / (1 + np.exp(-out["tied"]["0.99"][0]))
    return out, float(rough_metal)


@pytest.mark.slow
def test_metallic_trial_tells_a_metal_from_dielectrics():
    """``MeshConfig.metallic_trial`` (issue 18): the mesh stage decides metal or dielectric by a short fit of each,
    instead of a tied metallic that Adam steps by the sign of its mean gradient (which ended the metal capture's mesh
    at 0.11 and gadget's at 0.48). Gold (metallic 1, roughness 0.35) must come out metal from the soup's
    dielectric-looking start; an orange dielectric (roughness 0.3) and a mostly near-black dielectric (gadget's case)
    must stay dielectric. Measured (120 steps each; mean loss over the second half, dielectric / metal): gold 0.0177 /
    0.0027, the metal's roughness 0.355; orange 0.00029 / 0.0069; dark 0.00011 / 0.0029."""
    gold, r_gold = _metallic_trial([1.0, 0.78, 0.34], 0.35, 1.0)
    assert gold["metallic"] == 0.99, f"gold: {gold['loss']} (metal's roughness {r_gold:.2f})"
    assert r_gold < 0.6, f"gold's fitted roughness {r_gold:.2f} (truth 0.35)"
    orange, r_orange = _metallic_trial([0.6, 0.4, 0.25], 0.3, 0.0)
    assert orange["metallic"] == 0.01, f"orange dielectric: {orange['loss']} (metal's roughness {r_orange:.2f})"
    V, F, _ = _hl_sphere()
    spots, _ = _spotted(V, F, dark_above=-0.3, colours=((0.03, 0.03, 0.03), (0.8, 0.3, 0.1)))
    dark, r_dark = _metallic_trial(spots, 0.4, 0.0)
    assert dark["metallic"] == 0.01, f"dark dielectric: {dark['loss']} (metal's roughness {r_dark:.2f})"


def test_metallic_trial_refuses_a_near_lambertian_metal():
    """``metallic_trial``'s rule: a metal that wins only with its roughness fitted above ``MAX_METAL_ROUGHNESS`` is
    refused (the photos of so rough a metal are what a dielectric explains as well; measured on captures with two
    point lights and on gadget, both dielectric, the metal won at roughness 0.92 / 0.91). A made-up loss that
    prefers the metal while its gradient drives the roughness up; the scene is put back but for the metallic."""
    from autodiff import Param
    from triplet_cl.mesh.refine import MAX_METAL_ROUGHNESS, metallic_trial

    def scene_stub():
        class S:
            V = alpha = vertex_sh = light_params = None
        s = S()
        s.material = Param(np.tile(logit(np.array([0.5, 0.5, 0.5, 0.5, 0.1, 0.99])), (5, 1)), "material")
        return s

    def loss_and_backward(k):
        g = np.zeros_like(s.material.data)
        g[:, 3] = -1.0  # the roughness goes up at Adam's full rate: 0.5 -> ~0.95 in 60 steps
        s.material.grad = g
        return 0.5 if s.material.data[0, 4] > 0 else 1.0

    s = scene_stub()
    out = metallic_trial(s, [3, 4, 5], 4, loss_and_backward, 60, lr_material=0.05)
    assert out["metallic"] == 0.99 and out["refused"] is None  # no roughness column named: the loss decides
    s = scene_stub()
    before = np.array(s.material.data)
    out = metallic_trial(s, [3, 4, 5], 4, loss_and_backward, 60, lr_material=0.05, rough_col=3)
    r = 1 / (1 + np.exp(-out["tied"]["0.99"][0]))
    assert r > MAX_METAL_ROUGHNESS and out["refused"] == 0.99 and out["metallic"] == 0.01
    np.testing.assert_allclose(s.material.data[:, 4], logit(0.01), rtol=1e-6)
    np.testing.assert_array_equal(np.delete(s.material.data, 4, axis=1), np.delete(before, 4, axis=1))


def test_metallic_trial_holds_the_geometry():
    """The trial optimises materials and lights only: positions and opacities require no gradient while it runs (the
    renders skip the geometry's adjoint) and do again afterwards, also when a step fails."""
    from autodiff import Param
    from triplet_cl.mesh.refine import metallic_trial

    class S:
        light_params = None

    s = S()
    s.V, s.alpha = Param(np.zeros((5, 3)), "V"), Param(np.zeros((5, 1)), "alpha")
    s.vertex_sh = Param(np.zeros((5, 6)), "vertex_sh")
    s.vertex_sh.requires_grad = False  # held by its caller already: it stays held
    s.material = Param(np.tile(logit(np.array([0.5, 0.5, 0.5, 0.5, 0.1, 0.99])), (5, 1)), "material")
    seen = []

    def loss_and_backward(k):
        seen.append((s.V.requires_grad, s.alpha.requires_grad, s.vertex_sh.requires_grad))
        s.material.grad = np.ones_like(s.material.data)
        return 1.0

    metallic_trial(s, [3, 4, 5], 4, loss_and_backward, 3, lr_material=0.05)
    assert set(seen) == {(False, False, False)} and s.V.requires_grad and s.alpha.requires_grad
    assert not s.vertex_sh.requires_grad

    def failing(k):
        raise RuntimeError("a step failed")

    with pytest.raises(RuntimeError, match="a step failed"):
        metallic_trial(s, [3, 4, 5], 4, failing, 3, lr_material=0.05)
    assert s.V.requires_grad and s.alpha.requires_grad and not s.vertex_sh.requires_grad


def test_tie_rows_keeps_equal_rows_equal():
    """``tie_rows``: every row of the gradient becomes the mean, so equal rows with equal Adam moments stay equal."""
    from autodiff import Param

    p = Param(np.tile([0.2, -0.1, 0.3], (5, 1)), "material")
    opt = Adam()
    opt.add_group("material", [p], lr=0.1)
    rng = np.random.default_rng(3)
    for _ in range(4):
        p.grad = rng.normal(size=(5, 3))
        mean = p.grad.mean(axis=0)
        tie_rows(p)
        np.testing.assert_allclose(p.grad, np.tile(mean, (5, 1)), rtol=1e-12)
        opt.step()
        opt.zero_grad()
    assert np.ptp(p.data, axis=0).max() == 0 and np.abs(p.data - [0.2, -0.1, 0.3]).max() > 0.05
