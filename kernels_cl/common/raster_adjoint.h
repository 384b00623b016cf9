/* raster_adjoint.h — one fragment's geometric adjoint as moments of its (tile, face) entry.
 *
 * Shared by fragment_bwd.cl (the generic fragment adjoint) and blend.cl (the fused per-vertex
 * blend); fragment_bwd.cl's header derives the formulas. Per fragment at (dx, dy) = p - a0 with
 * screen barycentrics b_k, perspective-correct (lam0, lam1), depth zp and the adjoints v_lam0,
 * v_lam1 (v_lam2 = 0: lam2 = 1 - lam0 - lam1), v_zp, v_win:
 *   base = v_lam0 lam0 + v_lam1 lam1 + v_zp zp,  v_w_k = (v_lam_k - base) zp,  v_b_k = v_w_k / z_k
 *   window (nearest soft edge k*, d = d_k* > 0): v_d = v_win sigma e^(-sigma d),
 *     u_k* += v_d g_k*,  mL_k* += v_d d,  v_sigma += v_win d e^(-sigma d)
 *   u_k = v_b_k (+ window):  m[3k] += u_k,  m[3k+1] += u_k dx,  m[3k+2] += u_k dy
 *   m[9] += sum_k v_b_k b_k,  m[13 + k] += v_w_k b_k
 * entry_geom (fragment_bwd.cl) turns the moments into the adjoint of the face's screen vertices.
 */
#ifndef TRIPLET_RASTER_ADJOINT_H
#define TRIPLET_RASTER_ADJOINT_H

#include "raster_lists.h"

#define MOMENTS 16

/* Adds one fragment to the moments m [MOMENTS] of its entry (set-up s). (kk, dm, ex): the window's
 * arg-min edge, distance and exp(-sigma max(d, 0)) (setup_window_ex), read only when v_win != 0.
 * Returns the fragment's contribution to v_sigma. */
inline REAL fragment_moments(__global const REAL* s, REAL dx, REAL dy, REAL b0, REAL b1, REAL b2,
                             REAL l0, REAL l1, REAL zp, REAL vl0, REAL vl1, REAL vzp, REAL vw,
                             REAL sigma, int kk, REAL dm, REAL ex, __global REAL* m)
{
    const REAL base = vl0 * l0 + vl1 * l1 + vzp * zp;
    const REAL vw0 = (vl0 - base) * zp, vw1 = (vl1 - base) * zp, vw2 = -base * zp;
    const REAL vb0 = vw0 * s[6], vb1 = vw1 * s[7], vb2 = vw2 * s[8];
    REAL u0 = vb0, u1 = vb1, u2 = vb2;
    REAL vsig = (REAL)0;
    if (vw != (REAL)0 && dm > (REAL)0 && dm < HARD_EDGE_DISTANCE) {
        const REAL vd = vw * sigma * ex;
        vsig = vw * dm * ex;
        if (kk == 0) u0 += vd * s[9];
        else if (kk == 1) u1 += vd * s[10];
        else u2 += vd * s[11];
        m[10 + kk] += vd * dm;
    }
    m[0] += u0; m[1] += u0 * dx; m[2] += u0 * dy;
    m[3] += u1; m[4] += u1 * dx; m[5] += u1 * dy;
    m[6] += u2; m[7] += u2 * dx; m[8] += u2 * dy;
    m[9] += vb0 * b0 + vb1 * b1 + vb2 * b2;
    m[13] += vw0 * b0; m[14] += vw1 * b1; m[15] += vw2 * b2;
    return vsig;
}

#endif /* TRIPLET_RASTER_ADJOINT_H */
