/* vertex_sh.cl — the per-vertex SH light of the Triplet method, and the raw SH basis (for tests).
 *
 * Forward, per vertex i (coefficients c [N, 6, NK], NK = (VSH_MAX_DEG+1)^2, active degree
 * deg <= VSH_MAX_DEG at run time; coefficients of bands > deg are ignored):
 *   w   = cam - V_i,   d = safe_normalize(w),   Y = sh_eval(deg, d)
 *   s_j = sum_{k < (deg+1)^2} Y_k c[i, j, k]                                       j = 0..5
 *   out[i, 0:3] = relu(s_{0:3} + 0.5)           incoming radiance (rgb)
 *   out[i, 3:6] = s_{3:6}                       incoming light direction (unnormalised)
 *
 * Adjoint (v_out [N, 6]):
 *   v_s_j = v_out_j [s_j + 0.5 > 0] (j < 3),  v_s_j = v_out_j (j >= 3)
 *   v_c[i, j, k] = v_s_j Y_k  (k < (deg+1)^2, else 0)
 *   v_Y_k = sum_j v_s_j c[i, j, k];  v_d = sh_eval_vjp(deg, d, v_Y)
 *   v_V_i = -safe_normalize_vjp(w, v_d)
 *
 * sh_basis_fwd / sh_basis_bwd: Y = sh_eval(deg, d) of raw directions [n, 3] and its vjp (the SH
 * polynomial; used by the tests of common/sh.h).
 */
#include "real.h"
#include "shade_math.h"
#include "sh.h"

#ifndef VSH_MAX_DEG
#define VSH_MAX_DEG 3
#endif
#define VSH_NK ((VSH_MAX_DEG + 1) * (VSH_MAX_DEG + 1))

__kernel void vertex_sh_fwd(__global const REAL* V,     // [N, 3]
                            __global const REAL* coef,  // [N, 6, VSH_NK]
                            const REAL cx, const REAL cy, const REAL cz,
                            const int N,
                            const int deg,              // active degree <= VSH_MAX_DEG
                            __global REAL* out)         // [N, 6]
{
    const int i = get_global_id(0);
    if (i >= N) return;
    const int nk = (deg + 1) * (deg + 1);
    REAL Y[VSH_NK];
    const REAL3 d = safe_normalize((REAL3)(cx, cy, cz) - LOAD3(V, i));
    sh_eval(deg, d, Y);
    __global const REAL* c = coef + (size_t)i * 6 * VSH_NK;
    for (int j = 0; j < 6; ++j) {
        REAL s = (REAL)0;
        for (int k = 0; k < nk; ++k) s += Y[k] * c[j * VSH_NK + k];
        out[6 * i + j] = j < 3 ? fmax(s + (REAL)0.5, (REAL)0) : s;
    }
}

__kernel void vertex_sh_bwd(__global const REAL* V,      // [N, 3]
                            __global const REAL* coef,   // [N, 6, VSH_NK]
                            const REAL cx, const REAL cy, const REAL cz,
                            const int N,
                            const int deg,
                            __global const REAL* v_out,  // [N, 6]
                            __global REAL* v_coef,       // [N, 6, VSH_NK]
                            __global REAL* v_V)          // [N, 3]
{
    const int i = get_global_id(0);
    if (i >= N) return;
    const int nk = (deg + 1) * (deg + 1);
    REAL Y[VSH_NK], v_Y[VSH_NK];
    const REAL3 w = (REAL3)(cx, cy, cz) - LOAD3(V, i);
    const REAL3 d = safe_normalize(w);
    sh_eval(deg, d, Y);
    __global const REAL* c = coef + (size_t)i * 6 * VSH_NK;
    __global REAL* vc = v_coef + (size_t)i * 6 * VSH_NK;
    for (int k = 0; k < VSH_NK; ++k) v_Y[k] = (REAL)0;
    for (int j = 0; j < 6; ++j) {
        REAL v_s = v_out[6 * i + j];
        if (j < 3) {
            REAL s = (REAL)0;
            for (int k = 0; k < nk; ++k) s += Y[k] * c[j * VSH_NK + k];
            if (!(s + (REAL)0.5 > (REAL)0)) v_s = (REAL)0;
        }
        for (int k = 0; k < VSH_NK; ++k) {
            vc[j * VSH_NK + k] = k < nk ? v_s * Y[k] : (REAL)0;
            if (k < nk) v_Y[k] += v_s * c[j * VSH_NK + k];
        }
    }
    const REAL3 v_d = sh_eval_vjp(deg, d, v_Y);
    STORE3(-safe_normalize_vjp(w, v_d), v_V, i);
}

__kernel void sh_basis_fwd(__global const REAL* dirs,  // [n, 3]
                           const int n,
                           const int deg,               // <= SH_MAX_DEGREE
                           __global REAL* out)          // [n, (deg+1)^2]
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int nk = (deg + 1) * (deg + 1);
    REAL Y[SH_MAX_COEFFS];
    sh_eval(deg, LOAD3(dirs, i), Y);
    for (int k = 0; k < nk; ++k) out[(size_t)i * nk + k] = Y[k];
}

__kernel void sh_basis_bwd(__global const REAL* dirs,  // [n, 3]
                           const int n,
                           const int deg,
                           __global const REAL* v_Y,    // [n, (deg+1)^2]
                           __global REAL* v_dirs)       // [n, 3]
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int nk = (deg + 1) * (deg + 1);
    REAL vy[SH_MAX_COEFFS];
    for (int k = 0; k < nk; ++k) vy[k] = v_Y[(size_t)i * nk + k];
    STORE3(sh_eval_vjp(deg, LOAD3(dirs, i), vy), v_dirs, i);
}
