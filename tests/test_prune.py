"""``RenderSettings.prune`` (``ops/prune.py``): the fragments behind each pixel's ``t_min`` cut-off dropped before
shading. The image must be the full list's bit for bit and every gradient the same (to the summation order of the
light parameters' partials); an opaque mesh keeps about one fragment per covered pixel."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_render import cam, small_scene
from triplet_cl.ops.prune import PRUNE_MARGIN, prune_fragments
from triplet_cl.ops.raster import read_fragments
from triplet_cl.render import RenderSettings, render


def two_layers(scene):
    """The mesh and a copy 0.5 behind it (a second surface in every pixel, as a closed object's back faces)."""
    from triplet_cl.scene import Scene

    V = np.asarray(scene.V.data)
    n = len(V)
    return Scene.from_arrays(np.concatenate([V, V - [0.0, 0.0, 0.5]]), np.concatenate([scene.F, scene.F + n]),
                             material=np.concatenate([scene.material.data] * 2),
                             alpha=np.concatenate([scene.alpha.data] * 2), lights=scene.lights, brdf=scene.brdf,
                             dtype=np.float64)


def _grads(scene, r, w):
    scene.zero_grad()
    r.backward(w[..., :3], w[..., 3])
    return {p.name: np.array(p.grad) for p in scene.params if p.grad is not None}


@pytest.mark.parametrize("mesh,alpha,sigma,K,transfer", [(True, 11.5, 1.0, 4, "srgb"),   # an opaque mesh
                                                         (True, 4.6, 1.0, 4, None),      # the mesh stage before
                                                         (True, None, None, 6, None),     # half transparent
                                                         (False, None, 0.8, 6, "srgb"),   # a soup
                                                         (False, 3.0, 0.8, 1, None)])     # K = 1
@pytest.mark.parametrize("real", [np.float64, np.float32])
def test_pruned_render_equals_the_full_list(device, device64, rng, mesh, alpha, sigma, K, transfer, real):
    d = device64 if real == np.float64 else device
    scene = small_scene(rng, "cook_torrance", mesh=mesh, M=30)
    if mesh:
        scene = two_layers(scene)
    if alpha is not None:
        scene.alpha.data[:] = alpha
    if real == np.float32:
        for p in scene.params:
            p.data = p.data.astype(np.float32)
    kw = dict(K=K, sigma=sigma, real=real, background=(0.3, 0.5, 0.9), normals="vertex" if mesh else "face",
              soft_edges="silhouette" if mesh and sigma else "all", transfer=transfer)
    w = rng.standard_normal((12, 15, 4))
    r0 = render(scene, cam(), RenderSettings(**kw), d)
    g0 = _grads(scene, r0, w)
    r1 = render(scene, cam(), RenderSettings(prune=True, **kw), d)
    g1 = _grads(scene, r1, w)
    assert np.array_equal(r0.rgba.data, r1.rgba.data)
    P0, P1 = r0.info["frags"].P, r1.info["frags"].P
    assert 0 < P1 <= P0
    if alpha is not None and alpha > 10:  # opaque: at most the front fragment and the window's neighbours
        assert P1 < 0.8 * P0, (P0, P1)
    assert g0.keys() == g1.keys() and g0
    for k in g0:
        tol = 1e-12 if real == np.float64 else 1e-5
        np.testing.assert_allclose(g1[k], g0[k], rtol=tol, atol=tol * max(np.abs(g0[k]).max(), 1e-30), err_msg=k)


@pytest.mark.parametrize("with_win", [False, True])
def test_prune_fragments_keeps_what_compositing_reaches(device64, rng, with_win):
    """The op against a numpy reference of its rule on random opacities (and windows), on a soup's fragments."""
    from triplet_cl.ops.composite import coverage
    from triplet_cl.ops.interpolate import interpolate

    scene = small_scene(rng, "cook_torrance", M=40)
    r = render(scene, cam(), RenderSettings(K=8, sigma=0.8, real=np.float64), device64)
    fr = r.info["frags"]
    C = 5
    attr = rng.uniform(0.0, 1.0, (scene.V.data.shape[0], C))
    attr[:, 2] = rng.choice([0.3, 0.9, 0.99999], size=len(attr))
    import pyopencl.array as cla

    fa = interpolate(device64, cla.to_device(device64.queue, attr), fr)
    win = coverage(device64, fr, 0.8) if with_win else None
    t_min = 1e-3
    fr2, fa2, win2 = prune_fragments(device64, fr, fa, 2, win, t_min)
    h0, h2 = read_fragments(fr), read_fragments(fr2)
    a_full = fr.to_hwk(fa.get()[:, 2] * (win.get() if with_win else 1.0))
    fa_full, fa_kept = fr.to_hwk(fa.get()), fr2.to_hwk(fa2.get())
    n_ref = np.zeros(h0["count"].shape, int)
    for y, x in np.ndindex(*n_ref.shape):
        T = 1.0
        for i in range(h0["count"][y, x]):
            T *= 1.0 - a_full[y, x, i]
            n_ref[y, x] = i + 1
            if T < PRUNE_MARGIN * t_min:
                break
    np.testing.assert_array_equal(h2["count"], n_ref)
    assert fr2.P == n_ref.sum() <= fr.P
    assert with_win or fr2.P < fr.P
    keep = np.arange(fr.K)[None, None, :] < n_ref[..., None]
    for key in ("face", "entry", "bary", "depth"):
        np.testing.assert_array_equal(h2[key][keep], h0[key][keep])
    np.testing.assert_array_equal(fa_kept[keep], fa_full[keep])
    if with_win:
        np.testing.assert_array_equal(fr2.to_hwk(win2.get())[keep], fr.to_hwk(win.get())[keep])
    else:
        assert win2 is None


def test_prune_fragments_rejects_bad_input(device64, rng):
    scene = small_scene(rng, "cook_torrance")
    r = render(scene, cam(), RenderSettings(K=4, real=np.float64), device64)
    fr = r.info["frags"]
    import pyopencl.array as cla

    fa = cla.to_device(device64.queue, np.zeros((fr.P, 3)))
    with pytest.raises(ValueError, match="alpha_col"):
        prune_fragments(device64, fr, fa, 3, None, 1e-4)
    with pytest.raises(ValueError, match="t_min"):
        prune_fragments(device64, fr, fa, 0, None, 0.0)
    with pytest.raises(ValueError, match="one row per fragment"):
        prune_fragments(device64, fr, cla.to_device(device64.queue, np.zeros((fr.P + 1, 3))), 0, None, 1e-4)


def test_pruned_render_of_a_view_that_sees_nothing(device, rng):
    scene = small_scene(rng, "cook_torrance", mesh=True)
    from triplet_cl.camera import Camera

    away = Camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 6.0], [0, 1, 0], 40, 15, 12)
    r = render(scene, away, RenderSettings(K=4, prune=True, normals="vertex"), device)
    assert r.info["frags"].P == 0
    np.testing.assert_allclose(r.image, np.broadcast_to([1.0, 1.0, 1.0], r.image.shape))
