/* face_visibility.cl — density control's per-view visibility from the packed fragments, on the
 * device (triplet_cl/ops/face_visibility.py), so that the [P] face ids stay where the rasterizer
 * wrote them; the host functions density.visible_faces / density.front_faces are the reference.
 *
 * visible_mark: one work-item per packed fragment i: vis[face[i]] = 1 for 0 <= face[i] < M
 *   (vis zeroed first; every writer stores the same byte, so the order does not matter: no atomics).
 * front_face: one work-item per pixel p, its fragments at rows off[p] .. off[p] + count[p] − 1
 *   (nearest first): front[p] = the first face id (FACE_OK: the first face f >= 0 with
 *   face_ok[f] != 0, i.e. alpha >= the threshold, decided on the host), −1 if none.
 * Integers only: the results are exact.
 */

__kernel void visible_mark(__global const int* face,   // [P] packed fragment face ids (−1: empty)
                           const int P,
                           const int M,
                           __global uchar* vis)        // [M] zeroed, set to 1 where seen
{
    const int i = get_global_id(0);
    if (i >= P) return;
    const int f = face[i];
    if (f >= 0 && f < M) vis[f] = (uchar)1;
}

__kernel void front_face(__global const int* count,    // [H*W] fragments of each pixel
                         __global const int* off,      // [H*W + 1] first packed row of each pixel
                         __global const int* face,     // [P] packed face ids
#ifdef FACE_OK
                         __global const uchar* face_ok,  // [M] 1 where the face may own a pixel
#endif
                         const int npix,
                         __global int* front)          // [H*W] nearest (qualifying) face, −1 if none
{
    const int p = get_global_id(0);
    if (p >= npix) return;
    const int n = count[p], o = off[p];
    int out = -1;
    for (int k = 0; k < n; ++k) {
        const int f = face[o + k];
#ifdef FACE_OK
        if (f >= 0 && face_ok[f]) { out = f; break; }
#else
        out = f;
        break;
#endif
    }
    front[p] = out;
}
