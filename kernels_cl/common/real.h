/* real.h — the scalar type of a program and small helpers shared by every kernel.
 *
 * Programs are built with -DREAL=float (production) or -DREAL=double (float64 gradient tests on
 * devices with cl_khr_fp64). Kernels use REAL, REAL2, REAL3, REAL4 and never write float/double.
 * OpenCL C 1.2 only: no float atomics, no generic address space.
 */
#ifndef TRIPLET_REAL_H
#define TRIPLET_REAL_H

#ifndef REAL
#define REAL float
#endif

#define TRIPLET_CAT_(a, b) a##b
#define TRIPLET_CAT(a, b) TRIPLET_CAT_(a, b)

#define REAL_IS_DOUBLE (sizeof(REAL) == 8)

#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#define REAL2 TRIPLET_CAT(REAL, 2)
#define REAL3 TRIPLET_CAT(REAL, 3)
#define REAL4 TRIPLET_CAT(REAL, 4)
#define REAL8 TRIPLET_CAT(REAL, 8)
#define REAL16 TRIPLET_CAT(REAL, 16)

/* Load/store a 3-vector from a packed [N,3] array (vload3 works on both float and double). */
#define LOAD3(p, i) vload3((i), (p))
#define STORE3(v, p, i) vstore3((v), (i), (p))

#endif /* TRIPLET_REAL_H */
