/* silhouette.cl — the soft-edge bit masks of a connected mesh seen from an eye, on the device
 * (triplet_cl/ops/silhouette.py; the host reference is tests/reference/silhouette.py).
 *
 * face_front: one work-item per face f: front[f] = 1 where the face's raw normal
 *   c = (v1 − v0) × (v2 − v0) points towards the eye from its centroid: dot(c, eye − (v0 + v1 + v2)/3) > 0.
 * silhouette_bits: one work-item per face f: bit k of soft[f] is set where edge k (opposite vertex k) is on
 *   the silhouette: the face across it, nb[f, k], faces the eye differently, or nb < 0 (a boundary, −1, or a
 *   non-manifold edge, −2).
 * The front test is made in REAL (the host reference in double): only a face seen exactly edge-on can differ.
 */
#include "real.h"

__kernel void face_front(__global const REAL* V,   // [N, 3]
                         __global const int* F,    // [M, 3]
                         const int M,
                         const REAL ex, const REAL ey, const REAL ez,  // the eye
                         __global uchar* front)    // [M]
{
    const int f = get_global_id(0);
    if (f >= M) return;
    const REAL3 a = LOAD3(V, F[3 * f]), b = LOAD3(V, F[3 * f + 1]), c = LOAD3(V, F[3 * f + 2]);
    const REAL3 n = cross(b - a, c - a);
    const REAL3 eye = (REAL3)(ex, ey, ez);
    front[f] = (uchar)(dot(n, eye - (a + b + c) / (REAL)3) > (REAL)0);
}

__kernel void silhouette_bits(__global const uchar* front,  // [M]
                              __global const int* nb,       // [M, 3] face across edge k (−1, −2: none)
                              const int M,
                              __global int* soft)           // [M] 3-bit masks
{
    const int f = get_global_id(0);
    if (f >= M) return;
    const uchar me = front[f];
    int bits = 0;
    for (int k = 0; k < 3; ++k) {
        const int o = nb[3 * f + k];
        if (o < 0 || front[o] != me) bits |= 1 << k;
    }
    soft[f] = bits;
}
