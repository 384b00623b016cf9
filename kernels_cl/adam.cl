/* adam.cl — one Adam update of a parameter buffer (triplet_cl/optim.py's numpy step, fused).
 *
 * Per element, in REAL arithmetic, in the order numpy evaluates the reference (optim.Adam.step,
 * scalars rounded to REAL on the host the way numpy casts a python float against a REAL array):
 *   g  = grad · coef                      (coef: the group's clipping factor, 1 when not clipping)
 *   m  = m · β1 + (1 − β1) · g
 *   v  = v · β2 + ((1 − β2) · g) · g
 *   x  = x − ((lr / (1 − β1^t)) · m) / (sqrt(v / (1 − β2^t)) + eps)
 * `nonfinite` is set when a new x is NaN/Inf (Adam.step's finiteness guard).
 * FP_CONTRACT is off so no multiply-add is fused: the result matches numpy bit for bit where the
 * device's division and square root are correctly rounded (PoCL on the CPU), else to a few ulp.
 */
#include "real.h"

#pragma OPENCL FP_CONTRACT OFF

__kernel void adam_step(__global REAL* x,          // [n] parameter (updated)
                        __global REAL* m,          // [n] first moment (updated)
                        __global REAL* v,          // [n] second moment (updated)
                        __global const REAL* grad, // [n]
                        const int n,
                        const REAL coef, const REAL beta1, const REAL one_minus_beta1,
                        const REAL beta2, const REAL one_minus_beta2,
                        const REAL step_size,      // lr / (1 − β1^t)
                        const REAL bias2,          // 1 − β2^t
                        const REAL eps,
                        __global int* nonfinite)   // [1] set to 1 when an updated x is NaN/Inf
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const REAL g = grad[i] * coef;
    REAL mi = m[i] * beta1;
    mi = mi + one_minus_beta1 * g;
    REAL vi = v[i] * beta2;
    const REAL gb = one_minus_beta2 * g;
    vi = vi + gb * g;
    m[i] = mi;
    v[i] = vi;
    const REAL num = step_size * mi;
    const REAL den = sqrt(vi / bias2) + eps;
    const REAL xi = x[i] - num / den;
    x[i] = xi;
    if (!isfinite(xi)) *nonfinite = 1;  // every writer stores 1: no atomic needed
}
