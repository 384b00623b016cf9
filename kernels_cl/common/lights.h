/* lights.h — every light of the light table (triplet_cl/lights.py): its incident radiance at a
 * shaded point, the adjoint of that, and its shadow ray. shade.cl (both passes) and trace.cl
 * (shadow rays) read lights only through this header.
 *
 * Type ids come from the Python registry as generated defines (triplet_cl.lights.kernel_defines):
 *   -DLIGHT_<NAME>=id per light class, -DLIGHT_SHADOW_MASK = OR of (1 << id) of the shadow casters.
 * A light-table row is (type, off, a, b); q = lt_f + off are its parameters (see lights.py).
 *
 * What a light gives the shading (light_incident), by its term (light_term):
 *   LIGHT_TERM_DIRECT   radiance Li arriving along the unit direction L -> brdf_direct(N, V, L, Li, m)
 *     directional (d, I):          L = safe_normalize(d),  Li = I T
 *     point (q, I, falloff a):     w = q - x, L = safe_normalize(w), sc = a ? 1 / max(|w|^2, 1e-6) : 1,
 *                                  Li = I (sc T)
 *     vertex SH (vl = the fragment's row rad | wi):  L = safe_normalize(wi), Li = rad
 *   LIGHT_TERM_AMBIENT  constant radiance Li from every direction -> ambient_term(N, V, Li, m)
 *     ambient (La):                Li = La
 *     bounce (vl = the fragment's row rad | unused):  Li = rad (one diffuse bounce, traced per vertex)
 *   LIGHT_TERM_SH_ENV   SH radiance c [3, b], active degree a -> env_term (shade_brdf.h)
 *   (T: the transmittance vis[p, j] towards the j-th shadow caster, 1 without ray-traced shadows.)
 * Adjoint (light_incident_vjp), from v_L, v_Li (the BRDF's adjoints):
 *   v_T = v_Li . (Li / T)  (shadow casters, with vis), then v_Li *= T;
 *   directional: g = (safe_normalize_vjp(d, v_L), v_Li)
 *   point:       v_w = safe_normalize_vjp(w, v_L) - 2 w (I . v_Li) sc^2 [a, |w|^2 > 1e-6],
 *                v_x -= v_w, g = (v_w, v_Li sc)
 *   ambient:     g = v_Li
 *   vertex SH:   v_rad += v_Li, v_wi += safe_normalize_vjp(wi, v_L)
 *   bounce:      v_rad += v_Li
 *   (g: the gradients of the light's n parameters (its packed size, at most RED_W = 16), summed
 *   over fragments by shade.cl; the SH environment's coefficients have their own reduction.)
 * Shadow rays (light_shadow_ray; every light with CASTS_SHADOWS in lights.py owns one column of
 *   vis, in light order, whether or not it has a ray at a point): point: d = q - x,
 *   t in (eps / |d|, 1 - eps / |d|); directional: d = w, t in (eps / |w|, 1e30). Adjoint: the ray
 *   adjoint v_d is the light's SHADOW_RAY_PARAM's (position / direction, added by render.py) and,
 *   when light_shadow_ray_from_x, -v_d is the shaded point's.
 * Adding a light: its branch in each function below (and its class in lights.py).
 */
#ifndef TRIPLET_LIGHTS_H
#define TRIPLET_LIGHTS_H

#include "real.h"
#include "shade_math.h"

#ifndef LIGHT_SHADOW_MASK
#error "lights.h needs the light defines of triplet_cl.lights.kernel_defines()"
#endif

#define LIGHT_TERM_NONE 0
#define LIGHT_TERM_DIRECT 1
#define LIGHT_TERM_AMBIENT 2
#define LIGHT_TERM_SH_ENV 3

#define POINT_D2_EPS ((REAL)1e-6)
#define LIGHT_RGB(m, i) ((REAL3)((m)[(i)], (m)[(i) + 1], (m)[(i) + 2]))

/* whether lights of this type cast ray-traced shadows (a column of vis) */
inline int light_casts_shadows(const int type)
{
    return (LIGHT_SHADOW_MASK >> type) & 1;
}

/* How the shading uses a light (LIGHT_TERM_*). */
inline int light_term(const int type)
{
    if (type == LIGHT_AMBIENT || type == LIGHT_BOUNCE) return LIGHT_TERM_AMBIENT;
    if (type == LIGHT_DIRECTIONAL || type == LIGHT_POINT || type == LIGHT_VERTEX_SH) return LIGHT_TERM_DIRECT;
    if (type == LIGHT_SH_ENV) return LIGHT_TERM_SH_ENV;
    return LIGHT_TERM_NONE;
}

/* The light's term at a fragment at x (vl: the fragment's row of a per-fragment light, rad | wi); tv:
 * transmittance towards it (1 without shadows). Fills L, Li for LIGHT_TERM_DIRECT, Li for LIGHT_TERM_AMBIENT. */
inline int light_incident(const int type, const int a, __global const REAL* q, const REAL3 x,
                          __global const REAL* vl, const REAL tv, REAL3* L, REAL3* Li)
{
    if (type == LIGHT_AMBIENT) {
        *Li = LIGHT_RGB(q, 0);
    } else if (type == LIGHT_DIRECTIONAL) {
        *L = safe_normalize(LIGHT_RGB(q, 0));
        *Li = LIGHT_RGB(q, 3) * tv;
    } else if (type == LIGHT_POINT) {
        const REAL3 w = LIGHT_RGB(q, 0) - x;
        const REAL sc = a ? (REAL)1 / fmax(dot(w, w), POINT_D2_EPS) : (REAL)1;
        *L = safe_normalize(w);
        *Li = LIGHT_RGB(q, 3) * (sc * tv);
    } else if (type == LIGHT_VERTEX_SH) {
        *L = safe_normalize(LIGHT_RGB(vl, 3));
        *Li = LIGHT_RGB(vl, 0);
    } else if (type == LIGHT_BOUNCE) {
        *Li = LIGHT_RGB(vl, 0);
    }
    return light_term(type);
}

/* Adjoint of light_incident for v_L, v_Li: the light's parameter gradients g[0..n),
 * v_x (shaded point), v_rad / v_wi (vlight), and with has_vis the transmittance's v_tv. */
inline void light_incident_vjp(const int type, const int a, __global const REAL* q, const REAL3 x,
                               __global const REAL* vl, const REAL tv, const int has_vis,
                               const REAL3 v_L, REAL3 v_Li, REAL* g, REAL3* v_x, REAL3* v_rad, REAL3* v_wi,
                               REAL* v_tv)
{
    if (type == LIGHT_AMBIENT) {
        g[0] = v_Li.x;
        g[1] = v_Li.y;
        g[2] = v_Li.z;
    } else if (type == LIGHT_DIRECTIONAL) {
        const REAL3 d = LIGHT_RGB(q, 0);
        if (has_vis) {
            *v_tv = dot(v_Li, LIGHT_RGB(q, 3));
            v_Li *= tv;
        }
        const REAL3 v_d = safe_normalize_vjp(d, v_L);
        g[0] = v_d.x;
        g[1] = v_d.y;
        g[2] = v_d.z;
        g[3] = v_Li.x;
        g[4] = v_Li.y;
        g[5] = v_Li.z;
    } else if (type == LIGHT_POINT) {
        const REAL3 I = LIGHT_RGB(q, 3);
        const REAL3 w = LIGHT_RGB(q, 0) - x;
        const REAL d2 = dot(w, w);
        const REAL sc = a ? (REAL)1 / fmax(d2, POINT_D2_EPS) : (REAL)1;
        if (has_vis) {
            *v_tv = dot(v_Li, I * sc);
            v_Li *= tv;
        }
        REAL3 v_w = safe_normalize_vjp(w, v_L);
        if (a && d2 > POINT_D2_EPS) v_w -= (REAL)2 * w * (dot(I, v_Li) * sc * sc);
        *v_x -= v_w;
        g[0] = v_w.x;
        g[1] = v_w.y;
        g[2] = v_w.z;
        g[3] = v_Li.x * sc;
        g[4] = v_Li.y * sc;
        g[5] = v_Li.z * sc;
    } else if (type == LIGHT_VERTEX_SH) {
        *v_rad += v_Li;
        *v_wi += safe_normalize_vjp(LIGHT_RGB(vl, 3), v_L);
    } else if (type == LIGHT_BOUNCE) {
        *v_rad += v_Li;
    }
}

/* The shadow ray of a light for a point x: direction d (unnormalised), [tmin, tmax]; 0: no ray. */
inline int light_shadow_ray(const int type, __global const REAL* q, const REAL3 x, const REAL eps, REAL3* d,
                            REAL* tmin, REAL* tmax)
{
    const REAL3 a = (REAL3)(q[0], q[1], q[2]);
    if (type == LIGHT_POINT) {
        *d = a - x;
        const REAL len = length(*d);
        *tmin = eps / fmax(len, (REAL)1e-30);
        *tmax = (REAL)1 - *tmin;
        return 1;
    }
    if (type == LIGHT_DIRECTIONAL) {
        *d = a;
        *tmin = eps / fmax(length(a), (REAL)1e-30);
        *tmax = (REAL)1e30;
        return 1;
    }
    return 0;
}

/* Adjoint of the shadow ray's direction v_d: the light parameter's share (its first 3 parameters)
 * is v_d itself; when this returns 1 (d = q - x) the shaded point's share is -v_d. */
inline int light_shadow_ray_from_x(const int type)
{
    return type == LIGHT_POINT;
}

#endif /* TRIPLET_LIGHTS_H */
