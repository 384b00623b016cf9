/* density.cl — DensityStats.add (triplet_cl/density.py) for one view, one work-item per face.
 *
 * For every face f with visible[f] != 0, in double precision, in the order of the numpy reference:
 *   g             = Σ_c v_vs[F[f,c], 0:2]                  (c = 0, 1, 2 summed left to right)
 *   grad_accum[f] += grad_scale · sqrt(g.x² + g.y²)
 *   denom[f]      += 1
 *   V_GRAD:  world_grad_accum[f] += Σ_c v_V[F[f,c]]
 *   VS:      ext = max_c vs[F[f,c], 0:2] − min_c ...;  area = ext.x · ext.y;
 *            max_screen_area[f] = max(.., area);  max_screen_frac[f] = max(.., area / (W·H))
 *   FRONT:   where front_hit[f] (the face is the nearest face of at least one pixel of the view):
 *            front_views[f] += 1;  front_grad_accum[f] += grad_scale · sqrt(g.x² + g.y²)
 * Inputs are REAL (the renderer's arrays), widened to double; v_vs rows have VS_STRIDE (2 or 3)
 * entries. One face per work-item writes only its own rows: no atomics.
 */
#include "real.h"

#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#ifndef VS_STRIDE
#define VS_STRIDE 3
#endif

__kernel void face_stats_add(__global const int* F,          // [M, 3]
                             __global const uchar* visible,  // [M]
                             const int M,
                             __global const REAL* v_vs,      // [N, VS_STRIDE]
                             const double grad_scale,
#ifdef V_GRAD
                             __global const REAL* v_V,       // [N, 3]
                             __global double* world_grad_accum, // [M, 3]
#endif
#ifdef VS
                             __global const REAL* vs,        // [N, 3]
                             const double image_area,        // W · H
                             __global double* max_screen_area,  // [M]
                             __global double* max_screen_frac,  // [M]
#endif
#ifdef FRONT
                             __global const uchar* front_hit,   // [M] the face is the nearest of >= 1 pixel
                             __global long* front_views,        // [M]
                             __global double* front_grad_accum, // [M]
#endif
                             __global double* grad_accum,    // [M]
                             __global long* denom)           // [M]
{
    const int f = get_global_id(0);
    if (f >= M || !visible[f]) return;
    const int c0 = F[3 * f], c1 = F[3 * f + 1], c2 = F[3 * f + 2];
    const double gx = ((double)v_vs[VS_STRIDE * c0] + (double)v_vs[VS_STRIDE * c1]) + (double)v_vs[VS_STRIDE * c2];
    const double gy = ((double)v_vs[VS_STRIDE * c0 + 1] + (double)v_vs[VS_STRIDE * c1 + 1])
                      + (double)v_vs[VS_STRIDE * c2 + 1];
    const double gn = grad_scale * sqrt(gx * gx + gy * gy);
    grad_accum[f] = grad_accum[f] + gn;
    denom[f] += 1;
#ifdef FRONT
    if (front_hit[f]) {
        front_views[f] += 1;
        front_grad_accum[f] = front_grad_accum[f] + gn;
    }
#endif
#ifdef V_GRAD
    for (int k = 0; k < 3; ++k) {
        const double w = ((double)v_V[3 * c0 + k] + (double)v_V[3 * c1 + k]) + (double)v_V[3 * c2 + k];
        world_grad_accum[3 * f + k] = world_grad_accum[3 * f + k] + w;
    }
#endif
#ifdef VS
    double ext[2];
    for (int k = 0; k < 2; ++k) {
        const double a = (double)vs[3 * c0 + k], b = (double)vs[3 * c1 + k], c = (double)vs[3 * c2 + k];
        ext[k] = fmax(fmax(a, b), c) - fmin(fmin(a, b), c);
    }
    const double area = ext[0] * ext[1];
    max_screen_area[f] = fmax(max_screen_area[f], area);
    max_screen_frac[f] = fmax(max_screen_frac[f], area / image_area);
#endif
}
