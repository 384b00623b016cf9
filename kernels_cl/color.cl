/* color.cl — the photos' image formation on top of linear compositing: the sRGB transfer function
 * and compositing over the background in encoded space (straight alpha).
 *
 * Per pixel, linear premultiplied radiance C [3] (composited over a black background), accumulated
 * alpha A, background bg [3] (encoded values), eps > 0 the alpha guard:
 *   a' = max(A, eps),  u_c = C_c / a'                  (straight linear colour)
 *   out_c = A s(u_c) + (1 - A) bg_c
 *   s(u) = 12.92 u                        (u <= 0.0031308)
 *        = 1.055 u^(1/2.4) - 0.055        (u >  0.0031308)
 * Adjoint (v_out given; s' the derivative of s):
 *   v_C_c = v_out_c A s'(u_c) / a'
 *   v_A   = sum_c v_out_c ( s(u_c) - bg_c - [A >= eps] s'(u_c) u_c )
 * (below eps the guard a' is the constant eps, so u no longer depends on A). One work-item per pixel.
 *
 * With SRGB_CLIP defined, the camera's saturation: s(u) = 1 for u >= 1 (s(1) = 1). An 8/16-bit photo clips there,
 * so a clipped photo pixel only says "at least 1": a render above it must not be pulled down. The adjoint takes the
 * unclipped curve's slope s'(u) (a straight-through gradient, not the clip's zero slope) with the forward's clipped
 * value s = 1 (v_A's s - bg term), one-sided: above the clip only a cotangent that lowers the value passes
 *   v_C = max(v, 0) A s'(u) / a',  v_A = sum_c [ v (1 - bg_c) - max(v, 0) [A >= eps] s'(u) u ]   (u >= 1)
 * Where the photo is clipped too, render and photo both read 1 and the L1 term's cotangent is zero, so it does not
 * pull the render down; where the photo is not clipped, the render is pulled down with the unclipped slope. The
 * clip's zero slope left such a pixel with no gradient at all, a trap: under the mesh stage's Gaussian pixel filter,
 * over-exposed yellow spread into bob_env's blue spots, whose red channel then stayed saturated (magenta) for good.
 * Two-sided (the first version), the SSIM term's local statistics pushed saturated pixels further up through the
 * unclipped slope: on spot under a bright environment (54 % of the object clipped) the mesh stage's point light
 * went inside the object at 4x its intensity (mesh NVS 36.4 -> 26.1 dB).
 *
 * The root r_c = u_c^(1/2.4) (0 on the linear segment) is the only transcendental of either pass (as the
 * builtins exp2 and log2, ~10 ns a channel on PoCL's CPU device, most of both kernels' time; see srgb_root
 * below for what it is now). With KEEP_ROOT the forward writes it out ([H*W, 3]) and with HAS_ROOT the
 * adjoint reads it back instead of computing it again: the same values, bit for bit (u is computed by the
 * same expression in both passes).
 */
#include "real.h"
#include "fast_math.h"

#define SRGB_KNEE ((REAL)0.0031308)

/* u^(1/2.4) for u > 0. PoCL's generic pow() measured 0.2 us per call on the CPU (27 ms for one 200x200
 * forward), and its log2 / exp2 are scalar library calls too (fast_math.h): in float, exp(log2(u) ln2 / 2.4)
 * with fast_math.h's log2 (exp vectorises): relative error against float64 at most 3.1e-7 from the knee to 1e4,
 * where exp2(log2(u) / 2.4) measured 4.2e-7 (tests/test_fast_math.py); in double (the float64 checks) the
 * builtins. */
inline REAL srgb_root(const REAL u) {
#ifdef REAL_FP64
    return exp2(log2(u) * (REAL)(1.0 / 2.4));
#else
    return exp(tl_log2(u) * (REAL)(0.69314718055994530942 / 2.4));
#endif
}

inline REAL srgb_s(const REAL u) {
#ifdef SRGB_CLIP
    if (u >= (REAL)1) return (REAL)1;
#endif
    return u <= SRGB_KNEE ? (REAL)12.92 * u : (REAL)1.055 * srgb_root(u) - (REAL)0.055;
}

/* s'(u) = 1.055 / 2.4 · u^(1/2.4 − 1) = 1.055 / 2.4 · u^(1/2.4) / u  (u > knee > 0) */
inline REAL srgb_ds(const REAL u) {
    return u <= SRGB_KNEE ? (REAL)12.92 : (REAL)(1.055 / 2.4) * srgb_root(u) / u;
}

/* One work-item per channel value (global size 3 npix): consecutive work-items read and write consecutive
 * values, so the work-group loop vectorises (one work-item per pixel, with its three channels, did not:
 * 2.4 -> 0.8 ms at 200x200 with the root of fast_math.h, bench/results/fast_math_pocl_2026-11-28.txt). */
__kernel void srgb_composite_fwd(__global const REAL* C,   // [H*W, 3] linear premultiplied radiance
                                 __global const REAL* A,   // [H*W]    accumulated alpha
                                 const REAL bg0, const REAL bg1, const REAL bg2, const REAL eps,
                                 const int npix,
#ifdef KEEP_ROOT
                                 __global REAL* root,      // [H*W, 3] r_c (0 on the linear segment)
#endif
                                 __global REAL* out)       // [H*W, 3] encoded, over bg
{
    const int i = get_global_id(0);
    if (i >= 3 * npix) return;
    const int p = i / 3, c = i - 3 * p;
    const REAL a = A[p];
    const REAL ad = fmax(a, eps);
    const REAL bg = c == 0 ? bg0 : (c == 1 ? bg1 : bg2);
    const REAL u = C[i] / ad;
#ifdef KEEP_ROOT
    /* srgb_s(u) from the root the adjoint reads back (the same expressions: bit for bit) */
    const int lin = u <= SRGB_KNEE;
    const REAL r = lin ? (REAL)0 : srgb_root(u);
#ifdef SRGB_CLIP
    const int sat = u >= (REAL)1;
#else
    const int sat = 0;
#endif
    const REAL sv = sat ? (REAL)1 : (lin ? (REAL)12.92 * u : (REAL)1.055 * r - (REAL)0.055);
    root[i] = r;
#else
    const REAL sv = srgb_s(u);
#endif
    out[i] = a * sv + ((REAL)1 - a) * bg;
}

__kernel void srgb_composite_bwd(__global const REAL* C,     // [H*W, 3]
                                 __global const REAL* A,     // [H*W]
                                 const REAL bg0, const REAL bg1, const REAL bg2, const REAL eps,
                                 const int npix,
                                 __global const REAL* v_out, // [H*W, 3]
#ifdef HAS_ROOT
                                 __global const REAL* root,  // [H*W, 3] the forward's roots (KEEP_ROOT)
#endif
                                 __global REAL* v_C,         // [H*W, 3]
                                 __global REAL* v_A)         // [H*W]
{
    const int p = get_global_id(0);
    if (p >= npix) return;
    const REAL a = A[p];
    const REAL ad = fmax(a, eps);
    const REAL inside = a >= eps ? (REAL)1 : (REAL)0;
    const REAL bg[3] = {bg0, bg1, bg2};
    REAL va = (REAL)0;
    for (int c = 0; c < 3; ++c) {
        const REAL u = C[p * 3 + c] / ad;
        const REAL g = v_out[p * 3 + c];
        /* s and s' from one root (the same expressions as srgb_s / srgb_ds: bit for bit, half the
         * exp2/log2 calls) */
        const int lin = u <= SRGB_KNEE;
#ifdef HAS_ROOT
        const REAL r = root[p * 3 + c];
#else
        const REAL r = lin ? (REAL)0 : srgb_root(u);
#endif
        /* the unclipped curve's slope s' also with SRGB_CLIP (the straight-through adjoint of the header), and the
         * forward's value s (clipped) */
#ifdef SRGB_CLIP
        const int sat = u >= (REAL)1;
#else
        const int sat = 0;
#endif
        const REAL ds = lin ? (REAL)12.92 : (REAL)(1.055 / 2.4) * r / u;
        const REAL s = sat ? (REAL)1 : (lin ? (REAL)12.92 * u : (REAL)1.055 * r - (REAL)0.055);
        /* one-sided above the clip: only a cotangent that lowers the value passes (g > 0); a saturated value
         * cannot rise, so a push upwards (g < 0) is dropped */
        const REAL gs = sat ? fmax(g, (REAL)0) : g;
        v_C[p * 3 + c] = gs * a * ds / ad;
        va += g * (s - bg[c]) - gs * inside * ds * u;
    }
    v_A[p] = va;
}
