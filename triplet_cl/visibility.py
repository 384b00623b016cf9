"""Cached per-vertex visibility: cast shadows at the price of one extra interpolated column.

``vertex_visibility(scene)`` traces one shadow ray from every vertex towards every shadow-casting
light (point, directional: ``CASTS_SHADOWS`` in ``lights.py``) through the BVH of the soup and
returns the transmittance ``T = Π(1 − α)`` of the triplets crossed (the kernels of
``ops/trace.py``: own face skipped, start offset ``ray_eps`` × the bounding-box diagonal, as the
hybrid renderer). :func:`~triplet_cl.render.render` takes it as ``vis=[N, NV]``: the values are
interpolated over each triangle like any attribute and scale each light's intensity in the shading
(``HAS_VIS`` of ``shade.cl``). Visibility is a constant for the gradient (no adjoint through the
shadow boundary, the occluders' alphas or the light position's shadow rays); the shading's own
gradients are unchanged.

:class:`VisibilityCache` is what training holds: the visibility is re-traced every ``every`` steps,
whenever the topology changes (density control) and whenever the lights' shadow-ray parameters
moved by more than ``move_tol`` × the scene extent since the last trace.

Why per vertex: a training step renders a few hundred thousand fragments but the soup has tens of
thousands of vertices, and the lights move slowly; one trace per vertex every 100 steps costs
a fraction of one hybrid step (``bench/shadow_step.py``).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from .activations import sigmoid
from .device import Device, get_device
from .lights import pack_lights
from .ops import trace as trace_op
from .ops.bvh import build_bvh
from .render import device_mesh
from .scene import Scene

SHADOW_MODES = ("off", "vertex")


def owner_faces(F: np.ndarray, n: int) -> np.ndarray:
    """``[n] int32``: a face of each vertex (the last one listing it; −1 for unused vertices). In a soup
    every vertex has exactly one face, which its shadow ray skips."""
    own = np.full(n, -1, np.int32)
    F = np.asarray(F)
    if F.size:
        own[F.reshape(-1)] = np.repeat(np.arange(len(F), dtype=np.int32), 3)
    return own


def vertex_visibility(scene: Scene, device: Device | None = None, lights=None, ray_eps: float = 1e-2,
                      real=np.float32, vertices: np.ndarray | None = None,
                      normals: np.ndarray | None = None) -> np.ndarray:
    """``[N, NV]`` transmittance from every vertex of ``scene`` towards each shadow-casting light.

    Args:
        scene: the soup (its current ``V``, ``alpha`` and, unless ``lights`` is given, its current lights).
        lights: other lights to trace towards (relighting); default ``scene.current_lights()``.
        ray_eps: ray start offset, × the bounding-box diagonal of ``V`` (``RenderSettings.ray_eps``).
        vertices: trace from these vertex indices only (default all); the occluders are always the whole soup.
        normals: ``[N, 3]`` (one per traced vertex), or None: a light behind a vertex's normal (``n · l <= 0``) gets
            no ray and T = 1 there (for callers that weight it by ``max(0, n · l)``: ambient occlusion).

    A ray's walk stops once its transmittance is below 1e-4 (``trace.cl``'s ``EARLY_OUT``; no adjoint is
    needed here): values are within 1e-4 of the full product, and an occluded ray no longer crosses every
    surface behind its first hit.

    Returns:
        float64 ``[N, NV]`` (``N`` the number of ``vertices`` when given), NV the number of shadow-casting lights in
        light order (the columns of ``shade.cl``'s ``vis``); ``[N, 0]`` when no light casts shadows.
    """
    if not (np.isfinite(ray_eps) and ray_eps >= 0):
        raise ValueError(f"ray_eps must be a finite number >= 0, got {ray_eps}")
    d = device or get_device()
    lights = scene.current_lights() if lights is None else list(lights)
    table = pack_lights(lights)
    V = np.asarray(scene.V.data, np.float64)
    N = V.shape[0]
    sel = np.arange(N) if vertices is None else np.asarray(vertices, np.int64).reshape(-1)
    NV = table.num_shadowed
    if NV == 0 or len(sel) == 0 or len(scene.F) == 0:
        return np.ones((len(sel), NV))
    mesh = device_mesh(d, scene.F, N)
    # built afresh (not refitted): the hit order, hence T's rounding, depends on the tree, which must depend on V
    # alone for a resumed run to continue bit for bit
    bvh = build_bvh(d, np.ascontiguousarray(V, real), mesh)
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    eps = ray_eps * max(diag, 1e-12)
    q = d.queue
    Vd = cla.to_device(q, np.ascontiguousarray(V, real))
    alpha = cla.to_device(q, np.ascontiguousarray(sigmoid(np.asarray(scene.alpha.data, np.float64)).reshape(N, 1),
                                                  real))
    own = owner_faces(scene.F, N)
    pos = Vd if vertices is None else cla.to_device(q, np.ascontiguousarray(V[sel], real))
    nrm = None
    if normals is not None:
        normals = np.asarray(normals, np.float64)
        if normals.shape != (len(sel), 3):
            raise ValueError(f"normals must have shape {[len(sel), 3]} (one per traced vertex), got "
                             f"{list(normals.shape)}")
        nrm = cla.to_device(q, np.ascontiguousarray(normals, real))
    st = trace_op.shadow_forward(d, bvh, Vd, alpha, 0, pos, cla.to_device(q, own if vertices is None else own[sel]),
                                 cla.to_device(q, table.ints),
                                 cla.to_device(q, np.ascontiguousarray(table.params, real)), table, eps,
                                 nrm=nrm, two_sided=False, early_out=True)
    return st.vis.get().astype(np.float64).reshape(len(sel), NV)


def sphere_directions(n: int) -> np.ndarray:
    """``[n, 3]`` unit directions spread evenly over the sphere (a Fibonacci lattice; deterministic)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    ph = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(ph), r * np.sin(ph), z], axis=1)


def vertex_ambient_occlusion(scene: Scene, normals: np.ndarray, device: Device | None = None,
                             directions: int = 64, ray_eps: float = 1e-2) -> np.ndarray:
    """``[N]`` ambient occlusion of every vertex of ``scene``: the cosine-weighted share of its hemisphere (around
    ``normals [N, 3]``) from which a constant environment reaches it, ``Σ_k T_k max(0, n·d_k) / Σ_k max(0, n·d_k)``
    over ``directions`` evenly spread directions ``d_k``, ``T_k`` the transmittance of a shadow ray along ``d_k``
    (:func:`vertex_visibility` towards a directional light each: the same trace kernels, constant for the
    gradient). 1 where nothing occludes (a convex object), lower in concavities."""
    return vertex_occlusion(scene, normals, device, directions, 0, ray_eps)[0]


def vertex_occlusion(scene: Scene, normals: np.ndarray, device: Device | None = None, directions: int = 64,
                     degree: int = 2, ray_eps: float = 1e-2) -> tuple[np.ndarray, np.ndarray]:
    """``(ao [N], U [N, (degree + 1)² − 1])``: what the geometry hides of an environment, from one trace.

    ``ao`` is :func:`vertex_ambient_occlusion` (the visible share of the cosine-weighted hemisphere). ``U`` is the
    occlusion of the SH bands 1 .. ``degree`` that an SH environment's irradiance needs besides it (``shade.cl``
    ``ENV_OCC``): with ``w_k = max(0, n·d_k)`` and ``T_k`` the transmittance along ``d_k``,

        U_j = π [Σ_k w_k Y_j(d_k) / Σ_k w_k − Σ_k T_k w_k Y_j(d_k) / Σ_k T_k w_k]     (j ≥ 1)

    the cosine-weighted SH moments of the whole hemisphere less those of its visible part, each normalised to a
    cosine integral of π. The shading's irradiance ``ao Σ_j c_j (A_l Y_j(n) − U_j)`` is then the precomputed
    radiance transfer ``Σ_j c_j ∫ V(ω) max(0, n·ω) Y_j(ω) dω`` (its band 0 carried by ``ao``), with the quadrature
    error of the two sums cancelling where nothing occludes: ``U = 0`` exactly there (the same sums; a convex object
    renders as without it). 0 too where (almost) nothing is visible: ``ao`` below 1e-4, where the traces' early-out
    and not the geometry would set the ratio. A constant for the gradient, as the visibility.
    """
    from .lights import DirectionalLight
    from .mesh.envmap import sh_basis

    if directions < 1:
        raise ValueError(f"directions must be >= 1, got {directions}")
    if not (0 <= int(degree) <= 8):
        raise ValueError(f"degree must be in [0, 8], got {degree}")
    D = sphere_directions(directions)
    # no rays behind a vertex's normal: w = 0 there, whatever T
    T = vertex_visibility(scene, device, lights=[DirectionalLight(d, np.ones(3)) for d in D], ray_eps=ray_eps,
                          normals=normals)
    w = np.maximum(np.asarray(normals, np.float64) @ D.T, 0.0)
    tot = w.sum(axis=1)
    Tw = T * w
    seen = Tw.sum(axis=1)
    ao = np.where(tot > 0, seen / np.maximum(tot, 1e-12), 1.0)
    nk = (int(degree) + 1) ** 2
    U = np.zeros((len(w), nk - 1))
    if nk > 1 and len(w):
        Y = sh_basis(int(degree), D)[:, 1:]  # [K, nk - 1]
        # U is a ratio of transmittances: where the visible share is below the traces' early-out (1e-4: the walk's
        # stopping point, not the geometry, would set the ratio) it is 0, as where nothing is visible
        ok = (tot > 0) & (seen > 1e-4 * np.maximum(tot, 1e-300))
        U[ok] = np.pi * ((w[ok] @ Y) / tot[ok, None] - (Tw[ok] @ Y) / seen[ok, None])
    return ao, U


def vertex_bounce(scene: Scene, normals: np.ndarray, device: Device | None = None, lights=None,
                  vis: np.ndarray | None = None, directions: int = 32, ray_eps: float = 1e-2,
                  real=np.float32) -> np.ndarray:
    """``[N, 3]`` light that reaches each vertex of ``scene`` after one bounce off the rest of it (interreflection),
    as the uniform radiance with the same irradiance: the input of :class:`~triplet_cl.lights.BounceLight`.

    From every vertex a ray along each of ``directions`` evenly spread directions ``d_k`` (:func:`sphere_directions`)
    in the hemisphere of its normal (``normals [N, 3]``) finds its nearest hit (``ops.trace.trace_rays``: own face
    skipped, start offset ``ray_eps`` × the bounding-box diagonal); the hit point is shaded by the shading kernels
    with ``lights`` (default the scene's current ones) as seen from the vertex (``eye``), its material, normal,
    alpha and cast shadows (``vis [N, NV]``, the scene's visibility towards ``lights``) interpolated there. The
    radiance returned is ``Σ_k w_k L_k / Σ_k w_k``, ``w_k = n · d_k``, misses counting 0: the cosine-weighted mean
    of what the hemisphere sends (``π`` × it is the irradiance; the sky the misses see is the ambient light's
    part). One bounce only, a constant for the gradient (re-traced by the caller, as the visibility); 0 where
    nothing is hit (a convex object), so the rendering of a convex object does not change."""
    from .materials import get_brdf
    from .ops import shade as shade_op

    if directions < 1:
        raise ValueError(f"directions must be >= 1, got {directions}")
    if not (np.isfinite(ray_eps) and ray_eps >= 0):
        raise ValueError(f"ray_eps must be a finite number >= 0, got {ray_eps}")
    d = device or get_device()
    lights = scene.current_lights() if lights is None else list(lights)
    V = np.asarray(scene.V.data, np.float64)
    N = V.shape[0]
    out = np.zeros((N, 3))
    if N == 0 or len(scene.F) == 0 or not lights:
        return out
    F = np.asarray(scene.F)
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    D = sphere_directions(directions)
    w = n @ D.T  # [N, K]
    vi, ki = np.nonzero(w > 0)
    wk = w[vi, ki]
    mesh = device_mesh(d, F, N)
    bvh = build_bvh(d, np.ascontiguousarray(V, real), mesh)
    eps = ray_eps * max(float(np.linalg.norm(V.max(0) - V.min(0))), 1e-12)
    Vd = cla.to_device(d.queue, np.ascontiguousarray(V, real))
    hf, hb = trace_op.trace_rays(d, bvh, Vd, V[vi], D[ki], owner_faces(F, N)[vi], eps)
    hf, hb = hf.get(), hb.get().astype(np.float64)
    hit = np.nonzero(hf >= 0)[0]
    L = np.zeros((len(vi), 3))
    if len(hit):
        f = hf[hit]
        lam = np.stack([hb[hit, 0], hb[hit, 1], 1.0 - hb[hit, 0] - hb[hit, 1]], 1)  # [H, 3]
        corners = F[f]

        def at_hits(a):
            a = np.asarray(a, np.float64).reshape(N, -1)
            return np.einsum("hc,hcj->hj", lam, a[corners])

        mat = get_brdf(scene.brdf).activate(scene.material.data)
        _, inp = shade_op.prepare(at_hits(V), at_hits(n), at_hits(mat), f.astype(np.int32), np.zeros(3), lights,
                                  brdf=scene.brdf, two_sided=True, device=d, real=real,
                                  vis=None if vis is None or vis.shape[1] == 0 else at_hits(vis), eye=V[vi[hit]])
        rgb = shade_op.forward(d, inp).get().astype(np.float64).reshape(-1, 3)
        L[hit] = rgb * at_hits(sigmoid(np.asarray(scene.alpha.data, np.float64)))
    tot = np.bincount(vi, weights=wk, minlength=N)
    for c in range(3):
        out[:, c] = np.bincount(vi, weights=wk * L[:, c], minlength=N)
    return out / np.maximum(tot, 1e-12)[:, None]


_RAY_OFFSETS: dict = {}  # the light layout's shadow-ray offsets (a layout: the lights' types and parameter counts)


def _shadow_rays(scene: Scene) -> np.ndarray:
    """The shadow casters' ray parameters (positions / directions) ``[NV, 3]``, for the move test: read from the
    packed parameters at the offsets of their layout (packing the current lights for them took ~0.5 ms a step)."""
    lights = scene.lights
    params = scene.light_params.data if scene.light_params is not None else None
    key = tuple((type(lt), lt.num_params) for lt in lights)
    offsets = _RAY_OFFSETS.get(key)
    if offsets is None:
        offsets = _RAY_OFFSETS[key] = pack_lights(lights).shadow_ray_offsets
    if params is None:  # (a scene without learnable lights: its own values)
        params = pack_lights(lights).params
    p = np.asarray(params, np.float64)
    return np.array([p[o:o + 3] for o in offsets]).reshape(-1, 3)


class VisibilityCache:
    """Per-vertex visibility held across training steps (see the module docstring).

    Args:
        every: re-trace every this many steps (≥ 1).
        start: no shadows before this iteration (``get`` returns None): the soup is a cloud of
            half-transparent triangles at first, whose transmittance says nothing yet.
        extent: the scene's size (the unit of ``move_tol``).
        move_tol: re-trace early when a shadow caster's position / direction moved by more than this
            (× ``extent`` for positions, radians-ish for unit directions) ...
        move_every: ... and at least this many steps have passed since the last trace (default ``every`` // 2).
            A light that Adam keeps stepping (beta1 0.5: about its learning rate every step, to the end) jitters
            across the tolerance: gadget's soup re-traced 145 times in 3000 steps, 122 of them for moves 2 to 20
            steps apart (40 of its 151 s).
    """

    def __init__(self, every: int = 100, start: int = 0, extent: float = 1.0, move_tol: float = 0.05,
                 ray_eps: float = 1e-2, move_every: int | None = None):
        if int(every) < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.every, self.start, self.extent, self.move_tol = int(every), int(start), float(extent), float(move_tol)
        self.move_every = max(self.every // 2, 1) if move_every is None else int(move_every)
        if self.move_every < 1:
            raise ValueError(f"move_every must be >= 1, got {move_every}")
        self.ray_eps = ray_eps
        self.vis: np.ndarray | None = None
        self.at = -1  # iteration of the last trace
        self.rays: np.ndarray | None = None
        self.F = None
        self.traces = 0  # how many traces so far (tests, benchmarks)

    def invalidate(self) -> None:
        """Forget the cached values (the next :meth:`get` traces)."""
        self.vis = None

    def stale(self, scene: Scene, it: int) -> bool:
        if self.vis is None or self.F is not scene.F or self.vis.shape[0] != scene.V.shape[0]:
            return True
        if it - self.at >= self.every:
            return True
        rays = _shadow_rays(scene)
        if self.rays is None or rays.shape != self.rays.shape:
            return True
        if it - self.at < self.move_every:
            return False
        return bool(len(rays)) and float(np.abs(rays - self.rays).max()) > self.move_tol * max(self.extent, 1e-12)

    def get(self, scene: Scene, it: int, device: Device | None = None) -> np.ndarray | None:
        """``[N, NV]`` visibility for iteration ``it`` (re-traced when stale), None before ``start``."""
        if it < self.start:
            return None
        if self.stale(scene, it):
            self.vis = vertex_visibility(scene, device, ray_eps=self.ray_eps)
            self.at, self.F, self.rays = it, scene.F, _shadow_rays(scene)
            self.traces += 1
        return self.vis


__all__ = ["SHADOW_MODES", "VisibilityCache", "owner_faces", "vertex_occlusion", "vertex_visibility"]
