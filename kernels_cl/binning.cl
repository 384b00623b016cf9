/* binning.cl — faces binned into TILE x TILE screen tiles: the (tile, face) "entries" that the
 * list builders (raster.cl, blend.cl, trace.cl's packing) and the atomics-free adjoints
 * (fragment_bwd.cl, blend.cl) walk. Host side: ops/binning.py.
 *
 * Tiles are TILE x TILE pixels (TILE = 8 unless defined). One "entry" is one (tile, face) pair.
 *
 * bin_count   per face: cull (any vertex z < near, all z > far, |A| tiny, back-facing when
 *             cull_back, no pixel centre in its bounding box); count the tiles of its bounding box;
 *             atomically count faces per tile (int atomics only: core OpenCL 1.1).
 * bin_fill    per face: write the entries of each overlapped tile (tile-major lists, their order
 *             inside a tile is arbitrary) with the face's edge-function set-up, and the face-major
 *             list face_entries (entry ids of each face, in tile order) used by the adjoint gather.
 *             With SOFT_EDGES defined, only the edges marked in soft_edges get the coverage window
 *             (the silhouette edges of a connected mesh: its shared interior edges stay hard, no
 *             seams). Per entry also entry_rows: the tile rows inside the face's pixel bounding box
 *             (the list builders skip the entry elsewhere) and a coverage estimate (upper bits).
 * bin_depth_order  per tile: the order in which the list builders visit its entries (nearest
 *             first where its lists fill up, else the binning's order; the lists do not depend on it).
 */
/* No a*b+c contraction into FMA: the set-up must be the same numbers the raster kernels were
 * written against (raster.cl, blend.cl compile with FP_CONTRACT OFF too). */
#pragma OPENCL FP_CONTRACT OFF

#include "real.h"
#include "raster_math.h"

#ifndef TILE
#define TILE 8
#endif
#define SETUP 12 /* a0x a0y  A0 B0  A1 B1  iz0 iz1 iz2  g0 g1 g2 :  b0 = 1 + A0 dx + B0 dy,
                     b1 = A1 dx + B1 dy, g_k = 1 / |grad b_k| (pixel distance to edge k = b_k g_k) */


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
#ifdef SOFT_EDGES
                       __global const int* soft_edges,  // [M] bit k: edge k has the soft window
#endif
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
#ifdef SOFT_EDGES
    {  /* hard edges (no window) are marked by g_k = -1 */
        const int bits = soft_edges[f];
        if (!(bits & 1)) s[9] = (REAL)-1;
        if (!(bits & 2)) s[10] = (REAL)-1;
        if (!(bits & 4)) s[11] = (REAL)-1;
    }
#endif
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
