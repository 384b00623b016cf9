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

/* ---- eight pixels of a row per work-item: the same four passes for C = 3 on CPU devices ----------------------
 * (losses.py: _lanes). PoCL vectorises none of the kernels above across work-items (a REAL3 pixel, an 11-tap loop
 * per work-item). Here work-item (gx, py) computes pixels px0 = 8 gx .. px0 + 7 of row py: their 24 values
 * (8 pixels x 3 channels, contiguous in [H, W, 3]) as three REAL8, every operation element by element, the same
 * per value and in the same order as above (a tap outside the image adds w * 0 instead of nothing: the same sum),
 * so the same bits. A vertical tap reads 24 contiguous values of another row, a horizontal one the 24 values three
 * (one pixel) further on; only the work-items at a row's ends go through a zero-padded private copy. */
#ifdef CH3
#define PX 8
#define VEC TRIPLET_CAT(REAL, 8)
#define NV (3 * PX)                 /* values per work-item */
#define HALO (3 * (PX + 2 * RADIUS))  /* values of the horizontal taps' window */

/* the 24 values of pixels x0 .. x0 + 7 of row py as v[0..2] (0 for the pixels past the n that exist) */
inline void ld24(__global const REAL* img, const int W, const int py, const int x0, const int n, VEC* v)
{
    __global const REAL* p = img + ((size_t)py * W + x0) * 3;
    if (n == PX) {
        v[0] = vload8(0, p);
        v[1] = vload8(1, p);
        v[2] = vload8(2, p);
        return;
    }
    REAL t[NV];
    for (int j = 0; j < NV; ++j) t[j] = j < 3 * n ? p[j] : (REAL)0;
    v[0] = vload8(0, t);
    v[1] = vload8(1, t);
    v[2] = vload8(2, t);
}

/* write the 24 values v[0..2] of pixels x0 .. x0 + n - 1 of row py */
inline void st24(__global REAL* img, const int W, const int py, const int x0, const int n, const VEC* v)
{
    __global REAL* p = img + ((size_t)py * W + x0) * 3;
    if (n == PX) {
        vstore8(v[0], 0, p);
        vstore8(v[1], 1, p);
        vstore8(v[2], 2, p);
        return;
    }
    REAL t[NV];
    vstore8(v[0], 0, t);
    vstore8(v[1], 1, t);
    vstore8(v[2], 2, t);
    for (int j = 0; j < 3 * n; ++j) p[j] = t[j];
}

/* the 24 values of pixels x0 .. x0 + 7 of row py of a scratch map as v[0..2], read in place also past the row's end
 * (the last work-item of a row: values of the next row, or of the buffer's slack of NV values: losses.py allocates
 * it), which only lanes that are never stored see */
#define LDS24(img, py, c) vload8((c), (img) + ((size_t)(py) * W + px0) * 3)

/* the horizontal taps' window of row py: pixels x0 - RADIUS .. x0 + 7 + RADIUS, 0 outside [0, W) (the end
 * work-items of a row); interior work-items read the row in place (halo returns 0 and leaves h unset) */
inline int halo(__global const REAL* img, const int W, const int py, const int x0, REAL* h)
{
    if (x0 - RADIUS >= 0 && x0 + PX + RADIUS <= W) return 0;
    __global const REAL* row = img + (size_t)py * W * 3;
    for (int j = 0; j < HALO; ++j) {
        const int xx = x0 - RADIUS + j / 3;
        h[j] = (xx >= 0 && xx < W) ? row[3 * xx + j % 3] : (REAL)0;
    }
    return 1;
}

/* the 24 values of tap k (0 .. 2 RADIUS: pixels x0 + k - RADIUS ..) from the row or the window */
#define TAP(img, h, use_h, k, c) \
    ((use_h) ? vload8(0, (h) + 3 * (k) + 8 * (c)) : vload8(0, (img) + ((size_t)py * W + px0 + (k) - RADIUS) * 3 + 8 * (c)))

__kernel void photometric_h_fwd8(__global const REAL* x,    // [H, W, 3]
                                 __global const REAL* y,    // [H, W, 3]
                                 __constant REAL* win,      // [11]
                                 const int H, const int W,
                                 __global REAL* tmp)        // [5, H, W, 3]
{
    const int px0 = PX * get_global_id(0), py = get_global_id(1);
    if (px0 >= W || py >= H) return;
    const int n = min(PX, W - px0), hwc = H * W * 3;
    REAL hx[HALO], hy[HALO];
    const int use_h = halo(x, W, py, px0, hx);
    halo(y, W, py, px0, hy);
    VEC s0[3], s1[3], s2[3], s3[3], s4[3];
    for (int c = 0; c < 3; ++c) {
        s0[c] = s1[c] = s2[c] = s3[c] = s4[c] = (VEC)(0);
        for (int k = 0; k <= 2 * RADIUS; ++k) {
            const REAL w = win[k];
            const VEC a = TAP(x, hx, use_h, k, c), b = TAP(y, hy, use_h, k, c);
            s0[c] += w * a; s1[c] += w * b; s2[c] += w * a * a; s3[c] += w * b * b; s4[c] += w * a * b;
        }
    }
    st24(tmp, W, py, px0, n, s0);
    st24(tmp + hwc, W, py, px0, n, s1);
    st24(tmp + 2 * hwc, W, py, px0, n, s2);
    st24(tmp + 3 * hwc, W, py, px0, n, s3);
    st24(tmp + 4 * hwc, W, py, px0, n, s4);
}

__kernel void photometric_v_fwd8(__global const REAL* x,    // [H, W, 3]
                                 __global const REAL* y,    // [H, W, 3]
                                 __global const REAL* tmp,  // [5, H, W, 3]
                                 __constant REAL* win,      // [11]
                                 const int H, const int W,
                                 const REAL lam, const int with_ssim,
                                 const int border, const REAL inv_count,
                                 __global REAL* term,       // [H, W, 3]
                                 __global REAL* d)          // [4, H, W, 3]
{
    const int px0 = PX * get_global_id(0), py = get_global_id(1);
    if (px0 >= W || py >= H) return;
    const int n = min(PX, W - px0), hwc = H * W * 3;
    const REAL inv_n = (REAL)1 / (REAL)hwc;
    REAL gt[NV];  /* the SSIM seed of each value's pixel */
    for (int j = 0; j < NV; ++j) {
        const int px = px0 + j / 3;
        gt[j] = (px >= border && px < W - border && py >= border && py < H - border) ? inv_count : (REAL)0;
    }
    VEC xa[3], ya[3], t[3];
    ld24(x, W, py, px0, n, xa);
    ld24(y, W, py, px0, n, ya);
    for (int c = 0; c < 3; ++c) t[c] = ((REAL)1 - lam) * fabs(xa[c] - ya[c]) * inv_n;
    if (with_ssim) {
        VEC mx[3], my[3], sxx[3], syy[3], sxy[3];
        for (int c = 0; c < 3; ++c) mx[c] = my[c] = sxx[c] = syy[c] = sxy[c] = (VEC)(0);
        for (int k = -RADIUS; k <= RADIUS; ++k) {
            const int yy = py + k;
            if (yy < 0 || yy >= H) continue;
            const REAL w = win[k + RADIUS];
            for (int c = 0; c < 3; ++c) {
                mx[c] += w * LDS24(tmp, yy, c);
                my[c] += w * LDS24(tmp + hwc, yy, c);
                sxx[c] += w * LDS24(tmp + 2 * hwc, yy, c);
                syy[c] += w * LDS24(tmp + 3 * hwc, yy, c);
                sxy[c] += w * LDS24(tmp + 4 * hwc, yy, c);
            }
        }
        VEC o0[3], o1[3], o2[3], o3[3];
        for (int c = 0; c < 3; ++c) {
            const VEC g = vload8(c, gt);
            const VEC a1 = 2 * mx[c] * my[c] + C1, a2 = 2 * (sxy[c] - mx[c] * my[c]) + C2;
            const VEC b1 = mx[c] * mx[c] + my[c] * my[c] + C1, b2 = sxx[c] + syy[c] - mx[c] * mx[c] - my[c] * my[c] + C2;
            const VEC m = (a1 * a2) / (b1 * b2);
            t[c] -= lam * g * m;
            const VEC q = g / (b1 * b2);
            const VEC da1 = q * a2, da2 = q * a1, db1 = -g * m / b1, db2 = -g * m / b2;
            o0[c] = 2 * (my[c] * (da1 - da2) + mx[c] * (db1 - db2));
            o1[c] = 2 * (mx[c] * (da1 - da2) + my[c] * (db1 - db2));
            o2[c] = db2;
            o3[c] = 2 * da2;
        }
        st24(d, W, py, px0, n, o0);
        st24(d + hwc, W, py, px0, n, o1);
        st24(d + 2 * hwc, W, py, px0, n, o2);
        st24(d + 3 * hwc, W, py, px0, n, o3);
    }
    st24(term, W, py, px0, n, t);
}

__kernel void photometric_h_bwd8(__global const REAL* d,    // [4, H, W, 3]
                                 __constant REAL* win,      // [11]
                                 const int H, const int W,
                                 __global REAL* tmp2)       // [4, H, W, 3]
{
    const int px0 = PX * get_global_id(0), py = get_global_id(1);
    if (px0 >= W || py >= H) return;
    const int n = min(PX, W - px0), hwc = H * W * 3;
    for (int s = 0; s < 4; ++s) {
        __global const REAL* ds = d + s * hwc;
        REAL h[HALO];
        const int use_h = halo(ds, W, py, px0, h);
        VEC acc[3];
        for (int c = 0; c < 3; ++c) {
            acc[c] = (VEC)(0);
            for (int k = 0; k <= 2 * RADIUS; ++k) acc[c] += win[k] * TAP(ds, h, use_h, k, c);
        }
        st24(tmp2 + s * hwc, W, py, px0, n, acc);
    }
}

__kernel void photometric_v_bwd8(__global const REAL* x,     // [H, W, 3]
                                 __global const REAL* y,     // [H, W, 3]
                                 __global const REAL* tmp2,  // [4, H, W, 3]
                                 __constant REAL* win,       // [11]
                                 const int H, const int W,
                                 const REAL lam, const int with_ssim, const REAL v,
                                 const int want_target,
                                 __global REAL* v_x,         // [H, W, 3]
                                 __global REAL* v_y)         // [H, W, 3] (unused unless want_target)
{
    const int px0 = PX * get_global_id(0), py = get_global_id(1);
    if (px0 >= W || py >= H) return;
    const int n = min(PX, W - px0), hwc = H * W * 3;
    const REAL l1_scale = ((REAL)1 - lam) * v / (REAL)hwc, s = -lam * v;
    VEC a[3], b[3], gx[3], gy[3];
    ld24(x, W, py, px0, n, a);
    ld24(y, W, py, px0, n, b);
    for (int c = 0; c < 3; ++c) {
        const VEC diff = a[c] - b[c];
        const VEC l1 = l1_scale * (select((VEC)(0), (VEC)(1), diff > (VEC)(0)) - select((VEC)(0), (VEC)(1), diff < (VEC)(0)));
        gx[c] = l1;
        gy[c] = -l1;
    }
    if (with_ssim) {
        VEC f0[3], f1[3], f2[3], f3[3];
        for (int c = 0; c < 3; ++c) f0[c] = f1[c] = f2[c] = f3[c] = (VEC)(0);
        for (int k = -RADIUS; k <= RADIUS; ++k) {
            const int yy = py + k;
            if (yy < 0 || yy >= H) continue;
            const REAL w = win[k + RADIUS];
            for (int c = 0; c < 3; ++c) {
                f0[c] += w * LDS24(tmp2, yy, c);
                f1[c] += w * LDS24(tmp2 + hwc, yy, c);
                f2[c] += w * LDS24(tmp2 + 2 * hwc, yy, c);
                f3[c] += w * LDS24(tmp2 + 3 * hwc, yy, c);
            }
        }
        for (int c = 0; c < 3; ++c) {
            gx[c] += s * (f0[c] + 2 * a[c] * f2[c] + b[c] * f3[c]);
            gy[c] += s * (f1[c] + 2 * b[c] * f2[c] + a[c] * f3[c]);
        }
    }
    st24(v_x, W, py, px0, n, gx);
    if (want_target) st24(v_y, W, py, px0, n, gy);
}
#undef NV
#endif /* CH3 */
