/* blend.cl — the fused raster path for per-vertex attributes: K nearest fragments → perspective-
 * correct interpolation of attributes and opacity → soft-coverage window → front-to-back
 * compositing, in one forward kernel, and its whole adjoint in one backward kernel.
 *
 * It computes exactly what raster.cl → interpolate.cl → coverage.cl → composite.cl compute
 * (ops/raster.py, ops/interpolate.py, ops/composite.py) for per-vertex features, without writing
 * a packed fragment array in between: the per-fragment work stays in registers and cache, and the
 * backward pass recomputes it from the lists. Used where the colour of a fragment is an
 * interpolated per-vertex value (unlit / emissive vertex colours, per-vertex radiance, depth or
 * any feature channel, the opaque K = 1 job); deferred shading uses the generic chain.
 *
 * Inputs: attr [N, C+1] per vertex (C features, then the opacity in the last column), the entries
 * of the tile binning (binning.cl: set-up s [E, SETUP], face [E]), background bg [C].
 * Forward, per pixel p with its K-nearest list (common/raster_lists.h), fragment i of entry e:
 *   b0 = 1 + s2 dx + s3 dy,  b1 = s4 dx + s5 dy,  b2 = 1 - b0 - b1,   (dx, dy) = p - a0
 *   w_k = b_k s_{6+k} (= b_k / z_k),  zp = 1 / (w0 + w1 + w2),  lam_k = w_k zp  (lam2 = 1 - lam0 - lam1)
 *   f_ic = sum_k lam_k attr[F[f,k], c],   ab_i = sum_k lam_k attr[F[f,k], C]
 *   win_i = 1 - exp(-sigma max(0, min_k b_k g_k))   (sigma > 0; else win_i = 1; setup_window_ex)
 *   a_i = ab_i win_i,   T_0 = 1,  T_{i+1} = T_i (1 - a_i)
 *   out_c = sum_{i<n} f_ic a_i T_i + bg_c T_n,   trans = T_n,   n = n_contrib
 *   (compositing stops after the first fragment that brings T below t_min, as composite.cl)
 *   The entry e, T_i and (sigma > 0) the window's exp(-sigma d) of each composited fragment go to
 *   scratch for the adjoint (which then needs no second exp), laid out as the
 *   CPU kernel's lanes: [tile, row pair, slot i, lane] (BLEND_SLOT), so that a pixel's slots are 16
 *   apart and the 16 pixels of a row pair sit side by side, whatever K (a [H, W, K] layout put
 *   consecutive pixels K slots apart: at K = 150 the backward pass was 1.6x slower).
 * Adjoint (one work-item per tile, its pixels and their fragments back to front; composite.cl):
 *   R_c = bg_c, G = 1;  for i = n-1 .. 0:
 *     v_f_ic = v_out_c a_i T_i,   v_a_i = T_i (sum_c v_out_c (f_ic - R_c) + v_acc G)
 *     R_c = f_ic a_i + (1 - a_i) R_c,   G = G (1 - a_i)
 *     v_ab_i = v_a_i win_i,   v_win_i = v_a_i ab_i
 *   interpolation (interpolate.cl): v_attr[F[f,k], c] += lam_k v_f_ic, v_attr[F[f,k], C] += lam_k v_ab_i,
 *     v_lam0 = sum_c v_f_ic (a0_c - a2_c) + v_ab_i (a0_C - a2_C), v_lam1 likewise with a1
 *   geometry: v_lam, v_win -> the entry's moments (common/raster_adjoint.h).
 * No float atomics: the tile's work-item owns the records of the tile's (tile, face) entries,
 * partial [E, pstride] = (moments [MOMENTS], then [3, C+1] for the corner attributes), zeroed first.
 * Then per face (blend_face_grad): its entries' records summed, the moments turned into the adjoint
 * of its screen vertices once (moments_geom_vjp; the moments are linear and relative to the face's
 * a0, so the entries' sums can be added), written per face corner; for a soup with face f on
 * vertices 3f .. 3f + 2 those are the vertex adjoints, otherwise gather_corner sums them per vertex.
 * Two kernel shapes, same arithmetic, tested against each other:
 *   pixel / blend_bwd   scalar per pixel (GPU-shaped forward: one work-item per pixel);
 *   rows16              CPU-shaped: the 16 pixels of two tile rows are the lanes of 16-wide vectors,
 *                       for the lists (rows16_lists), the blend and the adjoint. A slot's 16 entries
 *                       differ per lane: their set-ups (rows of entry_setup) and the corner
 *                       attributes of their faces (face_attr [M, 16], blend_face_attr) are loaded as
 *                       16 rows and transposed in registers (load_rows16), and the slot's per-lane
 *                       contributions (moments, then the corner attributes' adjoint: C <= 4 fits 32)
 *                       are transposed back and added to each lane's entry record as two 16-wide
 *                       vectors. On PoCL (AVX-512) blend_bwd_rows16 at 400^2, 100k faces, K = 30
 *                       took 27-30 ms with 16-lane gathers and per-lane scalar adds, 17 ms so.
 *                       The adjoint walks a tile's pixels in one of two lane schedules, chosen per
 *                       tile (two tile rows at a time, or a queue of pixels: blend_bwd_rows16).
 */
#pragma OPENCL FP_CONTRACT OFF /* the same depths and barycentrics as raster.cl */

#include "real.h"
#include "raster_adjoint.h" /* fragment_moments, pixel_list, rows16_lists, setup_window_ex */

#ifndef TILE
#define TILE 8
#endif
#if TILE != 8
#error "blend.cl: the scratch layout and the rows16 kernel assume 8x8 tiles"
#endif
/* scratch index of slot i of pixel (x, y) in tile t: [t, (y & 7) >> 1, i, (x & 7) + 8 (y & 1)] */
#define BLEND_SLOT(t, x, y, i, K) \
    ((((long)(t) * 4 + (((y) & 7) >> 1)) * (K) + (i)) * 16 + ((x) & 7) + (((y) & 1) << 3))
#ifndef K_MAX
#define K_MAX 1
#endif
#ifndef C_MAX
#define C_MAX 4
#endif
/* V_ACC: the adjoint of the accumulated alpha v_acc [H, W] is given (else it is 0 and the kernels
 * have no v_acc parameter) */
#ifdef V_ACC
#define V_ACC_AT(pix) v_acc[pix]
#else
#define V_ACC_AT(pix) ((REAL)0)
#endif
#ifndef BWD_SCHEDULE
#define BWD_SCHEDULE 0 /* blend_bwd_rows16: 0 per tile, 1 row pairs, 2 queue */
#endif

/* Interpolates, windows and composites the list el[i * stride] (i < cnt) of pixel pix at (px, py). */
inline void blend_pixel(const int* el, int stride, int cnt, REAL px, REAL py, int pix, long slot0,
                        __global const int* entry_face, __global const REAL* entry_setup,
                        __global const int* F, __global const REAL* attr, int C,
                        __global const REAL* bg, REAL sigma, REAL t_min,
                        __global REAL* out, __global REAL* trans, __global int* n_contrib,
                        __global int* s_entry, __global REAL* s_T, __global REAL* s_ex)
{
    const int CA = C + 1;
    REAL acc[C_MAX];
    for (int c = 0; c < C; ++c) acc[c] = (REAL)0;
    REAL T = (REAL)1;
    int n = 0;
    for (int i = 0; i < cnt; ++i) {
        const int e = el[i * stride];
        __global const REAL* s = entry_setup + e * SETUP;
        const REAL dx = px - s[0], dy = py - s[1];
        const REAL b0 = (REAL)1 + s[2] * dx + s[3] * dy;
        const REAL b1 = s[4] * dx + s[5] * dy;
        const REAL b2 = (REAL)1 - b0 - b1;
        const REAL w0 = b0 * s[6], w1 = b1 * s[7], w2 = b2 * s[8];
        const REAL zp = (REAL)1 / (w0 + w1 + w2);
        const REAL l0 = w0 * zp, l1 = w1 * zp, l2 = (REAL)1 - l0 - l1;
        const int f = entry_face[e];
        __global const REAL* a0 = attr + F[3 * f] * CA;
        __global const REAL* a1 = attr + F[3 * f + 1] * CA;
        __global const REAL* a2 = attr + F[3 * f + 2] * CA;
        REAL a = l0 * a0[C] + l1 * a1[C] + l2 * a2[C];
        if (sigma > (REAL)0) {
            int kk;
            REAL dm, ex;
            a *= setup_window_ex(s, b0, b1, b2, sigma, &kk, &dm, &ex);
            s_ex[slot0 + 16 * i] = ex;  /* the adjoint reuses it (no second exp) */
        }
        const REAL wgt = a * T;
        for (int c = 0; c < C; ++c) acc[c] += (l0 * a0[c] + l1 * a1[c] + l2 * a2[c]) * wgt;
        s_entry[slot0 + 16 * i] = e;
        s_T[slot0 + 16 * i] = T;
        T *= (REAL)1 - a;
        n = i + 1;
        if (T < t_min) break;
    }
    for (int c = 0; c < C; ++c) out[pix * C + c] = acc[c] + bg[c] * T;
    trans[pix] = T;
    n_contrib[pix] = n;
}

/* GPU-shaped: one work-item per pixel, one 8x8 work-group per tile. */
__kernel void blend_fwd(__global const int* tile_off,      // [T + 1]
                        __global const int* entry_order,   // [E]  (bin_depth_order)
                        __global const int* entry_face,    // [E]
                        __global const REAL* entry_setup,  // [E, SETUP]
                        __global const int* entry_rows,    // [E]
                        __global const int* F,             // [M, 3]
                        __global const REAL* attr,         // [N, C + 1]
                        __global const REAL* bg,           // [C]
                        const int width, const int height, const int tiles_x,
                        const int K, const REAL far, const int C, const REAL sigma, const REAL t_min,
                        __global REAL* out,                // [H, W, C]
                        __global REAL* trans,              // [H, W]
                        __global int* n_contrib,           // [H, W]
                        __global int* count,               // [H, W]  fragments found (<= K)
                        __global int* s_entry,             // [T * 4, K, 16]  entry of composited slot i
                        __global REAL* s_T,                // [T * 4, K, 16]  T_i of composited slot i
                        __global REAL* s_ex)               // [T * 4, K, 16]  exp(-sigma d) of slot i (sigma > 0)
{
    const int tx = get_group_id(0), ty = get_group_id(1);
    const int x = tx * TILE + get_local_id(0), y = ty * TILE + get_local_id(1);
    if (x >= width || y >= height) return;
    const int t = ty * tiles_x + tx;
    const REAL px = (REAL)x + (REAL)0.5, py = (REAL)y + (REAL)0.5;
    REAL dk[K_MAX];
    int fk[K_MAX], ek[K_MAX];
    const int cnt = pixel_list(tile_off, entry_order, entry_face, entry_setup, entry_rows, t, px, py, y, K, far, dk, fk, ek);
    const int pix = y * width + x;
    count[pix] = cnt;
    blend_pixel(ek, 1, cnt, px, py, pix, BLEND_SLOT(t, x, y, 0, K), entry_face, entry_setup, F, attr, C, bg, sigma, t_min,
                out, trans, n_contrib, s_entry, s_T, s_ex);
}


#if TILE == 8
/* ---- 16-lane (CPU-shaped) blending: the lanes are the 16 pixels of two rows of a tile ---------- */

/* In-register 16 x 16 transpose: r[l] (lane l's 16 values) <-> r[j] (value j of the 16 lanes).
 * Four rounds of off-diagonal b x b block swaps (b = 8, 4, 2, 1), 16 two-vector shuffles each:
 *   rows i, i + b (i & b = 0):  r_i[j] <- j & b ? r_{i+b}[j - b] : r_i[j],
 *                               r_{i+b}[j] <- j & b ? r_{i+b}[j] : r_i[j + b].
 * Constant shuffles: __builtin_shufflevector where the compiler has it (clang: PoCL, Intel,
 * most GPU drivers; one permute instruction each), else OpenCL's shuffle2. */
#if defined(__clang__)
#define SHUF16(x, y, m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf) \
    __builtin_shufflevector(x, y, m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf)
#else
#ifdef REAL_FP64
#define SHUF16(x, y, m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf) \
    shuffle2(x, y, (ulong16)(m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf))
#else
#define SHUF16(x, y, m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf) \
    shuffle2(x, y, (uint16)(m0, m1, m2, m3, m4, m5, m6, m7, m8, m9, ma, mb, mc, md, me, mf))
#endif
#endif
#define TRANSPOSE_PAIR8(r, i) { const REAL16 x_ = (r)[i], y_ = (r)[(i) + 8]; \
    (r)[i] = SHUF16(x_, y_, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23); \
    (r)[(i) + 8] = SHUF16(x_, y_, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31); }
#define TRANSPOSE_PAIR4(r, i) { const REAL16 x_ = (r)[i], y_ = (r)[(i) + 4]; \
    (r)[i] = SHUF16(x_, y_, 0, 1, 2, 3, 16, 17, 18, 19, 8, 9, 10, 11, 24, 25, 26, 27); \
    (r)[(i) + 4] = SHUF16(x_, y_, 4, 5, 6, 7, 20, 21, 22, 23, 12, 13, 14, 15, 28, 29, 30, 31); }
#define TRANSPOSE_PAIR2(r, i) { const REAL16 x_ = (r)[i], y_ = (r)[(i) + 2]; \
    (r)[i] = SHUF16(x_, y_, 0, 1, 16, 17, 4, 5, 20, 21, 8, 9, 24, 25, 12, 13, 28, 29); \
    (r)[(i) + 2] = SHUF16(x_, y_, 2, 3, 18, 19, 6, 7, 22, 23, 10, 11, 26, 27, 14, 15, 30, 31); }
#define TRANSPOSE_PAIR1(r, i) { const REAL16 x_ = (r)[i], y_ = (r)[(i) + 1]; \
    (r)[i] = SHUF16(x_, y_, 0, 16, 2, 18, 4, 20, 6, 22, 8, 24, 10, 26, 12, 28, 14, 30); \
    (r)[(i) + 1] = SHUF16(x_, y_, 1, 17, 3, 19, 5, 21, 7, 23, 9, 25, 11, 27, 13, 29, 15, 31); }
inline void transpose16(REAL16* r)
{
    TRANSPOSE_PAIR8(r, 0) TRANSPOSE_PAIR8(r, 1) TRANSPOSE_PAIR8(r, 2) TRANSPOSE_PAIR8(r, 3)
    TRANSPOSE_PAIR8(r, 4) TRANSPOSE_PAIR8(r, 5) TRANSPOSE_PAIR8(r, 6) TRANSPOSE_PAIR8(r, 7)
    TRANSPOSE_PAIR4(r, 0) TRANSPOSE_PAIR4(r, 1) TRANSPOSE_PAIR4(r, 2) TRANSPOSE_PAIR4(r, 3)
    TRANSPOSE_PAIR4(r, 8) TRANSPOSE_PAIR4(r, 9) TRANSPOSE_PAIR4(r, 10) TRANSPOSE_PAIR4(r, 11)
    TRANSPOSE_PAIR2(r, 0) TRANSPOSE_PAIR2(r, 1) TRANSPOSE_PAIR2(r, 4) TRANSPOSE_PAIR2(r, 5)
    TRANSPOSE_PAIR2(r, 8) TRANSPOSE_PAIR2(r, 9) TRANSPOSE_PAIR2(r, 12) TRANSPOSE_PAIR2(r, 13)
    TRANSPOSE_PAIR1(r, 0) TRANSPOSE_PAIR1(r, 2) TRANSPOSE_PAIR1(r, 4) TRANSPOSE_PAIR1(r, 6)
    TRANSPOSE_PAIR1(r, 8) TRANSPOSE_PAIR1(r, 10) TRANSPOSE_PAIR1(r, 12) TRANSPOSE_PAIR1(r, 14)
}

/* Lane l's 16 values from row e.l of p (row stride `stride`, 16 readable values per row), as
 * r[j] = value j of the 16 lanes: 16 row loads and a transpose (on CPUs much faster than 16-lane
 * gathers of each value). */
inline void load_rows16(__global const REAL* p, int stride, int16 e, REAL16* r)
{
    r[0] = vload16(0, p + e.s0 * stride); r[1] = vload16(0, p + e.s1 * stride);
    r[2] = vload16(0, p + e.s2 * stride); r[3] = vload16(0, p + e.s3 * stride);
    r[4] = vload16(0, p + e.s4 * stride); r[5] = vload16(0, p + e.s5 * stride);
    r[6] = vload16(0, p + e.s6 * stride); r[7] = vload16(0, p + e.s7 * stride);
    r[8] = vload16(0, p + e.s8 * stride); r[9] = vload16(0, p + e.s9 * stride);
    r[10] = vload16(0, p + e.sa * stride); r[11] = vload16(0, p + e.sb * stride);
    r[12] = vload16(0, p + e.sc * stride); r[13] = vload16(0, p + e.sd * stride);
    r[14] = vload16(0, p + e.se * stride); r[15] = vload16(0, p + e.sf * stride);
    transpose16(r);
}

/* The fragments of entries e (one per lane) at the lanes' pixel centres: the set-up s [16] (SETUP
 * values, rows of entry_setup, which the binning pads to be readable 16 wide), (dx, dy), screen
 * barycentrics b [3], depth zp and perspective-correct l [3], with the operations (and so the
 * roundings) of blend_pixel. */
inline void fragment16(__global const REAL* entry_setup, int16 e, REAL16 px, REAL16 py, REAL16* s,
                       REAL16* dx, REAL16* dy, REAL16* b, REAL16* zp, REAL16* l)
{
    load_rows16(entry_setup, SETUP, e, s);
    *dx = px - s[0];
    *dy = py - s[1];
    b[0] = (REAL)1 + s[2] * *dx + s[3] * *dy;
    b[1] = s[4] * *dx + s[5] * *dy;
    b[2] = (REAL)1 - b[0] - b[1];
    const REAL16 w0 = b[0] * s[6], w1 = b[1] * s[7], w2 = b[2] * s[8];
    *zp = (REAL)1 / (w0 + w1 + w2);
    l[0] = w0 * *zp;
    l[1] = w1 * *zp;
    l[2] = (REAL)1 - l[0] - l[1];
}

/* setup_window_arg in lanes: *kk = the nearest soft edge, returns its distance d_k* */
inline REAL16 window_arg16(const REAL16* s, const REAL16* b, int16* kk)
{
    const REAL16 hard = (REAL16)(HARD_EDGE_DISTANCE);
    const REAL16 d0 = select(b[0] * s[9], hard, s[9] < (REAL)0);
    const REAL16 d1 = select(b[1] * s[10], hard, s[10] < (REAL)0);
    const REAL16 d2 = select(b[2] * s[11], hard, s[11] < (REAL)0);
    const MASK16 m1 = d1 < d0;
    REAL16 dm = select(d0, d1, m1);
    int16 k = select((int16)0, (int16)1, CONVERT_INT16(m1));
    const MASK16 m2 = d2 < dm;
    dm = select(dm, d2, m2);
    *kk = select(k, (int16)2, CONVERT_INT16(m2));
    return dm;
}

/* The rows16 kernels' per-face attributes: face_attr [M, 16] = attr of the face's corners
 * [3, C + 1], then zeros (C <= 4), so that the 16 lanes load them as rows (load_rows16). */
__kernel void blend_face_attr(__global const int* F,           // [M, 3]
                              __global const REAL* attr,       // [N, C + 1]
                              const int C, const int num_faces,
                              __global REAL* face_attr)        // [M, 16]
{
    const int f = get_global_id(0);
    if (f >= num_faces) return;
    const int CA = C + 1;
    REAL r[16];
    for (int q = 0; q < 16; ++q) r[q] = (REAL)0;
    for (int k = 0; k < 3; ++k) {
        __global const REAL* a = attr + F[3 * f + k] * CA;
        for (int c = 0; c < CA; ++c) r[k * CA + c] = a[c];
    }
    vstore16(vload16(0, r), f, face_attr);
}

/* CPU-shaped: one work-item per two rows of an 8x8 tile, the 16 pixels' lists built in vector
 * lanes (rows16_lists), then blended in the same lanes (set-ups and attributes loaded as rows and
 * transposed); the scratch slots of the row pair are 16-lane vectors. */
__kernel void blend_fwd_rows16(__global const int* tile_off,      // [T + 1]
                               __global const int* entry_order,   // [E]  (bin_depth_order)
                               __global const int* entry_face,    // [E]
                               __global const REAL* entry_setup,  // [E, SETUP]
                               __global const int* entry_rows,    // [E]
                               __global const REAL* face_attr,    // [M, 16]  (blend_face_attr)
                               __global const REAL* bg,           // [C]
                               const int width, const int height, const int tiles_x,
                               const int K, const REAL far, const int C, const REAL sigma, const REAL t_min,
                               __global REAL* out,                // [H, W, C]
                               __global REAL* trans,              // [H, W]
                               __global int* n_contrib,           // [H, W]
                               __global int* count,               // [H, W]
                               __global int* s_entry,             // [T * 4, K, 16]
                               __global REAL* s_T,                // [T * 4, K, 16]
                               __global REAL* s_ex)               // [T * 4, K, 16]  (sigma > 0)
{
    const int tx = get_global_id(0), pair = get_global_id(1);
    const int ty = pair >> 2;
    const int y0 = ty * TILE + 2 * (pair & 3);
    if (y0 >= height) return;
    const int x0 = tx * TILE;
    const int t = ty * tiles_x + tx;
    ROWS16_LANES(x0, y0, width, height, px, py, inimg);
    REAL16 dk[K_MAX];
    int16 ek[K_MAX];
    const int16 cnt16 = rows16_lists(tile_off, entry_order, entry_face, entry_setup, entry_rows, t, pair & 3, px, py, inimg, K, far, dk, ek, face_attr);
    const int CA = C + 1;
    REAL16 acc[C_MAX];
    for (int c = 0; c < C; ++c) acc[c] = (REAL16)0;
    REAL16 T = (REAL16)1;
    int16 n16 = (int16)0, alive = (int16)(-1);
    const int16 e_safe = (int16)tile_off[t];  /* lanes past their list read a valid entry */
    const long slot0 = BLEND_SLOT(t, x0, y0, 0, K);
    const int cmax = max_i16(cnt16);
    for (int i = 0; i < cmax; ++i) {
        const int16 acti = ((int16)i < cnt16) & alive;
        if (!any_i16(acti)) break;
        const MASK16 act = CONVERT_MASK16(acti);
        const int16 e = select(e_safe, ek[i], acti);
        REAL16 s[16], A[16], b[3], l[3], dx, dy, zp;
        fragment16(entry_setup, e, px, py, s, &dx, &dy, b, &zp, l);
        load_rows16(face_attr, 16, gather16i(entry_face, e), A);  /* A[k CA + c]: attribute c of the face's corner k */
        REAL16 a = l[0] * A[C] + l[1] * A[CA + C] + l[2] * A[2 * CA + C];
        if (sigma > (REAL)0) {
            int16 kk;
            const REAL16 dm = window_arg16(s, b, &kk);
            const REAL16 ex = exp(-sigma * fmax(dm, (REAL)0));
            a *= (REAL)1 - ex;
            vstore16(ex, 0, s_ex + slot0 + 16 * i);  /* the adjoint reuses it (no second exp) */
        }
        const REAL16 wgt = a * T;
        for (int c = 0; c < C; ++c) {
            const REAL16 fc = l[0] * A[c] + l[1] * A[CA + c] + l[2] * A[2 * CA + c];
            acc[c] = select(acc[c], acc[c] + fc * wgt, act);
        }
        vstore16(e, 0, s_entry + slot0 + 16 * i);
        vstore16(T, 0, s_T + slot0 + 16 * i);
        T = select(T, T * ((REAL)1 - a), act);
        n16 = select(n16, (int16)(i + 1), acti);
        alive &= CONVERT_INT16(T >= t_min);
    }
    for (int ln = 0; ln < 16; ++ln) {
        const int x = x0 + (ln & 7), y = y0 + (ln >> 3);
        if (x >= width || y >= height) continue;
        const int pix = y * width + x;
        const REAL Tl = ((const REAL*)&T)[ln];
        for (int c = 0; c < C; ++c) out[pix * C + c] = ((const REAL*)&acc[c])[ln] + bg[c] * Tl;
        trans[pix] = Tl;
        n_contrib[pix] = ((const int*)&n16)[ln];
        count[pix] = ((const int*)&cnt16)[ln];
    }
}
#endif

/* The adjoint kernels' records of tile entries [e0, e1) (partial [E, pstride]), zeroed before the
 * tile's pixels (entries without fragments keep zeros: blend_face_grad sums every entry). */
inline void tile_records_zero(int e0, int e1, __global REAL* partial, int pstride)
{
    for (long q = (long)e0 * pstride; q < (long)e1 * pstride; ++q) partial[q] = (REAL)0;
}

/* Per face, after the tile pass: the records of its entries summed (moments, then the corner
 * attributes' adjoint [3, C + 1]), the moments turned into the adjoint of the face's screen
 * vertices once (moments_geom_vjp: the moments of all entries are relative to the same a0), both
 * written per face corner: v_attr_corner [M, 3, C + 1], v_vs_corner [M, 3, 3]. For a soup whose
 * face f has the vertices 3f, 3f + 1, 3f + 2 these are the per-vertex adjoints; otherwise
 * gather_corner (fragment_bwd.cl) sums them per vertex. */
#ifndef FACE_GRAD_AHEAD
#define FACE_GRAD_AHEAD 8 /* blend_face_grad prefetches the records of face f + 8 (800^2, 1M faces: 25.3 -> 22.4 ms) */
#endif
__kernel void blend_face_grad(__global const int* face_off,      // [M + 1]
                              __global const int* face_entries,  // [E]
                              __global const REAL* partial,      // [E, pstride]
                              const int pstride,
                              __global const REAL* vs,           // [N, 3]
                              __global const int* F,             // [M, 3]
                              const int C, const int num_faces,
                              __global REAL* v_attr_corner,      // [M, 3, C + 1]
                              __global REAL* v_vs_corner)        // [M, 3, 3]
{
    const int f = get_global_id(0);
    if (f >= num_faces) return;
    const int CA = C + 1, R = MOMENTS + 3 * CA;
    const int j0 = face_off[f], j1 = face_off[f + 1];
    if (f + FACE_GRAD_AHEAD < num_faces) {  /* the records of a face a few work-items ahead (scattered) */
        const int fa = f + FACE_GRAD_AHEAD;
        for (int j = face_off[fa]; j < face_off[fa + 1]; ++j) {
            __global const REAL* p = partial + (long)face_entries[j] * pstride;
            PREFETCH_LINE(p);
            PREFETCH_LINE(p + pstride - 1);
        }
    }
    REAL r[MOMENTS + 3 * (C_MAX + 1)];
    if (pstride == 32) {  /* rows16 records: two 16-wide rows */
        REAL16 lo = (REAL16)0, hi = (REAL16)0;
        for (int j = j0; j < j1; ++j) {
            __global const REAL* p = partial + (long)face_entries[j] * 32;
            lo += vload16(0, p);
            hi += vload16(1, p);
        }
        vstore16(lo, 0, r);
        for (int q = 16; q < R; ++q) r[q] = ((const REAL*)&hi)[q - 16];
    } else {
        for (int q = 0; q < R; ++q) r[q] = (REAL)0;
        for (int j = j0; j < j1; ++j) {
            __global const REAL* p = partial + (long)face_entries[j] * pstride;
            for (int q = 0; q < R; ++q) r[q] += p[q];
        }
    }
    REAL g[9];
    if (j0 < j1) moments_geom_vjp(vs, F, f, r, g);  /* faces with entries are not degenerate */
    else for (int q = 0; q < 9; ++q) g[q] = (REAL)0;
    for (int q = 0; q < 9; ++q) v_vs_corner[9L * f + q] = g[q];
    for (int q = 0; q < 3 * CA; ++q) v_attr_corner[(long)f * 3 * CA + q] = j0 < j1 ? r[MOMENTS + q] : (REAL)0;
}

__kernel void blend_bwd(__global const int* tile_off,      // [T + 1]
                        __global const int* entry_face,    // [E]
                        __global const REAL* entry_setup,  // [E, SETUP]
                        __global const int* F,             // [M, 3]
                        __global const REAL* attr,         // [N, C + 1]
                        __global const REAL* bg,           // [C]
                        __global const int* n_contrib,     // [H, W]
                        __global const int* s_entry,       // [T * 4, K, 16]
                        __global const REAL* s_T,          // [T * 4, K, 16]
                        __global const REAL* s_ex,         // [T * 4, K, 16]  (sigma > 0)
                        __global const REAL* v_out,        // [H, W, C]
#ifdef V_ACC
                        __global const REAL* v_acc,        // [H, W]
#endif
                        const int C, const int K, const REAL sigma,
                        const int width, const int height, const int tiles_x, const int num_tiles,
                        const int pstride,
                        __global REAL* partial,            // [E, pstride]: moments, then [3, C + 1]
                        __global REAL* v_sigma_tile)       // [T]
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int CA = C + 1;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    tile_records_zero(e0, e1, partial, pstride);
    REAL vsig = (REAL)0;
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int xe = min(width, tx * TILE + TILE), ye = min(height, ty * TILE + TILE);
    for (int y = ty * TILE; y < ye; ++y)
        for (int x = tx * TILE; x < xe; ++x) {
            const int pix = y * width + x;
            const int n = n_contrib[pix];
            if (n == 0) continue;
            REAL vo[C_MAX], R[C_MAX];
            for (int c = 0; c < C; ++c) { vo[c] = v_out[pix * C + c]; R[c] = bg[c]; }
            const REAL va = V_ACC_AT(pix);
            REAL G = (REAL)1;
            const REAL px = (REAL)x + (REAL)0.5, py = (REAL)y + (REAL)0.5;
            const long slot0 = BLEND_SLOT(t, x, y, 0, K);
            for (int i = n - 1; i >= 0; --i) {
                const int e = s_entry[slot0 + 16 * i];
                const REAL T = s_T[slot0 + 16 * i];
                __global const REAL* s = entry_setup + e * SETUP;
                const REAL dx = px - s[0], dy = py - s[1];
                const REAL b0 = (REAL)1 + s[2] * dx + s[3] * dy;
                const REAL b1 = s[4] * dx + s[5] * dy;
                const REAL b2 = (REAL)1 - b0 - b1;
                const REAL w0 = b0 * s[6], w1 = b1 * s[7], w2 = b2 * s[8];
                const REAL zp = (REAL)1 / (w0 + w1 + w2);
                const REAL l0 = w0 * zp, l1 = w1 * zp, l2 = (REAL)1 - l0 - l1;
                int kk = 0;
                REAL dm = (REAL)0, ex = (REAL)0, win = (REAL)1;
                if (sigma > (REAL)0) {
                    dm = setup_window_arg(s, b0, b1, b2, &kk);
                    ex = s_ex[slot0 + 16 * i];
                    win = (REAL)1 - ex;
                }
                const int f = entry_face[e];
                __global const REAL* a0 = attr + F[3 * f] * CA;
                __global const REAL* a1 = attr + F[3 * f + 1] * CA;
                __global const REAL* a2 = attr + F[3 * f + 2] * CA;
                const REAL ab = l0 * a0[C] + l1 * a1[C] + l2 * a2[C];
                const REAL a = ab * win;
                const REAL wgt = a * T;
                REAL dot = (REAL)0, g0 = (REAL)0, g1 = (REAL)0;
                for (int c = 0; c < C; ++c) {
                    const REAL fc = l0 * a0[c] + l1 * a1[c] + l2 * a2[c];
                    dot += vo[c] * (fc - R[c]);
                    R[c] = fc * a + ((REAL)1 - a) * R[c];
                    g0 += vo[c] * (a0[c] - a2[c]);
                    g1 += vo[c] * (a1[c] - a2[c]);
                }
                const REAL v_a = T * (dot + va * G);
                G *= (REAL)1 - a;
                const REAL v_ab = v_a * win;
                const REAL v_win = sigma > (REAL)0 ? v_a * ab : (REAL)0;
                __global REAL* m = partial + (long)e * pstride;
                __global REAL* d = m + MOMENTS;
                for (int c = 0; c < C; ++c) {
                    const REAL gc = vo[c] * wgt;
                    d[c] += l0 * gc;
                    d[CA + c] += l1 * gc;
                    d[2 * CA + c] += l2 * gc;
                }
                d[C] += l0 * v_ab;
                d[CA + C] += l1 * v_ab;
                d[2 * CA + C] += l2 * v_ab;
                const REAL vl0 = wgt * g0 + v_ab * (a0[C] - a2[C]);
                const REAL vl1 = wgt * g1 + v_ab * (a1[C] - a2[C]);
                vsig += fragment_moments(s, dx, dy, b0, b1, b2, l0, l1, zp, vl0, vl1, (REAL)0, v_win, sigma,
                                         kk, dm, ex, m);
            }
        }
    v_sigma_tile[t] = vsig;
}

#if TILE == 8
/* One slot of 16 pixels in the CPU-shaped adjoint: lane l composites entry e.l at pixel centre
 * (px.l, py.l) with transmittance T.l (and exp(-sigma d) ex.l) in front of it, act.l set; R, G
 * (the colour and transmittance behind, per lane) and vsig are updated. The arithmetic of blend_bwd
 * in lanes (set-ups and corner attributes loaded as rows and transposed, composite and
 * interpolation adjoint, moments), then the slot's contributions transposed into per-lane records
 * and added to the lanes' entries one lane at a time (lanes may share an entry). */
inline void bwd_slot16(__global const int* entry_face, __global const REAL* entry_setup,
                       __global const REAL* face_attr, int C, REAL sigma, int16 acti, int16 e, REAL16 T,
                       REAL16 ex, REAL16 px, REAL16 py, const REAL16* vo, REAL16 va, REAL16* R, REAL16* G,
                       REAL16* vsig, __global REAL* partial, int pstride)
{
    const int CA = C + 1;
    const MASK16 act = CONVERT_MASK16(acti);
    REAL16 s[16], A[16], b[3], l[3], dx, dy, zp;
    fragment16(entry_setup, e, px, py, s, &dx, &dy, b, &zp, l);
    load_rows16(face_attr, 16, gather16i(entry_face, e), A);
    int16 kk = (int16)0;
    REAL16 dm = (REAL16)0, win = (REAL16)1;
    if (sigma > (REAL)0) {
        dm = window_arg16(s, b, &kk);
        win = (REAL)1 - ex;
    }
    const REAL16 a0C = A[C], a1C = A[CA + C], a2C = A[2 * CA + C];
    const REAL16 ab = l[0] * a0C + l[1] * a1C + l[2] * a2C;
    const REAL16 a = ab * win;
    const REAL16 wgt = a * T;
    REAL16 dot = (REAL16)0, g0 = (REAL16)0, g1 = (REAL16)0;
    for (int c = 0; c < C; ++c) {
        const REAL16 a0c = A[c], a1c = A[CA + c], a2c = A[2 * CA + c];
        const REAL16 fc = l[0] * a0c + l[1] * a1c + l[2] * a2c;
        dot += vo[c] * (fc - R[c]);
        R[c] = select(R[c], fc * a + ((REAL)1 - a) * R[c], act);
        g0 += vo[c] * (a0c - a2c);
        g1 += vo[c] * (a1c - a2c);
    }
    const REAL16 v_a = T * (dot + va * *G);
    *G = select(*G, *G * ((REAL)1 - a), act);
    const REAL16 v_ab = v_a * win;
    const REAL16 v_win = sigma > (REAL)0 ? v_a * ab : (REAL16)0;
    const REAL16 vl0 = wgt * g0 + v_ab * (a0C - a2C);
    const REAL16 vl1 = wgt * g1 + v_ab * (a1C - a2C);
    /* fragment_moments in lanes (v_zp = 0) */
    const REAL16 base = vl0 * l[0] + vl1 * l[1];
    const REAL16 vw0 = (vl0 - base) * zp, vw1 = (vl1 - base) * zp, vw2 = -base * zp;
    const REAL16 vb0 = vw0 * s[6], vb1 = vw1 * s[7], vb2 = vw2 * s[8];
    const MASK16 wnd = act & (v_win != (REAL)0) & (dm > (REAL)0) & (dm < HARD_EDGE_DISTANCE);
    const REAL16 vd = select((REAL16)0, v_win * sigma * ex, wnd);
    *vsig += select((REAL16)0, v_win * dm * ex, wnd);
    const REAL16 u0 = vb0 + select((REAL16)0, vd * s[9], CONVERT_MASK16(kk == 0));
    const REAL16 u1 = vb1 + select((REAL16)0, vd * s[10], CONVERT_MASK16(kk == 1));
    const REAL16 u2 = vb2 + select((REAL16)0, vd * s[11], CONVERT_MASK16(kk == 2));
    /* the slot's contributions, one row per partial-sum slot of the entry record */
    REAL16 P[32];
    P[0] = u0; P[1] = u0 * dx; P[2] = u0 * dy;
    P[3] = u1; P[4] = u1 * dx; P[5] = u1 * dy;
    P[6] = u2; P[7] = u2 * dx; P[8] = u2 * dy;
    P[9] = vb0 * b[0] + vb1 * b[1] + vb2 * b[2];
    const REAL16 mw = vd * dm;
    P[10] = select((REAL16)0, mw, CONVERT_MASK16(kk == 0));
    P[11] = select((REAL16)0, mw, CONVERT_MASK16(kk == 1));
    P[12] = select((REAL16)0, mw, CONVERT_MASK16(kk == 2));
    P[13] = vw0 * b[0]; P[14] = vw1 * b[1]; P[15] = vw2 * b[2];
    for (int q = 16; q < 32; ++q) P[q] = (REAL16)0;
    for (int c = 0; c < C; ++c) {
        const REAL16 gc = vo[c] * wgt;
        P[16 + c] = l[0] * gc;
        P[16 + CA + c] = l[1] * gc;
        P[16 + 2 * CA + c] = l[2] * gc;
    }
    P[16 + C] = l[0] * v_ab;
    P[16 + CA + C] = l[1] * v_ab;
    P[16 + 2 * CA + C] = l[2] * v_ab;
    transpose16(P);
    transpose16(P + 16);  /* now P[ln], P[16 + ln]: lane ln's record */
    int el[16], al[16];
    vstore16(e, 0, el);
    vstore16(acti, 0, al);
    for (int ln = 0; ln < 16; ++ln) {
        if (!al[ln]) continue;
        __global REAL* rec = partial + (long)el[ln] * pstride;
        vstore16(vload16(0, rec) + P[ln], 0, rec);
        vstore16(vload16(0, rec + 16) + P[16 + ln], 0, rec + 16);
    }
}

/* CPU-shaped adjoint: one work-item per tile, its pixels' slots back to front in 16 vector lanes
 * (bwd_slot16), in one of two schedules chosen per tile by the slots they walk:
 *   row pairs  the lanes are the 16 pixels of two tile rows, all at the same slot i (from the
 *              longest list of the row pair down; lanes with shorter lists idle meanwhile):
 *              contiguous scratch loads;
 *   queue      the lanes take the tile's pixels from a queue, longest lists first (a counting
 *              sort of n_contrib), each at its own slot; a lane whose pixel is done takes the next
 *              one (its composite state R, G, pixel centre and v_out reloaded): busy lanes, at the
 *              price of gathering the scratch and of the refills.
 * On a surface-like soup (61 % of the row pairs' lane slots busy) the queue walks 36 % fewer
 * slots; on a dense soup (88 % busy) 5 % fewer, less than its overhead: the queue is taken when
 * it saves more than a fifth of the slots. The tile's records are zeroed up front. */
__kernel void blend_bwd_rows16(__global const int* tile_off,      // [T + 1]
                               __global const int* entry_face,    // [E]
                               __global const REAL* entry_setup,  // [E, SETUP]
                               __global const REAL* face_attr,    // [M, 16]  (blend_face_attr)
                               __global const REAL* bg,           // [C]
                               __global const int* n_contrib,     // [H, W]
                               __global const int* s_entry,       // [T * 4, K, 16]
                               __global const REAL* s_T,          // [T * 4, K, 16]
                               __global const REAL* s_ex,         // [T * 4, K, 16]  (sigma > 0)
                               __global const REAL* v_out,        // [H, W, C]
#ifdef V_ACC
                               __global const REAL* v_acc,        // [H, W]
#endif
                               const int C, const int K, const REAL sigma,
                               const int width, const int height, const int tiles_x, const int num_tiles,
                               const int pstride,                 // 32 (C <= 4)
                               __global REAL* partial,            // [E, 32]: moments, then [3, C + 1]
                               __global REAL* v_sigma_tile)       // [T]
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    tile_records_zero(e0, e1, partial, pstride);
    /* the faces' attribute rows, scattered over face_attr, requested up front (the slots read them
     * in an unpredictable order; their cache misses took 2 ms of 13.5 at 400^2, 100k faces) */
    for (int e = e0; e < e1; ++e) PREFETCH_LINE(face_attr + (long)entry_face[e] * 16);
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int x0 = tx * TILE, y0 = ty * TILE;
    /* pixel q of the tile: (x0 + (q & 7), y0 + (q >> 3)); its slot i in the scratch at tile base +
     * (q >> 4) K 16 + (q & 15) + 16 i (BLEND_SLOT) */
    int nq[64];
    int total = 0, rowpair_slots = 0;
    for (int r = 0; r < 4; ++r) {
        int m = 0;
        for (int q = 16 * r; q < 16 * r + 16; ++q) {
            const int x = x0 + (q & 7), y = y0 + (q >> 3);
            nq[q] = x < width && y < height ? n_contrib[y * width + x] : 0;
            total += nq[q];
            m = max(m, nq[q]);
        }
        rowpair_slots += m;
    }
    if (total == 0) { v_sigma_tile[t] = (REAL)0; return; }
    const long tbase = BLEND_SLOT(t, 0, 0, 0, K);
    __global const int* se = s_entry + tbase;
    __global const REAL* sT = s_T + tbase;
    __global const REAL* sx = s_ex + (sigma > (REAL)0 ? tbase : 0);
    const int16 e_safe = (int16)e0;  /* idle lanes read a valid entry */
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    REAL16 vo[C_MAX], R[C_MAX], G, vsig = (REAL16)0;
    /* the queue walks about ceil(total / 16) + 2 slots (the tail: lanes finishing unevenly) */
    const int queue_slots = (total + 15) / 16 + 2;
    const int use_queue = BWD_SCHEDULE == 2 || (BWD_SCHEDULE == 0 && 5 * queue_slots < 4 * rowpair_slots);
    if (!use_queue) {
        for (int r = 0; r < 4; ++r) {
            const int16 n16 = vload16(0, nq + 16 * r);
            const int nmax = max_i16(n16);
            if (nmax == 0) continue;
            const int16 q16 = 16 * r + lane;
            const int16 xl = x0 + (q16 & 7), yl = y0 + (q16 >> 3);
            const int16 in = (xl < width) & (yl < height);
            const int16 pix = select((int16)0, yl * width + xl, in);
            const REAL16 px = CONVERT_REAL16(xl) + (REAL)0.5, py = CONVERT_REAL16(yl) + (REAL)0.5;
            for (int c = 0; c < C; ++c) { vo[c] = select((REAL16)0, gather16r(v_out + c, pix * C), CONVERT_MASK16(in)); R[c] = (REAL16)bg[c]; }
#ifdef V_ACC
            const REAL16 va = select((REAL16)0, gather16r(v_acc, pix), CONVERT_MASK16(in));
#else
            const REAL16 va = (REAL16)0;
#endif
            G = (REAL16)1;
            for (int i = nmax - 1; i >= 0; --i) {
                const int16 acti = (int16)i < n16;
                const MASK16 act = CONVERT_MASK16(acti);
                const int o = r * K * 16 + 16 * i;
                const int16 e = select(e_safe, vload16(0, se + o), acti);
                const REAL16 T = select((REAL16)0, vload16(0, sT + o), act);
                const REAL16 ex = sigma > (REAL)0 ? select((REAL16)1, vload16(0, sx + o), act) : (REAL16)0;
                bwd_slot16(entry_face, entry_setup, face_attr, C, sigma, acti, e, T, ex, px, py, vo, va, R, &G,
                           &vsig, partial, pstride);
            }
        }
    } else {
        /* queue: pixels with fragments by n descending (counting sort on min(n, 63)) */
        int queue[64], bucket[64];
        for (int b = 0; b < 64; ++b) bucket[b] = 0;
        for (int q = 0; q < 64; ++q)
            if (nq[q] > 0) ++bucket[min(nq[q], 63)];
        int qlen = 0;
        for (int b = 63; b > 0; --b) { const int c = bucket[b]; bucket[b] = qlen; qlen += c; }
        for (int q = 0; q < 64; ++q)
            if (nq[q] > 0) queue[bucket[min(nq[q], 63)]++] = q;
        /* lane state: slot (-1: idle), scratch offset of slot 0, pixel centre, v_out, v_acc */
        int l_i[16], l_off[16], l_new[16];
        REAL l_px[16], l_py[16], l_va[16], l_vo[C_MAX][16];
        for (int ln = 0; ln < 16; ++ln) { l_i[ln] = -1; l_off[ln] = 0; l_px[ln] = l_py[ln] = l_va[ln] = (REAL)0; }
        for (int c = 0; c < C; ++c)
            for (int ln = 0; ln < 16; ++ln) l_vo[c][ln] = (REAL)0;
        int16 il = (int16)(-1), off = (int16)0;
        REAL16 px = (REAL16)0, py = (REAL16)0, va = (REAL16)0;
        for (int c = 0; c < C; ++c) { vo[c] = (REAL16)0; R[c] = (REAL16)bg[c]; }
        G = (REAL16)1;
        int qpos = 0;
        for (;;) {
            if (qpos < qlen && any_i16(il)) {  /* idle lanes (il = -1) take the next pixels */
                vstore16(il, 0, l_i);
                for (int ln = 0; ln < 16; ++ln) {
                    l_new[ln] = 0;
                    if (l_i[ln] >= 0 || qpos >= qlen) continue;
                    const int q = queue[qpos++];
                    const int x = x0 + (q & 7), y = y0 + (q >> 3), pix = y * width + x;
                    l_i[ln] = nq[q] - 1;
                    l_off[ln] = (q >> 4) * K * 16 + (q & 15);
                    l_new[ln] = -1;
                    l_px[ln] = (REAL)x + (REAL)0.5;
                    l_py[ln] = (REAL)y + (REAL)0.5;
                    l_va[ln] = V_ACC_AT(pix);
                    for (int c = 0; c < C; ++c) l_vo[c][ln] = v_out[pix * C + c];
                }
                il = vload16(0, l_i);
                off = vload16(0, l_off);
                px = vload16(0, l_px);
                py = vload16(0, l_py);
                va = vload16(0, l_va);
                const MASK16 fresh = CONVERT_MASK16(vload16(0, l_new));
                for (int c = 0; c < C; ++c) {
                    vo[c] = vload16(0, l_vo[c]);
                    R[c] = select(R[c], (REAL16)bg[c], fresh);
                }
                G = select(G, (REAL16)1, fresh);
            }
            const int16 acti = il >= 0;
            if (!any_i16(acti)) break;
            const MASK16 act = CONVERT_MASK16(acti);
            const int16 so = select((int16)0, off + 16 * il, acti);  /* each lane's slot */
            const int16 e = select(e_safe, gather16i(se, so), acti);
            const REAL16 T = select((REAL16)0, gather16r(sT, so), act);
            const REAL16 ex = sigma > (REAL)0 ? select((REAL16)1, gather16r(sx, so), act) : (REAL16)0;
            bwd_slot16(entry_face, entry_setup, face_attr, C, sigma, acti, e, T, ex, px, py, vo, va, R, &G,
                       &vsig, partial, pstride);
            il = select(il, il - 1, acti);
        }
    }
    const REAL8 h8 = vsig.lo + vsig.hi;
    const REAL4 h4 = h8.lo + h8.hi;
    const REAL2 h2 = h4.lo + h4.hi;
    v_sigma_tile[t] = h2.x + h2.y;
}
#endif
