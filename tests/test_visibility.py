"""Cached per-vertex visibility (``triplet_cl/visibility.py``, issue 18 item 2 / issue 20 item 4).

A box shadows a plane (a soup of separate square tiles, each tile wholly inside or outside the shadow
of a light straight above), so per-vertex visibility is exact there and the cached shadows must
render what the hybrid renderer's per-fragment shadow rays render. Also: the visibility against the
numpy transmittance reference, the render's gradients with the visibility held constant (float64
central differences), the cache's refresh rules, and a recovery: the plane's albedo under the cast
shadow comes out uniform when fitted with shadows, and darkened (the shadow painted in) without.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import sampled_fd
from tests.reference import trace as ref
from triplet_cl.camera import Camera
from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight
from triplet_cl.losses import photometric_loss_and_grad
from triplet_cl.ops.raster import read_fragments
from triplet_cl.optim import Adam
from triplet_cl.render import RenderSettings, render
from triplet_cl.scene import Scene, logit
from triplet_cl.visibility import VisibilityCache, owner_faces, vertex_visibility

RES = 40
HALF = 0.305  # the box's half-width; tile edges fall at ±0.31 (outside) and ±0.29 (inside)


def _tiles(n=10, lo=-1.5, hi=1.5, gap=0.02, y=0.0):
    """A plane at height ``y`` as separate square tiles (2 triangles each, shrunk by ``gap``)."""
    edges = np.linspace(lo, hi, n + 1)
    tris = []
    for i in range(n):
        for k in range(n):
            x0, x1 = edges[i] + gap / 2, edges[i + 1] - gap / 2
            z0, z1 = edges[k] + gap / 2, edges[k + 1] - gap / 2
            a, b, c, d = [x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]
            tris += [[a, b, c], [a, c, d]]
    return np.array(tris, np.float64)


def _box(lo, hi):
    """An axis-aligned box as 12 triangles."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    quads = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (3, 2, 6, 7), (0, 3, 7, 4), (1, 2, 6, 5)]
    return np.array([t for a, b, cc, d in quads for t in ([c[a], c[b], c[cc]], [c[a], c[cc], c[d]])], np.float64)


def box_over_plane(lights, albedo=0.6, dtype=np.float64):
    tris = np.concatenate([_tiles(), _box([-HALF, 0.35, -HALF], [HALF, 0.65, HALF])])
    V = tris.reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    n = len(V)
    mat = np.tile(np.r_[np.full(3, albedo), 0.9, 0.02, 0.99], (n, 1))
    return Scene.from_arrays(V, F, material=logit(mat), alpha=np.full((n, 1), logit(0.999)), lights=lights,
                             dtype=dtype), 200  # the first 200 faces are the plane's


def cameras():
    out = []
    for k in range(4):
        t = 2 * np.pi * (k + 0.3) / 4
        out.append(Camera.look_at([2.6 * np.sin(t), 2.2, 2.6 * np.cos(t)], [0, 0.1, 0], [0, 1, 0], 45, RES, RES))
    return out


def overhead():
    return [DirectionalLight([0.0, 1.0, 0.0], [2.0, 2.0, 2.0]), AmbientLight([0.3, 0.3, 0.3])]


def test_vertex_visibility_matches_reference(device64):
    lights = [PointLight([0.3, 3.0, -0.2], [9.0, 9.0, 9.0]), DirectionalLight([0.2, 1.0, 0.1], [1.0, 1.0, 1.0]),
              AmbientLight([0.1, 0.1, 0.1])]
    scene, _ = box_over_plane(lights)
    scene.alpha.data[:] = np.random.default_rng(3).normal(1.0, 1.5, scene.alpha.data.shape)  # partial occluders
    vis = vertex_visibility(scene, device64, real=np.float64)
    V = scene.V.data
    alpha_v = 1.0 / (1.0 + np.exp(-scene.alpha.data[:, 0]))
    eps = 1e-2 * np.linalg.norm(V.max(0) - V.min(0))
    T, n = ref.transmittance_ref(V, scene.F, alpha_v, V, owner_faces(scene.F, len(V)),
                                 [("point", [0.3, 3.0, -0.2]), ("dir", [0.2, 1.0, 0.1])], eps)
    assert vis.shape == (len(V), 2)
    assert (n > 0).mean() > 0.05 and (n == 0).mean() > 0.3  # some vertices are shadowed, many are not
    np.testing.assert_allclose(vis, T, rtol=1e-10, atol=1e-12)


def test_vertex_visibility_skips_lights_behind_given_normals(device64):
    """``normals``: T = 1 (no ray) where ``n · l <= 0``, the traced value elsewhere; a wrong shape is refused."""
    lights = [PointLight([0.3, 3.0, -0.2], [9.0, 9.0, 9.0]), DirectionalLight([0.2, 1.0, 0.1], [1.0, 1.0, 1.0])]
    scene, _ = box_over_plane(lights)
    V = scene.V.data
    normals = np.random.default_rng(5).normal(size=V.shape)
    full = vertex_visibility(scene, device64, real=np.float64)
    vis = vertex_visibility(scene, device64, real=np.float64, normals=normals)
    ldir = np.stack([np.array([0.3, 3.0, -0.2]) - V, np.broadcast_to([0.2, 1.0, 0.1], V.shape)], 1)  # [N, 2, 3]
    behind = np.einsum("nk,njk->nj", normals, ldir) <= 0
    assert 0.3 < behind.mean() < 0.7 and (full[behind] < 1).any()
    np.testing.assert_array_equal(vis[behind], 1.0)
    np.testing.assert_array_equal(vis[~behind], full[~behind])
    with pytest.raises(ValueError, match="normals"):
        vertex_visibility(scene, device64, normals=normals[:-1])


def test_owner_faces_and_no_shadow_casters(device):
    F = np.array([[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(owner_faces(F, 7), [0, 0, 0, 1, 1, 1, -1])
    scene, _ = box_over_plane([AmbientLight([0.5, 0.5, 0.5])], dtype=np.float32)
    assert vertex_visibility(scene, device).shape == (len(scene.V.data), 0)
    with pytest.raises(ValueError, match="ray_eps"):
        vertex_visibility(scene, device, ray_eps=-1.0)


def test_cached_shadows_render_the_hybrid_image(device64):
    scene, plane = box_over_plane(overhead())
    vis = vertex_visibility(scene, device64, real=np.float64)
    # the plane: the tiles under the box are dark, the others lit, nothing in between
    pv = vis[: 3 * plane, 0]
    dark = pv < 1e-5  # alpha is clamped below 1 - 1e-6 in the shadow rays
    assert np.all(dark | (pv == 1.0)) and dark.sum() == 4 * 6  # the 2 x 2 tiles under the box
    for c in cameras()[:2]:
        # t_min = 0: the hybrid renderer traces every fragment (else none behind transmittance 1e-4, T = 1 there)
        traced = render(scene, c, RenderSettings(K=8, sigma=1.0, real=np.float64, t_min=0.0, renderer="hybrid",
                                                 reflections=False), device64).image
        cached = render(scene, c, RenderSettings(K=8, sigma=1.0, real=np.float64, t_min=0.0), device64, vis=vis).image
        plain = render(scene, c, RenderSettings(K=8, sigma=1.0, real=np.float64, t_min=0.0), device64).image
        assert np.abs(plain - traced).max() > 0.1  # the shadow is in the picture
        # up to 3e-4: the box's hidden bottom, seen through its top (alpha 0.999: weight 1e-3), has corner vertices
        # whose rays graze the box's edges (T 1e-3 against 1e-6 per fragment); elsewhere exact but for the alpha
        # clamp at 1 - 1e-6 (T ~1e-6 in the shadow)
        np.testing.assert_allclose(cached, traced, atol=3e-4)
        assert (np.abs(cached - traced).max(-1) > 1e-5).mean() < 0.05


def test_render_rejects_bad_vis(device):
    scene, _ = box_over_plane(overhead(), dtype=np.float32)
    c = cameras()[0]
    with pytest.raises(ValueError, match="vis must have shape"):
        render(scene, c, RenderSettings(K=4), device, vis=np.ones((5, 1)))
    with pytest.raises(ValueError, match="environment-occlusion"):  # 2 shadow columns, then 3, 8, 15, ...
        render(scene, c, RenderSettings(K=4), device, vis=np.ones((len(scene.V.data), 3)))
    with pytest.raises(ValueError, match="renderer='raster'"):
        render(scene, c, RenderSettings(K=4, renderer="hybrid"), device, vis=np.ones((len(scene.V.data), 1)))


@pytest.mark.parametrize("attributes,occ", [("device", 0), ("host", 0), ("device", 3), ("host", 3)])
def test_gradients_with_cached_visibility_central_differences(device64, rng, attributes, occ):
    """Every parameter's gradient with the visibility held constant (it has no adjoint); perturbations
    that change the fragments are left out, as in tests/test_render.py. Both attribute paths (the device op
    with a constant block, the host Concat); with the environment's occlusion (3 columns: the scene's SH
    environment is of degree 1) and without."""
    from tests.test_render import cam as rcam
    from tests.test_render import small_scene

    scene = small_scene(rng, "cook_torrance", False, M=12)
    vis = rng.uniform(0.0, 1.0, (len(scene.V.data), 2))  # point + directional light
    if occ:
        vis = np.concatenate([vis, rng.normal(0.0, 1.0, (len(vis), occ))], 1)
    s = RenderSettings(K=6, sigma=1.0, real=np.float64, t_min=0.0, attributes=attributes)
    c = rcam()
    r = render(scene, c, s, device64, vis=vis)
    assert np.abs(r.image - render(scene, c, s, device64).image).max() > 1e-3  # the visibility acts
    if occ:
        assert np.abs(r.image - render(scene, c, s, device64, vis=vis[:, :2]).image).max() > 1e-3  # the occlusion
    faces0 = read_fragments(r.info["frags"])["face"]
    w = rng.standard_normal(r.rgba.data.shape)
    scene.zero_grad()
    grads = r.backward(w[..., :3], w[..., 3])

    def loss():
        rr = render(scene, c, s, device64, vis=vis)
        return float((rr.rgba.data * w).sum()), np.array_equal(read_fragments(rr.info["frags"])["face"], faces0)

    for p in scene.params:
        idx, num, ok = sampled_fd(p, loss, rng, 30)
        ana = grads[p.name].reshape(-1)[idx]
        assert ok.mean() > 0.8, f"{p.name}: perturbations changed coverage too often"
        np.testing.assert_allclose(ana[ok], num[ok], rtol=1e-5, atol=1e-7, err_msg=p.name)
        assert np.abs(ana).max() > 0, p.name


def test_cache_refresh_rules(device):
    scene, _ = box_over_plane(overhead(), dtype=np.float32)
    cache = VisibilityCache(every=10, start=5, extent=2.0, move_tol=0.05)
    assert cache.get(scene, 0, device) is None and cache.traces == 0
    v = cache.get(scene, 5, device)
    assert v.shape == (len(scene.V.data), 1) and cache.traces == 1
    assert cache.get(scene, 14, device) is v and cache.traces == 1  # within the interval: cached
    cache.get(scene, 15, device)
    assert cache.traces == 2  # interval over
    scene.light_params.data[:3] += np.array([0.5, 0.0, 0.0], np.float32)  # the light turned: early re-trace ...
    cache.get(scene, 16, device)
    assert cache.traces == 2  # ... but not within move_every (every // 2 = 5) steps of the last trace
    cache.get(scene, 20, device)
    assert cache.traces == 3 and cache.move_every == 5
    cache.invalidate()  # density control
    cache.get(scene, 21, device)
    assert cache.traces == 4
    one = VisibilityCache(every=10, start=5, extent=2.0, move_tol=0.05, move_every=1)
    one.get(scene, 5, device)
    scene.light_params.data[:3] += np.array([0.5, 0.0, 0.0], np.float32)
    one.get(scene, 6, device)
    assert one.traces == 2
    with pytest.raises(ValueError, match="every"):
        VisibilityCache(every=0)
    with pytest.raises(ValueError, match="move_every"):
        VisibilityCache(every=10, move_every=0)


def _fit_albedo(device, scene, targets, cams, vis, steps=120):
    """Fit the materials (geometry and lights fixed) to ``targets``; returns the plane's albedo [n, 3]."""
    opt = Adam()
    opt.add_group("material", [scene.material], lr=0.05, betas=(0.5, 0.999), eps=1e-15)
    s = RenderSettings(K=8, sigma=1.0, background=(0.0, 0.0, 0.0))
    for it in range(steps):
        k = it % len(cams)
        r = render(scene, cams[k], s, device, vis=vis)
        _, v_img = photometric_loss_and_grad(r.image, targets[k], lam=0.2)
        r.backward(v_img)
        opt.step()
        opt.zero_grad()
    return 1.0 / (1.0 + np.exp(-scene.material.data[:, :3].astype(np.float64)))


def test_recovery_uniform_albedo_under_a_cast_shadow(device):
    """Photos path-traced in spirit (per-fragment shadow rays, the hybrid renderer) of a uniform plane
    (albedo 0.6) under a box; fitting the albedo with the cached shadows gives a uniform plane
    (measured, 120 steps: 0.599 under the shadow, 0.595 elsewhere), without shadows the shadow is painted
    in (measured: 0.201 under the shadow, 0.596 elsewhere, std over the plane 0.078)."""
    truth, plane = box_over_plane(overhead(), dtype=np.float32)
    cams = cameras()
    gts = [render(truth, c, RenderSettings(K=8, sigma=1.0, background=(0.0, 0.0, 0.0), renderer="hybrid",
                                           reflections=False), device).image for c in cams]
    vis = vertex_visibility(truth, device)
    shadowed = vis[: 3 * plane, 0] < 0.5
    seen = np.zeros(3 * plane, bool)  # plane vertices some camera sees (the rest keep their initial value)
    for c in cams:
        fr = render(truth, c, RenderSettings(K=8, sigma=1.0), device).info["frags"].face.get()
        f = np.unique(fr[(fr >= 0) & (fr < plane)])
        seen[(3 * f[:, None] + np.arange(3)).reshape(-1)] = True
    assert (shadowed & seen).sum() > 20
    out = {}
    for mode in ("shadows", "none"):
        scene, _ = box_over_plane(overhead(), albedo=0.5, dtype=np.float32)
        alb = _fit_albedo(device, scene, gts, cams, vis if mode == "shadows" else None)[: 3 * plane]
        out[mode] = (alb[shadowed & seen].mean(0), alb[~shadowed & seen].mean(0), alb[seen].std(0).max())
    in_s, out_s, spread = out["shadows"]
    assert np.abs(in_s - 0.6).max() < 0.03 and np.abs(out_s - 0.6).max() < 0.03 and spread < 0.03, out
    in_n, out_n, spread_n = out["none"]
    assert (in_n < 0.35).all() and np.abs(out_n - 0.6).max() < 0.03 and spread_n > 0.05, out


def floor_and_wall(n: int = 21):
    """A floor (z = 0, x in [0, 2]) and a wall (x = 0, z in [0.05, 2.05]: a gap of 0.05 above the floor) made of
    quads, every normal +z (the floor's, up): ``(scene, normals, n, idx [n, n] of the floor's vertices)``."""
    g = np.linspace(0.0, 2.0, n)
    gx, gy = np.meshgrid(g, np.linspace(-1.0, 1.0, n), indexing="ij")
    floor = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], 1)
    wall = np.stack([np.zeros(n * n), gy.ravel(), gx.ravel() + 0.05], 1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    V = np.concatenate([floor, wall])
    F = np.concatenate([tri, tri + n * n]).astype(np.int32)
    scene = Scene.from_arrays(V, F, alpha=np.full((len(V), 1), logit(0.999)))
    return scene, np.tile([0.0, 0.0, 1.0], (len(V), 1)), n, idx


def test_vertex_ambient_occlusion_open_sky_and_a_corner(device):
    """``vertex_ambient_occlusion``: a sphere's vertices see their whole hemisphere (AO 1); on a floor beside a wall
    the vertices at the wall's foot see half of it blocked (about 1/2 for a cosine-weighted hemisphere whose quarter-
    space is cut: the analytic value at the foot is 1/2), those far from it see the open sky."""
    import trimesh

    from triplet_cl.mesh.bake import vertex_normals
    from triplet_cl.visibility import sphere_directions, vertex_ambient_occlusion

    D = sphere_directions(64)
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1.0, rtol=1e-12)
    assert np.abs(D.mean(axis=0)).max() < 0.02  # evenly spread
    m = trimesh.creation.icosphere(2, radius=0.8)
    sphere = Scene.from_arrays(np.asarray(m.vertices), np.asarray(m.faces), alpha=np.full((len(m.vertices), 1),
                                                                                        logit(0.999)))
    ao = vertex_ambient_occlusion(sphere, vertex_normals(m.vertices, m.faces), device, directions=64)
    assert ao.min() > 0.97, ao.min()
    scene, normals, n, _ = floor_and_wall()
    ao = vertex_ambient_occlusion(scene, normals, device, directions=256, ray_eps=1e-3)[: n * n].reshape(n, n)
    centre = n // 2  # y = 0, away from the wall's side edges
    assert 0.35 < ao[1, centre] < 0.65, ao[1, centre]  # x = 0.1, at the wall's foot
    assert ao[-1, centre] > 0.85 and ao[-1, centre] > ao[1, centre] + 0.3, (ao[-1, centre], ao[1, centre])
    assert np.all(np.diff(ao[1:, centre]) > -0.05)  # opens up away from the wall


def _bounce_reference(scene, normals, lights, directions, eps):
    """``vertex_bounce`` by brute force: the reference rays (``nearest_ref``) and the reference shading of each hit
    seen from its vertex (``tests/reference/shade.py``), unshadowed."""
    from tests.reference import shade as shade_ref
    from triplet_cl.lights import pack_lights
    from triplet_cl.visibility import sphere_directions

    V, F = np.asarray(scene.V.data, np.float64), np.asarray(scene.F)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    D = sphere_directions(directions)
    mat = 1.0 / (1.0 + np.exp(-np.asarray(scene.material.data, np.float64)))
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(scene.alpha.data, np.float64)))
    t = pack_lights(lights)
    own = owner_faces(F, len(V))
    out = np.zeros((len(V), 3))
    for i in range(len(V)):
        w = n[i] @ D.T
        k = np.nonzero(w > 0)[0]
        f, b = ref.nearest_ref(V, F, np.tile(V[i], (len(k), 1)), D[k], np.full(len(k), own[i]), eps)
        hit = f >= 0
        if not hit.any():
            continue
        lam = np.stack([b[hit, 0], b[hit, 1], 1 - b[hit, 0] - b[hit, 1]], 1)
        c = F[f[hit]]

        def at(a, lam=lam, c=c):
            return np.einsum("hc,hcj->hj", lam, a[c])

        rgb = shade_ref.shade(at(V), at(n), at(mat), f[hit], V[i], t.ints, t.params, "cook_torrance")
        L = np.zeros((len(k), 3))
        L[hit] = rgb * at(alpha)
        out[i] = (w[k, None] * L).sum(0) / w[k].sum()
    return out


def test_vertex_bounce_matches_reference_and_lights_what_faces_a_lit_surface(device64):
    """``vertex_bounce`` (the traced interreflection) against the brute-force reference; physics: the box's
    underside, facing the lit floor, receives the floor's light, the open floor receives none; the cast shadows
    given (``vis``) shade the hits (all ones: unchanged; all zeros: the ambient light's bounce alone)."""
    from triplet_cl.visibility import vertex_bounce

    lights = overhead()
    scene, nplane = box_over_plane(lights)
    V, F = np.asarray(scene.V.data), np.asarray(scene.F)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    normals = np.repeat(fn / np.linalg.norm(fn, axis=1, keepdims=True), 3, axis=0)  # a soup: the face's normal
    eps = 1e-2 * np.linalg.norm(V.max(0) - V.min(0))
    got = vertex_bounce(scene, normals, device64, directions=16, ray_eps=1e-2, real=np.float64)
    want = _bounce_reference(scene, normals, lights, 16, eps)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    under = np.nonzero(normals[:, 1] < -0.9)[0]
    under = under[under >= 3 * nplane]  # the box's underside
    far = np.nonzero(np.linalg.norm(V[: 3 * nplane, [0, 2]], axis=1) > 1.0)[0]  # the floor away from the box
    assert got[under].min() > 0.05 and np.all(got[far] == 0), (got[under].min(), got[far].max())
    ones = vertex_bounce(scene, normals, device64, vis=np.ones((len(V), 1)), directions=16, real=np.float64)
    np.testing.assert_allclose(ones, got, rtol=1e-12, atol=1e-15)
    dark = vertex_bounce(scene, normals, device64, vis=np.zeros((len(V), 1)), directions=16, real=np.float64)
    amb = vertex_bounce(scene, normals, device64, lights=[lights[1]], directions=16, real=np.float64)
    np.testing.assert_allclose(dark, amb, rtol=1e-12, atol=1e-15)
    assert dark[under].max() < 0.5 * got[under].min()
    with pytest.raises(ValueError, match="directions"):
        vertex_bounce(scene, normals, device64, directions=0)


@pytest.mark.parametrize("brdf", ["cook_torrance", "blinn_phong"])
def test_render_with_bounce_is_an_ambient_light_per_vertex(device64, rng, brdf):
    """``render(bounce=b)`` lights each vertex as an ambient light of radiance ``b`` would: with a uniform ``b`` the
    image and every gradient equal those of the scene with an extra ``AmbientLight(b)`` (but the light's own
    gradient); bad shapes and other renderers are refused."""
    from triplet_cl.materials import get_brdf

    scene, _ = box_over_plane(overhead())
    if brdf == "blinn_phong":
        n = len(scene.V.data)
        mat = rng.uniform(0.1, 0.9, (n, get_brdf("blinn_phong").num_channels))
        scene = Scene.from_arrays(scene.V.data, scene.F, material=logit(mat), alpha=scene.alpha.data,
                                  lights=overhead(), brdf="blinn_phong", dtype=np.float64)
    c = np.array([0.2, 0.15, 0.1])
    b = np.tile(c, (len(scene.V.data), 1))
    st = RenderSettings(K=4, sigma=1.0, background=(1, 1, 1), real=np.float64)
    cam = cameras()[0]
    v_img = rng.standard_normal((RES, RES, 3))
    r = render(scene, cam, st, device64, bounce=b)
    g = r.backward(v_img)
    scene2 = Scene.from_arrays(scene.V.data, scene.F, material=scene.material.data, alpha=scene.alpha.data,
                               lights=overhead() + [AmbientLight(c)], brdf=scene.brdf, dtype=np.float64)
    r2 = render(scene2, cam, st, device64)
    g2 = r2.backward(v_img)
    assert np.abs(r.image - render(scene, cam, st, device64).image).max() > 0.01  # the bounce adds light
    np.testing.assert_allclose(r.image, r2.image, rtol=1e-12, atol=1e-13)
    for name in ("V", "material", "alpha"):
        np.testing.assert_allclose(g[name], g2[name], rtol=1e-9, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(g["light_params"], g2["light_params"][:-3], rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="bounce must have shape"):
        render(scene, cam, st, device64, bounce=b[:-1])
    with pytest.raises(ValueError, match="raster"):
        render(scene, cam, RenderSettings(K=4, renderer="hybrid", real=np.float64), device64, bounce=b)


def test_environment_occlusion_is_the_transfer_of_the_visible_sky(device):
    """``vertex_occlusion``: on a floor beside a wall, under an SH environment with strong directional bands, the
    shading's irradiance ``ao · Σ_j c_j (A_l Y_j(n) − U_j)`` (64 directions) matches the visible sky's irradiance
    ``∫ V(ω) L(ω) max(0, n·ω) dω`` summed over 4096 directions (no SH projection, no normalisation: an independent
    quadrature), to a few % of the open sky's; the unoccluded formula is far off at the wall's foot. U is 0 exactly
    where nothing occludes (a sphere's vertices) and the degree sets its columns."""
    import trimesh

    from triplet_cl.lights import DirectionalLight
    from triplet_cl.mesh.bake import vertex_normals
    from triplet_cl.mesh.envmap import sh_basis
    from triplet_cl.visibility import sphere_directions, vertex_occlusion

    m = trimesh.creation.icosphere(2, radius=0.8)
    sphere = Scene.from_arrays(np.asarray(m.vertices), np.asarray(m.faces), alpha=np.full((len(m.vertices), 1),
                                                                                        logit(0.999)))
    ao, U = vertex_occlusion(sphere, vertex_normals(m.vertices, m.faces), device, directions=64, degree=2)
    assert U.shape == (len(m.vertices), 8) and not U.any() and ao.min() > 0.97
    assert vertex_occlusion(sphere, vertex_normals(m.vertices, m.faces), device, degree=0)[1].shape == (len(ao), 0)
    with pytest.raises(ValueError, match="degree"):
        vertex_occlusion(sphere, vertex_normals(m.vertices, m.faces), device, degree=9)
    scene, normals, n, idx = floor_and_wall()
    sel = idx[[1, 3, 6, -1], n // 2]  # x = 0.1, 0.3, 0.6, 2.0 on the floor's middle line
    c = np.zeros(9)
    c[0], c[1], c[3], c[2], c[8] = 2.0, 0.3, -1.2, 0.6, 0.4  # bright towards -x (the wall's side), a band-2 part
    A = np.repeat([np.pi, 2 * np.pi / 3, np.pi / 4], [1, 3, 5])
    Yn = sh_basis(2, normals[sel])
    open_sky = (A * Yn) @ c
    D = sphere_directions(4096)
    T = np.concatenate([vertex_visibility(scene, device, lights=[DirectionalLight(d, np.ones(3)) for d in D[k]],
                                          ray_eps=1e-3, vertices=sel) for k in np.array_split(np.arange(4096), 8)], 1)
    w = np.maximum(normals[sel] @ D.T, 0.0)
    truth = (T * w * (sh_basis(2, D) @ c)).sum(axis=1) * 4 * np.pi / len(D)
    assert truth[0] < 0.75 * open_sky[0]  # the wall hides much of the bright side at its foot
    # the formula with 1024 directions: within 1 %; the mesh stage's 64: within 5 % (the visibility's own
    # discretisation, the AO's as much: 0.77 for 0.71 at x = 0.6)
    for k, tol in ((1024, 0.01), (64, 0.05)):
        ao, U = vertex_occlusion(scene, normals, device, directions=k, degree=2, ray_eps=1e-3)
        shaded = ao[sel] * ((A * Yn) @ c - U[sel] @ c[1:])
        np.testing.assert_allclose(shaded, truth, atol=tol * open_sky.max(), err_msg=f"{k} directions")
        assert np.abs(ao[sel] * open_sky - truth)[0] > 0.1 * open_sky[0]  # the AO alone is far off at the foot
