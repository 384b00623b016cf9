/* project.cl — world vertices to screen (u, v) and camera depth z.
 *
 * cam (16 REAL): R row-major (9), t (3), fx, fy, cx, cy   (world-to-camera, OpenCV axes)
 * Forward:  pc = R v + t;  u = fx pc.x / pc.z + cx;  v = fy pc.y / pc.z + cy;  z = pc.z
 * Adjoint:  v_pc.x = v_u fx / z
 *           v_pc.y = v_v fy / z
 *           v_pc.z = v_z - (v_u fx pc.x + v_v fy pc.y) / z^2
 *           v_V    = R^T v_pc
 *           (camera pose: v_R = sum_n v_pc_n v_n^T, v_t = sum_n v_pc_n, done on the host from v_pc)
 * Vertices with z <= 0 produce non-finite u, v; the rasterizer culls every face that has a vertex
 * nearer than `near` before using them, and such vertices receive no adjoint.
 */
#include "real.h"

/* Camera-space position R v + t. */
inline REAL3 to_camera(__constant REAL* cam, REAL3 p)
{
    return (REAL3)(cam[0] * p.x + cam[1] * p.y + cam[2] * p.z + cam[9],
                   cam[3] * p.x + cam[4] * p.y + cam[5] * p.z + cam[10],
                   cam[6] * p.x + cam[7] * p.y + cam[8] * p.z + cam[11]);
}

__kernel void project_fwd(__global const REAL* V,     // [N, 3]
                          __constant REAL* cam,       // [16]
                          const int n,
                          __global REAL* vs)          // [N, 3]  (u, v, z)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const REAL3 pc = to_camera(cam, LOAD3(V, i));
    const REAL iz = (REAL)1 / pc.z;
    STORE3((REAL3)(cam[12] * pc.x * iz + cam[14], cam[13] * pc.y * iz + cam[15], pc.z), vs, i);
}

__kernel void project_bwd(__global const REAL* V,     // [N, 3]
                          __constant REAL* cam,       // [16]
                          __global const REAL* v_vs,  // [N, 3]
                          const int n,
                          __global REAL* v_V,         // [N, 3]
                          __global REAL* v_pc)        // [N, 3]  camera-space adjoint (pose gradients)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const REAL3 pc = to_camera(cam, LOAD3(V, i));
    const REAL3 g = LOAD3(v_vs, i);
    REAL3 vp = (REAL3)(0, 0, 0);
    if (pc.z > (REAL)0 && (g.x != (REAL)0 || g.y != (REAL)0 || g.z != (REAL)0)) {
        const REAL iz = (REAL)1 / pc.z;
        vp.x = g.x * cam[12] * iz;
        vp.y = g.y * cam[13] * iz;
        vp.z = g.z - (g.x * cam[12] * pc.x + g.y * cam[13] * pc.y) * iz * iz;
    }
    STORE3(vp, v_pc, i);
    STORE3((REAL3)(cam[0] * vp.x + cam[3] * vp.y + cam[6] * vp.z,
                   cam[1] * vp.x + cam[4] * vp.y + cam[7] * vp.z,
                   cam[2] * vp.x + cam[5] * vp.y + cam[8] * vp.z), v_V, i);
}
