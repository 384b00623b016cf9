/* composite.cl — front-to-back alpha blending of the K fragments of each pixel.
 *
 * Per pixel, fragments i = 0..n-1 (nearest first), features f_i [C], alpha a_i = ab_i * win_i
 * (win_i = 1 without a coverage window), background bg [C]:
 *   T_0 = 1,  T_{i+1} = T_i (1 - a_i)
 *   out[c] = sum_i f_ic a_i T_i + bg_c T_n,    acc = 1 - T_n  (accumulated alpha)
 * Early termination: compositing stops after the first fragment that brings T below t_min;
 *   n_contrib = the number of fragments composited (forward and adjoint use the same n).
 * Adjoint (back to front, as 3D Gaussian Splatting, with no division by 1 - a_i):
 *   R_{n-1,c} = bg_c,  R_{i-1,c} = f_ic a_i + (1 - a_i) R_{i,c}      (what lies behind i)
 *   G_{n-1} = 1,       G_{i-1} = G_i (1 - a_i)                        (transmittance behind i)
 *   v_f_ic = v_out_c a_i T_i
 *   v_a_i  = T_i ( sum_c v_out_c (f_ic - R_ic) + v_acc G_i )
 * T_i is recomputed front to back and parked in v_alpha before the back-to-front pass.
 *   v_ab_i = v_a_i win_i,  v_win_i = v_a_i ab_i,  v_bg_c = sum_pixels v_out_c T_n (host sum)
 * One work-item per pixel; its fragments are rows frag_off[pix] + i of the packed per-fragment
 * arrays (ops/raster.py Fragments).
 */
#include "real.h"

#ifndef C_MAX
#define C_MAX 16
#endif
/* NC: the channel count compiled in (ops/composite.py: every launch; the runtime argument C is then unused), so the
 * channel loops unroll and the pixel's sums stay in registers; the same operations in the same order as the loops
 * over the runtime C (tests/test_raster.py, bit for bit). (has_win stays a runtime value: compiled in, the adjoint's
 * 1 - alpha win became one fused multiply-add, its T no longer the forward's to the bit.) */
#ifdef NC
#define CH NC
#else
#define CH C
#endif

__kernel void composite_fwd(__global const REAL* feat,      // [P, C]      
                            __global const REAL* alpha,     // [P]      
                            __global const REAL* win,       // [P]        (if has_win)
                            __global const int* frag_count, // [H, W]
                            __global const REAL* bg,        // [C]
                            const int npix, __global const int* frag_off, const int C, const int has_win,
                            const REAL t_min,
                            __global REAL* out,             // [H, W, C]
                            __global REAL* trans,           // [H, W]  T_n
                            __global int* n_contrib)        // [H, W]
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    REAL acc[C_MAX];
    for (int c = 0; c < CH; ++c) acc[c] = (REAL)0;
    REAL T = (REAL)1;
    const int cnt = frag_count[pix];
    int n = 0;
    for (int i = 0; i < cnt; ++i) {
        const int o = frag_off[pix] + i;
        const REAL a = has_win ? alpha[o] * win[o] : alpha[o];
        const REAL w = a * T;
        for (int c = 0; c < CH; ++c) acc[c] += feat[(long)o * CH + c] * w;
        T *= (REAL)1 - a;
        n = i + 1;
        if (T < t_min) break;
    }
    for (int c = 0; c < CH; ++c) out[pix * CH + c] = acc[c] + bg[c] * T;
    trans[pix] = T;
    n_contrib[pix] = n;
}

__kernel void composite_bwd(__global const REAL* feat,      // [P, C]      
                            __global const REAL* alpha,     // [P]      
                            __global const REAL* win,       // [P]      
                            __global const int* n_contrib,  // [H, W]
                            __global const int* frag_count, // [H, W]
                            __global const REAL* bg,        // [C]
                            __global const REAL* v_out,     // [H, W, C]
                            __global const REAL* v_acc,     // [H, W]  (if has_vacc)
                            const int npix, __global const int* frag_off, const int C, const int has_win, const int has_vacc,
                            __global REAL* v_feat,          // [P, C]      
                            __global REAL* v_alpha,         // [P]      
                            __global REAL* v_winout)        // [P]        (if has_win)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int n = n_contrib[pix];
    REAL vo[C_MAX], R[C_MAX];
    for (int c = 0; c < CH; ++c) { vo[c] = v_out[pix * CH + c]; R[c] = bg[c]; }
    const REAL va = has_vacc ? v_acc[pix] : (REAL)0;
    /* first pass: T_i of every composited fragment, parked in v_alpha (no division by 1 - a_i) */
    REAL T = (REAL)1;
    for (int i = 0; i < n; ++i) {
        const int o = frag_off[pix] + i;
        v_alpha[o] = T;
        T *= (REAL)1 - (has_win ? alpha[o] * win[o] : alpha[o]);
    }
    REAL G = (REAL)1;
    for (int i = n - 1; i >= 0; --i) {
        const int o = frag_off[pix] + i;
        T = v_alpha[o];
        const REAL ab = alpha[o];
        const REAL wv = has_win ? win[o] : (REAL)1;
        const REAL a = ab * wv;
        REAL dot = (REAL)0;
        for (int c = 0; c < CH; ++c) {
            const REAL f = feat[(long)o * CH + c];
            v_feat[(long)o * CH + c] = vo[c] * a * T;
            dot += vo[c] * (f - R[c]);
            R[c] = f * a + ((REAL)1 - a) * R[c];
        }
        const REAL v_a = T * (dot + va * G);
        G *= (REAL)1 - a;
        v_alpha[o] = v_a * wv;
        if (has_win) v_winout[o] = v_a * ab;
    }
    /* fragments behind the early-termination point get zero adjoints (slots >= count untouched) */
    const int cnt = frag_count[pix];
    for (int i = n; i < cnt; ++i) {
        const int o = frag_off[pix] + i;
        for (int c = 0; c < CH; ++c) v_feat[(long)o * CH + c] = (REAL)0;
        v_alpha[o] = (REAL)0;
        if (has_win) v_winout[o] = (REAL)0;
    }
}
