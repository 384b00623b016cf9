"""Rasterization chain: project → bin → K-nearest raster → interpolate → coverage → composite.

Each op: forward against the numpy reference (tests/reference/raster.py), adjoint against the
reference through a random cotangent, and the whole chain against float64 central differences of
the kernels themselves (perturbations small enough not to change coverage; checked).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import fd_grad
from tests.reference import raster as ref
from triplet_cl.camera import Camera
from triplet_cl.ops.composite import composite, composite_backward, coverage
from triplet_cl.ops.interpolate import interpolate, interpolate_backward
from triplet_cl.ops.mesh import DeviceMesh
from triplet_cl.ops.raster import (
    camera_params,
    fragments_backward,
    project,
    project_backward,
    raster_backward,
    rasterize,
    read_fragments,
)

W, H = 23, 19


def soup(rng, M=40, spread=0.6, size=0.25, z0=0.0):
    c = rng.uniform(-spread, spread, (M, 1, 3)) + np.array([0, 0, z0])
    V = (c + rng.normal(0, size, (M, 3, 3))).reshape(-1, 3)
    return V, np.arange(3 * M).reshape(M, 3)


def cam(w=W, h=H):
    return Camera.look_at([0.3, -0.2, 3.0], [0, 0, 0], [0, 1, 0], 45, w, h)


def run_raster(device, V, F, K, real=np.float64, camera=None, **kw):
    camera = camera or cam()
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, np.asarray(V, real), camera)
    fr = rasterize(device, vs, mesh, camera.width, camera.height, K, **kw)
    return camera, mesh, vs, fr


# ------------------------------------------------------------------------------------------------ project


def test_project_forward_and_adjoint(device64, rng):
    V, _ = soup(rng)
    c = cam()
    vs = project(device64, V, c).get()
    np.testing.assert_allclose(vs, ref.project_ref(V, camera_params(c, np.float64)), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(vs, c.project_points(V), rtol=1e-12, atol=1e-9)
    v = rng.standard_normal(vs.shape)
    v_V, v_w2c = project_backward(device64, V, c, v, pose_grad=True)
    eps = 1e-6
    num = fd_grad(lambda x: (ref.project_ref(x, camera_params(c, np.float64)) * v).sum(), V, eps)
    np.testing.assert_allclose(v_V.get(), num, rtol=1e-6, atol=1e-6)
    # pose gradient: perturb the 3x4 block of w2c
    for i, j in [(0, 0), (1, 2), (2, 1), (0, 3), (2, 3)]:
        Wp, Wm = c.w2c.copy(), c.w2c.copy()
        Wp[i, j] += eps
        Wm[i, j] -= eps
        cp = camera_params(c, np.float64)
        cm = cp.copy()
        cp[(i * 3 + j) if j < 3 else 9 + i] += eps
        cm[(i * 3 + j) if j < 3 else 9 + i] -= eps
        fd = ((ref.project_ref(V, cp) - ref.project_ref(V, cm)) * v).sum() / (2 * eps)
        assert v_w2c[i, j] == pytest.approx(fd, rel=1e-6, abs=1e-6)


def test_project_float32_matches(device, rng):
    V, _ = soup(rng)
    c = cam()
    vs = project(device, V.astype(np.float32), c).get()
    assert vs.dtype == np.float32
    np.testing.assert_allclose(vs, c.project_points(V), rtol=1e-5, atol=1e-3)


# ------------------------------------------------------------------------------------------------ raster


@pytest.mark.parametrize("K", [1, 4, 30])
def test_raster_forward_matches_reference_float64(device64, rng, K):
    V, F = soup(rng, M=60)
    c, mesh, vs, fr = run_raster(device64, V, F, K)
    h = read_fragments(fr)
    face, bary, depth, count = ref.raster_ref(vs.get(), F, W, H, K)
    assert h["count"].sum() > 50, "the scene must produce fragments"
    np.testing.assert_array_equal(h["count"], count)
    np.testing.assert_array_equal(h["face"], face)
    np.testing.assert_allclose(h["bary"], bary, atol=1e-9)
    np.testing.assert_allclose(h["depth"], depth, rtol=1e-12)
    if K == 30:
        assert count.max() < K, "K larger than the faces at every pixel: slots stay empty"
        assert (h["face"][..., count.max():] == -1).all()


def test_packed_layout(device, rng):
    """Fragments are packed pixel-major: pixel p's fragments are rows off[p] .. off[p] + count[p] of
    every per-fragment array (P = sum of the counts rows, no padding); to_hwk / from_hwk convert
    to and from the padded [H, W, K] view; per-fragment ops return [P, C]."""
    V, F = soup(rng, M=200, spread=0.6, size=0.3)
    c = cam(23, 17)
    mesh = DeviceMesh(device, F, len(V))
    fr = rasterize(device, project(device, V.astype(np.float32), c), mesh, 23, 17, 9, sigma=0.7)
    count = fr.count.get().reshape(-1)
    off = fr.off.get()
    assert fr.P == count.sum() > 100 and off[0] == 0 and off[-1] == fr.P
    np.testing.assert_array_equal(np.diff(off), count)
    for a in (fr.face, fr.entry, fr.depth, fr.win):
        assert a.shape == (fr.P,)
    assert fr.bary.shape == (fr.P, 2)
    h = read_fragments(fr)
    face, depth = fr.face.get(), fr.depth.get()
    for p in rng.choice(np.nonzero(count)[0], 20, replace=False):
        y, x = divmod(int(p), 23)
        rows = slice(off[p], off[p] + count[p])
        np.testing.assert_array_equal(face[rows], h["face"][y, x, :count[p]])
        assert (np.diff(depth[rows]) >= 0).all()  # nearest first
    assert (h["face"][np.arange(9)[None, None, :] >= fr.count.get()[..., None]] == -1).all()
    x = rng.standard_normal((fr.P, 3))
    np.testing.assert_array_equal(fr.from_hwk(fr.to_hwk(x)), x)
    assert interpolate(device, rng.standard_normal((len(V), 5)).astype(np.float32), fr).shape == (fr.P, 5)
    with pytest.raises(ValueError, match="rows"):
        fr.to_hwk(x[:-1])


@pytest.mark.parametrize("K", [1, 7, 40, 150, 300])
def test_raster_variants_identical(device, rng, K):
    """The GPU-shaped (per pixel) and CPU-shaped (8-pixel rows; 2-row vector lanes) kernels give the
    same fragments, including at image borders that cut a tile (37 x 21 = 4 tiles + 5 columns,
    2 tiles + 5 rows: the last 2-row pair of rows16 has one row outside the image)."""
    V, F = soup(rng, M=600, spread=0.6, size=0.3)
    c = cam(37, 21)
    outs = []
    variants = ("pixel", "rows", "rows16") if K <= 256 else ("pixel", "rows")
    for variant in variants:
        mesh = DeviceMesh(device, F, len(V))
        vs = project(device, V.astype(np.float32), c)
        fr = rasterize(device, vs, mesh, 37, 21, K, variant=variant, sigma=0.7)
        h = read_fragments(fr)
        # entry ids depend on the binning's atomic order: compare the face each entry stands for
        h["entry"] = np.where(h["entry"] >= 0, fr.entry_face.get()[np.maximum(h["entry"], 0)], -1)
        h["win"] = fr.to_hwk(fr.win)
        outs.append(h)
    assert outs[0]["count"].sum() > 500
    for o in outs[1:]:
        for k in outs[0]:
            np.testing.assert_array_equal(outs[0][k], o[k], err_msg=k)
    with pytest.raises(ValueError, match="variant"):
        rasterize(device, vs, mesh, 37, 21, K, variant="simd")
    with pytest.raises(ValueError, match="rows16"):
        rasterize(device, vs, mesh, 37, 21, 257, variant="rows16")


def test_raster_forward_float32_agrees(device, rng):
    V, F = soup(rng, M=60)
    c, mesh, vs, fr = run_raster(device, V, F, 8, real=np.float32)
    h = read_fragments(fr)
    face, bary, depth, count = ref.raster_ref(vs.get(), F, W, H, 8)
    # float32 edge functions may flip pixels whose centre lies within ~1e-5 px of an edge
    assert (h["face"] != face).any(axis=-1).mean() < 0.01
    same = (h["face"] == face) & (face >= 0)
    np.testing.assert_allclose(h["bary"][same], bary[same], atol=2e-4)
    np.testing.assert_allclose(h["depth"][same], depth[same], rtol=1e-5)


def test_raster_many_tiles_and_large_K(device, rng):
    """Dense scene spanning many tiles, K=150 (the method's warm-up setting)."""
    V, F = soup(rng, M=2000, spread=0.5, size=0.4)
    c = cam(70, 45)
    _, _, vs, fr = run_raster(device, V, F, 150, real=np.float32, camera=c)
    h = read_fragments(fr)
    face, _, depth, count = ref.raster_ref(vs.get(), F, 70, 45, 150)
    assert count.max() > 30
    assert (h["count"] != count).mean() < 0.01
    ok = h["count"] == count
    np.testing.assert_array_equal((h["face"] >= 0)[ok], (face >= 0)[ok])


def test_binning_tiles_and_rows_of_each_face(device64, rng):
    """Each face is listed in the tiles of its pixel bounding box, with the tile rows of that box
    (entry_rows: the list builders' cheap per-row rejection)."""
    from triplet_cl.ops.raster import TILE, bin_faces

    V, F = soup(rng, M=300, spread=0.7, size=0.2)
    c = cam(53, 37)
    vs = project(device64, np.asarray(V, np.float64), c)
    bn = bin_faces(device64, vs, DeviceMesh(device64, F, len(V)), 53, 37)
    to, ef, er = bn.tile_off.get(), bn.entry_face.get(), bn.entry_rows.get()
    uv = vs.get()[:, :2][F]  # [M, 3, 2]
    x0 = np.ceil(np.maximum(uv[..., 0].min(1) - 0.5, 0)).astype(int)
    x1 = np.floor(np.minimum(uv[..., 0].max(1) - 0.5, 52)).astype(int)
    y0 = np.ceil(np.maximum(uv[..., 1].min(1) - 0.5, 0)).astype(int)
    y1 = np.floor(np.minimum(uv[..., 1].max(1) - 0.5, 36)).astype(int)
    expect = {}
    for f in range(len(F)):
        if x0[f] > x1[f] or y0[f] > y1[f]:
            continue
        for ty in range(y0[f] // TILE, y1[f] // TILE + 1):
            rows = sum(1 << r for r in range(TILE) if y0[f] <= ty * TILE + r <= y1[f])
            for tx in range(x0[f] // TILE, x1[f] // TILE + 1):
                expect[(ty * bn.tiles_x + tx, f)] = rows
    got = {}
    for t in range(bn.num_tiles):
        for e in range(to[t], to[t + 1]):
            got[(t, int(ef[e]))] = int(er[e]) & 0xFF
    assert len(expect) > 300 and got == expect
    # bits 8+: the coverage estimate, the face's area (quarter pixels) shared by its tiles
    cover = er[:bn.num_entries] >> 8
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area4 = 2 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ntiles = np.diff(bn.face_off.get())
    np.testing.assert_allclose(cover, np.minimum(area4[ef] / ntiles[ef], 256), atol=1.01)
    # entry_order: a permutation of each tile's entries; nearest vertex first (up to the depth
    # buckets) where the estimated fragments per pixel exceed K / 2
    K = 2
    bnk = bin_faces(device64, vs, DeviceMesh(device64, F, len(V)), 53, 37, K=K)
    order, inv_z, cov = bnk.entry_order.get(), bnk.entry_setup.get()[:, 6:9].max(1), bnk.entry_rows.get() >> 8
    kinds = set()
    for t in range(bnk.num_tiles):
        o = order[to[t]:to[t + 1]]
        np.testing.assert_array_equal(np.sort(o), np.arange(to[t], to[t + 1]))
        if len(o) > 1 and cov[o].sum() > 2 * K * 64 and np.ptp(inv_z[o]) > 0:
            bucket = np.floor((inv_z[o].max() - inv_z[o]) * (63 / np.ptp(inv_z[o])))  # the kernel's rounding
            assert np.all(np.diff(bucket) >= 0)
            kinds.add("depth")
        else:
            np.testing.assert_array_equal(o, np.arange(to[t], to[t + 1]))
            kinds.add("binning")
    assert kinds == {"depth", "binning"}


def test_raster_empty_and_degenerate(device):
    c = cam()
    # no faces at all
    _, _, _, fr = run_raster(device, np.zeros((0, 3)), np.zeros((0, 3), np.int32), 4, camera=c)
    h = read_fragments(fr)
    assert (h["count"] == 0).all() and (h["face"] == -1).all()
    # degenerate faces: repeated vertex, collinear vertices
    V = np.array([[0, 0, 0], [0, 0, 0], [0.5, 0.2, 0], [-0.5, -0.5, 0], [0, 0, 0], [0.5, 0.5, 0]], float)
    _, _, _, fr = run_raster(device, V, np.array([[0, 1, 2], [3, 4, 5]]), 4, camera=c)
    assert (read_fragments(fr)["count"] == 0).all()


def test_raster_near_plane_culls_and_behind_camera(device):
    c = Camera.look_at([0, 0, 2], [0, 0, 0], [0, 1, 0], 60, W, H, near=0.1)
    big = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], float)
    behind = big + [0, 0, 3.0]  # z = 3 in world = 1 unit behind the camera
    crossing = np.array([[-0.3, -0.3, 1.0], [0.3, -0.3, 1.0], [0, 0.3, 2.5]])  # one vertex behind
    V = np.concatenate([big, behind, crossing])
    F = np.arange(9).reshape(3, 3)
    _, _, _, fr = run_raster(device, V, F, 4, camera=c)
    h = read_fragments(fr)
    assert set(np.unique(h["face"])) <= {-1, 0}, "only the face in front is drawn"
    assert (h["face"] == 0).sum() > 20


def test_raster_face_covering_whole_screen_and_culling(device):
    c = Camera.look_at([0, 0, 2], [0, 0, 0], [0, 1, 0], 60, W, H)
    V = np.array([[-50, -50, 0], [50, -50, 0], [0, 50, 0]], float)
    _, _, vs, fr = run_raster(device, V, np.array([[0, 1, 2]]), 2, camera=c)
    h = read_fragments(fr)
    assert (h["count"] == 1).all() and (h["face"][..., 0] == 0).all()
    np.testing.assert_allclose(h["depth"][..., 0], 2.0, rtol=1e-12)
    # this face's normal (+z) points towards the camera at z=2: front-facing, kept by culling;
    # the reversed winding is back-facing and culled only when asked
    _, _, _, fr = run_raster(device, V, np.array([[0, 1, 2]]), 2, camera=c, cull_backface=True)
    assert (read_fragments(fr)["count"] == 1).all()
    _, _, _, fr = run_raster(device, V, np.array([[0, 2, 1]]), 2, camera=c, cull_backface=True)
    assert (read_fragments(fr)["count"] == 0).all()
    _, _, _, fr = run_raster(device, V, np.array([[0, 2, 1]]), 2, camera=c)
    assert (read_fragments(fr)["count"] == 1).all()


# ------------------------------------------------------------------------------------------------ interpolate


def test_interpolate_forward_and_vjp(device64, rng):
    V, F = soup(rng, M=50)
    _, mesh, vs, fr = run_raster(device64, V, F, 6)
    h = read_fragments(fr)
    attr = rng.standard_normal((len(V), 5))
    ok = h["face"] >= 0  # slots beyond the pixel's count are undefined by contract
    out = fr.to_hwk(interpolate(device64, attr, fr))
    np.testing.assert_allclose(out[ok], ref.interpolate_ref(attr, F, h["face"], h["bary"])[ok], atol=1e-12)
    v = rng.standard_normal(out.shape)
    v_attr, v_bary = interpolate_backward(device64, attr, fr, v)
    ra, rb = ref.interpolate_vjp_ref(attr, F, h["face"], h["bary"], v)
    np.testing.assert_allclose(v_attr.get(), ra, atol=1e-10)
    np.testing.assert_allclose(fr.to_hwk(v_bary)[ok], rb[ok], atol=1e-10)
    # accumulation into an existing barycentric adjoint
    _, v_bary2 = interpolate_backward(device64, attr, fr, v, v_bary_acc=v_bary)
    np.testing.assert_allclose(fr.to_hwk(v_bary2)[ok], 2 * rb[ok], atol=1e-10)
    # zero cotangent rows (fragments behind compositing's cut-off) are skipped: the same as the reference's
    v[rng.uniform(size=v.shape[:3]) < 0.4] = 0.0
    v_attr, v_bary = interpolate_backward(device64, attr, fr, v, v_bary_acc=v_bary)
    ra, rb2 = ref.interpolate_vjp_ref(attr, F, h["face"], h["bary"], v)
    np.testing.assert_allclose(v_attr.get(), ra, atol=1e-10)
    np.testing.assert_allclose(fr.to_hwk(v_bary)[ok], (rb + rb2)[ok], atol=1e-10)


def test_interpolate_shared_vertices(device64, rng):
    """A connected grid: vertices shared by up to 6 faces gather every corner's adjoint."""
    n = 6
    g = np.stack(np.meshgrid(np.linspace(-1, 1, n), np.linspace(-0.8, 0.8, n)), -1).reshape(-1, 2)
    V = np.concatenate([g, 0.1 * np.sin(3 * g[:, :1])], 1)
    idx = np.arange(n * n).reshape(n, n)
    F = np.concatenate([np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:]], -1).reshape(-1, 3),
                        np.stack([idx[:-1, :-1], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 3)])
    _, mesh, vs, fr = run_raster(device64, V, F, 3)
    h = read_fragments(fr)
    attr = rng.standard_normal((len(V), 3))
    v = rng.standard_normal((H, W, 3, 3))
    v_attr, _ = interpolate_backward(device64, attr, fr, v)
    ra, _ = ref.interpolate_vjp_ref(attr, F, h["face"], h["bary"], v)
    assert h["count"].sum() > 100
    np.testing.assert_allclose(v_attr.get(), ra, atol=1e-10)


# ---------------------------------------------------------------------------- coverage + geometry adjoint


def test_coverage_forward(device, device64, rng):
    V, F = soup(rng, M=50)
    _, _, vs, fr = run_raster(device64, V, F, 6)
    h = read_fragments(fr)
    ok = h["face"] >= 0
    win = fr.to_hwk(coverage(device64, fr, 0.7))
    r = ref.fragment_geometry_ref(vs.get(), F, h["face"], sigma=0.7)
    np.testing.assert_allclose(win[ok], r["win"][ok], atol=1e-12)
    assert (win[ok] > 0).mean() > 0.9 and (win[ok] <= 1).all()
    # the rasterizer computes the same window in its own pass (from the set-up coefficients)
    _, _, _, fr2 = run_raster(device64, V, F, 6, sigma=0.7)
    assert fr2.win is not None and coverage(device64, fr2, 0.7) is fr2.win
    np.testing.assert_allclose(fr2.to_hwk(fr2.win)[ok], r["win"][ok], rtol=1e-10, atol=1e-12)
    for variant in ("pixel", "rows", "rows16"):
        _, _, _, fr3 = run_raster(device, V.astype(np.float32), F, 6, real=np.float32, sigma=0.7, variant=variant)
        np.testing.assert_allclose(fr3.to_hwk(fr3.win)[ok], r["win"][ok], atol=2e-4)
    # sigma -> infinity is the hard edge: every covered fragment gets weight 1
    hard = fr.to_hwk(coverage(device64, fr, 1e9))
    assert np.allclose(hard[(h["face"] >= 0) & (r["win"] > 0)], 1.0)


def test_raster_backward_vjp_matches_reference_fd(device64, rng):
    """Adjoint of (barycentrics, depth, window) w.r.t. projected vertices vs central differences of
    the independent numpy formulas, on the kernel's own fragments."""
    V, F = soup(rng, M=25)
    _, _, vs, fr = run_raster(device64, V, F, 4)
    h = read_fragments(fr)
    sigma = 0.8
    v_b = rng.standard_normal((H, W, 4, 2))
    v_d = rng.standard_normal((H, W, 4))
    v_w = rng.standard_normal((H, W, 4))
    v_vs, v_sigma = raster_backward(device64, fr, v_bary=v_b, v_depth=v_d, v_win=v_w, sigma=sigma)
    vs0 = vs.get()

    def loss(vsx, s=sigma):
        r = ref.fragment_geometry_ref(vsx, F, h["face"], sigma=s)
        return (r["bary"] * v_b).sum() + (r["depth"] * v_d).sum() + (r["win"] * v_w).sum()

    eps = 1e-6
    num = fd_grad(loss, vs0, eps)
    np.testing.assert_allclose(v_vs.get(), num, rtol=1e-5, atol=1e-5)
    assert v_sigma == pytest.approx((loss(vs0, sigma + eps) - loss(vs0, sigma - eps)) / (2 * eps), rel=1e-6)


def test_soft_edges_window_forward_and_adjoint(device, device64, rng):
    """Only the marked edges of a face get the window (forward, both raster variants) and the
    adjoint of the masked window matches central differences of the reference."""
    V, F = soup(rng, M=25)
    soft = rng.integers(0, 8, len(F)).astype(np.int32)
    sigma = 0.8
    _, _, vs, fr = run_raster(device64, V, F, 4, sigma=sigma, soft_edges=soft)
    h = read_fragments(fr)
    ok = h["face"] >= 0
    r = ref.fragment_geometry_ref(vs.get(), F, h["face"], sigma=sigma, soft_edges=soft)
    np.testing.assert_allclose(fr.to_hwk(fr.win)[ok], r["win"][ok], rtol=1e-10, atol=1e-12)
    assert np.allclose(fr.to_hwk(fr.win)[ok & (soft[np.maximum(h["face"], 0)] == 0)], 1.0)  # no soft edge: window 1
    for variant in ("pixel", "rows", "rows16"):
        _, _, _, f32 = run_raster(device, V.astype(np.float32), F, 4, real=np.float32, sigma=sigma, variant=variant,
                                  soft_edges=soft)
        np.testing.assert_allclose(f32.to_hwk(f32.win)[ok], r["win"][ok], atol=2e-4)
    with pytest.raises(ValueError, match="sigma"):
        coverage(device64, fr, 0.5)  # the masked window exists only for the rasterizer's sigma
    v_b = rng.standard_normal((H, W, 4, 2))
    v_w = rng.standard_normal((H, W, 4))
    v_vs, v_sigma = raster_backward(device64, fr, v_bary=v_b, v_win=v_w, sigma=sigma)
    vs0 = vs.get()

    def loss(vsx, s=sigma):
        g = ref.fragment_geometry_ref(vsx, F, h["face"], sigma=s, soft_edges=soft)
        return (g["bary"] * v_b).sum() + (np.where(ok, g["win"], 0) * v_w).sum()

    eps = 1e-6
    np.testing.assert_allclose(v_vs.get(), fd_grad(loss, vs0, eps), rtol=1e-5, atol=1e-5)
    assert v_sigma == pytest.approx((loss(vs0, sigma + eps) - loss(vs0, sigma - eps)) / (2 * eps), rel=1e-6)
    with pytest.raises(ValueError, match="soft_edges"):
        run_raster(device64, V, F, 4, sigma=sigma, soft_edges=np.full(len(F), 9))


def test_silhouette_edges_open_no_seams_in_a_closed_mesh(device64):
    """An opaque closed mesh with the window on every edge lets the background through along its
    interior edges; with the window on its silhouette edges only it is opaque inside."""
    import trimesh

    from tests.reference.silhouette import silhouette_edges

    ico = trimesh.creation.icosphere(2, radius=0.8)
    V, F = np.asarray(ico.vertices), np.asarray(ico.faces)
    c = Camera.look_at([0.0, 0.0, 3.0], [0, 0, 0], [0, 1, 0], 40, 48, 48)
    col = np.ones((len(V), 1))

    def acc(soft):
        _, _, _, fr = run_raster(device64, V, F, 4, camera=c, sigma=2.0, soft_edges=soft)
        a = np.ones(fr.P)
        fa = interpolate(device64, col, fr)
        _, trans, _ = composite(device64, fr, fa, a, np.zeros(1), win=fr.win)
        return 1 - trans.get()

    inner = np.zeros((48, 48), bool)
    yy, xx = np.mgrid[:48, :48]
    inner[(xx - 23.5) ** 2 + (yy - 23.5) ** 2 < 12**2] = True  # well inside the disc
    all_edges, silhouette = acc(None), acc(silhouette_edges(V, F, c.center))
    assert all_edges[inner].min() < 0.9  # seams along the interior edges
    np.testing.assert_allclose(silhouette[inner], 1.0, atol=1e-12)
    edge = (all_edges > 0) & ~inner
    assert (silhouette[edge] < 1).any()  # the silhouette keeps its soft window


@pytest.mark.parametrize("real", [np.float32, np.float64])
def test_device_silhouette_bits_match_the_host_reference(device, device64, real):
    """``ops.silhouette.silhouette_bits`` (the render's path) against ``tests/reference/silhouette.py`` (double, on the
    host): the same masks on a bumpy closed mesh with a hole (boundary edges) and a non-manifold fin, from eyes
    all around; float32 may differ only where a face is seen edge-on (none is here: asserted)."""
    import pyopencl.array as cla
    import trimesh

    from tests.reference.silhouette import silhouette_edges
    from triplet_cl.ops.mesh import DeviceMesh
    from triplet_cl.ops.silhouette import silhouette_bits

    dev = device64 if real == np.float64 else device
    ico = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(4)
    V = np.asarray(ico.vertices) * rng.uniform(0.9, 1.1, (len(ico.vertices), 1))
    F = np.asarray(ico.faces)[5:]  # a hole: boundary edges
    F = np.concatenate([F, [[F[0, 0], F[0, 1], len(V)]]])  # a fin on an edge: three faces share it
    V = np.concatenate([V, [[2.0, 0.1, 0.2]]])
    mesh = DeviceMesh(dev, F, len(V))
    Vd = cla.to_device(dev.queue, V.astype(real))
    for eye in rng.normal(size=(8, 3)) * 4:
        tri = V.astype(real).astype(np.float64)[F]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        d = np.einsum("md,md->m", n, eye - tri.mean(1)) / np.linalg.norm(n, axis=1) / np.linalg.norm(eye)
        assert np.abs(d).min() > 1e-5  # no face edge-on: float32 decides as double
        want = silhouette_edges(V.astype(real), F, eye)
        got = silhouette_bits(dev, Vd, mesh, eye).get()
        assert got.dtype == np.int32 and (want > 0).sum() > 20 and (want == 7).sum() < len(F)
        np.testing.assert_array_equal(got, want)
    empty = DeviceMesh(dev, np.zeros((0, 3), np.int32), 3)
    assert silhouette_bits(dev, cla.to_device(dev.queue, np.zeros((3, 3), real)), empty, [0, 0, 1]).shape == (0,)
    with pytest.raises(ValueError, match="eye"):
        silhouette_bits(dev, Vd, mesh, [0, 0])


# ------------------------------------------------------------------------------------------------ composite


def _frag_inputs(device, rng, K=5, real=np.float64):
    V, F = soup(rng, M=50)
    _, _, vs, fr = run_raster(device, V, F, K, real=real)
    h = read_fragments(fr)
    C = 4
    feat = rng.uniform(0, 1, (H, W, K, C))
    alpha = rng.uniform(0.05, 0.95, (H, W, K))
    valid = h["face"] >= 0
    return fr, h, np.where(valid[..., None], feat, 0), np.where(valid, alpha, 0)


def test_composite_forward_and_vjp(device64, rng):
    fr, h, feat, alpha = _frag_inputs(device64, rng)
    bg = np.array([1.0, 0.5, 0.25, 0.0])
    img, trans, ncon = composite(device64, fr, feat, alpha, bg, t_min=0.0)
    r_img, r_trans, r_n = ref.composite_ref(feat, alpha, h["count"], bg)
    np.testing.assert_allclose(img.get(), r_img, atol=1e-12)
    np.testing.assert_allclose(trans.get(), r_trans, atol=1e-12)
    np.testing.assert_array_equal(ncon.get(), r_n)
    v_img = rng.standard_normal(r_img.shape)
    v_acc = rng.standard_normal(r_trans.shape)
    v_feat, v_alpha, v_win, v_bg = composite_backward(device64, fr, feat, alpha, bg, ncon, trans, v_img, v_acc,
                                                      bg_grad=True)
    rf, ra = ref.composite_vjp_ref(feat, alpha, h["count"], bg, v_img, v_acc)
    ok = h["face"] >= 0
    np.testing.assert_allclose(fr.to_hwk(v_feat)[ok], rf[ok], atol=1e-12)
    np.testing.assert_allclose(fr.to_hwk(v_alpha)[ok], ra[ok], atol=1e-10)
    np.testing.assert_allclose(v_bg, (v_img * r_trans[..., None]).reshape(-1, 4).sum(0), rtol=1e-12)
    assert v_win is None


def test_composite_with_window_and_early_stop(device64, rng):
    fr, h, feat, alpha = _frag_inputs(device64, rng)
    win = coverage(device64, fr, 1.3)
    bg = np.zeros(4)
    img, trans, ncon = composite(device64, fr, feat, alpha, bg, win=win, t_min=0.3)
    a_eff = np.where(h["face"] >= 0, alpha * fr.to_hwk(win), 0.0)
    r_img, r_trans, r_n = ref.composite_ref(feat, a_eff, h["count"], bg, t_min=0.3)
    np.testing.assert_allclose(img.get(), r_img, atol=1e-12)
    np.testing.assert_array_equal(ncon.get(), r_n)
    assert (r_n < h["count"]).any(), "early termination must trigger somewhere in this scene"
    v_img = rng.standard_normal(r_img.shape)
    v_feat, v_alpha, v_win, _ = composite_backward(device64, fr, feat, alpha, bg, ncon, trans, v_img, win=win)
    rf, ra = ref.composite_vjp_ref(feat, a_eff, h["count"], bg, v_img, t_min=0.3)
    ok = h["face"] >= 0
    np.testing.assert_allclose(fr.to_hwk(v_feat)[ok], rf[ok], atol=1e-12)
    np.testing.assert_allclose(fr.to_hwk(v_alpha)[ok], (ra * fr.to_hwk(win))[ok], atol=1e-10)
    np.testing.assert_allclose(fr.to_hwk(v_win)[ok], (ra * alpha)[ok], atol=1e-10)


@pytest.mark.parametrize("real", [np.float32, np.float64])
@pytest.mark.parametrize("C", [1, 3, 4, 7])
def test_composite_compiled_channels_are_the_runtime_bits(device, device64, rng, monkeypatch, real, C):
    """The composite pair with its channel count and the window's presence compiled in (the default) gives the
    runtime loops' values bit for bit (``ops.composite.COMPILED_CHANNELS`` False), with and without a window and
    early termination."""
    from triplet_cl.ops import composite as comp_mod

    dev = device if real == np.float32 else device64
    V, F = soup(rng, M=160)
    _, _, _, fr = run_raster(dev, V, F, 6, real=real, sigma=3.0)
    feat = rng.uniform(0, 1, (fr.P, C)).astype(real)
    alpha = rng.uniform(0.5, 0.99, fr.P).astype(real)
    v_img = rng.standard_normal((H, W, C)).astype(real)
    v_acc = rng.standard_normal((H, W)).astype(real)
    bg = rng.uniform(0, 1, C)
    for win in (None, fr.win):
        out = {}
        for compiled in (True, False):
            monkeypatch.setattr(comp_mod, "COMPILED_CHANNELS", compiled)
            img, trans, ncon = composite(dev, fr, feat, alpha, bg, win=win, t_min=0.2)
            vf, va, vw, vb = composite_backward(dev, fr, feat, alpha, bg, ncon, trans, v_img, v_acc=v_acc, win=win,
                                                bg_grad=True)
            out[compiled] = [img.get(), trans.get(), ncon.get(), vf.get(), va.get(), vb] + \
                ([vw.get()] if vw is not None else [])
        for a, b in zip(out[True], out[False], strict=True):
            np.testing.assert_array_equal(a, b)
        assert (out[True][2] < fr.count.get()).any()  # early termination somewhere


# ------------------------------------------------------------------------------------------------ whole chain


def render_chain(device, V, F, col, alv, sigma, K, bg, camera, want_grad=None):
    """Forward (and optionally backward) of the whole chain, float64. Returns image, fragments, grads."""
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, V, camera)
    fr = rasterize(device, vs, mesh, camera.width, camera.height, K)
    packed = np.concatenate([col, alv], 1)  # one interpolation of colour + alpha
    fa = interpolate(device, packed, fr).get()
    feat, a = np.ascontiguousarray(fa[..., :3]), np.ascontiguousarray(fa[..., 3])
    win = coverage(device, fr, sigma)
    img, trans, ncon = composite(device, fr, feat, a, bg, win=win, t_min=0.0)
    if want_grad is None:
        return img.get(), read_fragments(fr)
    v_feat, v_a, v_win, _ = composite_backward(device, fr, feat, a, bg, ncon, trans, want_grad, win=win)
    v_fa = np.concatenate([v_feat.get(), v_a.get()[..., None]], -1)
    v_packed, v_vs, v_sigma = fragments_backward(device, fr, packed, v_fa, v_win=v_win, sigma=sigma)
    v_V = project_backward(device, V, camera, v_vs)
    vp = v_packed.get()
    grads = {"V": v_V.get(), "col": vp[:, :3], "alpha": vp[:, 3:], "sigma": v_sigma}
    return img.get(), read_fragments(fr), grads


def test_whole_chain_central_differences(device64, rng):
    """d(sum(image * v)) / d{positions, colours, alphas, sigma} against float64 central differences."""
    V, F = soup(rng, M=12, size=0.35)
    c = cam(17, 13)
    col = rng.uniform(0, 1, (len(V), 3))
    alv = rng.uniform(0.2, 0.8, (len(V), 1))
    sigma, K, bg = 0.9, 6, np.array([0.2, 0.7, 1.0])
    v = rng.standard_normal((13, 17, 3))
    img, fr0, g = render_chain(device64, V, F, col, alv, sigma, K, bg, c, want_grad=v)
    assert fr0["count"].sum() > 40

    def f(Vx=V, colx=col, alx=alv, s=sigma):
        im, frx = render_chain(device64, Vx, F, colx, alx, s, K, bg, c)
        stable = np.array_equal(frx["face"], fr0["face"])
        return (im * v).sum(), stable

    eps = 1e-6
    checked = 0
    for name, x in (("V", V), ("col", col), ("alpha", alv)):
        num = np.zeros_like(x)
        mask = np.ones(x.shape, bool)
        for idx in np.ndindex(*x.shape):
            xp, xm = x.copy(), x.copy()
            xp[idx] += eps
            xm[idx] -= eps
            (lp, sp), (lm, sm) = f(**{{"V": "Vx", "col": "colx", "alpha": "alx"}[name]: xp}), \
                f(**{{"V": "Vx", "col": "colx", "alpha": "alx"}[name]: xm})
            mask[idx] = sp and sm
            num[idx] = (lp - lm) / (2 * eps)
        assert mask.mean() > 0.95, f"{name}: perturbations must rarely change coverage"
        np.testing.assert_allclose(g[name][mask], num[mask], rtol=1e-5, atol=1e-6, err_msg=name)
        checked += mask.sum()
    (lp, _), (lm, _) = f(s=sigma + eps), f(s=sigma - eps)
    assert g["sigma"] == pytest.approx((lp - lm) / (2 * eps), rel=1e-5)
    assert np.abs(g["V"]).sum() > 0 and checked > 100


@pytest.mark.parametrize("dead", [0.0, 0.4])
def test_fused_fragments_backward_equals_separate_ops(device64, rng, dead):
    """The fused pass against interpolation's and the raster's adjoints; ``dead``: that share of the fragments has a
    zero attribute cotangent (behind compositing's cut-off; the pass skips their attribute rows), half of them a
    zero window cotangent too."""
    V, F = soup(rng, M=60)
    _, _, vs, fr = run_raster(device64, V, F, 5)
    attr = rng.standard_normal((len(V), 4))
    v_out = rng.standard_normal((H, W, 5, 4))
    v_d, v_w = rng.standard_normal((H, W, 5)), rng.standard_normal((H, W, 5))
    gone = rng.uniform(size=(H, W, 5)) < dead
    v_out[gone] = 0.0
    v_w[gone & (rng.uniform(size=gone.shape) < 0.5)] = 0.0
    va_sep, vb = interpolate_backward(device64, attr, fr, v_out)
    vvs_sep, vsig_sep = raster_backward(device64, fr, v_bary=vb, v_depth=v_d, v_win=v_w, sigma=0.5)
    va, vvs, vsig = fragments_backward(device64, fr, attr, v_out, v_depth=v_d, v_win=v_w, sigma=0.5)
    np.testing.assert_allclose(va.get(), va_sep.get(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(vvs.get(), vvs_sep.get(), rtol=1e-10, atol=1e-12)
    assert vsig == pytest.approx(vsig_sep, rel=1e-12)
    with pytest.raises(ValueError, match="v_attr_frag is required"):
        fragments_backward(device64, fr, attr)


@pytest.mark.parametrize("real", [np.float32, np.float64])
@pytest.mark.parametrize("C", [1, 2, 3, 7, 8, 14, 17, 30])
def test_fragments_backward_vector_channels_are_the_scalar_bits(device, device64, rng, monkeypatch, real, C):
    """The attribute channels eight, four and two at a time (the default) give the one-at-a-time loop's values bit
    for bit (``ops.fragment_bwd.SCALAR_CHANNELS``): every channel count's chunks and tail, dead rows included."""
    from triplet_cl.ops import fragment_bwd as fbwd

    dev = device if real == np.float32 else device64
    V, F = soup(rng, M=80)
    _, _, _, fr = run_raster(dev, V, F, 5, real=real)
    attr = rng.standard_normal((len(V), C)).astype(real)
    v_out = rng.standard_normal((H, W, 5, C)).astype(real)
    v_out[rng.uniform(size=(H, W, 5)) < 0.3] = 0.0
    v_w = rng.standard_normal((H, W, 5)).astype(real)
    out = {}
    for scalar in (False, True):
        monkeypatch.setattr(fbwd, "SCALAR_CHANNELS", scalar)
        va, vvs, vsig = fragments_backward(dev, fr, attr, v_out, v_win=v_w, sigma=0.5)
        out[scalar] = (va.get(), vvs.get(), vsig)
    np.testing.assert_array_equal(out[False][0], out[True][0])
    np.testing.assert_array_equal(out[False][1], out[True][1])
    assert out[False][2] == out[True][2]
    assert np.abs(out[False][0]).sum() > 0


@pytest.mark.parametrize("real", [np.float32, np.float64])
@pytest.mark.parametrize("masked", [False, True])
def test_window_pass_is_the_packing_bits(device, device64, rng, monkeypatch, real, masked):
    """The coverage window's exp in its own pass over the fragments (``window_from_distance``, the default) gives the
    window computed in ``pack_raster_fragments``'s per-pixel loop (``ops.raster.WINDOW_IN_PACK``) bit for bit: soft
    edges everywhere (a soup) and on a random mask (the mesh stage's silhouettes: no soft edge, window exactly 1)."""
    from triplet_cl.ops import raster as raster_mod

    dev = device if real == np.float32 else device64
    V, F = soup(rng, M=120)
    soft = rng.integers(0, 8, len(F)).astype(np.int32) if masked else None
    for sigma in (0.5, 6.0):
        out = {}
        for in_pack in (False, True):
            monkeypatch.setattr(raster_mod, "WINDOW_IN_PACK", in_pack)
            _, _, _, fr = run_raster(dev, V, F, 6, real=real, sigma=sigma, soft_edges=soft)
            out[in_pack] = {k: getattr(fr, k).get() for k in ("face", "bary", "depth", "win")}
        for k in out[False]:
            np.testing.assert_array_equal(out[False][k], out[True][k], err_msg=k)
        win = out[False]["win"]
        assert len(win) > 100 and (win < 1).any() and (win > 0).all()
        if masked:
            assert (win == 1).any()


@pytest.mark.parametrize("real", [np.float32, np.float64])
@pytest.mark.parametrize("masked", [False, True])
def test_fragments_backward_stored_window_exp(device, device64, rng, monkeypatch, real, masked):
    """The adjoint reads the window's exp that the rasterizer's window pass stored (``Fragments.win_ex``) instead of
    taking it again (``ops.fragment_bwd.USE_WIN_EX`` False: the reference): the same adjoints (the vertices', sigma's,
    the attributes'), soft edges everywhere and on a random mask; a pruned list carries none (its adjoint takes the
    exp again), nor a window of another sigma."""
    from triplet_cl.ops import fragment_bwd as fbwd

    dev = device if real == np.float32 else device64
    V, F = soup(rng, M=120)
    soft = rng.integers(0, 8, len(F)).astype(np.int32) if masked else None
    _, _, _, fr = run_raster(dev, V, F, 6, real=real, sigma=0.7, soft_edges=soft)
    assert fr.win_ex is not None  # win = 1 - win_ex, as the kernel forms it
    np.testing.assert_array_equal(fr.win.get(), (real(1) - fr.win_ex.get()).astype(real))
    attr = rng.standard_normal((len(V), 5)).astype(real)
    v_out = rng.standard_normal((fr.P, 5)).astype(real)
    v_w = rng.standard_normal(fr.P).astype(real)
    v_w[rng.uniform(size=fr.P) < 0.2] = 0.0
    out = {}
    for stored in (True, False):
        monkeypatch.setattr(fbwd, "USE_WIN_EX", stored)
        va, vvs, vsig = fragments_backward(dev, fr, attr, v_out, v_win=v_w, sigma=0.7)
        out[stored] = (va.get(), vvs.get(), vsig)
    # not the same bits: fragment_bwd.cl may contract the edge functions b_k = 1 + A dx + B dy into fused multiply-adds
    # where raster.cl may not (FP_CONTRACT OFF there), so its own exp is of a distance an ulp or so away
    # (measured: at most 3e-8 of the largest value in float32, 1e-16 in float64)
    tol = 1e-6 if real == np.float32 else 1e-13
    for k in (0, 1):
        scale = np.abs(out[False][k]).max()
        np.testing.assert_allclose(out[True][k], out[False][k], rtol=0, atol=tol * scale)
    assert out[True][2] == pytest.approx(out[False][2], rel=tol * 10) and out[True][2] != 0
    # another sigma than the rasterizer's: the stored exp is not that window's, so it is not read
    other = {}
    for stored in (True, False):
        monkeypatch.setattr(fbwd, "USE_WIN_EX", stored)
        other[stored] = fragments_backward(dev, fr, attr, v_out, v_win=v_w, sigma=0.9)[1].get()
    np.testing.assert_array_equal(other[True], other[False])
    # a pruned list carries none
    from triplet_cl.ops.interpolate import interpolate
    from triplet_cl.ops.prune import prune_fragments

    opaque = np.full((len(V), 1), 0.999, real)
    pr, _, _ = prune_fragments(dev, fr, interpolate(dev, opaque, fr), 0, fr.win, 0.9)
    assert pr.P < fr.P and pr.win_ex is None


def test_backward_is_deterministic(device, rng):
    V, F = soup(rng, M=300, size=0.3)
    V = V.astype(np.float32)
    col = rng.uniform(0, 1, (len(V), 3)).astype(np.float32)
    alv = np.full((len(V), 1), 0.6, np.float32)
    c = cam(40, 32)
    v = rng.standard_normal((32, 40, 3)).astype(np.float32)
    _, _, g1 = render_chain(device, V, F, col, alv, 1.0, 8, np.zeros(3), c, want_grad=v)
    _, _, g2 = render_chain(device, V, F, col, alv, 1.0, 8, np.zeros(3), c, want_grad=v)
    for k in ("V", "col", "alpha"):
        np.testing.assert_array_equal(g1[k], g2[k])


# ------------------------------------------------------------------------------------------------ validation


def test_validation_errors(device, rng):
    c = cam()
    with pytest.raises(ValueError, match="V must have shape"):
        project(device, np.zeros((4, 2), np.float32), c)
    with pytest.raises(ValueError, match="finite"):
        project(device, np.full((2, 3), np.nan, np.float32), c)
    with pytest.raises(ValueError, match="floating"):
        project(device, np.zeros((2, 3), np.int32), c)
    with pytest.raises(ValueError, match=r"faces indices must lie in \[0, 2\]"):
        DeviceMesh(device, np.array([[0, 1, 3]]), 3)
    with pytest.raises(ValueError, match="faces must be an integer"):
        DeviceMesh(device, np.zeros((1, 3), np.float32), 3)
    V, F = soup(rng, M=3)
    mesh = DeviceMesh(device, F, len(V))
    vs = project(device, V.astype(np.float32), c)
    with pytest.raises(ValueError, match="K must be in"):
        rasterize(device, vs, mesh, W, H, 0)
    with pytest.raises(ValueError, match="near < far"):
        rasterize(device, vs, mesh, W, H, 2, near=1.0, far=0.5)
    fr = rasterize(device, vs, mesh, W, H, 2)
    with pytest.raises(ValueError, match="attr must have shape"):
        interpolate(device, np.zeros((len(V) + 1, 2), np.float32), fr)
    with pytest.raises(ValueError, match="sigma"):
        coverage(device, fr, -1.0)
    with pytest.raises(ValueError, match="alpha must have shape"):
        composite(device, fr, np.zeros((H, W, 2, 3), np.float32), np.zeros((H, W, 3), np.float32), 0.0)


def test_camera_conventions():
    # NeRF camera at +Z looking at the origin (identity rotation in Blender convention)
    c2w = np.eye(4)
    c2w[2, 3] = 3.0
    cn = Camera.from_nerf(c2w, 100, 80, camera_angle_x=np.radians(40))
    cl = Camera.look_at([0, 0, 3], [0, 0, 0], [0, 1, 0], 40, 100, 80)
    pts = np.array([[0.3, 0.2, 0.1], [-0.4, 0.5, -0.2]])
    np.testing.assert_allclose(cn.project_points(pts), cl.project_points(pts), atol=1e-9)
    assert cn.project_points(np.array([[0.5, 0, 0]]))[0, 0] > 50, "+X world appears to the right"
    assert cn.project_points(np.array([[0, 0.5, 0]]))[0, 1] < 40, "+Y world appears upwards"
    np.testing.assert_allclose(cn.center, [0, 0, 3])
    np.testing.assert_allclose(cn.c2w_nerf, c2w, atol=1e-12)  # from_nerf's inverse
    np.testing.assert_allclose(cl.c2w_nerf, c2w, atol=1e-12)
    # block_averaged(f): the image of f x f pixel blocks (a remainder dropped), a point lands at 1/f of its
    # pixel-edge coordinates; scaled() to the rounded size misplaces it when the size is not divisible by f
    odd = Camera.look_at([0, 0, 3], [0, 0, 0], [0, 1, 0], 40, 101, 83)
    for f in (1, 2, 3, 4):
        b = odd.block_averaged(f)
        assert (b.width, b.height) == (101 // f, 83 // f)
        np.testing.assert_allclose(b.project_points(pts)[:, :2], odd.project_points(pts)[:, :2] / f, atol=1e-9)
    off = odd.scaled((101 // 3) / 101).project_points(pts)[:, 0] - odd.project_points(pts)[:, 0] / 3
    assert np.abs(off).max() > 0.1  # what Targets used before
    with pytest.raises(ValueError, match="block size"):
        odd.block_averaged(0)
    # COLMAP: w2c rotation from the quaternion, same camera
    from scipy.spatial.transform import Rotation

    q_xyzw = Rotation.from_matrix(cl.w2c[:3, :3]).as_quat()
    cc = Camera.from_colmap([q_xyzw[3], *q_xyzw[:3]], cl.w2c[:3, 3], cl.fx, cl.fy, cl.cx, cl.cy, 100, 80)
    np.testing.assert_allclose(cc.project_points(pts), cl.project_points(pts), atol=1e-9)
    co = Camera.from_opencv([[cl.fx, 0, 49.5], [0, cl.fy, 39.5], [0, 0, 1]], cl.w2c, 100, 80)
    np.testing.assert_allclose(co.project_points(pts), cl.project_points(pts), atol=1e-9)
    half = cn.scaled(0.5)
    assert (half.width, half.height) == (50, 40)
    np.testing.assert_allclose(half.project_points(pts)[:, :2], cn.project_points(pts)[:, :2] / 2, atol=1e-9)
    with pytest.raises(ValueError, match="w2c must be a 4x4"):
        Camera(1, 1, 0, 0, 2, 2, np.eye(3)[:2])
    with pytest.raises(ValueError, match="near < far"):
        Camera(1, 1, 0, 0, 2, 2, np.eye(4), near=2, far=1)


@pytest.mark.parametrize("path", ["serial", "blocks", "pyopencl"])
def test_offsets_are_the_exclusive_prefix_sum(device, rng, monkeypatch, path):
    """scan.prefix_offsets (the binning's tile and face offsets): off[0] = 0, off[i + 1] = off[i] + counts[i],
    and the total; CPU devices scan in one work-item or in blocks (kernels_cl/scan.cl), others with
    pyopencl's scan."""
    import pyopencl.array as cla

    from triplet_cl.ops import scan as S

    if path == "blocks":
        monkeypatch.setattr(S, "SCAN_SERIAL", 10)
        monkeypatch.setattr(S, "SCAN_BLOCK", 7)
    if path == "pyopencl":
        monkeypatch.setattr(type(device), "is_cpu", property(lambda self: False))
    for n in (0, 1, 6, 7, 8, 50, 1001):
        c = rng.integers(0, 9, n).astype(np.int32)
        off, total = S.prefix_offsets(device, cla.to_device(device.queue, c))
        expect = np.concatenate([[0], np.cumsum(c)])
        np.testing.assert_array_equal(off.get(), expect)
        assert total == expect[-1]
        off, total = S.prefix_offsets(device, cla.to_device(device.queue, c), total=False)
        np.testing.assert_array_equal(off.get(), expect)
        assert total is None


# ------------------------------------------------------------------------------------------------ columns


@pytest.mark.parametrize("real", [np.float32, np.float64])
def test_split_and_merge_columns_equal_copy_columns(device, device64, rng, real):
    """split_columns / merge_columns (one pass, up to SPLIT_BLOCKS = 8 blocks) move exactly what one copy_columns
    per block moves; a layout that covers every column round-trips bit for bit."""
    import pyopencl.array as cla

    from triplet_cl.ops.columns import SPLIT_BLOCKS, copy_columns, merge_columns, split_columns

    dev = device64 if real == np.float64 else device
    V, F = soup(rng, M=60)
    _, _, _, fr = run_raster(dev, V, F, 6, real=real)
    assert fr.P > 0
    layout = [(0, 3), (3, 3), (6, 6), (12, 1), (13, 6), (19, 2), (21, 1), (22, 2)]  # pos|nrm|mat|alpha|vlight|…
    assert len(layout) == SPLIT_BLOCKS  # every slot of the kernels
    C = 24
    src_h = rng.standard_normal((fr.P, C)).astype(real)
    src = cla.to_device(dev.queue, src_h)
    parts = split_columns(dev, fr, src, layout)
    for (c0, n), part in zip(layout, parts, strict=True):
        want = cla.zeros(dev.queue, (fr.P, n), real)
        copy_columns(dev, fr, src, c0, want, 0, n)
        np.testing.assert_array_equal(part.get(), want.get())
        np.testing.assert_array_equal(part.get(), src_h[:, c0:c0 + n])
    dst = cla.zeros(dev.queue, (fr.P, C), real)
    merge_columns(dev, fr, [(p, c0) for p, (c0, _) in zip(parts, layout, strict=True)], dst)
    np.testing.assert_array_equal(dst.get(), src_h)
    # fewer blocks: the others untouched
    dst = cla.zeros(dev.queue, (fr.P, C), real)
    merge_columns(dev, fr, [(parts[3], 12)], dst)
    want = np.zeros((fr.P, C), real)
    want[:, 12] = src_h[:, 12]
    np.testing.assert_array_equal(dst.get(), want)
    with pytest.raises(ValueError, match="at most"):
        split_columns(dev, fr, src, [(0, 1)] * (SPLIT_BLOCKS + 1))
    with pytest.raises(ValueError, match="inside"):
        split_columns(dev, fr, src, [(C - 1, 2)])
    with pytest.raises(ValueError, match="inside"):
        merge_columns(dev, fr, [(parts[2], C - 2)], dst)
