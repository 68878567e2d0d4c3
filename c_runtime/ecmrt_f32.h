/*
 * ecmrt_f32.h - ecmgen C runtime, numeric = "float" (IEEE-754 binary32).
 *
 * Included once by a generated <prefix>_ecm.c after it defines
 *     ECMRT_VARIABLE_DT   1: step(state, i, dt), coefficients 1 - exp(-dt/tau) at run time
 *                         0: step(state, i), D = 1/(1 - exp(-dt/tau)) precomputed for the
 *                            build's dt and interpolated; the step divides by D
 * All functions are static inline: no external symbols, so several models link together.
 *
 * Bit-for-bit reproducibility (host == Cortex-M4F == ecmgen.cref.simulate_f32) rests on:
 *   - only + - * / on float, each rounded once (compile with -ffp-contract=off, never
 *     -ffast-math; FLT_EVAL_METHOD must be 0, checked below);
 *   - no libm: exp is ecmrt_f32_one_minus_exp_neg() below, built from those operations;
 *   - a fixed order of operations, mirrored line by line in src/ecmgen/cref.py.
 */
#ifndef ECMRT_F32_H
#define ECMRT_F32_H

#include <float.h>
#ifndef ECMRT_NEED_F32_STATE
#define ECMRT_NEED_F32_STATE
#endif
#include "ecmrt.h"

#if ECMRT_VERSION != 1
#error "ecmrt_f32.h does not match ecmrt.h"
#endif
#ifndef ECMRT_VARIABLE_DT
#error "define ECMRT_VARIABLE_DT (0 or 1) before including ecmrt_f32.h"
#endif
#if !defined(FLT_EVAL_METHOD) || FLT_EVAL_METHOD != 0
#error "float expressions must be evaluated in float (FLT_EVAL_METHOD == 0), e.g. SSE or an FPv4-SP FPU"
#endif

/* SOC is saturated to [ECMRT_F32_SOC_MIN, ECMRT_F32_SOC_MAX] (same span as the Q30 fixed-point
 * variant); dt to [0, ECMRT_F32_DT_MAX] seconds (negative or NaN dt counts as 0). */
#define ECMRT_F32_SOC_MIN (-2.0f)
#define ECMRT_F32_SOC_MAX 2.0f
#define ECMRT_F32_DT_MAX 32767.0f

/* One SOC grid: n breakpoints x (strictly increasing) and inv_dx[k] = 1 / (x[k+1] - x[k]). */
typedef struct {
    const float *x;
    const float *inv_dx;
    uint8_t n;
} ecmrt_f32_grid_t;

/* Parameters of one current direction: ECMRT_NPAR values per breakpoint, row after row,
 * rows[ECMRT_NPAR * k + ECMRT_P_*], so that one base pointer serves every interpolation.
 * Each parameter is a pair (y[k], y[k+1] - y[k]): the value and the float32 difference to
 * the next breakpoint (the subtraction done once by the generator, in float32, so the
 * interpolation gives the same bits as subtracting at run time; 0 in the last row).
 * ECMRT_P_KF / ECMRT_P_KS hold the time constants tau in s (ECMRT_VARIABLE_DT = 1) or
 * D = 1/(1 - exp(-dt/tau)) (ECMRT_VARIABLE_DT = 0). */
#define ECMRT_NPAR 10u
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 2u
#define ECMRT_P_KF 4u
#define ECMRT_P_RS 6u
#define ECMRT_P_KS 8u

typedef struct {
    ecmrt_f32_grid_t g;
    const float *rows;
} ecmrt_f32_dir_t;

typedef struct {
    ecmrt_f32_grid_t ocv_g;
    const float *ocv;         /* pairs (ocv[k], ocv[k+1] - ocv[k]), as the rows */
    ecmrt_f32_dir_t dir[2];   /* [ECMRT_DISCHARGE], [ECMRT_CHARGE] */
    float deadband_a;         /* |i| <= deadband keeps the last direction */
    float i_max_a;            /* current is saturated to [-i_max_a, i_max_a] */
    float k_soc;              /* 1/(3600 Q) per A*s (variable dt) or dt/(3600 Q) per A (fixed dt) */
} ecmrt_f32_model_t;

/* Segment k (0 <= k <= n-2) holding soc, returned in *hint, and the weight w in [0, 1] of
 * x[k+1]; SOC outside the grid gives w = 0 at the first point or w = 1 at the last (clamped
 * interpolation). The search walks from *hint (the last step's segment): exact whatever the
 * hint, and O(1) when SOC moves little (the usual case costs two comparisons: the table
 * ends are only looked at when the walk reaches them). */
static inline float ecmrt_f32_locate(const ecmrt_f32_grid_t *g, float soc, uint8_t *hint)
{
    const float *x = g->x;
    const unsigned last = (unsigned)g->n - 2u;
    unsigned k = *hint;
    if (k > last) {
        k = last;                           /* a corrupted hint costs a longer walk only */
    }
    if (soc < x[k]) {
        do {
            if (k == 0u) {
                *hint = 0u;                 /* soc < x[0] */
                return 0.0f;
            }
            k--;
        } while (soc < x[k]);
    } else if (soc >= x[k + 1u]) {
        do {
            if (k == last) {
                *hint = (uint8_t)last;      /* soc >= x[n-1] */
                return 1.0f;
            }
            k++;
        } while (soc >= x[k + 1u]);
    }
    *hint = (uint8_t)k;                     /* x[k] <= soc < x[k+1] (or soc NaN) */
    return (soc - x[k]) * g->inv_dx[k];
}

/* y[k] + (y[k+1] - y[k]) w from a pair (y[k], y[k+1] - y[k]) of a table */
static inline float ecmrt_f32_lerp(const float *yd, float w)
{
    return yd[0] + yd[1] * w;
}

/* c = 1 - exp(-x) for x = dt/tau >= 0, to ~1 ulp, from + - * and exact powers of two.
 * x <= 0 or NaN gives 0; x >= 87 gives 1. (Also the effects' exp, in both dt modes.) */
static inline float ecmrt_f32_one_minus_exp_neg(float x)
{
    int32_t n;
    float fn, r, t, q, s;
    union {
        uint32_t u;
        float f;
    } bits;
    bits.f = x;
    if (bits.u < 0x3D000000u) {             /* +0 <= x < 2^-5 (one unsigned compare) */
        /* c = x (1 - x (1/2 - x (1/6 - x/24))): relative truncation error < x^4/120 <
         * 2^-26.9; evaluated with alternating signs (q = -(1/6 - x/24), ...; negation is
         * exact) so that each step is one multiply and one add; x = +0 gives +0 */
        q = x * 4.16666679e-02f - 1.66666672e-01f;
        q = 0.5f + x * q;
        q = x * q - 1.0f;
        return -(x * q);
    }
    if (x < 0.346573591f) {                 /* ln2/2: no reduction needed (n = 0, r = x) */
        if (!(x > 0.0f)) {
            return 0.0f;                    /* x <= 0 (-0, negative) */
        }
        n = 0;
        r = x;
    } else if (!(x < 87.0f)) {
        return x == x ? 1.0f : 0.0f;        /* exp(-87) < 2^-125: c rounds to 1; NaN: 0 */
    } else {
        /* x = n ln2 + r, |r| <= ln2/2 (Cody-Waite: n * LN2_HI is exact for n < 256) */
        n = (int32_t)(x * 1.44269502f + 0.5f);
        fn = (float)n;
        r = (x - fn * 0.693145752f) - fn * 1.42860677e-06f;
    }
    /* q = exp(-r) - 1, Taylor series to t^7 in Horner form (t = -r, |t| < 0.35) */
    t = -r;
    q = 1.98412701e-04f;                    /* 1/5040 */
    q = 1.38888892e-03f + t * q;            /* 1/720 */
    q = 8.33333377e-03f + t * q;            /* 1/120 */
    q = 4.16666679e-02f + t * q;            /* 1/24 */
    q = 1.66666672e-01f + t * q;            /* 1/6 */
    q = 0.5f + t * q;
    q = 1.0f + t * q;
    q = t * q;
    if (n == 0) {
        return -q;
    }
    /* exp(-x) = s (1 + q), s = 2^-n (1 <= n <= 126: a normal number, built exactly) */
    bits.u = (uint32_t)(127 - n) << 23;
    s = bits.f;
    return (1.0f - s) - s * q;
}

static inline void ecmrt_f32_init(ecmrt_f32_state_t *s, float soc0)
{
    if (soc0 != soc0) {
        soc0 = 0.0f;                        /* NaN */
    } else if (soc0 < ECMRT_F32_SOC_MIN) {
        soc0 = ECMRT_F32_SOC_MIN;
    } else if (soc0 > ECMRT_F32_SOC_MAX) {
        soc0 = ECMRT_F32_SOC_MAX;
    }
    s->soc = soc0;
    s->soc_c = 0.0f;
    s->u_fast = 0.0f;
    s->u_slow = 0.0f;
    s->charging = (uint8_t)ECMRT_DISCHARGE;
    s->k_ocv = 0u;
    s->k_dir[0] = 0u;
    s->k_dir[1] = 0u;
}

/* One step of the discrete 2RC model (src/ecmgen/simulate.py), current i in A (positive =
 * charge) held over the step; returns the terminal voltage in V. */
#if ECMRT_VARIABLE_DT
static inline float ecmrt_f32_step(const ecmrt_f32_model_t *m, ecmrt_f32_state_t *s,
                                   float i, float dt)
#else
static inline float ecmrt_f32_step(const ecmrt_f32_model_t *m, ecmrt_f32_state_t *s, float i)
#endif
{
    const ecmrt_f32_dir_t *d;
    const float *row;
    unsigned dir;
    float soc, y, w, r0, rf, rs, uf, us, ocv;
    union {
        uint32_t u;
        float f;
    } bits;
#if ECMRT_VARIABLE_DT
    float cf, cs;
#else
    float df, ds;
#endif

    /* 0. saturate the inputs (NaN current counts as 0 A) */
    if (!(i >= -m->i_max_a)) {
        i = (i == i) ? -m->i_max_a : 0.0f;  /* below the range, or NaN */
    } else if (i > m->i_max_a) {
        i = m->i_max_a;
    }
#if ECMRT_VARIABLE_DT
    bits.f = dt;
    if (bits.u - 1u >= 0x46FFFE00u) {    /* not in (0, ECMRT_F32_DT_MAX] (= 0x46FFFE00) */
        dt = (dt > 0.0f) ? ECMRT_F32_DT_MAX : 0.0f;     /* +-0, negative and NaN: 0 */
    }
#endif
    /* 1. direction, with a deadband that keeps the last one */
    if (i > m->deadband_a) {
        s->charging = (uint8_t)ECMRT_CHARGE;
    } else if (i < -m->deadband_a) {
        s->charging = (uint8_t)ECMRT_DISCHARGE;
    }
    dir = s->charging;
    /* 2. SOC first (the parameters are looked up at the new SOC); Kahan-compensated sum,
     *    so a long run of equal small increments does not drift */
#if ECMRT_VARIABLE_DT
    y = (i * dt) * m->k_soc - s->soc_c;
#else
    y = i * m->k_soc - s->soc_c;
#endif
    soc = s->soc + y;
    s->soc_c = (soc - s->soc) - y;
    bits.f = soc;
    if ((bits.u & 0x7FFFFFFFu) > 0x40000000u) {     /* |soc| > 2 = ECMRT_F32_SOC_MAX, or NaN */
        if (soc < ECMRT_F32_SOC_MIN) {
            soc = ECMRT_F32_SOC_MIN;
            s->soc_c = 0.0f;
        } else if (soc > ECMRT_F32_SOC_MAX) {
            soc = ECMRT_F32_SOC_MAX;
            s->soc_c = 0.0f;
        }
    }
    s->soc = soc;
    /* 3. parameters of that direction, linear in SOC, clamped at the table ends */
    d = &m->dir[dir];
    w = ecmrt_f32_locate(&d->g, soc, &s->k_dir[dir]);
    row = d->rows + ECMRT_NPAR * (unsigned)s->k_dir[dir];
    r0 = ecmrt_f32_lerp(row + ECMRT_P_R0, w);
    rf = ecmrt_f32_lerp(row + ECMRT_P_RF, w);
    rs = ecmrt_f32_lerp(row + ECMRT_P_RS, w);
#if ECMRT_VARIABLE_DT
    cf = ecmrt_f32_one_minus_exp_neg(dt / ecmrt_f32_lerp(row + ECMRT_P_KF, w));
    cs = ecmrt_f32_one_minus_exp_neg(dt / ecmrt_f32_lerp(row + ECMRT_P_KS, w));
#else
    df = ecmrt_f32_lerp(row + ECMRT_P_KF, w);
    ds = ecmrt_f32_lerp(row + ECMRT_P_KS, w);
#endif
    w = ecmrt_f32_locate(&m->ocv_g, soc, &s->k_ocv);
    ocv = ecmrt_f32_lerp(m->ocv + 2u * (unsigned)s->k_ocv, w);
    /* 4. exact ZOH: u = a u + r (1 - a) i, written u + c (r i - u) with c = 1 - a = 1/D */
    uf = s->u_fast;
    us = s->u_slow;
#if ECMRT_VARIABLE_DT
    uf = uf + cf * (rf * i - uf);
    us = us + cs * (rs * i - us);
#else
    uf = uf + (rf * i - uf) / df;
    us = us + (rs * i - us) / ds;
#endif
    s->u_fast = uf;
    s->u_slow = us;
    /* 5. terminal voltage */
    return ((ocv + r0 * i) + uf) + us;
}

#endif /* ECMRT_F32_H */
