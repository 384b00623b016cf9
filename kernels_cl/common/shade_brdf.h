/* shade_brdf.h — the BRDFs and light terms of the shading op, as pairs f() / f_vjp().
 *
 * Compile-time choice: -DBRDF=<id of BRDF_COOK_TORRANCE or BRDF_BLINN_PHONG>, -DNMAT (generated).
 * Material channels per fragment (already activated by the parameter model):
 *   Cook-Torrance (NMAT 6):  albedo r,g,b | roughness r | metallic m | ambient occlusion ao
 *   Blinn-Phong  (NMAT 10):  kd r,g,b | ks r,g,b | shininess s (softplus'd) | ka r,g,b
 * N (unit shading normal), V (unit, surface -> camera), L (unit, surface -> light), Li (rgb).
 *
 * brdf_direct(N, V, L, Li, m): radiance reflected towards V from a light Li arriving along L.
 *   Both BRDFs return 0 (and zero gradients) when N.L <= 0.
 *   Cook-Torrance is Mitsuba 3's principled BSDF (the path tracer of the datasets and of the relit references) at its
 *   defaults (specular 0.5: a dielectric of index 1.5, F0 = 0.04; no sheen, clearcoat or transmission), checked
 *   against its eval() in tests/test_shade.py:
 *     a = r^2, nv = relu(N.V), nl = N.L, H = safe_normalize(L + V), nh = relu(N.H), hv = clamp(H.V, 0, 1),
 *     D = a^2 / (pi (nh^2 (a^2 - 1) + 1)^2 + 1e-6)  (the guard lowers a glossy lobe's very peak, 0.45x at roughness
 *       0.15, where Mitsuba has none and clamps a >= 1e-3; that exact form was measured worse from scratch on spot,
 *       relight -0.9 / -1.0 / -1.8 dB, session 38: kept),
 *     G / (4 nv nl) = 1 / (qv ql + 1e-6),  q(x) = x + sqrt(a^2 + (1 - a^2) x^2 + 1e-12)  (Smith's exact separable
 *       masking of GGX: G1(x) = 2 x / q(x)),
 *     F = (1 - m) Fd(hv) + m (albedo + (1 - albedo)(1 - hv)^5),  Fd the exact dielectric Fresnel (eta CT_ETA),
 *     s = (1 - Fo/2)(1 - Fi/2) + Rr (Fo + Fi + Fo Fi (Rr - 1)),  Fo = (1 - nl)^5, Fi = (1 - nv)^5, Rr = 2 r hv^2
 *       (the Disney diffuse with its retro-reflection; no (1 - F) factor, as Mitsuba's),
 *     out = [D F nl / (qv ql + 1e-6) + (1 - m) albedo s nl / pi] Li
 *   (until session 38: Schlick-GGX masking k = (r+1)^2/8, 0.36-0.69x the path tracer's lobe away from the normal,
 *   Schlick's Fresnel for the dielectric, a Lambert diffuse times relu(1 - F))
 *   Blinn-Phong:  e = relu(s) + 1,  out = [ks safe_pow(nh, e) + kd / pi nl] Li
 *     (the method's (N.L > 0) gate, docs/ARCHITECTURE.md §8, is the early return; the diffuse lobe is
 *     the normalised Lambert kd / pi, as Cook-Torrance's (at normal incidence) and the environment
 *     term's, so that kd is the base colour the exports write and a Mitsuba light set relights it in its
 *     units: the method's kd nl made kd = albedo / pi under point lights and the environment term pi times
 *     too dark)
 * ambient(N, V, La, m):  Cook-Torrance: the environment term below of a constant radiance La (E = pi La,
 *   Gl = La): ao [(1 - m) albedo + Fe] La, the Fresnel reflection of the surroundings included (issue 18: La albedo
 *   ao alone, the model before, left the grazing-angle reflection of a lit room to be faked by a rough, partly
 *   metallic lobe);  Blinn-Phong La ka.
 * env (SH environment light c [3, NK], radiance L(w) = sum_k c_k Y_k(w), active degree deg):
 *   E  = sum_k A_l(k) c_k Y_k(N)                       irradiance (Ramamoorthi-Hanrahan)
 *   R  = 2 (N.V) N - V,   Gl = sum_k g_l(k) c_k Y_k(R)   glossy radiance along the reflection,
 *   g_l the band attenuation of the glossy lobe (env_bands):
 *     Cook-Torrance: g_l = (1 - m) exp(-l (l + 1) a^2 / 2) + m LOBE_BANDS[r, l], a = r^2: a metal's is the GGX lobe's
 *       own band multipliers at normal incidence (ggx_tables.h, linear in r); the Gaussian is half the lobe's
 *       width, without its tails (band 2 at r = 0.35: 0.95 against 0.79). A dielectric keeps the Gaussian: with the
 *       table its faint glossy part kept view-dependent bands at the high roughness it is fitted with, -0.3 to
 *       -0.6 dB of novel views and no relight gain (session 46, bench/results/env_lobe_pocl_2026-11-27.txt).
 *     Blinn-Phong: g_l = exp(-l (l + 1) sigma^2 / 2), sigma^2 = 2/(e + 2) (the GGX-equivalent a^2 of an exponent e)
 *   Cook-Torrance:  Fe = (1 - m) [0.04 + 0.96 (1 - r)(1 - nv)^5] + m [albedo A(r, nv) + B(r, nv)],
 *                   out = ao [(1 - m) albedo / pi E + Fe Gl]
 *     a metal's weight under the SH environment (and the reflection bounce) is its lobe's exact directional albedo
 *     (DFG_A, DFG_B of ggx_tables.h, bilinear: the energy masking takes as the lobe roughens, 0.82 of the light at
 *     r = 0.6 as Mitsuba's own white furnace, and the Fresnel rise at grazing angles). Under an environment these
 *     two factors are all that tells a metal's roughness: with the damped Schlick and the Gaussian, spot_small as a
 *     metal of roughness 0.35 was fitted at 0.57 (0.39 with both from the lobe; session 46). The ambient light keeps
 *     the damped Schlick for a metal too (env_scales' lobe = 0): it is the
 *     soup's catch-all light, and with the lobe's weights there the soup's metallic probe (an ambient-lit trial)
 *     called three of four metal captures dielectrics (their soups then unrestarted: Chamfer 0.027 for 0.009).
 *     A dielectric keeps the roughness-damped Schlick everywhere: its exact table (session 38,
 *     bench/results/principled_bsdf_pocl_2026-11-27.txt) tied the environment's reflection to a roughness that drifts
 *     high on bob_env and gadget and cost bob_env 1.9 dB of albedo.
 *     (No (1 - Fe) on the diffuse, as the direct term has no (1 - F). For 0 < m < 1 the two blends multiply, Fe g_l,
 *     with cross terms; exact at m = 0 and 1, where every fitted material ends: the metallic trial holds 0.01 or 0.99.)
 *   Blinn-Phong:    out = kd / pi E + ks Gl
 *   (a constant white environment, c_0 = sqrt(4 pi), gives E = pi, Gl = 1: Cook-Torrance reflects
 *   ao [(1 - m) albedo + Fe]: albedo + 0.04 for a rough dielectric (1.04 for a white one), F0 A + B for a metal;
 *   an ambient light of the same radiance: F0 for a rough metal.)
 *   E and Gl are not clamped.
 *   Occluded environment (issue 18 item 2, shade.cl ENV_OCC): U [ENV_NK] (U_0 = 0) per fragment, the part of the
 *   bands above 0 that the geometry hides (visibility.vertex_occlusion: the cosine-weighted SH moments of the
 *   directions that reach the sky, normalised to the visible share, subtracted from those of the whole hemisphere):
 *     E = sum_k c_k (A_l(k) Y_k(N) - U_k)
 *   U = 0 reproduces the unoccluded E; band 0 stays with ao (the visible share), so ao E is the precomputed radiance
 *   transfer of the visible directions. Gl (the glossy part) is not occluded beyond ao. v_U_k = -gE . c_k.
 *
 * Adjoints (_vjp) are the hand-derived reverse of the statements above, line by line; relu, clamp
 * and fmax pass the gradient where their argument is inside the active range.
 */
#ifndef TRIPLET_SHADE_BRDF_H
#define TRIPLET_SHADE_BRDF_H

#include "real.h"
#include "shade_math.h"
#include "sh.h"
#include "ggx_tables.h"

/* BRDF (the selected model), BRDF_<NAME> (every model's id) and NMAT (its channel count) are
 * generated from the descriptors of triplet_cl/materials.py (BRDF.kernel_defines). */
#if !defined(BRDF) || !defined(NMAT)
#error "shade_brdf.h needs the BRDF defines of triplet_cl.materials (BRDF.kernel_defines())"
#endif

#define LOAD_RGB(m, i) ((REAL3)((m)[(i)], (m)[(i) + 1], (m)[(i) + 2]))
/* the dielectric's relative index of refraction (F0 = 0.04): Mitsuba's principled BSDF at its default specular 0.5 */
#define CT_ETA 1.5

inline REAL pow5(const REAL x)
{
    const REAL x2 = x * x;
    return x2 * x2 * x;
}

#if BRDF == BRDF_COOK_TORRANCE
/* ------------------------------------------------------------------------------------------ */

/* exact unpolarised Fresnel reflectance of a dielectric of relative index eta > 1 (light arriving from outside: no
 * total internal reflection) at the cosine c in [0, 1] of its incidence, and its derivative d/dc */
inline REAL fresnel_dielectric(const REAL c, const REAL eta, REAL* dF_dc)
{
    const REAL ct = sqrt(fmax((REAL)1 - ((REAL)1 - c * c) / (eta * eta), (REAL)0));
    const REAL ps = c + eta * ct, pp = eta * c + ct;
    const REAL rs = (c - eta * ct) / ps, rp = (eta * c - ct) / pp;
    /* d ct / dc = c / (eta^2 ct);  d rs / dc = 2 eta (ct - c ct') / ps^2,  d rp / dc = 2 eta (ct - c ct') / pp^2 */
    const REAL q = (REAL)2 * eta * (ct - c * c / (eta * eta * fmax(ct, (REAL)1e-12)));
    *dF_dc = rs * q / (ps * ps) + rp * q / (pp * pp);
    return (REAL)0.5 * (rs * rs + rp * rp);
}

inline REAL3 brdf_direct(const REAL3 N, const REAL3 V, const REAL3 L, const REAL3 Li, const REAL* m)
{
    const REAL nl = dot(N, L);
    if (!(nl > (REAL)0)) return (REAL3)(0);
    const REAL3 alb = LOAD_RGB(m, 0);
    const REAL r = m[3], met = m[4];
    const REAL nv = fmax(dot(N, V), (REAL)0);
    const REAL3 H = safe_normalize(L + V);
    const REAL nh = fmax(dot(N, H), (REAL)0);
    const REAL hv = clamp(dot(H, V), (REAL)0, (REAL)1);
    const REAL a2 = r * r * r * r;
    const REAL t = nh * nh * (a2 - (REAL)1) + (REAL)1;
    const REAL D = a2 / (R_PI * t * t + (REAL)1e-6);
    const REAL qv = nv + sqrt(a2 + ((REAL)1 - a2) * nv * nv + (REAL)1e-12);
    const REAL ql = nl + sqrt(a2 + ((REAL)1 - a2) * nl * nl + (REAL)1e-12);
    const REAL S = D * nl / (qv * ql + (REAL)1e-6);
    REAL dFd;
    const REAL Fd = fresnel_dielectric(hv, (REAL)CT_ETA, &dFd);
    const REAL f5 = pow5((REAL)1 - hv);
    const REAL3 F = ((REAL)1 - met) * Fd + met * (alb + ((REAL)1 - alb) * f5);
    const REAL Fo = pow5((REAL)1 - nl), Fi = pow5((REAL)1 - nv);
    const REAL Rr = (REAL)2 * r * hv * hv;
    const REAL s = ((REAL)1 - (REAL)0.5 * Fo) * ((REAL)1 - (REAL)0.5 * Fi) + Rr * (Fo + Fi + Fo * Fi * (Rr - (REAL)1));
    const REAL3 kd = ((REAL)1 - met) * alb * (s * nl / R_PI);
    return (S * F + kd) * Li;
}

inline void brdf_direct_vjp(const REAL3 N, const REAL3 V, const REAL3 L, const REAL3 Li, const REAL* m,
                            const REAL3 v_out, REAL3* v_N, REAL3* v_V, REAL3* v_L, REAL3* v_Li, REAL* v_m)
{
    const REAL nl = dot(N, L);
    if (!(nl > (REAL)0)) return;
    const REAL3 alb = LOAD_RGB(m, 0);
    const REAL r = m[3], met = m[4];
    const REAL nvr = dot(N, V);
    const REAL nv = fmax(nvr, (REAL)0);
    const REAL3 Hu = L + V;
    const REAL3 H = safe_normalize(Hu);
    const REAL nhr = dot(N, H);
    const REAL nh = fmax(nhr, (REAL)0);
    const REAL hvr = dot(H, V);
    const REAL hv = clamp(hvr, (REAL)0, (REAL)1);
    const REAL a2 = r * r * r * r;
    const REAL t = nh * nh * (a2 - (REAL)1) + (REAL)1;
    const REAL Dden = R_PI * t * t + (REAL)1e-6;
    const REAL D = a2 / Dden;
    const REAL sv = sqrt(a2 + ((REAL)1 - a2) * nv * nv + (REAL)1e-12);
    const REAL sl = sqrt(a2 + ((REAL)1 - a2) * nl * nl + (REAL)1e-12);
    const REAL qv = nv + sv, ql = nl + sl;
    const REAL den = qv * ql + (REAL)1e-6;
    const REAL S = D * nl / den;
    REAL dFd;
    const REAL Fd = fresnel_dielectric(hv, (REAL)CT_ETA, &dFd);
    const REAL omh = (REAL)1 - hv;
    const REAL f5 = pow5(omh);
    const REAL3 Fm = alb + ((REAL)1 - alb) * f5;
    const REAL3 F = ((REAL)1 - met) * Fd + met * Fm;
    const REAL Fo = pow5((REAL)1 - nl), Fi = pow5((REAL)1 - nv);
    const REAL Rr = (REAL)2 * r * hv * hv;
    const REAL s = ((REAL)1 - (REAL)0.5 * Fo) * ((REAL)1 - (REAL)0.5 * Fi) + Rr * (Fo + Fi + Fo * Fi * (Rr - (REAL)1));
    const REAL3 kd = ((REAL)1 - met) * alb * (s * nl / R_PI);

    *v_Li += v_out * (S * F + kd);
    const REAL3 g = v_out * Li;
    const REAL3 v_F = g * S;
    const REAL v_S = dot(g, F);
    /* kd = (1 - m) alb s nl / pi */
    REAL3 v_alb = g * ((REAL)1 - met) * (s * nl / R_PI);
    const REAL ga = dot(g, alb);
    REAL v_met = -ga * s * nl / R_PI;
    const REAL v_s = ga * ((REAL)1 - met) * nl / R_PI;
    REAL v_nl = ga * ((REAL)1 - met) * s / R_PI;
    /* s = (1 - Fo/2)(1 - Fi/2) + Rr (Fo + Fi + Fo Fi (Rr - 1)) */
    const REAL v_Rr = v_s * (Fo + Fi + Fo * Fi * ((REAL)2 * Rr - (REAL)1));
    const REAL v_Fo = v_s * (-(REAL)0.5 * ((REAL)1 - (REAL)0.5 * Fi) + Rr * ((REAL)1 + Fi * (Rr - (REAL)1)));
    const REAL v_Fi = v_s * (-(REAL)0.5 * ((REAL)1 - (REAL)0.5 * Fo) + Rr * ((REAL)1 + Fo * (Rr - (REAL)1)));
    const REAL onl = (REAL)1 - nl, onv = (REAL)1 - nv;
    v_nl -= (REAL)5 * onl * onl * onl * onl * v_Fo;
    REAL v_nv = -(REAL)5 * onv * onv * onv * onv * v_Fi;
    /* Rr = 2 r hv^2 */
    REAL v_r = v_Rr * (REAL)2 * hv * hv;
    REAL v_hv = v_Rr * (REAL)4 * r * hv;
    /* F = (1 - m) Fd + m (alb + (1 - alb) f5) */
    const REAL sF = v_F.x + v_F.y + v_F.z;
    v_met += dot(v_F, Fm) - Fd * sF;
    v_alb += v_F * met * ((REAL)1 - f5);
    const REAL v_f5 = met * dot(v_F, (REAL)1 - alb);
    v_hv += ((REAL)1 - met) * sF * dFd - (REAL)5 * omh * omh * omh * omh * v_f5;
    if (!(hvr > (REAL)0 && hvr < (REAL)1)) v_hv = (REAL)0;
    /* S = D nl / den,  den = qv ql + eps,  q = n + sqrt(a2 + (1 - a2) n^2 + eps) */
    const REAL v_D = v_S * nl / den;
    v_nl += v_S * D / den;
    const REAL v_den = -v_S * S / den;
    const REAL v_qv = v_den * ql, v_ql = v_den * qv;
    v_nv += v_qv * ((REAL)1 + ((REAL)1 - a2) * nv / sv);
    v_nl += v_ql * ((REAL)1 + ((REAL)1 - a2) * nl / sl);
    REAL v_a2 = v_qv * ((REAL)1 - nv * nv) / ((REAL)2 * sv) + v_ql * ((REAL)1 - nl * nl) / ((REAL)2 * sl);
    /* D = a2 / Dden */
    v_a2 += v_D / Dden;
    const REAL v_t = -v_D * D / Dden * (REAL)2 * R_PI * t;
    const REAL v_nh = v_t * (REAL)2 * nh * (a2 - (REAL)1);
    v_a2 += v_t * nh * nh;
    v_r += v_a2 * (REAL)4 * r * r * r;
    /* dot products */
    REAL3 v_H = (REAL3)(0);
    if (nhr > (REAL)0) {
        *v_N += v_nh * H;
        v_H += v_nh * N;
    }
    v_H += v_hv * V;
    *v_V += v_hv * H;
    const REAL3 v_Hu = safe_normalize_vjp(Hu, v_H);
    *v_L += v_Hu;
    *v_V += v_Hu;
    if (nvr > (REAL)0) {
        *v_N += v_nv * V;
        *v_V += v_nv * N;
    }
    *v_N += v_nl * L;
    *v_L += v_nl * N;
    v_m[0] += v_alb.x;
    v_m[1] += v_alb.y;
    v_m[2] += v_alb.z;
    v_m[3] += v_r;
    v_m[4] += v_met;
}

/* env_scales is defined below; the ambient term is the environment term of a constant radiance La (E = pi La,
 * Gl = La): ao [(1 - m) albedo + Fe] La — the Fresnel reflection of the surroundings as well (issue 18) */
inline void env_scales(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, REAL3* s_d, REAL3* s_g);
inline void env_scales_vjp(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, const REAL3 v_sd,
                           const REAL3 v_sg, REAL3* v_N, REAL3* v_V, REAL* v_m);

inline REAL3 ambient_term(const REAL3 N, const REAL3 V, const REAL3 La, const REAL* m)
{
    REAL3 s_d, s_g;
    env_scales(N, V, m, 0, &s_d, &s_g);
    return (s_d * R_PI + s_g) * La;
}

inline void ambient_term_vjp(const REAL3 N, const REAL3 V, const REAL3 La, const REAL* m, const REAL3 v_out,
                             REAL3* v_N, REAL3* v_V, REAL3* v_La, REAL* v_m)
{
    REAL3 s_d, s_g;
    env_scales(N, V, m, 0, &s_d, &s_g);
    *v_La += v_out * (s_d * R_PI + s_g);
    env_scales_vjp(N, V, m, 0, v_out * La * R_PI, v_out * La, v_N, v_V, v_m);
}

/* (A, B) of a metal's directional albedo F0 A + B at (r, nv), bilinear in ggx_tables.h's DFG_A / DFG_B (nodes k / 31
 * in both), and their slopes (0 outside (0, 1), where the lookup clamps) */
inline void env_dfg(const REAL r, const REAL nv, REAL* A, REAL* B, REAL* dAr, REAL* dBr, REAL* dAn, REAL* dBn)
{
    const REAL fr = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const REAL fn = clamp(nv, (REAL)0, (REAL)1) * (REAL)(GGX_NNV - 1);
    const int i = min((int)fr, GGX_NR - 2), j = min((int)fn, GGX_NNV - 2);
    const REAL t = fr - (REAL)i, u = fn - (REAL)j;
    const int k = i * GGX_NNV + j;
    const REAL a00 = DFG_A[k], a01 = DFG_A[k + 1], a10 = DFG_A[k + GGX_NNV], a11 = DFG_A[k + GGX_NNV + 1];
    const REAL b00 = DFG_B[k], b01 = DFG_B[k + 1], b10 = DFG_B[k + GGX_NNV], b11 = DFG_B[k + GGX_NNV + 1];
    const REAL a0 = a00 + (a01 - a00) * u, a1 = a10 + (a11 - a10) * u;
    const REAL b0 = b00 + (b01 - b00) * u, b1 = b10 + (b11 - b10) * u;
    *A = a0 + (a1 - a0) * t;
    *B = b0 + (b1 - b0) * t;
    const REAL sr = (r > (REAL)0 && r < (REAL)1) ? (REAL)(GGX_NR - 1) : (REAL)0;
    const REAL sn = (nv > (REAL)0 && nv < (REAL)1) ? (REAL)(GGX_NNV - 1) : (REAL)0;
    *dAr = (a1 - a0) * sr;
    *dBr = (b1 - b0) * sr;
    *dAn = ((a01 - a00) + ((a11 - a10) - (a01 - a00)) * t) * sn;
    *dBn = ((b01 - b00) + ((b11 - b10) - (b01 - b00)) * t) * sn;
}

/* the glossy lobe's attenuation g_l of the SH bands l = 0 .. deg, blended by the metallic m: (1 - m) G_l + m T_l,
 * G_l = exp(-l (l + 1) r^4 / 2) (by its recurrence G_l = G_(l-1) q^l, q = exp(-r^4): one exp a lobe) and
 * T_l = LOBE_BANDS[r, l] (ggx_tables.h, linear in r over nodes k / 31) */
inline void env_bands(const REAL* m, const int deg, REAL* gl)
{
    const REAL r = m[3], met = m[4];
    const REAL f = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const int i = min((int)f, GGX_NR - 2);
    const REAL t = f - (REAL)i;
    const REAL q = exp(-r * r * r * r);
    REAL G = (REAL)1, ql = (REAL)1;
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        const REAL a = LOBE_BANDS[i * GGX_NBANDS + l], b = LOBE_BANDS[(i + 1) * GGX_NBANDS + l];
        gl[l] = ((REAL)1 - met) * G + met * (a + (b - a) * t);
    }
}

/* v_gl (the adjoints of g_0 .. g_deg) -> v_m */
inline void env_bands_vjp(const REAL* m, const int deg, const REAL* v_gl, REAL* v_m)
{
    const REAL r = m[3], met = m[4];
    const REAL f = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const int i = min((int)f, GGX_NR - 2);
    const REAL t = f - (REAL)i;
    const REAL inside = (r > (REAL)0 && r < (REAL)1) ? (REAL)(GGX_NR - 1) : (REAL)0;
    const REAL q = exp(-r * r * r * r), r3 = r * r * r;
    REAL G = (REAL)1, ql = (REAL)1, v_met = (REAL)0, v_r = (REAL)0;
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        const REAL a = LOBE_BANDS[i * GGX_NBANDS + l], b = LOBE_BANDS[(i + 1) * GGX_NBANDS + l];
        v_met += v_gl[l] * (a + (b - a) * t - G);
        v_r += v_gl[l] * (-((REAL)1 - met) * G * (REAL)(2 * l * (l + 1)) * r3 + met * (b - a) * inside);
    }
    v_m[3] += v_r;
    v_m[4] += v_met;
}

/* out = s_d * E + s_g * Gl (per channel), with the material-dependent scales. lobe = 1 (the SH environment, the
 * reflection bounce): a metal's weight from its lobe, Fe = (1 - m) [0.04 + 0.96 (1 - r) f5] + m (alb A + B);
 * lobe = 0 (the ambient light): the damped Schlick Fe = F0 + (1 - F0)(1 - r) f5, F0 = 0.04 (1 - m) + m alb, the same
 * value for a dielectric, written as before session 46 so that an ambient-lit soup is the same bit for bit */
inline void env_scales(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, REAL3* s_d, REAL3* s_g)
{
    const REAL3 alb = LOAD_RGB(m, 0);
    const REAL r = m[3], met = m[4], ao = m[5];
    const REAL nv = fmax(dot(N, V), (REAL)0);
    REAL3 Fe;
    if (lobe) {
        REAL A, B, dAr, dBr, dAn, dBn;
        env_dfg(r, nv, &A, &B, &dAr, &dBr, &dAn, &dBn);
        const REAL Fd = (REAL)0.04 + (REAL)0.96 * ((REAL)1 - r) * pow5((REAL)1 - nv);
        Fe = ((REAL)1 - met) * Fd + met * (alb * A + B);
    } else {
        const REAL3 F0 = (REAL)0.04 * ((REAL)1 - met) + met * alb;
        Fe = F0 + ((REAL)1 - F0) * ((REAL)1 - r) * pow5((REAL)1 - nv);
    }
    *s_d = ao * ((REAL)1 - met) * alb / R_PI;
    *s_g = ao * Fe;
}

/* adjoint of env_scales: v_sd, v_sg -> v_N, v_V, v_m */
inline void env_scales_vjp(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, const REAL3 v_sd,
                           const REAL3 v_sg, REAL3* v_N, REAL3* v_V, REAL* v_m)
{
    const REAL3 alb = LOAD_RGB(m, 0);
    const REAL r = m[3], met = m[4], ao = m[5];
    const REAL nvr = dot(N, V);
    const REAL nv = fmax(nvr, (REAL)0);
    const REAL omv = (REAL)1 - nv;
    const REAL f5 = pow5(omv);
    REAL v_met, v_r, v_nv;
    REAL3 v_alb;
    if (lobe) {
        REAL A, B, dAr, dBr, dAn, dBn;
        env_dfg(r, nv, &A, &B, &dAr, &dBr, &dAn, &dBn);
        const REAL Fd = (REAL)0.04 + (REAL)0.96 * ((REAL)1 - r) * f5;
        const REAL3 Fm = alb * A + B;
        const REAL3 Fe = ((REAL)1 - met) * Fd + met * Fm;
        /* s_d = ao (1 - m) alb / pi,  s_g = ao Fe */
        v_m[5] += dot(v_sd, ((REAL)1 - met) * alb / R_PI) + dot(v_sg, Fe);
        const REAL3 v_Fe = ao * v_sg;
        v_met = -ao * dot(v_sd, alb) / R_PI;
        v_alb = ao * v_sd * ((REAL)1 - met) / R_PI;
        /* Fe = (1 - m) Fd + m Fm,  Fd = 0.04 + 0.96 (1 - r) f5,  Fm = alb A(r, nv) + B(r, nv) */
        const REAL sFe = v_Fe.x + v_Fe.y + v_Fe.z;
        v_met += dot(v_Fe, Fm) - Fd * sFe;
        const REAL v_Fd = ((REAL)1 - met) * sFe;
        v_alb += v_Fe * met * A;
        const REAL v_A = met * dot(v_Fe, alb), v_B = met * sFe;
        v_r = -v_Fd * (REAL)0.96 * f5 + v_A * dAr + v_B * dBr;
        v_nv = -(REAL)5 * omv * omv * omv * omv * v_Fd * (REAL)0.96 * ((REAL)1 - r) + v_A * dAn + v_B * dBn;
    } else {
        const REAL3 F0 = (REAL)0.04 * ((REAL)1 - met) + met * alb;
        const REAL3 Fe = F0 + ((REAL)1 - F0) * ((REAL)1 - r) * f5;
        /* s_d = ao (1 - m) alb / pi,  s_g = ao Fe */
        v_m[5] += dot(v_sd, ((REAL)1 - met) * alb / R_PI) + dot(v_sg, Fe);
        const REAL3 v_Fe = ao * v_sg;
        v_met = -ao * dot(v_sd, alb) / R_PI;
        v_alb = ao * v_sd * ((REAL)1 - met) / R_PI;
        /* Fe = F0 + (1 - F0)(1 - r) f5 */
        const REAL3 v_F0 = v_Fe * ((REAL)1 - ((REAL)1 - r) * f5);
        const REAL w = dot(v_Fe, (REAL)1 - F0);
        v_r = -w * f5;
        const REAL v_f5 = w * ((REAL)1 - r);
        v_nv = -(REAL)5 * omv * omv * omv * omv * v_f5;
        v_met += dot(v_F0, alb - (REAL)0.04);
        v_alb += v_F0 * met;
    }
    if (nvr > (REAL)0) {
        *v_N += v_nv * V;
        *v_V += v_nv * N;
    }
    v_m[0] += v_alb.x;
    v_m[1] += v_alb.y;
    v_m[2] += v_alb.z;
    v_m[3] += v_r;
    v_m[4] += v_met;
}

#elif BRDF == BRDF_BLINN_PHONG /* --------------------------------------------------------------- */

inline REAL3 brdf_direct(const REAL3 N, const REAL3 V, const REAL3 L, const REAL3 Li, const REAL* m)
{
    const REAL nl = dot(N, L);
    if (!(nl > (REAL)0)) return (REAL3)(0);
    const REAL3 H = safe_normalize(L + V);
    const REAL nh = fmax(dot(N, H), (REAL)0);
    const REAL e = fmax(m[6], (REAL)0) + (REAL)1;
    return (LOAD_RGB(m, 3) * safe_pow(nh, e) + LOAD_RGB(m, 0) * (nl / R_PI)) * Li;
}

inline void brdf_direct_vjp(const REAL3 N, const REAL3 V, const REAL3 L, const REAL3 Li, const REAL* m,
                            const REAL3 v_out, REAL3* v_N, REAL3* v_V, REAL3* v_L, REAL3* v_Li, REAL* v_m)
{
    const REAL nl = dot(N, L);
    if (!(nl > (REAL)0)) return;
    const REAL3 kd = LOAD_RGB(m, 0), ks = LOAD_RGB(m, 3);
    const REAL3 Hu = L + V;
    const REAL3 H = safe_normalize(Hu);
    const REAL nhr = dot(N, H);
    const REAL nh = fmax(nhr, (REAL)0);
    const REAL e = fmax(m[6], (REAL)0) + (REAL)1;
    const REAL sp = safe_pow(nh, e);
    const REAL nlp = nl / R_PI;
    *v_Li += v_out * (ks * sp + kd * nlp);
    const REAL3 g = v_out * Li;
    const REAL3 v_ks = g * sp, v_kd = g * nlp;
    REAL v_nh = (REAL)0, v_e = (REAL)0;
    safe_pow_vjp(nh, e, dot(g, ks), &v_nh, &v_e);
    const REAL v_nl = dot(g, kd) / R_PI;
    if (nhr > (REAL)0) {
        *v_N += v_nh * H;
        const REAL3 v_Hu = safe_normalize_vjp(Hu, v_nh * N);
        *v_L += v_Hu;
        *v_V += v_Hu;
    }
    *v_N += v_nl * L;
    *v_L += v_nl * N;
    v_m[0] += v_kd.x;
    v_m[1] += v_kd.y;
    v_m[2] += v_kd.z;
    v_m[3] += v_ks.x;
    v_m[4] += v_ks.y;
    v_m[5] += v_ks.z;
    if (m[6] > (REAL)0) v_m[6] += v_e;
}

inline REAL3 ambient_term(const REAL3 N, const REAL3 V, const REAL3 La, const REAL* m)
{
    return La * LOAD_RGB(m, 7);
}

inline void ambient_term_vjp(const REAL3 N, const REAL3 V, const REAL3 La, const REAL* m, const REAL3 v_out,
                             REAL3* v_N, REAL3* v_V, REAL3* v_La, REAL* v_m)
{
    *v_La += v_out * LOAD_RGB(m, 7);
    const REAL3 v_ka = v_out * La;
    v_m[7] += v_ka.x;
    v_m[8] += v_ka.y;
    v_m[9] += v_ka.z;
}

/* the glossy lobe's attenuation g_l = exp(-l (l + 1) sigma^2 / 2) of the SH bands l = 0 .. deg, sigma^2 =
 * 2 / (relu(s) + 3) (by its recurrence g_l = g_(l-1) q^l, q = exp(-sigma^2)) */
inline void env_bands(const REAL* m, const int deg, REAL* gl)
{
    const REAL q = exp(-(REAL)2 / (fmax(m[6], (REAL)0) + (REAL)3));
    REAL G = (REAL)1, ql = (REAL)1;
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        gl[l] = G;
    }
}

inline void env_bands_vjp(const REAL* m, const int deg, const REAL* v_gl, REAL* v_m)
{
    if (!(m[6] > (REAL)0)) return;
    const REAL qd = m[6] + (REAL)3;
    const REAL q = exp(-(REAL)2 / qd);
    REAL G = (REAL)1, ql = (REAL)1, v_s2 = (REAL)0;
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        v_s2 += v_gl[l] * G * (-(REAL)0.5 * (REAL)(l * (l + 1)));
    }
    v_m[6] += -v_s2 * (REAL)2 / (qd * qd);
}

inline void env_scales(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, REAL3* s_d, REAL3* s_g)
{
    (void)lobe;
    *s_d = LOAD_RGB(m, 0) / R_PI;
    *s_g = LOAD_RGB(m, 3);
}

inline void env_scales_vjp(const REAL3 N, const REAL3 V, const REAL* m, const int lobe, const REAL3 v_sd,
                           const REAL3 v_sg, REAL3* v_N, REAL3* v_V, REAL* v_m)
{
    (void)lobe;
    v_m[0] += v_sd.x / R_PI;
    v_m[1] += v_sd.y / R_PI;
    v_m[2] += v_sd.z / R_PI;
    v_m[3] += v_sg.x;
    v_m[4] += v_sg.y;
    v_m[5] += v_sg.z;
}

#else
#error "shade_brdf.h: no block for this BRDF (add its #elif BRDF == BRDF_<NAME> block)"
#endif /* BRDF */

/* ---- SH environment (shared by both BRDFs through env_scales) ----------------------------- */

#ifndef ENV_MAX_DEG
#define ENV_MAX_DEG 0
#endif
#define ENV_NK ((ENV_MAX_DEG + 1) * (ENV_MAX_DEG + 1))

/* Evaluates Yn = Y(N), Yr = Y(R) [ENV_NK], gl [ENV_MAX_DEG + 1]; returns E (irradiance, less the occluded part
 * U [ENV_NK], U_0 = 0: all zero without occlusion) and Gl. */
inline void env_eval(const REAL3 N, const REAL3 V, const REAL* m, const int deg, __global const REAL* c,
                     const int stride, const REAL* U, REAL* Yn, REAL* Yr, REAL* gl, REAL3* E, REAL3* Gl)
{
    const REAL3 R = (REAL)2 * dot(N, V) * N - V;
    sh_eval(deg, N, Yn);
    sh_eval(deg, R, Yr);
    env_bands(m, deg, gl);
    REAL3 e = (REAL3)(0), g = (REAL3)(0);
    for (int l = 0; l <= deg; ++l)
        for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
            const REAL3 ck = (REAL3)(c[k], c[stride + k], c[2 * stride + k]);
            e += (SH_BAND_A[l] * Yn[k] - U[k]) * ck;
            g += gl[l] * Yr[k] * ck;
        }
    *E = e;
    *Gl = g;
}

inline REAL3 env_term(const REAL3 N, const REAL3 V, const REAL* m, const int deg, __global const REAL* c,
                      const int stride, const REAL* U)
{
    REAL Yn[ENV_NK], Yr[ENV_NK], gl[ENV_MAX_DEG + 1];
    REAL3 E, Gl, s_d, s_g;
    env_eval(N, V, m, deg, c, stride, U, Yn, Yr, gl, &E, &Gl);
    env_scales(N, V, m, 1, &s_d, &s_g);
    return s_d * E + s_g * Gl;
}

/* Adjoint of env_term. Leaves Yn, Yr, gl and the coefficient weights gE = v_out s_d,
 * gG = v_out s_g for the coefficient gradients v_c[ch, k] = gE_ch (A_l Yn_k - U_k) + gG_ch g_l Yr_k
 * (and v_U_k = -gE . c_k, both formed by the caller). */
inline void env_term_vjp(const REAL3 N, const REAL3 V, const REAL* m, const int deg, __global const REAL* c,
                         const int stride, const REAL* U, const REAL3 v_out, REAL* Yn, REAL* Yr, REAL* gl,
                         REAL3* gE, REAL3* gG, REAL3* v_N, REAL3* v_V, REAL* v_m)
{
    REAL3 E, Gl, s_d, s_g;
    env_eval(N, V, m, deg, c, stride, U, Yn, Yr, gl, &E, &Gl);
    env_scales(N, V, m, 1, &s_d, &s_g);
    *gE = v_out * s_d;
    *gG = v_out * s_g;
    REAL v_Yn[ENV_NK], v_Yr[ENV_NK], v_gl[ENV_MAX_DEG + 1];
    for (int l = 0; l <= deg; ++l) {
        v_gl[l] = (REAL)0;
        for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
            const REAL3 ck = (REAL3)(c[k], c[stride + k], c[2 * stride + k]);
            v_Yn[k] = SH_BAND_A[l] * dot(*gE, ck);
            v_Yr[k] = gl[l] * dot(*gG, ck);
            v_gl[l] += Yr[k] * dot(*gG, ck);
        }
    }
    env_bands_vjp(m, deg, v_gl, v_m);
    const REAL nvr = dot(N, V);
    const REAL3 R = (REAL)2 * nvr * N - V;
    *v_N += sh_eval_vjp(deg, N, v_Yn);
    const REAL3 v_R = sh_eval_vjp(deg, R, v_Yr);
    const REAL rn = dot(v_R, N);
    *v_N += (REAL)2 * nvr * v_R + (REAL)2 * rn * V;
    *v_V += (REAL)2 * rn * N - v_R;
    env_scales_vjp(N, V, m, 1, v_out * E, v_out * Gl, v_N, v_V, v_m);
}

#endif /* TRIPLET_SHADE_BRDF_H */
