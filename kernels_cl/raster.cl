/* raster.cl — the K nearest fragments of every pixel, from the tile binning (binning.cl), and
 * their packing. Host side: ops/raster.py.
 *
 * raster_fwd  one work-item per pixel, one 8x8 work-group per tile: the K nearest fragments by
 *             (depth, face id) — the face id breaks ties so the result never depends on the
 *             arbitrary order of a tile's list. Forward formulas: see common/raster_math.h.
 *             (GPU-shaped; raster_fwd_rows and raster_fwd_rows16 are CPU-shaped twins with the
 *             same results: 8-pixel rows with vector edge tests and a scalar insertion, or two
 *             rows as 16 vector lanes with a lane-wise insertion.) Each pixel's list (entry and
 *             depth of its slots) goes to K-strided scratch.
 * pack_raster_fragments  per pixel: the list -> the packed fragments (rows off[pix] + k, off the
 *             prefix sum of the counts), with face, barycentrics and, with WINDOW, the coverage
 *             window (coverage.cl's formula from the set-up coefficients: no vertex loads).
 * pack_fragments  the generic copy of K-strided lists into the packed layout (ray-traced fragments).
 * Both pack kernels write the coverage window win [P] only when WINDOW is defined.
 * (adjoint)   fragment_bwd.cl: one pass over the fragments for interpolation, barycentrics,
 *             depth and window, into per-entry partial sums (no atomics, deterministic), and the
 *             per-vertex gathers.
 */
/* No a*b+c contraction into FMA here: the per-pixel and the 8-wide row variants must produce
 * bit-identical depths (the compiler contracts scalar and vector code differently). */
#pragma OPENCL FP_CONTRACT OFF

#include "real.h"
#include "raster_math.h"

#ifndef TILE
#define TILE 8
#endif
#ifndef K_MAX
#define K_MAX 1
#endif
#define SETUP 12 /* a0x a0y  A0 B0  A1 B1  iz0 iz1 iz2  g0 g1 g2 :  b0 = 1 + A0 dx + B0 dy,
                     b1 = A1 dx + B1 dy, g_k = 1 / |grad b_k| (pixel distance to edge k = b_k g_k) */
#include "raster_lists.h" /* pixel_list, rows16_lists, setup_window */

/* The raster kernels write each pixel's list into K-strided scratch (entry and depth of slot k,
 * slots beyond the count never written); pack_raster_fragments turns it into the packed fragments. */
#define STORE_SLOT(o, e, z) do { frag_entry[o] = (e); frag_depth[o] = (z); } while (0)

__kernel void raster_fwd(__global const int* tile_off,      // [T + 1]
                         __global const int* entry_order,   // [E]  (bin_depth_order)
                         __global const int* entry_face,    // [E]
                         __global const REAL* entry_setup,  // [E, SETUP]
                         __global const int* entry_rows,    // [E]
                         const int width, const int height, const int tiles_x,
                         const int K, const REAL far,
                         __global int* frag_entry,          // [H, W, K]  scratch: entry of slot k
                         __global REAL* frag_depth,         // [H, W, K]  scratch: depth of slot k
                         __global int* frag_count)          // [H, W]
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
    frag_count[pix] = cnt;
    for (int k = 0; k < cnt; ++k) STORE_SLOT(pix * K + k, ek[k], dk[k]);
}

#if TILE == 8
/* CPU-shaped variant of raster_fwd: one work-item per 8-pixel tile row, the edge tests of the 8
 * pixels done as one REAL8 vector operation (a scalar insertion only for the lanes that are hit).
 * Same arithmetic as raster_fwd, same results; chosen on CPU devices, where it is several times
 * faster because PoCL does not vectorise the per-pixel kernel across work-items. */
__kernel void raster_fwd_rows(__global const int* tile_off,      // [T + 1]
                              __global const int* entry_order,   // [E]  (bin_depth_order)
                              __global const int* entry_face,    // [E]
                              __global const REAL* entry_setup,  // [E, SETUP]
                              __global const int* entry_rows,    // [E]
                              const int width, const int height, const int tiles_x,
                              const int K, const REAL far,
                              __global int* frag_entry,          // [H, W, K]  scratch: entry of slot k
                              __global REAL* frag_depth,         // [H, W, K]  scratch: depth of slot k
                              __global int* frag_count)          // [H, W]
{
    const int tx = get_group_id(0), ty = get_group_id(1);
    const int y = ty * TILE + get_local_id(1);
    if (y >= height) return;
    const int x0 = tx * TILE;
    const int t = ty * tiles_x + tx;
    const REAL8 lane = (REAL8)(0, 1, 2, 3, 4, 5, 6, 7);
    const REAL8 px = (REAL)x0 + (REAL)0.5 + lane;
    const REAL py = (REAL)y + (REAL)0.5;
    const int nl = min(8, width - x0);

    REAL dk[8][K_MAX];
    int fk[8][K_MAX], ek[8][K_MAX];
    int cnt[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    const int e_end = tile_off[t + 1];
    const int rowbit = 1 << (y % TILE);
    for (int i = tile_off[t]; i < e_end; ++i) {
        const int e = entry_order[i];
        if (!(entry_rows[e] & rowbit)) continue;  /* row outside the face's bounding box */
        __global const REAL* s = entry_setup + e * SETUP;
        const REAL8 dx = px - s[0];
        const REAL dy = py - s[1];
        const REAL8 b0 = (REAL)1 + s[2] * dx + s[3] * dy;
        const REAL8 b1 = s[4] * dx + s[5] * dy;
        const REAL8 b2 = (REAL)1 - b0 - b1;
        if (!any((b0 >= (REAL)0) & (b1 >= (REAL)0) & (b2 >= (REAL)0))) continue;
        const REAL8 zp8 = (REAL)1 / (b0 * s[6] + b1 * s[7] + b2 * s[8]);
        REAL zs[8], c0[8], c1[8], c2[8];
        vstore8(zp8, 0, zs);
        vstore8(b0, 0, c0);
        vstore8(b1, 0, c1);
        vstore8(b2, 0, c2);
        const int f = entry_face[e];
        for (int l = 0; l < nl; ++l) {
            if (c0[l] < (REAL)0 || c1[l] < (REAL)0 || c2[l] < (REAL)0) continue;
            if (!(zs[l] <= far)) continue;
            insert_fragment(dk[l], fk[l], ek[l], &cnt[l], K, zs[l], f, e);
        }
    }
    for (int l = 0; l < nl; ++l) {
        const int x = x0 + l;
        const int pix = y * width + x;
        frag_count[pix] = cnt[l];
        for (int k = 0; k < cnt[l]; ++k) STORE_SLOT(pix * K + k, ek[l][k], dk[l][k]);
    }
}
#endif

#if TILE == 8
/* CPU-shaped variant with a vector insertion: one work-item per two rows of an 8x8 tile, the 16
 * pixels held as the 16 lanes of REAL16 vectors (lane l: x = x0 + (l & 7), y = y0 + (l >> 3)),
 * their K-nearest lists kept lane-wise and filled by rows16_lists (common/raster_lists.h: a
 * lane-wise back-to-front insertion, no per-lane branches). Same results as raster_fwd. Used for
 * K <= 256 (ROWS16_K_LIMIT in ops/raster.py; the lists live in private memory: 12 bytes x 16
 * lanes per slot). */
__kernel void raster_fwd_rows16(__global const int* tile_off,      // [T + 1]
                                __global const int* entry_order,   // [E]  (bin_depth_order)
                                __global const int* entry_face,    // [E]
                                __global const REAL* entry_setup,  // [E, SETUP]
                                __global const int* entry_rows,    // [E]
                                const int width, const int height, const int tiles_x,
                                const int K, const REAL far,
                                __global int* frag_entry,          // [H, W, K]  scratch: entry of slot k
                                __global REAL* frag_depth,         // [H, W, K]  scratch: depth of slot k
                                __global int* frag_count)          // [H, W]
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
    const int16 cnt16 = rows16_lists(tile_off, entry_order, entry_face, entry_setup, entry_rows, t, pair & 3, px, py, inimg, K, far, dk, ek, 0);
    for (int l = 0; l < 16; ++l) {
        const int x = x0 + (l & 7), y = y0 + (l >> 3);
        if (x >= width || y >= height) continue;
        const int pix = y * width + x;
        const REAL* dl = (const REAL*)dk;  /* slot k of lane l: [k * 16 + l] */
        const int* el = (const int*)ek;
        const int cnt = ((const int*)&cnt16)[l];
        frag_count[pix] = cnt;
        for (int k = 0; k < cnt; ++k) STORE_SLOT(pix * K + k, el[k * 16 + l], dl[k * 16 + l]);
    }
}
#endif

/* pack_raster_fragments: the raster kernels' scratch lists (entry, depth) -> packed fragments at
 * rows off[pix] + k, with the face, the perspective-correct barycentrics and (WINDOW) the
 * coverage window computed from the entry's set-up:
 *   b0 = 1 + s2 dx + s3 dy,  b1 = s4 dx + s5 dy,  b2 = 1 - b0 - b1,  (dx, dy) = p - a0
 *   w_k = b_k / z_k,  lam_k = w_k / (w0 + w1 + w2)   (raster_math.h)
 *   win = setup_window(b0, b1, b2)                  (coverage.cl's formula; its distance here, the exp in
 *                                                    window_from_distance)  */
__kernel void pack_raster_fragments(const int width, const int height, const int K, const REAL sigma,
                                    __global const int* count,        // [H, W]
                                    __global const int* off,          // [H * W + 1]
                                    __global const int* s_entry,      // [H, W, K] scratch
                                    __global const REAL* s_depth,     // [H, W, K] scratch
                                    __global const int* entry_face,   // [E]
                                    __global const REAL* entry_setup, // [E, SETUP]
                                    __global int* face,               // [P]
                                    __global int* entry,              // [P]
                                    __global REAL* bary,              // [P, 2]
#ifdef WINDOW
                                    __global REAL* win,               // [P]
#endif
                                    __global REAL* depth)             // [P]
{
    const int pix = get_global_id(0);
    if (pix >= width * height) return;
    const REAL px = (REAL)(pix % width) + (REAL)0.5, py = (REAL)(pix / width) + (REAL)0.5;
    const int c = count[pix], o0 = off[pix];
    for (int k = 0; k < c; ++k) {
        const int i = pix * K + k, o = o0 + k;
        const int e = s_entry[i];
        __global const REAL* s = entry_setup + e * SETUP;
        const REAL dx = px - s[0], dy = py - s[1];
        const REAL b0 = (REAL)1 + s[2] * dx + s[3] * dy;
        const REAL b1 = s[4] * dx + s[5] * dy;
        const REAL b2 = (REAL)1 - b0 - b1;
        const REAL w0 = b0 * s[6], w1 = b1 * s[7], w2 = b2 * s[8];
        const REAL is = (REAL)1 / (w0 + w1 + w2);
        face[o] = entry_face[e];
        entry[o] = e;
        bary[2 * o] = w0 * is;
        bary[2 * o + 1] = w1 * is;
        depth[o] = s_depth[i];
#if defined(WINDOW) && defined(WINDOW_IN_PACK)  /* the window itself, its exp in this loop (the reference) */
        win[o] = setup_window(s, b0, b1, b2, sigma);
#elif defined(WINDOW)
        int kk;
        win[o] = setup_window_arg(s, b0, b1, b2, &kk);  /* the distance: window_from_distance makes it the window */
#endif
    }
}

/* window_from_distance: win = 1 - exp(-sigma max(0, d)) in place, d the nearest soft edge's distance that
 * pack_raster_fragments wrote (setup_window_ex's formula and operations: the same bits). A separate pass, one
 * work-item per fragment, because the packing's per-pixel loop keeps the CPU device from vectorising it, and a
 * scalar exp there is a library call (session 60: 18 ns a value against 2 ns in this pass's vector lanes on PoCL,
 * the same bits). Its exp also goes to win_ex, which the adjoint (fragment_bwd.cl, WIN_EX) reads instead of
 * taking the exp again in its own scalar loop. */
__kernel void window_from_distance(const int P, const REAL sigma,
                                   __global REAL* win,     // [P] in: d, out: the window
                                   __global REAL* win_ex)  // [P] out: exp(-sigma max(0, d)), for fragment_bwd
{
    const int o = get_global_id(0);
    if (o >= P) return;
    const REAL d = win[o];
    const REAL ex = d < HARD_EDGE_DISTANCE ? exp(-sigma * fmax(d, (REAL)0)) : (REAL)0;
    win[o] = (REAL)1 - ex;
    win_ex[o] = ex;
}

/* Packed fragment layout (pack_fragments: the generic copy, used by ray-traced fragments): the
 * K-strided per-pixel lists ([H, W, K]); pack_fragments moves the first count[pix] slots of every pixel to
 * [off[pix], off[pix] + count[pix]) of dense [P] arrays (off = exclusive prefix sum of count, so
 * the fragments are pixel-major, nearest first). Every per-fragment array downstream is [P, C]:
 * consecutive pixels' fragments are adjacent in memory (streaming access), and memory follows the
 * fragments, not H x W x K. */
__kernel void pack_fragments(const int npix, const int K,
                             __global const int* count,        // [H, W]
                             __global const int* off,          // [H * W + 1]
                             __global const int* s_face,       // [H, W, K]
                             __global const int* s_entry,      // [H, W, K]
                             __global const REAL* s_bary,      // [H, W, K, 2]
                             __global const REAL* s_depth,     // [H, W, K]
#ifdef WINDOW
                             __global const REAL* s_win,       // [H, W, K]
#endif
                             __global int* face,               // [P]
                             __global int* entry,              // [P]
                             __global REAL* bary,              // [P, 2]
#ifdef WINDOW
                             __global REAL* win,               // [P]
#endif
                             __global REAL* depth)             // [P]
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int c = count[pix], o0 = off[pix];
    for (int k = 0; k < c; ++k) {
        const int i = pix * K + k, o = o0 + k;
        face[o] = s_face[i];
        entry[o] = s_entry[i];
        bary[2 * o] = s_bary[2 * i];
        bary[2 * o + 1] = s_bary[2 * i + 1];
        depth[o] = s_depth[i];
#ifdef WINDOW
        win[o] = s_win[i];
#endif
    }
}
