/* columns.cl — move channel blocks between per-fragment arrays (split / pack / their adjoints).
 *
 * Forward:  dst[o, cd0 + j] = src[o, cs0 + j]        j < n, for the first frag_count slots of
 *           (or += with accumulate; or = 0 when has_src = 0)      each pixel
 * Adjoint:  the same copy in the other direction (a split's adjoint is a pack and vice versa).
 * Slots k >= frag_count are never touched (see Fragments in triplet_cl/ops/raster.py).
 */
#include "real.h"

__kernel void copy_columns(__global const REAL* src,       // [H, W, K, Cs]  (has_src)
                           const int Cs, const int cs0,
                           __global REAL* dst,             // [H, W, K, Cd]
                           const int Cd, const int cd0, const int n,
                           __global const int* frag_count, // [H, W]
                           const int npix, const int K, const int has_src, const int accumulate)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int cnt = frag_count[pix];
    for (int k = 0; k < cnt; ++k) {
        const long o = (long)pix * K + k;
        __global REAL* d = dst + o * Cd + cd0;
        if (!has_src) {
            for (int j = 0; j < n; ++j) d[j] = (REAL)0;
            continue;
        }
        __global const REAL* s = src + o * Cs + cs0;
        if (accumulate)
            for (int j = 0; j < n; ++j) d[j] += s[j];
        else
            for (int j = 0; j < n; ++j) d[j] = s[j];
    }
}

/* Compaction of the valid fragment slots into a dense list (and back), so that per-fragment work
 * whose cost does not depend on the pixel (shading) runs on the fragments only, not on H·W·K slots.
 *   offsets[pix] = sum of frag_count over the pixels before pix (exclusive prefix sum)
 *   pack:    dst[offsets[pix] + k, j] = src[pix, k, cs0 + j]          k < frag_count[pix]
 *   unpack:  dst[pix, k, cd0 + j] = src[offsets[pix] + k, j]          (the adjoint of pack)
 */
__kernel void pack_rows(__global const REAL* src,       // [H, W, K, Cs]
                        const int Cs, const int cs0, const int n,
                        __global const int* offsets,    // [H*W + 1]
                        __global const int* frag_count, // [H, W]
                        const int npix, const int K,
                        __global REAL* dst)             // [Pv, n]
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int cnt = frag_count[pix], base = offsets[pix];
    for (int k = 0; k < cnt; ++k) {
        __global const REAL* s = src + ((long)pix * K + k) * Cs + cs0;
        __global REAL* d = dst + (long)(base + k) * n;
        for (int j = 0; j < n; ++j) d[j] = s[j];
    }
}

__kernel void unpack_rows(__global const REAL* src,     // [Pv, n]
                          const int n,
                          __global const int* offsets,  // [H*W + 1]
                          __global const int* frag_count,
                          const int npix, const int K,
                          __global REAL* dst,           // [H, W, K, Cd]
                          const int Cd, const int cd0)
{
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int cnt = frag_count[pix], base = offsets[pix];
    for (int k = 0; k < cnt; ++k) {
        __global const REAL* s = src + (long)(base + k) * n;
        __global REAL* d = dst + ((long)pix * K + k) * Cd + cd0;
        for (int j = 0; j < n; ++j) d[j] = s[j];
    }
}
