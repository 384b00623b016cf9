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
 *   ssim_x_maps:    src = {x, y, x², y², xy};  ssim_x_rows_e: tmp[k] = G_rows * src[k]         (k < 5)
 *   ssim_x_fwd_h_e: μx, μy, sxx, syy, sxy = G_cols * tmp; the SSIM map m (out) and, for the adjoint seed g,
 *                   d[0] = ∂μx, d[1] = ∂B2, d[2] = 2·∂A2                                  (_ssim_bwd's maps)
 *   ssim_x_rows_e:  tmp[k] = G_rows * d[k]                                                 (k < 3)
 *   ssim_x_bwd_h_e: F = G_cols * tmp; v_x = sign(x − y)·l1 + ((F0 + (2x)·F1) + y·F2)
 * One work-item per value (the _e kernels: 2D, x the W·C values of a row, y the row; scalar, the loops unrolled), so
 * that PoCL vectorises them across work-items: it left the earlier per-pixel kernels (a run-time channel and map loop
 * inside, conditional loads) scalar, 2.3-3.2x slower at 96² and 200²
 * (bench/results/ssim_vectorize_pocl_2026-11-27.txt).
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define RADIUS 5

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

/* One output of scipy's correlate1d loop along a line: in double, acc = m[i]·w0, then for k = 5, 4, …, 1
 * acc += (m[i − k] + m[i + k])·wk with 0.0 outside the line, rounded to float32. ``at(d)``: the line's value d steps
 * from the output's own, pos its position on the line of length len. Every load is made and a value outside the line
 * is selected away: no conditional load, which kept PoCL's vectoriser off. ``left(k, pos, len)`` / ``right(...)``: the
 * steps loaded for tap k, either clamped into the line (CORR_OFF, the rows pass: the clamp is the same for a whole row
 * of work-items) or not (CORR_COL, the columns pass: into the neighbouring row, or the margin of RADIUS·C values the
 * buffer has before and after the maps, never used; addresses that follow the work-item index in every lane). */
#define CORR_SEL(at, left, right, pos, len, w, out)                                     \
    do {                                                                                \
        double acc_ = (double)(at(0)) * w[0];                                           \
        _Pragma("unroll") for (int k_ = RADIUS; k_ >= 1; --k_) {                         \
            const double lv_ = (double)(at(left(k_, (pos), (len))));                    \
            const double rv_ = (double)(at(right(k_, (pos), (len))));                   \
            const double l_ = ((pos) - k_ >= 0) ? lv_ : 0.0;                            \
            const double r_ = ((pos) + k_ < (len)) ? rv_ : 0.0;                         \
            acc_ += (l_ + r_) * w[k_];                                                  \
        }                                                                               \
        out = (float)acc_;                                                              \
    } while (0)
#define STEP_L_CLAMPED(k, pos, len) (-min((k), (pos)))
#define STEP_R_CLAMPED(k, pos, len) (min((k), (len) - 1 - (pos)))
#define STEP_L(k, pos, len) (-(k))
#define STEP_R(k, pos, len) (k)
#define CORR_OFF(at, pos, len, w, out) CORR_SEL(at, STEP_L_CLAMPED, STEP_R_CLAMPED, pos, len, w, out)
#define CORR_COL(at, pos, len, w, out) CORR_SEL(at, STEP_L, STEP_R, pos, len, w, out)

/* Element-wise forms: per value the operations of the numpy reference (and of the per-pixel kernels they
 * replaced), one work-item per value of [H, W, C] on a 2D range (x: the W·C values of a row, y: the row), scalar, its
 * loops unrolled, so that consecutive work-items read consecutive values: PoCL vectorises them across work-items (the
 * per-pixel forms, with channel and map loops of run-time length inside, ran one work-item at a time). KMAPS (a
 * define, 5 or 3): the maps of the rows pass. */
#ifdef KMAPS
__kernel void ssim_x_rows_e(__global const float* src,   // [KMAPS, H, W, C]
                            __constant double* w,
                            const int H, const int W, const int C,
                            const int margin,
                            __global float* tmp)         // margin, then [KMAPS, H, W, C], then margin
{
    const int j = get_global_id(0), py = get_global_id(1);
    const int row = W * C, n = H * row;
    if (j >= row || py >= H) return;
    const int i = py * row + j;
    tmp += margin;
#pragma unroll
    for (int k = 0; k < KMAPS; ++k) {
#define AT(d) src[k * n + i + (d) * row]
        float v;
        CORR_OFF(AT, py, H, w, v);
#undef AT
        tmp[k * n + i] = v;
    }
}
#endif

/* The columns pass of an element-wise kernel over the K maps of tmp (a margin before them): the work-item's value i
 * (row py, column px) and f[k] = G_cols * tmp[k] at i, k < K. Returns from the kernel outside the image. */
#define COLUMNS_PASS(K)                                                                 \
    const int j = get_global_id(0), py = get_global_id(1);                              \
    const int row = W * C, n = H * row;                                                 \
    if (j >= row || py >= H) return;                                                    \
    const int i = py * row + j, px = j / C;                                             \
    tmp += margin;                                                                      \
    float f[K];                                                                         \
    _Pragma("unroll") for (int k = 0; k < (K); ++k) {                                   \
        CORR_COL(AT_COL, px, W, w, f[k]);                                               \
    }
#define AT_COL(d) tmp[k * n + i + (d) * C]

__kernel void ssim_x_fwd_h_e(__global const float* tmp,   // margin, [5, H, W, C], margin
                             const int margin,
                             __constant double* w,
                             const int H, const int W, const int C,
                             const float c1, const float c2, const float g,
                             __global float* ssim_map,    // [H, W, C]
                             __global float* d)           // [3, H, W, C]
{
    COLUMNS_PASS(5);
    const float mu_x = f[0], mu_y = f[1], s_xx = f[2], s_yy = f[3], s_xy = f[4];
    const float mu_xy = mu_x * mu_y;
    const float a1 = 2.0f * mu_xy + c1;
    const float a2 = 2.0f * (s_xy - mu_xy) + c2;
    const float mxx = mu_x * mu_x, myy = mu_y * mu_y;
    const float b1 = (mxx + myy) + c1;
    const float b2 = (((s_xx + s_yy) - mxx) - myy) + c2;
    const float m = fdiv(a1 * a2, b1 * b2);
    ssim_map[i] = m;
    const float dd = fdiv(g, b1 * b2);
    const float d_a1 = dd * a2, d_a2 = dd * a1;
    const float gm = (-g) * m;
    const float d_b1 = fdiv(gm, b1), d_b2 = fdiv(gm, b2);
    d[i] = 2.0f * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2));
    d[n + i] = d_b2;
    d[2 * n + i] = 2.0f * d_a2;
}

__kernel void ssim_x_bwd_h_e(__global const float* x, __global const float* y,  // [H, W, C]
                             __global const float* tmp,                         // margin, [3, H, W, C], margin
                             const int margin,
                             __constant double* w,
                             const int H, const int W, const int C,
                             const float l1,
                             __global float* v_x)                               // [H, W, C]
{
    COLUMNS_PASS(3);
    const float a = x[i], b = y[i];
    const float e = a - b;
    const float s = e > 0.0f ? 1.0f : (e < 0.0f ? -1.0f : (e == 0.0f ? 0.0f : e));
    const float vs = (f[0] + (2.0f * a) * f[1]) + b * f[2];
    v_x[i] = s * l1 + vs;
}
