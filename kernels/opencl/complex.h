/* complex.h: complex arithmetic shared by the OpenCL C kernels of rwwarp, one source for both
 * precisions (in the manner of pyopencl-complex.h).
 *
 * Build options (set by rwwarp/backend.py):
 *   -D REAL=double -D REAL_IS_DOUBLE=1   complex128 build (cplx_t = double2)
 *   -D REAL=float  -D REAL_IS_DOUBLE=0   complex64 build  (cplx_t = float2)
 *   -D RW_HAVE_FP64=1                    the device has double precision: phases, frequencies and
 *                                        coordinates (phase_t) are then always double, also in
 *                                        the complex64 build, because a phase of 1e5 cycles (z/lambda
 *                                        for z = 50 mm) cannot be formed in float
 *   -D RW_CUDA=1                         compiled as CUDA C++ by NVRTC (after cuda_compat.h)
 * A complex number is a 2-vector (x = real part, y = imaginary part), memory-compatible with numpy
 * complex64/complex128. Only .x/.y member access is used (no OpenCL vector literals or operators),
 * so the same code compiles as CUDA C++ where double2 is a plain struct.
 */
#ifndef RW_COMPLEX_H
#define RW_COMPLEX_H

#ifndef REAL
#define REAL double
#define REAL_IS_DOUBLE 1
#endif

#ifdef RW_CUDA
#define RW_FUNC __device__ __forceinline__
typedef long long idx_t;
#else
#if REAL_IS_DOUBLE || defined(RW_HAVE_FP64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif
#define RW_FUNC inline
typedef long idx_t;
#endif

typedef REAL real_t;
#if REAL_IS_DOUBLE
typedef double2 cplx_t;
#else
typedef float2 cplx_t;
#endif

#ifdef RW_HAVE_FP64
typedef double phase_t;
#else
typedef float phase_t;
#endif

#define RW_TWO_PI ((phase_t)6.28318530717958647692528676655900577)

#ifdef RW_CUDA
#define RW_SINCOS(x, s_ptr, c_ptr) sincos((x), (s_ptr), (c_ptr))
#else
#define RW_SINCOS(x, s_ptr, c_ptr) (*(s_ptr) = sincos((x), (c_ptr)))
#endif

RW_FUNC cplx_t c_make(const real_t re, const real_t im)
{
    cplx_t z;
    z.x = re;
    z.y = im;
    return z;
}

RW_FUNC cplx_t c_zero(void) { return c_make((real_t)0, (real_t)0); }

RW_FUNC cplx_t c_add(const cplx_t a, const cplx_t b) { return c_make(a.x + b.x, a.y + b.y); }

RW_FUNC cplx_t c_sub(const cplx_t a, const cplx_t b) { return c_make(a.x - b.x, a.y - b.y); }

RW_FUNC cplx_t c_conj(const cplx_t a) { return c_make(a.x, -a.y); }

RW_FUNC cplx_t c_mul(const cplx_t a, const cplx_t b)
{
    return c_make(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

/* conj(a) * b */
RW_FUNC cplx_t c_conj_mul(const cplx_t a, const cplx_t b)
{
    return c_make(a.x * b.x + a.y * b.y, a.x * b.y - a.y * b.x);
}

/* acc + a * b */
RW_FUNC cplx_t c_mad(const cplx_t a, const cplx_t b, const cplx_t acc)
{
    return c_make(acc.x + a.x * b.x - a.y * b.y, acc.y + a.x * b.y + a.y * b.x);
}

RW_FUNC cplx_t c_scale(const cplx_t a, const real_t s) { return c_make(a.x * s, a.y * s); }

RW_FUNC real_t c_abs2(const cplx_t a) { return a.x * a.x + a.y * a.y; }

/* exp(i * phase), phase in radians, formed in phase_t and rounded to real_t at the end */
RW_FUNC cplx_t c_expi(const phase_t phase)
{
    phase_t s, c;
    RW_SINCOS(phase, &s, &c);
    return c_make((real_t)c, (real_t)s);
}

/* t minus the nearest integer, in [-0.5, 0.5], for |t| < 2^51 (double) or 2^22 (float).
 * Adding and subtracting 1.5 * 2^52 (1.5 * 2^23) rounds to the nearest integer in the default
 * rounding mode; unlike rint() this vectorises on CPUs. Needs IEEE arithmetic (no fast-math). */
RW_FUNC phase_t rw_frac_nearest(const phase_t t)
{
#ifdef RW_HAVE_FP64
    const phase_t magic = (phase_t)6755399441055744.0;
#else
    const phase_t magic = (phase_t)12582912.0f;
#endif
    const phase_t shifted = t + magic;
    return t - (shifted - magic);
}

/* exp(2 pi i t), t in cycles; the whole cycles are removed first so that large t stays exact */
RW_FUNC cplx_t c_cis_cycles(const phase_t t)
{
#ifdef RW_CUDA
    phase_t s, c;
    sincospi((phase_t)2 * rw_frac_nearest(t), &s, &c);
    return c_make((real_t)c, (real_t)s);
#else
    return c_expi(RW_TWO_PI * rw_frac_nearest(t));
#endif
}

#endif /* RW_COMPLEX_H */
