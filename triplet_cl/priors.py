"""Material and light priors of the decomposition (issue "recover the real lights and materials"), host-side.

Each term is a scalar energy of the raw scene parameters with its exact gradient (``value_and_grad``
functions: ``(E, dE/dx)``); :class:`Priors` adds ``weight · dE/dx`` to the parameters' ``.grad`` after
the photometric backward pass of a training step. Activated material channels are the BRDF's
(``materials.py``: sigmoid); ``s(x) = sigmoid(x)``.

==================  =======================================================================  =============
term                energy                                                                   mean over
==================  =======================================================================  =============
kNN smoothness      ``Σ_(f,g) Σ_c ρ(m_fc − m_gc)``, ``m_f`` = the mean over a face's 3          pairs × channels
                    vertices of the activated albedo / roughness / metallic, ``(f, g)`` the
                    unique pairs of the ``k`` nearest face centroids (scipy ``cKDTree``),
                    ``ρ(d) = sqrt(d² + ε²) − ε`` (Charbonnier: ~L1, an edge-keeping TV)
metallic            ``Σ_i s(x_i,metallic)`` (L1 towards 0; metallic is ≥ 0)                   vertices
roughness           ``Σ_i (s(x_i,roughness) − r0)²``                                          vertices
ambient fraction    ``π|a| / (π|a| + p)``: ``a = mean(La)`` the ambient radiance (a negative   —
                    ambient, unphysical, is penalised too), ``p`` the irradiance of the
                    other lights at the scene centre ``c``:
                    point ``mean(I) / |q − c|²`` (``mean(I)`` without falloff), directional
                    ``mean(intensity)``; 0 when ``π|a| + p <= 0``
light chroma        ``Σ_lights |u|² / (c̄² + δ)``, ``u = c − c̄``, ``c`` each ambient colour /   —
                    point or directional intensity (rgb), ``c̄`` its mean (scale-free)
==================  =======================================================================  =============

Why these defaults (chosen by principle, not by the dev scenes' ground truth; see README "Priors"):
the roughness target ``r0 = 0.5`` is the middle of the range (no preference between matte and
glossy; the photometric gradient moves it where a highlight is seen); ``ε = 0.01`` keeps edges of
a texture (a TV prior) while being differentiable at 0; ``k = 8`` neighbours ≈ the 1-ring of a mesh
vertex; the ambient fraction is a scale-free ratio (any light unit, any scene size) and the chroma
term is scale-free as well. Every weight is 0 by default (``--priors lights`` / ``all`` turn them on):
measured at the end of 2026-11-24, the light terms cost the environment-lit bob_env 3.3–5.1 dB of
relight PSNR (``bench/results/final_defaults_pocl_2026-11-24.txt``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .lights import AmbientLight, DirectionalLight, PointLight, nonnegative_lights
from .materials import get_brdf
from .topology import unique_ints

#: the TrainConfig fields of the priors' weights (``--priors off`` sets them all to 0)
WEIGHT_FIELDS = ("prior_smooth", "prior_metallic", "prior_roughness", "prior_ambient", "prior_chroma")
#: the material terms' weights of ``--priors all`` (off by default: see README "Material and light priors")
MATERIAL_WEIGHTS = {"prior_smooth": 0.01, "prior_metallic": 0.01, "prior_roughness": 0.01}
LIGHT_WEIGHTS = {"prior_ambient": 0.02, "prior_chroma": 0.01}  # --priors lights (and all)
CHARBONNIER_EPS = 0.01
CHROMA_DELTA = 1e-6
DIST_FLOOR = 1e-6  # the point-light kernel's clamp of |q - x|^2


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


# ---- kNN graph -----------------------------------------------------------------------------------
def knn_pairs(points: np.ndarray, k: int) -> np.ndarray:
    """``[P, 2] int64`` unique undirected pairs ``(i, j)``, ``i < j``, of each point and its ``k``
    nearest other points (``cKDTree``); empty for fewer than 2 points."""
    pts = np.asarray(points, np.float64)
    n = len(pts)
    if n < 2 or k < 1:
        return np.zeros((0, 2), np.int64)
    kk = min(k, n - 1)
    _, idx = cKDTree(pts).query(pts, k=kk + 1)
    i = np.repeat(np.arange(n, dtype=np.int64), kk)
    j = idx[:, 1:].reshape(-1).astype(np.int64)
    keep = i != j  # coincident points may list themselves after another
    key = unique_ints(np.minimum(i, j)[keep] * n + np.maximum(i, j)[keep])  # sorted, as lexicographic pairs
    return np.stack([key // n, key % n], axis=1)


# ---- material terms ------------------------------------------------------------------------------
def knn_smoothness(raw: np.ndarray, faces: np.ndarray, pairs: np.ndarray, columns,
                   eps: float = CHARBONNIER_EPS) -> tuple[float, np.ndarray]:
    """Mean Charbonnier difference of the face-mean activated ``columns`` of ``raw [N, C]`` over
    ``pairs [P, 2]`` of faces ``faces [M, 3]``; returns ``(E, dE/draw [N, C])``."""
    raw = np.asarray(raw)
    cols = list(columns)
    g = np.zeros_like(raw)
    if len(pairs) == 0 or not cols:
        return 0.0, g
    s = _sigmoid(raw[:, cols])  # [N, c]
    m = s[faces].mean(axis=1)  # [M, c]
    d = m[pairs[:, 0]] - m[pairs[:, 1]]  # [P, c]
    r = np.sqrt(d * d + eps * eps)
    scale = 1.0 / d.size
    e = float(np.sum(r - eps) * scale)
    gd = d / r * scale
    a, b, fv = pairs[:, 0], pairs[:, 1], faces.reshape(-1)
    for c in range(len(cols)):  # scatter-adds by bincount (np.add.at is ~10x slower)
        gm = np.bincount(a, gd[:, c], len(m)) - np.bincount(b, gd[:, c], len(m))
        gs = np.bincount(fv, np.repeat(gm / 3.0, 3), len(s))
        g[:, cols[c]] = gs * s[:, c] * (1.0 - s[:, c])
    return e, g


def metallic_l1(raw: np.ndarray, column: int) -> tuple[float, np.ndarray]:
    """Mean activated metallic of ``raw [N, C]``: ``(E, dE/draw)``."""
    raw = np.asarray(raw)
    g = np.zeros_like(raw)
    if len(raw) == 0:
        return 0.0, g
    s = _sigmoid(raw[:, column])
    g[:, column] = s * (1.0 - s) / len(raw)
    return float(s.mean()), g


def roughness_target(raw: np.ndarray, column: int, target: float) -> tuple[float, np.ndarray]:
    """Mean ``(roughness − target)²`` of ``raw [N, C]``: ``(E, dE/draw)``."""
    raw = np.asarray(raw)
    g = np.zeros_like(raw)
    if len(raw) == 0:
        return 0.0, g
    s = _sigmoid(raw[:, column])
    d = s - target
    g[:, column] = 2.0 * d * s * (1.0 - s) / len(raw)
    return float(np.mean(d * d)), g


# ---- light terms ---------------------------------------------------------------------------------
def _slices(lights) -> list[tuple[object, int]]:
    out, off = [], 0
    for lt in lights:
        out.append((lt, off))
        off += lt.num_params
    return out


def ambient_fraction(lights, params: np.ndarray, center) -> tuple[float, np.ndarray]:
    """``π|a| / (π|a| + p)`` (module docstring) of the packed light ``params [T]``: ``(E, dE/dparams)``."""
    params = np.asarray(params)
    g = np.zeros_like(params)
    c = np.asarray(center, np.float64)
    a_terms, p_terms = [], []  # (offset, kind)
    a = p = 0.0
    for lt, off in _slices(lights):
        if isinstance(lt, AmbientLight):
            a += params[off:off + 3].mean()
            a_terms.append(off)
        elif isinstance(lt, PointLight):
            io = off + lt.param_offset("intensity")
            po = off + lt.param_offset("position")
            i = params[io:io + 3].mean()
            if lt.falloff:
                q = params[po:po + 3] - c
                d2 = max(float(np.dot(q, q)), DIST_FLOOR)
                p += i / d2
                p_terms.append(("point", io, po, i, d2, q))
            else:
                p += i
                p_terms.append(("const", io))
        elif isinstance(lt, DirectionalLight):
            io = off + lt.param_offset("intensity")
            p += params[io:io + 3].mean()
            p_terms.append(("const", io))
    if not a_terms:
        return 0.0, g
    sgn = 1.0 if a > 0 else (-1.0 if a < 0 else 0.0)  # |a|: a negative ambient light is penalised as well
    a_eff = np.pi * abs(a)
    den = a_eff + p
    if den <= 0:
        return 0.0, g
    e = a_eff / den
    da = sgn * np.pi * p / den ** 2  # dE/da
    for off in a_terms:
        g[off:off + 3] += da / 3.0
    dp = -a_eff / den ** 2  # dE/dp
    for t in p_terms:
        if t[0] == "const":
            g[t[1]:t[1] + 3] += dp / 3.0
        else:
            _, io, po, i, d2, q = t
            g[io:io + 3] += dp / (3.0 * d2)
            if d2 > DIST_FLOOR:
                g[po:po + 3] += dp * (-i / d2 ** 2) * 2.0 * q
    return float(e), g


def chroma(lights, params: np.ndarray, delta: float = CHROMA_DELTA) -> tuple[float, np.ndarray]:
    """``Σ |c − c̄|² / (c̄² + δ)`` over the rgb colour / intensity of every ambient, point and
    directional light in the packed ``params [T]``: ``(E, dE/dparams)``."""
    params = np.asarray(params)
    g = np.zeros_like(params)
    e = 0.0
    for lt, off in _slices(lights):
        name = {AmbientLight: "color", PointLight: "intensity", DirectionalLight: "intensity"}.get(type(lt))
        if name is None:
            continue
        o = off + lt.param_offset(name)
        col = params[o:o + 3]
        cm = col.mean()
        u = col - cm
        s = cm * cm + delta
        uu = np.sum(u * u)
        e = e + uu / s
        g[o:o + 3] += 2.0 * u / s - uu / s ** 2 * 2.0 * cm / 3.0
    return float(e), g


# ---- the training hook ---------------------------------------------------------------------------
class Priors:
    """Adds the weighted priors' gradients to a scene's ``.grad`` (training step hook).

    Weights come from :class:`~triplet_cl.train.TrainConfig` (``prior_*``; 0 disables a term); the
    priors act from iteration ``prior_from`` (before it the soup is 20k random triangles at reduced
    resolution: smoothing them is costly and means nothing).
    The kNN graph is rebuilt every ``rebuild_every`` iterations and whenever :meth:`invalidate`
    is called (density control changed or reordered the soup).
    """

    def __init__(self, cfg, center, rebuild_every: int = 100):
        self.w_smooth = float(cfg.prior_smooth)
        self.k = int(cfg.prior_k)
        self.w_metallic = float(cfg.prior_metallic)
        self.w_roughness = float(cfg.prior_roughness)
        self.r0 = float(cfg.prior_roughness_target)
        self.w_ambient = float(cfg.prior_ambient)
        self.w_chroma = float(cfg.prior_chroma)
        self.start = int(cfg.prior_from)
        self.center = np.asarray(center, np.float64)
        self.rebuild_every = int(rebuild_every)
        self.pairs: np.ndarray | None = None
        self.built_at = -1

    @property
    def active(self) -> bool:
        return any(w > 0 for w in (self.w_smooth, self.w_metallic, self.w_roughness, self.w_ambient, self.w_chroma))

    @staticmethod
    def off() -> dict:
        """The ``TrainConfig`` fields that switch every prior off (``--priors off``; runs saved before them)."""
        return dict.fromkeys(WEIGHT_FIELDS, 0.0)

    def invalidate(self) -> None:
        self.pairs = None

    def _graph(self, scene, it: int) -> np.ndarray:
        if self.pairs is None or it - self.built_at >= self.rebuild_every:
            V = np.asarray(scene.V.data, np.float64)
            cent = V[scene.F].mean(axis=1)
            self.pairs = knn_pairs(cent, self.k)
            self.built_at = it
        return self.pairs

    def project(self, scene) -> None:
        """After the optimizer step: light colours / intensities onto ``>= 0`` (a negative light is not physical
        and, measured on the synthetic recovery scene, lets a negative ambient light carve the shading the
        point light should make). Only while a prior is active (``--priors off`` leaves the run as before)."""
        if not self.active or scene.light_params is None:
            return
        lp = scene.light_params.data
        lp[...] = nonnegative_lights(scene.lights, lp)  # the rule balanced_lights applies after every step

    def apply(self, scene, it: int) -> dict:
        """Add the priors' gradients to ``scene.material.grad`` / ``scene.light_params.grad``;
        returns ``{term: energy}`` of the active terms."""
        from .autodiff.arrays import to_host

        out = {}
        if not self.active or it < self.start:
            return out
        names = get_brdf(scene.brdf).channel_names
        raw = np.asarray(scene.material.data, np.float64)
        gm = np.zeros_like(raw)
        col = {n: i for i, n in enumerate(names)}
        if self.w_smooth > 0:
            cols = [col[n] for n in ("albedo_r", "albedo_g", "albedo_b", "roughness", "metallic") if n in col]
            e, g = knn_smoothness(raw, np.asarray(scene.F, np.int64), self._graph(scene, it), cols)
            out["smooth"] = e
            gm += self.w_smooth * g
        if self.w_metallic > 0 and "metallic" in col:
            e, g = metallic_l1(raw, col["metallic"])
            out["metallic"] = e
            gm += self.w_metallic * g
        if self.w_roughness > 0 and "roughness" in col:
            e, g = roughness_target(raw, col["roughness"], self.r0)
            out["roughness"] = e
            gm += self.w_roughness * g
        if out:
            prev = scene.material.grad
            base = np.zeros_like(raw) if prev is None else np.asarray(to_host(prev), np.float64)
            scene.material.grad = (base + gm).astype(scene.material.data.dtype)
        if scene.light_params is not None and (self.w_ambient > 0 or self.w_chroma > 0):
            lp = np.asarray(scene.light_params.data, np.float64)
            gl = np.zeros_like(lp)
            if self.w_ambient > 0:
                e, g = ambient_fraction(scene.lights, lp, self.center)
                out["ambient"] = float(e)
                gl += self.w_ambient * g
            if self.w_chroma > 0:
                e, g = chroma(scene.lights, lp)
                out["chroma"] = float(e)
                gl += self.w_chroma * g
            prev = scene.light_params.grad
            base = np.zeros_like(lp) if prev is None else np.asarray(to_host(prev), np.float64)
            scene.light_params.grad = (base + gl).astype(scene.light_params.data.dtype)
        return out
