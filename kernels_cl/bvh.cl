/* bvh.cl — refit of the bounding-volume hierarchy over a triangle soup (bottom-up, no atomics).
 *
 * Layout (built on the host, triplet_cl/ops/bvh.py): an implicit complete binary tree in heap order
 * over P = 2^D leaves, 2P - 1 nodes; node n has children 2n + 1 and 2n + 2, level l holds nodes
 * [2^l - 1, 2^(l+1) - 1), leaf j is node P - 1 + j. Faces are stored in Morton order of their
 * centroids (prim [M]); leaf j owns prim[s(j) .. s(j+1)), s(j) = floor(j M / P): every leaf holds
 * floor(M/P) or ceil(M/P) faces (none when M < P and j has an empty range).
 *
 * Forward (no adjoint: the hierarchy is discrete, it only decides which triangles are tested):
 *   leaf bounds   lo = min over the leaf's vertices - pad,  hi = max + pad,
 *                 pad = 1e-6 (|lo| + |hi|) + 1e-30  (so rounding in the ray/box slab test cannot
 *                 miss a triangle touching the box surface); empty leaf: lo = +BIG, hi = -BIG.
 *   internal      lo = min(lo_left, lo_right), hi = max(hi_left, hi_right), one kernel launch per
 *                 level from the leaves up (the launch order is the synchronisation: no atomics).
 * nodes [2P - 1, 6] = (lo.x, lo.y, lo.z, hi.x, hi.y, hi.z).
 */
#include "real.h"

#define BVH_BIG ((REAL)1e30)

__kernel void bvh_leaf_bounds(__global const REAL* V,     // [N, 3]
                              __global const int* F,      // [M, 3]
                              __global const int* prim,   // [M]
                              const int M, const int P,
                              __global REAL* nodes)       // [2P - 1, 6]
{
    const int j = get_global_id(0);
    if (j >= P) return;
    const int s0 = (int)(((long)j * M) / P), s1 = (int)(((long)(j + 1) * M) / P);
    REAL3 lo = (REAL3)(BVH_BIG), hi = (REAL3)(-BVH_BIG);
    for (int i = s0; i < s1; ++i) {
        const int f = prim[i];
        for (int c = 0; c < 3; ++c) {
            const REAL3 p = LOAD3(V, F[3 * f + c]);
            lo = fmin(lo, p);
            hi = fmax(hi, p);
        }
    }
    if (s1 > s0) {
        const REAL3 pad = (REAL)1e-6 * (fabs(lo) + fabs(hi)) + (REAL)1e-30;
        lo -= pad;
        hi += pad;
    }
    __global REAL* o = nodes + (long)(P - 1 + j) * 6;
    o[0] = lo.x; o[1] = lo.y; o[2] = lo.z;
    o[3] = hi.x; o[4] = hi.y; o[5] = hi.z;
}

__kernel void bvh_level_bounds(const int first, const int count,  // nodes [first, first + count)
                               __global REAL* nodes)              // [2P - 1, 6]
{
    const int i = get_global_id(0);
    if (i >= count) return;
    const int n = first + i;
    __global const REAL* a = nodes + (long)(2 * n + 1) * 6;
    __global const REAL* b = a + 6;
    __global REAL* o = nodes + (long)n * 6;
    for (int c = 0; c < 3; ++c) {
        o[c] = fmin(a[c], b[c]);
        o[3 + c] = fmax(a[3 + c], b[3 + c]);
    }
}
