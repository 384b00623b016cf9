/* trace.cl — ray tracing over the BVH of bvh.cl: primary rays (K nearest hits as rasterizer
 * fragments), shadow rays with alpha transmittance and its adjoint, the reflection bounce.
 * Ray/box/triangle maths and the tree walk: common/ray_math.h.
 *
 * trace_primary (one work-item per pixel, 8x8 work-groups)
 *   ray of pixel (x, y): o = camera centre, d = R^T ((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1)
 *   (the rasterizer's pixel-centre convention; t along d is the camera-space depth). Keeps the K
 *   nearest hits with t <= far sorted by (t, face id) — the rasterizer's order — among the faces the
 *   rasterizer binned into the pixel's tile (tile_off / face_off / face_entries of ops/raster.py), so
 *   culling (near plane, degenerate, back faces) is the rasterizer's and each hit carries the
 *   (tile, face) entry whose partial sums fragment_bwd.cl accumulates into: the adjoint of a primary
 *   hit is the rasterizer's (its perspective-correct barycentrics equal the ray's). Discrete: no
 *   adjoint of its own.
 *
 * trace_shadow_fwd (one work-item per shaded fragment p; for each point / directional light j)
 *   point light at q: d = q - x, t in (eps / |d|, 1);  directional light towards w: d = w, t > eps / |w|
 *   (x the fragment's world position, eps a world-space offset against self-intersection; the
 *   fragment's own face is skipped too). No ray (T = 1, no hits) when the light is behind the shading
 *   normal (N.L <= 0 with shade.cl's N): the light then adds nothing and T gets no gradient, exactly.
 *   Over every triangle the segment crosses:
 *     a_k = sum_i l_ki A[F[f_k, i]]  (vertex alpha interpolated at the hit),  ac_k = clamp(a_k, 0, AMAX)
 *     T = prod_k (1 - ac_k)           vis[p, j] = T,  nhit[p, j] = number of hits
 *   (alpha only: the screen-space coverage window of the camera has no meaning along a shadow ray).
 * trace_shadow_bwd (same walk, same hit order), for v_T = v_vis[p, j]:
 *   g_k = dT/da_k v_T = -v_T T / (1 - ac_k)   (0 where the clamp is active)
 *   alpha:     v_A[F[f_k, i]] += g_k l_ki                          -> record w[0..3)
 *   positions: a_k depends on (u, v) = (l_k1, l_k2):  v_u = g_k (A1 - A0), v_v = g_k (A2 - A0), and
 *     u = [s, d, e2] / D, v = [d, s, e1] / D, D = [e1, d, e2]  ([a, b, c] = a . (b x c)),
 *     s = o - v0, e1 = v1 - v0, e2 = v2 - v0, o = x;  with grad_a [a,b,c] = b x c (cyclic):
 *     v_s  = (v_u/D) d x e2 + (v_v/D) e1 x d
 *     v_d  = (v_u/D) e2 x s + (v_v/D) s x e1 + v_D e2 x e1,      v_D = -(v_u u + v_v v) / D
 *     v_e1 = (v_v/D) d x s + v_D d x e2,    v_e2 = (v_u/D) s x d + v_D e1 x d
 *     occluder corners: v_v0 = -(v_s + v_e1 + v_e2), v_v1 = v_e1, v_v2 = v_e2 -> record w[3..12)
 *     fragment: v_x = v_s (- v_d for a point light);  light: v_q = v_d (point), v_w = v_d (directional)
 *   Records (face, w[12]) go to offsets from a prefix sum of nhit; the host sums them per vertex in
 *   a fixed order (no atomics). The set of hits is discrete (no gradient for a triangle entering or
 *   leaving the segment).
 *
 * trace_bounce (one work-item per shaded fragment): V = normalize(cam - x), N = normalize(n),
 *   flipped to face V when two_sided (as shade.cl), R = 2 (N.V) N - V; the nearest hit with
 *   t > eps (own face skipped): hit_face [P] (-1: none), hit_bary [P, 2]. The hit surface's
 *   attributes h = sum_i l_i attr[F[f, i]] are interpolated with gather_hits (adjoint: the per-corner
 *   scatter l_i v_h, on the host).
 * bounce_bwd (one work-item per fragment with a hit), for v_h [P, C] (adjoint of every gathered
 *   attribute column) and v_eye [P, 3] (adjoint of the hit shading's viewpoint = x):
 *   v_u = v_h . (a1 - a0), v_v = v_h . (a2 - a0)  (a_i the hit face's corner attributes)
 *   -> ray/triangle adjoint as in trace_shadow_bwd with o = x, d = R: v_s, v_d = v_R, v_e1, v_e2
 *   -> hit corners' positions rec_pos [P, 3, 3];
 *   R = 2 (N.V) N - V:  v_N = 2 (N.V) v_R + 2 (v_R . N) V,  v_V = 2 (v_R . N) N - v_R
 *   N = s normalize(n): v_n = safe_normalize_vjp(n, s v_N);  V = normalize(cam - x):
 *   v_x = v_s + v_eye - safe_normalize_vjp(cam - x, v_V).
 *   (the discrete choice of the hit face has no gradient)
 *
 * ray_mask (helper, discrete): the packed face ids of a view's fragments, -1 for
 *   fragments behind a transmittance prod_{j<k} (1 - alpha_j win_j) below t_min (no rays for them).
 */
#include "real.h"
#include "shade_math.h"
#include "ray_math.h"

#pragma OPENCL FP_CONTRACT OFF
#include "lights.h"

#ifndef TILE
#define TILE 8
#endif
#ifndef K_MAX
#define K_MAX 1
#endif
#define AMAX ((REAL)(1.0 - 1e-6))
/* EARLY_OUT: a ray's walk ends after the leaf that brought T below T_EARLY, so T is its exact value or a product
 * of fewer factors below T_EARLY (an absolute error under 1e-4, a 40th of an 8-bit step); nhit then counts the
 * hits walked. Occluded rays no longer cross the rest of the object (or, towards a directional light, every
 * surface behind the first). trace_shadow_bwd built with it walks the same leaves (the same running product in
 * the same order, so it stops where the forward stopped): the exact adjoint of the truncated product, whose
 * factors beyond the stop have no gradient (each would be under T_EARLY). */
#define T_EARLY ((REAL)1e-4)

/* entry id of (tile t, face f) in the rasterizer's binning, or -1 when f is not binned into t */
inline int find_entry(__global const int* tile_off, __global const int* face_off, __global const int* face_entries,
                      const int t, const int f)
{
    int lo = face_off[f], hi = face_off[f + 1];
    const int e0 = tile_off[t], e1 = tile_off[t + 1];
    while (lo < hi) {   /* face_entries of a face increase with the tile */
        const int mid = (lo + hi) >> 1;
        const int e = face_entries[mid];
        if (e < e0) lo = mid + 1;
        else if (e >= e1) hi = mid;
        else return e;
    }
    return -1;
}

inline void load_tri(__global const REAL* V, __global const int* F, const int f, REAL3* v0, REAL3* v1, REAL3* v2)
{
    *v0 = LOAD3(V, F[3 * f]);
    *v1 = LOAD3(V, F[3 * f + 1]);
    *v2 = LOAD3(V, F[3 * f + 2]);
}

__kernel void trace_primary(__global const REAL* nodes,       // [2P - 1, 6]
                            __global const int* prim,         // [M]
                            const int P, const int M,
                            __global const REAL* V,           // [N, 3]
                            __global const int* F,            // [M, 3]
                            __global const REAL* cam,         // [16] R (row-major), t, fx, fy, cx, cy
                            const REAL ox, const REAL oy, const REAL oz,   // camera centre
                            const int width, const int height, const int tiles_x, const int K,
                            const REAL far,
                            __global const int* tile_off,     // [T + 1]
                            __global const int* face_off,     // [M + 1]
                            __global const int* face_entries, // [E]
                            __global int* frag_face,          // [H, W, K]
                            __global int* frag_entry,         // [H, W, K]
                            __global REAL* frag_bary,         // [H, W, K, 2]
                            __global REAL* frag_depth,        // [H, W, K]
                            __global int* frag_count)         // [H, W]
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= width || y >= height) return;
    const int t_id = (y / TILE) * tiles_x + x / TILE;
    const REAL xc = ((REAL)x + (REAL)0.5 - cam[14]) / cam[12];
    const REAL yc = ((REAL)y + (REAL)0.5 - cam[15]) / cam[13];
    const REAL3 d = (REAL3)(cam[0] * xc + cam[3] * yc + cam[6],
                            cam[1] * xc + cam[4] * yc + cam[7],
                            cam[2] * xc + cam[5] * yc + cam[8]);
    const REAL3 o = (REAL3)(ox, oy, oz);
    const REAL3 inv = ray_inv_dir(d);
    REAL dk[K_MAX], bu[K_MAX], bv[K_MAX];
    int fk[K_MAX], ek[K_MAX];
    int cnt = 0;
    int stack[BVH_STACK];
    REAL tstack[BVH_STACK];
    int sp = 0;
    if (tile_off[t_id + 1] > tile_off[t_id]) bvh_begin(nodes, o, inv, (REAL)0, far, stack, tstack, &sp);
    for (;;) {
        const REAL tmax = cnt == K ? dk[K - 1] : far;
        const int j = bvh_next_leaf(nodes, P, o, inv, (REAL)0, tmax, stack, tstack, &sp);
        if (j < 0) break;
        const int s1 = leaf_begin(j + 1, M, P);
        for (int i = leaf_begin(j, M, P); i < s1; ++i) {
            const int f = prim[i];
            REAL3 v0, v1, v2;
            load_tri(V, F, f, &v0, &v1, &v2);
            REAL t, u, v;
            const REAL tm = cnt == K ? dk[K - 1] : far;
            if (!ray_tri(o, d, v0, v1, v2, (REAL)0, tm, &t, &u, &v)) continue;
            if (cnt == K && t == dk[K - 1] && f > fk[K - 1]) continue;
            const int e = find_entry(tile_off, face_off, face_entries, t_id, f);
            if (e < 0) continue;
            /* insert (t, f) sorted by (depth, face id), as raster.cl's insert_fragment */
            int q = cnt < K ? cnt : K - 1;
            while (q > 0 && (dk[q - 1] > t || (dk[q - 1] == t && fk[q - 1] > f))) {
                dk[q] = dk[q - 1]; fk[q] = fk[q - 1]; ek[q] = ek[q - 1]; bu[q] = bu[q - 1]; bv[q] = bv[q - 1];
                --q;
            }
            dk[q] = t; fk[q] = f; ek[q] = e; bu[q] = u; bv[q] = v;
            if (cnt < K) ++cnt;
        }
    }
    const int pix = y * width + x;
    frag_count[pix] = cnt;
    for (int k = 0; k < cnt; ++k) {
        const int o2 = pix * K + k;
        frag_face[o2] = fk[k];
        frag_entry[o2] = ek[k];
        frag_bary[2 * o2] = (REAL)1 - bu[k] - bv[k];
        frag_bary[2 * o2 + 1] = bu[k];
        frag_depth[o2] = dk[k];
    }
}

/* The shadow ray of light li (a shadow caster: one column j of vis) for a fragment at x: direction d
 * (unnormalised), [tmin, tmax] (lights.h); 0 when the light has no ray here (T = 1, no hits). */
inline int shadow_ray(__global const int* lt_i, __global const REAL* lt_f, const int li, const REAL3 x,
                      const REAL eps, REAL3* d, REAL* tmin, REAL* tmax)
{
    *d = (REAL3)(0);
    *tmin = *tmax = (REAL)0;
    return light_shadow_ray(lt_i[4 * li], lt_f + lt_i[4 * li + 1], x, eps, d, tmin, tmax);
}

/* Shadow rays skip lights behind the shading normal when the kernel is built with HAS_NRM (the
 * fragments' normals, the camera centre and two_sided are then parameters); without, every ray is
 * traced (the normal inputs are absent). */
#ifdef HAS_NRM
#define HAVE_NRM 1
#define NO_NRM_INPUTS
#else
#define HAVE_NRM 0
#define NO_NRM_INPUTS                                                                                 \
    __global const REAL* nrm = (__global const REAL*)0;                                              \
    const REAL cx = (REAL)0, cy = (REAL)0, cz = (REAL)0;                                             \
    const int two_sided = 0;
#endif

/* shade.cl's shading normal: normalised, flipped towards the camera when two_sided (N only matters
 * through the sign of N.L: a light behind the surface contributes 0 whatever its transmittance). */
inline REAL3 shading_normal(__global const REAL* nrm, const int has_nrm, const int p, const REAL3 x, const REAL3 cam,
                            const int two_sided)
{
    if (!has_nrm) return (REAL3)(0);
    REAL3 N = safe_normalize(LOAD3(nrm, p));
    if (two_sided && dot(N, safe_normalize(cam - x)) < (REAL)0) N = -N;
    return N;
}

inline REAL hit_alpha(__global const REAL* attr, const int C, const int ca, __global const int* F, const int f,
                      const REAL u, const REAL v, REAL3* A)
{
    *A = (REAL3)(attr[(long)F[3 * f] * C + ca], attr[(long)F[3 * f + 1] * C + ca], attr[(long)F[3 * f + 2] * C + ca]);
    return ((REAL)1 - u - v) * A->x + u * A->y + v * A->z;
}

__kernel void trace_shadow_fwd(__global const REAL* nodes,   // [2P - 1, 6]
                               __global const int* prim,     // [M]
                               const int P, const int M,
                               __global const REAL* V,       // [N, 3]
                               __global const int* F,        // [M, 3]
                               __global const REAL* attr,    // [N, C] (column ca: vertex alpha)
                               const int C, const int ca,
                               __global const REAL* pos,     // [Pf, 3] fragment positions
                               __global const int* face,     // [Pf] fragment face ids
#ifdef HAS_NRM
                               __global const REAL* nrm,     // [Pf, 3] fragment normals
                               const REAL cx, const REAL cy, const REAL cz, const int two_sided,
#endif
                               const int Pf,
                               __global const int* lt_i,     // [L, 4]
                               __global const REAL* lt_f,    // [T]
                               const int L, const int NV, const REAL eps,
                               __global REAL* vis,           // [Pf, NV]
                               __global int* nhit)           // [Pf, NV]
{
    NO_NRM_INPUTS
    const int has_nrm = HAVE_NRM;
    const int p = get_global_id(0);
    if (p >= Pf) return;
    const REAL3 x = LOAD3(pos, p);
    const int own = face[p];
    const REAL3 N = shading_normal(nrm, has_nrm, p, x, (REAL3)(cx, cy, cz), two_sided);
    int j = 0;
    for (int li = 0; li < L; ++li) {
        REAL3 d;
        REAL tmin, tmax;
        const int type = lt_i[4 * li];
        if (!light_casts_shadows(type)) continue;
        const int ray = shadow_ray(lt_i, lt_f, li, x, eps, &d, &tmin, &tmax);
        const int lit = ray && (!has_nrm || dot(N, safe_normalize(d)) > (REAL)0);
        const REAL3 inv = ray_inv_dir(d);
        REAL T = (REAL)1;
        int n = 0;
        int stack[BVH_STACK];
        REAL tstack[BVH_STACK];
        int sp = 0;
        if (own >= 0 && lit) bvh_begin(nodes, x, inv, tmin, tmax, stack, tstack, &sp);
        for (;;) {
            const int lf = bvh_next_leaf(nodes, P, x, inv, tmin, tmax, stack, tstack, &sp);
            if (lf < 0) break;
            const int s1 = leaf_begin(lf + 1, M, P);
            for (int i = leaf_begin(lf, M, P); i < s1; ++i) {
                const int f = prim[i];
                if (f == own) continue;
                REAL3 v0, v1, v2, A;
                load_tri(V, F, f, &v0, &v1, &v2);
                REAL t, u, v;
                if (!ray_tri(x, d, v0, v1, v2, tmin, tmax, &t, &u, &v)) continue;
                const REAL a = clamp(hit_alpha(attr, C, ca, F, f, u, v, &A), (REAL)0, AMAX);
                T *= (REAL)1 - a;
                ++n;
            }
#ifdef EARLY_OUT
            if (T < T_EARLY) break;   /* the walk stops: nothing farther can lift T above T_EARLY */
#endif
        }
        vis[p * NV + j] = T;
        nhit[p * NV + j] = n;
        ++j;
    }
}

inline REAL3 triple_grad(REAL3 b, REAL3 c) { return cross(b, c); }

__kernel void trace_shadow_bwd(__global const REAL* nodes,   // [2P - 1, 6]
                               __global const int* prim,     // [M]
                               const int P, const int M,
                               __global const REAL* V,       // [N, 3]
                               __global const int* F,        // [M, 3]
                               __global const REAL* attr,    // [N, C]
                               const int C, const int ca,
                               __global const REAL* pos,     // [Pf, 3]
                               __global const int* face,     // [Pf]
#ifdef HAS_NRM
                               __global const REAL* nrm,     // [Pf, 3]
                               const REAL cx, const REAL cy, const REAL cz, const int two_sided,
#endif
                               const int Pf,
                               __global const int* lt_i,     // [L, 4]
                               __global const REAL* lt_f,    // [T]
                               const int L, const int NV, const REAL eps,
                               __global const REAL* vis,     // [Pf, NV]
                               __global const REAL* v_vis,   // [Pf, NV]
                               __global const int* rec_off,  // [Pf * NV + 1]
                               __global int* rec_face,       // [R]
                               __global REAL* rec_w,         // [R, 12]  v_alpha (3) | v_position (3 x 3)
                               __global REAL* v_x,           // [Pf, 3]  fragment position adjoint
                               __global REAL* v_light)       // [Pf, NV, 3] light position / direction
{
    NO_NRM_INPUTS
    const int has_nrm = HAVE_NRM;
    const int p = get_global_id(0);
    if (p >= Pf) return;
    const REAL3 x = LOAD3(pos, p);
    const int own = face[p];
    const REAL3 N = shading_normal(nrm, has_nrm, p, x, (REAL3)(cx, cy, cz), two_sided);
    REAL3 gx = (REAL3)(0);
    int j = 0;
    for (int li = 0; li < L; ++li) {
        REAL3 d;
        REAL tmin, tmax;
        const int type = lt_i[4 * li];
        if (!light_casts_shadows(type)) continue;
        const int ray = shadow_ray(lt_i, lt_f, li, x, eps, &d, &tmin, &tmax);
        const int lit = ray && (!has_nrm || dot(N, safe_normalize(d)) > (REAL)0);
        const REAL3 inv = ray_inv_dir(d);
        const REAL T = vis[p * NV + j], vT = v_vis[p * NV + j];
#ifdef EARLY_OUT
        REAL Tw = (REAL)1;    /* the forward's running product, in its order: its walk ends at the same leaf */
#endif
        REAL3 gd = (REAL3)(0);
        int r = rec_off[p * NV + j];
        const int r_end = rec_off[p * NV + j + 1];  /* the forward's hits of this ray: never written past */
        int stack[BVH_STACK];
        REAL tstack[BVH_STACK];
        int sp = 0;
        if (own >= 0 && lit) bvh_begin(nodes, x, inv, tmin, tmax, stack, tstack, &sp);
        for (;;) {
            const int lf = bvh_next_leaf(nodes, P, x, inv, tmin, tmax, stack, tstack, &sp);
            if (lf < 0) break;
            const int s1 = leaf_begin(lf + 1, M, P);
            for (int i = leaf_begin(lf, M, P); i < s1; ++i) {
                const int f = prim[i];
                if (f == own) continue;
                REAL3 v0, v1, v2, A;
                load_tri(V, F, f, &v0, &v1, &v2);
                REAL t, u, v;
                if (!ray_tri(x, d, v0, v1, v2, tmin, tmax, &t, &u, &v)) continue;
                if (r >= r_end) break;  /* a walk that found more hits than the forward's (it cannot, by
                                           construction: a guard for the records of the next ray) */
                const REAL a = hit_alpha(attr, C, ca, F, f, u, v, &A);
#ifdef EARLY_OUT
                Tw *= (REAL)1 - clamp(a, (REAL)0, AMAX);
#endif
                const REAL g = (a >= (REAL)0 && a <= AMAX) ? -vT * T / ((REAL)1 - a) : (REAL)0;
                __global REAL* w = rec_w + (long)r * 12;
                rec_face[r++] = f;
                w[0] = g * ((REAL)1 - u - v);
                w[1] = g * u;
                w[2] = g * v;
                /* a = (1 - u - v) A0 + u A1 + v A2 -> v_u, v_v -> geometry of the hit */
                const REAL vu = g * (A.y - A.x), vv = g * (A.z - A.x);
                const REAL3 e1 = v1 - v0, e2 = v2 - v0, s = x - v0;
                const REAL D = dot(e1, cross(d, e2));
                const REAL cu = vu / D, cv = vv / D, cD = -(vu * u + vv * v) / D;
                const REAL3 vs = cu * cross(d, e2) + cv * cross(e1, d);
                const REAL3 vd = cu * cross(e2, s) + cv * cross(s, e1) + cD * cross(e2, e1);
                const REAL3 ve1 = cv * cross(d, s) + cD * cross(d, e2);
                const REAL3 ve2 = cu * cross(s, d) + cD * cross(e1, d);
                const REAL3 g0 = -(vs + ve1 + ve2);
                w[3] = g0.x; w[4] = g0.y; w[5] = g0.z;
                w[6] = ve1.x; w[7] = ve1.y; w[8] = ve1.z;
                w[9] = ve2.x; w[10] = ve2.y; w[11] = ve2.z;
                gx += vs;
                gd += vd;
            }
#ifdef EARLY_OUT
            if (Tw < T_EARLY) break;  /* where the forward's walk ended: T is the product of the factors walked */
#endif
        }
        if (light_shadow_ray_from_x(type)) gx -= gd;
        STORE3(gd, v_light, p * NV + j);
        ++j;
    }
    STORE3(gx, v_x, p);
}

/* The nearest hit of the ray x + t d, t > eps, face own skipped (own < 0: no ray): writes hit_face[p] (-1: none)
 * and hit_bary[p] = (l0, l1) (zeros without a hit). Ties in t go to the lower face id (deterministic). */
inline void nearest_hit(__global const REAL* nodes, __global const int* prim, const int P, const int M,
                        __global const REAL* V, __global const int* F, const REAL3 x, const REAL3 d, const int own,
                        const REAL eps, const int p, __global int* hit_face, __global REAL* hit_bary)
{
    const REAL3 inv = ray_inv_dir(d);
    REAL best = (REAL)1e30, bu = 0, bv = 0;
    int bf = -1;
    int stack[BVH_STACK];
    REAL tstack[BVH_STACK];
    int sp = 0;
    if (own >= 0) bvh_begin(nodes, x, inv, eps, best, stack, tstack, &sp);
    for (;;) {
        const int lf = bvh_next_leaf(nodes, P, x, inv, eps, best, stack, tstack, &sp);
        if (lf < 0) break;
        const int s1 = leaf_begin(lf + 1, M, P);
        for (int i = leaf_begin(lf, M, P); i < s1; ++i) {
            const int f = prim[i];
            if (f == own) continue;
            REAL3 v0, v1, v2;
            load_tri(V, F, f, &v0, &v1, &v2);
            REAL t, u, v;
            if (!ray_tri(x, d, v0, v1, v2, eps, best, &t, &u, &v)) continue;
            if (t == best && f > bf) continue;
            best = t; bf = f; bu = u; bv = v;
        }
    }
    hit_face[p] = bf;
    hit_bary[2 * p] = bf >= 0 ? (REAL)1 - bu - bv : (REAL)0;
    hit_bary[2 * p + 1] = bf >= 0 ? bu : (REAL)0;
}

__kernel void trace_bounce(__global const REAL* nodes,   // [2P - 1, 6]
                           __global const int* prim,     // [M]
                           const int P, const int M,
                           __global const REAL* V,       // [N, 3]
                           __global const int* F,        // [M, 3]
                           __global const REAL* pos,     // [Pf, 3]
                           __global const REAL* nrm,     // [Pf, 3]
                           __global const int* face,     // [Pf]
                           const int Pf,
                           const REAL cx, const REAL cy, const REAL cz, const int two_sided, const REAL eps,
                           __global int* hit_face,       // [Pf]  -1: no hit
                           __global REAL* hit_bary)      // [Pf, 2]  (l0, l1)
{
    const int p = get_global_id(0);
    if (p >= Pf) return;
    const REAL3 x = LOAD3(pos, p);
    const REAL3 Vd = safe_normalize((REAL3)(cx, cy, cz) - x);
    REAL3 N = safe_normalize(LOAD3(nrm, p));
    if (two_sided && dot(N, Vd) < (REAL)0) N = -N;
    const REAL3 d = (REAL)2 * dot(N, Vd) * N - Vd;
    nearest_hit(nodes, prim, P, M, V, F, x, d, face[p], eps, p, hit_face, hit_bary);
}

/* trace_rays (one work-item per ray): the nearest hit along origin[p] + t dir[p] (t > eps, the face own[p]
 * skipped; own[p] < 0: no ray), as trace_bounce's. The one-bounce interreflection (visibility.vertex_bounce)
 * traces its hemisphere rays with it. Discrete: no adjoint. */
__kernel void trace_rays(__global const REAL* nodes,   // [2P - 1, 6]
                         __global const int* prim,     // [M]
                         const int P, const int M,
                         __global const REAL* V,       // [N, 3]
                         __global const int* F,        // [M, 3]
                         __global const REAL* origin,  // [R, 3]
                         __global const REAL* dir,     // [R, 3]
                         __global const int* own,      // [R]
                         const int R, const REAL eps,
                         __global int* hit_face,       // [R]  -1: no hit
                         __global REAL* hit_bary)      // [R, 2]  (l0, l1)
{
    const int p = get_global_id(0);
    if (p >= R) return;
    nearest_hit(nodes, prim, P, M, V, F, LOAD3(origin, p), LOAD3(dir, p), own[p], eps, p, hit_face, hit_bary);
}

/* ray/triangle adjoint: (v_u, v_v) of the barycentrics (u, v) of the hit of o + t d -> v_o, v_d, corners */
inline void ray_tri_bary_vjp(const REAL3 o, const REAL3 d, const REAL3 v0, const REAL3 v1, const REAL3 v2,
                             const REAL u, const REAL v, const REAL vu, const REAL vv, REAL3* v_o, REAL3* v_d,
                             REAL3* g0, REAL3* g1, REAL3* g2)
{
    const REAL3 e1 = v1 - v0, e2 = v2 - v0, s = o - v0;
    const REAL D = dot(e1, cross(d, e2));
    const REAL cu = vu / D, cv = vv / D, cD = -(vu * u + vv * v) / D;
    const REAL3 vs = cu * cross(d, e2) + cv * cross(e1, d);
    *v_d = cu * cross(e2, s) + cv * cross(s, e1) + cD * cross(e2, e1);
    const REAL3 ve1 = cv * cross(d, s) + cD * cross(d, e2);
    const REAL3 ve2 = cu * cross(s, d) + cD * cross(e1, d);
    *v_o = vs;
    *g0 = -(vs + ve1 + ve2);
    *g1 = ve1;
    *g2 = ve2;
}

__kernel void bounce_bwd(__global const REAL* V,         // [N, 3]
                         __global const int* F,          // [M, 3]
                         __global const REAL* attr,      // [N, C]
                         const int C,
                         __global const REAL* pos,       // [Pf, 3]
                         __global const REAL* nrm,       // [Pf, 3]
                         __global const int* hit_face,   // [Pf]
                         __global const REAL* hit_bary,  // [Pf, 2]
                         __global const REAL* v_h,       // [Pf, C]
                         __global const REAL* v_eye,     // [Pf, 3]
                         const int Pf,
                         const REAL cx, const REAL cy, const REAL cz, const int two_sided,
                         __global REAL* v_pos,           // [Pf, 3]
                         __global REAL* v_nrm,           // [Pf, 3]
                         __global REAL* rec_pos)         // [Pf, 9]  hit corners' position adjoints
{
    const int p = get_global_id(0);
    if (p >= Pf) return;
    const int f = hit_face[p];
    REAL3 gx = (REAL3)(0), gn = (REAL3)(0), g0 = (REAL3)(0), g1 = (REAL3)(0), g2 = (REAL3)(0);
    if (f >= 0) {
        const REAL3 x = LOAD3(pos, p), n = LOAD3(nrm, p), cam = (REAL3)(cx, cy, cz);
        const REAL3 Vd = safe_normalize(cam - x);
        REAL3 N = safe_normalize(n);
        const REAL sg = (two_sided && dot(N, Vd) < (REAL)0) ? -(REAL)1 : (REAL)1;
        N *= sg;
        const REAL nv = dot(N, Vd);
        const REAL3 d = (REAL)2 * nv * N - Vd;
        const int i0 = F[3 * f], i1 = F[3 * f + 1], i2 = F[3 * f + 2];
        REAL vu = (REAL)0, vv = (REAL)0;
        for (int c = 0; c < C; ++c) {
            const REAL a0 = attr[(long)i0 * C + c];
            const REAL g = v_h[(long)p * C + c];
            vu += g * (attr[(long)i1 * C + c] - a0);
            vv += g * (attr[(long)i2 * C + c] - a0);
        }
        const REAL u = hit_bary[2 * p + 1], v = (REAL)1 - hit_bary[2 * p] - hit_bary[2 * p + 1];
        REAL3 vo, vd;
        ray_tri_bary_vjp(x, d, LOAD3(V, i0), LOAD3(V, i1), LOAD3(V, i2), u, v, vu, vv, &vo, &vd, &g0, &g1, &g2);
        const REAL rn = dot(vd, N);
        const REAL3 vN = (REAL)2 * nv * vd + (REAL)2 * rn * Vd;
        const REAL3 vV = (REAL)2 * rn * N - vd;
        gn = safe_normalize_vjp(n, sg * vN);
        gx = vo + LOAD3(v_eye, p) - safe_normalize_vjp(cam - x, vV);
    }
    STORE3(gx, v_pos, p);
    STORE3(gn, v_nrm, p);
    STORE3(g0, rec_pos, 3 * p);
    STORE3(g1, rec_pos, 3 * p + 1);
    STORE3(g2, rec_pos, 3 * p + 2);
}

/* out[p, c] = sum_i l_i attr[F[f, i], c0 + c] at the hit (f = hit_face[p]; zeros without a hit) */
__kernel void gather_hits(__global const REAL* attr,      // [N, C]
                          const int C, const int c0, const int n,
                          __global const int* F,          // [M, 3]
                          __global const int* hit_face,   // [Pf]
                          __global const REAL* hit_bary,  // [Pf, 2]
                          const int Pf,
                          __global REAL* out)             // [Pf, n]
{
    const int p = get_global_id(0);
    if (p >= Pf) return;
    const int f = hit_face[p];
    for (int c = 0; c < n; ++c) {
        REAL s = (REAL)0;
        if (f >= 0) {
            const REAL l0 = hit_bary[2 * p], l1 = hit_bary[2 * p + 1], l2 = (REAL)1 - l0 - l1;
            s = l0 * attr[(long)F[3 * f] * C + c0 + c] + l1 * attr[(long)F[3 * f + 1] * C + c0 + c] +
                l2 * attr[(long)F[3 * f + 2] * C + c0 + c];
        }
        out[(long)p * n + c] = s;
    }
}

/* Which compacted fragments need rays: -1 where the pixel's transmittance in front of the fragment,
 * prod_{j<k} (1 - alpha_j win_j), is already below t_min (compositing stops there: the fragment's
 * colour has no weight and no gradient), else its face id. */
__kernel void ray_mask(__global const int* face,       // [Pv] compacted face ids
                       __global const REAL* alpha,     // [Pv]
#ifdef HAS_WIN
                       __global const REAL* win,       // [Pv] coverage window
#endif
                       __global const int* frag_count, // [H, W]
                       __global const int* offsets,    // [H W + 1]
                       const int npix, const REAL t_min,
                       __global int* out)              // [Pv]
{
#ifndef HAS_WIN
    __global const REAL* win = (__global const REAL*)0;
#endif
#ifdef HAS_WIN
    const int has_win = 1;
#else
    const int has_win = 0;
#endif
    const int pix = get_global_id(0);
    if (pix >= npix) return;
    const int o = offsets[pix], c = frag_count[pix];
    REAL T = (REAL)1;
    for (int k = 0; k < c; ++k) {
        out[o + k] = T < t_min ? -1 : face[o + k];
        T *= (REAL)1 - alpha[o + k] * (has_win ? win[o + k] : (REAL)1);
    }
}

