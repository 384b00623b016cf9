"""Shading op: forward per (BRDF x light type) against the numpy reference, adjoints against the
reference's complex-step derivative (float32) and central differences of the kernel (float64),
and physical sanity checks."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reference import shade as ref
from triplet_cl.lights import (
    AmbientLight,
    BounceLight,
    DirectionalLight,
    PointLight,
    SHEnvironmentLight,
    VertexSHLight,
    pack_lights,
)
from triplet_cl.ops.shade import num_material_channels, shade, shade_backward

CAM = np.array([0.2, -0.4, 3.0])
BRDFS = ["cook_torrance", "blinn_phong"]


def make_lights(kind, rng, env_degree=2):
    if kind == "ambient":
        return [AmbientLight([0.2, 0.5, 0.8])]
    if kind == "directional":
        return [DirectionalLight([0.3, -0.2, 1.0], [1.5, 1.0, 0.7])]
    if kind == "point":
        return [PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0], falloff=True)]
    if kind == "point_nofalloff":
        return [PointLight([-1.0, 0.5, 2.0], [0.9, 0.8, 1.1], falloff=False)]
    if kind == "env":
        c = rng.standard_normal((3, (env_degree + 1) ** 2)) * 0.3
        c[:, 0] += 2.0
        return [SHEnvironmentLight(c)]
    if kind == "vertex_sh":
        return [VertexSHLight()]
    if kind == "bounce":  # the traced interreflection: a per-fragment uniform radiance, lit as the ambient light
        return [BounceLight()]
    if kind == "mix":
        return [l for k in ("ambient", "directional", "point", "point_nofalloff", "env", "vertex_sh")
                for l in make_lights(k, rng, env_degree)]
    if kind == "mix_bounce":  # what the mesh stage shades with (the bounce last, after the learned lights)
        return [l for k in ("ambient", "directional", "point", "env", "bounce")
                for l in make_lights(k, rng, env_degree)]
    raise KeyError(kind)


def make_fragments(rng, brdf, P=96, rough_lo=0.2):
    pos = rng.uniform(-0.5, 0.5, (P, 3))
    nrm = rng.standard_normal((P, 3))
    nrm[:, 2] += 1.0  # mostly towards the camera and the lights
    nrm *= rng.uniform(0.5, 2.0, (P, 1))  # not unit
    mat = rng.uniform(0.05, 0.95, (P, num_material_channels(brdf)))
    if brdf == "cook_torrance":
        mat[:, 3] = rng.uniform(rough_lo, 1.0, P)
    else:
        mat[:, 6] = rng.uniform(0.5, 30.0, P)  # shininess
    face_id = rng.integers(0, 50, P).astype(np.int32)
    face_id[::11] = -1
    vlight = np.concatenate([rng.uniform(0.2, 1.5, (P, 3)), rng.standard_normal((P, 3)) + [0, 0, 1.5]], 1)
    return pos, nrm, mat, face_id, vlight


def ref_shade(frag, lights, brdf, **kw):
    pos, nrm, mat, face_id, vlight = frag
    t = pack_lights(lights)
    return ref.shade(pos, nrm, mat, face_id, CAM, t.ints, t.params, brdf, vlight, **kw)


@pytest.mark.parametrize("brdf", BRDFS)
@pytest.mark.parametrize("kind", ["ambient", "directional", "point", "point_nofalloff", "env", "vertex_sh", "bounce",
                                  "mix", "mix_bounce"])
def test_forward_float32(device, rng, brdf, kind):
    frag = make_fragments(rng, brdf)
    lights = make_lights(kind, rng)
    got = shade(*frag[:4], CAM, lights, brdf=brdf, vlight=frag[4], device=device)
    want = ref_shade(frag, lights, brdf)
    assert np.abs(want).max() > 0.05  # the configuration lights something
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5 * max(1.0, np.abs(want).max()))
    assert np.all(got[frag[3] < 0] == 0)


@pytest.mark.parametrize("brdf", BRDFS)
def test_forward_env_degree8_and_one_sided(device, rng, brdf):
    frag = make_fragments(rng, brdf)
    lights = make_lights("env", rng, env_degree=8) + [SHEnvironmentLight(rng.standard_normal((3, 25)) * 0.2, 3)]
    got = shade(*frag[:4], CAM, lights, brdf=brdf, vlight=frag[4], two_sided=False, device=device)
    want = ref_shade(frag, lights, brdf, two_sided=False)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-4 * np.abs(want).max())


@pytest.mark.parametrize("brdf", BRDFS)
@pytest.mark.parametrize("mix", ["mix", "mix_bounce"])
def test_vjp_float32_vs_reference(device, rng, brdf, mix):
    P = 64
    frag = make_fragments(rng, brdf, P=P)
    pos, nrm, mat, face_id, vlight = frag
    lights = make_lights(mix, rng)
    t = pack_lights(lights)
    v_rgb = rng.standard_normal((P, 3))
    got = shade_backward(pos, nrm, mat, face_id, CAM, lights, v_rgb, brdf=brdf, vlight=vlight, device=device)
    want = ref.vjp(pos, nrm, mat, face_id, CAM, t.ints, t.params, v_rgb, brdf, vlight)
    for name in ("v_pos", "v_nrm", "v_mat", "v_vlight"):
        w, g = want[name], getattr(got, name)
        np.testing.assert_allclose(g, w, rtol=2e-3, atol=2e-4 * np.abs(w).max(), err_msg=name)
    w = want["v_params"]
    np.testing.assert_allclose(got.v_light_params, w, rtol=2e-3, atol=2e-4 * np.abs(w).max())
    env = 4 if mix == "mix" else 3
    assert set(got.v_lights[1]) == {"direction", "intensity"} and got.v_lights[env]["coeffs"].shape == (3, 9)
    if mix == "mix_bounce":  # the bounce's radiance: the only gradient it has (no parameters)
        assert got.v_lights[4] == {} and np.abs(got.v_vlight[:, :3]).max() > 0 and not got.v_vlight[:, 3:].any()


@pytest.mark.parametrize("brdf", BRDFS)
@pytest.mark.parametrize("mix", ["mix", "mix_bounce"])
def test_zero_cotangent_rows_are_skipped_exactly(device, rng, brdf, mix):
    """``shade_bwd`` skips a fragment whose colour cotangent is zero (behind compositing's cut-off, where
    ``composite_bwd`` writes 0): its adjoints are exactly 0, and every other row and the light gradients are the
    reference's with those rows' cotangent 0 (a third of the rows here, spread over the work-groups)."""
    P = 150
    pos, nrm, mat, face_id, vlight = make_fragments(rng, brdf, P=P)
    face_id = np.arange(P, dtype=np.int32)  # every row a fragment: only the cotangent decides
    lights = make_lights(mix, rng)
    t = pack_lights(lights)
    v_rgb = rng.standard_normal((P, 3))
    dead = rng.uniform(size=P) < 0.33
    v_rgb[dead] = 0.0
    got = shade_backward(pos, nrm, mat, face_id, CAM, lights, v_rgb, brdf=brdf, vlight=vlight, device=device)
    want = ref.vjp(pos, nrm, mat, face_id, CAM, t.ints, t.params, v_rgb, brdf, vlight)
    for name in ("v_pos", "v_nrm", "v_mat", "v_vlight"):
        w, g = want[name], getattr(got, name)
        assert not g[dead].any(), name
        np.testing.assert_allclose(g, w, rtol=2e-3, atol=2e-4 * np.abs(w).max(), err_msg=name)
    w = want["v_params"]
    np.testing.assert_allclose(got.v_light_params, w, rtol=2e-3, atol=2e-4 * np.abs(w).max())


@pytest.mark.parametrize("degree,kc", [(4, None), (8, None), (8, 8)])
def test_vjp_env_higher_degrees_vs_reference(device, rng, degree, kc, monkeypatch):
    """The SH environment's coefficient sums of ``shade_bwd`` go through local memory in chunks of 32 coefficients
    per channel (degree 8: three chunks, the last partial; ``kc`` 8: the smaller chunks of a device with little
    local memory, eleven); over several work-groups and a partial last one, every gradient against the numpy
    reference, beside a point light and with a second environment of another degree."""
    from triplet_cl.ops import shade as shade_op

    if kc is not None:
        monkeypatch.setattr(shade_op, "env_chunk", lambda inp, local_mem, itemsize: kc)
    P = 150
    frag = make_fragments(rng, "cook_torrance", P=P)
    pos, nrm, mat, face_id, vlight = frag
    lights = make_lights("point", rng) + make_lights("env", rng, env_degree=degree) + [
        SHEnvironmentLight(rng.standard_normal((3, 16)) * 0.2, 3)]
    t = pack_lights(lights)
    v_rgb = rng.standard_normal((P, 3))
    got = shade_backward(pos, nrm, mat, face_id, CAM, lights, v_rgb, brdf="cook_torrance", vlight=vlight,
                         device=device)
    want = ref.vjp(pos, nrm, mat, face_id, CAM, t.ints, t.params, v_rgb, "cook_torrance", vlight)
    for name in ("v_pos", "v_nrm", "v_mat"):
        w, g = want[name], getattr(got, name)
        np.testing.assert_allclose(g, w, rtol=2e-3, atol=2e-4 * np.abs(w).max(), err_msg=name)
    w = want["v_params"]
    np.testing.assert_allclose(got.v_light_params, w, rtol=2e-3, atol=2e-4 * np.abs(w).max())
    assert got.v_lights[1]["coeffs"].shape == (3, (degree + 1) ** 2) and np.abs(got.v_lights[1]["coeffs"]).min() > 0


def test_env_chunk_fits_the_device_local_memory():
    """``env_chunk``: 32 coefficients a chunk (fewer for a lower degree), halved while the scratch does not fit."""
    from types import SimpleNamespace

    from triplet_cl.ops.shade import LOCAL_SIZE, env_chunk, scratch_width

    def inp(deg):
        return SimpleNamespace(table=SimpleNamespace(env_degree=deg))

    assert [env_chunk(inp(d), 1 << 20, 8) for d in (-1, 2, 4, 8)] == [9, 9, 25, 32]
    assert env_chunk(inp(8), 32 * 1024, 8) == 16 and env_chunk(inp(8), 32 * 1024, 4) == 32
    assert LOCAL_SIZE * scratch_width(16) * 8 <= 32 * 1024 < LOCAL_SIZE * scratch_width(32) * 8


def test_vjp_env_degree8_float64_central_differences(device64, rng):
    """Degree 8's coefficient gradients (the three local-memory chunks) against float64 central differences."""
    P, h = 70, 1e-6
    pos, nrm, mat, face_id, vlight = make_fragments(rng, "cook_torrance", P=P)
    lights = make_lights("env", rng, env_degree=8)
    v_rgb = rng.standard_normal((P, 3))
    kw = {"brdf": "cook_torrance", "device": device64, "real": np.float64, "vlight": vlight}
    got = shade_backward(pos, nrm, mat, face_id, CAM, lights, v_rgb, **kw).v_lights[0]["coeffs"]
    fd = _fd_entries(lambda c: np.sum(v_rgb * shade(pos, nrm, mat, face_id, CAM, [SHEnvironmentLight(c, 8)], **kw)),
                     lights[0].coeffs, h)
    np.testing.assert_allclose(got, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def _fd_entries(f, base, h):
    """Central differences of the scalar ``f(array)`` for each entry of ``base``."""
    fd = np.zeros(base.shape)
    for idx in np.ndindex(base.shape):
        vals = []
        for s in (1, -1):
            arr = base.copy()
            arr[idx] += s * h
            vals.append(f(arr))
        fd[idx] = (vals[0] - vals[1]) / (2 * h)
    return fd


def _fd_columns(f, x, h):
    """Central differences of the per-fragment map ``f`` for each column of ``x`` (all rows at once)."""
    cols = []
    for j in range(x.shape[1]):
        xp, xm = x.copy(), x.copy()
        xp[:, j] += h
        xm[:, j] -= h
        cols.append((f(xp) - f(xm)) / (2 * h))
    return cols


@pytest.mark.parametrize("brdf", BRDFS)
@pytest.mark.parametrize("mix", ["mix", "mix_bounce"])
def test_vjp_float64_finite_differences(device64, rng, brdf, mix):
    """Every parameter family: positions, normals, each material channel, vertex-SH light, and each
    light parameter (ambient, directional, point position/intensity with and without falloff, SH env
    coefficients)."""
    P, h = 40, 1e-6
    frag = make_fragments(rng, brdf, P=P)
    pos, nrm, mat, face_id, vlight = frag
    lights = make_lights(mix, rng)
    v_rgb = rng.standard_normal((P, 3))
    kw = {"brdf": brdf, "device": device64, "real": np.float64}
    got = shade_backward(pos, nrm, mat, face_id, CAM, lights, v_rgb, vlight=vlight, **kw)

    def run(pos=pos, nrm=nrm, mat=mat, vlight=vlight, lights=lights):
        return shade(pos, nrm, mat, face_id, CAM, lights, vlight=vlight, **kw)

    for name, x, g in (("pos", pos, got.v_pos), ("nrm", nrm, got.v_nrm), ("mat", mat, got.v_mat),
                       ("vlight", vlight, got.v_vlight)):
        cols = _fd_columns(lambda y, name=name: run(**{name: y}), x, h)
        fd = np.stack([np.sum(v_rgb * c, axis=1) for c in cols], 1)
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max(), err_msg=name)

    for i, light in enumerate(lights):
        for pname, grad in got.v_lights[i].items():
            def loss(arr, i=i, light=light, pname=pname):
                mod = [type(light)(**{**light.__dict__, pname: arr}) if k == i else l for k, l in enumerate(lights)]
                return np.sum(v_rgb * run(lights=mod))

            fd = _fd_entries(loss, getattr(light, pname), h)
            np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * max(np.abs(fd).max(), 1e-3),
                                       err_msg=f"light {i} {pname}")


@pytest.mark.parametrize("kind", ["point", "env"])
def test_vjp_float64_finite_differences_in_the_highlight(device64, rng, kind):
    """Issue 18 (roughness / metallic recovery): the specular lobe's material gradient where it matters, at and
    near the highlight (the normal within ~0.1 rad of the half vector, a glossy roughness 0.15-0.5, metallic over
    [0, 1]); the random directions of the check above rarely fall there."""
    P, h = 48, 1e-6
    pos, _, mat, face_id, vlight = make_fragments(rng, "cook_torrance", P=P)
    face_id[:] = np.arange(P) % 50
    light = make_lights(kind, rng)[0] if kind == "env" else PointLight([0.8, 1.2, 2.0], [4.0, 3.0, 5.0])
    if kind == "env":
        light = SHEnvironmentLight(light.coeffs, 2)
        nrm = CAM - pos  # the glossy env lobe: its roughness gradient everywhere, strongest at grazing
        nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True) + rng.normal(0, 0.6, (P, 3))
    else:
        to_l = light.position - pos
        to_c = CAM - pos
        nrm = to_l / np.linalg.norm(to_l, axis=1, keepdims=True) + to_c / np.linalg.norm(to_c, axis=1, keepdims=True)
        nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True) + rng.normal(0, 0.05, (P, 3))
    mat[:, 3] = rng.uniform(0.15, 0.5, P)
    mat[:, 4] = rng.uniform(0.0, 1.0, P)
    v_rgb = rng.standard_normal((P, 3))
    kw = {"brdf": "cook_torrance", "device": device64, "real": np.float64}
    got = shade_backward(pos, nrm, mat, face_id, CAM, [light], v_rgb, vlight=vlight, **kw)
    out = shade(pos, nrm, mat, face_id, CAM, [light], vlight=vlight, **kw)
    if kind == "point":
        assert out.max() > 1.0  # the peak is in the set
    cols = _fd_columns(lambda y: shade(pos, nrm, y, face_id, CAM, [light], vlight=vlight, **kw), mat, h)
    fd = np.stack([np.sum(v_rgb * c, axis=1) for c in cols], 1)
    np.testing.assert_allclose(got.v_mat, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    assert np.abs(fd[:, 3]).max() > 0.02 and np.abs(fd[:, 4]).max() > 0.01  # roughness / metallic do matter here


def test_inactive_sh_bands_get_no_gradient(device, rng):
    frag = make_fragments(rng, "cook_torrance", P=32)
    lights = [SHEnvironmentLight(rng.standard_normal((3, 16)), degree=1)]
    g = shade_backward(*frag[:4], CAM, lights, np.ones((32, 3)), device=device)
    c = g.v_lights[0]["coeffs"]
    assert np.all(c[:, 4:] == 0) and np.all(np.abs(c[:, :4]) > 0)


# ---- physical sanity ------------------------------------------------------------------------


def _sphere_dirs(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# Mitsuba 3.9.1's principled BSDF (defaults: specular 0.5, no sheen / clearcoat / transmission), its eval()
# (BRDF times cos) at the normal +z: (base colour, roughness, metallic, view polar angle, light polar angle, light
# azimuth from the view's, value), the view at azimuth 0, angles in degrees. The path tracer of every dataset here.
MITSUBA_PRINCIPLED = [
    ((0.8, 0.8, 0.8), 0.4, 0.0, 60, 60, 180, (0.659099, 0.659099, 0.659099)),  # the mirror direction
    ((0.05, 0.05, 0.05), 0.4, 0.0, 75, 30, 180, (0.0292893, 0.0292893, 0.0292893)),
    ((0.8, 0.8, 0.8), 0.9, 0.0, 75, 80, 0, (0.0869399, 0.0869399, 0.0869399)),  # retro-reflection when rough
    ((0.8, 0.8, 0.8), 0.9, 0.0, 0, 0, 0, (0.259499, 0.259499, 0.259499)),
    ((0.9, 0.6, 0.3), 0.3, 1.0, 60, 80, 180, (0.762423, 0.542637, 0.32285)),
    ((0.9, 0.6, 0.3), 0.6, 0.5, 30, 60, 90, (0.0995667, 0.0667828, 0.0339988)),
    ((0.3, 0.6, 0.9), 0.15, 0.2, 45, 40, 170, (0.132285, 0.235806, 0.339327)),
]


def _sph(theta, phi):
    t, p = np.radians(theta), np.radians(phi)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


@pytest.mark.parametrize("case", MITSUBA_PRINCIPLED)
def test_cook_torrance_is_mitsubas_principled_bsdf(device, case):
    """The direct term of a directional light of irradiance 1 is the path tracer's BSDF × cos (the datasets' and
    the relit references' renderer), to the 1e-6 guard in D's denominator (4e-4 relative at the peak of a
    roughness-0.4 lobe, where that denominator is 2e-3; 2e-3 beside the peak of a roughness-0.15 one, 0.45x at its
    very peak: kept on purpose, shade_brdf.h)."""
    base, r, m, tv, tl, ph, want = case
    V, L = _sph(tv, 0), _sph(tl, ph)
    mat = np.array([[*base, r, m, 1.0]])
    got = shade(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), mat, [0], 5.0 * V, [DirectionalLight(L, [1.0] * 3)],
                device=device)[0]
    np.testing.assert_allclose(got, want, rtol=3e-3)
    np.testing.assert_allclose(ref.ct_direct(np.array([[0.0, 0, 1]]), V[None], L[None], np.ones((1, 3)), mat)[0],
                               want, rtol=3e-3)


def test_white_furnace_cook_torrance(device, rng):
    """metallic 0, roughness 1, white environment: reflects the albedo plus the F0 specular (Fe = F0 at roughness 1,
    no (1 - F) on the diffuse, as the direct term and the path tracer's principled BSDF): albedo + 0.04."""
    P = 256
    nrm = _sphere_dirs(rng, P)
    pos = np.zeros((P, 3))
    for albedo in (1.0, 0.5):
        mat = np.tile([albedo, albedo, albedo, 1.0, 0.0, 1.0], (P, 1))
        rgb = shade(pos, nrm, mat, np.zeros(P, np.int32), CAM, [SHEnvironmentLight.constant(1.0, 2)], device=device)
        np.testing.assert_allclose(rgb, albedo + 0.04, rtol=1e-5)


@pytest.mark.parametrize("rough", [0.45, 0.7, 1.0])
def test_metal_in_a_white_furnace_reflects_its_lobes_integral(device, rough):
    """A metal under a constant white SH environment reflects what its direct term
    integrates to over every light direction, ∫ f(l, v) (n·l) dl (the split sum is exact for a constant
    environment): the environment's weight F0 A + B is the lobe's own directional albedo (ggx_tables), at every
    angle of view. Independent of the tables: the reference's direct term summed over a fine grid of directions."""
    f0 = np.array([0.95, 0.64, 0.54])  # copper-like
    th = (np.arange(1200) + 0.5) / 1200 * (np.pi / 2)
    ph = (np.arange(600) + 0.5) / 600 * (2 * np.pi)
    T, Ph = np.meshgrid(th, ph, indexing="ij")
    L = np.stack([np.sin(T) * np.cos(Ph), np.sin(T) * np.sin(Ph), np.cos(T)], -1).reshape(-1, 3)
    dw = (np.sin(T) * (np.pi / 2 / 1200) * (2 * np.pi / 600)).reshape(-1, 1)
    n = np.array([0.0, 0.0, 1.0])
    views = [0.95, 0.6, 0.3, 0.12]
    mat = np.tile([*f0, rough, 1.0, 1.0], (len(views), 1))
    want = []
    for nv in views:
        V = np.array([np.sqrt(1 - nv * nv), 0.0, nv])
        m1 = np.tile(mat[0], (len(L), 1))
        f = ref.ct_direct(np.tile(n, (len(L), 1)), np.tile(V, (len(L), 1)), L, np.ones((len(L), 3)), m1)
        want.append((f * dw).sum(axis=0))
    # fragments at the origin seen from CAM: normals tilted so that n·v is each of views
    cam_dir = CAM / np.linalg.norm(CAM)
    side = np.cross(cam_dir, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    nrm = np.array([nv * cam_dir + np.sqrt(1 - nv * nv) * side for nv in views])
    pos = np.zeros((len(views), 3))
    rgb = shade(pos, nrm, mat, np.zeros(len(views), np.int32), CAM, [SHEnvironmentLight.constant(1.0, 2)],
                device=device)
    np.testing.assert_allclose(rgb, np.array(want), rtol=0.012, atol=2e-3)


def test_point_light_inverse_square(device, rng):
    P = 16
    pos = rng.uniform(-0.1, 0.1, (P, 3))
    nrm = np.tile([0.0, 0.0, 1.0], (P, 1))
    mat = np.tile([0.7, 0.6, 0.5, 0.8, 0.1, 1.0], (P, 1))
    d0 = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    out = []
    for dist in (1.0, 2.0, 4.0):
        # keep the light direction of fragment 0 fixed by moving the light along the ray from it
        light = PointLight(pos[0] + dist * d0, [2.0, 2.0, 2.0], falloff=True)
        out.append(shade(pos[:1], nrm[:1], mat[:1], [0], CAM, [light], device=device)[0])
    np.testing.assert_allclose(out[0] / out[1], 4.0, rtol=1e-5)
    np.testing.assert_allclose(out[0] / out[2], 16.0, rtol=1e-5)
    no = [shade(pos[:1], nrm[:1], mat[:1], [0], CAM, [PointLight(pos[0] + d * d0, [2.0] * 3, falloff=False)],
                device=device)[0] for d in (1.0, 4.0)]
    np.testing.assert_allclose(no[0], no[1], rtol=1e-5)


@pytest.mark.parametrize("degree", [2, 8])
def test_sh_irradiance_of_constant_environment_is_constant(device, rng, degree):
    P = 200
    mat = np.tile([0.3, 0.6, 0.9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], (P, 1))  # Blinn-Phong, ks = 0
    rgb = shade(rng.uniform(-1, 1, (P, 3)), _sphere_dirs(rng, P), mat, np.zeros(P, np.int32), CAM,
                [SHEnvironmentLight.constant([1.0, 2.0, 0.5], degree)], brdf="blinn_phong", device=device)
    np.testing.assert_allclose(rgb, np.tile([0.3, 1.2, 0.45], (P, 1)), rtol=1e-5)


@pytest.mark.parametrize("brdf", BRDFS)
def test_direct_and_environment_diffuse_agree(device, rng, brdf):
    """A purely diffuse material (Blinn-Phong ks = 0; Cook-Torrance metallic 0, roughness 1, seen and lit along
    the normal) reflects kd/π·E under a light of irradiance E and kd·c under a constant environment of radiance c:
    the same albedo relights the same under a Mitsuba point light and an environment (Blinn-Phong's diffuse was
    kd·N·L, π times the environment term's)."""
    P = 50
    nrm = _sphere_dirs(rng, P)
    pos = np.zeros((P, 3))
    kd = rng.uniform(0.1, 0.9, (P, 3))
    if brdf == "blinn_phong":
        mat = np.concatenate([kd, np.zeros((P, 3)), np.full((P, 1), 10.0), np.zeros((P, 3))], 1)
    else:
        mat = np.concatenate([kd, np.ones((P, 1)), np.zeros((P, 1)), np.ones((P, 1))], 1)
    direct, env = [], []
    for p in range(P):  # the light along the normal, 2 units away: irradiance I / 4 = pi
        n = nrm[p]
        cam = 3.0 * n
        d = shade(pos[p:p + 1], nrm[p:p + 1], mat[p:p + 1], [0], cam, [PointLight(2.0 * n, [4 * np.pi] * 3)],
                  brdf=brdf, device=device)
        e = shade(pos[p:p + 1], nrm[p:p + 1], mat[p:p + 1], [0], cam, [SHEnvironmentLight.constant([1.0] * 3, 2)],
                  brdf=brdf, device=device)
        direct.append(d[0])
        env.append(e[0])
    direct, env = np.array(direct), np.array(env)
    if brdf == "blinn_phong":
        np.testing.assert_allclose(direct, kd, rtol=1e-5)
        np.testing.assert_allclose(env, kd, rtol=1e-5)
    else:  # Disney's diffuse is Lambert's at normal incidence; the direct term adds the lobe's peak (~0.01), the
        # environment term Fe = 0.04: close
        np.testing.assert_allclose(direct, env, rtol=0.1, atol=0.03)


@pytest.mark.parametrize("brdf", BRDFS)
def test_degenerate_configurations_stay_finite(device, brdf):
    C = num_material_channels(brdf)
    n = np.array([0.0, 0.0, 1.0])
    cases = [  # (pos, nrm, roughness/shininess)
        ([0, 0, 0], n, 0.0),  # zero roughness / shininess
        ([0, 0, 0], [1.0, 0, 0], 0.5),  # grazing: N orthogonal to the light and nearly to V
        ([0, 0, 0], [0.0, 0, 0], 0.5),  # zero normal
        (CAM, n, 0.5),  # fragment at the camera centre (V = 0)
        ([1.0, 1.0, 1.0], n, 0.0),  # fragment at the point light
        ([0, 0, 0], -n, 1e-4),  # normal facing away
    ]
    pos = np.array([c[0] for c in cases], float)
    nrm = np.array([c[1] for c in cases], float)
    mat = np.full((len(cases), C), 0.5)
    mat[:, 3 if brdf == "cook_torrance" else 6] = [c[2] for c in cases]
    vlight = np.tile([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], (len(cases), 1))  # zero direction
    lights = [DirectionalLight([1.0, 0.0, 0.0], [1.0] * 3), DirectionalLight([0.0, 0.0, -3.0], [1.0] * 3),
              PointLight([1.0, 1.0, 1.0], [1.0] * 3), SHEnvironmentLight.constant(0.5, 2), AmbientLight(),
              VertexSHLight()]
    for two_sided in (True, False):
        kw = {"brdf": brdf, "vlight": vlight, "two_sided": two_sided, "device": device}
        rgb = shade(pos, nrm, mat, np.zeros(len(cases), np.int32), CAM, lights, **kw)
        g = shade_backward(pos, nrm, mat, np.zeros(len(cases), np.int32), CAM, lights, np.ones_like(rgb), **kw)
        assert np.isfinite(rgb).all()
        for a in (g.v_pos, g.v_nrm, g.v_mat, g.v_vlight, g.v_light_params):
            assert np.isfinite(a).all()


def test_empty_slots_and_determinism(device, rng):
    frag = make_fragments(rng, "cook_torrance", P=200)
    lights = make_lights("mix", rng)
    v = rng.standard_normal((200, 3))
    g1 = shade_backward(*frag[:4], CAM, lights, v, vlight=frag[4], device=device)
    g2 = shade_backward(*frag[:4], CAM, lights, v, vlight=frag[4], device=device)
    empty = frag[3] < 0
    for a, b in ((g1.v_pos, g2.v_pos), (g1.v_mat, g2.v_mat), (g1.v_light_params, g2.v_light_params)):
        assert np.array_equal(a, b)
    assert np.all(g1.v_pos[empty] == 0) and np.all(g1.v_mat[empty] == 0) and np.all(g1.v_vlight[empty] == 0)


def test_validation(device):
    P = 4
    pos, nrm, mat = np.zeros((P, 3)), np.ones((P, 3)), np.full((P, 6), 0.5)
    fid = np.zeros(P, np.int32)
    with pytest.raises(ValueError, match=r"pos must have shape \[\*, 3\], got \[5, 2\]"):
        shade(np.zeros((5, 2)), nrm, mat, fid, CAM, [], device=device)
    with pytest.raises(ValueError, match=r"mat must have shape \[4, 10\]"):
        shade(pos, nrm, mat, fid, CAM, [], brdf="blinn_phong", device=device)
    with pytest.raises(ValueError, match="brdf must be one of"):
        shade(pos, nrm, mat, fid, CAM, [], brdf="phong", device=device)
    with pytest.raises(ValueError, match="face_id must be >= -1"):
        shade(pos, nrm, mat, [0, -2, 0, 0], CAM, [], device=device)
    with pytest.raises(ValueError, match="vlight"):
        shade(pos, nrm, mat, fid, CAM, [VertexSHLight()], device=device)
    with pytest.raises(ValueError, match="nrm must be finite"):
        shade(pos, np.full((P, 3), np.inf), mat, fid, CAM, [], device=device)
    with pytest.raises(ValueError, match="SHEnvironmentLight.degree"):
        SHEnvironmentLight(np.zeros((3, 9)), degree=3)
    with pytest.raises(ValueError, match=r"DirectionalLight.direction must have shape \[3\]"):
        DirectionalLight([0, 1])
    with pytest.raises(ValueError, match=r"v_rgb must have shape \[4, 3\]"):
        shade_backward(pos, nrm, mat, fid, CAM, [], np.zeros((3, 3)), device=device)
    assert shade(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 6)), np.zeros(0, np.int32), CAM, [],
                 device=device).shape == (0, 3)


@pytest.mark.parametrize("brdf", BRDFS)
@pytest.mark.parametrize("kind", ["point", "mix"])
@pytest.mark.parametrize("with_vis", [False, True])
def test_packed_blocks_match_separate_arrays(device, rng, brdf, kind, with_vis, bitwise):
    """ShadeFragments' path: the inputs as column blocks of one packed [P, C] array (read in place, the adjoint
    written into the blocks, the alpha block copied out and its adjoint copied in) give the bits of the separate
    arrays (forward, every adjoint block, the light gradients), vertex-SH light and cached visibility included; rows
    with a zero colour cotangent get zero adjoints there too (their alpha's passes). Bits on PoCL; elsewhere the two
    builds may round differently (NVIDIA's OpenCL: a few ulp), so within 1e-5 there."""
    import pyopencl.array as cla

    def same(a, b):
        if bitwise:
            return np.array_equal(a, b)
        return np.allclose(a, b, rtol=1e-5, atol=1e-6 * max(np.abs(b).max(initial=0.0), 1e-30))

    from triplet_cl.ops import shade as shade_op

    pos, nrm, mat, _, vlight = make_fragments(rng, brdf)
    P = len(pos)
    lights = make_lights(kind, rng)
    table = pack_lights(lights)
    nv = table.num_shadowed if with_vis else 0
    vl = vlight if table.has_vertex_sh else None
    vis = rng.uniform(0, 1, (P, nv))
    alpha = rng.uniform(0, 1, (P, 1))
    named = [("POS", pos), ("NRM", nrm), ("MAT", mat), ("ALPHA", alpha)] + ([("VL", vl)] if vl is not None else []) \
        + ([("VIS", vis)] if nv else [])
    offs = np.cumsum([0] + [a.shape[1] for _, a in named])
    blocks = {n: (int(offs[i]), a.shape[1]) for i, (n, a) in enumerate(named)}
    fa = np.concatenate([a for _, a in named], 1).astype(np.float32)
    _, inp = shade_op.prepare(pos, nrm, mat, np.zeros(P, np.int32), CAM, lights, brdf=brdf, vlight=vl,
                              device=device, vis=vis if nv else None)
    q = device.queue
    pinp = shade_op.packed_inputs(device, cla.to_device(q, fa), blocks, CAM, table, inp.lt_i, inp.lt_f, brdf, True,
                                  np.float32)
    rgb, a = shade_op.forward_packed(device, pinp, lanes=False)  # shade.cl (shade_lanes.cl: test_shade_lanes.py)
    assert same(rgb.get(), shade_op.forward(device, inp).get())
    assert np.array_equal(a.get(), fa[:, blocks["ALPHA"][0]])
    v_rgb_h = rng.standard_normal((P, 3)).astype(np.float32)
    dead = rng.uniform(size=P) < 0.25  # rows behind the cut-off: skipped, every adjoint but alpha's exactly 0
    v_rgb_h[dead] = 0.0
    v_rgb = cla.to_device(q, v_rgb_h)
    v_a = cla.to_device(q, rng.standard_normal(P).astype(np.float32))
    v_fa, v_par = shade_op.backward_packed(device, pinp, v_rgb, v_a, lanes=False)
    g = shade_op.backward(device, inp, v_rgb)
    v_fa = v_fa.get()
    others = [c for c in range(v_fa.shape[1]) if c != blocks["ALPHA"][0]]
    assert not v_fa[np.ix_(dead, others)].any() and np.abs(v_fa[np.ix_(~dead, others)]).max() > 0
    for n, arr in (("POS", g.v_pos), ("NRM", g.v_nrm), ("MAT", g.v_mat), ("VL", g.v_vlight), ("VIS", g.v_vis)):
        if n in blocks:
            c0, w = blocks[n]
            assert same(v_fa[:, c0:c0 + w], arr.get()), n
    assert np.array_equal(v_fa[:, blocks["ALPHA"][0]], v_a.get())
    assert same(v_par, g.v_light_params) and np.abs(v_par).max() > 0


# ---- the environment's occlusion (shade.cl ENV_OCC: vis columns after the shadow casters) ----------------------


def _occ_case(rng, brdf, P=48, real=np.float64, n_occ=8):
    """Fragments under a point and a directional light (two shadow columns), an SH environment of degree 2 and one of
    degree 1 (sharing the occlusion's first 3 columns), ``vis [P, 2 + n_occ]``: transmittance then U_1 .. U_n_occ
    (8: the degree-2 bands; 3: fewer, bands 2 unoccluded; 15: more, those past the compiled degree unused)."""
    frag = make_fragments(rng, brdf, P=P)
    lights = make_lights("point", rng) + make_lights("directional", rng) + make_lights("env", rng, 2) + \
        make_lights("env", rng, 1)
    vis = np.concatenate([np.ones((P, 2)), rng.normal(0.0, 0.4, (P, n_occ))], 1)
    return frag, lights, vis


def normalize_rows(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _occ_shade(device, frag, lights, vis, brdf, real):
    from triplet_cl.ops import shade as shade_op

    pos, nrm, mat, face_id, _ = frag
    return shade_op.prepare(pos, nrm, mat, face_id, CAM, lights, brdf=brdf, device=device, real=real, vis=vis)


@pytest.mark.parametrize("brdf,n_occ", [("cook_torrance", 8), ("blinn_phong", 8), ("cook_torrance", 3),
                                        ("cook_torrance", 15)])
def test_environment_occlusion_forward_and_vjp_vs_reference(device, rng, brdf, n_occ):
    """The occluded irradiance E = Σ c_k (A_l Y_k(N) − U_k) against the reference, float32, and its adjoint
    (every input, the occlusion columns' v_U = −gE·c summed over both environment lights, the coefficients) against
    the reference's complex steps; U = 0 renders exactly as without the columns. Back faces (two-sided) take no
    occlusion (it was traced over the front hemisphere); fewer columns than bands leave the rest unoccluded, more
    leave the extra ones unused (their adjoint 0)."""
    import pyopencl.array as cla

    from triplet_cl.ops import shade as shade_op

    frag, lights, vis = _occ_case(rng, brdf, n_occ=n_occ)
    pos, nrm, mat, face_id, _ = frag
    t = pack_lights(lights)
    dev, inp = _occ_shade(device, frag, lights, vis, brdf, np.float32)
    got = shade_op.forward(dev, inp).get()
    want = ref.shade(pos, nrm, mat, face_id, CAM, t.ints, t.params, brdf, occ=vis[:, 2:])
    plain = ref.shade(pos, nrm, mat, face_id, CAM, t.ints, t.params, brdf)
    assert np.abs(want - plain).max() > 0.05  # the occlusion acts (the point light reaches ~8)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5 * np.abs(want).max())
    zero = vis.copy()
    zero[:, 2:] = 0.0
    dev, inp0 = _occ_shade(device, frag, lights, zero, brdf, np.float32)
    np.testing.assert_array_equal(shade_op.forward(dev, inp0).get(),
                                  shade(pos, nrm, mat, face_id, CAM, lights, brdf=brdf, device=device))
    v_rgb = rng.standard_normal(got.shape)
    out = shade_op.backward(dev, inp, cla.to_device(dev.queue, v_rgb.astype(np.float32)))
    w = ref.vjp(pos, nrm, mat, face_id, CAM, t.ints, t.params, v_rgb, brdf, occ=vis[:, 2:])
    for name, g in (("v_pos", out.v_pos.get()), ("v_nrm", out.v_nrm.get()), ("v_mat", out.v_mat.get()),
                    ("v_occ", out.v_vis.get()[:, 2:]), ("v_params", out.v_light_params)):
        np.testing.assert_allclose(g, w[name], rtol=2e-3, atol=2e-4 * np.abs(w[name]).max(), err_msg=name)
    assert np.abs(w["v_occ"][:, :3]).max() > 0
    if n_occ >= 8:
        assert np.abs(w["v_occ"][:, 3:8]).max() > 0 and not w["v_occ"][:, 8:].any()
    back = (np.sum(normalize_rows(frag[1]) * (CAM - frag[0]), axis=1) < 0) & (frag[3] >= 0)
    assert back.any() and not w["v_occ"][back].any() and not out.v_vis.get()[back, 2:].any()


def test_environment_occlusion_float64_central_differences(device64, rng):
    """float64 central differences of the kernel itself: the occlusion columns and the coefficients of both
    environments (the light gradients' reduction through the occluded weights)."""
    import pyopencl.array as cla

    from triplet_cl.ops import shade as shade_op

    frag, lights, vis = _occ_case(rng, "cook_torrance", P=40)
    v_rgb = rng.standard_normal((40, 3))

    def f(vis=vis, lights=lights):
        dev, inp = _occ_shade(device64, frag, lights, vis, "cook_torrance", np.float64)
        return float((shade_op.forward(dev, inp).get() * v_rgb).sum())

    dev, inp = _occ_shade(device64, frag, lights, vis, "cook_torrance", np.float64)
    out = shade_op.backward(dev, inp, cla.to_device(dev.queue, v_rgb))
    g_vis = out.v_vis.get()
    h = 1e-6
    for i in rng.choice(40 * 8, 16, replace=False):
        r, c = divmod(int(i), 8)
        xp, xm = vis.copy(), vis.copy()
        xp[r, 2 + c] += h
        xm[r, 2 + c] -= h
        assert g_vis[r, 2 + c] == pytest.approx((f(xp) - f(xm)) / (2 * h), rel=1e-6, abs=1e-9), (r, c)
    from triplet_cl.lights import unpack_gradients

    grads = unpack_gradients(lights, out.v_light_params)
    for li in (2, 3):
        base = lights[li].coeffs
        for idx in np.ndindex(3, min(base.shape[1], 9)):
            vals = []
            for s in (1, -1):
                arr = base.copy()
                arr[idx] += s * h
                mod = list(lights)
                mod[li] = SHEnvironmentLight(arr, lights[li].degree)
                vals.append(f(lights=mod))
            assert grads[li]["coeffs"][idx] == pytest.approx((vals[0] - vals[1]) / (2 * h), rel=1e-6, abs=1e-8), \
                (li, idx)


def test_environment_occlusion_columns_are_validated(device, rng):
    """vis: the shadow columns, then 0 or (d + 1)² − 1 occlusion columns; anything else is refused by name."""
    frag, lights, vis = _occ_case(rng, "cook_torrance", P=8)
    for bad in (vis[:, :1], vis[:, :4], vis[:, :7], np.ones((8, 0))):
        with pytest.raises(ValueError, match="environment-occlusion"):
            _occ_shade(device, frag, lights, bad, "cook_torrance", np.float32)
    for ok in (vis[:, :2], vis[:, :5], vis):
        _occ_shade(device, frag, lights, ok, "cook_torrance", np.float32)
