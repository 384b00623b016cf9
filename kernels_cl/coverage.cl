/* coverage.cl — the optional soft edge window of each fragment (Triangle-Splatting style).
 *
 * Forward (per fragment, face f, pixel centre p; see common/raster_math.h):
 *   win = 1 - exp(-sigma * max(0, min_k d_k)),  d_k the signed pixel distance to edge k
 *   (>= 0 inside). sigma -> inf gives the hard edge of the original method (win = 1 inside).
 *   Per pixel over its packed fragments (rows frag_off[pix] .. + frag_count[pix]).
 * Adjoint: fused into fragment_bwd (fragment_bwd.cl) through the window moments, so that all
 *   screen-space adjoints of a fragment reach its face in one pass: v_win -> v_(u, v) of the three
 *   vertices and v_sigma.
 */
#include "real.h"
#include "raster_math.h"

__kernel void coverage_fwd(__global const REAL* vs,         // [N, 3]
                           __global const int* F,           // [M, 3]
                           __global const int* frag_face,   // [P]
                           __global const int* frag_count,  // [H, W]
                           const int width, const int height,
                           __global const int* frag_off,    // [H * W + 1] first row of each pixel
                           const REAL sigma,
                           __global REAL* win)              // [P]
{
    const int pix = get_global_id(0);
    if (pix >= width * height) return;
    const REAL2 p = (REAL2)((REAL)(pix % width) + (REAL)0.5, (REAL)(pix / width) + (REAL)0.5);
    const int cnt = frag_count[pix];
    for (int k = 0; k < cnt; ++k) {
        const int o = frag_off[pix] + k;
        const int f = frag_face[o];
        const REAL2 a0 = LOAD3(vs, F[3 * f]).xy, a1 = LOAD3(vs, F[3 * f + 1]).xy, a2 = LOAD3(vs, F[3 * f + 2]).xy;
        int kmin;
        REAL dmin;
        win[o] = edge_window(p, a0, a1, a2, sigma, &kmin, &dmin);
    }
}
