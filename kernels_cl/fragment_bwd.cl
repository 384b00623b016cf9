/* fragment_bwd.cl — the one backward pass over the fragments of a view.
 *
 * Everything a fragment receives from a vertex goes through its face's three corners:
 *   attributes   out[o,c] = sum_i lam_i attr[F[f,i], c]            (interpolate.cl)
 *   barycentrics lam = bary_persp(a0, a1, a2, z0, z1, z2; p)       (raster.cl, raster_math.h)
 *   depth        zp  = 1 / sum_i (b_i / z_i)
 *   window       win = 1 - exp(-sigma max(0, min_k d_k))          (coverage.cl, raster_math.h)
 * so their adjoints are computed together, in one pass:
 *   v_attr[F[f,i], c]  += lam_i v_out[o,c]
 *   v_lam0 = sum_c v_out[o,c] (a0_c - a2_c) (+ v_bary_in),  v_lam1 likewise with a1
 *   (v_lam, v_zp, v_win) -> v_(u, v, z) of the corners by bary_persp_vjp and edge_window_vjp,
 *   v_sigma = sum over fragments of edge_window_vjp's sigma term.
 *
 * No float atomics: one work-item owns one tile and walks its pixels and fragments serially,
 * adding into the partial sums of that tile's (tile, face) entries,
 *   partial_attr [E, 3, C]  and  partial_geom [E, 3, 3],
 * which gather_vertex (raster.cl) then sums per vertex over the entries of each face corner, in a
 * fixed order (deterministic results). With do_geom = 0 the barycentric adjoint is written out
 * instead (v_bary_out = v_bary_in + own), for callers that chain several interpolations.
 */
#include "real.h"
#include "raster_math.h"

#ifndef TILE
#define TILE 8
#endif

__kernel void fragment_bwd(__global const REAL* vs,           // [N, 3]
                           __global const int* F,             // [M, 3]
                           __global const int* tile_off,      // [T + 1]
                           __global const int* frag_face,     // [H, W, K]
                           __global const int* frag_entry,    // [H, W, K]
                           __global const REAL* frag_bary,    // [H, W, K, 2]
                           __global const int* frag_count,    // [H, W]
                           __global const REAL* attr,         // [N, C]          (C > 0)
                           __global const REAL* v_out,        // [H, W, K, C]    (C > 0)
                           __global const REAL* v_bary_in,    // [H, W, K, 2]    (has_bary)
                           __global const REAL* v_depth,      // [H, W, K]       (has_depth)
                           __global const REAL* v_win,        // [H, W, K]       (has_win)
                           const int C, const int has_bary, const int has_depth, const int has_win,
                           const int do_geom, const REAL sigma,
                           const int width, const int height, const int tiles_x, const int num_tiles,
                           const int K,
                           __global REAL* partial_attr,       // [E, 3, C]       (C > 0)
                           __global REAL* partial_geom,       // [E, 3, 3]       (do_geom)
                           __global REAL* v_sigma_tile,       // [T]             (do_geom)
                           __global REAL* v_bary_out)         // [H, W, K, 2]    (!do_geom)
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    if (C > 0)
        for (long q = (long)e0 * 3 * C; q < (long)e1 * 3 * C; ++q) partial_attr[q] = (REAL)0;
    if (do_geom)
        for (int q = e0 * 9; q < e1 * 9; ++q) partial_geom[q] = (REAL)0;
    REAL vsig = (REAL)0;
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int xe = min(width, tx * TILE + TILE), ye = min(height, ty * TILE + TILE);
    for (int y = ty * TILE; y < ye; ++y)
        for (int x = tx * TILE; x < xe; ++x) {
            const int pix = y * width + x;
            const int cnt = frag_count[pix];
            const REAL2 p = (REAL2)((REAL)x + (REAL)0.5, (REAL)y + (REAL)0.5);
            for (int k = 0; k < cnt; ++k) {
                const int o = pix * K + k;
                const int f = frag_face[o];
                const int e = frag_entry[o];
                REAL vl0 = has_bary ? v_bary_in[2 * o] : (REAL)0;
                REAL vl1 = has_bary ? v_bary_in[2 * o + 1] : (REAL)0;
                if (C > 0) {
                    const REAL l0 = frag_bary[2 * o], l1 = frag_bary[2 * o + 1], l2 = (REAL)1 - l0 - l1;
                    __global const REAL* a0 = attr + F[3 * f] * C;
                    __global const REAL* a1 = attr + F[3 * f + 1] * C;
                    __global const REAL* a2 = attr + F[3 * f + 2] * C;
                    __global const REAL* g = v_out + (long)o * C;
                    __global REAL* d = partial_attr + (long)e * 3 * C;
                    for (int c = 0; c < C; ++c) {
                        const REAL gc = g[c];
                        d[c] += l0 * gc;
                        d[C + c] += l1 * gc;
                        d[2 * C + c] += l2 * gc;
                        vl0 += gc * (a0[c] - a2[c]);
                        vl1 += gc * (a1[c] - a2[c]);
                    }
                }
                if (!do_geom) {
                    v_bary_out[2 * o] = vl0;
                    v_bary_out[2 * o + 1] = vl1;
                    continue;
                }
                const REAL vzp = has_depth ? v_depth[o] : (REAL)0;
                const REAL vw = has_win ? v_win[o] : (REAL)0;
                if (vl0 == (REAL)0 && vl1 == (REAL)0 && vzp == (REAL)0 && vw == (REAL)0) continue;
                const REAL3 p0 = LOAD3(vs, F[3 * f]), p1 = LOAD3(vs, F[3 * f + 1]), p2 = LOAD3(vs, F[3 * f + 2]);
                const REAL3 z = (REAL3)(p0.z, p1.z, p2.z);
                REAL2 g0 = (REAL2)(0, 0), g1 = (REAL2)(0, 0), g2 = (REAL2)(0, 0);
                REAL3 gz = (REAL3)(0, 0, 0);
                if (vl0 != (REAL)0 || vl1 != (REAL)0 || vzp != (REAL)0) {
                    REAL vl[3] = {vl0, vl1, (REAL)0};
                    bary_persp_vjp(p, p0.xy, p1.xy, p2.xy, z, vl, vzp, &g0, &g1, &g2, &gz);
                }
                if (vw != (REAL)0)
                    vsig += edge_window_vjp(p, p0.xy, p1.xy, p2.xy, sigma, vw, &g0, &g1, &g2);
                __global REAL* d = partial_geom + e * 9;
                d[0] += g0.x; d[1] += g0.y; d[2] += gz.x;
                d[3] += g1.x; d[4] += g1.y; d[5] += gz.y;
                d[6] += g2.x; d[7] += g2.y; d[8] += gz.z;
            }
        }
    if (do_geom) v_sigma_tile[t] = vsig;
}
