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
 * Pixel (y, x, c) of an image lives at (y·W + x)·C + c (row = W·C values). The maps live in a padded layout,
 * [K, H + 2R, S] (R = RADIUS), the value (y, j) of map k at (k·(H + 2R) + y + R)·S + MC + j with MC = R·C zeros
 * before each row and S ≥ 2·MC + row a multiple of 8 (zeros after it), R rows of zeros above and below: the zero
 * padding of both passes is then in memory, and a pass reads its 11 taps without a bound test or a select (adding the
 * 0.0 the reference adds outside: the same bits).
 *   ssim_x_maps8:  src = {x, y, x², y², xy} (padded, pads written 0)
 *   ssim_x_rows8:  tmp[k] = G_rows * src[k], k < KMAPS (5, then 3), [K, H, S] after a margin of MC values
 *   ssim_x_fwd8:   μx, μy, sxx, syy, sxy = G_cols * tmp; the SSIM map m (out, [H, W, C]) and, for the adjoint seed
 *                  g, d[0] = ∂μx, d[1] = ∂B2, d[2] = 2·∂A2 (padded, pads written 0)       (_ssim_bwd's maps)
 *   ssim_x_rows8:  tmp[k] = G_rows * d[k]                                                 (k < 3)
 *   ssim_x_bwd8:   F = G_cols * tmp; v_x = sign(x − y)·l1 + ((F0 + (2x)·F1) + y·F2)        ([H, W, C])
 * Each work-item computes 8 consecutive values of a padded row as vector lanes (double8 / float8: every lane the
 * scalar operations above): 2.8-3.7x the pass of one work-item per value, which PoCL vectorised across work-items
 * but with the bound tests and selects (bench/results/ssim_exact_lanes_pocl_2026-11-29.txt).
 */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define RADIUS 5

/* The 8 values j0 … j0 + 7 of an image row of n values (0.0 outside [0, n)). */
static inline float8 load_row8(__global const float* row, const int j0, const int n)
{
    if (j0 >= 0 && j0 + 8 <= n) return vload8(0, row + j0);
    float v[8];
    for (int e = 0; e < 8; ++e) {
        const int j = j0 + e;
        v[e] = (j >= 0 && j < n) ? row[j] : 0.0f;
    }
    return vload8(0, v);
}

/* Stores the lanes of v whose index j0 + e lies in [0, n) of an image row. */
static inline void store_row8(__global float* row, const int j0, const int n, const float8 v)
{
    if (j0 >= 0 && j0 + 8 <= n) {
        vstore8(v, 0, row + j0);
        return;
    }
    float t[8];
    vstore8(v, 0, t);
    for (int e = 0; e < 8; ++e) {
        const int j = j0 + e;
        if (j >= 0 && j < n) row[j] = t[e];
    }
}

/* -1 (true) in the lanes whose index j0 + e lies in [0, n). */
static inline int8 lanes_inside(const int j0, const int n)
{
    const int8 j = (int8)(j0) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    return (j >= (int8)(0)) & (j < (int8)(n));
}

/* One correlate1d output per lane over 8 consecutive values at p (double, the reference's order): acc = p[0]·w0, then
 * for k = 5 … 1 acc += (p[−k·step] + p[k·step])·wk; rounded to float. */
static inline float8 corr8(__global const float* p, const int step, __constant double* w)
{
    double8 acc = convert_double8(vload8(0, p)) * w[0];
#pragma unroll
    for (int k = RADIUS; k >= 1; --k) {
        acc += (convert_double8(vload8(0, p - k * step)) + convert_double8(vload8(0, p + k * step))) * w[k];
    }
    return convert_float8(acc);
}

static inline float8 fdiv8(const float8 a, const float8 b) { return convert_float8(convert_double8(a) / convert_double8(b)); }

/* 2D range: x the S / 8 lane groups of a padded row (p8 = 8·x), y the padded row (H + 2R). */
__kernel void ssim_x_maps8(__global const float* x, __global const float* y,  // [H, W, C]
                           const int H, const int W, const int C, const int S,
                           __global float* src)                                // [5, H + 2R, S]
{
    const int p8 = get_global_id(0) * 8, yy = get_global_id(1);
    const int row = W * C, rows = H + 2 * RADIUS, plane = rows * S;
    if (p8 >= S || yy >= rows) return;
    const int py = yy - RADIUS, j0 = p8 - RADIUS * C;
    float8 a = (float8)(0.0f), b = (float8)(0.0f);
    if (py >= 0 && py < H) {
        a = load_row8(x + py * row, j0, row);
        b = load_row8(y + py * row, j0, row);
    }
    __global float* o = src + yy * S + p8;
    vstore8(a, 0, o);
    vstore8(b, 0, o + plane);
    vstore8(a * a, 0, o + 2 * plane);  // float32 products, as numpy's
    vstore8(b * b, 0, o + 3 * plane);
    vstore8(a * b, 0, o + 4 * plane);
}

/* The rows pass: 2D range, x the lane groups of a padded row, y the image row (H). */
#ifdef KMAPS
__kernel void ssim_x_rows8(__global const float* src,   // [KMAPS, H + 2R, S] padded
                           __constant double* w,
                           const int H, const int C, const int S,
                           __global float* tmp)         // R·C margin, then [KMAPS, H, S], then R·C margin
{
    const int p8 = get_global_id(0) * 8, py = get_global_id(1);
    if (p8 >= S || py >= H) return;
    const int plane = (H + 2 * RADIUS) * S;
    tmp += RADIUS * C;
#pragma unroll
    for (int k = 0; k < KMAPS; ++k) {
        vstore8(corr8(src + k * plane + (py + RADIUS) * S + p8, S, w), 0, tmp + (k * H + py) * S + p8);
    }
}
#endif

/* The columns pass over the K maps of tmp at lanes p8 of row py: f[k] = G_cols * tmp[k]. */
#define COLUMNS8(K)                                                                     \
    float8 f[K];                                                                        \
    _Pragma("unroll") for (int k = 0; k < (K); ++k) {                                   \
        f[k] = corr8(tmp + (k * H + py) * S + p8, C, w);                                \
    }

__kernel void ssim_x_fwd8(__global const float* tmp,    // R·C margin, [5, H, S], R·C margin
                          __constant double* w,
                          const int H, const int W, const int C, const int S,
                          const float c1, const float c2, const float g,
                          __global float* ssim_map,     // [H, W, C]
                          __global float* d)            // [3, H + 2R, S] padded
{
    const int p8 = get_global_id(0) * 8, yy = get_global_id(1);
    const int row = W * C, rows = H + 2 * RADIUS, plane = rows * S;
    if (p8 >= S || yy >= rows) return;
    __global float* o = d + yy * S + p8;
    const int py = yy - RADIUS, j0 = p8 - RADIUS * C;
    if (py < 0 || py >= H) {  // the padding rows of the next rows pass's input
        vstore8((float8)(0.0f), 0, o);
        vstore8((float8)(0.0f), 0, o + plane);
        vstore8((float8)(0.0f), 0, o + 2 * plane);
        return;
    }
    tmp += RADIUS * C;
    COLUMNS8(5);
    const float8 mu_x = f[0], mu_y = f[1], s_xx = f[2], s_yy = f[3], s_xy = f[4];
    const float8 mu_xy = mu_x * mu_y;
    const float8 a1 = 2.0f * mu_xy + c1;
    const float8 a2 = 2.0f * (s_xy - mu_xy) + c2;
    const float8 mxx = mu_x * mu_x, myy = mu_y * mu_y;
    const float8 b1 = (mxx + myy) + c1;
    const float8 b2 = (((s_xx + s_yy) - mxx) - myy) + c2;
    const float8 m = fdiv8(a1 * a2, b1 * b2);
    store_row8(ssim_map + py * row, j0, row, m);
    const float8 dd = fdiv8((float8)(g), b1 * b2);
    const float8 d_a1 = dd * a2, d_a2 = dd * a1;
    const float8 gm = (-g) * m;
    const float8 d_b1 = fdiv8(gm, b1), d_b2 = fdiv8(gm, b2);
    const int8 in = lanes_inside(j0, row);  // the padding columns: 0
    vstore8(select((float8)(0.0f), 2.0f * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2)), in), 0, o);
    vstore8(select((float8)(0.0f), d_b2, in), 0, o + plane);
    vstore8(select((float8)(0.0f), 2.0f * d_a2, in), 0, o + 2 * plane);
}

__kernel void ssim_x_bwd8(__global const float* x, __global const float* y,  // [H, W, C]
                          __global const float* tmp,                         // R·C margin, [3, H, S], R·C margin
                          __constant double* w,
                          const int H, const int W, const int C, const int S,
                          const float l1,
                          __global float* v_x)                               // [H, W, C]
{
    const int p8 = get_global_id(0) * 8, py = get_global_id(1);
    const int row = W * C, j0 = p8 - RADIUS * C;
    if (p8 >= S || py >= H || j0 >= row || j0 + 8 <= 0) return;
    tmp += RADIUS * C;
    COLUMNS8(3);
    const float8 a = load_row8(x + py * row, j0, row), b = load_row8(y + py * row, j0, row);
    const float8 e = a - b;
    // sign(e) as numpy's: 1, -1, 0 for ±0, and NaN stays NaN
    const float8 s = select(select(select(e, (float8)(0.0f), e == (float8)(0.0f)), (float8)(-1.0f), e < (float8)(0.0f)),
                            (float8)(1.0f), e > (float8)(0.0f));
    const float8 vs = (f[0] + (2.0f * a) * f[1]) + b * f[2];
    store_row8(v_x + py * row, j0, row, s * l1 + vs);
}
