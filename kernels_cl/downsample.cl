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
