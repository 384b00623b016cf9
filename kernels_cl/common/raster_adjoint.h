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
 * moments_geom_vjp turns the moments into the adjoint of the face's screen vertices (per entry in
 * fragment_bwd.cl's entry_geom, per face in blend.cl's blend_face_grad).
 */
#ifndef TRIPLET_RASTER_ADJOINT_H
#define TRIPLET_RASTER_ADJOINT_H

#include "raster_lists.h"
#include "raster_math.h"

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

/* Sum over an entry's fragments of u dE/d(x, y), E = cross(x - p, y - p), p = a0 + (dx, dy),
 * from the moments (m, mx, my) of u; rx, ry = x - a0, y - a0. Accumulates into gx, gy. */
inline void edge_moment_vjp(REAL2 rx, REAL2 ry, REAL mm, REAL mx, REAL my, REAL2* gx, REAL2* gy)
{
    /* d/dx = ((y - p).y, -(y - p).x) = (ry.y - dy, -(ry.x - dx));  d/dy = (-(rx.y - dy), rx.x - dx) */
    *gx += (REAL2)(ry.y * mm - my, -(ry.x * mm - mx));
    *gy += (REAL2)(-(rx.y * mm - my), rx.x * mm - mx);
}

/* The adjoint of the face's screen vertices (u, v, z) from the MOMENTS m of its fragments (summed
 * over one entry, or over all the entries of the face: the moments are relative to a0 and the map
 * is linear in them), d [3, 3]: corner, (u, v, z). Private arrays. */
inline void moments_geom_vjp(__global const REAL* vs, __global const int* F, int f, const REAL* m, REAL* d)
{
    const REAL3 p0 = LOAD3(vs, F[3 * f]), p1 = LOAD3(vs, F[3 * f + 1]), p2 = LOAD3(vs, F[3 * f + 2]);
    const REAL2 a0 = p0.xy, r1 = p1.xy - a0, r2 = p2.xy - a0, r0 = (REAL2)(0, 0);
    const REAL iA = (REAL)1 / cross2(r1, r2);
    REAL2 g0 = (REAL2)(0, 0), g1 = (REAL2)(0, 0), g2 = (REAL2)(0, 0);
    /* E0 = cross(a1 - p, a2 - p), E1 = cross(a2 - p, a0 - p), E2 = cross(a0 - p, a1 - p) */
    edge_moment_vjp(r1, r2, m[0], m[1], m[2], &g1, &g2);
    edge_moment_vjp(r2, r0, m[3], m[4], m[5], &g2, &g0);
    edge_moment_vjp(r0, r1, m[6], m[7], m[8], &g0, &g1);
    g0 *= iA; g1 *= iA; g2 *= iA;
    /* v_A = -sA / A  into  A = cross(a1 - a0, a2 - a0) */
    REAL2 vd1 = (REAL2)(0, 0), vd2 = (REAL2)(0, 0);
    cross2_vjp(r1, r2, -m[9] * iA, &vd1, &vd2);
    g0 -= vd1 + vd2; g1 += vd1; g2 += vd2;
    /* edge lengths: v_L_k = -mL_k / L_k, e_k = y_k - x_k, v_e = v_L e / L */
    const REAL2 e0 = r2 - r1, e1 = r0 - r2, e2 = r1 - r0;
    if (m[10] != (REAL)0) { const REAL L2 = dot(e0, e0); const REAL2 ve = -m[10] / L2 * e0; g2 += ve; g1 -= ve; }
    if (m[11] != (REAL)0) { const REAL L2 = dot(e1, e1); const REAL2 ve = -m[11] / L2 * e1; g0 += ve; g2 -= ve; }
    if (m[12] != (REAL)0) { const REAL L2 = dot(e2, e2); const REAL2 ve = -m[12] / L2 * e2; g1 += ve; g0 -= ve; }
    d[0] = g0.x; d[1] = g0.y; d[2] = -m[13] / (p0.z * p0.z);
    d[3] = g1.x; d[4] = g1.y; d[5] = -m[14] / (p1.z * p1.z);
    d[6] = g2.x; d[7] = g2.y; d[8] = -m[15] / (p2.z * p2.z);
}

/* moments_geom_vjp of one entry's record in global memory (entry_geom, fragment_bwd.cl). */
inline void entry_geom_vjp(__global const REAL* vs, __global const int* F, int f, __global const REAL* mom,
                           __global REAL* d)
{
    REAL m[MOMENTS], g[9];
    for (int q = 0; q < MOMENTS; ++q) m[q] = mom[q];
    moments_geom_vjp(vs, F, f, m, g);
    for (int q = 0; q < 9; ++q) d[q] = g[q];
}

#endif /* TRIPLET_RASTER_ADJOINT_H */
