/* downsample.cl — the box filter of a supersampled render (the mesh stage renders at f x the camera's resolution
 * and averages each f x f block, as a camera integrates a pixel), and its adjoint.
 *
 * box_down (one work-item per output pixel p = (i, j) of [H, W], C channels):
 *   y[i, j, c] = (sum over a = 0..f-1, then b = 0..f-1 of x[i f + a, j f + b, c]) / f^2   (a fixed order)
 * box_up (one work-item per input pixel q = (r, s) of [H f, W f]): the adjoint,
 *   v_x[r, s, c] = v_y[r / f, s / f, c] / f^2
 */
#include "real.h"

__kernel void box_down(__global const REAL* x,   // [H f, W f, C]
                       const int H, const int W, const int f, const int C,
                       __global REAL* y)         // [H, W, C]
{
    const int p = get_global_id(0);
    if (p >= H * W) return;
    const int i = p / W, j = p - (p / W) * W;
    const int Wf = W * f;
    const REAL w = (REAL)1 / (REAL)(f * f);
    for (int c = 0; c < C; ++c) {
        REAL s = (REAL)0;
        for (int a = 0; a < f; ++a)
            for (int b = 0; b < f; ++b) s += x[((size_t)(i * f + a) * Wf + (j * f + b)) * C + c];
        y[(size_t)p * C + c] = s * w;
    }
}

__kernel void box_up(__global const REAL* v_y,   // [H, W, C]
                     const int H, const int W, const int f, const int C,
                     __global REAL* v_x)         // [H f, W f, C]
{
    const int q = get_global_id(0);
    const int Wf = W * f;
    if (q >= H * f * Wf) return;
    const int r = q / Wf, s = q - (q / Wf) * Wf;
    const REAL w = (REAL)1 / (REAL)(f * f);
    const size_t src = ((size_t)(r / f) * W + s / f) * C;
    for (int c = 0; c < C; ++c) v_x[(size_t)q * C + c] = v_y[src + c] * w;
}

/* The capture's pixel filter (a camera's reconstruction filter, e.g. Mitsuba 3's default: a Gaussian of standard
 * deviation 0.5 pixel truncated at 4 sigma; Blender Cycles' 1.5-pixel Blackman-Harris is close): each output pixel is
 * the weighted mean of the supersamples near its centre, separably, one axis per launch (ops/downsample.py).
 *
 * The weights come from the host: wt[j], j = t - l f + R in [0, f + 2 R), the weight of supersample t in the window of
 * output l (it depends on the offset only), and inv_norm[l] = 1 / (sum of the weights of output l's supersamples that
 * lie inside the image), as a film divides by its weights.
 * filt_down (one work-item per output value (o, l, k) of [O, L, I]): along the middle axis of x [O, L f, I],
 *   y[o, l, k] = inv_norm[l] * sum over t in [l f - R, l f + f - 1 + R] ∩ [0, L f) of wt[t - l f + R] x[o, t, k]
 *   The two passes: x [H f, W f, C] as [H f, W, C] (O = H f, I = C), then [H f, W, C] as [1, H, W C] (O = 1, I = W C).
 * filt_up (one work-item per input value (o, t, k)): the adjoint,
 *   v_x[o, t, k] = sum over the outputs l whose window holds t of wt[t - l f + R] inv_norm[l] v_y[o, l, k].
 */
__kernel void filt_down(__global const REAL* x,        // [O, L f, I]
                        const int O, const int L, const int f, const int I, const int R,
                        __global const REAL* wt,       // [f + 2 R]
                        __global const REAL* inv_norm, // [L]
                        __global REAL* y)              // [O, L, I]
{
    const int p = get_global_id(0);
    if (p >= O * L * I) return;
    const int k = p % I, l = (p / I) % L, o = p / (I * L);
    const int Lf = L * f;
    const int t0 = max(0, l * f - R), t1 = min(Lf - 1, l * f + f - 1 + R);
    REAL s = (REAL)0;
    for (int t = t0; t <= t1; ++t) s += wt[t - l * f + R] * x[((size_t)o * Lf + t) * I + k];
    y[p] = s * inv_norm[l];
}

__kernel void filt_up(__global const REAL* v_y,        // [O, L, I]
                      const int O, const int L, const int f, const int I, const int R,
                      __global const REAL* wt,         // [f + 2 R]
                      __global const REAL* inv_norm,   // [L]
                      __global REAL* v_x)              // [O, L f, I]
{
    const int Lf = L * f;
    const int q = get_global_id(0);
    if (q >= O * Lf * I) return;
    const int k = q % I, t = (q / I) % Lf, o = q / (I * Lf);
    /* the outputs l with l f - R <= t <= l f + f - 1 + R: l from ceil((t - R - f + 1) / f) (the numerator shifted
     * to be non-negative before the integer division) to floor((t + R) / f) */
    const int l0 = max(0, (t - R + R * f) / f - R), l1 = min(L - 1, (t + R) / f);
    REAL s = (REAL)0;
    for (int l = l0; l <= l1; ++l) s += wt[t - l * f + R] * inv_norm[l] * v_y[((size_t)o * L + l) * I + k];
    v_x[q] = s;
}
