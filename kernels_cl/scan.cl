/* scan.cl — exclusive prefix sums of int counts as offsets, for CPU devices (ops/raster.py's
 * _offsets; GPUs take pyopencl's work-efficient scan).
 *
 *   off[0] = 0,  off[i + 1] = off[i] + counts[i]   (i < n),  off[n] = the total
 *
 * Up to a few hundred thousand counts in one launch and one work-item (scan_block_write as a
 * single block); beyond, in three launches over NB blocks of `block` consecutive counts: the
 * blocks' sums (one work-item each), their exclusive scan (one work-item: NB values), then each
 * block's own running sum from its offset. A CPU core streams through memory once per phase; PoCL
 * spends ~0.1 ms per launch. (pyopencl's GPU-shaped scan took 0.2 / 0.64 / 3.3 ms for 2.5k / 100k /
 * 1M counts on PoCL, 2 cores; these 0.10-0.13 / 0.15-0.19 / 0.37-0.56 ms.)
 * Integer sums: no adjoint.
 */

__kernel void scan_block_sums(__global const int* counts,  // [n]
                              const int n, const int block, const int nb,
                              __global int* sums)          // [nb]
{
    const int b = get_global_id(0);
    if (b >= nb) return;
    const int i1 = min(n, (b + 1) * block);
    int s = 0;
    for (int i = b * block; i < i1; ++i) s += counts[i];
    sums[b] = s;
}

__kernel void scan_block_offsets(__global int* sums,       // [nb]  in: block sums; out: exclusive scan
                                 const int nb)
{
    if (get_global_id(0) != 0) return;
    int run = 0;
    for (int b = 0; b < nb; ++b) {
        const int s = sums[b];
        sums[b] = run;
        run += s;
    }
}

/* Block b's offsets from the exclusive scan of the block sums (block 0 starts at 0 and reads no
 * sum: with one block, block = n, this is the whole serial scan); the last block writes off[n]. */
__kernel void scan_block_write(__global const int* counts, // [n]
                               const int n, const int block, const int nb,
                               __global const int* sums,   // [nb]  exclusive scan of the block sums (nb > 1)
                               __global int* off)          // [n + 1]
{
    const int b = get_global_id(0);
    if (b >= nb) return;
    const int i1 = min(n, (b + 1) * block);
    int run = b > 0 ? sums[b] : 0;
    for (int i = b * block; i < i1; ++i) {
        off[i] = run;
        run += counts[i];
    }
    if (i1 == n) off[n] = run;
}
