/* reduce.cl — block sums, the smallest real kernel of the project (used by the loader tests and
 * for loss sums).
 *
 * Forward:  out[g] = sum_{i in block g} x[i]   (block = one work-group, tree reduction in local
 *           memory; the host sums the per-group partials).
 * Adjoint:  v_x[i] = v_out[group of i]         (a broadcast; for a full sum v_x = v_total).
 */
#include "real.h"

__kernel void block_sum_fwd(__global const REAL* x,   // [N]
                            const int n,
                            __global REAL* out,       // [num_groups]
                            __local REAL* scratch)    // [local_size]
{
    const int lid = get_local_id(0);
    const int lsz = get_local_size(0);
    REAL acc = (REAL)0;
    for (int i = get_global_id(0); i < n; i += get_global_size(0))
        acc += x[i];
    scratch[lid] = acc;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = lsz / 2; s > 0; s >>= 1) {
        if (lid < s) scratch[lid] += scratch[lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0) out[get_group_id(0)] = scratch[0];
}

__kernel void block_sum_bwd(__global const REAL* v_out,  // [num_groups]
                            const int n,
                            __global REAL* v_x)          // [N]
{
    /* Every element of the grid-stride loop of group g contributed to out[g]. */
    const int g = get_group_id(0);
    for (int i = get_global_id(0); i < n; i += get_global_size(0))
        v_x[i] = v_out[g];
}
