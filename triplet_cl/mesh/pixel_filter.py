"""The capture's pixel filter, read from the photos' alpha edges (``MeshConfig.pixel_sigma`` ``None``: auto).

A renderer's film (or a camera's optics and demosaicing) spreads each pixel's value over a reconstruction filter:
Mitsuba 3's default is a Gaussian of standard deviation 0.5 pixel, Blender Cycles' a 1.5-pixel Blackman-Harris
(standard deviation ~0.21), a box over the pixel has 0.29. The photos' silhouettes show it: the wider the filter,
the more partly covered pixels per pixel of outline. :func:`edge_ratio` counts them — pixels with alpha strictly
between 0.02 and 0.98 per crossing of the alpha = ½ outline between neighbouring pixels — and
:func:`estimate_pixel_sigma` renders the extracted mesh's alpha from the same views once, supersampled, filters it
with each candidate Gaussian and picks the standard deviation whose renders show the photos' ratio (linear
interpolation between the candidates). Measured on the dev scenes' test views (Mitsuba 3, default film): photos
1.64–1.69, our box-filtered renders 0.75–0.79, our renders with the 0.5 Gaussian 1.60–1.65.

Without alpha in the photos (a capture with a background) there is no clean outline: the default, a Gaussian of
0.5 pixel (a camera's optics and demosaicing blur more than the pixel's box), is used.
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

CANDIDATES = (0.15, 0.25, 0.35, 0.45, 0.55, 0.65, 0.8)  # Gaussian standard deviations tried, in pixels
DEFAULT_SIGMA = 0.5  # without alpha edges to read it from
MIN_CROSSINGS = 200  # fewer outline crossings over the views than this: too little edge to read, the default


def edge_counts(alpha: np.ndarray) -> tuple[int, int]:
    """``(partial, crossings)`` of an ``[H, W]`` alpha image: pixels with 0.02 < alpha < 0.98, and neighbouring pixel
    pairs (horizontal and vertical) on different sides of alpha = ½."""
    a = np.asarray(alpha, np.float64)
    partial = int(((a > 0.02) & (a < 0.98)).sum())
    m = a > 0.5
    crossings = int((m[1:, :] != m[:-1, :]).sum() + (m[:, 1:] != m[:, :-1]).sum())
    return partial, crossings


def edge_ratio(alphas) -> tuple[float, int]:
    """``(partial pixels / outline crossings, crossings)`` summed over the alpha images."""
    p = c = 0
    for a in alphas:
        dp, dc = edge_counts(a)
        p, c = p + dp, c + dc
    return (p / c if c else float("nan")), c


def fit_sigma(photo_ratio: float, candidate_ratios, candidates=CANDIDATES) -> float:
    """The standard deviation whose renders' ratio is ``photo_ratio``: linear interpolation of ``candidates`` over
    their ``candidate_ratios`` (made monotone), clamped to the candidates' range."""
    r = np.maximum.accumulate(np.asarray(candidate_ratios, np.float64))
    s = np.asarray(candidates, np.float64)
    return float(np.interp(photo_ratio, r, s))


def estimate_pixel_sigma(stage, scene, max_views: int = 12) -> dict:
    """The pixel filter of the capture (module docstring) for the mesh stage ``stage`` (a
    :class:`~triplet_cl.mesh.refine.MeshStage`) from its extracted mesh ``scene``: ``{"sigma", "source",
    "photo_ratio", "render_ratios", "views"}``; ``source`` is ``"photos' alpha"`` or ``"default"`` (no or too little
    alpha outline in the photos or in the renders of the mesh)."""
    from ..ops import downsample as down
    from ..render import render

    views = [v for v in stage.ds.train if v.alpha is not None
             and v.alpha.shape == (v.camera.height, v.camera.width)]
    views = views[:: max(1, len(views) // max_views)][:max_views]
    photo_ratio, crossings = edge_ratio(v.alpha for v in views)
    out = {"sigma": DEFAULT_SIGMA, "source": "default", "photo_ratio": None, "render_ratios": None, "views": len(views)}
    if not views or crossings < MIN_CROSSINGS or not np.isfinite(photo_ratio):
        return out
    from .refine import supersample_for

    fs = [supersample_for(v.camera.width, v.camera.height, stage.cfg.supersample, stage.cfg.max_render_pixels)
          for v in views]
    dev = stage.device
    st = stage.settings(np.zeros(3, np.float32))
    from dataclasses import replace

    st = replace(st, transfer=None, downsample=1, pixel_sigma=0.0)
    big_alphas = []
    for v, f in zip(views, fs, strict=True):
        big = v.camera.scaled(f) if f > 1 else v.camera
        r = render(scene, big, st, dev)
        big_alphas.append(np.ascontiguousarray(r.alpha, np.float32))
    big_alphas = [cla.to_device(dev.queue, a) for a in big_alphas]  # uploaded once, filtered by each candidate
    ratios, usable = [], []
    for sigma in CANDIDATES:
        ratio, n = edge_ratio(down.gauss_down(dev, a, f, sigma).get() for a, f in zip(big_alphas, fs, strict=True))
        ratios.append(float(ratio))
        usable.append(n >= MIN_CROSSINGS and np.isfinite(ratio))
    out.update(photo_ratio=float(photo_ratio), render_ratios=ratios)
    if sum(usable) < 2:  # the extracted mesh shows too little outline in these views (off-frame, filling it, tiny)
        return out
    keep = [i for i, u in enumerate(usable) if u]
    sigma = fit_sigma(photo_ratio, [ratios[i] for i in keep], [CANDIDATES[i] for i in keep])
    if np.isfinite(sigma):
        out.update(sigma=sigma, source="photos' alpha")
    return out


__all__ = ["CANDIDATES", "DEFAULT_SIGMA", "edge_counts", "edge_ratio", "estimate_pixel_sigma", "fit_sigma"]
