/* vertex_attr.cl — the per-vertex attribute array that the rasterizer interpolates, built on the
 * device from the raw parameters (render.py's VertexAttributes; the host chain Normals →
 * MaterialActivation → SigmoidHost → Concat computes the same and stays as its reference).
 *
 * Layout of attr [N, C] (C = 3 + 3 + NMAT + 1 (+ 6) (+ NCONST)):  pos | nrm | mat | alpha | vlight | const
 *   pos   = V
 *   nrm   = n[i]                  (the normal array, per vertex; FACE_NRM: per face, vertex i on face i / 3:
 *                                  a soup whose face f has the vertices 3f, 3f + 1, 3f + 2)
 *   mat_j = sigmoid(raw_j), or softplus(raw_j) where bit j of SOFTPLUS_MASK is set
 *   alpha = sigmoid(alpha_raw)
 *   vlight = the vertex-SH light values as given (HAS_VLIGHT)
 *   const = NCONST constant per-vertex columns as given (HAS_CONST; e.g. a cached visibility): no adjoint
 * sigmoid(x) = 1 / (1 + exp(-x)),  softplus(x) = max(x, 0) + log1p(exp(-|x|))  (activations.py)
 * Adjoint (v_attr given): v_pos = v_attr[pos], v_nrm = v_attr[nrm] (to the normals' adjoint, done by
 * normals.cl; FACE_NRM: face_sum3 sums the three corners of a face), v_raw_j = v_mat_j y (1 - y)
 * (sigmoid) or v_mat_j sigmoid(raw_j) (softplus), v_alpha_raw = v_alpha y (1 - y), v_vlight. The
 * sigmoids y are read back from the forward's attr (the same values: no exp per channel again).
 * Defines: NMAT, SOFTPLUS_MASK, FACE_NRM, HAS_VLIGHT, HAS_CONST with NCONST (default 0).
 * One work-item per 8 vertices in the forward (VA_LANES), per vertex in the adjoint, per face for face_sum3.
 */
#include "real.h"

#ifndef SOFTPLUS_MASK
#define SOFTPLUS_MASK 0
#endif
#ifdef HAS_VLIGHT
#define NVL 6
#else
#define NVL 0
#endif
#ifndef NCONST
#define NCONST 0
#endif
#define ATTR_C (3 + 3 + NMAT + 1 + NVL + NCONST)

inline REAL va_sigmoid(const REAL x) { return (REAL)1 / ((REAL)1 + exp(-x)); }
inline REAL8 va_sigmoid8(const REAL8 x) { return (REAL)1 / ((REAL)1 + exp(-x)); }
inline REAL8 va_softplus8(const REAL8 x) { return fmax(x, (REAL)0) + log1p(exp(-fabs(x))); }

#define VA_LANES 8

/* VA_LANES vertices per work-item (global size ceil(N / 8)): the activations of each channel are computed
 * for the 8 vertices at once as REAL8 lanes. The rows [i, ATTR_C] are strided, so PoCL's work-group loop
 * does not vectorise this kernel, and a scalar exp is then a library call per value (2.2 ms of 2.8 ms at
 * 60k vertices); the REAL8 builtins are vector code (bench/results/fast_math_pocl_2026-11-28.txt). */
__kernel void vertex_attr_fwd(__global const REAL* V,          // [N, 3]
                              __global const REAL* nrm,        // [N, 3] ([M, 3] with FACE_NRM)
                              __global const REAL* mat_raw,    // [N, NMAT]
                              __global const REAL* alpha_raw,  // [N]
#ifdef HAS_VLIGHT
                              __global const REAL* vlight,     // [N, 6]
#endif
#ifdef HAS_CONST
                              __global const REAL* cst,        // [N, NCONST]
#endif
                              const int N,
                              __global REAL* attr)             // [N, ATTR_C]
{
    const int i0 = get_global_id(0) * VA_LANES;
    if (i0 >= N) return;
    const int n = min(VA_LANES, N - i0);
    REAL act[VA_LANES * (NMAT + 1)];  /* vertex k's activated channel j at [k * (NMAT + 1) + j] (j = NMAT: alpha) */
    for (int j = 0; j <= NMAT; ++j) {
        /* the lanes built and taken apart component by component: through a private array and vload8 / vstore8
         * the kernel measured no faster than the scalar one (2.0 against 1.1 ms); lanes past N repeat the last
         * vertex (not written) */
#define VA_RAW(k) (j < NMAT ? mat_raw[(long)(i0 + min(k, n - 1)) * NMAT + j] : alpha_raw[i0 + min(k, n - 1)])
        const REAL8 xv = (REAL8)(VA_RAW(0), VA_RAW(1), VA_RAW(2), VA_RAW(3), VA_RAW(4), VA_RAW(5), VA_RAW(6),
                                 VA_RAW(7));
#undef VA_RAW
        const REAL8 y = (j < NMAT && ((SOFTPLUS_MASK >> j) & 1)) ? va_softplus8(xv) : va_sigmoid8(xv);
        act[j] = y.s0;
        act[(NMAT + 1) + j] = y.s1;
        act[2 * (NMAT + 1) + j] = y.s2;
        act[3 * (NMAT + 1) + j] = y.s3;
        act[4 * (NMAT + 1) + j] = y.s4;
        act[5 * (NMAT + 1) + j] = y.s5;
        act[6 * (NMAT + 1) + j] = y.s6;
        act[7 * (NMAT + 1) + j] = y.s7;
    }
    for (int k = 0; k < n; ++k) {
        const int i = i0 + k;
        __global REAL* a = attr + (long)i * ATTR_C;
#ifdef FACE_NRM
        const long ni = i / 3;
#else
        const long ni = i;
#endif
        for (int c = 0; c < 3; ++c) {
            a[c] = V[(long)i * 3 + c];
            a[3 + c] = nrm[ni * 3 + c];
        }
        for (int j = 0; j <= NMAT; ++j) a[6 + j] = act[k * (NMAT + 1) + j];
#ifdef HAS_VLIGHT
        for (int c = 0; c < 6; ++c) a[7 + NMAT + c] = vlight[(long)i * 6 + c];
#endif
#ifdef HAS_CONST
        for (int c = 0; c < NCONST; ++c) a[7 + NMAT + NVL + c] = cst[(long)i * NCONST + c];
#endif
    }
}

__kernel void vertex_attr_bwd(__global const REAL* mat_raw,    // [N, NMAT]  (read for softplus channels only)
                              __global const REAL* attr,       // [N, ATTR_C] the forward's output
                              __global const REAL* v_attr,     // [N, ATTR_C]
                              const int N,
                              __global REAL* v_pos,            // [N, 3]
                              __global REAL* v_nrm,            // [N, 3]
                              __global REAL* v_mat_raw,        // [N, NMAT]
#ifdef HAS_VLIGHT
                              __global REAL* v_vlight,         // [N, 6]
#endif
                              __global REAL* v_alpha_raw)      // [N]
{
    const int i = get_global_id(0);
    if (i >= N) return;
    __global const REAL* g = v_attr + (long)i * ATTR_C;
    __global const REAL* y = attr + (long)i * ATTR_C;
    for (int c = 0; c < 3; ++c) {
        v_pos[(long)i * 3 + c] = g[c];
        v_nrm[(long)i * 3 + c] = g[3 + c];
    }
    for (int j = 0; j < NMAT; ++j) {
        REAL d;
        if ((SOFTPLUS_MASK >> j) & 1) {
            d = va_sigmoid(mat_raw[(long)i * NMAT + j]);
        } else {
            const REAL yj = y[6 + j];
            d = yj * ((REAL)1 - yj);
        }
        v_mat_raw[(long)i * NMAT + j] = g[6 + j] * d;
    }
    const REAL ya = y[6 + NMAT];
    v_alpha_raw[i] = g[6 + NMAT] * ya * ((REAL)1 - ya);
#ifdef HAS_VLIGHT
    for (int c = 0; c < 6; ++c) v_vlight[(long)i * 6 + c] = g[7 + NMAT + c];
#endif
}

/* out[f] = x[3f] + x[3f + 1] + x[3f + 2]  ([M, 3] from [3M, 3]): the adjoint of a soup's per-corner
 * copy of its face normal */
__kernel void face_sum3(__global const REAL* x,   // [3M, 3]
                        const int M,
                        __global REAL* out)       // [M, 3]
{
    const int f = get_global_id(0);
    if (f >= M) return;
    for (int c = 0; c < 3; ++c)
        out[(long)f * 3 + c] = x[(long)(3 * f) * 3 + c] + x[(long)(3 * f + 1) * 3 + c] + x[(long)(3 * f + 2) * 3 + c];
}
