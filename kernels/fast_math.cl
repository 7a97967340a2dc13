/* fast_math.cl: the fast builds' reciprocal and reciprocal square root over `floatv` (V lanes),
 * included by verlet_cloth.cl and pbd_cloth.cl after they define floatv and V. Fast builds only
 * (strict rounds every operation correctly). PoCL 3.1 builds rsqrt() as a correctly rounded
 * sqrt and division, and 1/x as a division, each costing more than the rest of a spring on
 * AVX-512 (docs/pbd.md, "Time per step on OpenCL"); its native_rsqrt() is no quicker. With AVX-512 and 16 lanes these are the 14-bit estimates with one Newton step
 * (about 23 bits); elsewhere the built-ins. */
#ifndef CLOTH_STRICT
#if V == 16 && defined(__AVX512F__)
#ifndef FLOATV_ZERO /* kernels/machine_bounds.c, which times these in C, spells it its own way */
#define FLOATV_ZERO 0.0f
#endif
typedef float v16sf __attribute__((vector_size(64)));
INLINE floatv fast_rsqrt(floatv x)
{
    union { floatv f; v16sf v; } in, zero, y;
    in.f = x, zero.f = FLOATV_ZERO;
    y.v = __builtin_ia32_rsqrt14ps512_mask(in.v, zero.v, (unsigned short)0xffff);
    return y.f * (1.5f - (0.5f * x) * (y.f * y.f));
}
INLINE floatv fast_recip(floatv x)
{
    union { floatv f; v16sf v; } in, zero, y;
    in.f = x, zero.f = FLOATV_ZERO;
    y.v = __builtin_ia32_rcp14ps512_mask(in.v, zero.v, (unsigned short)0xffff);
    return y.f * (2.0f - x * y.f);
}
#else
#define fast_rsqrt rsqrt
#define fast_recip(x) (1.0f / (x))
#endif
#endif
