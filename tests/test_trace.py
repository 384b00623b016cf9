"""Ray tracing (issue 7): BVH build/refit, primary rays vs the rasterizer, shadow transmittance and
the reflection bounce against numpy references, and their adjoints (float64 central differences
through whole renders, perturbations that change no discrete choice: fragments, shadow hits,
bounce hits)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reference import trace as ref
from triplet_cl.camera import Camera
from triplet_cl.lights import DirectionalLight, PointLight, pack_lights
from triplet_cl.ops import shade as shade_op
from triplet_cl.ops import trace as trace_op
from triplet_cl.ops.bvh import build_bvh, refit
from triplet_cl.ops.mesh import DeviceMesh
from triplet_cl.ops.raster import project, rasterize, read_fragments
from triplet_cl.render import RenderSettings, render

W, H = 23, 19


def soup(rng, M=60, spread=0.6, size=0.25):
    c = rng.uniform(-spread, spread, (M, 1, 3))
    V = (c + rng.normal(0, size, (M, 3, 3))).reshape(-1, 3)
    return V, np.arange(3 * M).reshape(M, 3)


def cam(w=W, h=H):
    return Camera.look_at([0.3, -0.2, 3.0], [0, 0, 0], [0, 1, 0], 45, w, h)


# ------------------------------------------------------------------------------------------------ BVH


def test_bvh_bounds_and_refit_equal_rebuild(device, rng):
    V0, F = soup(rng, M=37)  # not a multiple of the leaf size: uneven leaves
    mesh = DeviceMesh(device, F, len(V0))
    b = build_bvh(device, V0.astype(np.float32), mesh)
    assert b.num_leaves == 16 and b.depth == 4
    prim = b.prim.get()
    assert sorted(prim.tolist()) == list(range(37))
    np.testing.assert_allclose(b.nodes.get(), ref.bvh_bounds_ref(V0.astype(np.float32).astype(np.float64), F, prim,
                                                                 16), rtol=1e-6)
    V1 = V0 + rng.normal(0, 0.2, V0.shape)  # positions move, topology does not
    refit(device, b, V1.astype(np.float32))
    np.testing.assert_allclose(b.nodes.get(), ref.bvh_bounds_ref(V1.astype(np.float32).astype(np.float64), F, prim,
                                                                 16), rtol=1e-6)
    rebuilt = build_bvh(device, V1.astype(np.float32), mesh)
    # same scene bounds (up to the per-leaf padding of 1e-6 relative, which depends on the grouping)
    np.testing.assert_allclose(b.nodes.get()[0], rebuilt.nodes.get()[0], rtol=3e-6)
    # same hits through the refitted and the rebuilt tree
    c = cam()
    vs = project(device, V1.astype(np.float32), c)
    fa = read_fragments(trace_op.trace_primary(device, b, V1.astype(np.float32), vs, c, 8))
    fb = read_fragments(trace_op.trace_primary(device, rebuilt, V1.astype(np.float32), vs, c, 8))
    for k in ("face", "count", "bary", "depth"):
        np.testing.assert_array_equal(fa[k], fb[k])


def test_bvh_rejects_bad_input(device):
    mesh = DeviceMesh(device, np.arange(3).reshape(1, 3), 3)
    with pytest.raises(ValueError, match="leaf_size"):
        build_bvh(device, np.zeros((3, 3), np.float32), mesh, leaf_size=0)
    with pytest.raises(ValueError, match="V must"):
        build_bvh(device, np.zeros((4, 3), np.float32), mesh)
    b = build_bvh(device, np.eye(3, dtype=np.float32), mesh)
    with pytest.raises(ValueError, match=r"V must have shape \[3, 3\]"):
        refit(device, b, np.eye(3)[None])
    with pytest.raises(ValueError, match="renderer"):
        RenderSettings(renderer="pathtrace")
    with pytest.raises(ValueError, match="soft_edges='all' only"):
        RenderSettings(renderer="raytrace", soft_edges="silhouette")


# ------------------------------------------------------------------------------------------------ primary


@pytest.mark.parametrize("real", [np.float64, np.float32])
def test_primary_rays_match_raster_and_reference(device, device64, rng, real):
    dev = device64 if real == np.float64 else device
    V, F = soup(rng)
    c = cam()
    mesh = DeviceMesh(dev, F, len(V))
    Vr = V.astype(real)
    b = build_bvh(dev, Vr, mesh)
    vs = project(dev, Vr, c)
    tr = read_fragments(trace_op.trace_primary(dev, b, Vr, vs, c, 8))
    ra = read_fragments(rasterize(dev, vs, mesh, W, H, 8))
    assert tr["count"].sum() > 200
    # edge pixels (a ray within rounding of an edge) may differ: allow a handful in float32
    same = (tr["face"] == ra["face"]).all(-1)
    assert (~same).sum() <= (0 if real == np.float64 else 3)
    tol = 1e-9 if real == np.float64 else 2e-4
    np.testing.assert_allclose(tr["bary"][same], ra["bary"][same], atol=tol)
    np.testing.assert_allclose(tr["depth"][same], ra["depth"][same], rtol=tol)
    if real == np.float64:  # brute-force reference (all faces in front of the camera: no culling)
        r = ref.primary_ref(V, F, c, 8)
        np.testing.assert_array_equal(tr["face"], r["face"])
        np.testing.assert_allclose(tr["bary"], r["bary"], atol=1e-12)
        np.testing.assert_allclose(tr["depth"], r["depth"], rtol=1e-12)


# ------------------------------------------------------------------------------------------------ shadows


def _shadow(dev, V, F, alpha_v, pos, own, lights, eps, real=np.float64, early_out=False):
    mesh = DeviceMesh(dev, F, len(V))
    b = build_bvh(dev, V.astype(real), mesh)
    import pyopencl.array as cla

    q = dev.queue
    table = pack_lights(lights)
    st = trace_op.shadow_forward(dev, b, cla.to_device(q, V.astype(real)),
                                 cla.to_device(q, np.ascontiguousarray(alpha_v[:, None], real)), 0,
                                 cla.to_device(q, pos.astype(real)), cla.to_device(q, own.astype(np.int32)),
                                 cla.to_device(q, table.ints), cla.to_device(q, table.params.astype(real)), table, eps,
                                 early_out=early_out)
    return b, st


def test_shadow_early_out_stops_below_its_threshold(device64, rng):
    """``early_out``: a ray whose full transmittance is at least 1e-4 gets it exactly (and all its hits); one
    below gets a value in [full T, 1e-4) from fewer hits."""
    V, F = soup(rng, M=300)
    alpha_v = rng.uniform(0.6, 0.999, len(V))  # dense and nearly opaque: many rays fall below 1e-4
    Pn = 60
    pos = rng.uniform(-0.7, 0.7, (Pn, 3))
    own = rng.integers(0, len(F), Pn)
    lights = [PointLight([0.2, 1.9, 0.4], [1, 1, 1]), DirectionalLight([0.3, -1.0, 0.5], [1, 1, 1])]
    T, n = ref.transmittance_ref(V, F, alpha_v, pos, own, [("point", [0.2, 1.9, 0.4]), ("dir", [0.3, -1.0, 0.5])],
                                 1e-6)
    b, st = _shadow(device64, V, F, alpha_v, pos, own, lights, 1e-6, early_out=True)
    vis, hits = st.vis.get(), st.nhit.get().reshape(Pn, 2)
    deep = T < 1e-4
    assert 0.2 < deep.mean() < 0.9  # both kinds of rays
    np.testing.assert_allclose(vis[~deep], T[~deep], rtol=1e-12)
    np.testing.assert_array_equal(hits[~deep], n[~deep])
    assert (vis[deep] >= T[deep] * (1 - 1e-12)).all() and (vis[deep] < 1e-4).all()
    assert (hits[deep] <= n[deep]).all() and (hits[deep] < n[deep]).any()  # the walk did stop early


def test_shadow_early_out_adjoint(device64, rng):
    """The adjoint of the early-out transmittance (the hybrid renderer's): the backward walks the forward's hits
    and stops where it stopped. Rays that never fall below 1e-4 get the full walk's adjoint exactly; every
    occluder's alpha and position adjoint, and the shading points', match float64 central differences of the
    early-out forward (perturbations that move a ray's stop, a discrete change, skipped); occluders only the full
    walk reaches get no gradient."""
    V, F = soup(rng, M=300)
    alpha_v = rng.uniform(0.6, 0.999, len(V))  # dense and nearly opaque: many rays stop early
    Pn = 60
    pos = rng.uniform(-0.7, 0.7, (Pn, 3))
    own = rng.integers(0, len(F), Pn)
    lights = [PointLight([0.2, 1.9, 0.4], [1, 1, 1]), DirectionalLight([0.3, -1.0, 0.5], [1, 1, 1])]
    eps = 1e-6
    w = rng.standard_normal((Pn, 2))
    b, st = _shadow(device64, V, F, alpha_v, pos, own, lights, eps, early_out=True)
    g = trace_op.shadow_backward(device64, b, st, w)
    hits = st.nhit.get().reshape(Pn, 2)
    _, full = _shadow(device64, V, F, alpha_v, pos, own, lights, eps)
    deep = full.vis.get() < 1e-4
    assert deep.any() and (hits < full.nhit.get().reshape(Pn, 2)).any()
    # the rays that never fall below 1e-4: only their cotangents, against the full walk's adjoint
    w_shallow = np.where(deep, 0.0, w)
    g_e = trace_op.shadow_backward(device64, b, st, w_shallow)
    g_f = trace_op.shadow_backward(device64, b, full, w_shallow)
    np.testing.assert_allclose(g_e.v_alpha, g_f.v_alpha, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(g_e.v_V, g_f.v_V, rtol=1e-12, atol=1e-15)

    def value(alpha_v=alpha_v, V=V, pos=pos):
        _, s = _shadow(device64, V, F, alpha_v, pos, own, lights, eps, early_out=True)
        return (s.vis.get() * w).sum(), s.nhit.get().tobytes()

    sig = st.nhit.get().tobytes()
    h = 1e-6  # float64: the difference quotient's rounding error ~1e-16 x |value| / h, under the abs tolerance
    hit_vertices = np.flatnonzero(np.abs(g.v_alpha) > 0)
    assert len(hit_vertices) > 20
    checked = 0
    for i in rng.choice(hit_vertices, 12, replace=False):
        for what in ("alpha", "V"):
            arr = alpha_v if what == "alpha" else V
            idx = (i,) if what == "alpha" else (i, int(rng.integers(3)))
            a0 = arr[idx]
            arr[idx] = a0 + h
            fp, sp = value(alpha_v, V)
            arr[idx] = a0 - h
            fm, sm = value(alpha_v, V)
            arr[idx] = a0
            if sp != sig or sm != sig:
                continue
            got = g.v_alpha[i] if what == "alpha" else g.v_V[idx]
            assert got == pytest.approx((fp - fm) / (2 * h), rel=1e-5, abs=1e-8), (what, idx)
            checked += 1
    assert checked >= 16
    gp = g.v_pos.get()
    for p in rng.choice(Pn, 6, replace=False):
        k = int(rng.integers(3))
        p0 = pos[p, k]
        pos[p, k] = p0 + h
        fp, sp = value(pos=pos)
        pos[p, k] = p0 - h
        fm, sm = value(pos=pos)
        pos[p, k] = p0
        if sp == sig and sm == sig:
            assert gp[p, k] == pytest.approx((fp - fm) / (2 * h), rel=1e-5, abs=1e-8), (p, k)
    # an occluder the early walks never reach (only the full walk's hits beyond a stop) has no gradient
    g_full = trace_op.shadow_backward(device64, b, full, w)
    beyond = (np.abs(g_full.v_alpha) > 0) & (g.v_alpha == 0)
    assert beyond.any()


def test_shadow_early_out_adjoint_float32(device, device64, rng):
    """The hybrid renderer's float32 early-out: the adjoint walks the float32 forward's hits (its own rounding of the
    running product), so the occluders' adjoints match the float64 ones to float32 precision."""
    V, F = soup(rng, M=300)
    alpha_v = rng.uniform(0.6, 0.999, len(V))
    Pn = 60
    pos = rng.uniform(-0.7, 0.7, (Pn, 3))
    own = rng.integers(0, len(F), Pn)
    lights = [PointLight([0.2, 1.9, 0.4], [1, 1, 1]), DirectionalLight([0.3, -1.0, 0.5], [1, 1, 1])]
    w = rng.standard_normal((Pn, 2))
    out = {}
    for dev, real in ((device64, np.float64), (device, np.float32)):
        b, st = _shadow(dev, V, F, alpha_v, pos, own, lights, 1e-6, real=real, early_out=True)
        out[real] = (st.nhit.get(), trace_op.shadow_backward(dev, b, st, w))
    (n64, g64), (n32, g32) = out[np.float64], out[np.float32]
    np.testing.assert_array_equal(n32, n64)  # the same stops (no running product within rounding of 1e-4 here)
    scale = np.abs(g64.v_alpha).max()
    np.testing.assert_allclose(g32.v_alpha, g64.v_alpha, rtol=0, atol=2e-5 * scale)
    np.testing.assert_allclose(g32.v_V, g64.v_V, rtol=0, atol=2e-4 * np.abs(g64.v_V).max())


def test_shadow_transmittance_matches_reference(device64, rng):
    V, F = soup(rng, M=50)
    alpha_v = rng.uniform(0.05, 0.95, len(V))
    Pn = 40
    pos = rng.uniform(-0.7, 0.7, (Pn, 3))
    own = rng.integers(-0, len(F), Pn)
    lights = [PointLight([0.2, 1.9, 0.4], [1, 1, 1]), DirectionalLight([0.3, -1.0, 0.5], [1, 1, 1])]
    _, st = _shadow(device64, V, F, alpha_v, pos, own, lights, 1e-6)
    T, n = ref.transmittance_ref(V, F, alpha_v, pos, own, [("point", [0.2, 1.9, 0.4]), ("dir", [0.3, -1.0, 0.5])],
                                 1e-6)
    assert n.sum() > 30  # the rays do cross triplets
    np.testing.assert_array_equal(st.nhit.get().reshape(Pn, 2), n)
    np.testing.assert_allclose(st.vis.get(), T, rtol=1e-12)


def test_shadow_rays_through_shared_edges_and_grazing(device64):
    # two triangles in z = 0 sharing the edge x + y = 1 (vertices duplicated, as in a soup)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    F = np.arange(6).reshape(2, 3)
    alpha_v = np.full(6, 0.5)
    pos = np.array([[0.5, 0.5, -1.0],  # straight through the shared edge: both faces
                    [0.25, 0.75, -1.0],  # idem
                    [-1.0, 0.3, 0.0],  # in the triangles' plane (det = 0): no hit
                    [-0.5, 0.3, -0.0008],  # grazing at 1e-3 rad: hits face 0 at (0.3, 0.3)
                    [0.2, 0.2, -1.0]])  # interior of face 0
    own = np.full(len(pos), 99)
    dirs = [[0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 0, 1e-3], [0, 0, 1]]
    for p, d in enumerate(dirs):
        _, st = _shadow(device64, V, F, alpha_v, pos[p:p + 1], own[p:p + 1], [DirectionalLight(d, [1, 1, 1])], 1e-9)
        T, n = ref.transmittance_ref(V, F, alpha_v, pos[p:p + 1], own[p:p + 1], [("dir", d)], 1e-9)
        assert int(st.nhit.get()[0]) == int(n[0, 0]) == [2, 2, 0, 1, 1][p], p
        np.testing.assert_allclose(st.vis.get()[0, 0], T[0, 0], rtol=1e-12)


# ------------------------------------------------------------------------------------------------ bounce


def test_bounce_matches_reference(device64, rng):
    V, F = soup(rng, M=50)
    import pyopencl.array as cla

    q = device64.queue
    mesh = DeviceMesh(device64, F, len(V))
    b = build_bvh(device64, V, mesh)
    Pn = 60
    own = rng.integers(0, len(F), Pn)
    lam = rng.dirichlet([2, 2, 2], Pn)
    pos = (V[F[own]] * lam[..., None]).sum(1)  # points on their own faces
    nrm = np.cross(V[F[own, 1]] - V[F[own, 0]], V[F[own, 2]] - V[F[own, 0]])
    c = cam().center
    hf, hb = trace_op.bounce(device64, b, cla.to_device(q, V), cla.to_device(q, pos), cla.to_device(q, nrm),
                             cla.to_device(q, own.astype(np.int32)), c, True, 1e-6)
    rf, rb = ref.bounce_ref(V, F, pos, nrm, own, c, 1e-6)
    assert (rf >= 0).sum() > 10
    np.testing.assert_array_equal(hf.get(), rf)
    np.testing.assert_allclose(hb.get(), rb, atol=1e-12)
    # gather_hits and its adjoint scatter_hits are transposes of each other
    attr = rng.standard_normal((len(V), 4))
    g = trace_op.gather_hits(device64, cla.to_device(q, attr), 1, 3, mesh.F, hf, hb).get()
    w = rng.standard_normal(g.shape)
    back = trace_op.scatter_hits(F, len(V), hf.get(), hb.get(), w)
    assert (g * w).sum() == pytest.approx((attr[:, 1:4] * back).sum(), rel=1e-12)


def test_trace_rays_matches_reference(device64, rng):
    """``trace_rays`` (the interreflection's hemisphere rays): any origin and direction, its own face skipped, no ray
    where ``own < 0``; the same hits as the brute-force reference."""
    import pyopencl.array as cla

    V, F = soup(rng, M=50)
    mesh = DeviceMesh(device64, F, len(V))
    b = build_bvh(device64, V, mesh)
    R = 80
    own = rng.integers(0, len(F), R)
    own[:5] = -1
    lam = rng.dirichlet([2, 2, 2], R)
    origin = (V[F[own]] * lam[..., None]).sum(1)
    direction = rng.standard_normal((R, 3)) * rng.uniform(0.2, 3.0, (R, 1))  # not unit
    hf, hb = trace_op.trace_rays(device64, b, cla.to_device(device64.queue, V), origin, direction,
                                 own.astype(np.int32), 1e-6)
    rf, rb = ref.nearest_ref(V, F, origin, direction, own, 1e-6)
    assert (rf >= 0).sum() > 20 and (rf < 0).sum() > 5 and np.all(hf.get()[:5] == -1)
    np.testing.assert_array_equal(hf.get(), rf)
    np.testing.assert_allclose(hb.get(), rb, atol=1e-12)
    with pytest.raises(ValueError, match="own must be"):
        trace_op.trace_rays(device64, b, cla.to_device(device64.queue, V), origin, direction, own[:-1].astype(np.int32),
                            1e-6)


# ------------------------------------------------------------------------------------------------ shading terms


def test_shade_visibility_and_reflection_adjoints(device64, rng):
    Pn = 24
    pos = rng.normal(0, 0.5, (Pn, 3))
    nrm = rng.normal(0, 1, (Pn, 3))
    mat = rng.uniform(0.1, 0.9, (Pn, 6))
    fid = np.arange(Pn)
    camc = np.array([0.3, 0.2, 3.0])
    lights = [PointLight([1.5, 2.0, 3.0], [6.0, 5.0, 4.0]), DirectionalLight([0.3, 1.0, 0.5], [0.6, 0.7, 0.8])]
    vis = rng.uniform(0, 1, (Pn, 2))
    refl = rng.uniform(0, 1, (Pn, 3))
    v_rgb = rng.standard_normal((Pn, 3))

    def f(vis, refl, mat):
        dev, inp = shade_op.prepare(pos, nrm, mat, fid, camc, lights, device=device64, real=np.float64, vis=vis,
                                    refl=refl)
        return (shade_op.forward(dev, inp).get() * v_rgb).sum(), dev, inp

    # vis = 1 and refl = 0 reproduce the plain shading
    plain = shade_op.shade(pos, nrm, mat, fid, camc, lights, device=device64, real=np.float64)
    assert f(np.ones((Pn, 2)), np.zeros((Pn, 3)), mat)[0] == pytest.approx((plain * v_rgb).sum(), rel=1e-12)
    _, dev, inp = f(vis, refl, mat)
    import pyopencl.array as cla

    out = shade_op.backward(dev, inp, cla.to_device(dev.queue, v_rgb))
    v_mat, v_vis, v_refl = out.v_mat.get(), out.v_vis.get(), out.v_refl.get()
    eps = 1e-6
    for name, x, g in (("vis", vis, v_vis), ("refl", refl, v_refl), ("mat", mat, v_mat)):
        for i in rng.choice(x.size, 12, replace=False):
            xp, xm = x.copy(), x.copy()
            xp.flat[i] += eps
            xm.flat[i] -= eps
            args = {"vis": vis, "refl": refl, "mat": mat}
            fp = f(**{**args, name: xp})[0]
            fm = f(**{**args, name: xm})[0]
            assert g.flat[i] == pytest.approx((fp - fm) / (2 * eps), rel=1e-6, abs=1e-9), (name, i)


# ------------------------------------------------------------------------------------------------ render


def _scene(rng, M=14):
    from tests.test_render import small_scene

    return small_scene(rng, "cook_torrance", False, M=M)


def _rcam():
    from tests.test_render import cam as rcam

    return rcam()


def _signature(r):
    fr = read_fragments(r.info["frags"])["face"].tobytes()
    return fr, tuple(None if v is None else v.tobytes() for v in r.state.traced.values())


@pytest.mark.parametrize("renderer,reflections,params", [
    ("hybrid", False, ("V", "alpha", "light_params")),
    ("raytrace", True, ("V", "material", "alpha", "light_params")),
])
def test_traced_render_gradients_central_differences(device64, rng, renderer, reflections, params):
    """Shadows: adjoints to occluder alphas and positions, shaded points and lights; bounce: to the hit
    surface's materials / alpha and the lights, and to the reflecting surface's materials."""
    scene = _scene(rng)
    s = RenderSettings(K=6, sigma=1.0, real=np.float64, t_min=0.0, renderer=renderer, reflections=reflections)
    c = _rcam()
    r = render(scene, c, s, device64)
    sig0 = _signature(r)
    assert r.state.traced["shadow_hits"].sum() > 10
    if reflections:
        assert (r.state.traced["bounce_face"] >= 0).sum() > 5
    w = rng.standard_normal(r.rgba.data.shape)
    scene.zero_grad()
    grads = r.backward(w[..., :3], w[..., 3])
    eps = 1e-6
    for p in scene.params:
        if p.name not in params:
            continue
        flat = p.data.reshape(-1)
        checked = 0
        for i in rng.choice(flat.size, size=min(flat.size, 14), replace=False):
            old = flat[i]
            flat[i] = old + eps
            rp = render(scene, c, s, device64)
            flat[i] = old - eps
            rm = render(scene, c, s, device64)
            flat[i] = old
            if _signature(rp) != sig0 or _signature(rm) != sig0:
                continue
            num = ((rp.rgba.data - rm.rgba.data) * w).sum() / (2 * eps)
            assert grads[p.name].reshape(-1)[i] == pytest.approx(num, rel=1e-5, abs=1e-7), (p.name, i)
            checked += 1
        assert checked >= 10, p.name


def test_render_all_renderers_forward_backward_float32(device, rng):
    scene = _scene(rng, M=30)
    c = _rcam()
    imgs = {}
    for renderer in ("raster", "raytrace", "hybrid"):
        s = RenderSettings(K=8, sigma=1.0, renderer=renderer)
        r = render(scene, c, s, device)
        imgs[renderer] = r.image.copy()
        scene.zero_grad()
        g = r.backward(np.ones_like(r.image))
        for name, v in g.items():
            assert v is not None and np.isfinite(v).all(), (renderer, name)
        assert np.abs(g["V"]).max() > 0 and np.abs(g["alpha"]).max() > 0
    # without the traced terms, ray-traced primary visibility renders the raster image
    plain = render(scene, c, RenderSettings(K=8, sigma=1.0, renderer="raytrace", shadows=False, reflections=False),
                   device)
    diff = np.abs(plain.image - imgs["raster"]).max(-1)
    assert (diff > 1e-3).mean() < 0.02  # edge pixels only
    # shadows darken: the traced images differ from the raster one where light is blocked
    assert np.abs(imgs["hybrid"] - imgs["raster"]).max() > 1e-3


def test_ray_mask_skips_fragments_behind_opaque_ones(device, rng):
    """Fragments behind a transmittance below t_min get no rays (face −1), the others keep their face."""
    import pyopencl.array as cla

    from triplet_cl.ops.columns import Compaction

    V, F = soup(rng, M=80)
    c = cam()
    mesh = DeviceMesh(device, F, len(V))
    fr = rasterize(device, project(device, V.astype(np.float32), c), mesh, W, H, 12)
    comp = Compaction(device, fr)
    face = fr.face  # the packed fragments' face ids
    a = rng.uniform(0.3, 0.99, comp.P).astype(np.float32)
    w = rng.uniform(0.5, 1.0, comp.P).astype(np.float32)
    q = device.queue
    out = trace_op.ray_mask(device, fr, comp.offsets, face, cla.to_device(q, a), cla.to_device(q, w), 1e-2).get()
    cnt, off, fh = fr.count.get().reshape(-1), comp.offsets.get(), face.get()
    exp = fh.copy()
    for p in range(len(cnt)):
        T = 1.0
        for k in range(cnt[p]):
            if T < 1e-2:
                exp[off[p] + k] = -1
            T *= 1 - a[off[p] + k] * w[off[p] + k]
    np.testing.assert_array_equal(out, exp)
    assert (out < 0).sum() > 0 and (out >= 0).sum() > 0
