/* fast_math.h — transcendental functions written in arithmetic, for the builtins that PoCL's CPU device
 * does not vectorise.
 *
 * Measured on PoCL 3.1 (this project's CPU device), 131k scalar calls in a kernel the work-group loop
 * vectorises: exp 0.20 ms, sqrt 0.08 ms, but log2 1.3 ms, exp2 1.3 ms, log 2.1 ms, pow 14 ms
 * (bench/results/fast_math_pocl_2026-11-28.txt): the latter are scalar library calls inside a vector loop.
 * A function made of arithmetic, integer bit operations and selects is inlined and vectorised with the
 * rest of the kernel. Only the float versions are replaced: the double builds (float64 gradient checks)
 * keep the builtins, whose accuracy the checks rely on.
 *
 * tl_log2(x), x a positive normal float: x = m 2^e with m in [sqrt(1/2), sqrt(2)), f = m - 1,
 * s = f / (2 + f), ln m = f - (f²/2 - s (f²/2 + R(s²))) with the degree-4 minimax polynomial R of
 * FreeBSD's e_logf.c (its published coefficients Lg1..Lg4, as musl's logf uses them), then
 * log2 x = e + ln m / ln 2. Error against float64 within 6e-7 + 6e-8 |log2 x| over every normal float, and
 * no larger than the builtin's on [1e-3, 1e6] (tests/test_fast_math.py). +inf gives +inf and NaN gives NaN;
 * zero, negative and subnormal inputs are outside its contract (color.cl calls it above the sRGB knee).
 */
#ifndef TRIPLET_FAST_MATH_H
#define TRIPLET_FAST_MATH_H

inline float tl_log2(const float x)
{
    const int ix = as_int(x);
    int e = ((ix >> 23) & 0xff) - 127;
    float m = as_float((ix & 0x007fffff) | 0x3f800000);  /* [1, 2) */
    const int big = m > 1.41421356f;
    m = big ? m * 0.5f : m;
    e = big ? e + 1 : e;
    const float f = m - 1.0f;
    const float s = f / (2.0f + f);
    const float z = s * s, w = z * z;
    const float t1 = w * (0.40000972152f + w * 0.24279078841f);
    const float t2 = z * (0.66666662693f + w * 0.28498786688f);
    const float hfsq = 0.5f * f * f;
    const float lnm = f - (hfsq - s * (hfsq + (t2 + t1)));
    const float r = (float)e + lnm * 1.44269504089f;
    return isfinite(x) ? r : x;  /* +inf stays +inf and NaN stays NaN (as the builtin): a NaN render must not turn
                                  * into a finite colour past the training's finiteness check */
}

#endif /* TRIPLET_FAST_MATH_H */
