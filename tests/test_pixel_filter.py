"""The capture's pixel filter read from the photos' alpha edges (``triplet_cl/mesh/pixel_filter.py``): the edge
statistic, the interpolation, and the estimate recovering the filter of "photos" rendered by our own renderer with a
known Gaussian (at another supersampling than the estimate's) — and the default without alpha."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest
import trimesh

from triplet_cl.camera import Camera
from triplet_cl.mesh import pixel_filter as pf
from triplet_cl.ops.downsample import gauss_down
from triplet_cl.render import RenderSettings, render
from triplet_cl.scene import Scene


def test_edge_counts_of_a_hard_and_a_soft_edge():
    a = np.zeros((10, 10))
    a[:, 5:] = 1.0
    assert pf.edge_counts(a) == (0, 10)  # one crossing per row, no partial pixel
    a[:, 4] = 0.3
    a[:, 5] = 0.7
    assert pf.edge_counts(a) == (20, 10)
    ratio, crossings = pf.edge_ratio([a, a])
    assert ratio == 2.0 and crossings == 20


def test_fit_sigma_interpolates_and_clamps():
    cands = (0.2, 0.4, 0.6)
    assert pf.fit_sigma(1.5, [1.0, 1.4, 1.8], cands) == pytest.approx(0.45)
    assert pf.fit_sigma(0.5, [1.0, 1.4, 1.8], cands) == 0.2
    assert pf.fit_sigma(3.0, [1.0, 1.4, 1.8], cands) == 0.6
    assert pf.fit_sigma(1.2, [1.0, 0.9, 1.4], cands) == pytest.approx(0.5)  # made monotone first: 1.0, 1.0, 1.4


def _stage(device, sigma_true, f_photo=4, n=6, px=48, alpha=True):
    """A stand-in for MeshStage: the training views of a sphere whose "photo" alpha is our render at ``f_photo`` ×
    filtered by the Gaussian ``sigma_true`` (None entries without alpha)."""
    ico = trimesh.creation.icosphere(3, radius=0.8)
    scene = Scene.from_arrays(np.asarray(ico.vertices), np.asarray(ico.faces), alpha=np.full((len(ico.vertices), 1),
                                                                                           8.0))
    settings = RenderSettings(K=4, sigma=1.0, soft_edges="silhouette", normals="vertex", two_sided=False)
    views = []
    for i in range(n):
        ang = 2 * np.pi * i / n
        cam = Camera.look_at([2.6 * np.cos(ang), 2.6 * np.sin(ang), 0.7], [0, 0, 0], [0, 0, 1], 40, px, px)
        a = None
        if alpha:
            big = render(scene, cam.scaled(f_photo), settings, device).alpha.astype(np.float32)
            a = gauss_down(device, cla.to_device(device.queue, big), f_photo, sigma_true).get()
        views.append(SimpleNamespace(camera=cam, alpha=a))
    from dataclasses import replace

    stage = SimpleNamespace(ds=SimpleNamespace(train=views),
                            cfg=SimpleNamespace(supersample=3, max_render_pixels=4_000_000), device=device,
                            settings=lambda bg: replace(settings, background=tuple(float(x) for x in bg)))
    return stage, scene


@pytest.mark.parametrize("sigma_true", [0.3, 0.5, 0.7])
def test_estimate_recovers_the_photos_filter(device, sigma_true):
    stage, scene = _stage(device, sigma_true)
    est = pf.estimate_pixel_sigma(stage, scene)
    assert est["source"] == "photos' alpha" and est["views"] == 6
    assert np.all(np.diff(est["render_ratios"]) > 0)  # a wider filter, more partly covered pixels per outline
    assert est["sigma"] == pytest.approx(sigma_true, abs=0.08)


def test_estimate_without_alpha_is_the_default(device):
    stage, scene = _stage(device, 0.5, alpha=False)
    est = pf.estimate_pixel_sigma(stage, scene)
    assert est == {"sigma": pf.DEFAULT_SIGMA, "source": "default", "photo_ratio": None, "render_ratios": None,
                   "views": 0}


def test_estimate_without_outline_in_the_renders_is_the_default(device):
    """The photos show an outline but the extracted mesh is out of every view: too little outline in the renders to
    compare with, the default (not NaN)."""
    stage, scene = _stage(device, 0.5)
    scene.V.data[:] += np.float32(50.0)  # far outside every frustum
    est = pf.estimate_pixel_sigma(stage, scene)
    assert est["sigma"] == pf.DEFAULT_SIGMA and est["source"] == "default" and est["photo_ratio"] > 1


def test_filter_rejects_a_sigma_too_small_to_reach_a_supersample():
    from triplet_cl.ops.downsample import filter_weights

    with pytest.raises(ValueError, match="sigma"):
        filter_weights(4, 0.03, 5)
    wt, inv_norm, _ = filter_weights(16, 0.1, 5)  # the smallest sigma at the largest factor still reaches one
    assert np.isfinite(inv_norm).all() and wt.max() > 0
