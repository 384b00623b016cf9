/* interpolate.cl — per-vertex attributes to fragments, and the adjoint.
 *
 * Forward (per fragment o with face f = frag_face[o], lam2 = 1 - lam0 - lam1):
 *   out[o, c] = lam0 attr[F[f,0], c] + lam1 attr[F[f,1], c] + lam2 attr[F[f,2], c]
 *   One work-item per fragment of the packed list (ops/raster.py Fragments).
 * Adjoint (kernel fragment_bwd in fragment_bwd.cl, fused with the geometry adjoint):
 *   v_attr[F[f,i], c] += lam_i v_out[o, c]
 *   v_bary[o] = ( sum_c v_out[o,c] (a0_c - a2_c),  sum_c v_out[o,c] (a1_c - a2_c) )
 */
#include "real.h"

#ifndef TILE
#define TILE 8
#endif

__kernel void interpolate_fwd(__global const REAL* attr,       // [N, C]
                              __global const int* F,           // [M, 3]
                              __global const int* frag_face,   // [P]
                              __global const REAL* frag_bary,  // [P, 2]
                              const int P, const int C,
                              __global REAL* out)              // [P, C]
{
    const int o = get_global_id(0);
    if (o >= P) return;
    const int f = frag_face[o];
    const REAL l0 = frag_bary[2 * o], l1 = frag_bary[2 * o + 1], l2 = (REAL)1 - l0 - l1;
    __global const REAL* a0 = attr + F[3 * f] * C;
    __global const REAL* a1 = attr + F[3 * f + 1] * C;
    __global const REAL* a2 = attr + F[3 * f + 2] * C;
    __global REAL* d = out + (long)o * C;
    /* four channels at a time (vload4 / vstore4: PoCL vectorises neither this loop nor across work-items on its
     * own; measured 2x), the same expression per channel, so the same bits as the scalar loop */
    int c = 0;
    for (; c + 4 <= C; c += 4)
        vstore4(l0 * vload4(0, a0 + c) + l1 * vload4(0, a1 + c) + l2 * vload4(0, a2 + c), 0, d + c);
    for (; c < C; ++c) d[c] = l0 * a0[c] + l1 * a1[c] + l2 * a2[c];
}
