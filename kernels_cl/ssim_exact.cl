/* ssim_exact.cl — the photometric loss's adjoint (1 − λ)·L1 + λ·(1 − SSIM) of float32 [H, W, C] images, bit for
 * bit what the numpy reference computes (losses.py: _l1_bwd, _ssim_fwd, _ssim_bwd with padding "zero").
 *
 * The reference's operations, in its order:
 *  - the Gaussian passes are scipy.ndimage.correlate1d (zero padding) over axis 0 (rows) and then axis 1
 *    (columns) of float32 maps: per output, in double, acc = m[i]·w0, then for k = 5, 4, …, 1
 *    acc += (m[i − k] + m[i + k])·wk (values outside the image are 0.0), w = the float32 taps widened to double,
 *    the result rounded to float32 after each pass (scipy's symmetric-filter loop; no FMA on x86-64 wheels);
 *  - every other operation is one float32 numpy operation (each rounded), with python-float constants rounded
 *    to float32 (C1, C2, g and the L1 factor arrive as float arguments, rounded on the host).
 * FP_CONTRACT is off, so no a·b + c is fused; the float32 quotients are taken in double and rounded once
 * (a correctly rounded float division whatever the device's float division). Needs cl_khr_fp64.
 *
 * Pixel (y, x, c) lives at (y·W + x)·C + c; maps are [K, H, W, C] planes of n = H·W·C values.
 *   ssim_x_maps:   src = {x, y, x², y², xy};  ssim_x_rows: tmp[k] = G_rows * src[k]            (k < 5)
 *   ssim_x_fwd_h:  μx, μy, sxx, syy, sxy = G_cols * tmp; the SSIM map m (out) and, for the adjoint seed g,
 *                  d[0] = ∂μx, d[1] = ∂B2, d[2] = 2·∂A2                                   (_ssim_bwd's maps)
 *   ssim_x_rows:   tmp[k] = G_rows * d[k]                                                  (k < 3)
 *   ssim_x_bwd_h:  F = G_cols * tmp; v_x = sign(x − y)·l1 + ((F0 + (2x)·F1) + y·F2)
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define RADIUS 5

/* one output of the correlate1d loop along a line: `at(i)` the line's float32 value at i (0.0 outside). */
#define CORR(at, i, len, w, out)                                                        \
    do {                                                                                \
        double acc_ = (double)(at(i)) * w[0];                                           \
        for (int k_ = RADIUS; k_ >= 1; --k_) {                                          \
            const double l_ = ((i) - k_ >= 0) ? (double)(at((i) - k_)) : 0.0;           \
            const double r_ = ((i) + k_ < (len)) ? (double)(at((i) + k_)) : 0.0;        \
            acc_ += (l_ + r_) * w[k_];                                                  \
        }                                                                               \
        out = (float)acc_;                                                              \
    } while (0)

static inline float fdiv(const float a, const float b) { return (float)((double)a / (double)b); }

__kernel void ssim_x_maps(__global const float* x, __global const float* y,  // [H, W, C] = n values
                          const int n,
                          __global float* src)                                // [5, n]: x, y, x², y², xy
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const float a = x[i], b = y[i];
    src[i] = a;
    src[n + i] = b;
    src[2 * n + i] = a * a;  // float32 products, as numpy's
    src[3 * n + i] = b * b;
    src[4 * n + i] = a * b;
}

/* the rows pass (axis 0) of K maps: tmp[k] = G_rows * src[k] */
__kernel void ssim_x_rows(__global const float* src,   // [K, H, W, C]
                          __constant double* w,
                          const int H, const int W, const int C, const int K,
                          __global float* tmp)         // [K, H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int n = H * W * C, row = W * C;
    for (int c = 0; c < C; ++c) {
        const int base = px * C + c;  // column px, channel c: element of row r at base + r·row
        for (int k = 0; k < K; ++k) {
#define AT(r) src[k * n + base + (r) * row]
            float v;
            CORR(AT, py, H, w, v);
#undef AT
            tmp[k * n + py * row + base] = v;
        }
    }
}

__kernel void ssim_x_fwd_h(__global const float* tmp,   // [5, H, W, C]
                           __constant double* w,
                           const int H, const int W, const int C,
                           const float c1, const float c2, const float g,  // g: the adjoint seed per entry
                           __global float* ssim_map,    // [H, W, C]
                           __global float* d)           // [3, H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int n = H * W * C, row = W * C;
    for (int c = 0; c < C; ++c) {
        const int base = py * row + c;  // row py, channel c: element of column q at base + q·C
        float f[5];
        for (int k = 0; k < 5; ++k) {
#define AT(q) tmp[k * n + base + (q) * C]
            CORR(AT, px, W, w, f[k]);
#undef AT
        }
        const float mu_x = f[0], mu_y = f[1], s_xx = f[2], s_yy = f[3], s_xy = f[4];
        const float mu_xy = mu_x * mu_y;
        const float a1 = 2.0f * mu_xy + c1;
        const float a2 = 2.0f * (s_xy - mu_xy) + c2;
        const float mxx = mu_x * mu_x, myy = mu_y * mu_y;
        const float b1 = (mxx + myy) + c1;
        const float b2 = (((s_xx + s_yy) - mxx) - myy) + c2;
        const float m = fdiv(a1 * a2, b1 * b2);
        const int i = base + px * C;
        ssim_map[i] = m;
        const float dd = fdiv(g, b1 * b2);
        const float d_a1 = dd * a2, d_a2 = dd * a1;
        const float gm = (-g) * m;
        const float d_b1 = fdiv(gm, b1), d_b2 = fdiv(gm, b2);
        d[i] = 2.0f * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2));
        d[n + i] = d_b2;
        d[2 * n + i] = 2.0f * d_a2;
    }
}

__kernel void ssim_x_bwd_h(__global const float* x, __global const float* y,  // [H, W, C]
                           __global const float* tmp,                         // [3, H, W, C]
                           __constant double* w,
                           const int H, const int W, const int C,
                           const float l1,                                    // the L1 factor ((1 − λ)·v / n)
                           __global float* v_x)                               // [H, W, C]
{
    const int px = get_global_id(0), py = get_global_id(1);
    if (px >= W || py >= H) return;
    const int n = H * W * C, row = W * C;
    for (int c = 0; c < C; ++c) {
        const int base = py * row + c;
        float f[3];
        for (int k = 0; k < 3; ++k) {
#define AT(q) tmp[k * n + base + (q) * C]
            CORR(AT, px, W, w, f[k]);
#undef AT
        }
        const int i = base + px * C;
        const float a = x[i], b = y[i];
        const float e = a - b;
        /* np.sign: 1, −1, or +0 (for ±0); a NaN stays NaN (the images are finite) */
        const float s = e > 0.0f ? 1.0f : (e < 0.0f ? -1.0f : (e == 0.0f ? 0.0f : e));
        const float vs = (f[0] + (2.0f * a) * f[1]) + b * f[2];
        v_x[i] = s * l1 + vs;
    }
}
