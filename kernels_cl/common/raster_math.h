/* raster_math.h — per-fragment geometry of a screen triangle and its adjoints.
 *
 * Notation: pixel centre p, screen vertices a0, a1, a2 (2D, pixels), camera depths z0, z1, z2.
 *   cross(x, y) = x.x*y.y - x.y*y.x
 *   A   = cross(a1 - a0, a2 - a0)                  signed doubled area
 *   E0  = cross(a1 - p, a2 - p), E1 = cross(a2 - p, a0 - p), E2 = cross(a0 - p, a1 - p)
 *   b_k = E_k / A                                  screen-space barycentrics (sum to 1)
 *   w_k = b_k / z_k,  s = w0 + w1 + w2
 *   lam_k = w_k / s                                perspective-correct barycentrics
 *   zp  = 1 / s                                    camera depth of the fragment
 *
 * Adjoint (given v_lam[3], v_zp):
 *   v_w_k = (v_lam_k - sum_i v_lam_i lam_i - v_zp zp) / s
 *   v_b_k = v_w_k / z_k,   v_z_k = -v_w_k b_k / z_k
 *   v_E_k = v_b_k / A,     v_A = -sum_k v_b_k b_k / A
 *   d cross(x, y) / dx = ( y.y, -y.x ),  d cross(x, y) / dy = ( -x.y, x.x )
 *
 * Soft coverage window (Triangle-Splatting style, hard edge as sigma -> inf):
 *   L_k = |e_k|, e0 = a2 - a1, e1 = a0 - a2, e2 = a1 - a0   (edge opposite vertex k)
 *   d_k = sgn(A) E_k / L_k                         signed pixel distance to edge k (>= 0 inside)
 *   d   = max(0, min_k d_k),  win = 1 - exp(-sigma d)
 * Adjoint: v_d = v_win sigma exp(-sigma d), v_sigma = v_win d exp(-sigma d);
 *   for the arg-min edge k: v_E_k = v_d sgn / L_k, v_L_k = -v_d d_k / L_k, v_e_k = v_L_k e_k / L_k.
 */
#ifndef TRIPLET_RASTER_MATH_H
#define TRIPLET_RASTER_MATH_H

#include "real.h"

inline REAL cross2(REAL2 x, REAL2 y) { return x.x * y.y - x.y * y.x; }

/* Adjoint of c = cross(x, y): accumulate into v_x, v_y. */
inline void cross2_vjp(REAL2 x, REAL2 y, REAL v_c, REAL2* v_x, REAL2* v_y)
{
    *v_x += v_c * (REAL2)(y.y, -y.x);
    *v_y += v_c * (REAL2)(-x.y, x.x);
}

/* Perspective-correct barycentrics and depth of pixel p in a screen triangle.
 * Returns lam[3], zp; b[3] (screen barycentrics) also returned for the adjoint. */
inline void bary_persp(REAL2 p, REAL2 a0, REAL2 a1, REAL2 a2, REAL3 z,
                       REAL* lam, REAL* zp, REAL* b)
{
    const REAL A = cross2(a1 - a0, a2 - a0);
    b[0] = cross2(a1 - p, a2 - p) / A;
    b[1] = cross2(a2 - p, a0 - p) / A;
    b[2] = cross2(a0 - p, a1 - p) / A;
    const REAL w0 = b[0] / z.x, w1 = b[1] / z.y, w2 = b[2] / z.z;
    const REAL s = w0 + w1 + w2;
    lam[0] = w0 / s;
    lam[1] = w1 / s;
    lam[2] = w2 / s;
    *zp = (REAL)1 / s;
}

/* Adjoint of bary_persp: v_lam[3], v_zp -> v_a0, v_a1, v_a2 (2D) and v_z (3), accumulated.
 * (Recomputes the forward with reciprocals: 5 divisions in all.) */
inline void bary_persp_vjp(REAL2 p, REAL2 a0, REAL2 a1, REAL2 a2, REAL3 z,
                           const REAL* v_lam, REAL v_zp,
                           REAL2* v_a0, REAL2* v_a1, REAL2* v_a2, REAL3* v_z)
{
    const REAL iA = (REAL)1 / cross2(a1 - a0, a2 - a0);
    const REAL b0 = cross2(a1 - p, a2 - p) * iA, b1 = cross2(a2 - p, a0 - p) * iA, b2 = cross2(a0 - p, a1 - p) * iA;
    const REAL iz0 = (REAL)1 / z.x, iz1 = (REAL)1 / z.y, iz2 = (REAL)1 / z.z;
    const REAL w0 = b0 * iz0, w1 = b1 * iz1, w2 = b2 * iz2;
    const REAL zp = (REAL)1 / (w0 + w1 + w2);
    const REAL base = (v_lam[0] * w0 + v_lam[1] * w1 + v_lam[2] * w2) * zp + v_zp * zp;
    /* v_w_k = (v_lam_k - base) / s = (v_lam_k - base) zp;  v_b_k = v_w_k / z_k */
    const REAL vb0 = (v_lam[0] - base) * zp * iz0, vb1 = (v_lam[1] - base) * zp * iz1;
    const REAL vb2 = (v_lam[2] - base) * zp * iz2;
    *v_z -= (REAL3)(vb0 * b0 * iz0, vb1 * b1 * iz1, vb2 * b2 * iz2);
    const REAL vE0 = vb0 * iA, vE1 = vb1 * iA, vE2 = vb2 * iA;
    const REAL vA = -(vb0 * b0 + vb1 * b1 + vb2 * b2) * iA;
    REAL2 g0 = (REAL2)(0, 0), g1 = (REAL2)(0, 0), g2 = (REAL2)(0, 0);
    /* E_k = cross(x - p, y - p) with p fixed: d/dx = d/d(x - p) */
    cross2_vjp(a1 - p, a2 - p, vE0, &g1, &g2);
    cross2_vjp(a2 - p, a0 - p, vE1, &g2, &g0);
    cross2_vjp(a0 - p, a1 - p, vE2, &g0, &g1);
    REAL2 vd1 = (REAL2)(0, 0), vd2 = (REAL2)(0, 0);
    cross2_vjp(a1 - a0, a2 - a0, vA, &vd1, &vd2);
    *v_a0 += g0 - vd1 - vd2;
    *v_a1 += g1 + vd1;
    *v_a2 += g2 + vd2;
}

/* Signed pixel distances of p to the three edge lines (>= 0 inside), and the window value. */
inline REAL edge_window(REAL2 p, REAL2 a0, REAL2 a1, REAL2 a2, REAL sigma, int* kmin, REAL* dmin)
{
    const REAL A = cross2(a1 - a0, a2 - a0);
    const REAL sg = A >= (REAL)0 ? (REAL)1 : (REAL)-1;
    const REAL d0 = sg * cross2(a1 - p, a2 - p) / length(a2 - a1);
    const REAL d1 = sg * cross2(a2 - p, a0 - p) / length(a0 - a2);
    const REAL d2 = sg * cross2(a0 - p, a1 - p) / length(a1 - a0);
    int k = 0;
    REAL d = d0;
    if (d1 < d) { d = d1; k = 1; }
    if (d2 < d) { d = d2; k = 2; }
    *kmin = k;
    *dmin = d;
    d = fmax(d, (REAL)0);
    return (REAL)1 - exp(-sigma * d);
}

/* Adjoint of edge_window: v_win -> v_a0..2 (accumulated), returns v_sigma. */
inline REAL edge_window_vjp(REAL2 p, REAL2 a0, REAL2 a1, REAL2 a2, REAL sigma, REAL v_win,
                            REAL2* v_a0, REAL2* v_a1, REAL2* v_a2)
{
    int k;
    REAL dmin;
    edge_window(p, a0, a1, a2, sigma, &k, &dmin);
    if (dmin <= (REAL)0) {  /* window is 0 and flat on the edge / outside */
        return (REAL)0;
    }
    const REAL ex = exp(-sigma * dmin);
    const REAL v_d = v_win * sigma * ex;
    const REAL v_sigma = v_win * dmin * ex;
    const REAL A = cross2(a1 - a0, a2 - a0);
    const REAL sg = A >= (REAL)0 ? (REAL)1 : (REAL)-1;
    /* edge k: E = cross(x - p, y - p), e = y - x with (x, y) = (a1,a2), (a2,a0), (a0,a1) */
    REAL2 x = k == 0 ? a1 : (k == 1 ? a2 : a0);
    REAL2 y = k == 0 ? a2 : (k == 1 ? a0 : a1);
    const REAL2 e = y - x;
    const REAL L = length(e);
    const REAL v_E = v_d * sg / L;
    const REAL v_L = -v_d * dmin / L;
    REAL2 gx = (REAL2)(0, 0), gy = (REAL2)(0, 0);
    cross2_vjp(x - p, y - p, v_E, &gx, &gy);
    const REAL2 v_e = v_L * e / L;
    gy += v_e;
    gx -= v_e;
    if (k == 0) { *v_a1 += gx; *v_a2 += gy; }
    else if (k == 1) { *v_a2 += gx; *v_a0 += gy; }
    else { *v_a0 += gx; *v_a1 += gy; }
    return v_sigma;
}

#endif /* TRIPLET_RASTER_MATH_H */
