"""``shade_lanes.cl`` (eight fragments per work-item in vector lanes, the CPU path of the packed shading) against
``shade.cl`` (the reference): forward, every adjoint block, the light gradients, in float64 to rounding and in
float32 as accurate as shade.cl itself; its own float64 central differences; what it covers
(``lanes_supported``); and a whole render's gradients through it."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from tests.gradients import sampled_fd
from tests.test_shade import CAM, make_fragments
from triplet_cl.lights import (
    AmbientLight,
    BounceLight,
    DirectionalLight,
    PointLight,
    SHEnvironmentLight,
    VertexSHLight,
    pack_lights,
)
from triplet_cl.ops import shade as shade_op

ENV_C2 = np.array([[1.8, 0.3, -0.2, 0.1, 0.05, -0.1, 0.2, 0.0, -0.05],
                   [1.6, -0.1, 0.3, 0.2, -0.05, 0.1, 0.0, 0.1, 0.05],
                   [2.0, 0.2, 0.1, -0.3, 0.1, 0.0, -0.1, 0.05, 0.1]])

LIGHT_SETS = {
    "ambient": lambda: [AmbientLight([0.2, 0.5, 0.8])],
    "point": lambda: [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0], falloff=True)],
    "point_nofalloff": lambda: [PointLight([-1.0, 0.5, 2.0], [0.9, 0.8, 1.1], falloff=False)],
    "directional": lambda: [DirectionalLight([0.3, -0.2, 1.0], [1.5, 1.0, 0.7])],
    # the training's default (point + ambient, 9 parameters)
    "point_ambient": lambda: [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0]), AmbientLight([0.1, 0.1, 0.1])],
    # more parameters (21) than the reduction's 16 columns: two rounds of the group sum
    "mix": lambda: [AmbientLight([0.2, 0.5, 0.8]), PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0]),
                    DirectionalLight([0.3, -0.2, 1.0], [1.5, 1.0, 0.7]),
                    PointLight([-1.0, 0.5, 2.0], [0.9, 0.8, 1.1], falloff=False)],
    # an SH environment of degree 2 (27 coefficients) with a point light: the mesh stage's lights, and with its traced
    # bounce (a per-fragment radiance in the VL block); an environment whose active degree (1) is below its stored one
    "point_env2": lambda: [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0]), SHEnvironmentLight(ENV_C2)],
    "mesh_stage": lambda: [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0]), SHEnvironmentLight(ENV_C2), BounceLight()],
    "env_active1": lambda: [SHEnvironmentLight(ENV_C2, degree=1), AmbientLight([0.1, 0.1, 0.2])],
}


def packed_case(device, rng, lights, P, real, with_vis, rough_lo=0.2, two_sided=True):
    """Packed inputs (blocks in a shuffled order, as the rasterizer lays them out: alpha between position and normal,
    visibility last) and the same arrays; returns (packed ShadeInputs, the [P, C] host array, blocks)."""
    pos, nrm, mat, _, vlight = make_fragments(rng, "cook_torrance", P=P, rough_lo=rough_lo)
    table = pack_lights(lights)
    nv = table.num_shadowed if with_vis else 0
    named = [("POS", pos), ("ALPHA", rng.uniform(0, 1, (P, 1))), ("NRM", nrm), ("MAT", mat)]
    vl = vlight if table.has_vertex_sh else None  # the bounce's radiance (and a direction it does not use)
    if vl is not None:
        named.append(("VL", vl))
    if nv:
        named.append(("VIS", rng.uniform(0, 1, (P, nv))))
    offs = np.cumsum([0] + [a.shape[1] for _, a in named])
    blocks = {n: (int(offs[i]), a.shape[1]) for i, (n, a) in enumerate(named)}
    fa = np.concatenate([a for _, a in named], 1).astype(real)
    _, inp = shade_op.prepare(pos, nrm, mat, np.zeros(P, np.int32), CAM, lights, device=device, real=real, vlight=vl)
    pinp = shade_op.packed_inputs(device, cla.to_device(device.queue, fa), blocks, CAM, table, inp.lt_i, inp.lt_f,
                                  "cook_torrance", two_sided, real)
    return pinp, fa, blocks


def run(device, pinp, v_rgb_h, v_alpha_h, lanes):
    q = device.queue
    rgb, alpha = shade_op.forward_packed(device, pinp, lanes=lanes)
    v_fa, v_par = shade_op.backward_packed(device, pinp, cla.to_device(q, v_rgb_h), cla.to_device(q, v_alpha_h),
                                           lanes=lanes)
    return rgb.get().astype(np.float64), alpha.get(), v_fa.get().astype(np.float64), np.asarray(v_par)


def written_columns(blocks):
    return [c for n, (c0, w) in blocks.items() for c in range(c0, c0 + w)]


@pytest.mark.parametrize("kind", sorted(LIGHT_SETS))
@pytest.mark.parametrize("P", [1, 7, 96, 333, 1500])
@pytest.mark.parametrize("with_vis", [False, True])
def test_lanes_match_shade_cl_float64(device64, rng, kind, P, with_vis):
    """Every output of the lanes kernel equals shade.cl's to float64 rounding (the same formulas, evaluated in
    another order): rgb, the alpha copy (exact), each adjoint block, the alpha adjoint (exact) and the light
    gradients; P not a multiple of 8 (the last work-item's lanes past P), one fragment, several work-groups (1500:
    their partial sums added on the host), one-sided shading on the largest case, rows with a zero cotangent
    (exactly zero adjoints, as shade.cl's skip)."""
    lights = LIGHT_SETS[kind]()
    pinp, fa, blocks = packed_case(device64, rng, lights, P, np.float64, with_vis, two_sided=P != 1500)
    assert shade_op.lanes_cover(pinp)
    v_rgb = rng.standard_normal((P, 3))
    dead = rng.uniform(size=P) < 0.25
    v_rgb[dead] = 0.0
    v_a = rng.standard_normal(P)
    got = run(device64, pinp, v_rgb, v_a, True)
    want = run(device64, pinp, v_rgb, v_a, False)
    scale = np.abs(want[0]).max()
    np.testing.assert_allclose(got[0], want[0], rtol=1e-11, atol=1e-13 * scale)
    assert np.array_equal(got[1], want[1]) and np.array_equal(got[1], fa[:, blocks["ALPHA"][0]])
    a_col = blocks["ALPHA"][0]
    cols = [c for c in written_columns(blocks) if c != a_col]
    for c in cols:
        s = max(np.abs(want[2][:, c]).max(), 1e-300)
        np.testing.assert_allclose(got[2][:, c], want[2][:, c], rtol=1e-10, atol=1e-12 * s, err_msg=f"column {c}")
    assert np.array_equal(got[2][:, a_col], v_a)
    assert not got[2][np.ix_(dead, cols)].any()
    np.testing.assert_allclose(got[3], want[3], rtol=1e-10, atol=1e-12 * np.abs(want[3]).max())
    if (~dead).any():
        assert np.abs(got[3]).max() > 0


@pytest.mark.parametrize("kind", ["point_ambient", "mix", "mesh_stage"])
def test_lanes_float32_as_accurate_as_shade_cl(device64, rng, kind):
    """In float32 the two kernels round differently (both differ from float64 by up to ~5e-5 of the largest value
    on these inputs: the float32 inputs, near-grazing lights, sqrt and division): the lanes kernel's error against
    float64 shade.cl is at most twice shade.cl's own float32 error (plus 1e-6 of the scale), per output."""
    lights = LIGHT_SETS[kind]()
    P = 2000
    pinp64, fa, blocks = packed_case(device64, rng, lights, P, np.float64, True)
    _, inp = shade_op.prepare(np.zeros((1, 3)), np.ones((1, 3)), np.full((1, 6), 0.5), np.zeros(1, np.int32), CAM,
                              lights, device=device64, real=np.float32,
                              vlight=np.ones((1, 6)) if pack_lights(lights).has_vertex_sh else None)
    pinp32 = shade_op.packed_inputs(device64, cla.to_device(device64.queue, fa.astype(np.float32)), blocks, CAM,
                                    pack_lights(lights), inp.lt_i, inp.lt_f, "cook_torrance", True, np.float32)
    v_rgb = rng.standard_normal((P, 3))
    v_a = rng.standard_normal(P)
    truth = run(device64, pinp64, v_rgb, v_a, False)
    lanes = run(device64, pinp32, v_rgb.astype(np.float32), v_a.astype(np.float32), True)
    ref = run(device64, pinp32, v_rgb.astype(np.float32), v_a.astype(np.float32), False)
    for i, name in ((0, "rgb"), (2, "adjoint rows"), (3, "light gradients")):
        scale = np.abs(truth[i]).max()
        e_lanes = np.abs(lanes[i] - truth[i]).max() / scale
        e_ref = np.abs(ref[i] - truth[i]).max() / scale
        assert e_lanes <= 2 * e_ref + 1e-6, (name, e_lanes, e_ref)


@pytest.mark.parametrize("with_vis", [False, True])
def test_lanes_float64_central_differences(device64, rng, with_vis):
    """The lanes kernel's adjoint against central differences of its own forward (float64): sampled entries of
    every block of the packed rows (position, normal, material, the bounce's radiance, transmittance) and every light
    parameter, for L = Σ w · rgb under the training's point + ambient lights, a directional one, an SH environment of
    degree 2 and the bounce."""
    lights = [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0]), AmbientLight([0.1, 0.2, 0.1]),
              DirectionalLight([0.3, -0.2, 1.0], [1.5, 1.0, 0.7]), SHEnvironmentLight(ENV_C2), BounceLight()]
    P = 21
    pinp, fa, blocks = packed_case(device64, rng, lights, P, np.float64, with_vis, rough_lo=0.3)
    w = rng.standard_normal((P, 3))
    _, _, v_fa, v_par = run(device64, pinp, w, np.zeros(P), True)
    q = device64.queue

    def loss_fa(x):
        pinp.pos = pinp.nrm = pinp.mat = pinp.vlight = cla.to_device(q, x)
        if pinp.vis is not None:
            pinp.vis = pinp.pos
        return float((shade_op.forward_packed(device64, pinp, lanes=True)[0].get() * w).sum())

    h = 1e-6
    # (the VL block's direction columns: unused by the bounce, their adjoint 0 and so their differences)
    cols = [c for c in written_columns(blocks) if c != blocks["ALPHA"][0]]
    for c in cols:
        for p in rng.choice(P, 4, replace=False):
            xp, xm = fa.copy(), fa.copy()
            xp[p, c] += h
            xm[p, c] -= h
            num = (loss_fa(xp) - loss_fa(xm)) / (2 * h)
            assert v_fa[p, c] == pytest.approx(num, rel=1e-6, abs=1e-8), (p, c)
    pinp.pos = pinp.nrm = pinp.mat = pinp.vlight = cla.to_device(q, fa)
    if pinp.vis is not None:
        pinp.vis = pinp.pos
    lt = pinp.lt_f.get()

    def loss_lt(x):
        pinp.lt_f = cla.to_device(q, x)
        return float((shade_op.forward_packed(device64, pinp, lanes=True)[0].get() * w).sum())

    for j in range(len(lt)):
        xp, xm = lt.copy(), lt.copy()
        xp[j] += h
        xm[j] -= h
        num = (loss_lt(xp) - loss_lt(xm)) / (2 * h)
        assert v_par[j] == pytest.approx(num, rel=1e-6, abs=1e-8), j


def test_lanes_supported_and_refused(device, rng):
    """The lanes kernel covers Cook-Torrance under ambient / directional / point / SH environment / bounce lights
    (with the shadow casters' transmittance; at most LANES_MAX_PARAMS parameters) and is the default on a CPU device;
    everything else stays on shade.cl (a vertex-SH light, an environment of degree 4: 75 parameters,
    environment-occlusion columns, no lights, Blinn-Phong, separate arrays), and asking for lanes there is an error."""
    pinp, _, _ = packed_case(device, rng, LIGHT_SETS["mix"](), 16, np.float32, True)
    assert shade_op.lanes_supported(device, pinp) == device.is_cpu
    for lights in ([SHEnvironmentLight(np.ones((3, 25)))], [PointLight([1, 1, 1], [1, 1, 1]), VertexSHLight()]):
        table = pack_lights(lights)
        other = shade_op.ShadeInputs(pinp.pos, pinp.nrm, pinp.mat, None, pinp.pos if table.has_vertex_sh else None,
                                     CAM, table, pinp.lt_i, pinp.lt_f, "cook_torrance", True, np.float32,
                                     blocks=pinp.blocks)
        assert not shade_op.lanes_supported(device, other)
        with pytest.raises(ValueError, match="lanes_cover is False"):
            shade_op.forward_packed(device, other, lanes=True)
    bp = shade_op.ShadeInputs(**{**pinp.__dict__, "brdf": "blinn_phong"})
    assert not shade_op.lanes_supported(device, bp)
    unpacked = shade_op.ShadeInputs(**{**pinp.__dict__, "blocks": None})
    assert not shade_op.lanes_supported(device, unpacked)
    # the shadow casters' columns and then environment-occlusion ones (VIS wider than the casters)
    occ = shade_op.ShadeInputs(**{**pinp.__dict__, "blocks": {**pinp.blocks, "VIS": (pinp.blocks["VIS"][0],
                                                                                      pinp.table.num_shadowed + 3)}})
    assert occ.env_occ == 3 and not shade_op.lanes_cover(occ)
    empty = shade_op.ShadeInputs(**{**pinp.__dict__, "table": pack_lights([])})
    assert not shade_op.lanes_cover(empty)

    class Gpu:
        is_cpu = False

    assert not shade_op.lanes_supported(Gpu(), pinp) and shade_op.lanes_cover(pinp)


def test_render_through_lanes_matches_shade_cl(device64, rng, monkeypatch):
    """A whole render (soup, point + directional + ambient lights: the lanes path) and its backward: the image and
    every scene parameter's gradient as with shade.cl (float64), and the gradients against central differences."""
    from tests.test_render import H, W, cam
    from triplet_cl.ops.raster import read_fragments
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.scene import Scene

    M = 10
    c = rng.uniform(-0.45, 0.45, (M, 1, 3))
    V = (c + rng.normal(0, 0.3, (M, 3, 3))).reshape(-1, 3)
    F = np.arange(3 * M).reshape(M, 3)
    lights = [PointLight([1.5, 2.0, 3.0], [6.0, 5.0, 4.0]), DirectionalLight([0.3, 1.0, 0.5], [0.6, 0.7, 0.8]),
              AmbientLight([0.1, 0.15, 0.2])]
    scene = Scene.from_arrays(V, F, material=rng.normal(0, 0.8, (len(V), 6)), alpha=rng.normal(0.5, 0.5, (len(V), 1)),
                              lights=lights, dtype=np.float64)
    settings = RenderSettings(K=6, sigma=0.8, real=np.float64, t_min=0.0, background=(0.3, 0.5, 0.9))
    w = rng.standard_normal((H, W, 4))
    calls = []
    real_launch = shade_op.launch

    def spy(dev, file, kernel, *a, **k):
        calls.append(kernel)
        return real_launch(dev, file, kernel, *a, **k)

    monkeypatch.setattr(shade_op, "launch", spy)
    monkeypatch.setattr(shade_op, "lanes_supported", lambda dev, inp: shade_op.lanes_cover(inp))  # a GPU too
    monkeypatch.setattr(shade_op, "_lanes_verdicts", lambda dev: _Checked())  # no first-use check: the lanes alone
    r = render(scene, cam(), settings, device64)
    scene.zero_grad()
    grads = {k: np.array(v) for k, v in r.backward(w[..., :3], w[..., 3]).items()}
    assert calls == ["shade_lanes_fwd", "shade_lanes_bwd"]
    image = r.rgba.data.copy()
    monkeypatch.setattr(shade_op, "lanes_supported", lambda dev, inp: False)
    r0 = render(scene, cam(), settings, device64)
    scene.zero_grad()
    grads0 = r0.backward(w[..., :3], w[..., 3])
    assert calls[2:] == ["shade_fwd", "shade_bwd"]
    np.testing.assert_allclose(image, r0.rgba.data, rtol=1e-11, atol=1e-13)
    for name, g in grads.items():
        np.testing.assert_allclose(g, grads0[name], rtol=1e-9, atol=1e-12 * max(np.abs(g).max(), 1e-30),
                                   err_msg=name)
    monkeypatch.undo()

    faces0 = read_fragments(r.info["frags"])["face"]

    def loss():
        rr = render(scene, cam(), settings, device64)
        return float((rr.rgba.data * w).sum()), np.array_equal(read_fragments(rr.info["frags"])["face"], faces0)

    for p in scene.params:
        idx, num, ok = sampled_fd(p, loss, rng, 20)
        assert ok.mean() > 0.9, p.name
        np.testing.assert_allclose(grads[p.name].reshape(-1)[idx][ok], num[ok], rtol=1e-5, atol=1e-7, err_msg=p.name)


@pytest.mark.parametrize("kind", ["mix", "mesh_stage"])
def test_lanes_rows_without_cotangent_give_zeros_whatever_they_hold(device64, rng, kind):
    """A row whose colour cotangent is zero (behind the compositing cut-off) gets exact zeros, as shade.cl's skip
    gives it, even when its attributes are not finite (a NaN roughness also indexes the environment's tables):
    nothing of it reaches the light gradients of its work-group."""
    lights = LIGHT_SETS[kind]()
    P = 40
    pinp, fa, blocks = packed_case(device64, rng, lights, P, np.float64, True)
    dead = np.zeros(P, bool)
    dead[[3, 17, 39]] = True
    fa[3, blocks["MAT"][0] + 3] = np.nan
    fa[17, blocks["POS"][0]] = np.inf
    fa[39, blocks["NRM"][0] + 1] = np.nan
    pinp.pos = pinp.nrm = pinp.mat = cla.to_device(device64.queue, fa)
    pinp.vis = pinp.pos if pinp.vis is not None else None
    pinp.vlight = pinp.pos if pinp.vlight is not None else None
    v_rgb = rng.standard_normal((P, 3))
    v_rgb[dead] = 0.0
    v_a = rng.standard_normal(P)
    got = run(device64, pinp, v_rgb, v_a, True)
    want = run(device64, pinp, v_rgb, v_a, False)
    cols = [c for c in written_columns(blocks) if c != blocks["ALPHA"][0]]
    assert not got[2][np.ix_(dead, cols)].any()
    assert np.isfinite(got[2][np.ix_(~dead, cols)]).all() and np.isfinite(got[3]).all()
    np.testing.assert_allclose(got[3], want[3], rtol=1e-10, atol=1e-12 * np.abs(want[3]).max())


def _any_device(verdicts):
    """``lanes_supported`` on any device (a GPU too: the tests' cross-check), with the verdicts of ``verdicts``."""
    return lambda dev, inp: shade_op.lanes_cover(inp) and verdicts.get(shade_op._lanes_key(inp)) is not False


class _Checked(dict):
    """A verdict table in which every variant has passed its check."""

    def get(self, key, default=None):
        return True


@pytest.mark.parametrize("real", [np.float32, np.float64])
def test_first_use_check_keeps_a_variant_that_matches_shade_cl(device64, rng, monkeypatch, real):
    # the default path's first forward and backward of a variant also run shade.cl and compare (LANES_CHECK_TOL); on
    # this device they agree: the variant is kept, and the values returned are the lanes kernel's own, bit for bit
    verdicts = {}
    monkeypatch.setattr(shade_op, "_lanes_verdicts", lambda dev: verdicts)
    monkeypatch.setattr(shade_op, "lanes_supported", _any_device(verdicts))
    pinp, _, _ = packed_case(device64, rng, LIGHT_SETS["point_ambient"](), 333, real, True)
    q = device64.queue
    v_rgb, v_a = rng.standard_normal((333, 3)).astype(real), rng.standard_normal(333).astype(real)
    rgb, alpha = shade_op.forward_packed(device64, pinp)
    assert verdicts == {shade_op._lanes_key(pinp): "fwd"}
    v_fa, v_par = shade_op.backward_packed(device64, pinp, cla.to_device(q, v_rgb), cla.to_device(q, v_a))
    assert verdicts == {shade_op._lanes_key(pinp): True}
    want = run(device64, pinp, v_rgb, v_a, True)
    assert np.array_equal(rgb.get(), want[0]) and np.array_equal(alpha.get(), want[1])
    assert np.array_equal(v_fa.get(), want[2]) and np.array_equal(np.asarray(v_par), want[3])


def test_first_use_check_drops_a_variant_that_disagrees(device64, rng, monkeypatch):
    # a build of shade_lanes.cl whose adjoint is off (Intel's CPU runtime: a point light then an ambient one, albedo
    # and metallic adjoints 1-30 % off) is caught on its first backward: a warning, shade.cl's values returned, and
    # shade.cl for that variant from then on
    verdicts = {}
    monkeypatch.setattr(shade_op, "_lanes_verdicts", lambda dev: verdicts)
    monkeypatch.setattr(shade_op, "lanes_supported", _any_device(verdicts))
    real_bwd = shade_op._launch_lanes_backward

    def off(dev, inp, v_rgb, v_alpha, v_fa, deferred):  # the material block's adjoint 2 % off
        out = real_bwd(dev, inp, v_rgb, v_alpha, v_fa, deferred)
        c0, n = inp.blocks["MAT"]
        h = v_fa.get()
        h[:, c0:c0 + n] *= 1.02
        v_fa.set(h)
        return out

    monkeypatch.setattr(shade_op, "_launch_lanes_backward", off)
    pinp, _, _ = packed_case(device64, rng, LIGHT_SETS["point_ambient"](), 96, np.float64, False)
    q = device64.queue
    v_rgb, v_a = rng.standard_normal((96, 3)), rng.standard_normal(96)
    shade_op.forward_packed(device64, pinp)
    with pytest.warns(RuntimeWarning, match="shade_lanes.cl's adjoint disagrees with shade.cl"):
        v_fa, v_par = shade_op.backward_packed(device64, pinp, cla.to_device(q, v_rgb), cla.to_device(q, v_a))
    assert verdicts == {shade_op._lanes_key(pinp): False}
    want = run(device64, pinp, v_rgb, v_a, False)  # shade.cl
    c0, n = pinp.blocks["MAT"]
    assert np.array_equal(v_fa.get()[:, c0:c0 + n], want[2][:, c0:c0 + n])
    assert not shade_op.lanes_supported(device64, pinp)
    calls = []
    real_launch = shade_op.launch
    monkeypatch.setattr(shade_op, "launch", lambda dev, f, k, *a, **kw: calls.append(k) or real_launch(dev, f, k, *a,
                                                                                                       **kw))
    shade_op.forward_packed(device64, pinp)
    shade_op.backward_packed(device64, pinp, cla.to_device(q, v_rgb), cla.to_device(q, v_a))
    assert calls == ["shade_fwd", "shade_bwd"]
