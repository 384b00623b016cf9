/* raster_lists.h — the K-nearest fragment lists of the rasterizers (raster.cl, blend.cl).
 *
 * A pixel's list holds its K nearest fragments sorted by (depth, face id): the face id breaks ties
 * so the result never depends on the arbitrary order of a tile's (tile, face) entries.
 * Per entry (edge-function set-up s, binning.cl SETUP), pixel centre p, (dx, dy) = p - a0:
 *   b0 = 1 + s2 dx + s3 dy,  b1 = s4 dx + s5 dy,  b2 = 1 - b0 - b1   (hit: all >= 0)
 *   zp = 1 / (b0 s6 + b1 s7 + b2 s8)                                  (hit: zp <= far)
 * and the pixel's row is one of the entry's rows (entry_rows: the rows of the tile inside the
 * face's bounding box, bit r for row r: the same set as the binning's, and the cheap rejection of
 * most entries by the 16-lane builder, which tests two rows at a time).
 * Two builders with identical results:
 *   pixel_list   one pixel, scalar insertion (GPU-shaped kernels: one work-item per pixel);
 *   rows16_lists two rows of an 8x8 tile as the 16 lanes of REAL16 vectors, slot k of the 16
 *                lists one vector, lane-wise back-to-front insertion (CPU-shaped kernels).
 * The including file sets "#pragma OPENCL FP_CONTRACT OFF" first: the scalar and the vector
 * builders must produce bit-identical depths (compilers contract scalar and vector code differently).
 * Also here: the soft-coverage window from an entry's set-up (coverage.cl's formula, no vertex loads).
 */
#ifndef TRIPLET_RASTER_LISTS_H
#define TRIPLET_RASTER_LISTS_H

#include "real.h"

#ifndef TILE
#define TILE 8
#endif
#ifndef SETUP
#define SETUP 12 /* a0x a0y  A0 B0  A1 B1  iz0 iz1 iz2  g0 g1 g2 :  b0 = 1 + A0 dx + B0 dy,
                     b1 = A1 dx + B1 dy, g_k = 1 / |grad b_k| (pixel distance to edge k = b_k g_k) */
#endif
#ifndef ROWS16_CHUNK
#define ROWS16_CHUNK 64 /* rows16_lists: entries tested per branch-free pass */
#endif
#define HARD_EDGE_DISTANCE ((REAL)1e30) /* edges marked hard (g_k < 0) are left out of the window */

/* The coverage window from a face's edge-function set-up: the pixel distance to edge k is
 * d_k = b_k g_k (g_k = 1 / |grad b_k|), the same quantity as sgn(A) E_k / L_k of raster_math.h;
 *   d = max(0, min_k d_k) over the soft edges,  win = 1 - exp(-sigma d)
 * (no soft edge: d = HARD_EDGE_DISTANCE, win = 1). Returns win; *kmin = the arg-min edge, *dmin =
 * min_k d_k (before the clamp at 0) and *ex = exp(-sigma d) for the adjoint. */
/* The nearest soft edge: *kmin = k*, returns d_k* = min_k d_k (HARD_EDGE_DISTANCE: no soft edge). */
inline REAL setup_window_arg(__global const REAL* s, REAL b0, REAL b1, REAL b2, int* kmin)
{
    const REAL d0 = s[9] < (REAL)0 ? HARD_EDGE_DISTANCE : b0 * s[9];
    const REAL d1 = s[10] < (REAL)0 ? HARD_EDGE_DISTANCE : b1 * s[10];
    const REAL d2 = s[11] < (REAL)0 ? HARD_EDGE_DISTANCE : b2 * s[11];
    int k = 0;
    REAL dm = d0;
    if (d1 < dm) { dm = d1; k = 1; }
    if (d2 < dm) { dm = d2; k = 2; }
    *kmin = k;
    return dm;
}

inline REAL setup_window_ex(__global const REAL* s, REAL b0, REAL b1, REAL b2, REAL sigma,
                            int* kmin, REAL* dmin, REAL* ex)
{
    *dmin = setup_window_arg(s, b0, b1, b2, kmin);
    /* no soft edge: exp(-sigma 1e30) is 0 for every sigma above 1e-27, so the call is skipped (the same bits; in the
     * mesh stage, whose window is on silhouette edges only, pack_raster_fragments 1.4-1.9x: the scalar library exp
     * was most of its time, session 60) */
    *ex = *dmin < HARD_EDGE_DISTANCE ? exp(-sigma * fmax(*dmin, (REAL)0)) : (REAL)0;
    return (REAL)1 - *ex;
}

inline REAL setup_window(__global const REAL* s, REAL b0, REAL b1, REAL b2, REAL sigma)
{
    int k;
    REAL dm, ex;
    return setup_window_ex(s, b0, b1, b2, sigma, &k, &dm, &ex);
}

/* Insert fragment (zp, f, e) into a pixel's list of the K nearest, kept sorted by (depth, face id). */
inline void insert_fragment(REAL* dk, int* fk, int* ek, int* cnt, int K, REAL zp, int f, int e)
{
    const int n = *cnt;
    if (n == K && !(zp < dk[K - 1] || (zp == dk[K - 1] && f < fk[K - 1]))) return;
    int j = n < K ? n : K - 1;
    while (j > 0 && (dk[j - 1] > zp || (dk[j - 1] == zp && fk[j - 1] > f))) {
        dk[j] = dk[j - 1]; fk[j] = fk[j - 1]; ek[j] = ek[j - 1];
        --j;
    }
    dk[j] = zp; fk[j] = f; ek[j] = e;
    if (n < K) *cnt = n + 1;
}

/* The list of pixel centre (px, py), row y of the image, over the entries of tile t. Returns the
 * count. */
inline int pixel_list(__global const int* tile_off, __global const int* entry_order, __global const int* entry_face,
                      __global const REAL* entry_setup, __global const int* entry_rows, int t, REAL px,
                      REAL py, int y, int K, REAL far, REAL* dk, int* fk, int* ek)
{
    int cnt = 0;
    const int e_end = tile_off[t + 1];
    const int rowbit = 1 << (y % TILE);
    for (int i = tile_off[t]; i < e_end; ++i) {
        const int e = entry_order[i];
        if (!(entry_rows[e] & rowbit)) continue;  /* pixel centre outside the face's bounding box */
        __global const REAL* s = entry_setup + e * SETUP;
        const REAL dx = px - s[0], dy = py - s[1];
        const REAL b0 = (REAL)1 + s[2] * dx + s[3] * dy;
        const REAL b1 = s[4] * dx + s[5] * dy;
        const REAL b2 = (REAL)1 - b0 - b1;
        if (b0 < (REAL)0 || b1 < (REAL)0 || b2 < (REAL)0) continue;
        const REAL zp = (REAL)1 / (b0 * s[6] + b1 * s[7] + b2 * s[8]);
        if (!(zp <= far)) continue;
        insert_fragment(dk, fk, ek, &cnt, K, zp, entry_face[e], e);
    }
    return cnt;
}

/* Lane masks of REAL16 comparisons: int16 for float, long16 for double (REAL_FP64 is defined by the
 * host for double programs). */
#ifdef REAL_FP64
#define MASK16 long16
#define CONVERT_MASK16(x) convert_long16(x)
#define CONVERT_INT16(m) convert_int16(m)
#else
#define MASK16 int16
#define CONVERT_MASK16(x) (x)
#define CONVERT_INT16(m) (m)
#endif
#define CONVERT_REAL16(x) TRIPLET_CAT(convert_, REAL16)(x)
/* any() of an int16 mask (lanes 0 or -1) and the largest lane of an int16. PoCL lowers OpenCL's
 * any() of a 16-lane mask to a test per lane, and a reduction to a tree of shuffles; with AVX-512
 * the mask's sign bits go to a mask register in one instruction (vpmovd2m), tested at once. */
#if defined(__clang__) && defined(__AVX512F__) && defined(__has_builtin)
#if __has_builtin(__builtin_ia32_cvtd2mask512) && __has_builtin(__builtin_bit_cast)
#define TRIPLET_AVX512_MASK 1
#endif
#endif
#ifdef TRIPLET_AVX512_MASK
typedef int triplet_v16si __attribute__((vector_size(64)));
inline int any_i16(int16 m)
{
    return __builtin_ia32_cvtd2mask512(__builtin_bit_cast(triplet_v16si, m)) != 0;
}
#else
inline int any_i16(int16 m)
{
    const int8 a = m.lo | m.hi;
    const int4 b = a.lo | a.hi;
    const int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
}
#endif
#define ANY16(m) any_i16(CONVERT_INT16(m))
inline int max_i16(int16 v)
{
    const int8 a = max(v.lo, v.hi);
    const int4 b = max(a.lo, a.hi);
    const int2 c = max(b.lo, b.hi);
    return max(c.x, c.y);
}

/* A hint to bring the cache line of p in (a no-op where the compiler has no prefetch builtin;
 * PoCL's OpenCL prefetch() is one). __builtin_prefetch only on CPU devices (the host's -DTRIPLET_CPU):
 * NVIDIA's OpenCL refuses it ("changes address space of pointer": it takes a generic void*). */
#if defined(__clang__) && defined(TRIPLET_CPU)
#define PREFETCH_LINE(p) __builtin_prefetch(p)
#else
#define PREFETCH_LINE(p) prefetch(p, 1)
#endif

/* lane l reads p[i.l] */
inline int16 gather16i(__global const int* p, int16 i)
{
    return (int16)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7],
                   p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]);
}

/* lane l reads p[i.l] */
inline REAL16 gather16r(__global const REAL* p, int16 i)
{
    return (REAL16)(p[i.s0], p[i.s1], p[i.s2], p[i.s3], p[i.s4], p[i.s5], p[i.s6], p[i.s7],
                    p[i.s8], p[i.s9], p[i.sa], p[i.sb], p[i.sc], p[i.sd], p[i.se], p[i.sf]);
}

/* The edge tests of one entry (set-up s) at the 16 pixels of two tile rows; rows: which of the two
 * rows are inside the entry's bounding box (bits 0, 1). Returns the hit mask, and b0, b1, b2. */
inline MASK16 rows16_edge_test(__global const REAL* s, REAL16 px, REAL16 py, MASK16 inimg, int rows,
                               REAL16* b0, REAL16* b1, REAL16* b2)
{
    const int16 lane_row = (int16)(1, 1, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2);
    const REAL16 dx = px - s[0];
    const REAL16 dy = py - s[1];
    *b0 = (REAL)1 + s[2] * dx + s[3] * dy;
    *b1 = s[4] * dx + s[5] * dy;
    *b2 = (REAL)1 - *b0 - *b1;
    return (*b0 >= (REAL)0) & (*b1 >= (REAL)0) & (*b2 >= (REAL)0) & inimg &
           CONVERT_MASK16(((int16)rows & lane_row) != 0);
}

/* The 16 lists of two rows of a tile (lane l: pixel centre (px.l, py.l); lanes outside the image
 * have inimg = 0 and never hit), over the entries of tile t, kept lane-wise: slot k of the 16
 * lists is dk[k] (depth) / ek[k] (entry). A hit is inserted into all 16 lists at once, back to
 * front like an insertion sort: starting from slot k = (longest list among the hit lanes) - 1,
 *   mv = active & ((z < D_k) | (z == D_k & f < face(E_k)));   slot k+1 <- D_k where mv,
 *   z where active & !mv;  active = mv;  stop when no lane is active (then slot 0 <- z where still active)
 * (likewise for the entry ids). The face ids of the slots are gathered only for the (rare) equal
 * depths, not carried along. Lanes without a hit are never active; a lane with a shorter list
 * moves through its empty (+inf, INT_MAX) slots; slot K (the K+1-th) is dropped.
 * Same tests, same (depth, face id) order, same results as pixel_list, no per-lane branches.
 * The entries go in chunks of ROWS16_CHUNK: first the edge tests of the whole chunk, branch-free,
 * keeping the entries that hit any lane, then only those (tested again) into the lists. (One pass
 * with a branch per entry was 1.7 ms slower at 400^2, 100k faces, K = 30, surface-like, and 5.7 ms
 * dense, on PoCL: the branch on the tests is unpredictable and waits for them.)
 * face_rows (or 0): a [M, 16] per-face array the caller reads next for the lanes' faces; the rows
 * of the faces that enter the lists are prefetched.
 * Returns the count of each lane. */
inline int16 rows16_lists(__global const int* tile_off, __global const int* entry_order, __global const int* entry_face,
                          __global const REAL* entry_setup, __global const int* entry_rows, int t,
                          int pair, REAL16 px, REAL16 py, MASK16 inimg, int K, REAL far, REAL16* dk,
                          int16* ek, __global const REAL* face_rows)
{
    const REAL16 inf16 = (REAL16)(INFINITY);
    const int16 imax16 = (int16)(INT_MAX);
    for (int k = 0; k < K; ++k) {
        dk[k] = inf16;
        ek[k] = imax16;
    }
    int16 cnt16 = (int16)0;  /* slots in use per lane */
    const int e_end = tile_off[t + 1];
    int hits[ROWS16_CHUNK];
    for (int c0 = tile_off[t]; c0 < e_end; c0 += ROWS16_CHUNK) {
        const int c1 = min(c0 + ROWS16_CHUNK, e_end);
        /* pass 1, branch-free: the entries of the chunk that hit any of the 16 pixels */
        int nh = 0;
        for (int i = c0; i < c1; ++i) {
            const int e = entry_order[i];
            const int rows = (entry_rows[e] >> (2 * pair)) & 3;
            REAL16 b0, b1, b2;
            const MASK16 hit = rows16_edge_test(entry_setup + e * SETUP, px, py, inimg, rows, &b0, &b1, &b2);
            hits[nh] = e;
            nh += ANY16(hit);
        }
        /* pass 2: those entries into the lists */
        for (int j = 0; j < nh; ++j) {
            const int e = hits[j];
            const int rows = (entry_rows[e] >> (2 * pair)) & 3;
            __global const REAL* s = entry_setup + e * SETUP;
            REAL16 b0, b1, b2;
            MASK16 hit = rows16_edge_test(s, px, py, inimg, rows, &b0, &b1, &b2);
            const REAL16 zp = (REAL)1 / (b0 * s[6] + b1 * s[7] + b2 * s[8]);
            hit &= (zp <= far);
            if (!ANY16(hit)) continue;
            REAL16 z = select(inf16, zp, hit);
            const int16 hit_i = CONVERT_INT16(hit);
            const int f = entry_face[e];
            if (face_rows) PREFETCH_LINE(face_rows + (long)f * 16);  /* read when the lists are blended */
            int16 en = select(imax16, (int16)(e), hit_i);
            MASK16 act = hit;
            int16 actc = hit_i;
            const int kstart = min(max_i16(cnt16 & hit_i), K) - 1;  /* deepest list among the hit lanes */
            cnt16 = min(cnt16 - hit_i, K);
            REAL16 pd = kstart + 1 < K ? dk[kstart + 1] : inf16;
            int16 pe = kstart + 1 < K ? ek[kstart + 1] : imax16;
            int k = kstart;
            for (; k >= 0; --k) {
                const REAL16 d = dk[k];
                const int16 eo = ek[k];
                MASK16 mv = act & (z < d);
                const MASK16 tie = act & (z == d);  /* equal depths (rare): the face ids decide */
                if (ANY16(tie)) {
                    const int16 tie_i = CONVERT_INT16(tie);
                    const int16 fo = gather16i(entry_face, select((int16)e, eo, tie_i));
                    mv |= CONVERT_MASK16(tie_i & ((int16)f < fo));
                }
                const int16 mvi = CONVERT_INT16(mv);
                const int16 place = actc & ~mvi;
                if (k + 1 < K) {
                    dk[k + 1] = select(select(pd, z, CONVERT_MASK16(place)), d, mv);
                    ek[k + 1] = select(select(pe, en, place), eo, mvi);
                }
                act = mv; actc = mvi;
                if (!any_i16(mvi)) break;
                pd = d; pe = eo;
            }
            if (k < 0) {
                dk[0] = select(pd, z, act);
                ek[0] = select(pe, en, actc);
            }
        }
    }
    return cnt16;
}

/* Lane l's pixel centre and image mask of the two rows (y0, y0 + 1) from x0 of an 8x8 tile. */
#define ROWS16_LANES(x0, y0, width, height, px, py, inimg)                                          \
    const int16 lane_x_ = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3, 4, 5, 6, 7);                  \
    const int16 lane_y_ = (int16)(0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1);                  \
    const REAL16 px = (REAL)(x0) + (REAL)0.5 + CONVERT_REAL16(lane_x_);                             \
    const REAL16 py = (REAL)(y0) + (REAL)0.5 + CONVERT_REAL16(lane_y_);                             \
    const MASK16 inimg = CONVERT_MASK16(((x0) + lane_x_ < (width)) & ((y0) + lane_y_ < (height)))

#endif /* TRIPLET_RASTER_LISTS_H */
