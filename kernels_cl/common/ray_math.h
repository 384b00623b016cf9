/* ray_math.h — ray/box and ray/triangle tests and the BVH walk shared by the trace kernels.
 *
 * ray_tri (Moller-Trumbore), for the ray o + t d and the triangle (v0, v1, v2):
 *   e1 = v1 - v0, e2 = v2 - v0, p = d x e2, det = e1 . p   (det == 0: parallel, no hit)
 *   s = o - v0, u = (s . p) / det, q = s x e1, v = (d . q) / det, t = (e2 . q) / det
 *   hit when u >= 0, v >= 0, u + v <= 1 and tmin < t <= tmax (edges inclusive, as the rasterizer's
 *   edge test, so a ray through a shared edge reports both faces). Barycentrics of the hit point
 *   x = l0 v0 + l1 v1 + l2 v2: (l0, l1, l2) = (1 - u - v, u, v) — for a pinhole camera's primary ray
 *   these equal the rasterizer's perspective-correct barycentrics, and t is the camera depth when
 *   d's camera-space z component is 1.
 * ray_box: slab test with precomputed 1/d (zero components replaced by a tiny value of the same sign).
 * bvh_begin / bvh_next_leaf: the walk of the implicit heap-ordered tree of bvh.cl with an explicit
 *   stack (nearer child first), returning leaf after leaf whose box the ray meets within [tmin, tmax];
 *   callers shrink tmax as they go (K-nearest, nearest) or keep it (transmittance).
 */
#ifndef TRIPLET_RAY_MATH_H
#define TRIPLET_RAY_MATH_H

#define BVH_STACK 34

inline REAL3 ray_inv_dir(REAL3 d)
{
    const REAL tiny = (REAL)1e-30;
    d.x = fabs(d.x) < tiny ? (d.x < (REAL)0 ? -tiny : tiny) : d.x;
    d.y = fabs(d.y) < tiny ? (d.y < (REAL)0 ? -tiny : tiny) : d.y;
    d.z = fabs(d.z) < tiny ? (d.z < (REAL)0 ? -tiny : tiny) : d.z;
    return (REAL)1 / d;
}

/* entry distance of the ray into box b within [tmin, tmax], or -1 (as a REAL) when it misses */
inline REAL ray_box(__global const REAL* b, const REAL3 o, const REAL3 inv, const REAL tmin, const REAL tmax)
{
    const REAL3 lo = (REAL3)(b[0], b[1], b[2]), hi = (REAL3)(b[3], b[4], b[5]);
    const REAL3 t0 = (lo - o) * inv, t1 = (hi - o) * inv;
    const REAL3 tn = fmin(t0, t1), tf = fmax(t0, t1);
    const REAL a = fmax(fmax(tn.x, tn.y), fmax(tn.z, tmin));
    const REAL c = fmin(fmin(tf.x, tf.y), fmin(tf.z, tmax));
    return a <= c ? a : -(REAL)1;
}

inline int ray_tri(const REAL3 o, const REAL3 d, const REAL3 v0, const REAL3 v1, const REAL3 v2,
                   const REAL tmin, const REAL tmax, REAL* t, REAL* u, REAL* v)
{
    const REAL3 e1 = v1 - v0, e2 = v2 - v0;
    const REAL3 p = cross(d, e2);
    const REAL det = dot(e1, p);
    if (det == (REAL)0) return 0;
    const REAL id = (REAL)1 / det;
    const REAL3 s = o - v0;
    const REAL uu = dot(s, p) * id;
    if (!(uu >= (REAL)0 && uu <= (REAL)1)) return 0;
    const REAL3 q = cross(s, e1);
    const REAL vv = dot(d, q) * id;
    if (!(vv >= (REAL)0 && uu + vv <= (REAL)1)) return 0;
    const REAL tt = dot(e2, q) * id;
    if (!(tt > tmin && tt <= tmax)) return 0;
    *t = tt;
    *u = uu;
    *v = vv;
    return 1;
}

/* Start a walk: push the root when the ray meets its box. */
inline void bvh_begin(__global const REAL* nodes, const REAL3 o, const REAL3 inv, const REAL tmin, const REAL tmax,
                      int* stack, REAL* tstack, int* sp)
{
    *sp = 0;
    const REAL t = ray_box(nodes, o, inv, tmin, tmax);
    if (t >= tmin) {
        stack[0] = 0;
        tstack[0] = t;
        *sp = 1;
    }
}

/* Next leaf (index j in [0, P)) whose box the ray meets within [tmin, tmax], or -1 when the walk is
 * over. Each node's box is tested once, by its parent; of two children met, the nearer is descended
 * first and the farther pushed with its entry distance, skipped when popped beyond the current tmax
 * (which nearest-hit callers shrink as they go). */
inline int bvh_next_leaf(__global const REAL* nodes, const int P, const REAL3 o, const REAL3 inv, const REAL tmin,
                         const REAL tmax, int* stack, REAL* tstack, int* sp)
{
    while (*sp > 0) {
        --(*sp);
        int n = stack[*sp];
        if (tstack[*sp] > tmax) continue;
        for (;;) {
            if (n >= P - 1) return n - (P - 1);
            const int a = 2 * n + 1, b = 2 * n + 2;
            const REAL ta = ray_box(nodes + (long)a * 6, o, inv, tmin, tmax);
            const REAL tb = ray_box(nodes + (long)b * 6, o, inv, tmin, tmax);
            const int ha = ta >= tmin, hb = tb >= tmin;
            if (ha && hb) {
                const int near_a = ta <= tb;
                stack[*sp] = near_a ? b : a;
                tstack[*sp] = near_a ? tb : ta;
                ++(*sp);
                n = near_a ? a : b;
            } else if (ha) {
                n = a;
            } else if (hb) {
                n = b;
            } else {
                break;
            }
        }
    }
    return -1;
}

inline int leaf_begin(const int j, const int M, const int P) { return (int)(((long)j * M) / P); }

#endif /* TRIPLET_RAY_MATH_H */
