/* shade_math.h — small vector maths shared by the shading, normal and SH kernels, as pairs
 * f() / f_vjp().
 *
 *   safe_normalize(v) = v / sqrt(max(|v|^2, SAFE_EPS2))
 *     vjp: |v|^2 > SAFE_EPS2:  v_v = (v_n - n (n . v_n)) / |v|        (n = v/|v|)
 *          otherwise:          v_v = v_n / sqrt(SAFE_EPS2)             (the map is linear there)
 *     A zero vector maps to zero (no NaN); the derivative of exactly what is computed is returned.
 *
 *   cross(a, b):  v_a = b x v_c,  v_b = v_c x a
 *
 *   safe_pow(x, e) = x > 0 ? exp(e log x) : 0      (x >= 0, e >= 1 in use)
 *     vjp: v_x = v_y e x^(e-1),  v_e = v_y y log x  (both 0 where x <= 0)
 */
#ifndef TRIPLET_SHADE_MATH_H
#define TRIPLET_SHADE_MATH_H

#include "real.h"

#define SAFE_EPS2 ((REAL)1e-20)
#define R_PI ((REAL)3.14159265358979323846)

inline REAL3 safe_normalize(const REAL3 v)
{
    return v * rsqrt(fmax(dot(v, v), SAFE_EPS2));
}

inline REAL3 safe_normalize_vjp(const REAL3 v, const REAL3 v_n)
{
    const REAL l2 = dot(v, v);
    if (l2 > SAFE_EPS2) {
        const REAL il = rsqrt(l2);
        const REAL3 n = v * il;
        return (v_n - n * dot(n, v_n)) * il;
    }
    return v_n * rsqrt(SAFE_EPS2);
}

inline void cross_vjp(const REAL3 a, const REAL3 b, const REAL3 v_c, REAL3* v_a, REAL3* v_b)
{
    *v_a += cross(b, v_c);
    *v_b += cross(v_c, a);
}

inline REAL safe_pow(const REAL x, const REAL e)
{
    return x > (REAL)0 ? exp(e * log(x)) : (REAL)0;
}

inline void safe_pow_vjp(const REAL x, const REAL e, const REAL v_y, REAL* v_x, REAL* v_e)
{
    if (x > (REAL)0) {
        const REAL lx = log(x);
        *v_x += v_y * e * exp((e - (REAL)1) * lx);
        *v_e += v_y * exp(e * lx) * lx;
    }
}

#endif /* TRIPLET_SHADE_MATH_H */
