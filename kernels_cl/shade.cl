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
 *   SH env:      v_c[ch, k] = gE_ch A_l Yn_k + gG_ch g_l Yr_k  (see env_term_vjp)
 *   v_x -= safe_normalize_vjp(cam - x, v_V),  v_n = safe_normalize_vjp(n, s v_N)
 * Optional inputs are compiled in or out (defined or not; an absent one is not a parameter):
 *   HAS_VLIGHT: vlight [P, 6] and its adjoint v_vlight (a vertex-SH light).
 * Ray-traced terms (ops/trace.py; all off in the default raster path):
 *   HAS_VIS:  vis [P, NV] transmittance towards the j-th point/directional light (in light order)
 *             multiplies that light's intensity: brdf_direct(N, V, L, T I sc, m);
 *             v_T = v_Li_eff . (I sc), and the light's own adjoints see v_Li = T v_Li_eff.
 *   HAS_REFL: refl [P, 3] radiance arriving along the mirror direction R = 2 (N.V) N - V (the
 *             reflection bounce) adds s_g * refl, s_g the glossy weight of env_scales (the same
 *             weight the SH environment gives its glossy radiance): v_refl = s_g v_rgb,
 *             v_s_g = v_rgb refl -> env_scales_vjp -> v_N, v_V, v_m.
 *   HAS_EYE:  eye [P, 3] per-fragment viewpoint replacing cam (shading a bounce hit as seen from
 *             the reflecting point); v_eye = safe_normalize_vjp(eye - x, v_V).
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

/* Shared per-fragment set-up: x, V, N (and the flip sign) and the material channels. */
inline int load_fragment(const int p, __global const REAL* pos, __global const REAL* nrm, __global const REAL* mat,
                         const REAL3 cam, const int two_sided, REAL3* x, REAL3* V, REAL3* N, REAL* sgn, REAL* m)
{
    *x = LOAD3(pos, p);
    *V = safe_normalize(cam - *x);
    *N = safe_normalize(LOAD3(nrm, p));
    *sgn = (two_sided && dot(*N, *V) < (REAL)0) ? -(REAL)1 : (REAL)1;
    *N *= *sgn;
    for (int j = 0; j < NMAT; ++j) m[j] = mat[(size_t)p * NMAT + j];
    return 1;
}

__kernel void shade_fwd(__global const REAL* pos,     // [P, 3]
                        __global const REAL* nrm,     // [P, 3]
                        __global const REAL* mat,     // [P, NMAT]
#ifdef HAS_VLIGHT
                        __global const REAL* vlight,  // [P, 6]
#endif
                        __global const int* face_id,  // [P]
                        const int P,
                        const REAL cx, const REAL cy, const REAL cz,
                        const int two_sided,
                        __global const REAL* lt_f,    // [T]
#ifdef HAS_VIS
                        const int NV,                 // shadowed lights (columns of vis)
                        __global const REAL* vis,     // [P, NV]
#endif
#ifdef HAS_REFL
                        __global const REAL* refl,    // [P, 3]
#endif
#ifdef HAS_EYE
                        __global const REAL* eye,     // [P, 3]
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
    if (face_id[p] < 0) {
        STORE3((REAL3)(0), rgb, p);
        return;
    }
    REAL3 x, V, N;
    REAL sgn, m[NMAT];
    const REAL3 cam = has_eye ? LOAD3(eye, p) : (REAL3)(cx, cy, cz);
    load_fragment(p, pos, nrm, mat, cam, two_sided, &x, &V, &N, &sgn, m);
    REAL3 out = (REAL3)(0);
    int jv = 0;
#pragma unroll
    for (int li = 0; li < NUM_LIGHTS; ++li) {
        const int type = LIGHT_ROWS[4 * li], off = LIGHT_ROWS[4 * li + 1], a = LIGHT_ROWS[4 * li + 2],
                  b = LIGHT_ROWS[4 * li + 3];
        __global const REAL* q = lt_f + off;
        const int shadowed = light_casts_shadows(type);
        const REAL tv = (has_vis && shadowed) ? vis[p * NV + jv] : (REAL)1;
        jv += shadowed;
        REAL3 Lw, Li;
        const int term = light_incident(type, a, q, x, vlight, p, tv, &Lw, &Li);
        if (term == LIGHT_TERM_DIRECT) out += brdf_direct(N, V, Lw, Li, m);
        else if (term == LIGHT_TERM_AMBIENT) out += ambient_term(N, V, Li, m);
        else if (term == LIGHT_TERM_SH_ENV) out += env_term(N, V, m, a, q, b);
    }
    if (has_refl) {
        REAL3 s_d, s_g;
        env_scales(N, V, m, &s_d, &s_g);
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
                        __global const int* face_id,    // [P]
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
                        __global const REAL* vis,       // [P, NV]
                        __global REAL* v_vis,           // [P, NV]
#endif
#ifdef HAS_REFL
                        __global const REAL* refl,      // [P, 3]
                        __global REAL* v_refl,          // [P, 3]
#endif
#ifdef HAS_EYE
                        __global const REAL* eye,       // [P, 3]
                        __global REAL* v_eye,           // [P, 3]
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
    const int valid = p < P && face_id[p] >= 0;
    const REAL3 cam = (has_eye && p < P) ? LOAD3(eye, p) : (REAL3)(cx, cy, cz);
    int jv = 0;
    if (has_vis && p < P)
        for (int j = 0; j < NV; ++j) v_vis[p * NV + j] = (REAL)0;
    REAL3 x = (REAL3)(0), V = (REAL3)(0), N = (REAL3)(0), v_o = (REAL3)(0);
    REAL sgn = (REAL)1, m[NMAT], v_m[NMAT];
    for (int j = 0; j < NMAT; ++j) m[j] = v_m[j] = (REAL)0;
    if (valid) {
        load_fragment(p, pos, nrm, mat, cam, two_sided, &x, &V, &N, &sgn, m);
        v_o = LOAD3(v_rgb, p);
    }
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
            REAL Yn[ENV_NK], Yr[ENV_NK], gl[ENV_MAX_DEG + 1];
            REAL3 gE = (REAL3)(0), gG = (REAL3)(0);
            for (int k = 0; k < ENV_NK; ++k) Yn[k] = Yr[k] = (REAL)0;
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
                env_term_vjp(Ne, Ve, me, a, q, b, v_o, Yn, Yr, gl, &gE, &gG, &v_N, &v_V, v_m);
            }
            /* coefficient j = ch * nk + k of the active bands, RED_W at a time */
            for (int j0 = 0; j0 < 3 * nk; j0 += RED_W) {
                REAL g[RED_W];
                for (int jj = 0; jj < RED_W; ++jj) {
                    const int j = j0 + jj, ch = j / nk, k = j - ch * nk;
                    REAL val = (REAL)0;
                    if (j < 3 * nk) {
                        const int l = (int)floor(sqrt((REAL)k + (REAL)0.5));
                        const REAL ge = ch == 0 ? gE.x : (ch == 1 ? gE.y : gE.z);
                        const REAL gg = ch == 0 ? gG.x : (ch == 1 ? gG.y : gG.z);
                        val = ge * SH_BAND_A[l] * Yn[k] + gg * gl[l] * Yr[k];
                    }
                    g[jj] = val;
                }
                /* write into the [3, stride] layout of this light */
                const int lid = get_local_id(0), lsz = get_local_size(0);
                for (int jj = 0; jj < RED_W; ++jj) scratch[lid * RED_W + jj] = g[jj];
                barrier(CLK_LOCAL_MEM_FENCE);
                if (lid < RED_W && j0 + lid < 3 * nk) {
                    REAL s = (REAL)0;
                    for (int r = 0; r < lsz; ++r) s += scratch[r * RED_W + lid];
                    const int j = j0 + lid, ch = j / nk;
                    part[off + ch * b + (j - ch * nk)] = s;
                }
                barrier(CLK_LOCAL_MEM_FENCE);
            }
            continue;
        }
        REAL g[RED_W];
        for (int j = 0; j < RED_W; ++j) g[j] = (REAL)0;
        if (valid) {
            REAL3 v_L = (REAL3)(0), v_Li = (REAL3)(0), Lw, Li;
            const REAL tv = (has_vis && shadowed) ? vis[p * NV + jv] : (REAL)1;
            const int term = light_incident(type, a, q, x, vlight, p, tv, &Lw, &Li);
            if (term == LIGHT_TERM_DIRECT)
                brdf_direct_vjp(N, V, Lw, Li, m, v_o, &v_N, &v_V, &v_L, &v_Li, v_m);
            else if (term == LIGHT_TERM_AMBIENT)
                ambient_term_vjp(N, V, Li, m, v_o, &v_N, &v_V, &v_Li, v_m);
            REAL v_tv = (REAL)0;
            light_incident_vjp(type, a, q, x, vlight, p, tv, has_vis, v_L, v_Li, g, &v_x, &v_rad, &v_wi, &v_tv);
            if (has_vis && shadowed) v_vis[p * NV + jv] = v_tv;
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
            env_scales(Nr, Vr, mr, &s_d, &s_g);
            v_r = s_g * v_o;
            env_scales_vjp(Nr, Vr, mr, (REAL3)(0), v_o * LOAD3(refl, p), (REAL)0, &v_N, &v_V, v_m);
        }
        STORE3(v_r, v_refl, p);
    }

    if (p < P) {
        if (valid) {
            const REAL3 v_c = safe_normalize_vjp(cam - x, v_V);
            v_x -= v_c;
            if (has_eye) STORE3(v_c, v_eye, p);
            const REAL3 v_n = safe_normalize_vjp(LOAD3(nrm, p), sgn * v_N);
            STORE3(v_x, v_pos, p);
            STORE3(v_n, v_nrm, p);
        } else {
            STORE3((REAL3)(0), v_pos, p);
            STORE3((REAL3)(0), v_nrm, p);
            if (has_eye) STORE3((REAL3)(0), v_eye, p);
        }
        for (int j = 0; j < NMAT; ++j) v_mat[(size_t)p * NMAT + j] = v_m[j];
        if (has_vlight) {
            STORE3(v_rad, v_vlight, 2 * p);
            STORE3(v_wi, v_vlight, 2 * p + 1);
        }
    }
}
