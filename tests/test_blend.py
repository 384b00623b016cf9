"""The fused per-vertex raster path (ops/blend.py, kernels_cl/blend.cl).

Forward against the numpy reference (raster_ref → interpolate_ref → window → composite_ref) and
against the generic chain; the adjoint against the numpy reference through a random cotangent,
against the generic chain (itself checked by tests/test_raster.py), and against float64 central
differences of the fused kernels themselves (perturbations that do not change coverage; checked).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.reference import raster as ref
from tests.test_raster import cam, soup
from triplet_cl.camera import Camera
from triplet_cl.ops.blend import raster_blend, raster_blend_backward
from triplet_cl.ops.composite import composite, composite_backward
from triplet_cl.ops.interpolate import interpolate
from triplet_cl.ops.mesh import DeviceMesh
from triplet_cl.ops.raster import fragments_backward, project, project_backward, rasterize

W, H = 23, 19


def scene(rng, M=40, size=0.35, C=3):
    V, F = soup(rng, M=M, size=size)
    attr = np.concatenate([rng.uniform(0, 1, (len(V), C)), rng.uniform(0.2, 0.8, (len(V), 1))], 1)
    return V, F, attr


def blend(device, V, F, attr, K, camera=None, real=np.float64, **kw):
    camera = camera or cam()
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, np.asarray(V, real), camera)
    b = raster_blend(device, vs, mesh, np.asarray(attr, real), camera.width, camera.height, K, **kw)
    return camera, b


def list_faces(b):
    """[H, W, K] face of each composited fragment (-1 beyond n_contrib). Entry ids are not stable
    across runs (the binning fills a tile's entries in atomic order), the faces are."""
    e = b.entries()
    return np.where(e >= 0, b.binning.entry_face.get()[np.maximum(e, 0)], -1)


def reference_forward(V, F, attr, K, camera, bg, sigma=None, t_min=0.0):
    """Numpy: raster_ref → interpolate_ref → window (fragment_geometry_ref) → composite_ref."""
    vs = ref.project_ref(V, np.asarray(_cam16(camera)))
    face, bary, _, count = ref.raster_ref(vs, F, camera.width, camera.height, K)
    fa = ref.interpolate_ref(attr, F, face, bary)
    feat, a = fa[..., :-1], fa[..., -1]
    win = None
    if sigma is not None:
        win = ref.fragment_geometry_ref(vs, F, face, sigma=sigma)["win"]
        a = a * win
    img, trans, ncon = ref.composite_ref(feat, a, count, bg, t_min)
    return dict(img=img, trans=trans, ncon=ncon, count=count, face=face, bary=bary, feat=feat, alpha=a,
                ab=fa[..., -1], win=win)


def _cam16(camera):
    from triplet_cl.ops.raster import camera_params

    return camera_params(camera, np.float64)


def generic_chain(device, V, F, attr, K, camera, bg, sigma, t_min, v_img=None, v_acc=None):
    """The same job through the generic ops (rasterize → interpolate → coverage → composite)."""
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, V, camera)
    fr = rasterize(device, vs, mesh, camera.width, camera.height, K, sigma=sigma)
    fa = interpolate(device, attr, fr).get()
    feat, a = np.ascontiguousarray(fa[:, :-1]), np.ascontiguousarray(fa[:, -1])
    img, trans, ncon = composite(device, fr, feat, a, bg, win=fr.win, t_min=t_min)
    out = {"img": img.get(), "trans": trans.get(), "ncon": ncon.get(), "count": fr.count.get()}
    if v_img is not None:
        v_feat, v_a, v_win, _ = composite_backward(device, fr, feat, a, bg, ncon, trans, v_img, v_acc=v_acc,
                                                   win=fr.win)
        v_fa = np.concatenate([v_feat.get(), v_a.get()[:, None]], 1)
        v_attr, v_vs, v_sig = fragments_backward(device, fr, attr, v_fa, v_win=v_win, sigma=sigma or 0.0)
        out.update(v_attr=v_attr.get(), v_V=project_backward(device, V, camera, v_vs).get(), v_sigma=v_sig)
    return out


# ------------------------------------------------------------------------------------------------ forward


@pytest.mark.parametrize("variant", ["pixel", "rows16"])
@pytest.mark.parametrize("K,sigma,t_min", [(1, None, 0.0), (6, 0.9, 0.0), (40, 0.9, 0.3), (8, None, 0.5)])
def test_forward_matches_reference_float64(device64, rng, variant, K, sigma, t_min):
    V, F, attr = scene(rng)
    bg = np.array([0.2, 0.7, 1.0])
    c, b = blend(device64, V, F, attr, K, bg=bg, sigma=sigma, t_min=t_min, variant=variant)
    r = reference_forward(V, F, attr, K, c, bg, sigma, t_min)
    assert r["count"].sum() > 100
    np.testing.assert_array_equal(b.count.get(), r["count"])
    np.testing.assert_array_equal(b.n_contrib.get(), r["ncon"])
    np.testing.assert_allclose(b.image.get(), r["img"], rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(b.trans.get(), r["trans"], rtol=1e-11, atol=1e-12)
    # the scratch lists the adjoint reads: the composited fragments' faces, nearest first
    ent, ef = b.entries(), b.binning.entry_face.get()
    faces = np.where(ent >= 0, ef[np.maximum(ent, 0)], -1)
    np.testing.assert_array_equal(faces, np.where(np.arange(K) < r["ncon"][..., None], r["face"], -1))
    if t_min > 0:
        assert (r["ncon"] < r["count"]).any(), "the early stop must be exercised"


def test_forward_equals_generic_chain_float32(device, rng):
    V, F, attr = scene(rng, M=300, size=0.3)
    V, attr = V.astype(np.float32), attr.astype(np.float32)
    c = cam(61, 45)
    bg = np.array([1.0, 0.5, 0.0], np.float32)
    _, b = blend(device, V, F, attr, 30, camera=c, real=np.float32, bg=bg, sigma=1.0)
    g = generic_chain(device, V, F, attr, 30, c, bg, 1.0, 1e-4)
    np.testing.assert_array_equal(b.count.get(), g["count"])
    np.testing.assert_array_equal(b.n_contrib.get(), g["ncon"])
    np.testing.assert_allclose(b.image.get(), g["img"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.trans.get(), g["trans"], rtol=1e-5, atol=1e-6)


def test_variants_identical(device, rng):
    """pixel (GPU-shaped, scalar per pixel) and rows16 (CPU-shaped, 16 pixels in vector lanes) do the
    same operations in the same order on identical lists: without a window the images are
    bit-identical. With a window the only difference is exp(): the runtime's vector exp may round
    differently from its scalar exp (1 ulp on PoCL), so the images agree to a few ulp."""
    V, F, attr = scene(rng, M=200, size=0.3, C=4)
    c = cam(37, 29)  # partial tiles on both axes
    for sigma in (None, 2.0):
        outs = []
        for variant in ("pixel", "rows16"):
            _, b = blend(device, V, F, attr, 7, camera=c, real=np.float32, bg=0.3, sigma=sigma, variant=variant)
            outs.append((b.count.get(), b.n_contrib.get(), list_faces(b), b.image.get(), b.trans.get()))
        (c0, n0, e0, i0, t0), (c1, n1, e1, i1, t1) = outs
        np.testing.assert_array_equal(c0, c1)
        np.testing.assert_array_equal(n0, n1)
        np.testing.assert_array_equal(e0, e1)
        if sigma is None:
            np.testing.assert_array_equal(i0, i1)
            np.testing.assert_array_equal(t0, t1)
        else:
            np.testing.assert_allclose(i0, i1, rtol=4e-7, atol=1e-7)
            np.testing.assert_allclose(t0, t1, rtol=4e-7, atol=1e-7)


# ------------------------------------------------------------------------------------------------ adjoint


SCHEDULES = [("pixel", "auto"), ("rows16", "rows"), ("rows16", "queue"), ("rows16", "auto")]


@pytest.mark.parametrize("variant,schedule", SCHEDULES)
def test_vjp_matches_reference(device64, rng, variant, schedule):
    """v_attr of the fused adjoint (scalar per pixel, or 16 pixels in vector lanes) against the numpy
    chain rule (composite_vjp_ref → interpolate_vjp_ref)."""
    V, F, attr = scene(rng, C=2)
    bg = np.array([0.4, 0.9])
    K, sigma = 6, 0.7
    c, b = blend(device64, V, F, attr, K, bg=bg, sigma=sigma, t_min=0.0, variant=variant)
    v_img = rng.standard_normal((H, W, 2))
    v_acc = rng.standard_normal((H, W))
    v_attr, _, _ = raster_blend_backward(device64, b, v_img, v_acc, schedule=schedule)
    r = reference_forward(V, F, attr, K, c, bg, sigma)
    v_feat, v_a = ref.composite_vjp_ref(r["feat"], r["alpha"], r["count"], bg, v_img, v_acc)
    v_fa = np.concatenate([v_feat, (v_a * r["win"])[..., None]], -1)  # a = ab · win
    expect, _ = ref.interpolate_vjp_ref(attr, F, r["face"], r["bary"], v_fa)
    np.testing.assert_allclose(v_attr.get(), expect, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("variant,schedule", SCHEDULES)
@pytest.mark.parametrize("sigma,t_min", [(0.8, 1e-4), (None, 0.2)])
def test_backward_equals_generic_chain(device64, rng, sigma, t_min, variant, schedule):
    V, F, attr = scene(rng, M=60)
    bg = np.array([0.2, 0.7, 1.0])
    K = 9
    c = cam()
    v_img, v_acc = rng.standard_normal((H, W, 3)), rng.standard_normal((H, W))
    _, b = blend(device64, V, F, attr, K, camera=c, bg=bg, sigma=sigma, t_min=t_min, variant=variant)
    v_attr, v_vs, v_sig = raster_blend_backward(device64, b, v_img, v_acc, schedule=schedule)
    g = generic_chain(device64, V, F, attr, K, c, bg, sigma, t_min, v_img, v_acc)
    np.testing.assert_allclose(v_attr.get(), g["v_attr"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(project_backward(device64, V, c, v_vs).get(), g["v_V"], rtol=1e-9, atol=1e-11)
    assert v_sig == pytest.approx(g["v_sigma"], rel=1e-10, abs=1e-14)
    assert np.abs(g["v_V"]).sum() > 0


def wavy_grid(rng, n=7):
    """A connected mesh (shared vertices: the per-vertex gather of face-corner adjoints), two layers
    so that pixels blend several fragments, and one unused vertex."""
    u = np.linspace(-0.9, 0.9, n)
    X, Y = np.meshgrid(u, u)
    V, F = [], []
    for layer, z in enumerate((0.3, -0.2)):
        P = np.stack([X + 0.05 * layer, Y, z + 0.15 * np.sin(3 * X + layer) * np.cos(2 * Y)], -1).reshape(-1, 3)
        o = layer * n * n
        idx = np.arange(n * n).reshape(n, n) + o
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        F += [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
        V.append(P)
    V = np.concatenate(V + [np.array([[5.0, 5.0, 5.0]])])
    F = np.concatenate(F)
    attr = np.concatenate([rng.uniform(0, 1, (len(V), 3)), rng.uniform(0.3, 0.7, (len(V), 1))], 1)
    return V, F, attr


@pytest.mark.parametrize("variant,schedule", [("pixel", "auto"), ("rows16", "queue")])
def test_backward_shared_vertices_equals_generic_chain(device64, rng, variant, schedule):
    V, F, attr = wavy_grid(rng)
    bg = np.array([0.2, 0.7, 1.0])
    K, sigma, c = 5, 0.8, cam()
    v_img, v_acc = rng.standard_normal((H, W, 3)), rng.standard_normal((H, W))
    _, b = blend(device64, V, F, attr, K, camera=c, bg=bg, sigma=sigma, t_min=1e-4, variant=variant)
    assert not b.mesh.corners_are_vertices
    assert (b.count.get() >= 2).sum() > 50
    v_attr, v_vs, v_sig = raster_blend_backward(device64, b, v_img, v_acc, schedule=schedule)
    g = generic_chain(device64, V, F, attr, K, c, bg, sigma, 1e-4, v_img, v_acc)
    np.testing.assert_allclose(v_attr.get(), g["v_attr"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(project_backward(device64, V, c, v_vs).get(), g["v_V"], rtol=1e-9, atol=1e-11)
    assert v_sig == pytest.approx(g["v_sigma"], rel=1e-10, abs=1e-14)
    assert np.abs(v_attr.get()[-1]).max() == 0 and np.abs(g["v_V"]).sum() > 0


def test_central_differences(device64, rng):
    """d(sum(image · v) + sum(acc · v_acc)) / d{positions, features, opacity, sigma}, float64."""
    V, F, attr = scene(rng, M=12, size=0.35)
    c = cam(17, 13)
    sigma, K, bg = 0.9, 6, np.array([0.2, 0.7, 1.0])
    v = rng.standard_normal((13, 17, 3))
    va = rng.standard_normal((13, 17))

    def run(Vx=V, ax=attr, s=sigma):
        _, b = blend(device64, Vx, F, ax, K, camera=c, bg=bg, sigma=s, t_min=0.0)
        loss = (b.image.get() * v).sum() + ((1 - b.trans.get()) * va).sum()
        return loss, b

    _, b0 = run()
    cnt0 = b0.count.get()
    assert cnt0.sum() > 40
    v_attr, v_vs, v_sig = raster_blend_backward(device64, b0, v, va)
    grads = {"V": project_backward(device64, V, c, v_vs).get(), "attr": v_attr.get()}
    lists0 = list_faces(b0)
    eps = 1e-6
    checked = 0
    for name, x in (("V", V), ("attr", attr)):
        num = np.zeros_like(x)
        mask = np.ones(x.shape, bool)
        for idx in np.ndindex(*x.shape):
            xp, xm = x.copy(), x.copy()
            xp[idx] += eps
            xm[idx] -= eps
            kw = "Vx" if name == "V" else "ax"
            (lp, bp), (lm, bm) = run(**{kw: xp}), run(**{kw: xm})
            # stable: the same fragments in the same order (entries are per (tile, face): same lists)
            same = all(np.array_equal(bb.count.get(), cnt0) and np.array_equal(list_faces(bb), lists0)
                       for bb in (bp, bm))
            mask[idx] = same
            num[idx] = (lp - lm) / (2 * eps)
        assert mask.mean() > 0.95, f"{name}: perturbations must rarely change coverage"
        np.testing.assert_allclose(grads[name][mask], num[mask], rtol=1e-5, atol=1e-6, err_msg=name)
        checked += mask.sum()
    (lp, _), (lm, _) = run(s=sigma + eps), run(s=sigma - eps)
    assert v_sig == pytest.approx((lp - lm) / (2 * eps), rel=1e-5)
    assert np.abs(grads["V"]).sum() > 0 and checked > 100


def test_backward_deterministic(device, rng):
    V, F, attr = scene(rng, M=300, size=0.3)
    c = cam(40, 32)
    v = rng.standard_normal((32, 40, 3)).astype(np.float32)
    res = []
    for _ in range(2):
        _, b = blend(device, V, F, attr, 12, camera=c, real=np.float32, sigma=1.0)
        va, vvs, vs_ = raster_blend_backward(device, b, v)
        res.append((va.get(), vvs.get(), vs_))
    np.testing.assert_array_equal(res[0][0], res[1][0])
    np.testing.assert_array_equal(res[0][1], res[1][1])
    assert res[0][2] == res[1][2]


# ------------------------------------------------------------------------------------------------ edge cases


def test_no_faces_and_empty_view(device):
    c = cam()
    _, b = blend(device, np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 2)), 4, camera=c,
                 real=np.float32, bg=0.25)
    np.testing.assert_array_equal(b.image.get(), 0.25)
    np.testing.assert_array_equal(b.trans.get(), 1.0)
    v_attr, v_vs, v_sig = raster_blend_backward(device, b, np.ones((H, W, 1), np.float32))
    assert v_attr.shape == (0, 2) and v_vs.shape == (0, 3) and v_sig == 0.0
    # faces that are all off screen: nothing drawn, zero gradients
    rng = np.random.default_rng(3)
    V, F, attr = scene(rng, M=10)
    V = V + [50.0, 0, 0]
    _, b = blend(device, V, F, attr, 4, camera=c, real=np.float32, bg=0.0, sigma=1.0)
    assert (b.count.get() == 0).all()
    v_attr, v_vs, _ = raster_blend_backward(device, b, np.ones((H, W, 3), np.float32))
    assert not v_attr.get().any() and not v_vs.get().any()


def test_near_plane_whole_screen_degenerate_and_large_K(device64):
    c = Camera.look_at([0, 0, 2], [0, 0, 0], [0, 1, 0], 60, W, H, near=0.1)
    big = np.array([[-50, -50, 0], [50, -50, 0], [0, 50, 0]], float)  # covers the whole screen
    behind = big + [0, 0, 3.0]  # behind the camera
    crossing = np.array([[-0.3, -0.3, 1.0], [0.3, -0.3, 1.0], [0, 0.3, 2.5]])  # one vertex behind
    degenerate = np.array([[0, 0, 0.5], [0, 0, 0.5], [0.5, 0.2, 0.5]])
    V = np.concatenate([big, behind, crossing, degenerate])
    F = np.arange(12).reshape(4, 3)
    attr = np.concatenate([np.tile([[0.1, 0.6, 0.9]], (12, 1)), np.full((12, 1), 0.5)], 1)
    bg = np.array([1.0, 0.0, 0.0])
    _, b = blend(device64, V, F, attr, 200, camera=c, bg=bg)  # K far above the faces at any pixel
    assert (b.count.get() == 1).all(), "only the whole-screen face is drawn"
    np.testing.assert_allclose(b.image.get(), np.broadcast_to(0.5 * np.array([0.1, 0.6, 0.9]) + 0.5 * bg, (H, W, 3)),
                               rtol=1e-10)  # a constant interpolated by barycentrics that sum to 1 up to rounding
    v_attr, _, _ = raster_blend_backward(device64, b, np.ones((H, W, 3)))
    assert np.abs(v_attr.get()[3:]).max() == 0, "culled faces get no gradient"
    assert np.abs(v_attr.get()[:3]).sum() > 0


# ------------------------------------------------------------------------------------------------ validation


def test_validation_errors(device, rng):
    V, F, attr = scene(rng, M=5)
    c = cam()
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, V.astype(np.float32), c)
    A = attr.astype(np.float32)
    with pytest.raises(ValueError, match="attr must have shape"):
        raster_blend(device, vs, mesh, A[:-1], W, H, 4)
    with pytest.raises(ValueError, match="C \\+ 1 columns"):
        raster_blend(device, vs, mesh, A[:, :1], W, H, 4)
    bad = A.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="attr must be finite"):
        raster_blend(device, vs, mesh, bad, W, H, 4)
    with pytest.raises(ValueError, match="bg must have shape"):
        raster_blend(device, vs, mesh, A, W, H, 4, bg=[1, 2])
    with pytest.raises(ValueError, match="K must be in"):
        raster_blend(device, vs, mesh, A, W, H, 0)
    with pytest.raises(ValueError, match="variant"):
        raster_blend(device, vs, mesh, A, W, H, 4, variant="warp")
    with pytest.raises(ValueError, match="rows16"):
        raster_blend(device, vs, mesh, A, W, H, 300, variant="rows16")
    A6 = np.concatenate([A[:, :1]] * 5 + [A[:, -1:]], 1)  # C = 5
    with pytest.raises(ValueError, match="C <= 4"):
        raster_blend(device, vs, mesh, A6, W, H, 4, variant="rows16")
    assert raster_blend(device, vs, mesh, A6, W, H, 4).variant == "pixel"
    with pytest.raises(ValueError, match="sigma"):
        raster_blend(device, vs, mesh, A, W, H, 4, sigma=-1.0)
    with pytest.raises(ValueError, match="t_min"):
        raster_blend(device, vs, mesh, A, W, H, 4, t_min=1.0)
    with pytest.raises(ValueError, match="vs must have shape"):
        raster_blend(device, np.zeros((3, 3), np.float32), mesh, A, W, H, 4)
    with pytest.raises(ValueError, match="attr must have dtype"):
        import pyopencl.array as cla

        raster_blend(device, vs, mesh, cla.to_device(device.queue, attr), W, H, 4)
    b = raster_blend(device, vs, mesh, A, W, H, 4)
    with pytest.raises(ValueError, match="v_image must have shape"):
        raster_blend_backward(device, b, np.zeros((H, W, 2), np.float32))
    with pytest.raises(ValueError, match="v_alpha must have shape"):
        raster_blend_backward(device, b, np.zeros((H, W, 3), np.float32), np.zeros((H, W + 1)))
    with pytest.raises(ValueError, match="schedule must be one of"):
        raster_blend_backward(device, b, np.zeros((H, W, 3), np.float32), schedule="lanes")
