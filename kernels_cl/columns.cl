/* columns.cl — move channel blocks between per-fragment arrays (split / pack / their adjoints).
 *
 * Forward:  dst[o, cd0 + j] = src[o, cs0 + j]        j < n, every fragment o < P
 *           (or += with accumulate; or = 0 when has_src = 0)
 * Adjoint:  the same copy in the other direction (a split's adjoint is a pack and vice versa).
 * Per-fragment arrays are packed [P, C] (see Fragments in triplet_cl/ops/raster.py).
 */
#include "real.h"

__kernel void copy_columns(__global const REAL* src,       // [P, Cs]  (has_src)
                           const int Cs, const int cs0,
                           __global REAL* dst,             // [P, Cd]
                           const int Cd, const int cd0, const int n,
                           const int P, const int has_src, const int accumulate)
{
    const int o = get_global_id(0);
    if (o >= P) return;
    __global REAL* d = dst + (long)o * Cd + cd0;
    if (!has_src) {
        for (int j = 0; j < n; ++j) d[j] = (REAL)0;
        return;
    }
    __global const REAL* s = src + (long)o * Cs + cs0;
    if (accumulate)
        for (int j = 0; j < n; ++j) d[j] += s[j];
    else
        for (int j = 0; j < n; ++j) d[j] = s[j];
}

/* split_columns / merge_columns: up to 8 channel blocks in one pass over the fragments (the shading
 * inputs pos | nrm | mat | alpha | vlight | ... of the packed attributes, and their adjoints):
 *   split:  d_k[o, j] = src[o, c_k + j]        j < n_k
 *   merge:  dst[o, c_k + j] = s_k[o, j]        j < n_k
 * A block with n_k = 0 is absent (its buffer is a placeholder, never touched). One read of each
 * source row instead of one per block (copy_columns). SPLIT_BLOCKS in ops/columns.py matches. */
#define SPLIT_BLOCK(d, c, n) for (int j = 0; j < (n); ++j) (d)[(long)o * (n) + j] = s[(c) + j];
#define MERGE_BLOCK(s, c, n) for (int j = 0; j < (n); ++j) d[(c) + j] = (s)[(long)o * (n) + j];
#define BLOCK_ARG(q, k) __global q REAL* b##k, const int c##k, const int n##k

__kernel void split_columns(__global const REAL* src,       // [P, Cs]
                            const int Cs, const int P,
                            BLOCK_ARG(, 0), BLOCK_ARG(, 1), BLOCK_ARG(, 2), BLOCK_ARG(, 3),   // b_k [P, n_k]
                            BLOCK_ARG(, 4), BLOCK_ARG(, 5), BLOCK_ARG(, 6), BLOCK_ARG(, 7))
{
    const int o = get_global_id(0);
    if (o >= P) return;
    __global const REAL* s = src + (long)o * Cs;
    SPLIT_BLOCK(b0, c0, n0) SPLIT_BLOCK(b1, c1, n1) SPLIT_BLOCK(b2, c2, n2) SPLIT_BLOCK(b3, c3, n3)
    SPLIT_BLOCK(b4, c4, n4) SPLIT_BLOCK(b5, c5, n5) SPLIT_BLOCK(b6, c6, n6) SPLIT_BLOCK(b7, c7, n7)
}

__kernel void merge_columns(__global REAL* dst,             // [P, Cd]
                            const int Cd, const int P,
                            BLOCK_ARG(const, 0), BLOCK_ARG(const, 1), BLOCK_ARG(const, 2), BLOCK_ARG(const, 3),
                            BLOCK_ARG(const, 4), BLOCK_ARG(const, 5), BLOCK_ARG(const, 6), BLOCK_ARG(const, 7))
{
    const int o = get_global_id(0);
    if (o >= P) return;
    __global REAL* d = dst + (long)o * Cd;
    MERGE_BLOCK(b0, c0, n0) MERGE_BLOCK(b1, c1, n1) MERGE_BLOCK(b2, c2, n2) MERGE_BLOCK(b3, c3, n3)
    MERGE_BLOCK(b4, c4, n4) MERGE_BLOCK(b5, c5, n5) MERGE_BLOCK(b6, c6, n6) MERGE_BLOCK(b7, c7, n7)
}
