"""``render(scene, camera, settings)`` end to end: every scene parameter's gradient against float64
central differences of the whole chain (normals → vertex SH → activations → raster → interpolate →
coverage → shade → composite), and a ``render → loss → backward`` chain on one tape."""

from __future__ import annotations

import numpy as np
import pytest
from triplet_cl.autodiff import Tape

from tests.gradients import sampled_fd
from triplet_cl.camera import Camera
from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight, VertexSHLight
from triplet_cl.losses import PhotometricLoss
from triplet_cl.ops.raster import read_fragments
from triplet_cl.render import RenderSettings, render
from triplet_cl.scene import Scene

W, H = 15, 12


def grid_mesh(rng, n=5):
    """A connected, gently curved grid (vertices shared by up to 6 faces)."""
    g = np.stack(np.meshgrid(np.linspace(-0.8, 0.8, n), np.linspace(-0.7, 0.7, n)), -1).reshape(-1, 2)
    V = np.concatenate([g, 0.2 * np.sin(2.0 * g[:, :1]) + 0.05 * rng.normal(size=(len(g), 1))], 1)
    idx = np.arange(n * n).reshape(n, n)
    F = np.concatenate([np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:]], -1).reshape(-1, 3),
                        np.stack([idx[:-1, :-1], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 3)])
    return V, F


def small_scene(rng, brdf, vertex_sh=False, M=10, mesh=False):
    if mesh:
        V, F = grid_mesh(rng)
    else:
        c = rng.uniform(-0.45, 0.45, (M, 1, 3))
        V = (c + rng.normal(0, 0.3, (M, 3, 3))).reshape(-1, 3)
        F = np.arange(3 * M).reshape(M, 3)
    n = len(V)
    lights = [PointLight([1.5, 2.0, 3.0], [6.0, 5.0, 4.0]), DirectionalLight([0.3, 1.0, 0.5], [0.6, 0.7, 0.8]),
              AmbientLight([0.1, 0.15, 0.2]),
              SHEnvironmentLight(rng.normal(0, 0.2, (3, 4)) + np.array([[0.8], [0.8], [0.8]]) * [1, 0, 0, 0], 1)]
    vsh = None
    if vertex_sh:
        lights.append(VertexSHLight())
        vsh = rng.normal(0, 0.2, (n, 6, 4))
        vsh[:, 3:, 0] += 0.5
    from triplet_cl.ops.shade import num_material_channels

    mat = rng.normal(0, 0.8, (n, num_material_channels(brdf)))
    alpha = rng.normal(0.5, 0.5, (n, 1))
    return Scene.from_arrays(V, F, material=mat, alpha=alpha, lights=lights, vertex_sh=vsh, brdf=brdf,
                             dtype=np.float64)


def cam():
    return Camera.look_at([0.4, 0.3, 3.0], [0, 0, 0], [0, 1, 0], 40, W, H)


@pytest.mark.parametrize("brdf,vertex_sh,sigma,mesh,transfer", [("cook_torrance", True, 0.8, False, None),
                                                                 ("blinn_phong", False, None, False, None),
                                                                 ("cook_torrance", False, 1.5, True, None),
                                                                 ("cook_torrance", False, 0.8, False, "srgb")])
def test_render_gradients_central_differences(device64, rng, brdf, vertex_sh, sigma, mesh, transfer):
    """Soups with face normals, and a connected mesh with area-weighted vertex normals; the linear
    pipeline with the sRGB transfer after compositing."""
    scene = small_scene(rng, brdf, vertex_sh, mesh=mesh)
    settings = RenderSettings(K=6, sigma=sigma, real=np.float64, t_min=0.0, background=(0.3, 0.5, 0.9),
                              normals="vertex" if mesh else "face", transfer=transfer)
    c = cam()
    w = rng.standard_normal((H, W, 4))
    r = render(scene, c, settings, device64)
    faces0 = read_fragments(r.info["frags"])["face"]
    assert (faces0 >= 0).sum() > 40
    scene.zero_grad()
    grads = r.backward(w[..., :3], w[..., 3])

    def loss():
        rr = render(scene, c, settings, device64)
        same = np.array_equal(read_fragments(rr.info["frags"])["face"], faces0)
        return float((rr.rgba.data * w).sum()), same

    for p in scene.params:
        idx, num, ok = sampled_fd(p, loss, rng, 40)
        ana = grads[p.name].reshape(-1)[idx]
        assert ok.mean() > 0.9, f"{p.name}: perturbations changed coverage too often"
        np.testing.assert_allclose(ana[ok], num[ok], rtol=1e-5, atol=1e-7, err_msg=f"{brdf} {p.name}")
        if p.name != "vertex_sh":  # higher SH bands of hidden vertices may be exactly 0
            assert np.abs(ana).max() > 0, p.name


def test_render_srgb_transfer_is_the_photo_model(device64, rng):
    """``transfer="srgb"``: linear compositing over black, then ``A·s(C/A) + (1−A)·bg``."""
    from tests.reference.color import srgb_composite

    scene = small_scene(rng, "cook_torrance")
    bg = (0.3, 0.5, 0.9)
    lin = render(scene, cam(), RenderSettings(K=6, real=np.float64, background=(0, 0, 0)), device64)
    enc = render(scene, cam(), RenderSettings(K=6, real=np.float64, background=bg, transfer="srgb"), device64)
    np.testing.assert_allclose(enc.alpha, lin.alpha, rtol=1e-12)
    np.testing.assert_allclose(enc.image, srgb_composite(lin.image, lin.alpha, bg), rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="transfer must be"):
        RenderSettings(transfer="gamma")


def test_render_then_loss_on_one_tape(device64, rng):
    scene = small_scene(rng, "cook_torrance")
    settings = RenderSettings(K=4, sigma=1.0, real=np.float64)
    c = cam()
    target = rng.uniform(0, 1, (H, W, 3))

    def total():
        with Tape() as tape:
            r = render(scene, c, settings, device64)
            from triplet_cl.render import Stack  # noqa: F401 - render's output is RGBA

            img = _RGB()(r.rgba)
            loss = PhotometricLoss(lam=0.2)(img, target)
        return tape, loss

    tape, loss = total()
    scene.zero_grad()
    tape.backward(loss)
    g = scene.material.grad.copy()
    assert np.abs(g).max() > 0
    eps = 1e-6
    flat = scene.material.data.reshape(-1)
    for i in rng.choice(flat.size, 12, replace=False):
        old = flat[i]
        flat[i] = old + eps
        lp = float(total()[1].data)
        flat[i] = old - eps
        lm = float(total()[1].data)
        flat[i] = old
        assert g.reshape(-1)[i] == pytest.approx((lp - lm) / (2 * eps), rel=1e-5, abs=1e-9)


from triplet_cl.autodiff import Function  # noqa: E402


class _RGB(Function):
    def forward(self, ctx, rgba):
        return np.ascontiguousarray(rgba[..., :3])

    def backward(self, ctx, v):
        out = np.zeros(v.shape[:2] + (4,))
        out[..., :3] = v
        return out


def test_render_float32_runs_and_validates(device, rng):
    V = small_scene(rng, "cook_torrance").V.data
    scene = Scene.from_arrays(V, np.arange(len(V)).reshape(-1, 3), lights=[AmbientLight([1, 1, 1])])
    r = render(scene, cam(), RenderSettings(K=8))
    assert r.image.shape == (H, W, 3) and r.image.dtype == np.float32
    assert np.isfinite(r.image).all() and (r.alpha >= 0).all() and (r.alpha <= 1).all()
    g = r.backward(np.ones((H, W, 3)))
    assert all(np.isfinite(v).all() for v in g.values() if v is not None)
    with pytest.raises(ValueError, match="v_image must have shape"):
        r.backward(np.ones((H, W)))
    with pytest.raises(ValueError, match="normals must be"):
        RenderSettings(normals="smooth")


@pytest.mark.parametrize("renderer", ["raster", "raytrace"])
def test_render_info_reports_the_density_statistics(device64, rng, renderer):
    """``RenderResult.info`` (gsplat's ``info``): the fragments and projected vertices of the forward
    pass, and after ``backward`` the screen-space vertex adjoint (density control's statistic)."""
    from triplet_cl.ops.fragments import Fragments

    scene = small_scene(rng, "cook_torrance")
    r = render(scene, cam(), RenderSettings(K=6, sigma=0.8, real=np.float64, renderer=renderer), device64)
    info = r.info
    assert set(info) == {"frags", "vs", "v_vs"}
    assert isinstance(info["frags"], Fragments) and info["frags"].P > 0
    assert info["vs"] is info["frags"].vs and info["vs"].shape == (scene.V.shape[0], 3)
    assert info["v_vs"] is None
    r.backward(rng.standard_normal((H, W, 3)))
    v_vs = info["v_vs"].get()
    assert v_vs.shape == (scene.V.shape[0], 3) and np.abs(v_vs).sum() > 0


@pytest.mark.parametrize("renderer", ["raster", "hybrid", "raytrace"])
def test_render_a_view_that_sees_nothing(device, rng, renderer):
    """No fragment at all (P = 0, the camera looks away): every renderer returns the background and
    zero gradients, forward and backward, with no zero-size kernel launch failing."""
    scene = small_scene(rng, "cook_torrance")
    scene = Scene.from_arrays(np.asarray(scene.V.data, np.float32), scene.F, lights=[PointLight([0, 2, 3], [5, 5, 5])])
    away = Camera.look_at([0.0, 0.0, 3.0], [0, 0, 6], [0, 1, 0], 40, W, H)
    r = render(scene, away, RenderSettings(K=4, sigma=1.0, renderer=renderer, background=(0.2, 0.4, 0.6)))
    assert r.info["frags"].P == 0
    np.testing.assert_allclose(r.image, np.broadcast_to([0.2, 0.4, 0.6], (H, W, 3)), atol=1e-6)
    assert (r.alpha == 0).all()
    g = r.backward(np.ones((H, W, 3)))
    for k, v in g.items():
        if v is not None and k != "light_params":
            assert np.all(np.asarray(v) == 0), k


@pytest.mark.parametrize("brdf,vertex_sh,mesh,K,renderer", [("cook_torrance", True, False, 6, "raster"),
                                                            ("blinn_phong", False, False, 1, "raster"),
                                                            ("cook_torrance", False, True, 150, "raster"),
                                                            ("blinn_phong", True, False, 150, "raster"),
                                                            ("cook_torrance", False, False, 6, "hybrid")])
@pytest.mark.parametrize("real", [np.float64, np.float32])
def test_device_attributes_equal_the_host_chain(device, device64, rng, brdf, vertex_sh, mesh, K, renderer, real):
    """``RenderSettings.attributes="device"`` (VertexAttributes: normals, activations and the packed
    attribute array in one kernel, adjoint on the device) against the host chain Normals →
    MaterialActivation → SigmoidHost → Concat: the same image and every parameter's gradient, per
    BRDF (Blinn-Phong has a softplus channel), with vertex SH, on soups (face normals) and a mesh
    (vertex normals), K = 1 and 150, rasterized and hybrid (traced shadows and bounce read the
    device array)."""
    dev = device64 if real == np.float64 else device
    scene = small_scene(rng, brdf, vertex_sh, mesh=mesh)
    for p in scene.params:
        p.data = np.asarray(p.data, real)
    c = cam()
    w = rng.standard_normal((H, W, 4))
    out = {}
    for attributes in ("host", "device"):
        settings = RenderSettings(K=K, sigma=0.8, real=real, background=(0.3, 0.5, 0.9), renderer=renderer,
                                  normals="vertex" if mesh else "face", transfer="srgb", attributes=attributes)
        scene.zero_grad()
        r = render(scene, c, settings, dev)
        out[attributes] = (r.rgba.data.copy(), r.backward(w[..., :3], w[..., 3]))
    (img_h, g_h), (img_d, g_d) = out["host"], out["device"]
    tol = dict(rtol=1e-10, atol=1e-12) if real == np.float64 else dict(rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(img_d, img_h, **tol)
    assert set(g_d) == set(g_h)
    for k in g_h:
        scale = max(float(np.abs(g_h[k]).max()), 1e-12)
        np.testing.assert_allclose(g_d[k] / scale, g_h[k] / scale, rtol=0, atol=tol["rtol"] * 10, err_msg=k)
        assert np.abs(g_h[k]).max() > 0 or k == "vertex_sh", k


def test_device_attributes_setting_and_fallbacks(device, rng):
    """A bad value is refused; a soup not in the training layout (rotated corners) and
    ``attributes="host"`` take the host chain."""
    with pytest.raises(ValueError, match="attributes must be"):
        RenderSettings(attributes="gpu")
    from triplet_cl.ops.mesh import DeviceMesh
    from triplet_cl.render import use_device_attributes

    scene = small_scene(rng, "cook_torrance")
    F = np.asarray(scene.F)
    assert use_device_attributes(RenderSettings(), DeviceMesh(device, F, len(scene.V.data)))
    perm = F[:, [1, 2, 0]]
    assert not use_device_attributes(RenderSettings(), DeviceMesh(device, perm, len(scene.V.data)))
    assert not use_device_attributes(RenderSettings(attributes="host"), DeviceMesh(device, F, len(scene.V.data)))


@pytest.mark.parametrize("mesh,vertex_sh", [(False, True), (True, False)])
def test_vertex_attributes_with_constant_columns_equal_concat(device64, rng, mesh, vertex_sh):
    """``VertexAttributes(..., const=c)`` equals ``Concat(V, Normals(V), MaterialActivation(m),
    SigmoidHost(a)[, vlight], c)`` (a constant block last, e.g. a cached visibility): the array and,
    for a random cotangent, every input's adjoint (the constant columns have none)."""
    from triplet_cl.autodiff import Context

    from triplet_cl.render import (
        Concat,
        MaterialActivation,
        Normals,
        RenderState,
        SigmoidHost,
        VertexAttributes,
        device_mesh,
    )

    scene = small_scene(rng, "blinn_phong", vertex_sh=vertex_sh, mesh=mesh)
    V, m, a = scene.V.data, scene.material.data, scene.alpha.data
    n = len(V)
    vl = [rng.normal(size=(n, 6))] if vertex_sh else []
    const = rng.uniform(0, 1, (n, 2))
    settings = RenderSettings(real=np.float64, normals="vertex" if mesh else "face")
    dmesh = device_mesh(device64, scene.F, n)
    view = RenderState(device64, dmesh, cam(), settings)
    op = VertexAttributes(view, scene.brdf, const=const)
    ctx = Context((True,) * (3 + len(vl)))
    attr = op.forward(ctx, V, m, a, *vl).get()
    # the host chain
    fns = [Normals(dmesh, settings.normals, np.float64, device64), MaterialActivation(scene.brdf), SigmoidHost()]
    cts = [Context((True,)) for _ in fns]
    blocks = [V] + [f.forward(c, x) for f, c, x in zip(fns, cts, (V, m, a), strict=True)] + vl + [const]
    cat, cctx = Concat(), Context((True,) * len(blocks))
    want = cat.forward(cctx, *blocks)
    np.testing.assert_allclose(attr, want, rtol=1e-12, atol=1e-14)
    v = rng.standard_normal(want.shape)
    got = op.backward(ctx, v)
    parts = cat.backward(cctx, v)
    v_V = parts[0] + fns[0].backward(cts[0], parts[1])
    want_g = [v_V, fns[1].backward(cts[1], parts[2]), fns[2].backward(cts[2], parts[3])] + list(parts[4:4 + len(vl)])
    assert len(got) == len(want_g)
    for g, w in zip(got, want_g, strict=True):
        np.testing.assert_allclose(np.asarray(g), w, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("transfer,renderer,down,pixel_sigma", [(None, "raster", 1, 0.0), ("srgb", "raster", 1, 0.0),
                                                               ("srgb", "hybrid", 1, 0.0), (None, "raster", 2, 0.5),
                                                               ("srgb", "raster", 2, 0.5), ("srgb", "raster", 2, 0.0)])
def test_device_image_and_backward_device_equal_the_host_round_trip(device, rng, transfer, renderer, down,
                                                                    pixel_sigma):
    """The training loop's device loss: ``RenderResult.device_image`` is the host image bit for bit, and the
    device loss's adjoint seeded with ``backward_device`` gives every parameter the gradient, bit for bit,
    that the same adjoint downloaded and handed to ``backward`` gives (no host round trip, same numbers);
    the device loss against the host (numpy) loss within the existing float32 tolerances; bad input refused.
    Also through the mesh stage's supersampled render and its pixel filter (``down`` 2: the Gaussian of
    ``pixel_sigma`` or the box over the radiance and the alpha, ``render.PixelFilterRGBA``)."""
    import pyopencl.array as cla

    from triplet_cl.losses import photometric_loss_and_grad

    base = small_scene(rng, "cook_torrance", vertex_sh=True)
    scene = Scene.from_arrays(np.asarray(base.V.data, np.float32), base.F, material=base.material.data,
                              alpha=base.alpha.data, lights=base.lights, vertex_sh=base.vertex_sh.data,
                              brdf="cook_torrance", dtype=np.float32)
    settings = RenderSettings(K=8, sigma=1.0, transfer=transfer, renderer=renderer, downsample=down,
                              pixel_sigma=pixel_sigma)
    camera = cam().scaled(down) if down > 1 else cam()
    target = rng.random((H, W, 3)).astype(np.float32)
    grads = []
    for path in ("host", "device"):
        for p in scene.params:
            p.grad = None
        r = render(scene, camera, settings, device)
        assert r.image.shape == (H, W, 3)
        assert isinstance(r.device_image, cla.Array)
        np.testing.assert_array_equal(r.device_image.get(), r.image)
        loss, v_img = photometric_loss_and_grad(r.device_image, cla.to_device(device.queue, target))
        if path == "host":
            r.backward(v_img.get())
            host_loss, host_v = photometric_loss_and_grad(r.image, target, backend="numpy")
            assert abs(host_loss - loss) <= 1e-5
            np.testing.assert_allclose(v_img.get(), host_v, rtol=1e-3, atol=1e-8)
        else:
            r.backward_device(v_img)
        grads.append({p.name: None if p.grad is None else np.array(p.grad) for p in scene.params})
    assert any(g is not None and np.abs(g).sum() > 0 for g in grads[0].values())
    for k, g in grads[0].items():
        if g is None:
            assert grads[1][k] is None
        else:
            np.testing.assert_array_equal(grads[1][k], g, err_msg=k)
    r = render(scene, camera, settings, device)
    with pytest.raises(ValueError, match="v_image must be a device array"):
        r.backward_device(np.ones((H, W, 3), np.float32))
    with pytest.raises(ValueError, match="v_image must be a device array"):
        r.backward_device(cla.zeros(device.queue, (H, W), np.float32))


@pytest.mark.parametrize("transfer", [None, "srgb"])
@pytest.mark.parametrize("pixel_sigma", [0.0, 0.5])
def test_downsample_is_the_box_filtered_render(device64, rng, transfer, pixel_sigma):
    """``RenderSettings.downsample = f`` (the mesh stage's supersampling, on the device) is the full-resolution render
    box-filtered on the host (``pixel_sigma`` 0; > 0: filtered by the Gaussian pixel filter of the numpy reference):
    with the sRGB transfer, the linear premultiplied radiance and the alpha filtered, then composited over the
    background in encoded space; the image and every gradient (the host chain's adjoint: the composite's, then each
    cotangent spread back by the filter's transpose)."""
    from dataclasses import replace

    from tests.reference import downsample as ref_down
    from triplet_cl.ops.color import srgb_composite_backward_host, srgb_composite_host

    f, bg = 3, (0.2, 0.5, 0.9)
    scene = small_scene(rng, "cook_torrance", mesh=True)
    c = cam()
    big = c.scaled(f)
    st = RenderSettings(K=4, sigma=1.0, soft_edges="silhouette", normals="vertex", background=bg, transfer=transfer,
                        real=np.float64)
    r = render(scene, big, replace(st, downsample=f, pixel_sigma=pixel_sigma), device64)
    v = rng.standard_normal((H, W, 3))
    g = r.backward(v)
    for p in scene.params:  # backward accumulates into Param.grad: the host chain's gradients from zero
        p.grad = None

    def down(a):
        if pixel_sigma:
            return ref_down.gauss_down(a, f, pixel_sigma)
        return a.reshape((H, f, W, f) + a.shape[2:]).mean(axis=(1, 3))

    def up(a):
        if pixel_sigma:
            return ref_down.gauss_up(a, f, pixel_sigma)
        return np.repeat(np.repeat(a, f, axis=0), f, axis=1) / f ** 2

    if transfer is None:
        full = render(scene, big, st, device64)
        want, alpha = down(full.image), down(full.alpha)
        gw = full.backward(up(v))
    else:
        full = render(scene, big, replace(st, transfer=None, background=(0.0, 0.0, 0.0)), device64)
        C, alpha = down(full.image), down(full.alpha)
        want = srgb_composite_host(C, alpha, bg, device=device64, real=np.float64)
        v_C, v_A = srgb_composite_backward_host(C, alpha, bg, v, device=device64, real=np.float64)
        gw = full.backward(up(v_C), up(v_A))
    assert r.image.shape == (H, W, 3) and r.alpha.shape == (H, W) and r.out_size == (H, W)
    assert alpha.min() < 0.5 < alpha.max()  # an outline in view
    np.testing.assert_allclose(r.image, want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.alpha, alpha, rtol=1e-10, atol=1e-12)
    for name in ("V", "material", "alpha", "light_params"):
        np.testing.assert_allclose(g[name], gw[name], rtol=1e-8, atol=1e-10 * np.abs(gw[name]).max(), err_msg=name)
    with pytest.raises(ValueError, match="downsample"):
        RenderSettings(downsample=0)
    with pytest.raises(ValueError, match="divides"):  # 15 x 12 pixels in blocks of 2
        render(scene, c, replace(st, downsample=2), device64)


# Mitsuba 3.9.1 (path, max_depth 2: direct light only; principled, base colour 0.5, roughness 0.4, metallic 0; a point
# light of 10 W/sr at (0, 2, -2.5); perspective 50° look_at from (0, 2, 2.5) to the origin, up +y, 128², 1024 spp)
# on the plane y = 0, |x|, |z| <= 1: red channel at (row, column) — the camera column through the highlight and one
# 20 pixels beside it
MITSUBA_PLANE = {(50, 64): 0.338018, (58, 64): 0.405320, (64, 64): 0.376890, (72, 64): 0.258565, (80, 64): 0.159181,
                 (50, 84): 0.163899, (58, 84): 0.137819, (64, 84): 0.121916, (72, 84): 0.102704, (80, 84): 0.085601}


def test_plane_under_a_point_light_is_the_path_tracers(device):
    """End to end (camera, rasterizer, the point light's falloff, Cook-Torrance): our render of a plane lit by a
    point light is Mitsuba's, across the highlight, to 0.5 % (measured at most 0.29 %: its Gaussian pixel filter
    against our pixel centres)."""
    n = 40
    xs = np.linspace(-1, 1, n + 1)
    X, Z = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], 1)
    a = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    F = np.concatenate([np.stack([a, a + n + 1, a + 1], 1), np.stack([a + 1, a + n + 1, a + n + 2], 1)])
    mat = np.tile([0.0, 0.0, 0.0, np.log(0.4 / 0.6), -12.0, 12.0], (len(V), 1))  # sigmoid: 0.5, 0.4, ~0, ~1
    scene = Scene.from_arrays(V, F, material=mat, alpha=np.full((len(V), 1), 30.0),
                              lights=[PointLight([0.0, 2.0, -2.5], np.full(3, 10.0))])
    cam = Camera.look_at([0.0, 2.0, 2.5], [0, 0, 0], [0, 1, 0], 50.0, 128, 128)
    img = render(scene, cam, RenderSettings(K=4, sigma=None, normals="vertex", background=(0, 0, 0)), device).image
    for (y, x), want in MITSUBA_PLANE.items():
        assert img[y, x, 0] == pytest.approx(want, rel=5e-3), (y, x)


@pytest.mark.parametrize("prune,sigma", [(True, 0.8), (False, None)])
def test_fragment_cache_renders_bit_for_bit(device, rng, prune, sigma):
    """``render(frag_cache=...)`` (the metallic trial's renders: materials and lights change, the geometry does not):
    a view whose fragments it holds renders with them, and the image and every gradient equal an uncached render's
    bit for bit, after the materials and lights moved too; a change of the positions or opacities empties it; a
    budget of 0 bytes keeps nothing and changes nothing."""
    from triplet_cl.render import FragmentCache

    scene = small_scene(rng, "cook_torrance", mesh=True)
    scene.alpha.data[...] = 4.0  # nearly opaque: pruning drops the fragments behind
    settings = RenderSettings(K=6, sigma=sigma, background=(0.3, 0.5, 0.9), prune=prune, soft_edges="silhouette",
                              normals="vertex")
    views = [cam(), Camera.look_at([-0.6, 0.5, 2.8], [0, 0, 0], [0, 1, 0], 45, W, H)]
    w = rng.standard_normal((H, W, 4))

    def run(cache, c=views[0]):
        scene.zero_grad()
        r = render(scene, c, settings, device, frag_cache=cache)
        g = r.backward(w[..., :3], w[..., 3])
        return r.rgba.data.copy(), {k: None if v is None else np.array(v) for k, v in g.items()}, r.info["frags"].P

    cache = FragmentCache()
    for step in range(3):
        for c in views:
            want, g_want, P = run(None, c)
            got, g_got, P2 = run(cache, c)
            assert P == P2
            np.testing.assert_array_equal(got, want)
            for k in g_want:
                np.testing.assert_array_equal(g_got[k], g_want[k], err_msg=k)
        assert len(cache.entries) == 2 and cache.hits == 2 * step
        scene.material.data[...] += 0.1 * rng.standard_normal(scene.material.data.shape)  # the trial's steps
        scene.light_params.data[...] *= 1.05
    scene.V.data[0] += 0.01  # the geometry moved: rasterized again
    want, g_want, _ = run(None)
    got, g_got, _ = run(cache)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(g_got["V"], g_want["V"])
    assert len(cache.entries) == 1
    scene.alpha.data[3] -= 1.0
    run(cache)
    assert len(cache.entries) == 1 and cache.hits == 4
    other = RenderSettings(K=3, sigma=sigma, background=(0.3, 0.5, 0.9), prune=prune, soft_edges="silhouette",
                           normals="vertex")  # another setting, the same view and geometry: its own fragments
    scene.zero_grad()
    want = render(scene, views[0], other, device).rgba.data.copy()
    scene.zero_grad()
    got = render(scene, views[0], other, device, frag_cache=cache).rgba.data.copy()
    np.testing.assert_array_equal(got, want)
    assert len(cache.entries) == 2 and cache.hits == 4
    empty = FragmentCache(max_bytes=0)
    got, g_got, _ = run(empty)
    want, g_want, _ = run(None)
    np.testing.assert_array_equal(got, want)
    assert not empty.entries


@pytest.mark.parametrize("mesh", [True, False])
def test_held_positions_skip_the_geometric_adjoint(device, rng, mesh):
    """Positions (and opacities) that do not require a gradient (the metallic trial holds them): the backward skips
    the geometry's adjoint (fragments_backward without GEOMETRY, no normals' adjoint), and every other gradient is
    the full backward's bit for bit."""
    scene = small_scene(rng, "cook_torrance", mesh=mesh)
    settings = RenderSettings(K=6, sigma=0.8, background=(0.3, 0.5, 0.9), normals="vertex" if mesh else "face")
    w = rng.standard_normal((H, W, 4))
    scene.zero_grad()
    full = render(scene, cam(), settings, device).backward(w[..., :3], w[..., 3])
    scene.V.requires_grad = scene.alpha.requires_grad = False
    try:
        scene.zero_grad()
        held = render(scene, cam(), settings, device).backward(w[..., :3], w[..., 3])
    finally:
        scene.V.requires_grad = scene.alpha.requires_grad = True
    assert held["V"] is None and held["alpha"] is None and np.abs(full["V"]).max() > 0
    for k in ("material", "light_params"):
        np.testing.assert_array_equal(held[k], full[k], err_msg=k)
