"""Adaptive density control of the triangle soup (docs/ARCHITECTURE.md §8): split, clone, prune, alpha reset.

Everything here runs on the host (numpy, vectorised over faces) between optimisation steps.

The soup layout is required and kept: face ``f`` owns vertex rows ``3f, 3f+1, 3f+2`` and
``F = arange(3M).reshape(M, 3)``; every per-vertex parameter (``V``, ``material``, ``alpha``,
``vertex_sh``) has ``N = 3M`` rows.

Statistics (:class:`DensityStats`, the analogue of 3D Gaussian Splatting's ``xyz_gradient_accum`` /
``denom`` / ``max_radii2D``), accumulated once per rendered view between two densification steps,
only for the faces *visible* in that view (any fragment of the face kept by the rasterizer):

- ``grad_accum[f] += ‖Σ_{c=0..2} v_vs[F[f, c], :2]‖`` — the norm of the screen-space (u, v)
  gradient of the face, i.e. the gradient of the loss w.r.t. a 2D translation of the whole
  triangle on the image plane (the sum over its corners), like the gradient of a Gaussian's
  projected centre;
- ``denom[f] += 1``; ``mean_grad() = grad_accum / max(denom, 1)`` (0 for faces never seen);
- ``world_grad_accum[f] += Σ_c v_V[F[f, c]]`` (``[M, 3]``, the world-space position gradient,
  summed raw — not normalised per view): its negative direction is where clones are moved;
- ``max_screen_area[f] = max(.., bbox area of the projected corners (u, v) in pixels)`` and
  ``max_screen_frac[f]`` the same as a fraction of that view's image area (``W·H``), so that the
  screen-size prune criterion survives the resolution schedule (¼ → ½ → full).

**Unit of the gradient threshold.** ``v_vs`` is ``∂L/∂(u, v)`` with ``u, v`` in *pixels of the
rendered resolution*, so ``grad_threshold`` is in loss units per pixel. 3DGS thresholds the
gradient w.r.t. NDC coordinates, which is ``∂L/∂u · W/2``; pass ``grad_scale = 0.5 * W`` (and
``0.5 * H`` is the same for square pixels) to :meth:`DensityStats.add` to accumulate in that unit
and compare against 3DGS-style thresholds independently of the resolution. The loss normalisation
(a mean over pixels) also enters: the per-pixel gradient scales as ``1 / (H·W)``.

**Error criterion** (``error_threshold``; why a second statistic). The screen-space gradient of a
face is ``Σ (pixel error × coverage derivative)`` along its edges, so it is large for big faces on a
silhouette and small for the interior of a face whose *colour* is wrong (per-vertex colours: more
colour detail needs more faces) and for small faces on thin parts. Measured on gadget (lego-like, 100
views at 200², defaults before this criterion, ``bench/density_stats.py``): between
iterations 400 and 900 only the top ≈ 1–2 % of the faces (99th percentile of the mean gradient ≈ the
5e-3 threshold) were ever split (45–100 per step, no clones: every edge > 0.01 · extent), while
the alpha prune removed 130–1300 per step, so the soup shrank from 5.1k to 2.4k. Counting only
the views where the face is the nearest one (``mean_front_grad``) raised the count ≈ 3× — still
~200 faces a step. The faces were large (median projected bbox 160–670 px², mean error over their
nearest pixels: median 0.03, 90th percentile 0.14). ``mean_error`` — the mean absolute colour
error (0–1) over the pixels where the face is the nearest face, over all views of the interval —
is by construction independent of the resolution (a mean over pixels) and of the number of views (a
mean over views), and it is in colour units, so one threshold means the same on every scene: "the
pixels this face draws are off by more than 10 % on average". ``error_min_pixels`` (bbox area in
pixels of the rendered resolution, max over views) stops error-driven refinement once a face is a
few pixels wide: splitting it cannot add detail the images resolve. ``DensityStats.add`` needs
``error`` (``[H, W]``) and ``front`` (:func:`front_faces`) for it; without them ``mean_error`` is 0.

**Re-split rule** (``error_resplit_ratio``). With the error criterion alone the soup kept growing on
spot and gadget (120–290 error splits per step from iteration 400 to 2400, no levelling off), and
1.5–3 % of the faces kept ``mean_error ≥ 0.1`` after being split: an error that more geometry cannot
fix (shading / lighting mismatch). So a face densified by the error criterion records its mean error
(``DensifyReport.split_error``; the 4 children of a split, a clone and its source inherit it; faces
never split by error have ``inf``), and the error criterion selects it again only when its error is
``≤ error_resplit_ratio × record`` (the split helped). The gradient criterion is not affected.
The caller carries the records from one call to the next (permuted with the faces: the trainer
reorders them with :func:`reorder_faces`' order) and stores them in its checkpoints.

Order of one :func:`densify_and_prune` call (every mask is computed on the state *before* any face
is moved, removed or added — the original implementation computed its clone mask after the split
had reordered the faces):

1. **prune** candidates: face alpha ``≤ prune_alpha``, world area ``> prune_world_area · extent²``
   or max screen fraction ``> prune_screen_frac``; at most ``min(M − min_faces,
   ⌊max_prune_fraction · M⌋)`` are pruned (most transparent first, then the largest): a prune
   that would empty (or gut) the soup is limited to that many faces, never executed in full.
   Pruning takes precedence: a pruned face is neither split nor cloned.
2. **densify** candidates: ``mean_grad ≥ grad_threshold`` — or, with ``error_threshold`` set,
   ``mean_error ≥ error_threshold`` for a face whose projected bbox reached ``error_min_pixels``
   pixels (see *Error criterion* below) — among the faces not pruned; those whose
   longest edge ``> split_edge_ratio · extent`` are split, the others cloned (clones do happen since the
   error criterion splits faces down to that size: totals over the 3000-iteration runs with today's
   defaults, clones / splits — spot 66 / 3632, gadget 154 / 2955, bob_env 1082 / 5582, spot_small 46 / 882;
   so the clone rule is kept). When the result would
   exceed ``max_faces``, candidates are taken by decreasing ``max(mean_grad / grad_threshold,
   mean_error / error_threshold)`` (a split costs +3 faces, a
   clone +1) until the budget is spent.
3. the new soup is written: surviving faces (not pruned, not split) in their original order, then
   the 4 children of every split face (in parent order), then the clones (in source order).
4. every per-vertex optimizer group is remapped (:meth:`triplet_cl.optim.Adam.remap`): surviving
   rows keep their Adam moments, new rows (children and clones) get **zero** moments
   (``index_map = −1``; 3DGS does the same for densified points) or, with ``inherit_moments``, the
   moments of their parent's corner (a midpoint: its edge's first corner), and the statistics are
   reset. Why inherit: with one global step count ``t`` and the method's betas (0.5, 0.999), a
   zero-moment row's first update is ``m̂/√v̂ = 0.5 / √(0.001 / (1 − 0.999^t))`` ≈ 11× the learning
   rate at t = 700 (and still ≈ 2× a hundred steps later). Measured on gadget with the error
   criterion: with zero moments (1000+ new faces a step) the training loss rose to 0.058–0.072 by
   iterations 800–900 (the gradient-only run: 0.017–0.024); with inherited moments it was
   0.010–0.012 there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla
from scipy.special import expit

from .activations import inverse_softplus, logit
from .autodiff.arrays import to_host
from .materials import DEFAULT_BRDF, get_brdf
from .optim import owning_groups

__all__ = [
    "CHILDREN",
    "DensifyReport",
    "DensityConfig",
    "DensityStats",
    "check_soup",
    "densify_and_prune",
    "face_alpha",
    "face_areas",
    "face_longest_edges",
    "front_faces",
    "reset_alpha",
    "split_faces",
    "vertex_params",
    "visible_faces",
]

# Midpoint subdivision of a parent (a, b, c) = points 0, 1, 2 with midpoints m01 = 3, m12 = 4,
# m20 = 5: three corner children and the centre one, all with the parent's orientation.
CHILDREN = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]], dtype=np.int64)
_MID_PAIRS = np.array([[0, 1], [1, 2], [2, 0]], dtype=np.int64)
_PARENT_CORNER = np.array([0, 1, 2, 0, 1, 2], dtype=np.int64)  # the parent corner of points 0..5 (moments)


# ---------------------------------------------------------------------------------------------
# configuration and report
# ---------------------------------------------------------------------------------------------


@dataclass
class DensityConfig:
    """Settings of density control (defaults: the method's values for objects, docs/ARCHITECTURE.md §8)."""

    interval: int = 100  # densify every `interval` iterations ...
    densify_from: int = 500  # ... strictly after this iteration ...
    densify_until: int = 15_000  # ... and strictly before this one (stats are accumulated until then)
    grad_threshold: float = 7.5e-5  # mean ‖∂L/∂(u,v)‖ per face, loss per *pixel of the rendered resolution*
    #                                 (times `grad_scale` given to DensityStats.add); 2e-4 for scenes
    error_threshold: float | None = None  # also densify faces whose mean per-pixel error (over the pixels
    #                                       where they are the nearest face) ≥ this (None: off) ...
    error_min_pixels: float = 4.0  # ... and whose projected bbox reached this many pixels in some view
    error_min_alpha: float = 0.5  # a pixel's error belongs to its nearest face with alpha ≥ this (the trainer)
    split_edge_ratio: float = 0.01  # longest edge > ratio·extent: split into 4, otherwise clone
    clone_step: float = 0.5  # a clone is translated by clone_step × (its longest edge) along −∇_V
    prune_alpha: float = 0.05  # prune faces whose alpha (max over its vertices) ≤ this
    prune_world_area: float = 0.1  # prune faces whose world area > this × extent²
    prune_screen_frac: float = 0.001  # prune faces whose max 2D bbox area > this fraction of the image
    alpha_reset_interval: int = 3000  # every this many iterations: alpha = min(alpha, alpha_reset_value)
    alpha_reset_value: float = 0.01  # cap of the alpha reset (activated value)
    max_faces: int | None = None  # never densify above this many faces (None: no limit)
    min_faces: int = 1  # never prune below this many faces (an empty soup cannot be optimised)
    inherit_moments: bool = False  # children / clones start with their parent's Adam moments (False: zero)
    error_resplit_ratio: float | None = None  # a face densified by the error criterion records its mean error
    #                                           (children / clones inherit it); it is densified by error again
    #                                           only once its error is <= ratio x that record (None: off)
    max_prune_fraction: float = 1.0  # one call prunes at most this fraction of its faces (most transparent
    #                                  first): a prune that would empty the soup is limited, not executed
    split_interp: str = "raw"  # children's midpoint attributes: "raw" (linear on raw values) or
    #                            "activated" (linear on sigmoid/softplus values, mapped back: render-exact)

    def __post_init__(self):
        if self.interval <= 0 or self.alpha_reset_interval <= 0:
            raise ValueError(f"interval and alpha_reset_interval must be > 0, got {self.interval}, "
                             f"{self.alpha_reset_interval}")
        if self.grad_threshold <= 0:
            raise ValueError(f"grad_threshold must be > 0, got {self.grad_threshold}")
        if not 0.0 < self.alpha_reset_value < 1.0 or not 0.0 <= self.prune_alpha < 1.0:
            raise ValueError("alpha_reset_value must lie in (0, 1) and prune_alpha in [0, 1)")
        if self.error_threshold is not None and not self.error_threshold > 0:
            raise ValueError(f"error_threshold must be > 0 or None, got {self.error_threshold}")
        if not 0.0 <= self.error_min_alpha < 1.0:
            raise ValueError(f"error_min_alpha must lie in [0, 1), got {self.error_min_alpha}")
        if self.error_min_pixels < 0:
            raise ValueError(f"error_min_pixels must be >= 0, got {self.error_min_pixels}")
        if self.error_resplit_ratio is not None and not self.error_resplit_ratio > 0:
            raise ValueError(f"error_resplit_ratio must be > 0 or None, got {self.error_resplit_ratio}")
        if self.split_edge_ratio < 0 or self.clone_step < 0:
            raise ValueError("split_edge_ratio and clone_step must be >= 0")
        if self.min_faces < 0 or (self.max_faces is not None and self.max_faces < self.min_faces):
            raise ValueError(f"need 0 <= min_faces <= max_faces, got {self.min_faces}, {self.max_faces}")
        if not 0.0 < self.max_prune_fraction <= 1.0:
            raise ValueError(f"max_prune_fraction must lie in (0, 1], got {self.max_prune_fraction}")
        if self.split_interp not in ("raw", "activated"):
            raise ValueError(f"split_interp must be 'raw' or 'activated', got {self.split_interp!r}")

    def densify_at(self, iteration: int) -> bool:
        """Whether to call :func:`densify_and_prune` after completed step ``iteration`` (1-based, 3DGS's
        ``densify_from < it < densify_until and it % interval == 0``)."""
        return self.densify_from < iteration < self.densify_until and iteration % self.interval == 0

    def reset_alpha_at(self, iteration: int) -> bool:
        """Whether to call :func:`reset_alpha` after completed step ``iteration`` (only while densifying)."""
        return 0 < iteration < self.densify_until and iteration % self.alpha_reset_interval == 0


@dataclass
class DensifyReport:
    """What one :func:`densify_and_prune` call did."""

    faces_before: int
    faces_after: int
    split: int  # parents split (each replaced by 4 children: +3 faces)
    cloned: int  # faces cloned (+1 face each)
    pruned: int  # faces removed by the prune criteria
    pruned_alpha: int = 0  # prune candidates by criterion (a face may meet several; before min_faces)
    pruned_world_area: int = 0
    pruned_screen: int = 0
    by_error: int = 0  # densify candidates selected by the error criterion only (not by the gradient)
    error_blocked: int = 0  # faces over the error threshold refused by error_resplit_ratio (no drop since last split)
    split_error: np.ndarray | None = None  # [faces_after] the error record of every new face (error_resplit_ratio)
    skipped_max_faces: int = 0  # densify candidates dropped to respect max_faces
    spared_min_faces: int = 0  # prune candidates kept to respect min_faces / max_prune_fraction


# ---------------------------------------------------------------------------------------------
# per-face geometry
# ---------------------------------------------------------------------------------------------


def _corners(V, F) -> np.ndarray:
    return np.asarray(V, np.float64)[np.asarray(F)]  # [M, 3, 3]


def face_areas(V, F) -> np.ndarray:
    """``[M]`` world-space triangle areas ``½‖(b − a) × (c − a)‖``."""
    P = _corners(V, F)
    return 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)


def face_longest_edges(V, F) -> np.ndarray:
    """``[M]`` longest edge length of each triangle."""
    P = _corners(V, F)
    return np.linalg.norm(P - P[:, [1, 2, 0]], axis=2).max(axis=1)


def face_alpha(alpha_raw, F) -> np.ndarray:
    """``[M]`` face alpha used by the prune criterion: the **max** over the 3 vertices of
    ``sigmoid(raw alpha)``. The renderer interpolates activated alpha linearly across the face, so this
    bounds the alpha anywhere on it: a face is pruned only when it is transparent everywhere."""
    a = np.asarray(alpha_raw, np.float64).reshape(-1)
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3:
        return expit(a[F].max(axis=1))
    # the max of the three corners as two elementwise maxima of column gathers: the same values (max is exact,
    # NaN propagates alike) as ``a[F].max(axis=1)``, ~4x faster (a reduction over an axis of 3 is slow in numpy)
    return expit(np.maximum(np.maximum(a[F[:, 0]], a[F[:, 1]]), a[F[:, 2]]))


def visible_faces(face_ids, num_faces: int, device=None) -> np.ndarray:
    """``[M] bool``: faces with at least one fragment in ``face_ids`` (the rasterizer's ``frags.face``
    ``[P]``, or any array of face ids with −1 = empty; numpy or device array).

    ``device`` (a :class:`~triplet_cl.device.Device`) with an int32 device array: the ``visible_mark``
    kernel (``ops/face_visibility.py``) marks the faces there and only ``[M]`` bytes come down (the
    same result; this host bincount is its reference)."""
    if device is not None and isinstance(face_ids, cla.Array) and face_ids.dtype == np.int32:
        from .ops.face_visibility import visible_mask

        return visible_mask(device, face_ids.reshape(-1), num_faces)
    f = to_host(face_ids).reshape(-1)
    f = f[f >= 0]
    return np.bincount(f, minlength=num_faces)[:num_faces] > 0


# ---------------------------------------------------------------------------------------------
# statistics
# ---------------------------------------------------------------------------------------------


class DensityStats:
    """Per-face statistics between two densification steps (see the module docstring for the maths).

    Attributes (all ``[M]`` unless noted): ``grad_accum`` (Σ over views of the face's screen-gradient
    norm), ``denom`` (number of views where the face was visible), ``world_grad_accum [M, 3]``,
    ``max_screen_area`` (pixels) and ``max_screen_frac`` (fraction of the image).
    """

    def __init__(self, num_faces: int):
        self.reset(num_faces)

    @property
    def num_faces(self) -> int:
        return int(self.denom.shape[0])

    def reset(self, num_faces: int) -> None:
        """Zero every statistic for a soup of ``num_faces`` faces."""
        if num_faces < 0:
            raise ValueError(f"num_faces must be >= 0, got {num_faces}")
        m = int(num_faces)
        self.grad_accum = np.zeros(m, np.float64)
        self.denom = np.zeros(m, np.int64)
        self.world_grad_accum = np.zeros((m, 3), np.float64)
        self.max_screen_area = np.zeros(m, np.float64)
        self.max_screen_frac = np.zeros(m, np.float64)
        self.front_views = np.zeros(m, np.int64)
        self.front_grad_accum = np.zeros(m, np.float64)
        self.err_accum = np.zeros(m, np.float64)
        self.err_pixels = np.zeros(m, np.int64)

    def add(self, v_vs, visible, F, *, vs=None, image_size=None, v_V=None, grad_scale: float = 1.0,
            device=None, front=None, error=None) -> None:
        """Accumulate one rendered view.

        Args:
            v_vs: ``[N, 3]`` (or ``[N, 2]``) adjoint of each vertex's screen position (u, v[, z]) from
                ``fragments_backward`` (numpy or device); only (u, v) is used.
            visible: ``[M] bool`` faces visible in the view (:func:`visible_faces`); only they are updated.
            F: ``[M, 3]`` faces.
            vs: optional ``[N, 3]`` projected vertices (u, v, z) for the screen-size statistic; needs
                ``image_size = (width, height)`` of that render.
            v_V: optional ``[N, 3]`` world-space position gradient of the view (e.g. ``scene.V.grad``).
            grad_scale: multiplies the screen gradient (e.g. ``0.5 * width`` for 3DGS's NDC units).
            device: a :class:`~triplet_cl.device.Device` with fp64: the update runs as the
                ``face_stats_add`` kernel (``kernels_cl/density.cl``, one pass over the faces, on the
                statistics arrays themselves, the front-visibility statistics included; the per-pixel
                bincounts of ``front`` / ``error`` stay numpy), bit for bit the numpy update; None: numpy.
            front: optional ``[H, W]`` id of the nearest face of every pixel (−1: none; :func:`front_faces`)
                for the front-visibility statistics ``front_views`` / ``front_grad_accum``.
            error: optional ``[H, W]`` per-pixel photometric error of the view (e.g. the mean absolute
                colour error); with ``front``, accumulates ``err_accum`` / ``err_pixels`` per face.
        """
        F = np.asarray(F)
        m = self.num_faces
        if F.shape != (m, 3):
            raise ValueError(f"F must have shape [{m}, 3] (stats were reset for {m} faces), got {list(F.shape)}")
        vis = np.asarray(to_host(visible))
        if vis.shape != (m,) or vis.dtype != np.bool_:
            raise ValueError(f"visible must be a bool array of shape [{m}], got {vis.dtype} {list(vis.shape)}")
        g = to_host(v_vs)
        if g.ndim != 2 or g.shape[1] not in (2, 3) or (m and g.shape[0] <= F.max()):
            raise ValueError(f"v_vs must have shape [N, 3] or [N, 2] covering F, got {list(g.shape)}")
        fmap = e = None
        if front is not None:
            fmap = np.asarray(to_host(front)).reshape(-1).astype(np.int64)
            if fmap.size and fmap.max() >= m:
                raise ValueError(f"front holds face ids up to {fmap.max()}, the soup has {m} faces")
            if error is not None:
                e = np.asarray(to_host(error), np.float64).reshape(-1)
                if e.shape != fmap.shape:
                    raise ValueError(f"error must have the shape of front ({fmap.size} pixels), got {e.size}")
        elif error is not None:
            raise ValueError("error needs front (the nearest face of every pixel, density.front_faces)")
        gw = uv = None
        if v_V is not None:
            gw = to_host(v_V)
            if gw.ndim != 2 or gw.shape[1] != 3 or gw.shape[0] != g.shape[0]:
                raise ValueError(f"v_V must have shape [{g.shape[0]}, 3], got {list(gw.shape)}")
        if vs is not None:
            if image_size is None:
                raise ValueError("image_size=(width, height) is required with vs")
            w, h = (int(x) for x in image_size)
            if w <= 0 or h <= 0:
                raise ValueError(f"image_size must be positive, got {image_size}")
            uv = to_host(vs)
        on_device = device is not None and device.fp64 and m
        if on_device:
            npix = None
            if front is not None:
                on = fmap >= 0
                npix = np.bincount(fmap[on], minlength=m)
            self._add_device(device, F, vis, g, gw, uv, None if vs is None else w * h, float(grad_scale),
                             None if npix is None else npix > 0)
            if front is None:
                return
            # the front statistics of the visible faces came from the kernel; a face nearest somewhere but not
            # in ``visible`` (inconsistent inputs only) counts its view with a zero gradient, as below
            self.front_views[(npix > 0) & ~vis] += 1
            if error is not None:
                self.err_accum += np.bincount(fmap[on], weights=e[on], minlength=m)
                self.err_pixels += npix
            return
        g = np.asarray(g, np.float64)
        idx = np.flatnonzero(vis)
        Fv = F[idx]
        g_face = g[Fv, :2].sum(axis=1)  # [m_vis, 2]: Σ over corners
        self.grad_accum[idx] += float(grad_scale) * np.linalg.norm(g_face, axis=1)
        self.denom[idx] += 1
        if gw is not None:
            self.world_grad_accum[idx] += np.asarray(gw, np.float64)[Fv].sum(axis=1)
        if uv is not None:
            uv = np.asarray(uv, np.float64)[:, :2][Fv]  # [m_vis, 3, 2]
            ext = uv.max(axis=1) - uv.min(axis=1)
            area = ext[:, 0] * ext[:, 1]
            self.max_screen_area[idx] = np.maximum(self.max_screen_area[idx], area)
            self.max_screen_frac[idx] = np.maximum(self.max_screen_frac[idx], area / (w * h))
        if front is not None:  # the front-visibility and error statistics (host: per-pixel bincounts)
            on = fmap >= 0
            npix = np.bincount(fmap[on], minlength=m)
            fv = npix > 0
            gn = np.zeros(m)
            gn[idx] = float(grad_scale) * np.linalg.norm(g_face, axis=1)
            self.front_views[fv] += 1
            self.front_grad_accum[fv] += gn[fv]
            if error is not None:
                self.err_accum += np.bincount(fmap[on], weights=e[on], minlength=m)
                self.err_pixels += npix

    def _add_device(self, device, F, vis, g, gw, uv, image_area, grad_scale, front_hit=None) -> None:
        """:meth:`add` as the ``face_stats_add`` kernel; the statistics (numpy) are the kernel's
        buffers (USE_HOST_PTR: no copy on a CPU device) and are mapped back afterwards."""
        import pyopencl as cl

        from .ops.common import run_1d

        inputs = [a for a in (g, gw, uv) if a is not None]
        real = np.float32 if all(np.asarray(a).dtype == np.float32 for a in inputs) else np.float64
        mf = cl.mem_flags
        written = []

        def src(a, dtype=real):
            a = np.ascontiguousarray(a, dtype=dtype)
            return a, cl.Buffer(device.ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=a)

        def dst(a):
            written.append(cl.Buffer(device.ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=a))
            return written[-1]

        for name in ("grad_accum", "denom", "world_grad_accum", "max_screen_area", "max_screen_frac", "front_views",
                     "front_grad_accum"):
            if not getattr(self, name).flags.c_contiguous:
                setattr(self, name, np.ascontiguousarray(getattr(self, name)))
        keep = [src(F, np.int32), src(vis, np.uint8), src(g)]  # the host arrays stay alive until finish()
        args = [keep[0][1], keep[1][1], np.int32(len(F)), keep[2][1], np.float64(grad_scale)]
        defines = {"VS_STRIDE": int(g.shape[1])}
        if gw is not None:
            keep.append(src(gw))
            args += [keep[-1][1], dst(self.world_grad_accum)]
            defines["V_GRAD"] = 1
        if uv is not None:
            keep.append(src(uv))
            args += [keep[-1][1], np.float64(image_area), dst(self.max_screen_area), dst(self.max_screen_frac)]
            defines["VS"] = 1
        if front_hit is not None:
            keep.append(src(front_hit, np.uint8))
            args += [keep[-1][1], dst(self.front_views), dst(self.front_grad_accum)]
            defines["FRONT"] = 1
        args += [dst(self.grad_accum), dst(self.denom)]
        run_1d(device, device.kernel("density", "face_stats_add", defines, real=real), len(F), *args)
        q = device.queue
        for buf in written:
            mapped, _ = cl.enqueue_map_buffer(q, buf, cl.map_flags.READ, 0, (buf.size,), np.uint8)
            mapped.base.release(q)
        q.finish()

    def mean_grad(self) -> np.ndarray:
        """``[M]`` ``grad_accum / denom`` (0 for faces never visible)."""
        return self.grad_accum / np.maximum(self.denom, 1)

    def mean_front_grad(self) -> np.ndarray:
        """``[M]`` mean screen-gradient norm over the views where the face is the *nearest* face of at
        least one pixel (0 if never): views where it is only hidden behind others do not dilute it."""
        return self.front_grad_accum / np.maximum(self.front_views, 1)

    def mean_error(self) -> np.ndarray:
        """``[M]`` mean per-pixel error over the pixels where the face is the nearest (0 if none)."""
        return self.err_accum / np.maximum(self.err_pixels, 1)


def front_faces(frags, face_alpha=None, min_alpha: float = 0.0, device=None) -> np.ndarray:
    """Host ``[H, W] int64``: the nearest face of every pixel of a
    :class:`~triplet_cl.ops.fragments.Fragments` (its first packed fragment), −1 where none.

    With ``face_alpha`` (``[M]``, e.g. :func:`face_alpha`) the nearest face whose alpha ≥ ``min_alpha``:
    a faint face in front (a floater, a face fading out) does not own the colour of the pixel, the
    first (nearly) opaque one behind it does.

    ``device`` (a :class:`~triplet_cl.device.Device`): the ``front_face`` kernel walks each pixel's
    fragments there (``ops/face_visibility.py``; the alpha test ``face_alpha ≥ min_alpha`` is decided
    here per face, in float64 as below) and only the ``[H, W]`` map comes down: the same result, without
    the ``[P]`` download and the sort of this host path (its reference)."""
    if device is not None:
        from .ops.face_visibility import front_face_map

        ok = None
        if face_alpha is not None and min_alpha > 0.0:
            ok = np.asarray(face_alpha, np.float64).reshape(-1) >= min_alpha
        return front_face_map(device, frags, ok)
    count = np.asarray(to_host(frags.count)).reshape(-1).astype(np.int64)
    face = np.asarray(to_host(frags.face)).reshape(-1).astype(np.int64)
    out = np.full(count.size, -1, np.int64)
    if face_alpha is None or min_alpha <= 0.0:
        off = np.asarray(to_host(frags.off)).reshape(-1)[:-1]
        has = count > 0
        out[has] = face[off[has]]
    else:
        fa = np.asarray(face_alpha, np.float64).reshape(-1)
        pix = np.repeat(np.arange(count.size), count)  # packed rows are nearest first within a pixel
        ok = np.flatnonzero((face >= 0) & (fa[np.maximum(face, 0)] >= min_alpha))
        first_pix, first = np.unique(pix[ok], return_index=True)
        out[first_pix] = face[ok[first]]
    return out.reshape(int(frags.height), int(frags.width))


# ---------------------------------------------------------------------------------------------
# soup helpers
# ---------------------------------------------------------------------------------------------


def vertex_params(scene) -> list:
    """The per-vertex parameters of ``scene`` (positions, material, alpha, vertex SH): the arrays
    density control and remeshing remap row by row."""
    return [p for p in (scene.V, scene.material, scene.alpha, scene.vertex_sh) if p is not None]


def check_soup(scene) -> int:
    """Raise ValueError unless ``scene`` is a soup in the canonical layout; return its face count."""
    F = np.asarray(scene.F)
    n = np.asarray(scene.V.data).shape[0]
    if F.ndim != 2 or F.shape[1] != 3 or n != 3 * F.shape[0] or not np.array_equal(F, np.arange(n).reshape(-1, 3)):
        raise ValueError("density control needs a triangle soup with F = arange(3M).reshape(M, 3) (vertices of face f "
                         f"are 3f, 3f+1, 3f+2); got F {list(F.shape)} with {n} vertices")
    for p in vertex_params(scene):
        if np.asarray(p.data).shape[0] != n:
            raise ValueError(f"per-vertex parameter {p.name!r} has {np.asarray(p.data).shape[0]} rows, expected {n}")
    return F.shape[0]


def _logit(p):
    return logit(p, eps=None)


def _inv_softplus(y):
    return inverse_softplus(y, floor=1e-300, linear_above=30.0)


def _midpoints(X, space: str, kind: str, brdf: str) -> np.ndarray:
    """``X [S, 3, ...]`` raw corner values → ``[S, 3, ...]`` values at the edge midpoints (m01, m12, m20)."""
    a, b = X[:, _MID_PAIRS[:, 0]], X[:, _MID_PAIRS[:, 1]]
    mid = 0.5 * (a + b)
    if space == "raw" or kind not in ("material", "alpha"):
        return mid
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    act = _logit(np.clip(0.5 * (expit(a) + expit(b)), 1e-300, 1.0 - 1e-16))
    for j in get_brdf(brdf).softplus_columns if kind == "material" else ():  # e.g. Blinn-Phong shininess
        sp = np.logaddexp(0.0, a[..., j]) + np.logaddexp(0.0, b[..., j])
        act[..., j] = _inv_softplus(0.5 * sp)
    return np.clip(act, lo, hi)  # the activated midpoint lies between the corners; clip rounding


def split_faces(X, space: str = "raw", kind: str = "linear", brdf: str = DEFAULT_BRDF) -> np.ndarray:
    """Children of midpoint subdivision: ``X [S, 3, ...]`` per-corner values of S parents →
    ``[S, 4, 3, ...]`` per-corner values of their 4 children (:data:`CHILDREN`). Corner vertices are
    copied exactly; midpoints are linear on the raw values (``space="raw"``) or, for ``kind`` in
    ``{"material", "alpha"}`` with ``space="activated"``, linear on the activated values."""
    X = np.asarray(X, np.float64)
    P6 = np.concatenate([X, _midpoints(X, space, kind, brdf)], axis=1)  # [S, 6, ...]
    return P6[:, CHILDREN]


def _apply(scene, optimizer, index_map: np.ndarray, new_data: dict[int, np.ndarray], num_faces: int) -> None:
    vparams = vertex_params(scene)
    groups = owning_groups(optimizer, vparams)
    done = set()
    for name, params in groups.items():
        optimizer.remap(name, index_map, [new_data[id(p)] for p in params])
        done |= {id(p) for p in params}
    for p in vparams:
        if id(p) not in done:  # not optimised: only the values follow
            p.data = np.ascontiguousarray(new_data[id(p)].astype(p.data.dtype, copy=False))
            p.grad = None
    scene.F = np.arange(3 * num_faces, dtype=np.int32).reshape(num_faces, 3)


def reorder_faces(scene, optimizer, order: np.ndarray) -> None:
    """Permute the soup's faces (``order[new] = old face``) with their vertices, attributes and
    optimizer moments (e.g. by :func:`triplet_cl.topology.morton_order` of the face centroids)."""
    M = check_soup(scene)
    order = np.asarray(order, np.int64)
    if order.shape != (M,) or not np.array_equal(np.sort(order), np.arange(M)):
        raise ValueError(f"order must be a permutation of the {M} faces")
    index_map = (3 * order[:, None] + np.arange(3)[None, :]).reshape(-1)
    new_data = {id(p): np.asarray(p.data)[index_map] for p in vertex_params(scene)}
    _apply(scene, optimizer, index_map, new_data, M)


# ---------------------------------------------------------------------------------------------
# density control
# ---------------------------------------------------------------------------------------------


def densify_and_prune(scene, optimizer, stats: DensityStats, config: DensityConfig, extent: float, *,
                      densify: bool = True, prune: bool = True, prune_screen: bool = True,
                      split_error: np.ndarray | None = None) -> DensifyReport:
    """Split, clone and prune the soup of ``scene`` in place (see the module docstring for the order).

    Args:
        scene: a :class:`~triplet_cl.scene.Scene` soup (``F = arange(3M).reshape(M, 3)``, else ValueError).
        optimizer: the :class:`~triplet_cl.optim.Adam` whose groups hold the scene's per-vertex
            parameters (found by identity; a group must hold only per-vertex parameters), or None.
        stats: statistics accumulated since the last call (``stats.num_faces == M``); reset on return.
        config: thresholds; extent: the scene extent (radius of the cameras / object, world units).
        densify, prune: switch the two halves; prune_screen: use the screen-size criterion (3DGS
            enables it only after the first alpha reset).
        split_error: ``[M]`` per-face error records for ``config.error_resplit_ratio`` (the previous
            report's ``split_error``, permuted with the faces; None: no face has a record, ``inf``).

    Returns:
        a :class:`DensifyReport`. ``scene.V/material/alpha/vertex_sh`` and ``scene.F`` are replaced, the
        optimizer's moments follow (surviving rows keep theirs, new rows start at zero).
    """
    m = check_soup(scene)
    if stats.num_faces != m:
        raise ValueError(f"stats hold {stats.num_faces} faces, the scene has {m} (reset the stats after changes)")
    if not (np.isfinite(extent) and extent > 0):
        raise ValueError(f"extent must be > 0, got {extent}")
    if split_error is None:
        split_error = np.full(m, np.inf)
    split_error = np.asarray(split_error, np.float64)
    if split_error.shape != (m,):
        raise ValueError(f"split_error must have shape [{m}], got {list(split_error.shape)}")
    F = np.asarray(scene.F)
    V = np.asarray(scene.V.data)

    # ---- every mask on the state before any change --------------------------------------------
    grads = stats.mean_grad()
    longest = face_longest_edges(V, F)
    alpha_f = face_alpha(scene.alpha.data, F)
    by_alpha = alpha_f <= config.prune_alpha
    by_world = face_areas(V, F) > config.prune_world_area * extent**2
    by_screen = stats.max_screen_frac > config.prune_screen_frac if prune_screen else np.zeros(m, bool)
    prune_cand = (by_alpha | by_world | by_screen) if prune else np.zeros(m, bool)
    cand_idx = np.flatnonzero(prune_cand)
    allowed = max(0, min(m - config.min_faces, int(np.floor(config.max_prune_fraction * m))))
    if cand_idx.size > allowed:  # most transparent first, then the largest
        order = np.lexsort((-longest[cand_idx], alpha_f[cand_idx]))
        cand_idx = cand_idx[order[:allowed]]
    prune_mask = np.zeros(m, bool)
    prune_mask[cand_idx] = True

    # priority of a densify candidate: how far its statistic is above its threshold (≥ 1 = candidate)
    prio = grads / config.grad_threshold
    n_by_error = n_blocked = 0
    err_prio = np.zeros(m)
    mean_err = stats.mean_error() if config.error_threshold is not None else np.zeros(m)
    if config.error_threshold is not None:
        err_prio = np.where(stats.max_screen_area >= config.error_min_pixels, mean_err / config.error_threshold, 0.0)
        if config.error_resplit_ratio is not None:  # no drop since its last error split: splitting did not help
            stuck = (err_prio >= 1.0) & (mean_err > config.error_resplit_ratio * split_error)
            n_blocked = int((stuck & (prio < 1.0) & ~prune_mask).sum()) if densify else 0
            err_prio = np.where(stuck, 0.0, err_prio)
        n_by_error = int(((err_prio >= 1.0) & (prio < 1.0) & ~prune_mask).sum()) if densify else 0
        prio = np.maximum(prio, err_prio)
    dens = (prio >= 1.0) & ~prune_mask if densify else np.zeros(m, bool)
    big = longest > config.split_edge_ratio * extent
    d_idx = np.flatnonzero(dens)
    skipped = 0
    if config.max_faces is not None:
        budget = config.max_faces - (m - int(prune_mask.sum()))
        cost = np.where(big[d_idx], 3, 1)
        if cost.sum() > budget:
            order = np.argsort(-prio[d_idx], kind="stable")
            take = order[np.cumsum(cost[order]) <= budget]
            skipped = d_idx.size - take.size
            d_idx = np.sort(d_idx[take])
    split_idx = d_idx[big[d_idx]]
    clone_idx = d_idx[~big[d_idx]]

    # ---- new soup: survivors, children of splits, clones ----------------------------------------
    keep = np.ones(m, bool)
    keep[prune_mask] = False
    keep[split_idx] = False
    keep_idx = np.flatnonzero(keep)
    s, c = split_idx.size, clone_idx.size
    m_new = keep_idx.size + 4 * s + c
    if config.inherit_moments:  # a child vertex: its parent's corner (a midpoint: the edge's first corner)
        new_rows = np.concatenate([(3 * split_idx[:, None, None] + _PARENT_CORNER[CHILDREN][None]).reshape(-1),
                                   (3 * clone_idx[:, None] + np.arange(3)).reshape(-1)])
    else:
        new_rows = np.full(12 * s + 3 * c, -1)
    index_map = np.concatenate([(3 * keep_idx[:, None] + np.arange(3)).reshape(-1), new_rows]).astype(np.int64)

    shift = None
    if c:
        g = stats.world_grad_accum[clone_idx]
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        direction = np.divide(g, norm, out=np.zeros_like(g), where=norm > 0)
        shift = -config.clone_step * longest[clone_idx, None] * direction  # [C, 3]

    new_data = {}
    kinds = {id(scene.V): "position", id(scene.material): "material", id(scene.alpha): "alpha"}
    for p in vertex_params(scene):
        X = np.asarray(p.data)
        Xf = X.reshape(m, 3, *X.shape[1:])
        children = split_faces(Xf[split_idx], config.split_interp, kinds.get(id(p), "linear"), scene.brdf)
        clones = Xf[clone_idx].astype(np.float64)
        if p is scene.V and c:
            clones = clones + shift[:, None, :]
        tail = X.shape[1:]
        new_data[id(p)] = np.concatenate([Xf[keep_idx].reshape(-1, *tail),
                                          children.reshape(-1, *tail).astype(X.dtype),
                                          clones.reshape(-1, *tail).astype(X.dtype)]).astype(X.dtype, copy=False)
    # error records: a face densified by the error criterion records its error, children / clones inherit
    rec = np.where(err_prio >= 1.0, mean_err, split_error)
    new_rec = np.concatenate([split_error[keep_idx], np.repeat(rec[split_idx], 4), rec[clone_idx]])
    if c:
        rec_src = split_error.copy()
        rec_src[clone_idx] = rec[clone_idx]  # the source of a clone was densified too
        new_rec[:keep_idx.size] = rec_src[keep_idx]
    _apply(scene, optimizer, index_map, new_data, m_new)
    stats.reset(m_new)
    return DensifyReport(
        faces_before=m, faces_after=m_new, split=s, cloned=c, pruned=int(prune_mask.sum()),
        pruned_alpha=int((by_alpha & prune).sum()), pruned_world_area=int((by_world & prune).sum()),
        pruned_screen=int((by_screen & prune).sum()), by_error=n_by_error, skipped_max_faces=int(skipped),
        error_blocked=n_blocked, split_error=new_rec,
        spared_min_faces=int(prune_cand.sum() - prune_mask.sum()))


def reset_alpha(scene, optimizer=None, value: float = 0.01) -> int:
    """``alpha = min(alpha, value)`` (activated), i.e. ``raw = min(raw, logit(value))``, and zero the Adam
    moments of the alpha parameter (3DGS ``reset_opacity``). Returns the number of vertices lowered."""
    if not 0.0 < value < 1.0:
        raise ValueError(f"value must lie in (0, 1), got {value}")
    p = scene.alpha
    cap = float(_logit(np.float64(value)))
    raw = np.asarray(p.data)
    lowered = int(np.count_nonzero(raw > cap))
    p.data = np.ascontiguousarray(np.minimum(raw, np.asarray(cap, raw.dtype)))
    if optimizer is not None:
        for g in optimizer.groups.values():
            for k, q in enumerate(g.params):
                if q is p:
                    g.exp_avg[k] = np.zeros_like(p.data)
                    g.exp_avg_sq[k] = np.zeros_like(p.data)
    return lowered
