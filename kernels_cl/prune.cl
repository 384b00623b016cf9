/* prune.cl — drop the fragments that compositing never reaches (composite.cl's early termination), before
 * they are shaded: per pixel, with a_i = alpha_i win_i (the interpolated opacity times the coverage window, 1
 * without one), T_0 = 1, T_{i+1} = T_i (1 - a_i), keep fragments 0 .. n-1 where n - 1 is the first i with
 * T_{i+1} < t_keep (all of them if none). t_keep is half the compositing's t_min: whatever the rounding of
 * this pass against composite.cl's, its n is never below the compositing's (which stops at T < t_min), so the
 * composite, its adjoint and every fragment adjoint of the kept list equal the full list's (the dropped fragments'
 * weights are exactly zero there; both kernels form T the same way, and a compiler contracting 1 - a w into an FMA in
 * one of them moves T by far less than the factor 2 while t_min is well above float32's resolution). An opaque mesh (alpha 1 - 1e-5) keeps one fragment where its front face covers
 * the pixel, against two (front and back face) before.
 *
 * prune_count: one work-item per pixel -> count2 [H W].
 * prune_pack:  one work-item per pixel: rows off[p] + i -> off2[p] + i (i < count2[p]) of the fragments' face,
 *              entry, barycentrics, depth, window and the C interpolated attributes.
 */
#include "real.h"

__kernel void prune_count(__global const REAL* fa,       // [P, C] interpolated attributes (opacity in column ca)
                          const int C, const int ca,
                          __global const REAL* win,      // [P] (if has_win)
                          const int has_win,
                          __global const int* count,     // [H W]
                          __global const int* off,       // [H W + 1]
                          const int npix, const REAL t_keep,
                          __global int* count2)          // [H W]
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int cnt = count[pix], o0 = off[pix];
    REAL T = (REAL)1;
    int n = 0;
    for (int i = 0; i < cnt; ++i) {
        const int o = o0 + i;
        const REAL a = has_win ? fa[(long)o * C + ca] * win[o] : fa[(long)o * C + ca];
        T *= (REAL)1 - a;
        n = i + 1;
        if (T < t_keep) break;
    }
    count2[pix] = n;
}

__kernel void prune_pack(__global const int* count2,    // [H W]
                         __global const int* off,       // [H W + 1] the full list's
                         __global const int* off2,      // [H W + 1] the kept list's
                         const int npix, const int C, const int has_win,
                         __global const int* face, __global const int* entry, __global const REAL* bary,
                         __global const REAL* depth, __global const REAL* win, __global const REAL* fa,
                         __global int* face2, __global int* entry2, __global REAL* bary2,
                         __global REAL* depth2, __global REAL* win2, __global REAL* fa2)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int n = count2[pix], s0 = off[pix], d0 = off2[pix];
    for (int i = 0; i < n; ++i) {
        const int s = s0 + i, d = d0 + i;
        face2[d] = face[s];
        entry2[d] = entry[s];
        bary2[2 * d] = bary[2 * s];
        bary2[2 * d + 1] = bary[2 * s + 1];
        depth2[d] = depth[s];
        if (has_win) win2[d] = win[s];
        for (int c = 0; c < C; ++c) fa2[(long)d * C + c] = fa[(long)s * C + c];
    }
}
