"""The Cook-Torrance lobe's reflection of an environment, tabulated (``kernels_cl/common/ggx_tables.h``).

A metal's SH environment light is shaded with the split-sum form: the environment filtered by the
specular lobe, seen along the mirror direction, times the lobe's directional albedo. Both factors are read from
tables of *our own* lobe (``shade_brdf.h`` ``brdf_direct``: GGX with ``α = roughness²``, separable Smith masking,
Schlick's Fresnel on ``h·v`` for a metal), integrated here once, over roughness 0, 1/31, …, 1:

``DFG_A[ρ, n·v]``, ``DFG_B[ρ, n·v]``
    a metal's directional albedo ``F0 A + B`` (``A = ∫ f_s (1 − (1 − h·v)⁵) cos θ_l dω_l``, ``B`` the same with
    ``(1 − h·v)⁵``; ``f_s`` the lobe without its Fresnel factor) at ``n·v`` 0, 1/31, …, 1: the energy masking takes
    as the lobe roughens and the Fresnel rise at grazing angles.
``LOBE_BANDS[ρ, l]``
    the lobe's band multipliers at normal incidence (its normalised Legendre moments, the zonal filter of the
    Funk-Hecke theorem), ``Λ_l = ∫ w P_l(cos θ_l) dω / ∫ w dω`` (``w = f_s cos θ_l``), bands l = 0 … 8: how much of
    each band of the environment the lobe passes (1 for a mirror).

Why (session 46, bench/results/env_lobe_pocl_2026-11-27.txt): a metal's environment weight was the damped Schlick
``F0 + (1 − F0)(1 − ρ)(1 − n·v)⁵`` (no masking loss) and its filter the Gaussian ``exp(−l(l + 1) α² / 2)``, half the
width of the lobe's reflection and without its tails (``Λ_2`` at ρ = 0.35: 0.95 against 0.79). Under an
environment only those two factors tell a metal's roughness, and the fit made up for them with a rougher lobe:
spot_small re-rendered by Mitsuba as a metal of roughness 0.35 came out at 0.57 under an HDR environment (0.49 under
sun and sky), 0.39 (0.40) with both from the lobe. (The ambient light keeps the damped Schlick: shade_brdf.h says
why.) Mitsuba's own white furnace checks the DFG's energy (a metal of
roughness 0.6 returns 0.82 of a uniform light at normal incidence, the table 0.81 at 0.61).

The lobe is the path tracer's: ``brdf_direct``'s guard ``D = α⁴ / (π t² + 1e-6)`` is left out (it lowers a glossy
lobe's peak, 0.45× at roughness 0.15, and with it the lobe's energy: 0.75 of the light at 0.15, 0.25 at 0.1, where
Mitsuba's and this table's keep ~1.0); above roughness ~0.25 the two agree.

The tables are integrated by stratified importance sampling of the GGX half-vector (deterministic: no random state)
and committed as the header; ``python -m triplet_cl.ggx_tables`` rewrites it, and a test checks that the committed
header is what this module computes.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

N_ROUGH = 32  # table rows: roughness 0, 1/31, ..., 1
N_NV = 32  # DFG columns: n·v 0, 1/31, ..., 1
N_BANDS = 9  # SH bands 0 .. 8 (an SHEnvironmentLight has degree <= 8)
SAMPLES = 128  # per axis of the stratified half-vector samples (128² per table entry)


def _half_vectors(a2: float, n: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """``(H [n², 3], cos θ_h [n²])``: GGX half-vectors about +z (density ``D(h) cos θ_h``), stratified."""
    u = (np.arange(n) + 0.5) / n
    u1, u2 = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    c2 = (1.0 - u1) / (1.0 + (a2 - 1.0) * u1)
    ch = np.sqrt(c2)
    sh = np.sqrt(np.maximum(1.0 - c2, 0.0))
    ph = 2.0 * np.pi * u2
    return np.stack([sh * np.cos(ph), sh * np.sin(ph), ch], axis=-1), ch


def _lobe_weights(a2: float, nv: float, H: np.ndarray, ch: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w, h·v, n·l)`` per half-vector sample: ``w = f_s cos θ_l / pdf(l)`` for the view at ``nv`` (f_s the lobe
    without Fresnel, ``D n·l / (q_v q_l)`` as brdf_direct's ``S``; pdf(l) = D cos θ_h / (4 h·v), so D cancels)."""
    V = np.array([np.sqrt(max(1.0 - nv * nv, 0.0)), 0.0, nv])
    hv = H @ V
    L = 2.0 * hv[:, None] * H - V
    nl = L[:, 2]
    qv = nv + np.sqrt(a2 + (1.0 - a2) * nv * nv)
    ql = nl + np.sqrt(np.maximum(a2 + (1.0 - a2) * nl * nl, 0.0))
    ok = (nl > 0) & (hv > 0)
    w = np.where(ok, 4.0 * np.maximum(nl, 0) * hv / (qv * np.where(ok, ql, 1.0) * ch), 0.0)
    return w, hv, nl


def compute() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(DFG_A [N_ROUGH, N_NV], DFG_B [N_ROUGH, N_NV], LOBE_BANDS [N_ROUGH, N_BANDS])`` (float64)."""
    from numpy.polynomial import legendre

    A = np.zeros((N_ROUGH, N_NV))
    B = np.zeros((N_ROUGH, N_NV))
    bands = np.zeros((N_ROUGH, N_BANDS))
    for i, r in enumerate(np.linspace(0.0, 1.0, N_ROUGH)):
        a2 = max(r ** 4, 1e-10)  # a mirror's lobe as the limit of a very sharp one
        H, ch = _half_vectors(a2)
        for j, nv in enumerate(np.linspace(0.0, 1.0, N_NV)):
            w, hv, _ = _lobe_weights(a2, max(nv, 1e-4), H, ch)
            f5 = (1.0 - np.clip(hv, 0.0, 1.0)) ** 5
            A[i, j] = np.mean(w * (1.0 - f5))
            B[i, j] = np.mean(w * f5)
        w, _, nl = _lobe_weights(a2, 1.0, H, ch)  # normal incidence: the reflection lobe is centred on n
        for band in range(N_BANDS):
            p = legendre.legval(np.clip(nl, -1.0, 1.0), [0.0] * band + [1.0])
            bands[i, band] = np.sum(w * p) / np.sum(w)
    return A, B, bands


NAMES = ("DFG_A", "DFG_B", "LOBE_BANDS")


def header_text() -> str:
    """The header's text: the tables as ``__constant float`` arrays (row-major, roughness first)."""
    def arr(name: str, x: np.ndarray) -> str:
        w = x.shape[1]
        vals = [f"{v:.7f}f" for v in x.ravel()]
        rows = [", ".join(vals[k:k + w]) for k in range(0, len(vals), w)]
        return f"__constant float {name}[{x.size}] = {{\n    " + ",\n    ".join(rows) + "\n};\n"

    head = ("ggx_tables.h — GENERATED by `python -m triplet_cl.ggx_tables` (triplet_cl/ggx_tables.py): do not edit.",
            "The Cook-Torrance (GGX) lobe's directional albedo for a metal, F0 DFG_A + DFG_B [roughness, n.v], and",
            "its band multipliers LOBE_BANDS [roughness, band] at normal incidence (bands 0 .. 8); rows at",
            "roughness k / 31, DFG columns at n.v k / 31.")
    return ("/* " + "\n * ".join(head) + " */\n"
            "#ifndef TRIPLET_GGX_TABLES_H\n#define TRIPLET_GGX_TABLES_H\n"
            f"#define GGX_NR {N_ROUGH}\n#define GGX_NNV {N_NV}\n#define GGX_NBANDS {N_BANDS}\n"
            + "".join(arr(n, x) for n, x in zip(NAMES, compute(), strict=True)) + "#endif\n")


def header_path() -> Path:
    """``kernels_cl/common/ggx_tables.h`` where the kernels are read from (a checkout's or the installed package's)."""
    from .device import kernel_dir

    return kernel_dir() / "common" / "ggx_tables.h"


@functools.cache
def load() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The committed header's tables as float32 arrays ``(DFG_A, DFG_B, LOBE_BANDS)`` (what the kernels read; read
    once, the arrays read-only)."""
    import re

    text = header_path().read_text()
    out = []
    for name, shape in zip(NAMES, ((N_ROUGH, N_NV), (N_ROUGH, N_NV), (N_ROUGH, N_BANDS)), strict=True):
        body = re.search(name + r"\[\d+\] = \{([^}]*)\}", text).group(1)
        a = np.array([float(v.strip().rstrip("f")) for v in body.split(",")], np.float32).reshape(shape)
        a.flags.writeable = False
        out.append(a)
    return tuple(out)


def _cell(x, n: int):
    """Cell index (from the real part) and fraction (complex-step friendly) of ``x`` on ``n`` nodes over [0, 1],
    clamped; the fraction's slope is 0 outside (0, 1), as the kernel's."""
    xr = np.real(x)
    f = np.clip(xr, 0.0, 1.0) * (n - 1)
    i = np.minimum(f.astype(int), n - 2)
    return i, np.where((xr > 0) & (xr < 1), x * (n - 1) - i, f - i)


def dfg(rough, nv, tables=None):
    """``(A, B)`` at ``rough``, ``nv`` (arrays of one shape), bilinear as the kernel's ``env_dfg``."""
    A, B, _ = load() if tables is None else tables
    i, t = _cell(rough, N_ROUGH)
    j, s = _cell(nv, N_NV)

    def bil(T):
        T = T.astype(np.float64)
        return (T[i, j] * (1 - s) + T[i, j + 1] * s) * (1 - t) + (T[i + 1, j] * (1 - s) + T[i + 1, j + 1] * s) * t

    return bil(A), bil(B)


def lobe_bands(rough, bands, tables=None):
    """``Λ_l`` at ``rough`` for each entry of ``bands``, linear in roughness as the kernel's ``env_bands``."""
    lb = (load() if tables is None else tables)[2].astype(np.float64)
    i, t = _cell(rough, N_ROUGH)
    return lb[i, bands] * (1 - t) + lb[i + 1, bands] * t


def main() -> int:
    path = header_path()
    tmp = path.with_suffix(".h.tmp")
    tmp.write_text(header_text())
    tmp.replace(path)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
