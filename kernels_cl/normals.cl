/* normals.cl — face and (area-weighted) vertex normals with adjoints back to the vertices.
 *
 * Forward:
 *   c_f = (v1 - v0) x (v2 - v0)                       unnormalised cross product of face f [M, 3]
 *   face normal      n_f = safe_normalize(c_f)
 *   vertex normal    n_v = safe_normalize(s_v),  s_v = sum_{faces f incident to v} c_f
 *                    (|c_f| = 2 area, so the sum is area weighted)
 *
 * Adjoint (e1 = v1 - v0, e2 = v2 - v0):
 *   v_c_f = safe_normalize_vjp(c_f, v_n_f)                       (face normals)
 *   v_s_v = safe_normalize_vjp(s_v, v_n_v),  v_c_f = sum_{corners of f} v_s_{F[f, corner]}  (vertex)
 *   v_e1 = e2 x v_c,  v_e2 = v_c x e1
 *   corner gradients: v_v0 = -v_e1 - v_e2, v_v1 = v_e1, v_v2 = v_e2          [M, 3 corners, 3]
 *   v_V[v] = sum over the corners of v (CSR table of triplet_cl/topology.py)  — a gather, no atomics.
 *
 * Kernels: face_normals_fwd (cross or unit normal per face), face_normals_bwd (corner gradients),
 * vertex_normals_fwd / vertex_normals_bwd (per-vertex gather of c_f and its adjoint),
 * face_gather_vertex (v_c_f = sum over the 3 vertices of f), corner_gather (corners -> vertices).
 */
#include "real.h"
#include "shade_math.h"

__kernel void face_normals_fwd(__global const REAL* V,  // [N, 3]
                               __global const int* F,   // [M, 3]
                               const int M,
                               const int unit,          // 1: unit normal, 0: raw cross product
                               __global REAL* out)      // [M, 3]
{
    const int f = get_global_id(0);
    if (f >= M) return;
    const REAL3 v0 = LOAD3(V, F[3 * f]), v1 = LOAD3(V, F[3 * f + 1]), v2 = LOAD3(V, F[3 * f + 2]);
    const REAL3 c = cross(v1 - v0, v2 - v0);
    STORE3(unit ? safe_normalize(c) : c, out, f);
}

__kernel void face_normals_bwd(__global const REAL* V,     // [N, 3]
                               __global const int* F,      // [M, 3]
                               const int M,
                               const int unit,             // 1: v_n is the adjoint of the unit normal
                               __global const REAL* v_n,   // [M, 3]
                               __global REAL* v_corner)    // [M, 3, 3]
{
    const int f = get_global_id(0);
    if (f >= M) return;
    const REAL3 v0 = LOAD3(V, F[3 * f]), v1 = LOAD3(V, F[3 * f + 1]), v2 = LOAD3(V, F[3 * f + 2]);
    const REAL3 e1 = v1 - v0, e2 = v2 - v0;
    REAL3 v_c = LOAD3(v_n, f);
    if (unit) v_c = safe_normalize_vjp(cross(e1, e2), v_c);
    REAL3 v_e1 = (REAL3)(0), v_e2 = (REAL3)(0);
    cross_vjp(e1, e2, v_c, &v_e1, &v_e2);
    STORE3(-v_e1 - v_e2, v_corner, 3 * f);
    STORE3(v_e1, v_corner, 3 * f + 1);
    STORE3(v_e2, v_corner, 3 * f + 2);
}

/* s_v = sum of the face cross products around v (corners encoded 3 * face + corner). */
inline REAL3 gather_faces(__global const REAL* fc, __global const int* offsets, __global const int* corners,
                          const int v)
{
    REAL3 s = (REAL3)(0);
    for (int i = offsets[v]; i < offsets[v + 1]; ++i) s += LOAD3(fc, corners[i] / 3);
    return s;
}

__kernel void vertex_normals_fwd(__global const REAL* fc,      // [M, 3] face cross products
                                 __global const int* offsets,  // [N + 1]
                                 __global const int* corners,  // [3M]
                                 const int N,
                                 __global REAL* out)           // [N, 3]
{
    const int v = get_global_id(0);
    if (v >= N) return;
    STORE3(safe_normalize(gather_faces(fc, offsets, corners, v)), out, v);
}

__kernel void vertex_normals_bwd(__global const REAL* fc,      // [M, 3]
                                 __global const int* offsets,  // [N + 1]
                                 __global const int* corners,  // [3M]
                                 const int N,
                                 __global const REAL* v_n,     // [N, 3]
                                 __global REAL* v_s)           // [N, 3]
{
    const int v = get_global_id(0);
    if (v >= N) return;
    STORE3(safe_normalize_vjp(gather_faces(fc, offsets, corners, v), LOAD3(v_n, v)), v_s, v);
}

__kernel void face_gather_vertex(__global const int* F,      // [M, 3]
                                 const int M,
                                 __global const REAL* v_s,   // [N, 3]
                                 __global REAL* v_c)         // [M, 3]
{
    const int f = get_global_id(0);
    if (f >= M) return;
    STORE3(LOAD3(v_s, F[3 * f]) + LOAD3(v_s, F[3 * f + 1]) + LOAD3(v_s, F[3 * f + 2]), v_c, f);
}

__kernel void corner_gather(__global const int* offsets,     // [N + 1]
                            __global const int* corners,     // [3M]
                            const int N,
                            __global const REAL* v_corner,   // [M, 3, 3]
                            __global REAL* v_V)              // [N, 3]
{
    const int v = get_global_id(0);
    if (v >= N) return;
    REAL3 s = (REAL3)(0);
    for (int i = offsets[v]; i < offsets[v + 1]; ++i) s += LOAD3(v_corner, corners[i]);
    STORE3(s, v_V, v);
}
