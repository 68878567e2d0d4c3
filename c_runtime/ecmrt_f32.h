/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_f32.h - ecmgen C runtime, numeric = "float" (IEEE-754 binary32): the one step of
 * every model, with compile-time switches for what the model has.
 *
 * Included once by a generated <prefix>_ecm_f32_config.h after it defines ECMRT_STATE and
 * the switches of ecmrt_config.h (the one list, with what each means).
 * A plain model compiles to the 2RC step alone. All functions are static inline: no external
 * symbols, so several models link together.
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

#if ECMRT_VERSION != 3
#error "ecmrt_f32.h does not match ecmrt.h"
#endif
#include "ecmrt_config.h"  /* the switches */
#include "ecmrt_state.h"   /* the state at init, the hints */

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

#define ECMRT_BRANCHES (ECMRT_DIFF || ECMRT_BV)
/* values per temperature row of a direction's branch table: r_diff, k_diff (tau_diff or D),
 * i0 - those present, in this order, each a pair (y, y[next row] - y) */
#define ECMRT_NB (2u * (unsigned)ECMRT_DIFF + (unsigned)ECMRT_BV)
#define ECMRT_B_RD 0u
#define ECMRT_B_KD 2u
#define ECMRT_B_I0 (4u * (unsigned)ECMRT_DIFF)

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
#if ECMRT_RC_UNIFORM
#define ECMRT_F32_RC_GRID ecmrt_f32_ugrid_t
#define ECMRT_F32_RC_LOCATE ecmrt_f32_ulocate
#else
#define ECMRT_F32_RC_GRID ecmrt_f32_grid_t
#define ECMRT_F32_RC_LOCATE ecmrt_f32_locate
#endif
#if ECMRT_OCV_UNIFORM
#define ECMRT_F32_OCV_GRID ecmrt_f32_ugrid_t
#define ECMRT_F32_OCV_LOCATE ecmrt_f32_ulocate
#else
#define ECMRT_F32_OCV_GRID ecmrt_f32_grid_t
#define ECMRT_F32_OCV_LOCATE ecmrt_f32_locate
#endif

/* Parameters of one current direction: ECMRT_NPAR values per SOC breakpoint, breakpoint after
 * breakpoint, then (ECMRT_TEMP) temperature row after temperature row:
 * rows[ECMRT_NPAR * (n * row + k) + ECMRT_P_*], so that one base pointer serves every
 * interpolation. Each parameter is a pair (y[k], y[k+1] - y[k]): the value and the float32
 * difference to the next SOC breakpoint (the subtraction done once by the generator, in
 * float32, so the interpolation gives the same bits as subtracting at run time; 0 at the
 * last breakpoint): r0, r_fast, k_fast, r_slow, k_slow, where k is the time constant tau in
 * s (ECMRT_VARIABLE_DT = 1) or D = 1/(1 - exp(-dt/tau)) (ECMRT_VARIABLE_DT = 0). With
 * ECMRT_TAU_T the time constants are not in the rows but in the table tk (per temperature
 * row the pairs (k_fast, next row - k_fast), (k_slow, ...)). With ECMRT_OCV_SHARED the OCV
 * (on the same SOC grid) is the last parameter of every row, and the model has no OCV
 * table of its own. */
#if ECMRT_TAU_T
#define ECMRT_NPAR (6u + 2u * (unsigned)ECMRT_OCV_SHARED)
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 2u
#define ECMRT_P_RS 4u
#define ECMRT_P_OCV 6u
#else
#define ECMRT_NPAR (10u + 2u * (unsigned)ECMRT_OCV_SHARED)
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 2u
#define ECMRT_P_KF 4u
#define ECMRT_P_RS 6u
#define ECMRT_P_KS 8u
#define ECMRT_P_OCV 10u
#endif

typedef struct {
    ECMRT_F32_RC_GRID g;      /* SOC breakpoints of this direction */
    const float *rows;
#if ECMRT_TAU_T
    const float *tk;          /* [temperature row][k_fast pair, k_slow pair] */
#endif
#if ECMRT_BRANCHES
    const float *branch;      /* [temperature row][ECMRT_NB pairs] */
#endif
} ecmrt_f32_dir_t;

typedef struct {
#if ECMRT_TEMP
    ecmrt_f32_grid_t t;       /* temperature breakpoints, degC, of every table */
#endif
#if !ECMRT_OCV_SHARED
    ECMRT_F32_OCV_GRID ocv_g;
    const float *ocv;         /* pairs (ocv[k], ocv[k+1] - ocv[k]), temperature row after row */
#endif
#if ECMRT_SURFACE
    const float *sv;          /* 1/V at the OCV's breakpoints, laid out as ocv */
#endif
    ecmrt_f32_dir_t dir[2];   /* [ECMRT_DISCHARGE], [ECMRT_CHARGE] */
    float deadband_a;         /* |i| <= deadband keeps the last direction */
    float i_max_a;            /* current is saturated to [-i_max_a, i_max_a] */
    float k_soc;              /* 1/(3600 Q) per A*s (variable dt) or dt/(3600 Q) per A (fixed dt) */
#if ECMRT_FX_HYST
    float h_init;             /* hysteresis: initial_state */
    float h_k;                /* 1/(3600 decay_ah) per A*s (variable dt) or dt/(3600 decay_ah) per A */
    float h_m;                /* m_v, V */
    float h_m0;               /* m0_v, V */
    float h_ref;              /* ocv_table_state */
#endif
#if ECMRT_FX_XRC
    float x_r;                /* extra_rc: r_ohm */
    float x_k;                /* tau_s (variable dt) or D = 1/(1 - exp(-dt/tau_s)) (fixed dt) */
#endif
#if ECMRT_FX_CDR
    float g_scale;            /* current_dependent_resistance: scale_at_zero */
    float g_inv_i0;           /* 1 / i0_a */
#endif
#if ECMRT_FX_ARR
    float a_k;                /* temperature_dependence: activation_k, K */
    float a_inv_ref;          /* 1 / (t_ref_c + 273.15) */
#endif
#if ECMRT_AGE
    ecmrt_f32_grid_t age;     /* ageing law: equivalent full cycles */
    const float *age_scale;   /* per breakpoint the pairs (resistance scale, difference to the
                               * next), (1 / capacity scale, difference to the next) */
#endif
} ecmrt_f32_model_t;

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

#if ECMRT_RC_UNIFORM || ECMRT_OCV_UNIFORM
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
#endif

/* y[k] + (y[k+1] - y[k]) w from a pair (y[k], y[k+1] - y[k]) of a table */
static inline float ecmrt_f32_lerp(const float *yd, float w)
{
    return yd[0] + yd[1] * w;
}

#if defined(__GNUC__)
#define ECMRT_F32_COLD static __attribute__((noinline))     /* out of the step's hot path */
#else
#define ECMRT_F32_COLD static
#endif

#if ECMRT_TEMP
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
#define ECMRT_F32_AT(s, p, off, w) ((s)->pc[off] + (s)->pc[(off) + 1u] * (w))
#define ECMRT_F32_TV(b, j, wt) ((b)[j] + (b)[(j) + 1u] * (wt))
#else
#define ECMRT_F32_AT(s, p, off, w) ecmrt_f32_lerp((p) + (off), (w))
#define ECMRT_F32_TV(b, j, wt) ((b)[j])
#endif

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

#if ECMRT_FX_ARR
/* f = exp(a_k (1/(T + 273.15) - 1/(t_ref + 273.15))), T saturated to [-40, 85] degC (NaN:
 * -40); exp(y) as exp(-(-y)) for y <= 0, 1/exp(-y) for y > 0 */
static inline float ecmrt_f32_arrhenius(const ecmrt_f32_model_t *m, float temp)
{
    float y, q, s;
    if (!(temp >= ECMRT_F32_ARR_T_MIN)) {
        temp = ECMRT_F32_ARR_T_MIN;
    } else if (temp > ECMRT_F32_ARR_T_MAX) {
        temp = ECMRT_F32_ARR_T_MAX;
    }
    y = (1.0f / (temp + 273.149994f) - m->a_inv_ref) * m->a_k;
    if (y > 0.0f) {
        q = ecmrt_f32_exp_neg_parts(y, &s);
        return 1.0f / (s + s * q);
    }
    q = ecmrt_f32_exp_neg_parts(-y, &s);
    return s + s * q;
}
#endif

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

#if ECMRT_FX_CDR || ECMRT_BV
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
#endif

#if ECMRT_TAU_T
/* The coefficients of the time constants at the temperature of row kt, weight wt, for both
 * directions, into the state: 1/tau (variable dt: x = dt/tau is then dt * kc) or 1/D = c
 * (fixed dt). A function of the temperature alone: the step recomputes them when the
 * temperature changes, init at the first row. */
ECMRT_F32_COLD void ecmrt_f32_coefs(const ecmrt_f32_model_t *m, ECMRT_STATE *s, unsigned kt, float wt)
{
    unsigned d;
    for (d = 0u; d < ECMRT_KC_DIRS; d++) {
        const float *tk = m->dir[d].tk + 4u * kt;
#if ECMRT_DIFF
        const float *br = m->dir[d].branch + 2u * ECMRT_NB * kt;
#endif
        s->kc[d][ECMRT_K_F] = 1.0f / ECMRT_F32_TV(tk, 0u, wt);
        s->kc[d][ECMRT_K_S] = 1.0f / ECMRT_F32_TV(tk, 2u, wt);
#if ECMRT_DIFF
        s->kc[d][ECMRT_K_D] = 1.0f / ECMRT_F32_TV(br, ECMRT_B_KD, wt);
#endif
    }
    (void)wt;
}
#endif

#if ECMRT_SURFACE
/* The surface SOC the RC tables are read at: soc + sv u_diff (u_diff of the previous step,
 * sv = lam / max(dOCV/dSOC, 0.3 V) at (soc, T), interpolated as the OCV), clamped to [0, 1]
 * (NaN: 0). */
static inline float ecmrt_f32_surface(const ECMRT_STATE *s, float soc, float sv)
{
    float r = soc + sv * s->u_diff;
    if (!(r >= 0.0f)) {
        r = 0.0f;
    } else if (r > 1.0f) {
        r = 1.0f;
    }
    return r;
}
#endif

#if ECMRT_AGE
/* The cell's age, efc equivalent full cycles (clamped to the law's breakpoints; NaN: the
 * first): the resistance scale and the SOC's k_soc over the aged capacity, kept in the state
 * until the next call (the age changes over weeks; the step only multiplies). The table holds
 * 1 / capacity scale, so nothing divides. */
static inline void ecmrt_f32_age(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float efc)
{
    unsigned k = 0u;
    const float w = ecmrt_f32_locate(&m->age, efc, &k);
    const float *a = m->age_scale + 4u * k;
    s->age_r = ecmrt_f32_lerp(a, w);
    s->k_soc = m->k_soc * ecmrt_f32_lerp(a + 2u, w);
}
#define ECMRT_F32_K_SOC(m, s) ((s)->k_soc)
#else
#define ECMRT_F32_K_SOC(m, s) ((m)->k_soc)
#endif

static inline void ecmrt_f32_init(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float soc0)
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
    ecmrt_state_init_common(s);
#if ECMRT_FX_HYST
    s->h = m->h_init;
#endif
#if ECMRT_TEMP
    s->t_in = 0x7FC00000u;                  /* a NaN: its row and weight are k_t = 0, w_t = 0 */
    s->w_t = 0.0f;
#endif
#if ECMRT_TAU_T
    ecmrt_f32_coefs(m, s, 0u, 0.0f);         /* those of k_t = 0, w_t = 0 */
#endif
#if ECMRT_AGE
    ecmrt_f32_age(m, s, 0.0f);               /* fresh: both scales exactly 1 */
#endif
    (void)m;
}

#include "ecmrt_f32_step.h"  /* the step: its units, one per stage and effect */

#undef ECMRT_F32_AT
#undef ECMRT_F32_TV
#undef ECMRT_F32_K_SOC
#endif /* ECMRT_F32_H */
