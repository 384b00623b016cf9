/* raster.cl — tile binning, K-nearest fragments per pixel, and the adjoint of the fragment
 * geometry (barycentrics, depth, soft-coverage window) back to screen-space vertices.
 *
 * Tiles are TILE x TILE pixels (TILE = 8 unless defined). One "entry" is one (tile, face) pair.
 *
 * bin_count   per face: cull (any vertex z < near, all z > far, |A| tiny, back-facing when
 *             CULL_BACK, no pixel centre in its bounding box); count the tiles of its bounding box;
 *             atomically count faces per tile (int atomics only: core OpenCL 1.1).
 * bin_fill    per face: write the entries of each overlapped tile (tile-major lists, their order
 *             inside a tile is arbitrary) with the face's edge-function set-up, and the face-major
 *             list face_entries (entry ids of each face, in tile order) used by the adjoint gather.
 *             With soft_edges, only the marked edges of a face get the coverage window (the
 *             silhouette edges of a connected mesh: its shared interior edges stay hard, no seams).
 *             Per entry also entry_rows: the tile rows inside the face's pixel bounding box (the
 *             list builders skip the entry elsewhere) and a coverage estimate (upper bits).
 * bin_depth_order  per tile: the order in which the list builders visit its entries (nearest
 *             first where its lists fill up, else the binning's order; the lists do not depend on it).
 * raster_fwd  one work-item per pixel, one 8x8 work-group per tile: the K nearest fragments by
 *             (depth, face id) — the face id breaks ties so the result never depends on the
 *             arbitrary order of a tile's list. Forward formulas: see common/raster_math.h.
 *             (GPU-shaped; raster_fwd_rows and raster_fwd_rows16 are CPU-shaped twins with the
 *             same results: 8-pixel rows with vector edge tests and a scalar insertion, or two
 *             rows as 16 vector lanes with a lane-wise insertion.) Each pixel's list (entry and
 *             depth of its slots) goes to K-strided scratch.
 * pack_raster_fragments  per pixel: the list -> the packed fragments (rows off[pix] + k, off the
 *             prefix sum of the counts), with face, barycentrics and, for sigma > 0, the coverage
 *             window (coverage.cl's formula from the set-up coefficients: no vertex loads).
 * (adjoint)   fragment_bwd.cl: one pass over the fragments for interpolation, barycentrics,
 *             depth and window, into per-entry partial sums (no atomics, deterministic).
 * gather_vertex  per vertex: sum partial[entry, corner, :] over every face corner of the vertex
 *             (CSR) and every entry of that face that has fragments (entry_hit), for two partial
 *             arrays at once (attributes, geometry). Adjoint of "vertex -> fragment".
 * gather_corner  per vertex: sum per-face-corner adjoints [M, 3, C] over the vertex's corners
 *             (CSR), for two arrays at once (blend.cl's blend_face_grad writes them per corner).
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

/* The pixel indices whose centres (i + 0.5) lie in [lo, hi] (lo > hi: none), clamped to [0, n - 1]:
 * *i0 = ceil(lo - 0.5), *i1 = floor(hi - 0.5). Clamped to [-1, n] before the conversion (exact
 * there) and rounded by comparison: PoCL's ceil() and floor() are branchy library calls that cost
 * a third of bin_count. */
inline void centre_range(REAL lo, REAL hi, int n, int* i0, int* i1)
{
    const REAL a = fmin(fmax(lo - (REAL)0.5, (REAL)0), (REAL)n);
    const REAL b = fmin(fmax(hi - (REAL)0.5, (REAL)-1), (REAL)(n - 1));
    const int ia = (int)a, ib = (int)b;   /* truncation: a >= 0; b >= -1 */
    *i0 = ia + ((REAL)ia < a);            /* ceil */
    *i1 = ib - ((REAL)ib > b);            /* floor */
}

__kernel void bin_count(__global const REAL* vs,        // [N, 3] (u, v, z)
                        __global const int* F,          // [M, 3]
                        const int m, const int width, const int height,
                        const int tiles_x,
                        const REAL near, const REAL far, const int cull_back,
                        __global int* face_ntiles,      // [M]
                        __global int* face_bbox,        // [M, 4] tile bbox tx0 ty0 tx1 ty1
                        __global int* tile_count)       // [T]  (atomic increments)
{
    const int f = get_global_id(0);
    if (f >= m) return;
    const int i0 = F[3 * f], i1 = F[3 * f + 1], i2 = F[3 * f + 2];
    const REAL3 p0 = LOAD3(vs, i0), p1 = LOAD3(vs, i1), p2 = LOAD3(vs, i2);
    int ok = p0.z >= near && p1.z >= near && p2.z >= near;
    ok = ok && !(p0.z > far && p1.z > far && p2.z > far);
    const REAL2 a0 = p0.xy, a1 = p1.xy, a2 = p2.xy;
    const REAL A = cross2(a1 - a0, a2 - a0);
    ok = ok && isfinite(A) && fabs(A) > (REAL)1e-10;
    ok = ok && !(cull_back && A > (REAL)0);   /* A > 0 on screen (y down) = facing away */
    int x0 = 0, y0 = 0, x1 = -1, y1 = -1;
    if (ok) {
        /* pixels whose centre (i + 0.5) lies inside the bounding box */
        const REAL minu = fmin(a0.x, fmin(a1.x, a2.x)), maxu = fmax(a0.x, fmax(a1.x, a2.x));
        const REAL minv = fmin(a0.y, fmin(a1.y, a2.y)), maxv = fmax(a0.y, fmax(a1.y, a2.y));
        centre_range(minu, maxu, width, &x0, &x1);
        centre_range(minv, maxv, height, &y0, &y1);
        if (maxu - (REAL)0.5 < (REAL)0 || maxv - (REAL)0.5 < (REAL)0 ||
            minu - (REAL)0.5 > (REAL)(width - 1) || minv - (REAL)0.5 > (REAL)(height - 1))
            x1 = -1;
    }
    int n = 0;
    if (x0 <= x1 && y0 <= y1) {
        const int tx0 = x0 / TILE, ty0 = y0 / TILE, tx1 = x1 / TILE, ty1 = y1 / TILE;
        face_bbox[4 * f] = tx0; face_bbox[4 * f + 1] = ty0;
        face_bbox[4 * f + 2] = tx1; face_bbox[4 * f + 3] = ty1;
        for (int ty = ty0; ty <= ty1; ++ty)
            for (int tx = tx0; tx <= tx1; ++tx)
                atomic_inc(&tile_count[ty * tiles_x + tx]);
        n = (tx1 - tx0 + 1) * (ty1 - ty0 + 1);
    }
    face_ntiles[f] = n;
}

__kernel void bin_fill(__global const REAL* vs,         // [N, 3]
                       __global const int* F,           // [M, 3]
                       __global const int* soft_edges,  // [M] bit k: edge k has the soft window (has_soft)
                       const int has_soft,
                       const int m, const int tiles_x, const int height,
                       __global const int* face_ntiles, // [M]
                       __global const int* face_bbox,   // [M, 4]
                       __global const int* face_off,    // [M + 1]
                       __global const int* tile_off,    // [T + 1]
                       __global int* tile_cursor,       // [T]  zeroed before the call
                       __global int* entry_face,        // [E]
                       __global REAL* entry_setup,      // [E, SETUP]
                       __global int* entry_rows,        // [E]  bit r: row r of the tile in the bounding box;
                                                        //      bits 8+: coverage estimate (quarter pixels)
                       __global int* face_entries)      // [E]
{
    const int f = get_global_id(0);
    if (f >= m || face_ntiles[f] == 0) return;
    const int i0 = F[3 * f], i1 = F[3 * f + 1], i2 = F[3 * f + 2];
    const REAL3 p0 = LOAD3(vs, i0), p1 = LOAD3(vs, i1), p2 = LOAD3(vs, i2);
    const REAL2 d1 = p1.xy - p0.xy, d2 = p2.xy - p0.xy;
    const REAL iA = (REAL)1 / cross2(d1, d2);
    REAL s[SETUP];
    s[0] = p0.x; s[1] = p0.y;
    s[2] = (d1.y - d2.y) * iA; s[3] = (d2.x - d1.x) * iA;
    s[4] = d2.y * iA;          s[5] = -d2.x * iA;
    s[6] = (REAL)1 / p0.z; s[7] = (REAL)1 / p1.z; s[8] = (REAL)1 / p2.z;
    s[9] = (REAL)1 / sqrt(s[2] * s[2] + s[3] * s[3]);
    s[10] = (REAL)1 / sqrt(s[4] * s[4] + s[5] * s[5]);
    s[11] = (REAL)1 / sqrt((s[2] + s[4]) * (s[2] + s[4]) + (s[3] + s[5]) * (s[3] + s[5]));
    if (has_soft) {  /* hard edges (no window) are marked by g_k = -1 */
        const int bits = soft_edges[f];
        if (!(bits & 1)) s[9] = (REAL)-1;
        if (!(bits & 2)) s[10] = (REAL)-1;
        if (!(bits & 4)) s[11] = (REAL)-1;
    }
    const int tx0 = face_bbox[4 * f], ty0 = face_bbox[4 * f + 1];
    const int tx1 = face_bbox[4 * f + 2], ty1 = face_bbox[4 * f + 3];
    /* the pixel rows whose centres lie in the bounding box (as bin_count) */
    const REAL minv = fmin(p0.y, fmin(p1.y, p2.y)), maxv = fmax(p0.y, fmax(p1.y, p2.y));
    int y0, y1;
    centre_range(minv, maxv, height, &y0, &y1);
    /* coverage estimate of each entry: the face's area shared evenly by its tiles, in quarter
     * pixels, at most the tile's (bin_depth_order) */
    const int cover = (int)fmin((REAL)0.5 * fabs((REAL)4 / iA) / (REAL)face_ntiles[f] + (REAL)0.5,
                                (REAL)(4 * TILE * TILE));
    int j = face_off[f];
    for (int ty = ty0; ty <= ty1; ++ty) {
        const int r0 = max(y0 - ty * TILE, 0), r1 = min(y1 - ty * TILE, TILE - 1);
        const int rows = ((2 << r1) - (1 << r0)) | (cover << 8);  /* bits r0 .. r1, coverage */
        for (int tx = tx0; tx <= tx1; ++tx) {
            const int t = ty * tiles_x + tx;
            const int e = tile_off[t] + atomic_inc(&tile_cursor[t]);
            entry_face[e] = f;
            entry_rows[e] = rows;
            for (int q = 0; q < SETUP; ++q) entry_setup[e * SETUP + q] = s[q];
            face_entries[j++] = e;
        }
    }
}

/* Per tile: the order in which the list builders visit its entries. The lists do not depend on it
 * (they keep the K nearest by (depth, face id)); the cost of their insertion does: visited nearest
 * first, a fragment behind a full list is dropped at its first test. So where the tile's lists
 * fill up — its estimated fragments per pixel (the entries' coverage estimates of bin_fill summed
 * over the tile's pixels) above K / 2, K > 1 — the entries go nearest
 * first (a counting sort of their nearest vertex, 1 / z = max(s6, s7, s8), into DEPTH_BUCKETS
 * buckets between the tile's nearest and farthest); elsewhere in the binning's order, which keeps
 * neighbouring faces together (depth order made the short lists of a surface-like soup slower).
 * 400^2, 100k faces, K = 30, 16-lane list build: a dense soup (~25 fragments per pixel) 12 ms
 * faster than in the binning's order (of 55), a surface-like one (~7) unchanged. */
#ifndef DEPTH_BUCKETS
#define DEPTH_BUCKETS 64
#endif
/* the entry's nearest vertex as 1 / z (set-up s6..s8), and its bucket (0: the tile's nearest) */
inline REAL nearest_inv_depth(__global const REAL* s) { return fmax(s[6], fmax(s[7], s[8])); }
inline int depth_bucket(__global const REAL* s, REAL kmax, REAL scale)
{
    return clamp((int)((kmax - nearest_inv_depth(s)) * scale), 0, DEPTH_BUCKETS - 1);
}
__kernel void bin_depth_order(__global const int* tile_off,      // [T + 1]
                              __global const REAL* entry_setup,  // [E, SETUP]
                              __global const int* entry_rows,    // [E]  bits 8+: estimated coverage
                              const int num_tiles, const int K,
                              __global int* entry_order)         // [E]  entries of tile t, in visiting order
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    REAL kmin = INFINITY, kmax = -INFINITY;
    int area = 0;  /* the tile's fragments, estimated (quarter pixels) */
    for (int e = e0; e < e1; ++e) {
        __global const REAL* s = entry_setup + e * SETUP;
        const REAL k = nearest_inv_depth(s);
        kmin = fmin(kmin, k);
        kmax = fmax(kmax, k);
        area += entry_rows[e] >> 8;
    }
    if (K < 2 || area <= 2 * K * TILE * TILE || !(kmax > kmin)) {  /* area / 4 <= K / 2 per pixel */  /* the binning's order */
        for (int e = e0; e < e1; ++e) entry_order[e] = e;
        return;
    }
    const REAL scale = (REAL)(DEPTH_BUCKETS - 1) / (kmax - kmin);
    int start[DEPTH_BUCKETS];
    for (int b = 0; b < DEPTH_BUCKETS; ++b) start[b] = 0;
    for (int e = e0; e < e1; ++e) {
        __global const REAL* s = entry_setup + e * SETUP;
        ++start[depth_bucket(s, kmax, scale)];
    }
    int n = e0;
    for (int b = 0; b < DEPTH_BUCKETS; ++b) { const int c = start[b]; start[b] = n; n += c; }
    for (int e = e0; e < e1; ++e) {
        __global const REAL* s = entry_setup + e * SETUP;
        entry_order[start[depth_bucket(s, kmax, scale)]++] = e;
    }
}

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
 * rows off[pix] + k, with the face, the perspective-correct barycentrics and (sigma > 0) the
 * coverage window computed from the entry's set-up:
 *   b0 = 1 + s2 dx + s3 dy,  b1 = s4 dx + s5 dy,  b2 = 1 - b0 - b1,  (dx, dy) = p - a0
 *   w_k = b_k / z_k,  lam_k = w_k / (w0 + w1 + w2)   (raster_math.h)
 *   win = setup_window(b0, b1, b2)                  (coverage.cl's formula)  */
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
                                    __global REAL* depth,             // [P]
                                    __global REAL* win)               // [P]  (sigma > 0)
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
        if (sigma > (REAL)0) win[o] = setup_window(s, b0, b1, b2, sigma);
    }
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
                             __global const REAL* s_win,       // [H, W, K]  (has_win)
                             const int has_win,
                             __global int* face,               // [P]
                             __global int* entry,              // [P]
                             __global REAL* bary,              // [P, 2]
                             __global REAL* depth,             // [P]
                             __global REAL* win)               // [P]  (has_win)
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
        if (has_win) win[o] = s_win[i];
    }
}

__kernel void gather_vertex(__global const REAL* partial_a,    // [E, a_stride]: [3, Ca] from a_off  (Ca > 0)
                            __global const REAL* partial_b,    // [E, b_stride]: [3, Cb] from b_off  (Cb > 0)
                            __global const int* entry_hit,     // [E]  0: no fragments, partials unset
                            __global const int* face_off,      // [M + 1]
                            __global const int* face_entries,  // [E]
                            __global const int* csr_off,       // [N + 1]
                            __global const int* csr_corner,    // [3M]  3 * face + corner
                            const int n, const int Ca, const int Cb, const int a_stride, const int a_off,
                            const int b_stride, const int b_off,
                            __global REAL* out_a,              // [N, Ca]
                            __global REAL* out_b)              // [N, Cb]
{
    /* one work-item per vertex, both partial arrays (attributes and geometry) in one walk of the
     * corner / entry indices */
    const int v = get_global_id(0);
    if (v >= n) return;
    __global REAL* oa = out_a + (long)v * Ca;
    __global REAL* ob = out_b + (long)v * Cb;
    for (int c = 0; c < Ca; ++c) oa[c] = (REAL)0;
    for (int c = 0; c < Cb; ++c) ob[c] = (REAL)0;
    for (int q = csr_off[v]; q < csr_off[v + 1]; ++q) {
        const int corner = csr_corner[q];
        const int f = corner / 3, i = corner - 3 * f;
        for (int j = face_off[f]; j < face_off[f + 1]; ++j) {
            const int e = face_entries[j];
            if (!entry_hit[e]) continue;
            __global const REAL* pa = partial_a + (long)e * a_stride + a_off + i * Ca;
            for (int c = 0; c < Ca; ++c) oa[c] += pa[c];
            __global const REAL* pb = partial_b + (long)e * b_stride + b_off + i * Cb;
            for (int c = 0; c < Cb; ++c) ob[c] += pb[c];
        }
    }
}

__kernel void gather_corner(__global const REAL* corner_a,     // [M, 3, Ca]
                            __global const REAL* corner_b,     // [M, 3, Cb]
                            __global const int* csr_off,       // [N + 1]
                            __global const int* csr_corner,    // [3M]  3 * face + corner
                            const int n, const int Ca, const int Cb,
                            __global REAL* out_a,              // [N, Ca]
                            __global REAL* out_b)              // [N, Cb]
{
    const int v = get_global_id(0);
    if (v >= n) return;
    __global REAL* oa = out_a + (long)v * Ca;
    __global REAL* ob = out_b + (long)v * Cb;
    for (int c = 0; c < Ca; ++c) oa[c] = (REAL)0;
    for (int c = 0; c < Cb; ++c) ob[c] = (REAL)0;
    for (int q = csr_off[v]; q < csr_off[v + 1]; ++q) {
        const long corner = csr_corner[q];
        for (int c = 0; c < Ca; ++c) oa[c] += corner_a[corner * Ca + c];
        for (int c = 0; c < Cb; ++c) ob[c] += corner_b[corner * Cb + c];
    }
}
