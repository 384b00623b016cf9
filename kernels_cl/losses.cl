/* losses.cl — the photometric loss (1 − λ)·L1 + λ·(1 − SSIM) of [H, W, C] images and its adjoint.
 *
 * SSIM as in 3D Gaussian Splatting: separable 11-tap Gaussian (σ = 1.5, taps in `win`), zero
 * padding, "same" size; C1 = 0.01², C2 = 0.03². Pixel (y, x, c) lives at (y·W + x)·C + c.
 *
 * Forward (two passes):
 *   photometric_h_fwd:  tmp[k] = G_x * {x, y, x², y², xy}[k]               (horizontal pass)
 *   photometric_v_fwd:  μx, μy, sxx, syy, sxy = G_y * tmp;  m = A1·A2 / (B1·B2) with
 *                       A1 = 2μxμy + C1, A2 = 2(sxy − μxμy) + C2, B1 = μx² + μy² + C1,
 *                       B2 = sxx − μx² + syy − μy² + C2;
 *                       term = (1 − λ)|x − y| / n − λ·mask·m / count   (loss = λ + Σ term)
 *                       and, for a unit SSIM seed g = mask / count, the maps
 *                       d[0] = ∂μx, d[1] = ∂μy, d[2] = ∂sxx = ∂syy = ∂B2, d[3] = ∂sxy = 2∂A2 with
 *                       ∂A1 = g·A2/(B1B2), ∂A2 = g·A1/(B1B2), ∂B1 = −g·m/B1, ∂B2 = −g·m/B2,
 *                       ∂μx = 2μy(∂A1 − ∂A2) + 2μx(∂B1 − ∂B2)  (μx ↔ μy for ∂μy).
 *   mask = 1 inside the averaged region (all pixels, or ≥ `border` px from the edge), count its size.
 * Adjoint (two passes; the zero-padded symmetric filter is its own transpose):
 *   photometric_h_bwd:  tmp2[k] = G_x * d[k]
 *   photometric_v_bwd:  F = G_y * tmp2;  with s = −λ·v (v: the loss adjoint)
 *                       v_x = s·(F0 + 2x·F2 + y·F3) + (1 − λ)·v·sign(x − y)/n
 *                       v_y = s·(F1 + 2y·F2 + x·F3) − (1 − λ)·v·sign(x − y)/n   (when v_y != 0)
 */
#include "real.h"

#define C1 ((REAL)0.0001)
#define C2 ((REAL)0.0009)
#define RADIUS 5

/* Channels in groups: with CH3 (C = 3, the colour images; losses.py defines it) a pixel's three channels are
 * one REAL3 (vload3 / vstore3): the same operations per channel as the scalar loop, so the same bits, with a
 * third of the instructions (PoCL vectorises neither the channel loop nor across work-items: measured 2.6x
 * on the horizontal pass). Otherwise one channel at a time. CW channels per group, NCG groups per pixel. */
#ifdef CH3
#define CV REAL3
#define CW 3
#define NCG 1
#define LDC(p, i) vload3(0, (p) + (i))
#define STC(v, p, i) vstore3((v), 0, (p) + (i))
#define SIGNC(d) (select((CV)(0), (CV)(1), (d) > (CV)(0)) - select((CV)(0), (CV)(1), (d) < (CV)(0)))
#else
#define CV REAL
#define CW 1
#define NCG C
#define LDC(p, i) ((p)[i])
#define STC(v, p, i) ((p)[i] = (v))
#define SIGNC(d) ((REAL)(((d) > 0) - ((d) < 0)))
#endif

__kernel void photometric_h_fwd(__global const REAL* x,    // [H, W, C]
                                __global const REAL* y,    // [H, W, C]
                                __constant REAL* win,      // [11]
                                const int H, const int W, const int C,
                                __global REAL* tmp)        // [5, H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int hwc = H * W * C;
    for (int c = 0; c < NCG; ++c) {
        CV s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0;
        for (int k = -RADIUS; k <= RADIUS; ++k) {
            const int xx = px + k;
            if (xx < 0 || xx >= W) continue;
            const int i = (py * W + xx) * C + c * CW;
            const REAL w = win[k + RADIUS];
            const CV a = LDC(x, i), b = LDC(y, i);
            s0 += w * a; s1 += w * b; s2 += w * a * a; s3 += w * b * b; s4 += w * a * b;
        }
        const int o = (py * W + px) * C + c * CW;
        STC(s0, tmp, o); STC(s1, tmp, hwc + o); STC(s2, tmp, 2 * hwc + o); STC(s3, tmp, 3 * hwc + o);
        STC(s4, tmp, 4 * hwc + o);
    }
}

__kernel void photometric_v_fwd(__global const REAL* x,    // [H, W, C]
                                __global const REAL* y,    // [H, W, C]
                                __global const REAL* tmp,  // [5, H, W, C]
                                __constant REAL* win,      // [11]
                                const int H, const int W, const int C,
                                const REAL lam, const int with_ssim,
                                const int border, const REAL inv_count,
                                __global REAL* term,       // [H, W, C]
                                __global REAL* d)          // [4, H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int hwc = H * W * C;
    const REAL inv_n = (REAL)1 / (REAL)hwc;
    const REAL g = (px >= border && px < W - border && py >= border && py < H - border) ? inv_count : (REAL)0;
    for (int c = 0; c < NCG; ++c) {
        const int o = (py * W + px) * C + c * CW;
        CV t = ((REAL)1 - lam) * fabs(LDC(x, o) - LDC(y, o)) * inv_n;
        if (with_ssim) {
            CV mx = 0, my = 0, sxx = 0, syy = 0, sxy = 0;
            for (int k = -RADIUS; k <= RADIUS; ++k) {
                const int yy = py + k;
                if (yy < 0 || yy >= H) continue;
                const int i = (yy * W + px) * C + c * CW;
                const REAL w = win[k + RADIUS];
                mx += w * LDC(tmp, i); my += w * LDC(tmp, hwc + i); sxx += w * LDC(tmp, 2 * hwc + i);
                syy += w * LDC(tmp, 3 * hwc + i); sxy += w * LDC(tmp, 4 * hwc + i);
            }
            const CV a1 = 2 * mx * my + C1, a2 = 2 * (sxy - mx * my) + C2;
            const CV b1 = mx * mx + my * my + C1, b2 = sxx + syy - mx * mx - my * my + C2;
            const CV m = (a1 * a2) / (b1 * b2);
            t -= lam * g * m;
            const CV q = g / (b1 * b2);
            const CV da1 = q * a2, da2 = q * a1, db1 = -g * m / b1, db2 = -g * m / b2;
            STC(2 * (my * (da1 - da2) + mx * (db1 - db2)), d, o);
            STC(2 * (mx * (da1 - da2) + my * (db1 - db2)), d, hwc + o);
            STC(db2, d, 2 * hwc + o);
            STC(2 * da2, d, 3 * hwc + o);
        }
        STC(t, term, o);
    }
}

__kernel void photometric_h_bwd(__global const REAL* d,    // [4, H, W, C]
                                __constant REAL* win,      // [11]
                                const int H, const int W, const int C,
                                __global REAL* tmp2)       // [4, H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int hwc = H * W * C;
    for (int c = 0; c < NCG; ++c) {
        CV s0 = 0, s1 = 0, s2 = 0, s3 = 0;
        for (int k = -RADIUS; k <= RADIUS; ++k) {
            const int xx = px + k;
            if (xx < 0 || xx >= W) continue;
            const int i = (py * W + xx) * C + c * CW;
            const REAL w = win[k + RADIUS];
            s0 += w * LDC(d, i); s1 += w * LDC(d, hwc + i); s2 += w * LDC(d, 2 * hwc + i); s3 += w * LDC(d, 3 * hwc + i);
        }
        const int o = (py * W + px) * C + c * CW;
        STC(s0, tmp2, o); STC(s1, tmp2, hwc + o); STC(s2, tmp2, 2 * hwc + o); STC(s3, tmp2, 3 * hwc + o);
    }
}

__kernel void photometric_v_bwd(__global const REAL* x,     // [H, W, C]
                                __global const REAL* y,     // [H, W, C]
                                __global const REAL* tmp2,  // [4, H, W, C]
                                __constant REAL* win,       // [11]
                                const int H, const int W, const int C,
                                const REAL lam, const int with_ssim, const REAL v,
                                const int want_target,
                                __global REAL* v_x,         // [H, W, C]
                                __global REAL* v_y)         // [H, W, C] (unused unless want_target)
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int hwc = H * W * C;
    const REAL l1_scale = ((REAL)1 - lam) * v / (REAL)hwc, s = -lam * v;
    for (int c = 0; c < NCG; ++c) {
        const int o = (py * W + px) * C + c * CW;
        const CV a = LDC(x, o), b = LDC(y, o);
        const CV diff = a - b;
        const CV l1 = l1_scale * SIGNC(diff);
        CV gx = l1, gy = -l1;
        if (with_ssim) {
            CV f0 = 0, f1 = 0, f2 = 0, f3 = 0;
            for (int k = -RADIUS; k <= RADIUS; ++k) {
                const int yy = py + k;
                if (yy < 0 || yy >= H) continue;
                const int i = (yy * W + px) * C + c * CW;
                const REAL w = win[k + RADIUS];
                f0 += w * LDC(tmp2, i); f1 += w * LDC(tmp2, hwc + i); f2 += w * LDC(tmp2, 2 * hwc + i);
                f3 += w * LDC(tmp2, 3 * hwc + i);
            }
            gx += s * (f0 + 2 * a * f2 + b * f3);
            gy += s * (f1 + 2 * b * f2 + a * f3);
        }
        STC(gx, v_x, o);
        if (want_target) STC(gy, v_y, o);
    }
}
