/* downsample.cl — the box filter of a supersampled render (the mesh stage renders at f x the camera's resolution
 * and averages each f x f block, as a camera integrates a pixel), and its adjoint.
 *
 * box_down (one work-item per output pixel p = (i, j) of [H, W], C channels):
 *   y[i, j, c] = (sum over a = 0..f-1, then b = 0..f-1 of x[i f + a, j f + b, c]) / f^2   (a fixed order)
 * box_up (one work-item per input pixel q = (r, s) of [H f, W f]): the adjoint,
 *   v_x[r, s, c] = v_y[r / f, s / f, c] / f^2
 */
#include "real.h"

__kernel void box_down(__global const REAL* x,   // [H f, W f, C]
                       const int H, const int W, const int f, const int C,
                       __global REAL* y)         // [H, W, C]
{
    const int p = get_global_id(0);
    if (p >= H * W) return;
    const int i = p / W, j = p - (p / W) * W;
    const int Wf = W * f;
    const REAL w = (REAL)1 / (REAL)(f * f);
    for (int c = 0; c < C; ++c) {
        REAL s = (REAL)0;
        for (int a = 0; a < f; ++a)
            for (int b = 0; b < f; ++b) s += x[((size_t)(i * f + a) * Wf + (j * f + b)) * C + c];
        y[(size_t)p * C + c] = s * w;
    }
}

__kernel void box_up(__global const REAL* v_y,   // [H, W, C]
                     const int H, const int W, const int f, const int C,
                     __global REAL* v_x)         // [H f, W f, C]
{
    const int q = get_global_id(0);
    const int Wf = W * f;
    if (q >= H * f * Wf) return;
    const int r = q / Wf, s = q - (q / Wf) * Wf;
    const REAL w = (REAL)1 / (REAL)(f * f);
    const size_t src = ((size_t)(r / f) * W + s / f) * C;
    for (int c = 0; c < C; ++c) v_x[(size_t)q * C + c] = v_y[src + c] * w;
}

/* The capture's pixel filter (a camera's reconstruction filter, e.g. Mitsuba 3's default: a Gaussian of standard
 * deviation 0.5 pixel truncated at 4 sigma; Blender Cycles' 1.5-pixel Blackman-Harris is close): each output pixel is
 * the weighted mean of the supersamples near its centre, separably: along the rows (the x pass, C <= 4 channels per
 * work-item) then along the columns (the y pass, one value per work-item). F (a define: the supersampling factor, so
 * that the divisions by it are by a constant) samples per output pixel; ops/downsample.py.
 *
 * The weights come from the host: wt[j], j = t - l F + R in [0, F + 2 R), the weight of supersample t in the window of
 * output l (it depends on the offset only), and inv_norm[l] = 1 / (sum of the weights of output l's supersamples that
 * lie inside the image), as a film divides by its weights.
 *   down: y[l] = inv_norm[l] * sum over t in [l F - R, l F + F - 1 + R] ∩ [0, L F) of wt[t - l F + R] x[t]
 *   up (the adjoint): v_x[t] = sum over the outputs l whose window holds t of wt[t - l F + R] inv_norm[l] v_y[l],
 *     l from ceil((t - R - F + 1) / F) = floor((t - R) / F) to floor((t + R) / F)
 * rows_*: x [O, L F, C] <-> y [O, L, C], one work-item per (o, l) (down) or (o, t) (up);
 * cols_*: x [L F, K] <-> y [L, K], one work-item per (l, k) (down) or (t, k) (up).
 */
#ifndef F
#define F 1
#endif
#define FILT_MAX_C 4

/* floor((t - R) / F) for t >= 0: the numerator shifted to be non-negative before the integer division */
#define FIRST_OUTPUT(t, R) (((t) - (R) + (R) * F) / F - (R))

__kernel void gauss_rows_down(__global const REAL* src,      // x [O, L F, C]
                              const int O, const int L, const int C, const int R,
                              __global const REAL* wt,       // [F + 2 R]
                              __global const REAL* inv_norm, // [L]
                              __global REAL* dst)            // y [O, L, C]
{
    const int p = get_global_id(0);
    if (p >= O * L) return;
    const int o = p / L, l = p - o * L, LF = L * F;
    const int t0 = max(0, l * F - R), t1 = min(LF - 1, l * F + F - 1 + R);
    REAL acc[FILT_MAX_C] = {(REAL)0};
    __global const REAL* row = src + (size_t)o * LF * C;
    for (int t = t0; t <= t1; ++t) {
        const REAL w = wt[t - l * F + R];
        for (int c = 0; c < C; ++c) acc[c] += w * row[t * C + c];
    }
    const REAL n = inv_norm[l];
    for (int c = 0; c < C; ++c) dst[(size_t)p * C + c] = acc[c] * n;
}

__kernel void gauss_cols_down(__global const REAL* src,      // x [L F, K]
                              const int L, const int K, const int R,
                              __global const REAL* wt, __global const REAL* inv_norm,
                              __global REAL* dst)            // y [L, K]
{
    const int p = get_global_id(0);
    if (p >= L * K) return;
    const int l = p / K, k = p - l * K;
    const int t0 = max(0, l * F - R), t1 = min(L * F - 1, l * F + F - 1 + R);
    REAL s = (REAL)0;
    for (int t = t0; t <= t1; ++t) s += wt[t - l * F + R] * src[(size_t)t * K + k];
    dst[p] = s * inv_norm[l];
}

__kernel void gauss_rows_up(__global const REAL* src,        // v_y [O, L, C]
                            const int O, const int L, const int C, const int R,
                            __global const REAL* wt, __global const REAL* inv_norm,
                            __global REAL* dst)              // v_x [O, L F, C]
{
    const int LF = L * F;
    const int p = get_global_id(0);
    if (p >= O * LF) return;
    const int o = p / LF, t = p - o * LF;
    const int l0 = max(0, FIRST_OUTPUT(t, R)), l1 = min(L - 1, (t + R) / F);
    REAL acc[FILT_MAX_C] = {(REAL)0};
    __global const REAL* row = src + (size_t)o * L * C;
    for (int l = l0; l <= l1; ++l) {
        const REAL w = wt[t - l * F + R] * inv_norm[l];
        for (int c = 0; c < C; ++c) acc[c] += w * row[l * C + c];
    }
    for (int c = 0; c < C; ++c) dst[(size_t)p * C + c] = acc[c];
}

__kernel void gauss_cols_up(__global const REAL* src,        // v_y [L, K]
                            const int L, const int K, const int R,
                            __global const REAL* wt, __global const REAL* inv_norm,
                            __global REAL* dst)              // v_x [L F, K]
{
    const int p = get_global_id(0);
    if (p >= L * F * K) return;
    const int t = p / K, k = p - t * K;
    const int l0 = max(0, FIRST_OUTPUT(t, R)), l1 = min(L - 1, (t + R) / F);
    REAL s = (REAL)0;
    for (int l = l0; l <= l1; ++l) s += wt[t - l * F + R] * inv_norm[l] * src[(size_t)l * K + k];
    dst[p] = s;
}

/* The image and its alpha in one pass (gauss4_*): the radiance [.., 3] and the alpha [..] of a render filtered
 * together as four channels, C = 4 compiled in (float4 per sample; one instruction for the four channels, where the
 * per-array kernels above loop over a run-time channel count), NTAP = F + 2 GR taps compiled in (GR: the radius R of
 * the kernels above, a define): the same sums in the same order as the per-array kernels (t, then l, increasing),
 * bit for bit, one launch per pass instead of two.
 *   rows_down8: rgb [O, L F, 3], a [O, L F] -> tmp [O, L, 4]     (one work-item per (o, eight outputs l))
 *   cols_down:  tmp [L F, W, 4] -> rgb [L, W, 3], a [L, W]        (one work-item per (l, w))
 *   cols_upF:   v_rgb [L, W, 3], v_a [L, W] -> tmp [L F, W, 4]    (one work-item per (output l, w): its F rows t;
 *               HAS_VA: v_a given, else 0)
 *   rows_up8:   tmp [O, L, 4] -> v_rgb [O, L F, 3], v_a [O, L F]  (one work-item per (o, eight outputs' 8 F samples))
 * The intermediate tmp is [rows, columns, 4] in both directions, so a pass reads or writes one float4 per sample.
 * Several outputs per work-item (session 59; 600² -> 200², sigma 0.49: forward + adjoint 1.1-1.9x on PoCL):
 * the samples (rows_down8) or the outputs (the up passes) a work-item's results share are loaded once into private
 * memory, zero outside the row or column, and the up passes' taps follow the sample's phase r = t mod F, which fixes
 * which outputs it reads and their weights, so every loop has a compile-time count. A zero tap adds +0, so the sums
 * keep the bits of the loops that skip them (the accumulator starts at +0 and is never -0). */
#ifdef NTAP
inline REAL4 load_rgba(__global const REAL* rgb, __global const REAL* a, const size_t i)
{
    const REAL3 c = vload3(i, rgb);
    return (REAL4)(c.x, c.y, c.z, a[i]);
}

inline void store_rgba(const REAL4 v, __global REAL* rgb, __global REAL* a, const size_t i)
{
    vstore3(v.xyz, i, rgb);
    a[i] = v.w;
}

#define ROW_SPAN (7 * F + NTAP)                 /* rows_down8: the samples eight outputs read */
#define UP_DLO (FIRST_OUTPUT(0, GR))             /* up passes: the first output read, relative to the first */
#define UP_SPAN (8 + (F - 1 + GR) / F - UP_DLO) /* rows_up8: the outputs its 8 F samples read */
#define UP_SPAN1 (UP_SPAN - 7)                 /* cols_upF: the outputs one output's F rows read */

__kernel void gauss4_rows_down8(__global const REAL* rgb,      // [O, L F, 3]
                                __global const REAL* a,        // [O, L F]
                                const int O, const int L,
                                __global const REAL* wt,       // [NTAP]
                                __global const REAL* inv_norm, // [L]
                                __global REAL* dst)            // [O, L, 4]
{
    const int L8 = (L + 7) / 8;
    const int p = get_global_id(0);
    if (p >= O * L8) return;
    const int o = p / L8, l = (p - o * L8) * 8, LF = L * F, t0 = l * F - GR;
    const size_t row = (size_t)o * LF;
    REAL4 s[ROW_SPAN];
    for (int k = 0; k < ROW_SPAN; ++k) {
        const int t = t0 + k;
        s[k] = (t >= 0 && t < LF) ? load_rgba(rgb, a, row + t) : (REAL4)(0);
    }
    REAL w[NTAP];
    for (int j = 0; j < NTAP; ++j) w[j] = wt[j];
    for (int i = 0; i < 8; ++i) {
        if (l + i >= L) break;
        REAL4 acc = (REAL4)(0);
        for (int j = 0; j < NTAP; ++j) acc += w[j] * s[i * F + j];
        vstore4(acc * inv_norm[l + i], (size_t)o * L + l + i, dst);
    }
}

__kernel void gauss4_rows_up8(__global const REAL* src,        // [O, L, 4]
                              const int O, const int L,
                              __global const REAL* wt, __global const REAL* inv_norm,
                              __global REAL* v_rgb,            // [O, L F, 3]
                              __global REAL* v_a)              // [O, L F]
{
    /* the 8 F samples t = (m0 + i) F + r (i < 8, r < F) of eight outputs' footprints: sample t reads the outputs
     * l = m0 + i + d, d from FIRST_OUTPUT(r, GR) to (r + GR) / F, with the weight wt[r - d F + GR]: a pattern
     * fixed by r, so every loop below has a compile-time count and every weight a compile-time index */
    const int M8 = (L + 7) / 8;
    const int p = get_global_id(0);
    if (p >= O * M8) return;
    const int o = p / M8, m0 = (p - o * M8) * 8;
    REAL4 v[UP_SPAN];
    REAL n[UP_SPAN], w[NTAP];
    for (int j = 0; j < NTAP; ++j) w[j] = wt[j];
    for (int k = 0; k < UP_SPAN; ++k) {
        const int l = m0 + UP_DLO + k;
        const bool in = l >= 0 && l < L;
        v[k] = in ? vload4((size_t)o * L + l, src) : (REAL4)(0);
        n[k] = in ? inv_norm[l] : (REAL)0;
    }
    const size_t row = (size_t)o * L * F;
    for (int i = 0; i < 8; ++i) {
        if (m0 + i >= L) break;
        for (int r = 0; r < F; ++r) {
            REAL4 acc = (REAL4)(0);
            for (int d = FIRST_OUTPUT(r, GR); d <= (r + GR) / F; ++d)  /* a tap outside the row adds +0 */
                acc += (w[r - d * F + GR] * n[i + d - UP_DLO]) * v[i + d - UP_DLO];
            store_rgba(acc, v_rgb, v_a, row + (size_t)(m0 + i) * F + r);
        }
    }
}

__kernel void gauss4_cols_upF(__global const REAL* v_rgb,     // [L, W, 3]
#ifdef HAS_VA
                              __global const REAL* v_a,       // [L, W]
#endif
                              const int L, const int W,
                              __global const REAL* wt, __global const REAL* inv_norm,
                              __global REAL* dst)             // [L F, W, 4]
{
    /* the F rows t = m F + r of output row m's footprint, column w: as rows_up8, the outputs read and their
     * weights fixed by r, the outputs loaded once for the F rows */
    const int p = get_global_id(0);
    if (p >= L * W) return;
    const int m = p / W, w = p - m * W;
    REAL4 v[UP_SPAN1];
    REAL n[UP_SPAN1], wj[NTAP];
    for (int j = 0; j < NTAP; ++j) wj[j] = wt[j];
    for (int k = 0; k < UP_SPAN1; ++k) {
        const int l = m + UP_DLO + k;
        const bool in = l >= 0 && l < L;
        const size_t i = (size_t)(in ? l : 0) * W + w;
#ifdef HAS_VA
        v[k] = in ? load_rgba(v_rgb, v_a, i) : (REAL4)(0);
#else
        v[k] = in ? (REAL4)(vload3(i, v_rgb), (REAL)0) : (REAL4)(0);
#endif
        n[k] = in ? inv_norm[l] : (REAL)0;
    }
    for (int r = 0; r < F; ++r) {
        REAL4 acc = (REAL4)(0);
        for (int d = FIRST_OUTPUT(r, GR); d <= (r + GR) / F; ++d)  /* a tap outside the column adds +0 */
            acc += (wj[r - d * F + GR] * n[d - UP_DLO]) * v[d - UP_DLO];
        vstore4(acc, (size_t)(m * F + r) * W + w, dst);
    }
}

__kernel void gauss4_cols_down(__global const REAL* src,      // [L F, W, 4]
                               const int L, const int W,
                               __global const REAL* wt, __global const REAL* inv_norm,
                               __global REAL* rgb,            // [L, W, 3]
                               __global REAL* a)              // [L, W]
{
    const int p = get_global_id(0);
    if (p >= L * W) return;
    const int l = p / W, w = p - l * W, LF = L * F, t0 = l * F - GR;
    REAL4 acc = (REAL4)(0);
    for (int j = 0; j < NTAP; ++j) {
        const int t = t0 + j;
        if (t >= 0 && t < LF) acc += wt[j] * vload4((size_t)t * W + w, src);
    }
    store_rgba(acc * inv_norm[l], rgb, a, p);
}

#endif
