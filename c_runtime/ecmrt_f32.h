/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_f32.h - ecmgen C runtime, numeric = "float" (IEEE-754 binary32): the grids, the
 * lookups and interpolation, the maths without libm, and (ecmrt_f32_step.h) the step's units.
 *
 * Included by a generated <prefix>_ecm_f32_config.h, whose <prefix>_ecm_f32.c writes the
 * model's step from these units, calling those its model has (hand-written,
 * model-independent: every function takes what it reads as arguments, so this compiles as it
 * is for every model; an unused static inline function costs nothing). All functions are
 * static: no external symbols, so several models link together.
 *
 * Bit-for-bit reproducibility (host == Cortex-M4F == ecmgen.c.cref.simulate_f32) rests on:
 *   - only + - * / on float, each rounded once (compile with -ffp-contract=off, never
 *     -ffast-math; FLT_EVAL_METHOD must be 0, checked below);
 *   - no libm: exp, log, sqrt are built here from those operations;
 *   - a fixed order of operations, mirrored line by line in src/ecmgen/c/cref.py.
 */
#ifndef ECMRT_F32_H
#define ECMRT_F32_H

#include <float.h>
#include "ecmrt.h"

#if defined(__FAST_MATH__) && !defined(ECMRT_ALLOW_FAST_MATH)
#error "-ffast-math reorders and contracts float arithmetic: the step is no longer bit-exact (build without it and with -ffp-contract=off, or define ECMRT_ALLOW_FAST_MATH)"
#endif
#if !defined(FLT_EVAL_METHOD) || FLT_EVAL_METHOD != 0
#error "float expressions must be evaluated in float (FLT_EVAL_METHOD == 0), e.g. SSE or an FPv4-SP FPU"
#endif

/* SOC is saturated to [ECMRT_F32_SOC_MIN, ECMRT_F32_SOC_MAX] (same span as the Q30 fixed-point
 * variant); dt to [0, ECMRT_F32_DT_MAX] seconds (negative or NaN dt counts as 0). */
#define ECMRT_F32_SOC_MIN (-2.0f)
#define ECMRT_F32_SOC_MAX 2.0f
#define ECMRT_F32_DT_MAX 32767.0f
/* temperature_dependence: the temperature saturates to [-40, 85] degC (NaN: -40) */
#define ECMRT_F32_ARR_T_MIN (-40.0f)
#define ECMRT_F32_ARR_T_MAX 85.0f

/* One grid: n breakpoints x (strictly increasing) and inv_dx[k] = 1 / (x[k+1] - x[k]). */
typedef struct {
    const float *x;
    const float *inv_dx;
    uint8_t n;
} ecmrt_f32_grid_t;

/* A uniform grid: n breakpoints x0 + k / inv_h; um = n - 1. */
typedef struct {
    float x0;
    float inv_h;
    float um;
    uint8_t n;
} ecmrt_f32_ugrid_t;

/* The tables (generated): per direction the parameters per SOC breakpoint, breakpoint after
 * breakpoint, then temperature row after temperature row, so that one base pointer serves
 * every interpolation; each value a pair (y[k], y[k+1] - y[k]), the value and the float32
 * difference to the next SOC breakpoint (over temperature: to the next temperature row), the
 * subtraction done once by the generator, in float32, so the interpolation gives the same
 * bits as subtracting at run time (0 at the last breakpoint). The generated header says which
 * parameters a model's rows hold, in which order. */

/* Segment k (0 <= k <= n-2) holding v, returned in *kp, and the weight w in [0, 1] of
 * x[k+1]; v outside the grid gives w = 0 at the first point or w = 1 at the last (clamped
 * interpolation), NaN counts as below the grid. The search walks from *kp (the last step's
 * segment, a hint kept in the state): exact whatever the hint, and O(1) when v moves little
 * (the usual case costs two comparisons: the table ends are only looked at when the walk
 * reaches them). *kp is a local of the step: the hints go back to the state at its end, so
 * that no uint8_t store (which may alias anything) forces the tables to be reloaded. */
static inline float ecmrt_f32_locate(const ecmrt_f32_grid_t *g, float v, unsigned *kp)
{
    const float *x = g->x;
    const unsigned last = (unsigned)g->n - 2u;
    unsigned k = *kp;
    if (k > last) {
        k = last;                           /* a corrupted hint costs a longer walk only */
    }
    if (!(v >= x[k])) {
        do {
            if (k == 0u) {
                *kp = 0u;                   /* v < x[0], or NaN */
                return 0.0f;
            }
            k--;
        } while (!(v >= x[k]));
    } else if (v >= x[k + 1u]) {
        do {
            if (k == last) {
                *kp = last;                 /* v >= x[n-1] */
                return 1.0f;
            }
            k++;
        } while (v >= x[k + 1u]);
    }
    *kp = k;                                /* x[k] <= v < x[k+1] */
    return (v - x[k]) * g->inv_dx[k];
}

/* As ecmrt_f32_locate on a uniform grid, in O(1): u = (v - x0) inv_h, k = floor(u), w = u - k
 * (exact); below the grid (or NaN) k = 0, w = 0, at or above its end k = n - 2, w = 1. */
static inline float ecmrt_f32_ulocate(const ecmrt_f32_ugrid_t *g, float v, unsigned *kp)
{
    const float u = (v - g->x0) * g->inv_h;
    int32_t k;
    if (!(u >= 0.0f)) {
        *kp = 0u;
        return 0.0f;
    }
    if (!(u < g->um)) {
        *kp = (unsigned)g->n - 2u;
        return 1.0f;
    }
    k = (int32_t)u;
    *kp = (unsigned)k;
    return u - (float)k;
}

/* y[k] + (y[k+1] - y[k]) w from a pair (y[k], y[k+1] - y[k]) of a table (or of the pairs
 * ecmrt_f32_segment keeps) */
static inline float ecmrt_f32_lerp(const float *yd, float w)
{
    return yd[0] + yd[1] * w;
}

/* out of the step's hot path (and no warning where a model does not call it) */
#if defined(__GNUC__)
#define ECMRT_F32_COLD static __attribute__((noinline, unused))
#else
#define ECMRT_F32_COLD static inline
#endif

/* Bilinear, temperature first: the pairs of a segment at the temperature. yd points at SOC
 * point k of temperature row kt of a table whose values are pairs along temperature
 * (y[kt][k], y[kt+1][k] - y[kt][k]), npar floats per SOC point; for each of the np / 2
 * parameters, pc gets (a, b - a) with a, b the values at points k, k+1 at weight wt between
 * the rows. The step then takes a + (b - a) w: pc is kept in the state with the segment,
 * direction and temperature it belongs to (the SOC moves little between steps). */
ECMRT_F32_COLD void ecmrt_f32_segment(const float *yd, unsigned npar, unsigned np, float wt,
                                      float *pc)
{
    unsigned j;
    for (j = 0u; j < np; j += 2u) {
        const float a = yd[j] + yd[j + 1u] * wt;
        const float b = yd[npar + j] + yd[npar + j + 1u] * wt;
        pc[j] = a;
        pc[j + 1u] = b - a;
    }
}

/* The same for one parameter, inline, and the value at weight w along SOC: a + (b - a) w */
static inline float ecmrt_f32_bilerp(const float *yd, unsigned npar, float wt, float w)
{
    const float a = yd[0] + yd[1] * wt;
    return a + ((yd[npar] + yd[npar + 1u] * wt) - a) * w;
}

/* exp(-x) = s (1 + q) for 0 <= x < 87: x = n ln2 + r, |r| <= ln2/2 (Cody-Waite: n * LN2_HI
 * is exact for n < 256; n = 0, r = x below ln2/2), s = 2^-n built exactly (a normal
 * number), q = exp(-r) - 1 by its Taylor series to t^7 (t = -r); returns q, s in *sp. */
static inline float ecmrt_f32_exp_neg_parts(float x, float *sp)
{
    int32_t n = 0;
    float fn, r = x, t, q;
    union {
        uint32_t u;
        float f;
    } bits;
    if (!(x < 0.346573591f)) {
        n = (int32_t)(x * 1.44269502f + 0.5f);
        fn = (float)n;
        r = (x - fn * 0.693145752f) - fn * 1.42860677e-06f;
    }
    t = -r;
    q = 1.98412701e-04f;                    /* 1/5040 */
    q = 1.38888892e-03f + t * q;            /* 1/720 */
    q = 8.33333377e-03f + t * q;            /* 1/120 */
    q = 4.16666679e-02f + t * q;            /* 1/24 */
    q = 1.66666672e-01f + t * q;            /* 1/6 */
    q = 0.5f + t * q;
    q = 1.0f + t * q;
    bits.u = (uint32_t)(127 - n) << 23;
    *sp = bits.f;
    return t * q;
}

/* c = 1 - exp(-x) for x = dt/tau >= 0, to < 2 ulp, from + - * and exact powers of two.
 * x <= 0 or NaN gives 0; x >= 87 gives 1. (Also the effects' exp, in both dt modes.) */
static inline float ecmrt_f32_one_minus_exp_neg(float x)
{
    float q, s;
    union {
        uint32_t u;
        float f;
    } bits;
    bits.f = x;
    if (bits.u < 0x3E800000u) {             /* +0 <= x < 1/4 (one unsigned compare) */
        /* the dt/tau of a 10 Hz task (tau > 0.4 s): c = x P(x), P(x) = 1 - b1 x + b2 x^2 -
         * b3 x^3 + b4 x^4 the minimax polynomial of (1 - exp(-x))/x on [0, 1/4] with P(0) = 1
         * (relative error < 2^-28.4; evaluated < 1.6 ulp); x = +0 gives +0 */
        q = x * 7.53017003e-03f - 4.15001325e-02f;
        q = x * q + 1.66652888e-01f;
        q = x * q - 4.99999642e-01f;
        q = x * q + 1.0f;
        return x * q;
    }
    if (!(x > 0.0f)) {
        return 0.0f;                        /* x <= 0 (-0, negative) */
    }
    if (!(x < 87.0f)) {
        return x == x ? 1.0f : 0.0f;        /* exp(-87) < 2^-125: c rounds to 1; NaN: 0 */
    }
    q = ecmrt_f32_exp_neg_parts(x, &s);
    return (1.0f - s) - s * q;              /* s = 1 (n = 0): exactly -q */
}

/* temperature_dependence's factor f = exp(a_k (1/(T + 273.15) - 1/(t_ref + 273.15))),
 * inv_ref = 1/(t_ref + 273.15), T saturated to [-40, 85] degC (NaN: -40); exp(y) as
 * exp(-(-y)) for y <= 0, 1/exp(-y) for y > 0 */
static inline float ecmrt_f32_arrhenius(float a_k, float inv_ref, float temp)
{
    float y, q, s;
    if (!(temp >= ECMRT_F32_ARR_T_MIN)) {
        temp = ECMRT_F32_ARR_T_MIN;
    } else if (temp > ECMRT_F32_ARR_T_MAX) {
        temp = ECMRT_F32_ARR_T_MAX;
    }
    y = (1.0f / (temp + 273.149994f) - inv_ref) * a_k;
    if (y > 0.0f) {
        q = ecmrt_f32_exp_neg_parts(y, &s);
        return 1.0f / (s + s * q);
    }
    q = ecmrt_f32_exp_neg_parts(-y, &s);
    return s + s * q;
}

/* sqrt(w) for 1 <= w < 2^100 (the Butler-Volmer and current-dependent factors) and for the
 * estimator's SOC sigma (1e-12 < w <= 1): bit-trick start (within 4 % at any exponent),
 * four Newton steps (deterministic, <= 1 ulp) */
static inline float ecmrt_f32_sqrt(float w)
{
    union {
        uint32_t u;
        float f;
    } bits;
    float r;
    bits.f = w;
    bits.u = (bits.u >> 1) + 0x1FBD1DF5u;
    r = bits.f;
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    return r;
}

/* log(1 + y) for 0 <= y < 2^100: 1 + y = 2^n m, m in [sqrt(1/2), sqrt(2)) (n = 0 and
 * m - 1 = y exactly below sqrt(2) - 1), log = n ln2 + 2 atanh(f / (2 + f)), f = m - 1,
 * atanh by its series to t^13 (|t| < 0.172: error < 1e-9 relative). */
static inline float ecmrt_f32_log1p(float y)
{
    union {
        uint32_t u;
        float f;
    } bits;
    int32_t n;
    float f, t, t2, p;
    if (y < 0.414213568f) {
        n = 0;
        f = y;
    } else {
        bits.f = 1.0f + y;
        n = (int32_t)((bits.u >> 23) & 0xFFu) - 127;
        bits.u = (bits.u & 0x007FFFFFu) | 0x3F800000u;   /* m in [1, 2) */
        f = bits.f;
        if (f > 1.41421354f) {
            f = f * 0.5f;
            n = n + 1;
        }
        f = f - 1.0f;
    }
    t = f / (2.0f + f);
    t2 = t * t;
    p = 7.69230798e-02f;                    /* 1/13 */
    p = 9.09090936e-02f + t2 * p;           /* 1/11 */
    p = 1.11111112e-01f + t2 * p;           /* 1/9 */
    p = 1.42857149e-01f + t2 * p;           /* 1/7 */
    p = 2.00000003e-01f + t2 * p;           /* 1/5 */
    p = 3.33333343e-01f + t2 * p;           /* 1/3 */
    p = (2.0f * t) + (2.0f * t) * (t2 * p);
    if (n == 0) {
        return p;
    }
    return ((float)n * 0.693145752f + p) + (float)n * 1.42860677e-06f;
}

/* asinh(x) for 1e-12 <= x <= 1e9: log1p(x + x^2/(sqrt(x^2+1)+1)); *xp = max(x, 1e-12) */
static inline float ecmrt_f32_asinh(float *xp)
{
    float x = *xp, x2;
    if (!(x > 1.0e-12f)) {
        x = 1.0e-12f;
    }
    *xp = x;
    x2 = x * x;
    return ecmrt_f32_log1p(x + x2 / (ecmrt_f32_sqrt(x2 + 1.0f) + 1.0f));
}

/* The cell's age, efc equivalent full cycles (clamped to the law's breakpoints g; NaN: the
 * first): the resistance scale (*age_r) and the SOC's k_soc over the aged capacity (*k_aged,
 * k_soc times 1 / capacity scale), kept in the state until the next call (the age changes
 * over weeks; the step only multiplies). scale holds per breakpoint the pairs of the
 * resistance scale and of 1 / capacity scale, so nothing divides. */
static inline void ecmrt_f32_age(const ecmrt_f32_grid_t *g, const float *scale, float k_soc,
                                 float efc, float *age_r, float *k_aged)
{
    unsigned k = 0u;
    const float w = ecmrt_f32_locate(g, efc, &k);
    const float *a = scale + 4u * k;
    *age_r = ecmrt_f32_lerp(a, w);
    *k_aged = k_soc * ecmrt_f32_lerp(a + 2u, w);
}

/* the SOC at init, saturated to [SOC_MIN, SOC_MAX] (NaN: 0) */
static inline float ecmrt_f32_soc0(float soc0)
{
    if (soc0 != soc0) {
        soc0 = 0.0f;                        /* NaN */
    } else if (soc0 < ECMRT_F32_SOC_MIN) {
        soc0 = ECMRT_F32_SOC_MIN;
    } else if (soc0 > ECMRT_F32_SOC_MAX) {
        soc0 = ECMRT_F32_SOC_MAX;
    }
    return soc0;
}

#include "ecmrt_f32_step.h"  /* the step's units, one per stage and effect */

#endif /* ECMRT_F32_H */
