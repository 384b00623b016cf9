/* interpolate.cl — per-vertex attributes to fragments, and the adjoint.
 *
 * Forward (per fragment o with face f = frag_face[o] >= 0, lam2 = 1 - lam0 - lam1):
 *   out[o, c] = lam0 attr[F[f,0], c] + lam1 attr[F[f,1], c] + lam2 attr[F[f,2], c]
 *   One work-item per pixel, over its frag_count fragments; slots k >= count are not written
 *   (every consumer stops at count: writing them would cost more than the interpolation).
 * Adjoint:
 *   v_attr[F[f,i], c] += lam_i v_out[o, c]                       (scatter: see below)
 *   v_bary[o] = ( sum_c v_out[o,c] (a0_c - a2_c),  sum_c v_out[o,c] (a1_c - a2_c) )
 * interpolate_bwd runs one work-item per tile, serially over the tile's fragments, and adds
 * lam_i v_out into partial[entry, i, c]; gather_vertex (raster.cl) then sums the entries of every
 * face corner of each vertex. No float atomics, deterministic order.
 */
#include "real.h"

#ifndef TILE
#define TILE 8
#endif

__kernel void interpolate_fwd(__global const REAL* attr,       // [N, C]
                              __global const int* F,           // [M, 3]
                              __global const int* frag_face,   // [H, W, K]
                              __global const REAL* frag_bary,  // [H, W, K, 2]
                              __global const int* frag_count,  // [H, W]
                              const int npix, const int K, const int C,
                              __global REAL* out)              // [H, W, K, C]
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int cnt = frag_count[pix];
    for (int k = 0; k < cnt; ++k) {
        const int o = pix * K + k;
        const int f = frag_face[o];
        const REAL l0 = frag_bary[2 * o], l1 = frag_bary[2 * o + 1], l2 = (REAL)1 - l0 - l1;
        __global const REAL* a0 = attr + F[3 * f] * C;
        __global const REAL* a1 = attr + F[3 * f + 1] * C;
        __global const REAL* a2 = attr + F[3 * f + 2] * C;
        __global REAL* d = out + (long)o * C;
        for (int c = 0; c < C; ++c) d[c] = l0 * a0[c] + l1 * a1[c] + l2 * a2[c];
    }
}

__kernel void interpolate_bwd(__global const REAL* attr,       // [N, C]
                              __global const int* F,           // [M, 3]
                              __global const int* tile_off,    // [T + 1]
                              __global const int* frag_face,   // [H, W, K]
                              __global const int* frag_entry,  // [H, W, K]
                              __global const REAL* frag_bary,  // [H, W, K, 2]
                              __global const int* frag_count,  // [H, W]
                              __global const REAL* v_out,      // [H, W, K, C]
                              const int width, const int height, const int tiles_x, const int num_tiles,
                              const int K, const int C, const int accumulate,
                              __global REAL* partial,          // [E, 3, C]
                              __global REAL* v_bary)           // [H, W, K, 2]  (+= when accumulate)
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    for (long q = (long)e0 * 3 * C; q < (long)e1 * 3 * C; ++q) partial[q] = (REAL)0;
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int xe = min(width, tx * TILE + TILE), ye = min(height, ty * TILE + TILE);
    for (int y = ty * TILE; y < ye; ++y)
        for (int x = tx * TILE; x < xe; ++x) {
            const int pix = y * width + x;
            const int cnt = frag_count[pix];
            for (int k = 0; k < cnt; ++k) {
                const int o = pix * K + k;
                const int f = frag_face[o];
                const REAL l0 = frag_bary[2 * o], l1 = frag_bary[2 * o + 1], l2 = (REAL)1 - l0 - l1;
                __global const REAL* a0 = attr + F[3 * f] * C;
                __global const REAL* a1 = attr + F[3 * f + 1] * C;
                __global const REAL* a2 = attr + F[3 * f + 2] * C;
                __global REAL* d = partial + (long)frag_entry[o] * 3 * C;
                REAL g0 = (REAL)0, g1 = (REAL)0;
                for (int c = 0; c < C; ++c) {
                    const REAL g = v_out[(long)o * C + c];
                    d[c] += l0 * g;
                    d[C + c] += l1 * g;
                    d[2 * C + c] += l2 * g;
                    g0 += g * (a0[c] - a2[c]);
                    g1 += g * (a1[c] - a2[c]);
                }
                if (accumulate) {
                    v_bary[2 * o] += g0;
                    v_bary[2 * o + 1] += g1;
                } else {
                    v_bary[2 * o] = g0;
                    v_bary[2 * o + 1] = g1;
                }
            }
        }
}
