/* shade.cl — physically based shading of a flat list of P fragments under a packed light table.
 *
 * Defines: BRDF, BRDF_<NAME>, NMAT (generated from triplet_cl/materials.py), LIGHT_<NAME>,
 * LIGHT_SHADOW_MASK (generated from triplet_cl/lights.py), ENV_MAX_DEG (largest active SH degree of
 * the environment lights, sizes private arrays), RED_W (width of the light-gradient reduction),
 * NUM_LIGHTS and LIGHT_TABLE: the rows (type, offset, a, b) of the light table's ints, flattened
 * (ops/shade.py). The table's structure is compiled in (the parameters lt_f stay an argument): the
 * light loop unrolls and each light's branches fold, measured 1.2-1.4x faster on PoCL than reading
 * the rows at run time; a run compiles one variant per light set (and per SH environment degree).
 * The BRDF maths, formulas and adjoints are in common/shade_brdf.h; each light's incident radiance
 * and its adjoint in common/lights.h.
 *
 * Forward, per fragment p with face_id[p] >= 0 (else rgb = 0):
 *   V = safe_normalize(cam - x),  N = s safe_normalize(n)   (s = -1 when two_sided and N.V < 0)
 *   rgb = sum over lights of
 *     ambient     (La)                   ambient_term(N, V, La, m)
 *     directional (d, I)                 brdf_direct(N, V, safe_normalize(d), I, m)
 *     point       (q, I, falloff)        w = q - x, brdf_direct(N, V, safe_normalize(w),
 *                                               falloff ? I / max(|w|^2, 1e-6) : I, m)
 *     SH env      (c [3, stride], deg)   env_term(N, V, m, deg, c)
 *     vertex SH   (vlight[p] = rad, wi)  brdf_direct(N, V, safe_normalize(wi), rad, m)
 *
 * Adjoint (v_rgb): each light's vjp gives v_N, v_V, v_L, v_Li, v_m; then
 *   directional: v_d = safe_normalize_vjp(d, v_L), v_I = v_Li
 *   point:       v_w = safe_normalize_vjp(w, v_L) - 2 w (I . v_Li) / |w|^4 [falloff, |w|^2 > 1e-6],
 *                v_q = v_w, v_x -= v_w, v_I = v_Li / max(|w|^2, 1e-6) (or v_Li)
 *   vertex SH:   v_rad = v_Li, v_wi = safe_normalize_vjp(wi, v_L)
 *   SH env:      v_c[ch, k] = gE_ch (A_l Yn_k - U_k) + gG_ch g_l Yr_k  (see env_term_vjp; U = 0 without ENV_OCC)
 *   v_x -= safe_normalize_vjp(cam - x, v_V),  v_n = safe_normalize_vjp(n, s v_N)
 * Optional inputs are compiled in or out (defined or not; an absent one is not a parameter):
 *   HAS_VLIGHT: vlight [P, 6] and its adjoint v_vlight (a vertex-SH light).
 * Ray-traced terms (ops/trace.py; all off in the default raster path):
 *   HAS_VIS:  vis [P, NV + ENV_OCC]: NV columns of transmittance towards the j-th point/directional light (in
 *             light order), which multiplies that light's intensity: brdf_direct(N, V, L, T I sc, m);
 *             v_T = v_Li_eff . (I sc), and the light's own adjoints see v_Li = T v_Li_eff.
 *             Then ENV_OCC (a define, 0 by default) columns U_1 .. U_ENV_OCC: the environment's occlusion
 *             (SH bands 1 and up, shared by every SH environment light; env_eval in shade_brdf.h):
 *             E = sum_k c_k (A_l Y_k(N) - U_k), v_U_k = -(v_rgb s_d) . c_k summed over the environment lights
 *             (U = 0 on a back face seen through two_sided: U was traced over the front normal's hemisphere).
 *   HAS_REFL: refl [P, 3] radiance arriving along the mirror direction R = 2 (N.V) N - V (the
 *             reflection bounce) adds s_g * refl, s_g the glossy weight of env_scales (the same
 *             weight the SH environment gives its glossy radiance): v_refl = s_g v_rgb,
 *             v_s_g = v_rgb refl -> env_scales_vjp -> v_N, v_V, v_m.
 *   HAS_EYE:  eye [P, 3] per-fragment viewpoint replacing cam (shading a bounce hit as seen from
 *             the reflecting point); v_eye = safe_normalize_vjp(eye - x, v_V).
 * Layout of the per-fragment arrays (ops/shade.py): each its own [P, n] array by default, or column blocks
 * of the packed fragment attributes [P, C] (ShadeFragments: no split into per-block arrays, and the adjoint
 * written straight into the attributes' adjoint): X_LD / X_OFF (X = POS, NRM, MAT, VL, VIS) give the row
 * stride and first column of each; the same buffer is then bound to all of pos, nrm, mat (, vlight, vis)
 * and to all of their adjoints. ALL_VALID: every row is a fragment (no face_id, the packed fragments).
 *   ALPHA_COPY: the forward also copies the alpha column (ALPHA_LD / ALPHA_OFF of alpha_src) to alpha [P]
 *   and the adjoint writes v_alpha [P] into that column of the adjoint's rows (what the compositing reads
 *   and returns), so the packed attributes pass through shading in one read and one write.
 * Per-fragment adjoints are written by the fragment's own work-item. Light-parameter adjoints are
 * sums over fragments: each work-group reduces its items' values in local memory (RED_W columns at
 * a time, one column per item, fixed order: deterministic) and writes one row of v_light_part
 * [num_groups, T]; the host sums the rows. No atomics.
 */
#include "real.h"
#include "shade_math.h"
#include "sh.h"
#include "shade_brdf.h"
#include "lights.h"

#ifndef RED_W
#define RED_W 16
#endif
/* the SH environment's coefficient sums in shade_bwd: ENV_KC coefficients per channel a chunk, a local row of ENV_SW
 * per work-item (the host picks ENV_KC by the device's local memory and sizes scratch as local size x max(RED_W,
 * ENV_SW): ops/shade.py, env_chunk and scratch_width) */
#ifndef ENV_KC
#define ENV_KC (ENV_NK < 32 ? ENV_NK : 32)
#endif
#define ENV_SW (3 * ENV_KC + 6)
#if !defined(NUM_LIGHTS) || !defined(LIGHT_TABLE)
#error "shade.cl needs NUM_LIGHTS and LIGHT_TABLE (ops/shade.py: _defines)"
#endif
/* the light table's rows (type, offset, a, b), NUM_LIGHTS of them (one placeholder row without lights) */
__constant int LIGHT_ROWS[] = {LIGHT_TABLE};
/* The optional inputs a kernel was built without (HAS_* not defined): null pointers, never read
 * (every use is guarded by the matching has_* constant). */
#define ABSENT ((__global REAL*)0)
#ifdef HAS_VLIGHT
#define HAVE_VLIGHT 1
#else
#define HAVE_VLIGHT 0
#endif
#ifdef HAS_VIS
#define HAVE_VIS 1
#else
#define HAVE_VIS 0
#endif
#ifdef HAS_REFL
#define HAVE_REFL 1
#else
#define HAVE_REFL 0
#endif
#ifdef HAS_EYE
#define HAVE_EYE 1
#else
#define HAVE_EYE 0
#endif

/* Row layouts (see the header): row stride X_LD and first column X_OFF of each per-fragment array. */
#ifndef POS_LD
#define POS_LD 3
#define POS_OFF 0
#endif
#ifndef NRM_LD
#define NRM_LD 3
#define NRM_OFF 0
#endif
#ifndef MAT_LD
#define MAT_LD NMAT
#define MAT_OFF 0
#endif
#ifndef VL_LD
#define VL_LD 6
#define VL_OFF 0
#endif
#ifndef ENV_OCC
#define ENV_OCC 0
#endif
#ifndef VIS_LD
#define VIS_LD (NV + ENV_OCC)
#define VIS_OFF 0
#endif
#define ROW(a, X, p) ((a) + (size_t)(p) * X##_LD + X##_OFF)

/* The environment occlusion U [ENV_NK] of fragment p (U_0 = 0; U_k = vis[p, NV + k - 1] for 1 <= k <= ENV_OCC;
 * all 0 without vis or ENV_OCC, and on a back face seen through two_sided (sgn < 0): U was traced over the front
 * normal's hemisphere). */
inline void load_env_occ(const int p, __global const REAL* vis, const int NV, const int has_vis, const REAL sgn,
                         REAL* U)
{
    for (int k = 0; k < ENV_NK; ++k) U[k] = (REAL)0;
    if (ENV_OCC > 0 && has_vis && sgn > (REAL)0) {
        __global const REAL* r = ROW(vis, VIS, p) + NV;
        for (int k = 1; k < ENV_NK && k <= ENV_OCC; ++k) U[k] = r[k - 1];
    }
}

/* Shared per-fragment set-up: x, V, N (and the flip sign) and the material channels. */
inline int load_fragment(const int p, __global const REAL* pos, __global const REAL* nrm, __global const REAL* mat,
                         const REAL3 cam, const int two_sided, REAL3* x, REAL3* V, REAL3* N, REAL* sgn, REAL* m)
{
    *x = vload3(0, ROW(pos, POS, p));
    *V = safe_normalize(cam - *x);
    *N = safe_normalize(vload3(0, ROW(nrm, NRM, p)));
    *sgn = (two_sided && dot(*N, *V) < (REAL)0) ? -(REAL)1 : (REAL)1;
    *N *= *sgn;
    __global const REAL* mr = ROW(mat, MAT, p);
    for (int j = 0; j < NMAT; ++j) m[j] = mr[j];
    return 1;
}

__kernel void shade_fwd(__global const REAL* pos,     // [P, 3]
                        __global const REAL* nrm,     // [P, 3]
                        __global const REAL* mat,     // [P, NMAT]
#ifdef HAS_VLIGHT
                        __global const REAL* vlight,  // [P, 6]
#endif
#ifndef ALL_VALID
                        __global const int* face_id,  // [P]
#endif
                        const int P,
                        const REAL cx, const REAL cy, const REAL cz,
                        const int two_sided,
                        __global const REAL* lt_f,    // [T]
#ifdef HAS_VIS
                        const int NV,                 // shadowed lights (the first columns of vis)
                        __global const REAL* vis,     // [P, NV + ENV_OCC]
#endif
#ifdef HAS_REFL
                        __global const REAL* refl,    // [P, 3]
#endif
#ifdef HAS_EYE
                        __global const REAL* eye,     // [P, 3]
#endif
#ifdef ALPHA_COPY
                        __global const REAL* alpha_src,  // the alpha column (ALPHA_LD, ALPHA_OFF)
                        __global REAL* alpha,            // [P]
#endif
                        __global REAL* rgb)           // [P, 3]
{
#ifndef HAS_VLIGHT
    __global const REAL* vlight = ABSENT;
#endif
#ifndef HAS_VIS
    const int NV = 0;
    __global const REAL* vis = ABSENT;
#endif
#ifndef HAS_REFL
    __global const REAL* refl = ABSENT;
#endif
#ifndef HAS_EYE
    __global const REAL* eye = ABSENT;
#endif
    const int has_vis = HAVE_VIS, has_refl = HAVE_REFL, has_eye = HAVE_EYE;
    const int p = get_global_id(0);
    if (p >= P) return;
#ifdef ALPHA_COPY
    alpha[p] = *ROW(alpha_src, ALPHA, p);
#endif
#ifndef ALL_VALID
    if (face_id[p] < 0) {
        STORE3((REAL3)(0), rgb, p);
        return;
    }
#endif
    REAL3 x, V, N;
    REAL sgn, m[NMAT];
    const REAL3 cam = has_eye ? LOAD3(eye, p) : (REAL3)(cx, cy, cz);
    load_fragment(p, pos, nrm, mat, cam, two_sided, &x, &V, &N, &sgn, m);
    __global const REAL* vl = HAVE_VLIGHT ? ROW(vlight, VL, p) : ABSENT;  /* this fragment's vertex-SH row */
    REAL3 out = (REAL3)(0);
    int jv = 0;
#pragma unroll
    for (int li = 0; li < NUM_LIGHTS; ++li) {
        const int type = LIGHT_ROWS[4 * li], off = LIGHT_ROWS[4 * li + 1], a = LIGHT_ROWS[4 * li + 2],
                  b = LIGHT_ROWS[4 * li + 3];
        __global const REAL* q = lt_f + off;
        const int shadowed = light_casts_shadows(type);
        const REAL tv = (has_vis && shadowed) ? ROW(vis, VIS, p)[jv] : (REAL)1;
        jv += shadowed;
        REAL3 Lw, Li;
        const int term = light_incident(type, a, q, x, vl, tv, &Lw, &Li);
        if (term == LIGHT_TERM_DIRECT) out += brdf_direct(N, V, Lw, Li, m);
        else if (term == LIGHT_TERM_AMBIENT) out += ambient_term(N, V, Li, m);
        else if (term == LIGHT_TERM_SH_ENV) {
            REAL U[ENV_NK];
            load_env_occ(p, vis, NV, has_vis, sgn, U);
            out += env_term(N, V, m, a, q, b, U);
        }
    }
    if (has_refl) {
        REAL3 s_d, s_g;
        env_scales(N, V, m, 1, &s_d, &s_g);
        out += s_g * LOAD3(refl, p);
    }
    STORE3(out, rgb, p);
}

/* Sum g[0..n) over the work-group into out[0..n) (one column per item, fixed order). All items
 * of the group must call it (it holds barriers). */
inline void group_sum_store(const REAL* g, const int n, __local REAL* scratch, __global REAL* out)
{
    const int lid = get_local_id(0), lsz = get_local_size(0);
    for (int j = 0; j < RED_W; ++j) scratch[lid * RED_W + j] = g[j];
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid < n) {
        REAL s = (REAL)0;
        for (int r = 0; r < lsz; ++r) s += scratch[r * RED_W + lid];
        out[lid] = s;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
}

__kernel void shade_bwd(__global const REAL* pos,       // [P, 3]
                        __global const REAL* nrm,       // [P, 3]
                        __global const REAL* mat,       // [P, NMAT]
#ifdef HAS_VLIGHT
                        __global const REAL* vlight,    // [P, 6]
#endif
#ifndef ALL_VALID
                        __global const int* face_id,    // [P]
#endif
                        const int P,
                        const REAL cx, const REAL cy, const REAL cz,
                        const int two_sided,
                        __global const REAL* lt_f,      // [T]
                        const int T,
                        __global const REAL* v_rgb,     // [P, 3]
                        __global REAL* v_pos,           // [P, 3]
                        __global REAL* v_nrm,           // [P, 3]
                        __global REAL* v_mat,           // [P, NMAT]
#ifdef HAS_VLIGHT
                        __global REAL* v_vlight,        // [P, 6]
#endif
#ifdef HAS_VIS
                        const int NV,
                        __global const REAL* vis,       // [P, NV + ENV_OCC]
                        __global REAL* v_vis,           // [P, NV + ENV_OCC]
#endif
#ifdef HAS_REFL
                        __global const REAL* refl,      // [P, 3]
                        __global REAL* v_refl,          // [P, 3]
#endif
#ifdef HAS_EYE
                        __global const REAL* eye,       // [P, 3]
                        __global REAL* v_eye,           // [P, 3]
#endif
#ifdef ALPHA_COPY
                        __global const REAL* v_alpha,   // [P]
                        __global REAL* v_alpha_dst,     // its column of the adjoint's rows (ALPHA_LD, ALPHA_OFF)
#endif
                        __global REAL* v_light_part,    // [num_groups, T]
                        __local REAL* scratch)          // [local_size * RED_W]
{
#ifndef HAS_VLIGHT
    __global const REAL* vlight = ABSENT;
    __global REAL* v_vlight = ABSENT;
#endif
#ifndef HAS_VIS
    const int NV = 0;
    __global const REAL* vis = ABSENT;
    __global REAL* v_vis = ABSENT;
#endif
#ifndef HAS_REFL
    __global const REAL* refl = ABSENT;
    __global REAL* v_refl = ABSENT;
#endif
#ifndef HAS_EYE
    __global const REAL* eye = ABSENT;
    __global REAL* v_eye = ABSENT;
#endif
    const int has_vlight = HAVE_VLIGHT, has_vis = HAVE_VIS, has_refl = HAVE_REFL, has_eye = HAVE_EYE;
    const int p = get_global_id(0);
    /* a fragment whose colour cotangent is zero (behind compositing's t_min cut-off: composite_bwd writes 0 there,
     * 17-25 % of a soup's fragments) has every adjoint zero: it skips the shading's adjoint and writes the zeros */
    const REAL3 v_o = p < P ? LOAD3(v_rgb, p) : (REAL3)(0);
#ifdef ALL_VALID
    const int valid = p < P && (v_o.x != (REAL)0 || v_o.y != (REAL)0 || v_o.z != (REAL)0);
#else
    const int valid = p < P && face_id[p] >= 0 && (v_o.x != (REAL)0 || v_o.y != (REAL)0 || v_o.z != (REAL)0);
#endif
    const REAL3 cam = (has_eye && p < P) ? LOAD3(eye, p) : (REAL3)(cx, cy, cz);
    int jv = 0;
    if (has_vis && p < P)
        for (int j = 0; j < NV + ENV_OCC; ++j) ROW(v_vis, VIS, p)[j] = (REAL)0;
#ifdef ALPHA_COPY
    if (p < P) *ROW(v_alpha_dst, ALPHA, p) = v_alpha[p];
#endif
    __global const REAL* vl = (HAVE_VLIGHT && p < P) ? ROW(vlight, VL, p) : ABSENT;  /* vertex-SH row */
    REAL3 x = (REAL3)(0), V = (REAL3)(0), N = (REAL3)(0);
    REAL sgn = (REAL)1, m[NMAT], v_m[NMAT];
    for (int j = 0; j < NMAT; ++j) m[j] = v_m[j] = (REAL)0;
    if (valid) load_fragment(p, pos, nrm, mat, cam, two_sided, &x, &V, &N, &sgn, m);
    REAL3 v_x = (REAL3)(0), v_V = (REAL3)(0), v_N = (REAL3)(0), v_rad = (REAL3)(0), v_wi = (REAL3)(0);
    __global REAL* part = v_light_part + (size_t)get_group_id(0) * T;

#pragma unroll
    for (int li = 0; li < NUM_LIGHTS; ++li) {
        const int type = LIGHT_ROWS[4 * li], off = LIGHT_ROWS[4 * li + 1], a = LIGHT_ROWS[4 * li + 2],
                  b = LIGHT_ROWS[4 * li + 3];
        __global const REAL* q = lt_f + off;
        const int shadowed = light_casts_shadows(type);
        if (light_term(type) == LIGHT_TERM_SH_ENV) {
            const int nk = (a + 1) * (a + 1);
            REAL Yn[ENV_NK], Yr[ENV_NK], gl[ENV_MAX_DEG + 1], U[ENV_NK];
            REAL3 gE = (REAL3)(0), gG = (REAL3)(0);
            for (int k = 0; k < ENV_NK; ++k) Yn[k] = Yr[k] = U[k] = (REAL)0;
            for (int l = 0; l <= ENV_MAX_DEG; ++l) gl[l] = (REAL)0;
            if (valid) {
                /* Re-load the fragment here instead of using x, V, N, m: Intel's CPU OpenCL
                 * compiler (2026.22, optimised builds) keeps loop-invariant values derived from them
                 * that cross the barriers of the previous lights in a single copy per work-group, so
                 * env_term_vjp saw another work-item's V and material (wrong v_pos/v_nrm/v_mat and
                 * env coefficient gradients whenever an env light follows a reduced light). */
                REAL3 xe, Ve, Ne;
                REAL se, me[NMAT];
                load_fragment(p, pos, nrm, mat, cam, two_sided, &xe, &Ve, &Ne, &se, me);
                load_env_occ(p, vis, NV, has_vis, se, U);
                env_term_vjp(Ne, Ve, me, a, q, b, U, v_o, Yn, Yr, gl, &gE, &gG, &v_N, &v_V, v_m);
#if ENV_OCC > 0
                if (has_vis && se > (REAL)0) {  /* v_U_k = -gE . c_k, summed over the environment lights */
                    __global REAL* vu = ROW(v_vis, VIS, p) + NV;
                    for (int k = 1; k < nk && k <= ENV_OCC; ++k)
                        vu[k - 1] -= dot(gE, (REAL3)(q[k], q[b + k], q[2 * b + k]));
                }
#endif
            }
            /* the diffuse factor once per k: Yn_k <- A_l Yn_k - U_k; the band factor g_l of each k kept beside it */
            REAL gk[ENV_NK];
            for (int l = 0; l <= a; ++l)
                for (int k = l * l; k < (l + 1) * (l + 1); ++k) {
                    Yn[k] = SH_BAND_A[l] * Yn[k] - U[k];
                    gk[k] = gl[l];
                }
            /* v_c[ch, k] = sum over the work-group of gE_ch Yn_k + gG_ch g_l Yr_k: ENV_KC values of k at a time
             * through local memory (a row of ENV_SW per work-item: gE, gG, Yn, g, Yr), then each work-item sums its
             * coefficients of the chunk over the rows, in the row order and with the products of the former one
             * group sum per RED_W coefficients (the same sums bit for bit); two barriers per chunk (three chunks at
             * degree 8) where that took 32 */
            const int lid = get_local_id(0), lsz = get_local_size(0);
            for (int k0 = 0; k0 < nk; k0 += ENV_KC) {
                __local REAL* row = scratch + lid * ENV_SW;
                row[0] = gE.x; row[1] = gE.y; row[2] = gE.z;
                row[3] = gG.x; row[4] = gG.y; row[5] = gG.z;
                for (int kk = 0; kk < ENV_KC; ++kk) {
                    const int k = k0 + kk;
                    row[6 + kk] = k < nk ? Yn[k] : (REAL)0;
                    row[6 + ENV_KC + kk] = k < nk ? gk[k] : (REAL)0;
                    row[6 + 2 * ENV_KC + kk] = k < nk ? Yr[k] : (REAL)0;
                }
                barrier(CLK_LOCAL_MEM_FENCE);
                for (int j = lid; j < 3 * ENV_KC; j += lsz) {
                    const int ch = j / ENV_KC, kk = j - ch * ENV_KC;
                    if (k0 + kk < nk) {
                        REAL s = (REAL)0;
                        for (int r = 0; r < lsz; ++r) {
                            __local const REAL* w = scratch + r * ENV_SW;
                            const REAL val = w[ch] * w[6 + kk] + w[3 + ch] * w[6 + ENV_KC + kk] * w[6 + 2 * ENV_KC + kk];
                            s += val;
                        }
                        part[off + ch * b + k0 + kk] = s;
                    }
                }
                barrier(CLK_LOCAL_MEM_FENCE);
            }
            continue;
        }
        REAL g[RED_W];
        for (int j = 0; j < RED_W; ++j) g[j] = (REAL)0;
        if (valid) {
            REAL3 v_L = (REAL3)(0), v_Li = (REAL3)(0), Lw, Li;
            const REAL tv = (has_vis && shadowed) ? ROW(vis, VIS, p)[jv] : (REAL)1;
            const int term = light_incident(type, a, q, x, vl, tv, &Lw, &Li);
            if (term == LIGHT_TERM_DIRECT)
                brdf_direct_vjp(N, V, Lw, Li, m, v_o, &v_N, &v_V, &v_L, &v_Li, v_m);
            else if (term == LIGHT_TERM_AMBIENT)
                ambient_term_vjp(N, V, Li, m, v_o, &v_N, &v_V, &v_Li, v_m);
            REAL v_tv = (REAL)0;
            light_incident_vjp(type, a, q, x, vl, tv, has_vis, v_L, v_Li, g, &v_x, &v_rad, &v_wi, &v_tv);
            if (has_vis && shadowed) ROW(v_vis, VIS, p)[jv] = v_tv;
        }
        jv += shadowed;
        const int n = (li + 1 < NUM_LIGHTS ? LIGHT_ROWS[4 * (li + 1) + 1] : T) - off;  /* its parameter count */
        if (n > 0) group_sum_store(g, n, scratch, part + off);
    }
    if (has_refl && p < P) {
        REAL3 v_r = (REAL3)(0);
        if (valid) {
            REAL3 xr, Vr, Nr, s_d, s_g;
            REAL sr, mr[NMAT];
            load_fragment(p, pos, nrm, mat, cam, two_sided, &xr, &Vr, &Nr, &sr, mr); /* see the env note */
            env_scales(Nr, Vr, mr, 1, &s_d, &s_g);
            v_r = s_g * v_o;
            env_scales_vjp(Nr, Vr, mr, 1, (REAL3)(0), v_o * LOAD3(refl, p), &v_N, &v_V, v_m);
        }
        STORE3(v_r, v_refl, p);
    }

    if (p < P) {
        if (valid) {
            const REAL3 v_c = safe_normalize_vjp(cam - x, v_V);
            v_x -= v_c;
            if (has_eye) STORE3(v_c, v_eye, p);
            const REAL3 v_n = safe_normalize_vjp(vload3(0, ROW(nrm, NRM, p)), sgn * v_N);
            vstore3(v_x, 0, ROW(v_pos, POS, p));
            vstore3(v_n, 0, ROW(v_nrm, NRM, p));
        } else {
            vstore3((REAL3)(0), 0, ROW(v_pos, POS, p));
            vstore3((REAL3)(0), 0, ROW(v_nrm, NRM, p));
            if (has_eye) STORE3((REAL3)(0), v_eye, p);
        }
        __global REAL* vm = ROW(v_mat, MAT, p);
        for (int j = 0; j < NMAT; ++j) vm[j] = v_m[j];
        if (has_vlight) {
            vstore3(v_rad, 0, ROW(v_vlight, VL, p));
            vstore3(v_wi, 1, ROW(v_vlight, VL, p));
        }
    }
}
