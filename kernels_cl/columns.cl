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

/* split_columns / merge_columns: up to SPLIT_BLOCKS channel blocks in one pass over the fragments
 * (the shading inputs pos | nrm | mat | alpha | vlight of the packed attributes, and their adjoints):
 *   split:  d_k[o, j] = src[o, c_k + j]        j < n_k
 *   merge:  dst[o, c_k + j] = s_k[o, j]        j < n_k
 * A block with n_k = 0 is absent (its buffer is a placeholder, never touched). One read of each
 * source row instead of one per block (copy_columns). */
#define SPLIT_BLOCK(d, c, n) for (int j = 0; j < (n); ++j) (d)[(long)o * (n) + j] = s[(c) + j];
#define MERGE_BLOCK(s, c, n) for (int j = 0; j < (n); ++j) d[(c) + j] = (s)[(long)o * (n) + j];

__kernel void split_columns(__global const REAL* src,       // [P, Cs]
                            const int Cs, const int P,
                            __global REAL* d0, const int c0, const int n0,   // [P, n0]
                            __global REAL* d1, const int c1, const int n1,
                            __global REAL* d2, const int c2, const int n2,
                            __global REAL* d3, const int c3, const int n3,
                            __global REAL* d4, const int c4, const int n4)
{
    const int o = get_global_id(0);
    if (o >= P) return;
    __global const REAL* s = src + (long)o * Cs;
    SPLIT_BLOCK(d0, c0, n0)
    SPLIT_BLOCK(d1, c1, n1)
    SPLIT_BLOCK(d2, c2, n2)
    SPLIT_BLOCK(d3, c3, n3)
    SPLIT_BLOCK(d4, c4, n4)
}

__kernel void merge_columns(__global REAL* dst,             // [P, Cd]
                            const int Cd, const int P,
                            __global const REAL* s0, const int c0, const int n0,   // [P, n0]
                            __global const REAL* s1, const int c1, const int n1,
                            __global const REAL* s2, const int c2, const int n2,
                            __global const REAL* s3, const int c3, const int n3,
                            __global const REAL* s4, const int c4, const int n4)
{
    const int o = get_global_id(0);
    if (o >= P) return;
    __global REAL* d = dst + (long)o * Cd;
    MERGE_BLOCK(s0, c0, n0)
    MERGE_BLOCK(s1, c1, n1)
    MERGE_BLOCK(s2, c2, n2)
    MERGE_BLOCK(s3, c3, n3)
    MERGE_BLOCK(s4, c4, n4)
}
