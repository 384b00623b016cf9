/* tsdf.cl — the per-voxel votes of TSDF fusion over a chunk of views, one work-item per voxel
 * (triplet_cl/ops/tsdf.py; the numpy reference is tests/reference/tsdf.py; the rules are those of
 * triplet_cl/mesh/extract.py's module docstring).
 *
 * tsdf_fuse: voxel p = (i·ny + j)·nz + k sits at (gx[i], gy[j], gz[k]). For each view c of the chunk, in
 *   order (so the sums add up in the reference's order), with R, t its world-to-camera rotation and
 *   translation:
 *     zc = R2·x + t2; skipped unless zc > near;
 *     (uc, vc) = ((R0·x + t0)/zc·fx + cx, (R1·x + t1)/zc·fy + cy), the nearest pixel (floor(uc), floor(vc));
 *     skipped unless inside the image;
 *     seen += 1;  hull_out += 1 where the pixel is on the photo's (eroded) background (FLAG_PHOTO_BG);
 *     with the view's silhouette-distance map: sd = bilinear(map, uc, vc)·zc·sd_scale; where sd > 0,
 *       hull_exact += 1 and hull_sdf = max(hull_sdf, min(sd, 1));
 *     a = acc[pixel]; surf = a ≥ alpha_threshold; s = (depth[pixel] − zc)·inv_tau; behind = surf ∧ s < −1;
 *     hidden += behind;
 *     where FLAG_FREE (the pixel carves) or (surf ∧ ¬behind): w = surf ? a : 1;
 *       num += w·(surf ? min(s, 1) : 1), wsum += w.
 *   The accumulators are read at the start and written at the end: a chunk continues the previous one's sums.
 * Each dot product is written out left to right and FP_CONTRACT is off, as the reference evaluates it.
 */
#include "real.h"
#pragma OPENCL FP_CONTRACT OFF

#define FLAG_FREE 1      /* the pixel carves: free space (accumulated alpha below the threshold, eroded) */
#define FLAG_PHOTO_BG 2  /* the pixel lies on the photo's (eroded) background: outside the visual hull */

#define CAM_STRIDE 20    /* R (9, row-major), t (3), fx, fy, cx, cy, near, sd_scale, 2 unused */
#define VIEW_STRIDE 4    /* width, height, offset of the view's pixels in the maps, has a silhouette map */

/* bilinear sample of a [H, W] map at the continuous position (uc, vc), pixel centres at j + 0.5, clamped */
inline REAL bilinear(__global const REAL* img, const int W, const int H, const REAL uc, const REAL vc)
{
    const REAL x = clamp(uc - (REAL)0.5, (REAL)0, (REAL)(W - 1));
    const REAL y = clamp(vc - (REAL)0.5, (REAL)0, (REAL)(H - 1));
    const int x0 = min((int)floor(x), W > 1 ? W - 2 : 0);
    const int y0 = min((int)floor(y), H > 1 ? H - 2 : 0);
    const int x1 = min(x0 + 1, W - 1), y1 = min(y0 + 1, H - 1);
    const REAL fx = x - (REAL)x0, fy = y - (REAL)y0;
    const REAL top = img[y0 * W + x0] * ((REAL)1 - fx) + img[y0 * W + x1] * fx;
    const REAL bot = img[y1 * W + x0] * ((REAL)1 - fx) + img[y1 * W + x1] * fx;
    return top * ((REAL)1 - fy) + bot * fy;
}

__kernel void tsdf_fuse(__global const REAL* gx, __global const REAL* gy, __global const REAL* gz,
                        const int nx, const int ny, const int nz,
                        __global const REAL* cams,     // [C, CAM_STRIDE]
                        __global const int* views,     // [C, VIEW_STRIDE]
                        const int C,
                        __global const REAL* depth,    // the views' [H, W] maps, one after the other
                        __global const REAL* acc,
                        __global const uchar* flags,
                        __global const REAL* sdmap,    // the silhouette-distance maps (views that have one)
                        const REAL alpha_threshold,
                        const REAL inv_tau,
                        __global REAL* num, __global REAL* wsum,
                        __global int* seen, __global int* hidden, __global int* hull_out,
                        __global int* hull_exact, __global REAL* hull_sdf)
{
    const int p = get_global_id(0);
    if (p >= nx * ny * nz) return;
    const int k = p % nz, j = (p / nz) % ny, i = p / (nz * ny);
    const REAL x = gx[i], y = gy[j], z = gz[k];
    REAL nm = num[p], ws = wsum[p], hs = hull_sdf[p];
    int se = seen[p], hi = hidden[p], ho = hull_out[p], he = hull_exact[p];
    for (int c = 0; c < C; ++c) {
        __global const REAL* cm = cams + CAM_STRIDE * c;
        const REAL zc = x * cm[6] + y * cm[7] + z * cm[8] + cm[11];
        if (!(zc > cm[16])) continue;
        const REAL uc = (x * cm[0] + y * cm[1] + z * cm[2] + cm[9]) / zc * cm[12] + cm[14];
        const REAL vc = (x * cm[3] + y * cm[4] + z * cm[5] + cm[10]) / zc * cm[13] + cm[15];
        const REAL u = floor(uc), v = floor(vc);
        const int W = views[VIEW_STRIDE * c], H = views[VIEW_STRIDE * c + 1];
        if (!(u >= (REAL)0 && u < (REAL)W && v >= (REAL)0 && v < (REAL)H)) continue;
        const int off = views[VIEW_STRIDE * c + 2];
        const int q = off + (int)v * W + (int)u;
        se += 1;
        const uchar fl = flags[q];
        if (fl & FLAG_PHOTO_BG) ho += 1;
        if (views[VIEW_STRIDE * c + 3]) {
            const REAL sd = bilinear(sdmap + off, W, H, uc, vc) * zc * cm[17];
            if (sd > (REAL)0) {
                he += 1;
                hs = fmax(hs, fmin(sd, (REAL)1));
            }
        }
        const REAL a = acc[q];
        const bool surf = a >= alpha_threshold;
        const REAL s = (depth[q] - zc) * inv_tau;
        const bool behind = surf && s < (REAL)-1;
        if (behind) hi += 1;
        if ((fl & FLAG_FREE) || (surf && !behind)) {
            const REAL w = surf ? a : (REAL)1;
            nm += w * (surf ? fmin(s, (REAL)1) : (REAL)1);
            ws += w;
        }
    }
    num[p] = nm;
    wsum[p] = ws;
    hull_sdf[p] = hs;
    seen[p] = se;
    hidden[p] = hi;
    hull_out[p] = ho;
    hull_exact[p] = he;
}
