/* fragment_bwd.cl — the one backward pass over the fragments of a view, and the per-vertex gathers
 * of per-entry / per-corner adjoints (gather_vertex, gather_corner). Host side: ops/fragment_bwd.py.
 *
 * Everything a fragment receives from a vertex goes through its face's three corners:
 *   attributes   out[o,c] = sum_i lam_i attr[F[f,i], c]            (interpolate.cl)
 *   barycentrics lam = bary_persp(a0, a1, a2, z0, z1, z2; p)       (raster.cl, raster_math.h)
 *   depth        zp  = 1 / sum_i (b_i / z_i)
 *   window       win = 1 - exp(-sigma max(0, min_k d_k))          (coverage.cl, raster_math.h)
 * so their adjoints are computed together, in one pass.
 *
 * Attributes:  v_attr[F[f,i], c] += lam_i v_out[o,c];
 *              v_lam0 = sum_c v_out[o,c] (a0_c - a2_c) (+ v_bary_in), v_lam1 likewise with a1.
 *
 * Geometry, by per-entry moments (no vertex loads, no divisions per fragment). With the entry's
 * set-up (binning.cl: a0, grad b0, grad b1, 1/z_k, g_k = 1/|grad b_k| = |A| / L_k) and
 * (dx, dy) = p - a0:  b0 = 1 + grad b0 . (dx, dy),  b1 = grad b1 . (dx, dy),  b2 = 1 - b0 - b1.
 * The adjoint of raster_math.h per fragment is
 *   base  = sum_k v_lam_k lam_k + v_zp zp,   v_w_k = (v_lam_k - base) zp,   v_b_k = v_w_k / z_k,
 *   v_z_k = -v_w_k b_k / z_k^2,   v_E_k = v_b_k / A,   v_A = -sum_k v_b_k b_k / A,
 *   window (d = d_k* = b_k* g_k* > 0 the nearest edge): v_d = v_win sigma e^(-sigma d),
 *     v_E_k* += v_d g_k* / A (= v_d sgn(A) / L_k*),  v_L_k* = -v_d d / L_k*,
 *     v_sigma += v_win d e^(-sigma d).
 * E_k = cross(x_k - p, y_k - p) is affine in p, so the sum over an entry's fragments of
 * v_E_k dE_k/d(x_k, y_k) needs only the moments of u_k = A v_E_k:
 *   m_k = sum u_k,  mx_k = sum u_k dx,  my_k = sum u_k dy,
 * plus sA = sum_k,frag v_b_k b_k,  mL_k = sum v_d d (edge k nearest),  mz_k = sum v_w_k b_k:
 * MOMENTS = 16 numbers per entry, partial_mom [E, 16]. entry_geom (one work-item per entry) then
 * loads the face's screen vertices once and forms, with q = p - a0 = (dx, dy) and r_j = a_j - a0,
 *   sum v_E_k cross'(x_k - p, y_k - p) = (1/A) [ m_k cross'(r_x - 0, r_y - 0) - moment terms ],
 *   d cross(x - p, y - p)/dx = ((y - p).y, -(y - p).x),  d/dy = (-(x - p).y, (x - p).x),
 *   v_A -> cross(a1 - a0, a2 - a0),   v_L_k -> v_e_k = v_L_k e_k / L_k,   v_z_k = -mz_k / z_k^2,
 * into partial_geom [E, 3, 3] (corner, (u, v, z)) for gather_vertex (below).
 *
 * No float atomics: one work-item owns one tile and walks its pixels and fragments serially,
 * adding into the partial sums of that tile's (tile, face) entries (partial_attr [E, 3, C],
 * partial_mom [E, 16], zeroed at the entry's first fragment; entry_hit [E] marks the entries that
 * have any); gather_vertex sums them per vertex in a fixed order (deterministic), skipping the
 * entries without fragments.
 * Without GEOMETRY the barycentric adjoint is written out instead (v_bary_out = v_bary_in + own),
 * for callers that chain several interpolations.
 *
 * Optional inputs and outputs are compile-time defines (ops/fragment_bwd.py sets them), and their
 * parameters exist only in the builds that use them:
 *   ATTR       attr [N, C], v_out [P, C] in, partial_attr [E, 3, C] out (interpolated attributes)
 *   V_BARY_IN  v_bary_in [P, 2]      V_DEPTH  v_depth [P]      V_WIN  v_win [P]
 *   WIN_EX     win_ex [P]: the window's exp(-sigma max(0, d)) from the forward (else taken here again)
 *   GEOMETRY   partial_mom [E, MOMENTS], v_sigma_tile [T] out; else v_bary_out [P, 2] out
 */
#include "real.h"
#include "raster_math.h"
#include "raster_adjoint.h" /* fragment_moments, MOMENTS, SETUP, setup_window_ex */

#ifndef TILE
#define TILE 8
#endif

/* ATTR_CHUNK(N): fragment_bwd's attribute channels c .. c + N - 1 as N-wide vectors (the rows' loads and stores), the
 * cotangent's dot products vl0, vl1 summed lane by lane in channel order: the scalar loop's operations and order */
#define ATTR_CHUNK(N) {                                                                                               \
        const TRIPLET_CAT(REAL, N) gc = TRIPLET_CAT(vload, N)(0, g + c);                                              \
        const TRIPLET_CAT(REAL, N) x2 = TRIPLET_CAT(vload, N)(0, a2 + c);                                             \
        TRIPLET_CAT(vstore, N)(TRIPLET_CAT(vload, N)(0, d + c) + l0 * gc, 0, d + c);                                  \
        TRIPLET_CAT(vstore, N)(TRIPLET_CAT(vload, N)(0, d + C + c) + l1 * gc, 0, d + C + c);                          \
        TRIPLET_CAT(vstore, N)(TRIPLET_CAT(vload, N)(0, d + 2 * C + c) + l2 * gc, 0, d + 2 * C + c);                  \
        REAL gs[N], e0[N], e1[N];                                                                                     \
        TRIPLET_CAT(vstore, N)(gc, 0, gs);                                                                            \
        TRIPLET_CAT(vstore, N)(TRIPLET_CAT(vload, N)(0, a0 + c) - x2, 0, e0);                                         \
        TRIPLET_CAT(vstore, N)(TRIPLET_CAT(vload, N)(0, a1 + c) - x2, 0, e1);                                         \
        for (int k = 0; k < N; ++k) {                                                                                 \
            vl0 += gs[k] * e0[k];                                                                                     \
            vl1 += gs[k] * e1[k];                                                                                     \
        }                                                                                                             \
    }

__kernel void fragment_bwd(__global const REAL* entry_setup,  // [E, SETUP]
                           __global const int* F,             // [M, 3]
                           __global const int* tile_off,      // [T + 1]
                           __global const int* frag_face,     // [P]
                           __global const int* frag_entry,    // [P]
                           __global const REAL* frag_bary,    // [P, 2]
                           __global const REAL* frag_depth,   // [P]
                           __global const int* frag_count,    // [H, W]
#ifdef ATTR
                           __global const REAL* attr,         // [N, C]
                           __global const REAL* v_out,        // [P, C]
                           const int C,
#endif
#ifdef V_BARY_IN
                           __global const REAL* v_bary_in,    // [P, 2]
#endif
#ifdef V_DEPTH
                           __global const REAL* v_depth,      // [P]
#endif
#ifdef V_WIN
                           __global const REAL* v_win,        // [P]
#endif
#ifdef WIN_EX
                           __global const REAL* win_ex,       // [P] the forward's exp(-sigma max(0, d))
#endif
                           const REAL sigma,
                           const int width, const int height, const int tiles_x, const int num_tiles,
                           __global const int* frag_off,      // [H * W + 1] first row of each pixel
#ifdef ATTR
                           __global REAL* partial_attr,       // [E, 3, C]
#endif
#ifdef GEOMETRY
                           __global REAL* partial_mom,        // [E, MOMENTS]
                           __global REAL* v_sigma_tile,       // [T]
#else
                           __global REAL* v_bary_out,         // [P, 2]
#endif
                           __global int* entry_hit)           // [E]  1: the entry has fragments
{
    const int t = get_global_id(0);
    if (t >= num_tiles) return;
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    /* an entry's partial sums are zeroed at its first fragment; entries without fragments (a face
     * whose bounding box meets the tile but that covers none of its pixel centres, or lies behind
     * the K nearest everywhere: two thirds of them at K = 1) keep entry_hit = 0 and are never
     * written nor read */
    for (int e = e0; e < e1; ++e) entry_hit[e] = 0;
    REAL vsig = (REAL)0;
    const int tx = t % tiles_x, ty = t / tiles_x;
    const int xe = min(width, tx * TILE + TILE), ye = min(height, ty * TILE + TILE);
    for (int y = ty * TILE; y < ye; ++y)
        for (int x = tx * TILE; x < xe; ++x) {
            const int pix = y * width + x;
            const int cnt = frag_count[pix];
            for (int k = 0; k < cnt; ++k) {
                const int o = frag_off[pix] + k;
                const int e = frag_entry[o];
                if (!entry_hit[e]) {
                    entry_hit[e] = 1;
#ifdef ATTR
                    for (int q = 0; q < 3 * C; ++q) partial_attr[(long)e * 3 * C + q] = (REAL)0;
#endif
#ifdef GEOMETRY
                    for (int q = 0; q < MOMENTS; ++q) partial_mom[(long)e * MOMENTS + q] = (REAL)0;
#endif
                }
                const REAL l0 = frag_bary[2 * o], l1 = frag_bary[2 * o + 1];
#ifdef V_BARY_IN
                REAL vl0 = v_bary_in[2 * o], vl1 = v_bary_in[2 * o + 1];
#else
                REAL vl0 = (REAL)0, vl1 = (REAL)0;
#endif
#ifdef ATTR
                /* a zero cotangent row (a fragment behind compositing's cut-off, 17-25 % of a soup's) adds nothing:
                 * its three vertices' rows are not read */
                int any = 0;
                for (int c = 0; c < C; ++c) any |= v_out[(long)o * C + c] != (REAL)0;
                if (any) {
                    const int f = frag_face[o];
                    const REAL l2 = (REAL)1 - l0 - l1;
                    __global const REAL* a0 = attr + F[3 * f] * C;
                    __global const REAL* a1 = attr + F[3 * f + 1] * C;
                    __global const REAL* a2 = attr + F[3 * f + 2] * C;
                    __global const REAL* g = v_out + (long)o * C;
                    __global REAL* d = partial_attr + (long)e * 3 * C;
                    int c = 0;
#ifndef SCALAR_CHANNELS
                    /* the channels eight, four and two at a time (vector loads and stores of the rows; session 59: the
                     * pass 1.08-1.24x faster on PoCL at C = 14), the cotangent's dot products still summed channel by
                     * channel in order: the same operations on the same values as the scalar loop (the tail and,
                     * with SCALAR_CHANNELS, every channel), the same bits */
                    for (; c + 8 <= C; c += 8) ATTR_CHUNK(8)
                    if (c + 4 <= C) { ATTR_CHUNK(4) c += 4; }
                    if (c + 2 <= C) { ATTR_CHUNK(2) c += 2; }
#endif
                    for (; c < C; ++c) {
                        const REAL gc = g[c];
                        d[c] += l0 * gc;
                        d[C + c] += l1 * gc;
                        d[2 * C + c] += l2 * gc;
                        vl0 += gc * (a0[c] - a2[c]);
                        vl1 += gc * (a1[c] - a2[c]);
                    }
                }
#endif
#ifndef GEOMETRY
                v_bary_out[2 * o] = vl0;
                v_bary_out[2 * o + 1] = vl1;
#else
#ifdef V_DEPTH
                const REAL vzp = v_depth[o];
#else
                REAL vzp = (REAL)0;  /* not const: a constant operand of && draws a clang warning */
#endif
#ifdef V_WIN
                const REAL vw = v_win[o];
#else
                REAL vw = (REAL)0;
#endif
                if (vl0 == (REAL)0 && vl1 == (REAL)0 && vzp == (REAL)0 && vw == (REAL)0) continue;
                __global const REAL* s = entry_setup + (long)e * SETUP;
                const REAL dx = ((REAL)x + (REAL)0.5) - s[0], dy = ((REAL)y + (REAL)0.5) - s[1];
                const REAL b0 = (REAL)1 + s[2] * dx + s[3] * dy;
                const REAL b1 = s[4] * dx + s[5] * dy;
                const REAL b2 = (REAL)1 - b0 - b1;
                const REAL zp = frag_depth[o];
                int kk = 0;
                REAL dm = (REAL)0, ex = (REAL)0;
                if (vw != (REAL)0) {
#ifdef WIN_EX
                    /* the exp the rasterizer's window pass took in vector lanes (raster.cl window_from_distance): a
                     * scalar exp in this loop is a library call (~18 ns a fragment on PoCL) */
                    dm = setup_window_arg(s, b0, b1, b2, &kk);
                    ex = win_ex[o];
#else
                    setup_window_ex(s, b0, b1, b2, sigma, &kk, &dm, &ex);
#endif
                }
                vsig += fragment_moments(s, dx, dy, b0, b1, b2, l0, l1, zp, vl0, vl1, vzp, vw, sigma, kk, dm, ex,
                                         partial_mom + (long)e * MOMENTS);
#endif
            }
        }
#ifdef GEOMETRY
    v_sigma_tile[t] = vsig;
#endif
}

__kernel void entry_geom(__global const REAL* vs,           // [N, 3]
                         __global const int* F,             // [M, 3]
                         __global const int* entry_face,    // [E]
                         __global const REAL* partial_mom,  // [E, MOMENTS]
                         __global const int* entry_hit,     // [E]
                         const int num_entries,
                         __global REAL* partial_geom)       // [E, 3, 3]  (entries with fragments only)
{
    const int e = get_global_id(0);
    if (e >= num_entries || !entry_hit[e]) return;
    entry_geom_vjp(vs, F, entry_face[e], partial_mom + (long)e * MOMENTS, partial_geom + (long)e * 9);
}

/* gather_vertex  per vertex: sum partial[entry, corner, :] over every face corner of the vertex
 *             (CSR) and every entry of that face that has fragments (entry_hit), for two partial
 *             arrays at once (attributes, geometry). Adjoint of "vertex -> fragment".
 * gather_corner  per vertex: sum per-face-corner adjoints [M, 3, C] over the vertex's corners
 *             (CSR), for two arrays at once (blend.cl's blend_face_grad writes them per corner). */
__kernel void gather_vertex(__global const REAL* partial_a,    // [E, a_stride]: [3, Ca] from a_off  (Ca > 0)
                            __global const REAL* partial_b,    // [E, b_stride]: [3, Cb] from b_off  (Cb > 0)
                            __global const int* entry_hit,     // [E]  0: no fragments, partials unset
                            __global const int* face_off,      // [M + 1]
                            __global const int* face_entries,  // [E]
                            __global const int* csr_off,       // [N + 1]
                            __global const int* csr_corner,    // [3M]  3 * face + corner
                            const int n, const int Ca, const int Cb, const int a_stride, const int a_off,
                            const int b_stride, const int b_off,
                            __global REAL* out_a,              // [N, Ca]
                            __global REAL* out_b)              // [N, Cb]
{
    /* one work-item per vertex, both partial arrays (attributes and geometry) in one walk of the
     * corner / entry indices */
    const int v = get_global_id(0);
    if (v >= n) return;
    __global REAL* oa = out_a + (long)v * Ca;
    __global REAL* ob = out_b + (long)v * Cb;
    for (int c = 0; c < Ca; ++c) oa[c] = (REAL)0;
    for (int c = 0; c < Cb; ++c) ob[c] = (REAL)0;
    for (int q = csr_off[v]; q < csr_off[v + 1]; ++q) {
        const int corner = csr_corner[q];
        const int f = corner / 3, i = corner - 3 * f;
        for (int j = face_off[f]; j < face_off[f + 1]; ++j) {
            const int e = face_entries[j];
            if (!entry_hit[e]) continue;
            __global const REAL* pa = partial_a + (long)e * a_stride + a_off + i * Ca;
            for (int c = 0; c < Ca; ++c) oa[c] += pa[c];
            __global const REAL* pb = partial_b + (long)e * b_stride + b_off + i * Cb;
            for (int c = 0; c < Cb; ++c) ob[c] += pb[c];
        }
    }
}

__kernel void gather_corner(__global const REAL* corner_a,     // [M, 3, Ca]
                            __global const REAL* corner_b,     // [M, 3, Cb]
                            __global const int* csr_off,       // [N + 1]
                            __global const int* csr_corner,    // [3M]  3 * face + corner
                            const int n, const int Ca, const int Cb,
                            __global REAL* out_a,              // [N, Ca]
                            __global REAL* out_b)              // [N, Cb]
{
    const int v = get_global_id(0);
    if (v >= n) return;
    __global REAL* oa = out_a + (long)v * Ca;
    __global REAL* ob = out_b + (long)v * Cb;
    for (int c = 0; c < Ca; ++c) oa[c] = (REAL)0;
    for (int c = 0; c < Cb; ++c) ob[c] = (REAL)0;
    for (int q = csr_off[v]; q < csr_off[v + 1]; ++q) {
        const long corner = csr_corner[q];
        for (int c = 0; c < Ca; ++c) oa[c] += corner_a[corner * Ca + c];
        for (int c = 0; c < Cb; ++c) ob[c] += corner_b[corner * Cb + c];
    }
}
