"""Reference implementation of the shading op (numpy), written to be complex-step differentiable.

Every branch (relu, clamp, masks, the two-sided flip) tests the real part, and only analytic
operations touch the values, so ``f(x + i h e).imag / h`` is the exact derivative: the reference
adjoint ``vjp`` below is built that way (independent of the hand-derived kernel adjoints).
Light parameters are passed packed (``ints [L, 4]``, ``params [T]``) as in triplet_cl.lights.
"""

from __future__ import annotations

import numpy as np

from triplet_cl import ggx_tables
from triplet_cl.lights import AmbientLight, BounceLight, DirectionalLight, PointLight, SHEnvironmentLight, VertexSHLight

from . import sh as shref

# the light-table type ids (a convention of triplet_cl.lights, not maths)
AMBIENT, DIRECTIONAL, POINT, SH_ENV, VERTEX_SH, BOUNCE = (AmbientLight.TYPE, DirectionalLight.TYPE, PointLight.TYPE,
                                                          SHEnvironmentLight.TYPE, VertexSHLight.TYPE, BounceLight.TYPE)
EPS2 = 1e-20
POINT_D2_EPS = 1e-6
# the Cook-Torrance lobe's tables as the kernels read them (ggx_tables.h's float32 values; interpolated in float64)
GGX = ggx_tables.load()


def relu(x):
    return np.where(x.real > 0, x, 0)


def fmax(x, e):
    return np.where(x.real > e, x, e)


def dot(a, b):
    return np.sum(a * b, axis=-1, keepdims=True)


def normalize(v):
    l2 = dot(v, v)
    return v / np.sqrt(fmax(l2, EPS2))


def safe_pow(x, e):
    xr = x.real > 0
    xs = np.where(xr, x, 1.0)
    return np.where(xr, np.exp(e * np.log(xs)), 0)


def fresnel_dielectric(c, eta=1.5):
    """Exact unpolarised Fresnel reflectance of a dielectric (index ``eta``) at the incidence cosine ``c`` in [0, 1]."""
    ct = np.sqrt(1 - (1 - c * c) / (eta * eta))
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def ct_direct(N, V, L, Li, m):
    """Cook-Torrance as Mitsuba 3's principled BSDF (its defaults: specular 0.5, no sheen / clearcoat / transmission):
    GGX with a = r^2, Smith's exact separable masking, the exact dielectric Fresnel (eta 1.5) blended with Schlick's
    on the albedo by metallic, and the Disney diffuse (its retro-reflection included)."""
    alb, r, met = m[:, 0:3], m[:, 3:4], m[:, 4:5]
    nl = dot(N, L)
    on = nl.real > 0
    nv = relu(dot(N, V))
    H = normalize(L + V)
    nh = relu(dot(N, H))
    hvr = dot(H, V)
    hv = np.where(hvr.real < 0, 0, np.where(hvr.real > 1, 1, hvr))
    a2 = r**4
    D = a2 / (np.pi * (nh * nh * (a2 - 1) + 1) ** 2 + 1e-6)
    qv = nv + np.sqrt(a2 + (1 - a2) * nv * nv + 1e-12)
    ql = nl + np.sqrt(a2 + (1 - a2) * nl * nl + 1e-12)
    F = (1 - met) * fresnel_dielectric(hv) + met * (alb + (1 - alb) * (1 - hv) ** 5)
    spec = D * F / (qv * ql + 1e-6) * nl
    Fo, Fi = (1 - nl) ** 5, (1 - nv) ** 5
    Rr = 2 * r * hv * hv
    s = (1 - 0.5 * Fo) * (1 - 0.5 * Fi) + Rr * (Fo + Fi + Fo * Fi * (Rr - 1))
    diff = (1 - met) * alb / np.pi * s * nl
    return np.where(on, (spec + diff) * Li, 0)


def bp_direct(N, V, L, Li, m):
    """Blinn-Phong: ks (relu(N.H) [N.L > 0])^(relu(s)+1) Li + kd / pi relu(N.L) Li."""
    kd, ks, s = m[:, 0:3], m[:, 3:6], m[:, 6:7]
    nl = dot(N, L)
    on = nl.real > 0
    nh = relu(dot(N, normalize(L + V)))
    e = relu(s) + 1
    return np.where(on, (ks * safe_pow(nh, e) + kd / np.pi * nl) * Li, 0)


def ambient(N, V, La, m, brdf):
    """Cook-Torrance: the SH environment term of a constant radiance La (E = pi La, Gl = La); Blinn-Phong: La ka."""
    if brdf != "cook_torrance":
        return La * m[:, 7:10]
    alb, r, met, ao = m[:, 0:3], m[:, 3:4], m[:, 4:5], m[:, 5:6]
    F0 = 0.04 * (1 - met) + met * alb
    Fe = F0 + (1 - F0) * (1 - r) * (1 - relu(dot(N, V))) ** 5  # a metal's too: the damped Schlick (shade_brdf.h)
    return ao * ((1 - met) * alb + Fe) * La


def env_fresnel(alb, r, met, nv):
    """Cook-Torrance's SH environment weight Fe: a dielectric's damped Schlick 0.04 + 0.96 (1 - r)(1 - nv)^5 blended
    with a metal's exact directional albedo alb A + B (ggx_tables' bilinear DFG)."""
    A, B = ggx_tables.dfg(r, nv, GGX)
    return (1 - met) * (0.04 + 0.96 * (1 - r) * (1 - nv) ** 5) + met * (alb * A + B)


def env(N, V, m, brdf, c, deg, occ=None):
    """SH environment: c [3, stride] (only the first (deg+1)^2 columns are used); ``occ [P, NO]`` the occlusion of
    bands 1.. (U_1 .. U_NO, subtracted from the irradiance's coefficients; shade.cl ENV_OCC)."""
    nk = (deg + 1) ** 2
    c = c[:, :nk]
    band = shref.band_of(nk)
    nv_raw = dot(N, V)
    R = 2 * nv_raw * N - V
    Yn, Yr = shref.sh_eval(deg, N), shref.sh_eval(deg, R)
    if brdf == "cook_torrance":  # a dielectric's Gaussian, a metal's GGX lobe's own zonal coefficients (blended)
        r, met = m[:, 3:4], m[:, 4:5]
        gl = (1 - met) * np.exp(-0.5 * band * (band + 1) * r ** 4) + met * ggx_tables.lobe_bands(r, band[None, :], GGX)
    else:
        s2 = 2 / (relu(m[:, 6:7]) + 3)
        gl = np.exp(-0.5 * band * (band + 1) * s2)  # [P, nk]
    tn = Yn * shref.BAND_A[band]
    if occ is not None:
        n = min(nk - 1, occ.shape[1])
        tn = tn.astype(np.result_type(tn, occ))
        tn[:, 1:1 + n] = tn[:, 1:1 + n] - occ[:, :n]
    E = np.einsum("pk,ck->pc", tn, c)  # irradiance
    Gl = np.einsum("pk,ck->pc", Yr * gl, c)  # band-attenuated radiance along R
    if brdf == "cook_torrance":
        alb, r, met, ao = m[:, 0:3], m[:, 3:4], m[:, 4:5], m[:, 5:6]
        Fe = env_fresnel(alb, r, met, relu(nv_raw))
        return ao * ((1 - met) * alb / np.pi * E + Fe * Gl)
    return m[:, 0:3] / np.pi * E + m[:, 3:6] * Gl


def shade(pos, nrm, mat, face_id, cam, ints, params, brdf="cook_torrance", vlight=None, two_sided=True, occ=None):
    """Reference implementation of shade: ``rgb [P, 3]`` from the packed light table (``occ``: the environment's
    occlusion, :func:`env`)."""
    direct = ct_direct if brdf == "cook_torrance" else bp_direct
    V = normalize(cam - pos)
    N = normalize(nrm)
    if two_sided:
        back = dot(N, V).real < 0
        N = np.where(back, -N, N)
        if occ is not None:  # traced over the front normal's hemisphere: not applied to a back face
            occ = np.where(back, 0, occ)
    out = np.zeros(pos.shape, dtype=np.result_type(pos, nrm, mat, params, V, 0.0))
    for typ, off, a, b in np.asarray(ints):
        q = params[off:]
        if typ == AMBIENT:
            out = out + ambient(N, V, q[0:3], mat, brdf)
        elif typ == DIRECTIONAL:
            out = out + direct(N, V, normalize(q[0:3])[None], q[3:6], mat)
        elif typ == POINT:
            w = q[0:3] - pos
            sc = 1 / fmax(dot(w, w), POINT_D2_EPS) if a else 1.0
            out = out + direct(N, V, normalize(w), q[3:6] * sc, mat)
        elif typ == SH_ENV:
            out = out + env(N, V, mat, brdf, q[: 3 * b].reshape(3, b), a, occ)
        elif typ == VERTEX_SH:
            out = out + direct(N, V, normalize(vlight[:, 3:6]), vlight[:, 0:3], mat)
        elif typ == BOUNCE:
            out = out + ambient(N, V, vlight[:, 0:3], mat, brdf)
    return np.where((np.asarray(face_id) >= 0)[:, None], out, 0)


def vjp(pos, nrm, mat, face_id, cam, ints, params, v_rgb, brdf="cook_torrance", vlight=None, two_sided=True,
        h=1e-30, occ=None):
    """Reference adjoint by complex steps: ``dict(v_pos, v_nrm, v_mat, v_vlight, v_occ, v_params)``.

    Fragments are independent, so one complex step on a whole column of a per-fragment input gives
    that column's derivative for every fragment at once; light parameters take one step each.
    """
    args = {"pos": pos, "nrm": nrm, "mat": mat, "vlight": vlight, "params": params, "occ": occ}

    def run(**kw):
        a = dict(args, **kw)
        return shade(a["pos"], a["nrm"], a["mat"], face_id, cam, ints, a["params"], brdf, a["vlight"], two_sided,
                     a["occ"])

    out = {}
    for name in ("pos", "nrm", "mat", "vlight", "occ"):
        x = args[name]
        if x is None:
            out["v_" + name] = None
            continue
        g = np.zeros(x.shape)
        for j in range(x.shape[1]):
            xc = x.astype(np.complex128)
            xc[:, j] += 1j * h
            g[:, j] = np.sum(v_rgb * run(**{name: xc}).imag / h, axis=1)
        out["v_" + name] = g
    g = np.zeros(len(params))
    for j in range(len(params)):
        pc = params.astype(np.complex128)
        pc[j] += 1j * h
        g[j] = np.sum(v_rgb * run(params=pc).imag / h)
    out["v_params"] = g
    return out
