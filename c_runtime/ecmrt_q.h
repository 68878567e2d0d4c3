/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_q.h - ecmgen C runtime, numeric = "fixed": int32 Q formats, int64 intermediates,
 * no floating point and no 64-bit division anywhere: the grids, the lookups and
 * interpolation, the reciprocal and exp (ecmrt_q_exp.h) and the step's units
 * (ecmrt_q_step.h).
 *
 * Included by a generated <prefix>_ecm_q_config.h, whose <prefix>_ecm_q.c writes the model's
 * step from these units (hand-written, model-independent: every function takes the tables,
 * constants and formats it reads as arguments, so this compiles as it is for every model).
 * The formats (value = raw / 2^Q) are the model's, chosen by the generator and defined in its
 * <prefix>_ecm_q.h (the table there says what each holds): Q_I current, Q_V voltages (OCV
 * table, RC voltages, output), Q_G inverse SOC breakpoint spacings (w = (soc - x[k]) inv_dx
 * >> Q_G), Q_R0 / Q_RF / Q_RS resistances, SH_DSOC the SOC increment's scale (2^SH_DSOC
 * units = 1 LSB of Q30), and those of what the model has (time constants Q_T or the D tables
 * Q_DF / Q_DS and c = 1/D in Q_CF / Q_CS, temperature spacings Q_GT, ...). Fixed by the
 * runtime: SOC, breakpoints and interpolation weights Q30; dt Q16 (variable dt); temperature
 * Q8 degC (ECMRT_Q_TEMP); run-time c (variable dt) Q30.
 *
 * Arithmetic: every product is formed in int64 from int32 operands whose ranges the code
 * generator has checked cannot overflow; results are rounded (half up, ECMRT_RSHR) and
 * saturated back to int32 (ecmrt_q_sat32). Right shifts of negative values are arithmetic
 * (implementation-defined in C99, true of GCC, Clang, IAR and Arm Compiler; checked below);
 * nothing left-shifts a negative value. Reciprocals (1/tau, 1/D, 1/i0, 1/T) come from a
 * 65-entry seed table and one Newton step (ecmrt_q_recip): no division at all.
 * src/ecmgen/c/cref.py mirrors every operation.
 */
#ifndef ECMRT_Q_H
#define ECMRT_Q_H

#include "ecmrt.h"

/* compile-time checks: arithmetic right shift, two's complement int64 */
typedef char ecmrt_q_check_asr[((((int32_t)-1) >> 1) == -1 && (((int64_t)-8) >> 2) == -2) ? 1 : -1];

#define ECMRT_Q30 30
#define ECMRT_ONE30 ((int32_t)1 << 30)
#define ECMRT_Q_D 16

/* x / 2^n rounded half up, n >= 1 a constant; x is int64 and |x| < 2^63 - 2^(n-1) */
#define ECMRT_RSHR(x, n) (((x) + ((int64_t)1 << ((n) - 1))) >> (n))
/* the same for a shift n >= 1 known at run time: ((x >> (n-1)) + 1) >> 1 is
 * (x + 2^(n-1)) >> n exactly, without forming 2^(n-1) */
#define ECMRT_RSHRV(x, n) ((((x) >> ((n) - 1u)) + 1) >> 1)

typedef struct {
    const int32_t *x;        /* breakpoints: SOC Q30, temperature Q8 */
    const int32_t *inv_dx;   /* 2^(30 + Q_G) / (x[k+1] - x[k]), rounded */
    uint8_t n;
} ecmrt_q_grid_t;

/* A uniform SOC grid: n breakpoints x0 + k h (Q30), inv_h = 2^shift / h (Q_GU or Q_GUO;
 * h = 1/inv_h exactly when the shift is 0), um = (n - 1) 2^30. */
typedef struct {
    int64_t um;
    int32_t x0;
    int32_t inv_h;
    uint8_t n;
} ecmrt_q_ugrid_t;

/* The tables (generated): per direction the parameters per SOC breakpoint, breakpoint after
 * breakpoint, then temperature row after row (as in ecmrt_f32.h, plain values); the generated
 * header says which, in which order and in which formats. */

/* the hot helpers of the step: inlined even where the compiler would rather call them,
 * unless the build optimises for size (-Os) */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define ECMRT_Q_HOT static inline __attribute__((always_inline))
#else
#define ECMRT_Q_HOT static inline
#endif
/* helpers used at several places of the step: one copy when optimising for size; and the
 * step's cold helpers, out of its hot path (no warning where a model does not call them) */
#if defined(__GNUC__) && defined(__OPTIMIZE_SIZE__)
#define ECMRT_Q_SHARED static __attribute__((noinline, unused))
#define ECMRT_Q_COLD static __attribute__((noinline, unused))
#elif defined(__GNUC__)
#define ECMRT_Q_SHARED static inline
#define ECMRT_Q_COLD static __attribute__((noinline, unused))
#else
#define ECMRT_Q_SHARED static inline
#define ECMRT_Q_COLD static inline
#endif

ECMRT_Q_SHARED int32_t ecmrt_q_sat32(int64_t x)
{
    if ((uint64_t)x + 0x80000000u > 0xFFFFFFFFu) {    /* outside [INT32_MIN, INT32_MAX] */
        return x < 0 ? INT32_MIN : INT32_MAX;
    }
    return (int32_t)x;
}

/* As ecmrt_f32_locate: segment in *kp (a local hint), returns the weight w in Q30,
 * 0 <= w <= 2^30; inv_dx scaled by 2^(30 + qg). */
static inline int32_t ecmrt_q_locate(const ecmrt_q_grid_t *g, int32_t v, unsigned *kp, int qg)
{
    const int32_t *x = g->x;
    const unsigned last = (unsigned)g->n - 2u;
    unsigned k = *kp;
    int64_t w;
    if (k > last) {
        k = last;                           /* a corrupted hint costs a longer walk only */
    }
    if (v < x[k]) {
        do {
            if (k == 0u) {
                *kp = 0u;                   /* v < x[0] */
                return 0;
            }
            k--;
        } while (v < x[k]);
    } else if (v >= x[k + 1u]) {
        do {
            if (k == last) {
                *kp = last;                 /* v >= x[n-1] */
                return ECMRT_ONE30;
            }
            k++;
        } while (v >= x[k + 1u]);
    }
    *kp = k;
    /* here x[k] <= v < x[k+1]: the difference is below the grid's span (< 2^31) */
    w = ECMRT_RSHR((int64_t)(v - x[k]) * g->inv_dx[k], qg);
    return w > (int64_t)ECMRT_ONE30 ? ECMRT_ONE30 : (int32_t)w;
}

/* As ecmrt_q_locate on a uniform grid, in O(1) and exact: u = (v - x0) / h in Q30 (the
 * product < 2^63: |v - x0| < 2^32, inv_h < 2^31), k = floor(u), w = the bits below; below
 * the grid k = 0, w = 0, at or above its end k = n - 2, w = 2^30. */
static inline int32_t ecmrt_q_ulocate(const ecmrt_q_ugrid_t *g, int32_t v, unsigned *kp, int gs)
{
    const int64_t u = (((int64_t)v - g->x0) * g->inv_h) >> gs;
    if ((uint64_t)u >= (uint64_t)g->um) {  /* outside [x0, x[n-1]): one compare on the way */
        if (u < 0) {
            *kp = 0u;
            return 0;
        }
        *kp = (unsigned)g->n - 2u;
        return ECMRT_ONE30;
    }
    *kp = (unsigned)(u >> ECMRT_Q30);
    return (int32_t)(u & (ECMRT_ONE30 - 1));
}

/* y[0] + (y[stride] - y[0]) w (y = &table[k]); table values are >= 0, so the difference
 * fits int32 */
ECMRT_Q_SHARED int32_t ecmrt_q_lerp(const int32_t *y, unsigned stride, int32_t w)
{
    return y[0] + (int32_t)ECMRT_RSHR((int64_t)(y[stride] - y[0]) * w, ECMRT_Q30);
}

/* Bilinear, temperature first: the pairs of a segment at the temperature. y points at SOC
 * point k of temperature row kt of a table with npar values per SOC point and st per row;
 * for each of the np parameters, pc gets (a, b - a) with a, b the values at points k, k+1
 * linear in temperature at weight wt between the rows (values >= 0 and < 2^31: b - a fits).
 * The step then takes a + (b - a) w (ECMRT_Q_PAIR): pc is kept in the state with the
 * segment, direction and temperature it belongs to (the SOC moves little between steps). */
ECMRT_Q_SHARED void ecmrt_q_segment(const int32_t *y, unsigned npar, unsigned np, unsigned st,
                                    int32_t wt, int32_t *pc)
{
    unsigned j;
    for (j = 0u; j < np; j++) {
        const int32_t a = ecmrt_q_lerp(y + j, st, wt);
        pc[2u * j] = a;
        pc[2u * j + 1u] = ecmrt_q_lerp(y + npar + j, st, wt) - a;
    }
}
/* a + (b - a) w from a pair (a, b - a) of ecmrt_q_segment */
#define ECMRT_Q_PAIR(pc, w) ((pc)[0] + (int32_t)ECMRT_RSHR((int64_t)(pc)[1] * (w), ECMRT_Q30))

/* The same for one parameter, inline, and the value at weight w along SOC: y points at SOC
 * point k of temperature row kt, st values per row */
static inline int32_t ecmrt_q_bilerp(const int32_t *y, unsigned st, int32_t wt, int32_t w)
{
    const int32_t a = ecmrt_q_lerp(y, st, wt);
    return a + (int32_t)ECMRT_RSHR((int64_t)(ecmrt_q_lerp(y + 1u, st, wt) - a) * w, ECMRT_Q30);
}

/* the reciprocal and 1 - exp(-x) (ecmrt_q_clz32, ecmrt_q_recip, ecmrt_q_horner,
 * ecmrt_q_one_minus_exp_neg_small / _big / _q26) */
#include "ecmrt_q_exp.h"

/* c = 1 - exp(-x) in Q30 for x = dt r 2^-sh (in Q30), dt >= 0 in Q16 s, r = ecmrt_q_recip
 * of tau (in Q_T s) and sh >= 1 its shift minus Q_T + 14: the polynomial below x = 1/4, the
 * range-reduced exp above; dt = 0 gives 0 */
ECMRT_Q_HOT int32_t ecmrt_q_c_rate(int32_t dt, uint32_t r, unsigned sh)
{
    const int64_t x = ECMRT_RSHRV((int64_t)dt * (int64_t)r, sh);     /* Q30 */
    if (x < ECMRT_XSMALL_Q30) {
        return ecmrt_q_one_minus_exp_neg_small(x);
    }
    return ecmrt_q_one_minus_exp_neg_big(ECMRT_RSHR(x, 4));
}

/* c = 1 - exp(-x) in Q30 for x = dt kc, dt >= 0 in Q16 s, kc = 1/tau in Q(q_kr) (the state's
 * coefficient): x in Q30 by one multiply and a constant shift (16 + q_kr - 30 >= 1) */
ECMRT_Q_HOT int32_t ecmrt_q_c_kr(int32_t dt, int32_t kc, int q_kr)
{
    const int64_t x = ECMRT_RSHR((int64_t)dt * kc, q_kr - 14);
    if (x < ECMRT_XSMALL_Q30) {
        return ecmrt_q_one_minus_exp_neg_small(x);
    }
    return ecmrt_q_one_minus_exp_neg_big(ECMRT_RSHR(x, 4));
}

/* c = 1 - exp(-dt/tau) in Q30, dt >= 0 in Q16 s, tau in Q(q_t) s (q_t <= 21) at least
 * 2^-16 s (2^(q_t - 16) raw, which the generator checks; interpolated taus are not smaller):
 * x = dt (1/tau) = dt r 2^-sh in Q30 with the shift sh - q_t - 14 >= 1 */
ECMRT_Q_HOT int32_t ecmrt_q_c_dt_tau(int32_t dt, int32_t tau, int q_t)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)tau, &sh);
    return ecmrt_q_c_rate(dt, r, sh - (unsigned)(q_t + 14));
}

/* c = 1/D in Q(qcd - Q_D'), D >= 1 in Q_D' (qcd = Q_C + Q_D' <= 30 + Q_D'): the shift
 * sh - qcd >= 1 because D >= 1 */
static inline int32_t ecmrt_q_inv_d(int32_t dd, unsigned qcd)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)dd, &sh);
    return (int32_t)ECMRT_RSHRV((int64_t)r, sh - qcd);
}

/* 1/tau in Q(q_kr) (< 2^31: the generator picks q_kr for the smallest tau of the tables)
 * from tau in Q(q_t): r 2^-sh = 1/tau_raw, so 1/tau 2^q_kr = r 2^(q_t + q_kr - sh), rounded
 * (the shift of 2 r is >= 1) */
ECMRT_Q_SHARED int32_t ecmrt_q_rate(int32_t tau, int q_t, int q_kr)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)tau, &sh);
    return (int32_t)ECMRT_RSHRV((int64_t)r << 1, sh + 1u - (unsigned)(q_t + q_kr));
}

#define ECMRT_G_K 6u    /* 2^6 segments in [0, 1) and per binade */

/* tab(x) by linear interpolation, 0 <= x < 2^31 in Q(qx), x < 2^(31 - qx) = 2^E: nodes
 * k/64 for k = 0..63 (x < 1), then 2^b (1 + j/64) for b = 0.., j = 0..63; the segment from
 * the bit length of x, the Q30 weight from the bits below it */
static inline int32_t ecmrt_q_gtab(const int32_t *tab, uint32_t x, unsigned qx)
{
    unsigned s = qx - ECMRT_G_K;
    uint32_t idx = x >> s;
    if (idx >= (1u << ECMRT_G_K)) {
        const unsigned b = 31u - ecmrt_q_clz32(x);     /* 2^b <= x < 2^(b+1), b >= qx */
        s = b - ECMRT_G_K;
        idx = ((uint32_t)(b - qx) << ECMRT_G_K) + (x >> s);
    }
    return ecmrt_q_lerp(tab + idx, 1u, (int32_t)((x & ((1u << s) - 1u)) << (30u - s)));
}

#define ECMRT_ARR_TMIN (-40 * 256)
#define ECMRT_ARR_TMAX (85 * 256)
#define ECMRT_ARR_DLO 1193728          /* (-40 + 273.15) * 5120 */
/* temperature_dependence's factor f = exp(A (1/(T + 273.15) - 1/(t_ref + 273.15))) in
 * Q(q_f), T (Q8) saturated to [-40, 85] degC: with d = (T + 273.15) 5120 = 20 T_q8 + 1398528
 * (exact) and d_lo that of -40 degC, f = F exp(-x), x = B (d - d_lo) / d, B = A / 233.15 K
 * (a_b in Q(q_b)), F = f(-40 degC) (a_fmax) */
static inline int32_t ecmrt_q_arrhenius(int32_t a_b, int32_t a_fmax, int32_t temp, int q_b)
{
    unsigned sh;
    uint32_t r;
    int32_t d, z;
    if (temp < ECMRT_ARR_TMIN) {
        temp = ECMRT_ARR_TMIN;
    } else if (temp > ECMRT_ARR_TMAX) {
        temp = ECMRT_ARR_TMAX;
    }
    d = 20 * temp + 1398528;
    r = ecmrt_q_recip((uint32_t)d, &sh);
    z = (int32_t)ECMRT_RSHRV((int64_t)(d - ECMRT_ARR_DLO) * (int64_t)r, sh - 30u);  /* Q30 */
    return (int32_t)ECMRT_RSHR((int64_t)a_fmax * (ECMRT_ONE30 - ecmrt_q_one_minus_exp_neg_q26(
        ECMRT_RSHR((int64_t)a_b * z, q_b + 4))), ECMRT_Q30);
}

/* The cell's age, efc equivalent full cycles in Q8 (clamped to the law's breakpoints g, whose
 * spacings are in Q(q_ga)): the resistance scale (*age_r, Q_AR) and k_soc times 1 / capacity
 * scale (*k_aged; the table holds 1 / capacity scale in Q(q_aq): no division), rounded half
 * up and saturated, kept in the state until the next call. The generator chose k_soc's
 * format for the largest 1 / capacity scale, so the saturation is a guard that never acts. */
static inline void ecmrt_q_age(const ecmrt_q_grid_t *g, const int32_t *scale, int32_t k_soc,
                               int32_t efc, int q_ga, int q_aq, int32_t *age_r, int32_t *k_aged)
{
    unsigned k = 0u;
    const int32_t w = ecmrt_q_locate(g, efc, &k, q_ga);
    const int32_t *a = scale + 2u * k;
    *age_r = ecmrt_q_lerp(a, 2u, w);
    *k_aged = ecmrt_q_sat32(ECMRT_RSHR((int64_t)k_soc * ecmrt_q_lerp(a + 1u, 2u, w), q_aq));
}
/* a product r i (Q_V, int64, < 2^31 by Q_V's choice) times the resistance scale age_r in
 * Q(q_ar) */
#define ECMRT_Q_AGED(t, age_r, q_ar) ECMRT_RSHR((t) * (age_r), (q_ar))

/* u + c (t - u) with c in [0, 2^qc] in Q(qc): the rounded step lies between 0 and t - u, so
 * the result lies between u and t, and t (r i, in Q_V) is within the int32 range by the
 * choice of Q_V (it holds i_max times every resistance with its largest factor): no
 * saturation is needed */
ECMRT_Q_SHARED int32_t ecmrt_q_rc(int32_t u, int32_t c, int64_t t, unsigned qc)
{
    return (int32_t)((int64_t)u + ECMRT_RSHRV((t - (int64_t)u) * c, qc));
}
#if defined(__OPTIMIZE_SIZE__)
#define ECMRT_Q_RC(u, c, t, qc) ecmrt_q_rc((u), (c), (t), (unsigned)(qc))
#else
/* inline, the same bits with the constant shift's rounding (one operation less) */
#define ECMRT_Q_RC(u, c, t, qc) ((int32_t)((int64_t)(u) + ECMRT_RSHR(((t) - (int64_t)(u)) * (c), (qc))))
#endif

#include "ecmrt_q_step.h"  /* the step's units, one per stage and effect */

#endif /* ECMRT_Q_H */
