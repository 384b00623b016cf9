/* shade_lanes.cl — the shading pair of shade.cl for the training's common case, eight fragments per work-item
 * in explicit vector lanes (REAL8), for CPU devices.
 *
 * Why: PoCL (and Intel's CPU runtime) vectorise a kernel across work-items only when it holds no float3 and its
 * work-items read consecutive values (bench/pocl_vectorize.py); shade.cl holds both, so it runs one fragment per
 * SIMD lane-slot of a scalar core. Here each work-item shades W = 8 fragments, every value a REAL8 whose lane k
 * is fragment p0 + k, and the maths is written per component (a 3-vector is three REAL8: struct V3). Measured on
 * a toy of the Cook-Torrance point-light forward: 2-3x the scalar kernel (bench/results/shade_lanes_*.txt).
 *
 * What it covers (ops/shade.py: lanes_cover; the CPU default: lanes_supported): the Cook-Torrance BRDF (NMAT 6:
 * albedo rgb, roughness, metallic, ambient occlusion), lights among ambient, directional, point, SH environment
 * (at most NUM_PARAMS <= 64: degree 2 with a few point lights) and the traced bounce (its radiance in the VL block),
 * their table compiled in as in shade.cl; the packed fragment attributes (every row a fragment, X_LD / X_OFF column
 * blocks, ALPHA_COPY), optionally HAS_VIS (the shadow casters' transmittance, no environment occlusion). Everything
 * else, and GPUs by default, take shade.cl, which stays the reference this is tested against
 * (tests/test_shade_lanes.py: images, every adjoint, float64, central differences).
 *
 * The formulas are shade_brdf.h's, sh.h's and lights.h's (brdf_direct, ambient_term and env_term with env_scales'
 * lobes 0 and 1, sh_eval, light_incident) and their adjoints, with each branch a per-lane select: brdf_direct's
 * "nl <= 0: no light" masks the lane's result (forward) or its cotangent (adjoint: every adjoint is linear in it,
 * and every intermediate is finite there); the GGX tables are looked up lane by lane. A lane past P repeats row
 * P - 1, a lane whose cotangent is zero (behind the compositing's cut-off) computes anyway; both are masked to
 * exact zeros (KEEP) before the stores and the light sums, as shade_bwd's skip gives them.
 * Light-parameter adjoints: each work-item sums its lanes, then the work-group sums its items (local memory, fixed
 * order, RED_W columns at a time, after the light loop) into one row of v_light_part [num_groups, NUM_PARAMS].
 */
#include "real.h"
#include "sh.h"          /* SH_KLM, SH_BAND_A (included before S is defined: its functions name a variable S) */
#include "ggx_tables.h"  /* DFG_A, DFG_B, LOBE_BANDS */

#ifndef ENV_MAX_DEG
#define ENV_MAX_DEG 0
#endif
#define ENV_NK ((ENV_MAX_DEG + 1) * (ENV_MAX_DEG + 1))
#define W 8
#define S REAL8
#define R_PI ((REAL)3.14159265358979323846)
#define SAFE_EPS2 ((REAL)1e-20)
#define POINT_D2_EPS ((REAL)1e-6)
#define CT_ETA ((REAL)1.5)
#ifndef RED_W
#define RED_W 16
#endif
#if !defined(NUM_LIGHTS) || !defined(LIGHT_TABLE) || !defined(NUM_PARAMS)
#error "shade_lanes.cl needs NUM_LIGHTS, LIGHT_TABLE and NUM_PARAMS (ops/shade.py)"
#endif
__constant int LIGHT_ROWS[] = {LIGHT_TABLE};
/* the lane select: c ? b : a, per lane (c a comparison of S values, of type MASK_OF_<REAL>_8) */
#define MASK_OF_float_8 int8
#define MASK_OF_double_8 long8
#define WHERE(c, b, a) select((a), (b), (c))

typedef struct {
    S x, y, z;
} V3;

inline V3 v3(const S x, const S y, const S z)
{
    V3 r;
    r.x = x;
    r.y = y;
    r.z = z;
    return r;
}
inline V3 v3_add(const V3 a, const V3 b) { return v3(a.x + b.x, a.y + b.y, a.z + b.z); }
inline V3 v3_sub(const V3 a, const V3 b) { return v3(a.x - b.x, a.y - b.y, a.z - b.z); }
inline V3 v3_mul(const V3 a, const V3 b) { return v3(a.x * b.x, a.y * b.y, a.z * b.z); }
inline V3 v3_scale(const V3 a, const S s) { return v3(a.x * s, a.y * s, a.z * s); }
inline S v3_dot(const V3 a, const V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
#define V3_WHERE(c, b, a) v3(WHERE((c), (b).x, (a).x), WHERE((c), (b).y, (a).y), WHERE((c), (b).z, (a).z))

inline S pow5w(const S x)
{
    const S x2 = x * x;
    return x2 * x2 * x;
}

inline V3 safe_normalize_w(const V3 v) { return v3_scale(v, rsqrt(fmax(v3_dot(v, v), SAFE_EPS2))); }

/* shade_math.h's safe_normalize_vjp per lane */
inline V3 safe_normalize_vjp_w(const V3 v, const V3 v_n)
{
    const S l2 = v3_dot(v, v);
    const S il = rsqrt(fmax(l2, SAFE_EPS2));
    const V3 n = v3_scale(v, il);
    const V3 in = v3_scale(v3_sub(v_n, v3_scale(n, v3_dot(n, v_n))), il);
    const V3 out = v3_scale(v_n, rsqrt(SAFE_EPS2));
    return V3_WHERE(l2 > SAFE_EPS2, in, out);
}

/* shade_brdf.h's fresnel_dielectric per lane (c in [0, 1]) */
inline S fresnel_w(const S c, S* dF_dc)
{
    const REAL eta = CT_ETA;
    const S ct = sqrt(fmax((REAL)1 - ((REAL)1 - c * c) / (eta * eta), (REAL)0));
    const S ps = c + eta * ct, pp = eta * c + ct;
    const S rs = (c - eta * ct) / ps, rp = (eta * c - ct) / pp;
    const S q = (REAL)2 * eta * (ct - c * c / (eta * eta * fmax(ct, (REAL)1e-12)));
    *dF_dc = rs * q / (ps * ps) + rp * q / (pp * pp);
    return (REAL)0.5 * (rs * rs + rp * rp);
}

/* brdf_direct (Cook-Torrance) per lane; m: the 6 material channels */
inline V3 ct_direct(const V3 N, const V3 V, const V3 L, const V3 Li, const S* m)
{
    const S nl = v3_dot(N, L);
    const V3 alb = v3(m[0], m[1], m[2]);
    const S r = m[3], met = m[4];
    const S nv = fmax(v3_dot(N, V), (REAL)0);
    const V3 H = safe_normalize_w(v3_add(L, V));
    const S nh = fmax(v3_dot(N, H), (REAL)0);
    const S hv = clamp(v3_dot(H, V), (REAL)0, (REAL)1);
    const S a2 = r * r * r * r;
    const S t = nh * nh * (a2 - (REAL)1) + (REAL)1;
    const S D = a2 / (R_PI * t * t + (REAL)1e-6);
    const S qv = nv + sqrt(a2 + ((REAL)1 - a2) * nv * nv + (REAL)1e-12);
    const S ql = nl + sqrt(a2 + ((REAL)1 - a2) * nl * nl + (REAL)1e-12);
    const S Sg = D * nl / (qv * ql + (REAL)1e-6);
    S dFd;
    const S Fd = fresnel_w(hv, &dFd);
    const S f5 = pow5w((REAL)1 - hv);
    const S Fo = pow5w((REAL)1 - nl), Fi = pow5w((REAL)1 - nv);
    const S Rr = (REAL)2 * r * hv * hv;
    const S s = ((REAL)1 - (REAL)0.5 * Fo) * ((REAL)1 - (REAL)0.5 * Fi) + Rr * (Fo + Fi + Fo * Fi * (Rr - (REAL)1));
    const S kk = s * nl / R_PI, om = (REAL)1 - met, fd = om * Fd;
    /* F_c = (1 - met) Fd + met (alb_c + (1 - alb_c) f5),  kd_c = (1 - met) alb_c kk */
    const V3 F = v3(fd + met * (alb.x + ((REAL)1 - alb.x) * f5), fd + met * (alb.y + ((REAL)1 - alb.y) * f5),
                    fd + met * (alb.z + ((REAL)1 - alb.z) * f5));
    const V3 kd = v3_scale(v3_scale(alb, om), kk);
    const V3 out = v3_mul(v3_add(v3_scale(F, Sg), kd), Li);
    const S zero = (S)(0);
    return V3_WHERE(nl > (REAL)0, out, v3(zero, zero, zero));
}

/* brdf_direct_vjp (Cook-Torrance) per lane; v_out already zero on the lanes without a cotangent */
inline void ct_direct_vjp(const V3 N, const V3 V, const V3 L, const V3 Li, const S* m, V3 v_out, V3* v_N, V3* v_V,
                          V3* v_L, V3* v_Li, S* v_m)
{
    const S nl = v3_dot(N, L);
    const S zero = (S)(0);
    v_out = V3_WHERE(nl > (REAL)0, v_out, v3(zero, zero, zero));
    const V3 alb = v3(m[0], m[1], m[2]);
    const S r = m[3], met = m[4];
    const S nvr = v3_dot(N, V);
    const S nv = fmax(nvr, (REAL)0);
    const V3 Hu = v3_add(L, V);
    const V3 H = safe_normalize_w(Hu);
    const S nhr = v3_dot(N, H);
    const S nh = fmax(nhr, (REAL)0);
    const S hvr = v3_dot(H, V);
    const S hv = clamp(hvr, (REAL)0, (REAL)1);
    const S a2 = r * r * r * r;
    const S t = nh * nh * (a2 - (REAL)1) + (REAL)1;
    const S Dden = R_PI * t * t + (REAL)1e-6;
    const S D = a2 / Dden;
    const S sv = sqrt(a2 + ((REAL)1 - a2) * nv * nv + (REAL)1e-12);
    const S sl = sqrt(a2 + ((REAL)1 - a2) * nl * nl + (REAL)1e-12);
    const S qv = nv + sv, ql = nl + sl;
    const S den = qv * ql + (REAL)1e-6;
    const S Sg = D * nl / den;
    S dFd;
    const S Fd = fresnel_w(hv, &dFd);
    const S omh = (REAL)1 - hv;
    const S f5 = pow5w(omh);
    const V3 Fm = v3(alb.x + ((REAL)1 - alb.x) * f5, alb.y + ((REAL)1 - alb.y) * f5, alb.z + ((REAL)1 - alb.z) * f5);
    const S om = (REAL)1 - met;
    const V3 F = v3(om * Fd + met * Fm.x, om * Fd + met * Fm.y, om * Fd + met * Fm.z);
    const S Fo = pow5w((REAL)1 - nl), Fi = pow5w((REAL)1 - nv);
    const S Rr = (REAL)2 * r * hv * hv;
    const S s = ((REAL)1 - (REAL)0.5 * Fo) * ((REAL)1 - (REAL)0.5 * Fi) + Rr * (Fo + Fi + Fo * Fi * (Rr - (REAL)1));
    const S kk = s * nl / R_PI;
    const V3 kd = v3_scale(v3_scale(alb, om), kk);

    *v_Li = v3_add(*v_Li, v3_mul(v_out, v3_add(v3_scale(F, Sg), kd)));
    const V3 g = v3_mul(v_out, Li);
    const V3 v_F = v3_scale(g, Sg);
    const S v_S = v3_dot(g, F);
    /* kd = (1 - m) alb s nl / pi */
    V3 v_alb = v3_scale(g, om * kk);
    const S ga = v3_dot(g, alb);
    S v_met = -ga * kk;
    const S v_s = ga * om * nl / R_PI;
    S v_nl = ga * om * s / R_PI;
    /* s = (1 - Fo/2)(1 - Fi/2) + Rr (Fo + Fi + Fo Fi (Rr - 1)) */
    const S v_Rr = v_s * (Fo + Fi + Fo * Fi * ((REAL)2 * Rr - (REAL)1));
    const S v_Fo = v_s * (-(REAL)0.5 * ((REAL)1 - (REAL)0.5 * Fi) + Rr * ((REAL)1 + Fi * (Rr - (REAL)1)));
    const S v_Fi = v_s * (-(REAL)0.5 * ((REAL)1 - (REAL)0.5 * Fo) + Rr * ((REAL)1 + Fo * (Rr - (REAL)1)));
    const S onl = (REAL)1 - nl, onv = (REAL)1 - nv;
    v_nl -= (REAL)5 * onl * onl * onl * onl * v_Fo;
    S v_nv = -(REAL)5 * onv * onv * onv * onv * v_Fi;
    /* Rr = 2 r hv^2 */
    S v_r = v_Rr * (REAL)2 * hv * hv;
    S v_hv = v_Rr * (REAL)4 * r * hv;
    /* F = (1 - m) Fd + m (alb + (1 - alb) f5) */
    const S sF = v_F.x + v_F.y + v_F.z;
    v_met += v3_dot(v_F, Fm) - Fd * sF;
    const S mf = met * ((REAL)1 - f5);
    v_alb = v3_add(v_alb, v3_scale(v_F, mf));
    const S v_f5 = met * (v_F.x * ((REAL)1 - alb.x) + v_F.y * ((REAL)1 - alb.y) + v_F.z * ((REAL)1 - alb.z));
    v_hv += om * sF * dFd - (REAL)5 * omh * omh * omh * omh * v_f5;
    v_hv = WHERE(hvr > (REAL)0 && hvr < (REAL)1, v_hv, zero);
    /* S = D nl / den,  den = qv ql + eps,  q = n + sqrt(a2 + (1 - a2) n^2 + eps) */
    const S v_D = v_S * nl / den;
    v_nl += v_S * D / den;
    const S v_den = -v_S * Sg / den;
    const S v_qv = v_den * ql, v_ql = v_den * qv;
    v_nv += v_qv * ((REAL)1 + ((REAL)1 - a2) * nv / sv);
    v_nl += v_ql * ((REAL)1 + ((REAL)1 - a2) * nl / sl);
    S v_a2 = v_qv * ((REAL)1 - nv * nv) / ((REAL)2 * sv) + v_ql * ((REAL)1 - nl * nl) / ((REAL)2 * sl);
    /* D = a2 / Dden */
    v_a2 += v_D / Dden;
    const S v_t = -v_D * D / Dden * (REAL)2 * R_PI * t;
    const S v_nh = WHERE(nhr > (REAL)0, v_t * (REAL)2 * nh * (a2 - (REAL)1), zero);
    v_a2 += v_t * nh * nh;
    v_r += v_a2 * (REAL)4 * r * r * r;
    /* dot products */
    *v_N = v3_add(*v_N, v3_scale(H, v_nh));
    V3 v_H = v3_add(v3_scale(N, v_nh), v3_scale(V, v_hv));
    *v_V = v3_add(*v_V, v3_scale(H, v_hv));
    const V3 v_Hu = safe_normalize_vjp_w(Hu, v_H);
    *v_L = v3_add(*v_L, v_Hu);
    *v_V = v3_add(*v_V, v_Hu);
    const S v_nvp = WHERE(nvr > (REAL)0, v_nv, zero);
    *v_N = v3_add(*v_N, v3_scale(V, v_nvp));
    *v_V = v3_add(*v_V, v3_scale(N, v_nvp));
    *v_N = v3_add(*v_N, v3_scale(L, v_nl));
    *v_L = v3_add(*v_L, v3_scale(N, v_nl));
    v_m[0] += v_alb.x;
    v_m[1] += v_alb.y;
    v_m[2] += v_alb.z;
    v_m[3] += v_r;
    v_m[4] += v_met;
}

/* ambient_term (env_scales' lobe 0) per lane: ao [(1 - m) alb + pi Fe] La / ... as shade_brdf.h */
inline void ambient_scales(const V3 N, const V3 V, const S* m, V3* s_d, V3* s_g)
{
    const S r = m[3], met = m[4], ao = m[5];
    const S nv = fmax(v3_dot(N, V), (REAL)0);
    const S rf = ((REAL)1 - r) * pow5w((REAL)1 - nv), f0d = (REAL)0.04 * ((REAL)1 - met), aom = ao * ((REAL)1 - met);
    const V3 F0 = v3(f0d + met * m[0], f0d + met * m[1], f0d + met * m[2]);
    *s_d = v3(aom * m[0] / R_PI, aom * m[1] / R_PI, aom * m[2] / R_PI);
    *s_g = v3(ao * (F0.x + ((REAL)1 - F0.x) * rf), ao * (F0.y + ((REAL)1 - F0.y) * rf),
              ao * (F0.z + ((REAL)1 - F0.z) * rf));
}

inline V3 ct_ambient(const V3 N, const V3 V, const V3 La, const S* m)
{
    V3 s_d, s_g;
    ambient_scales(N, V, m, &s_d, &s_g);
    return v3_mul(v3_add(v3_scale(s_d, (S)(R_PI)), s_g), La);
}

inline void ct_ambient_vjp(const V3 N, const V3 V, const V3 La, const S* m, const V3 v_out, V3* v_N, V3* v_V,
                           V3* v_La, S* v_m)
{
    V3 s_d, s_g;
    ambient_scales(N, V, m, &s_d, &s_g);
    *v_La = v3_add(*v_La, v3_mul(v_out, v3_add(v3_scale(s_d, (S)(R_PI)), s_g)));
    const V3 v_sg = v3_mul(v_out, La), v_sd = v3_scale(v_sg, (S)(R_PI));
    /* env_scales_vjp, lobe 0 */
    const V3 alb = v3(m[0], m[1], m[2]);
    const S r = m[3], met = m[4], ao = m[5];
    const S nvr = v3_dot(N, V);
    const S nv = fmax(nvr, (REAL)0);
    const S omv = (REAL)1 - nv;
    const S f5 = pow5w(omv);
    const S om = (REAL)1 - met, f0d = (REAL)0.04 * om, rf = ((REAL)1 - r) * f5;
    const V3 F0 = v3(f0d + met * alb.x, f0d + met * alb.y, f0d + met * alb.z);
    const V3 Fe = v3(F0.x + ((REAL)1 - F0.x) * rf, F0.y + ((REAL)1 - F0.y) * rf, F0.z + ((REAL)1 - F0.z) * rf);
    v_m[5] += v3_dot(v_sd, v3_scale(alb, om / R_PI)) + v3_dot(v_sg, Fe);
    const V3 v_Fe = v3_scale(v_sg, ao);
    S v_met = -ao * v3_dot(v_sd, alb) / R_PI;
    V3 v_alb = v3_scale(v_sd, ao * om / R_PI);
    const V3 v_F0 = v3_scale(v_Fe, (REAL)1 - rf);
    const S w = v_Fe.x * ((REAL)1 - F0.x) + v_Fe.y * ((REAL)1 - F0.y) + v_Fe.z * ((REAL)1 - F0.z);
    const S v_r = -w * f5;
    const S v_f5 = w * ((REAL)1 - r);
    const S v_nv = WHERE(nvr > (REAL)0, -(REAL)5 * omv * omv * omv * omv * v_f5, (S)(0));
    v_met += v_F0.x * (alb.x - (REAL)0.04) + v_F0.y * (alb.y - (REAL)0.04) + v_F0.z * (alb.z - (REAL)0.04);
    v_alb = v3_add(v_alb, v3_scale(v_F0, met));
    *v_N = v3_add(*v_N, v3_scale(V, v_nv));
    *v_V = v3_add(*v_V, v3_scale(N, v_nv));
    v_m[0] += v_alb.x;
    v_m[1] += v_alb.y;
    v_m[2] += v_alb.z;
    v_m[3] += v_r;
    v_m[4] += v_met;
}


/* ---- the SH environment (env_scales' lobe 1, env_eval, env_term and their adjoints: shade_brdf.h, sh.h) --------- */

/* eight lookups of a __constant table, one per lane */
inline S lookup_w(__constant const float* tab, const int8 i)
{
    return (S)((REAL)tab[i.s0], (REAL)tab[i.s1], (REAL)tab[i.s2], (REAL)tab[i.s3], (REAL)tab[i.s4], (REAL)tab[i.s5],
               (REAL)tab[i.s6], (REAL)tab[i.s7]);
}

/* sh.h's sh_eval per lane (its recurrences; qmm depends on m only) */
inline void sh_eval_w(const int deg, const V3 d, S* Y)
{
    const S x = d.x, y = d.y, z = d.z;
    S Cc = (S)(1), Sc = (S)(0);
    REAL qmm = (REAL)1;
    for (int m = 0; m <= deg; ++m) {
        if (m > 0) {
            const S Cn = x * Cc - y * Sc;
            Sc = x * Sc + y * Cc;
            Cc = Cn;
            qmm *= -(REAL)(2 * m - 1);
        }
        S q2 = (S)(0), q1 = (S)(0);
        for (int l = m; l <= deg; ++l) {
            S q;
            if (l == m) q = (S)(qmm);
            else if (l == m + 1) q = (REAL)(2 * m + 1) * z * qmm;
            else q = ((REAL)(2 * l - 1) * z * q1 - (REAL)(l + m - 1) * q2) / (REAL)(l - m);
            const S kq = SH_KLM[l * (l + 1) / 2 + m] * q;
            const int c = l * l + l;
            if (m == 0) {
                Y[c] = kq;
            } else {
                Y[c + m] = kq * Cc;
                Y[c - m] = kq * Sc;
            }
            q2 = q1;
            q1 = q;
        }
    }
}

/* sh.h's sh_eval_vjp per lane */
inline V3 sh_eval_vjp_w(const int deg, const V3 d, const S* v_Y)
{
    const S x = d.x, y = d.y, z = d.z;
    S Cc = (S)(1), Sc = (S)(0);
    REAL qmm = (REAL)1;
    S v_x = (S)(0), v_y = (S)(0), v_z = (S)(0);
    for (int m = 0; m <= deg; ++m) {
        const S Cp = Cc, Sp = Sc;
        if (m > 0) {
            const S Cn = x * Cc - y * Sc;
            Sc = x * Sc + y * Cc;
            Cc = Cn;
            qmm *= -(REAL)(2 * m - 1);
        }
        S q2 = (S)(0), q1 = (S)(0), dq2 = (S)(0), dq1 = (S)(0);
        S v_C = (S)(0), v_S = (S)(0);
        for (int l = m; l <= deg; ++l) {
            S q, dq;
            if (l == m) {
                q = (S)(qmm);
                dq = (S)(0);
            } else if (l == m + 1) {
                q = (REAL)(2 * m + 1) * z * qmm;
                dq = (S)((REAL)(2 * m + 1) * qmm);
            } else {
                const REAL a = (REAL)(2 * l - 1), b = (REAL)(l + m - 1), inv = (REAL)1 / (REAL)(l - m);
                q = (a * z * q1 - b * q2) * inv;
                dq = (a * (q1 + z * dq1) - b * dq2) * inv;
            }
            const REAL K = SH_KLM[l * (l + 1) / 2 + m];
            const int c = l * l + l;
            if (m == 0) {
                v_z += v_Y[c] * K * dq;
            } else {
                v_z += K * dq * (v_Y[c + m] * Cc + v_Y[c - m] * Sc);
                v_C += K * q * v_Y[c + m];
                v_S += K * q * v_Y[c - m];
            }
            q2 = q1;
            q1 = q;
            dq2 = dq1;
            dq1 = dq;
        }
        if (m > 0) {
            const REAL fm = (REAL)m;
            v_x += fm * (v_C * Cp + v_S * Sp);
            v_y += fm * (v_S * Cp - v_C * Sp);
        }
    }
    return v3(v_x, v_y, v_z);
}

/* shade_brdf.h's env_dfg per lane: (A, B) bilinear in DFG_A / DFG_B at (r, nv) and their slopes */
inline void env_dfg_w(const S r, const S nv, S* A, S* B, S* dAr, S* dBr, S* dAn, S* dBn)
{
    const S fr = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const S fn = clamp(nv, (REAL)0, (REAL)1) * (REAL)(GGX_NNV - 1);
    const int8 i = min(convert_int8(fr), GGX_NR - 2), j = min(convert_int8(fn), GGX_NNV - 2);
    const S t = fr - TRIPLET_CAT(convert_, S)(i), u = fn - TRIPLET_CAT(convert_, S)(j);
    const int8 k = i * GGX_NNV + j;
    const S a00 = lookup_w(DFG_A, k), a01 = lookup_w(DFG_A, k + 1), a10 = lookup_w(DFG_A, k + GGX_NNV),
            a11 = lookup_w(DFG_A, k + GGX_NNV + 1);
    const S b00 = lookup_w(DFG_B, k), b01 = lookup_w(DFG_B, k + 1), b10 = lookup_w(DFG_B, k + GGX_NNV),
            b11 = lookup_w(DFG_B, k + GGX_NNV + 1);
    const S a0 = a00 + (a01 - a00) * u, a1 = a10 + (a11 - a10) * u;
    const S b0 = b00 + (b01 - b00) * u, b1 = b10 + (b11 - b10) * u;
    *A = a0 + (a1 - a0) * t;
    *B = b0 + (b1 - b0) * t;
    const S sr = WHERE(r > (REAL)0 && r < (REAL)1, (S)((REAL)(GGX_NR - 1)), (S)(0));
    const S sn = WHERE(nv > (REAL)0 && nv < (REAL)1, (S)((REAL)(GGX_NNV - 1)), (S)(0));
    *dAr = (a1 - a0) * sr;
    *dBr = (b1 - b0) * sr;
    *dAn = ((a01 - a00) + ((a11 - a10) - (a01 - a00)) * t) * sn;
    *dBn = ((b01 - b00) + ((b11 - b10) - (b01 - b00)) * t) * sn;
}

/* env_bands per lane: g_l = (1 - m) G_l + m T_l (LOBE_BANDS linear in r) */
inline void env_bands_w(const S* m, const int deg, S* gl)
{
    const S r = m[3], met = m[4];
    const S f = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const int8 i = min(convert_int8(f), GGX_NR - 2);
    const S t = f - TRIPLET_CAT(convert_, S)(i);
    const S q = exp(-r * r * r * r);
    S G = (S)(1), ql = (S)(1);
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        const S a = lookup_w(LOBE_BANDS, i * GGX_NBANDS + l), b = lookup_w(LOBE_BANDS, (i + 1) * GGX_NBANDS + l);
        gl[l] = ((REAL)1 - met) * G + met * (a + (b - a) * t);
    }
}

inline void env_bands_vjp_w(const S* m, const int deg, const S* v_gl, S* v_m)
{
    const S r = m[3], met = m[4];
    const S f = clamp(r, (REAL)0, (REAL)1) * (REAL)(GGX_NR - 1);
    const int8 i = min(convert_int8(f), GGX_NR - 2);
    const S t = f - TRIPLET_CAT(convert_, S)(i);
    const S inside = WHERE(r > (REAL)0 && r < (REAL)1, (S)((REAL)(GGX_NR - 1)), (S)(0));
    const S q = exp(-r * r * r * r), r3 = r * r * r;
    S G = (S)(1), ql = (S)(1), v_met = (S)(0), v_r = (S)(0);
    for (int l = 0; l <= deg; ++l) {
        if (l > 0) {
            ql *= q;
            G *= ql;
        }
        const S a = lookup_w(LOBE_BANDS, i * GGX_NBANDS + l), b = lookup_w(LOBE_BANDS, (i + 1) * GGX_NBANDS + l);
        v_met += v_gl[l] * (a + (b - a) * t - G);
        v_r += v_gl[l] * (-((REAL)1 - met) * G * (REAL)(2 * l * (l + 1)) * r3 + met * (b - a) * inside);
    }
    v_m[3] += v_r;
    v_m[4] += v_met;
}

/* env_scales, lobe 1 (the SH environment): s_d = ao (1 - m) alb / pi, s_g = ao Fe,
 * Fe = (1 - m) [0.04 + 0.96 (1 - r) f5] + m (alb A + B) */
inline void env_scales1_w(const V3 N, const V3 V, const S* m, V3* s_d, V3* s_g)
{
    const S r = m[3], met = m[4], ao = m[5];
    const S nv = fmax(v3_dot(N, V), (REAL)0);
    S A, B, dAr, dBr, dAn, dBn;
    env_dfg_w(r, nv, &A, &B, &dAr, &dBr, &dAn, &dBn);
    const S Fd = (REAL)0.04 + (REAL)0.96 * ((REAL)1 - r) * pow5w((REAL)1 - nv);
    const S om = (REAL)1 - met, fd = om * Fd, aom = ao * om;
    *s_d = v3(aom * m[0] / R_PI, aom * m[1] / R_PI, aom * m[2] / R_PI);
    *s_g = v3(ao * (fd + met * (m[0] * A + B)), ao * (fd + met * (m[1] * A + B)), ao * (fd + met * (m[2] * A + B)));
}

inline void env_scales1_vjp_w(const V3 N, const V3 V, const S* m, const V3 v_sd, const V3 v_sg, V3* v_N, V3* v_V,
                              S* v_m)
{
    const V3 alb = v3(m[0], m[1], m[2]);
    const S r = m[3], met = m[4], ao = m[5];
    const S nvr = v3_dot(N, V);
    const S nv = fmax(nvr, (REAL)0);
    const S omv = (REAL)1 - nv;
    const S f5 = pow5w(omv);
    S A, B, dAr, dBr, dAn, dBn;
    env_dfg_w(r, nv, &A, &B, &dAr, &dBr, &dAn, &dBn);
    const S Fd = (REAL)0.04 + (REAL)0.96 * ((REAL)1 - r) * f5;
    const S om = (REAL)1 - met;
    const V3 Fm = v3(alb.x * A + B, alb.y * A + B, alb.z * A + B);
    const V3 Fe = v3(om * Fd + met * Fm.x, om * Fd + met * Fm.y, om * Fd + met * Fm.z);
    v_m[5] += v3_dot(v_sd, v3_scale(alb, om / R_PI)) + v3_dot(v_sg, Fe);
    const V3 v_Fe = v3_scale(v_sg, ao);
    S v_met = -ao * v3_dot(v_sd, alb) / R_PI;
    V3 v_alb = v3_scale(v_sd, ao * om / R_PI);
    const S sFe = v_Fe.x + v_Fe.y + v_Fe.z;
    v_met += v3_dot(v_Fe, Fm) - Fd * sFe;
    const S v_Fd = om * sFe;
    v_alb = v3_add(v_alb, v3_scale(v_Fe, met * A));
    const S v_A = met * v3_dot(v_Fe, alb), v_B = met * sFe;
    const S v_r = -v_Fd * (REAL)0.96 * f5 + v_A * dAr + v_B * dBr;
    const S v_nv = WHERE(nvr > (REAL)0,
                         -(REAL)5 * omv * omv * omv * omv * v_Fd * (REAL)0.96 * ((REAL)1 - r) + v_A * dAn + v_B * dBn,
                         (S)(0));
    *v_N = v3_add(*v_N, v3_scale(V, v_nv));
    *v_V = v3_add(*v_V, v3_scale(N, v_nv));
    v_m[0] += v_alb.x;
    v_m[1] += v_alb.y;
    v_m[2] += v_alb.z;
    v_m[3] += v_r;
    v_m[4] += v_met;
}

/* env_eval (no occlusion): Yn = Y(N), Yr = Y(R), gl; E = sum A_l Yn_k c_k, Gl = sum g_l Yr_k c_k */
inline void env_eval_w(const V3 N, const V3 V, const S* m, const int deg, __global const REAL* c, const int stride,
                       S* Yn, S* Yr, S* gl, V3* E, V3* Gl)
{
    const S nv2 = (REAL)2 * v3_dot(N, V);
    const V3 R = v3_sub(v3_scale(N, nv2), V);
    sh_eval_w(deg, N, Yn);
    sh_eval_w(deg, R, Yr);
    env_bands_w(m, deg, gl);
    V3 e = v3((S)(0), (S)(0), (S)(0)), g = e;
    for (int l = 0; l <= deg; ++l)
        for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
            const S wn = SH_BAND_A[l] * Yn[k], wr = gl[l] * Yr[k];
            const REAL c0 = c[k], c1 = c[stride + k], c2 = c[2 * stride + k];
            e = v3(e.x + wn * c0, e.y + wn * c1, e.z + wn * c2);
            g = v3(g.x + wr * c0, g.y + wr * c1, g.z + wr * c2);
        }
    *E = e;
    *Gl = g;
}

inline V3 env_term_w(const V3 N, const V3 V, const S* m, const int deg, __global const REAL* c, const int stride)
{
    S Yn[ENV_NK], Yr[ENV_NK], gl[ENV_MAX_DEG + 1];
    V3 E, Gl, s_d, s_g;
    env_eval_w(N, V, m, deg, c, stride, Yn, Yr, gl, &E, &Gl);
    env_scales1_w(N, V, m, &s_d, &s_g);
    return v3_add(v3_mul(s_d, E), v3_mul(s_g, Gl));
}

/* env_term_vjp: leaves Yn, Yr, gl and gE = v_out s_d, gG = v_out s_g for the coefficient gradients
 * v_c[ch, k] = gE_ch A_l Yn_k + gG_ch g_l Yr_k (formed by the caller) */
inline void env_term_vjp_w(const V3 N, const V3 V, const S* m, const int deg, __global const REAL* c, const int stride,
                           const V3 v_out, S* Yn, S* Yr, S* gl, V3* gE, V3* gG, V3* v_N, V3* v_V, S* v_m)
{
    V3 E, Gl, s_d, s_g;
    env_eval_w(N, V, m, deg, c, stride, Yn, Yr, gl, &E, &Gl);
    env_scales1_w(N, V, m, &s_d, &s_g);
    *gE = v3_mul(v_out, s_d);
    *gG = v3_mul(v_out, s_g);
    S v_Yn[ENV_NK], v_Yr[ENV_NK], v_gl[ENV_MAX_DEG + 1];
    for (int k = 0; k < ENV_NK; ++k) v_Yn[k] = v_Yr[k] = (S)(0);
    for (int l = 0; l <= deg; ++l) {
        v_gl[l] = (S)(0);
        for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
            const REAL c0 = c[k], c1 = c[stride + k], c2 = c[2 * stride + k];
            const S dE = gE->x * c0 + gE->y * c1 + gE->z * c2, dG = gG->x * c0 + gG->y * c1 + gG->z * c2;
            v_Yn[k] = SH_BAND_A[l] * dE;
            v_Yr[k] = gl[l] * dG;
            v_gl[l] += Yr[k] * dG;
        }
    }
    env_bands_vjp_w(m, deg, v_gl, v_m);
    const S nvr = v3_dot(N, V);
    const V3 R = v3_sub(v3_scale(N, (REAL)2 * nvr), V);
    *v_N = v3_add(*v_N, sh_eval_vjp_w(deg, N, v_Yn));
    const V3 v_R = sh_eval_vjp_w(deg, R, v_Yr);
    const S rn = v3_dot(v_R, N);
    *v_N = v3_add(*v_N, v3_add(v3_scale(v_R, (REAL)2 * nvr), v3_scale(V, (REAL)2 * rn)));
    *v_V = v3_add(*v_V, v3_sub(v3_scale(N, (REAL)2 * rn), v_R));
    env_scales1_vjp_w(N, V, m, v3_mul(v_out, E), v3_mul(v_out, Gl), v_N, v_V, v_m);
}

/* ---- the packed rows: 8 rows p0 .. p0 + 7 (a row past P repeats row P - 1) ------------------------------------ */
#define ROWP(k) (fa + (size_t)min(p0 + (k), P - 1) * POS_LD)
#define LANES(c) ((S)(r0[(c)], r1[(c)], r2[(c)], r3[(c)], r4[(c)], r5[(c)], r6[(c)], r7[(c)]))
#define ROWS_DECL                                                                                    \
    __global const REAL *r0 = ROWP(0), *r1 = ROWP(1), *r2 = ROWP(2), *r3 = ROWP(3), *r4 = ROWP(4), \
                        *r5 = ROWP(5), *r6 = ROWP(6), *r7 = ROWP(7)
#if POS_LD != NRM_LD || POS_LD != MAT_LD
#error "shade_lanes.cl reads the packed rows: POS_LD, NRM_LD and MAT_LD must be equal"
#endif
#if defined(VL_OFF) && VL_LD != POS_LD
#error "shade_lanes.cl reads the packed rows: VL_LD must be POS_LD"
#endif

/* the fragment's x, V, N (flipped towards the camera when two-sided) and material, as shade.cl's load_fragment */
#define LOAD_FRAGMENT                                                                                       \
    ROWS_DECL;                                                                                              \
    const V3 x = v3(LANES(POS_OFF), LANES(POS_OFF + 1), LANES(POS_OFF + 2));                                \
    const V3 nraw = v3(LANES(NRM_OFF), LANES(NRM_OFF + 1), LANES(NRM_OFF + 2));                             \
    const V3 V = safe_normalize_w(v3_sub(v3((S)(cx), (S)(cy), (S)(cz)), x));                                \
    V3 N = safe_normalize_w(nraw);                                                                          \
    const S sgn = WHERE(v3_dot(N, V) < (REAL)0, (S)(two_sided ? -1 : 1), (S)(1));                           \
    N = v3_scale(N, sgn);                                                                                   \
    S m[6];                                                                                                 \
    for (int j = 0; j < 6; ++j) m[j] = LANES(MAT_OFF + j);

/* a shadow caster's transmittance column jv (1 without HAS_VIS) */
#ifdef HAS_VIS
#define TV(jv) LANES(VIS_OFF + (jv))
#else
#define TV(jv) ((S)(1))
#endif

__kernel void shade_lanes_fwd(__global const REAL* fa,   // [P, LD] packed fragment attributes
                              const int P,
                              const REAL cx, const REAL cy, const REAL cz,
                              const int two_sided,
                              __global const REAL* lt_f,   // [NUM_PARAMS]
#ifdef ALPHA_COPY
                              __global REAL* alpha,        // [P]
#endif
                              __global REAL* rgb)          // [P, 3]
{
    const int p0 = W * get_global_id(0);
    if (p0 >= P) return;
    LOAD_FRAGMENT
    V3 out = v3((S)(0), (S)(0), (S)(0));
    int jv = 0;
#pragma unroll
    for (int li = 0; li < NUM_LIGHTS; ++li) {
        const int type = LIGHT_ROWS[4 * li], off = LIGHT_ROWS[4 * li + 1], a = LIGHT_ROWS[4 * li + 2],
                  b = LIGHT_ROWS[4 * li + 3];
        __global const REAL* q = lt_f + off;
        if (type == LIGHT_SH_ENV) {
            out = v3_add(out, env_term_w(N, V, m, a, q, b));
#ifdef VL_OFF
        } else if (type == LIGHT_BOUNCE) {
            out = v3_add(out, ct_ambient(N, V, v3(LANES(VL_OFF), LANES(VL_OFF + 1), LANES(VL_OFF + 2)), m));
#endif
        } else if (type == LIGHT_AMBIENT) {
            out = v3_add(out, ct_ambient(N, V, v3((S)(q[0]), (S)(q[1]), (S)(q[2])), m));
        } else if (type == LIGHT_DIRECTIONAL) {
            const S tv = TV(jv);
            ++jv;
            const V3 L = safe_normalize_w(v3((S)(q[0]), (S)(q[1]), (S)(q[2])));
            out = v3_add(out, ct_direct(N, V, L, v3(q[3] * tv, q[4] * tv, q[5] * tv), m));
        } else if (type == LIGHT_POINT) {
            const S tv = TV(jv);
            ++jv;
            const V3 w = v3_sub(v3((S)(q[0]), (S)(q[1]), (S)(q[2])), x);
            const S sc = a ? (REAL)1 / fmax(v3_dot(w, w), POINT_D2_EPS) : (S)(1);
            const S st = sc * tv;
            out = v3_add(out, ct_direct(N, V, safe_normalize_w(w), v3(q[3] * st, q[4] * st, q[5] * st), m));
        }
    }
    REAL o[3][W];
    vstore8(out.x, 0, o[0]);
    vstore8(out.y, 0, o[1]);
    vstore8(out.z, 0, o[2]);
    const int n = min(W, P - p0);
    for (int k = 0; k < n; ++k) {
        const int p = p0 + k;
        rgb[3 * p] = o[0][k];
        rgb[3 * p + 1] = o[1][k];
        rgb[3 * p + 2] = o[2][k];
#ifdef ALPHA_COPY
        alpha[p] = fa[(size_t)p * ALPHA_LD + ALPHA_OFF];
#endif
    }
}

inline REAL lane_sum(const S v)
{
    return ((v.s0 + v.s1) + (v.s2 + v.s3)) + ((v.s4 + v.s5) + (v.s6 + v.s7));
}

__kernel void shade_lanes_bwd(__global const REAL* fa,      // [P, LD] packed fragment attributes
                              const int P,
                              const REAL cx, const REAL cy, const REAL cz,
                              const int two_sided,
                              __global const REAL* lt_f,      // [NUM_PARAMS]
                              __global const REAL* v_rgb,     // [P, 3]
#ifdef ALPHA_COPY
                              __global const REAL* v_alpha,   // [P]
#endif
                              __global REAL* v_fa,            // [P, LD] the adjoint's rows (the blocks written)
                              __global REAL* v_light_part,    // [num_groups, NUM_PARAMS]
                              __local REAL* scratch)          // [local_size * RED_W]
{
    const int p0 = W * get_global_id(0);
    REAL gsum[NUM_PARAMS];
    for (int j = 0; j < NUM_PARAMS; ++j) gsum[j] = (REAL)0;
    if (p0 < P) {
        LOAD_FRAGMENT
        /* the cotangent, zero on the lanes past P (their row repeats P - 1) */
        REAL vo[3][W];
        for (int k = 0; k < W; ++k) {
            const int p = p0 + k < P ? p0 + k : -1;
            vo[0][k] = p >= 0 ? v_rgb[3 * p] : (REAL)0;
            vo[1][k] = p >= 0 ? v_rgb[3 * p + 1] : (REAL)0;
            vo[2][k] = p >= 0 ? v_rgb[3 * p + 2] : (REAL)0;
        }
        const V3 v_o = v3(vload8(0, vo[0]), vload8(0, vo[1]), vload8(0, vo[2]));
        const S zero = (S)(0);
        /* the lanes with a cotangent: the others (past P, or behind the compositing's cut-off) get exact zeros, as
         * shade.cl's skip gives them, whatever their attributes hold (a non-finite one must not reach the sums) */
#define KEEP(v) WHERE(live, (v), zero)
        const TRIPLET_CAT(TRIPLET_CAT(MASK_OF_, REAL), _8) live = (v_o.x != (REAL)0) | (v_o.y != (REAL)0) | (v_o.z != (REAL)0);
        V3 v_x = v3(zero, zero, zero), v_V = v_x, v_N = v_x;
        S v_m[6];
        for (int j = 0; j < 6; ++j) v_m[j] = zero;
        S v_tv[NUM_LIGHTS];
        V3 v_rad = v3(zero, zero, zero);  /* the bounce's per-fragment radiance (the VL block's first three columns) */
        int jv = 0;
#pragma unroll
        for (int li = 0; li < NUM_LIGHTS; ++li) {
            const int type = LIGHT_ROWS[4 * li], off = LIGHT_ROWS[4 * li + 1], a = LIGHT_ROWS[4 * li + 2],
                      b = LIGHT_ROWS[4 * li + 3];
            __global const REAL* q = lt_f + off;
            V3 v_L = v3(zero, zero, zero), v_Li = v_L;
            if (type == LIGHT_SH_ENV) {
                /* v_c[ch, k] = gE_ch A_l Yn_k + gG_ch g_l Yr_k, the active bands only */
                S Yn[ENV_NK], Yr[ENV_NK], gl[ENV_MAX_DEG + 1];
                V3 gE, gG;
                env_term_vjp_w(N, V, m, a, q, b, v_o, Yn, Yr, gl, &gE, &gG, &v_N, &v_V, v_m);
                for (int l = 0; l <= a; ++l)
                    for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
                        const S yn = SH_BAND_A[l] * Yn[k], yr = gl[l] * Yr[k];
                        gsum[off + k] += lane_sum(KEEP(gE.x * yn + gG.x * yr));
                        gsum[off + b + k] += lane_sum(KEEP(gE.y * yn + gG.y * yr));
                        gsum[off + 2 * b + k] += lane_sum(KEEP(gE.z * yn + gG.z * yr));
                    }
#ifdef VL_OFF
            } else if (type == LIGHT_BOUNCE) {
                ct_ambient_vjp(N, V, v3(LANES(VL_OFF), LANES(VL_OFF + 1), LANES(VL_OFF + 2)), m, v_o, &v_N, &v_V,
                               &v_rad, v_m);
#endif
            } else if (type == LIGHT_AMBIENT) {
                ct_ambient_vjp(N, V, v3((S)(q[0]), (S)(q[1]), (S)(q[2])), m, v_o, &v_N, &v_V, &v_Li, v_m);
                gsum[off] += lane_sum(KEEP(v_Li.x));
                gsum[off + 1] += lane_sum(KEEP(v_Li.y));
                gsum[off + 2] += lane_sum(KEEP(v_Li.z));
            } else if (type == LIGHT_DIRECTIONAL) {
                const S tv = TV(jv);
                const V3 d = v3((S)(q[0]), (S)(q[1]), (S)(q[2]));
                ct_direct_vjp(N, V, safe_normalize_w(d), v3(q[3] * tv, q[4] * tv, q[5] * tv), m, v_o, &v_N, &v_V,
                              &v_L, &v_Li, v_m);
                v_tv[jv++] = v_Li.x * q[3] + v_Li.y * q[4] + v_Li.z * q[5];
                v_Li = v3_scale(v_Li, tv);
                const V3 v_d = safe_normalize_vjp_w(d, v_L);
                gsum[off] += lane_sum(KEEP(v_d.x));
                gsum[off + 1] += lane_sum(KEEP(v_d.y));
                gsum[off + 2] += lane_sum(KEEP(v_d.z));
                gsum[off + 3] += lane_sum(KEEP(v_Li.x));
                gsum[off + 4] += lane_sum(KEEP(v_Li.y));
                gsum[off + 5] += lane_sum(KEEP(v_Li.z));
            } else if (type == LIGHT_POINT) {
                const S tv = TV(jv);
                const V3 w = v3_sub(v3((S)(q[0]), (S)(q[1]), (S)(q[2])), x);
                const S d2 = v3_dot(w, w);
                const S sc = a ? (REAL)1 / fmax(d2, POINT_D2_EPS) : (S)(1);
                const S st = sc * tv;
                ct_direct_vjp(N, V, safe_normalize_w(w), v3(q[3] * st, q[4] * st, q[5] * st), m, v_o, &v_N, &v_V,
                              &v_L, &v_Li, v_m);
                v_tv[jv++] = (v_Li.x * q[3] + v_Li.y * q[4] + v_Li.z * q[5]) * sc;
                v_Li = v3_scale(v_Li, tv);
                V3 v_w = safe_normalize_vjp_w(w, v_L);
                if (a) {
                    const S k2 = WHERE(d2 > POINT_D2_EPS,
                                       (REAL)2 * (q[3] * v_Li.x + q[4] * v_Li.y + q[5] * v_Li.z) * sc * sc, zero);
                    v_w = v3_sub(v_w, v3_scale(w, k2));
                }
                v_x = v3_sub(v_x, v_w);
                gsum[off] += lane_sum(KEEP(v_w.x));
                gsum[off + 1] += lane_sum(KEEP(v_w.y));
                gsum[off + 2] += lane_sum(KEEP(v_w.z));
                gsum[off + 3] += lane_sum(KEEP(v_Li.x * sc));
                gsum[off + 4] += lane_sum(KEEP(v_Li.y * sc));
                gsum[off + 5] += lane_sum(KEEP(v_Li.z * sc));
            }
        }
        /* the view direction and the normal's own normalisation (with the two-sided flip) */
        const V3 v_c = safe_normalize_vjp_w(v3_sub(v3((S)(cx), (S)(cy), (S)(cz)), x), v_V);
        v_x = v3_sub(v_x, v_c);
        const V3 v_n = safe_normalize_vjp_w(nraw, v3_scale(v_N, sgn));
        /* the rows: every written column of each of the (up to) eight fragments */
#ifdef HAS_VIS
#define NCOL (12 + NUM_LIGHTS)
#else
#define NCOL 12
#endif
        REAL o[NCOL][W];
        vstore8(KEEP(v_x.x), 0, o[0]);
        vstore8(KEEP(v_x.y), 0, o[1]);
        vstore8(KEEP(v_x.z), 0, o[2]);
        vstore8(KEEP(v_n.x), 0, o[3]);
        vstore8(KEEP(v_n.y), 0, o[4]);
        vstore8(KEEP(v_n.z), 0, o[5]);
        for (int j = 0; j < 6; ++j) vstore8(KEEP(v_m[j]), 0, o[6 + j]);
#ifdef HAS_VIS
        for (int j = 0; j < jv; ++j) vstore8(KEEP(v_tv[j]), 0, o[12 + j]);
#endif
#ifdef VL_OFF
        REAL orad[3][W];
        vstore8(KEEP(v_rad.x), 0, orad[0]);
        vstore8(KEEP(v_rad.y), 0, orad[1]);
        vstore8(KEEP(v_rad.z), 0, orad[2]);
#endif
#undef KEEP
        const int n = min(W, P - p0);
        for (int k = 0; k < n; ++k) {
            __global REAL* row = v_fa + (size_t)(p0 + k) * POS_LD;
            for (int j = 0; j < 3; ++j) row[POS_OFF + j] = o[j][k];
            for (int j = 0; j < 3; ++j) row[NRM_OFF + j] = o[3 + j][k];
            for (int j = 0; j < 6; ++j) row[MAT_OFF + j] = o[6 + j][k];
#ifdef HAS_VIS
            for (int j = 0; j < jv; ++j) row[VIS_OFF + j] = o[12 + j][k];
#endif
#ifdef VL_OFF
            for (int j = 0; j < 3; ++j) row[VL_OFF + j] = orad[j][k];
            for (int j = 3; j < 6; ++j) row[VL_OFF + j] = (REAL)0;  /* the bounce has no direction */
#endif
#ifdef ALPHA_COPY
            row[ALPHA_OFF] = v_alpha[p0 + k];
#endif
        }
    }
    /* the light parameters' sums over the work-group, RED_W columns at a time, in a fixed order */
    __global REAL* part = v_light_part + (size_t)get_group_id(0) * NUM_PARAMS;
    const int lid = get_local_id(0), lsz = get_local_size(0);
    for (int c0 = 0; c0 < NUM_PARAMS; c0 += RED_W) {
        for (int j = 0; j < RED_W; ++j) scratch[lid * RED_W + j] = c0 + j < NUM_PARAMS ? gsum[c0 + j] : (REAL)0;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid < RED_W && c0 + lid < NUM_PARAMS) {
            REAL s = (REAL)0;
            for (int r = 0; r < lsz; ++r) s += scratch[r * RED_W + lid];
            part[c0 + lid] = s;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}
