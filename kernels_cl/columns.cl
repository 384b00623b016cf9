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
