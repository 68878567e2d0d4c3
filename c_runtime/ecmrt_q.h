/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_q.h - ecmgen C runtime, numeric = "fixed": int32 Q formats, int64 intermediates,
 * no floating point and no 64-bit division anywhere; the one step of every model, with
 * compile-time switches for what the model has.
 *
 * Included once by a generated <prefix>_ecm_q_config.h after it defines ECMRT_STATE, the
 * switches of ecmrt_config.h and the formats (value = raw / 2^Q)
 *     ECMRT_Q_I           current, A
 *     ECMRT_Q_V           voltages: OCV table, RC voltages, output
 *     ECMRT_Q_G           inverse SOC breakpoint spacings inv_dx (w = (soc - x[k]) inv_dx >> Q_G)
 *     ECMRT_Q_R0, ECMRT_Q_RF, ECMRT_Q_RS   resistance tables, ohm
 *     ECMRT_SH_DSOC       scale of the SOC increment: 2^SH_DSOC units = 1 LSB of Q30
 *     ECMRT_Q_T           time-constant tables (and tau_diff, tau_x), s    (variable dt)
 *     ECMRT_SH_RATE       shift of i * k_soc to the SOC rate               (variable dt)
 *     ECMRT_Q_DF, ECMRT_Q_DS   D = 1/(1 - exp(-dt/tau)) tables             (fixed dt)
 *     ECMRT_Q_CF, ECMRT_Q_CS   c = 1/D formed at run time                  (fixed dt)
 *   with ECMRT_TEMP:  ECMRT_Q_GT   inverse temperature breakpoint spacings (per Q8 degC)
 *   with ECMRT_RC_UNIFORM / ECMRT_OCV_UNIFORM: ECMRT_Q_GU / ECMRT_Q_GUO, the shift of
 *                     (soc - x0) inv_h to Q30 steps (0 when 1/spacing is an integer)
 *   with ECMRT_TAU_T at variable dt: ECMRT_Q_KR   1/tau kept in the state (kc), 1/s
 *   with ECMRT_DIFF:  ECMRT_Q_RD   r_diff; fixed dt: ECMRT_Q_DD, ECMRT_Q_CD (D and c of the pair)
 *   with ECMRT_BV:    ECMRT_Q_I0 (i0), ECMRT_BV_QX (x = |i|/i0), ECMRT_BV_K = Q_I0 - Q_I + BV_QX
 *   hysteresis:       ECMRT_FX_SH_HR (variable dt), ECMRT_FX_SH_HX, ECMRT_FX_SH_HM
 *   extra_rc:         ECMRT_FX_SH_XR
 *   current_dependent_resistance: ECMRT_FX_SH_GX, ECMRT_FX_CDR_QX, ECMRT_FX_CDR_QG
 *   temperature_dependence: ECMRT_FX_ARR_QB, ECMRT_FX_ARR_QF
 *   with ECMRT_AGE:   ECMRT_Q_GA (inverse spacings of the age grid, per Q8 equivalent full
 *                     cycle), ECMRT_Q_AR (resistance scale), ECMRT_Q_AQ (1 / capacity scale)
 *   with ECMRT_SURFACE: ECMRT_Q_SV, the table sv = lam /
 *                     max(dOCV/dSOC, 0.3 V) in Q_SV 1/V (chosen by the generator from its
 *                     largest value, lam / 0.3 V at most; Q_SV + Q_V - 30 >= 1)
 * Fixed by the runtime: SOC, breakpoints and interpolation weights Q30; dt Q16 (variable dt);
 * temperature Q8 degC (ECMRT_Q_TEMP); run-time c (variable dt) Q30.
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

#if ECMRT_VERSION != 3
#error "ecmrt_q.h does not match ecmrt.h"
#endif
#include "ecmrt_config.h"  /* the switches */
#if !defined(ECMRT_Q_I) || !defined(ECMRT_Q_V) || !defined(ECMRT_Q_G) || !defined(ECMRT_Q_R0) || \
    !defined(ECMRT_Q_RF) || !defined(ECMRT_Q_RS) || !defined(ECMRT_SH_DSOC)
#error "ecmrt_q.h needs the formats of a generated <prefix>_ecm_q_config.h"
#endif
#if ECMRT_SURFACE && !defined(ECMRT_Q_SV)
#error "ECMRT_SURFACE needs ECMRT_Q_SV"
#endif

#include "ecmrt_state.h"    /* the state at init, the hints */

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

#define ECMRT_BRANCHES (ECMRT_DIFF || ECMRT_BV)
/* values per temperature row of a direction's branch table: r_diff (Q_RD), k_diff (tau_diff
 * in Q_T or D in Q_DD), i0 (Q_I0) - those present, in this order */
#define ECMRT_NB (2u * (unsigned)ECMRT_DIFF + (unsigned)ECMRT_BV)
#define ECMRT_B_RD 0u
#define ECMRT_B_KD 1u
#define ECMRT_B_I0 (2u * (unsigned)ECMRT_DIFF)

typedef struct {
    const int32_t *x;        /* breakpoints: SOC Q30, temperature Q8 */
    const int32_t *inv_dx;   /* 2^(30 + Q_G) / (x[k+1] - x[k]), rounded */
    uint8_t n;
} ecmrt_q_grid_t;

/* A uniform SOC grid: n breakpoints x0 + k h (Q30), inv_h = 2^shift / h (ECMRT_Q_GU or
 * ECMRT_Q_GUO; h = 1/inv_h exactly when the shift is 0), um = (n - 1) 2^30. */
typedef struct {
    int64_t um;
    int32_t x0;
    int32_t inv_h;
    uint8_t n;
} ecmrt_q_ugrid_t;
#if ECMRT_RC_UNIFORM
#define ECMRT_Q_RC_GRID ecmrt_q_ugrid_t
#define ECMRT_Q_RC_LOCATE(g, v, kp) ecmrt_q_ulocate((g), (v), (kp), ECMRT_Q_GU)
#else
#define ECMRT_Q_RC_GRID ecmrt_q_grid_t
#define ECMRT_Q_RC_LOCATE(g, v, kp) ecmrt_q_locate((g), (v), (kp), ECMRT_Q_G)
#endif
#if ECMRT_OCV_UNIFORM
#define ECMRT_Q_OCV_GRID ecmrt_q_ugrid_t
#define ECMRT_Q_OCV_LOCATE(g, v, kp) ecmrt_q_ulocate((g), (v), (kp), ECMRT_Q_GUO)
#else
#define ECMRT_Q_OCV_GRID ecmrt_q_grid_t
#define ECMRT_Q_OCV_LOCATE(g, v, kp) ecmrt_q_locate((g), (v), (kp), ECMRT_Q_G)
#endif

/* Parameters of one direction, ECMRT_NPAR values per SOC breakpoint, breakpoint after
 * breakpoint, then temperature row after row (as in ecmrt_f32.h, plain values): r0 (Q_R0),
 * r_fast (Q_RF), k_fast, r_slow (Q_RS), k_slow, where k is tau in Q_T s (variable dt) or
 * D = 1/(1 - exp(-dt/tau)) in Q_DF / Q_DS (fixed dt); with ECMRT_TAU_T the k are not in the
 * rows but in the table tk (per temperature row k_fast, k_slow); with ECMRT_OCV_SHARED the
 * OCV (Q_V) is the last parameter. */
#if ECMRT_TAU_T
#define ECMRT_NPAR (3u + (unsigned)ECMRT_OCV_SHARED)
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 1u
#define ECMRT_P_RS 2u
#define ECMRT_P_OCV 3u
#else
#define ECMRT_NPAR (5u + (unsigned)ECMRT_OCV_SHARED)
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 1u
#define ECMRT_P_KF 2u
#define ECMRT_P_RS 3u
#define ECMRT_P_KS 4u
#define ECMRT_P_OCV 5u
#endif

typedef struct {
    ECMRT_Q_RC_GRID g;
    const int32_t *rows;
#if ECMRT_TAU_T
    const int32_t *tk;       /* [temperature row][k_fast, k_slow] */
#endif
#if ECMRT_BRANCHES
    const int32_t *branch;   /* [temperature row][ECMRT_NB] */
#endif
} ecmrt_q_dir_t;

typedef struct {
#if ECMRT_TEMP
    ecmrt_q_grid_t t;        /* temperature breakpoints (Q8 degC) of every table */
#endif
#if !ECMRT_OCV_SHARED
    ECMRT_Q_OCV_GRID ocv_g;
    const int32_t *ocv;      /* Q_V, temperature row after row */
#endif
#if ECMRT_SURFACE
    const int32_t *sv;       /* Q_SV 1/V (>= 0) at the OCV's breakpoints, laid out as ocv */
#endif
    ecmrt_q_dir_t dir[2];    /* [ECMRT_DISCHARGE], [ECMRT_CHARGE] */
    int32_t deadband;        /* Q_I, >= 0 */
    int32_t k_soc;           /* 1/(3600 Q) (variable dt) or dt/(3600 Q) (fixed dt), scaled */
#if ECMRT_BV
    const int32_t *bv_tab;   /* asinh(x)/x in Q30 at the nodes of ecmrt_q_gtab */
#endif
#if ECMRT_FX_HYST
    int32_t h_init;          /* hysteresis: initial_state, Q30 */
    int32_t h_k;             /* 1/(3600 decay_ah) per A*s (variable dt) or dt/(3600 decay_ah) per A */
    int32_t h_m;             /* m_v */
    int32_t h_m0;            /* m0_v */
    int32_t h_ref;           /* ocv_table_state, Q30 */
#endif
#if ECMRT_FX_XRC
    int32_t x_r;             /* extra_rc: r_ohm */
    int32_t x_k;             /* tau_s in Q_T (variable dt) or c_x = 1 - exp(-dt/tau_s) in Q30 (fixed dt) */
#endif
#if ECMRT_FX_CDR
    int32_t g_k;             /* current_dependent_resistance: 1/i0_a */
    const int32_t *g_tab;    /* scale asinh(x)/x in Q(CDR_QG) at the nodes of ecmrt_q_gtab */
#endif
#if ECMRT_FX_ARR
    int32_t a_b;             /* temperature_dependence: B = activation_k / 233.15 K, Q(ARR_QB) */
    int32_t a_fmax;          /* F = the factor at -40 degC, Q(ARR_QF) */
#endif
#if ECMRT_AGE
    ecmrt_q_grid_t age;      /* ageing law: equivalent full cycles, Q8 */
    const int32_t *age_scale; /* per breakpoint: resistance scale (Q_AR), 1 / capacity scale (Q_AQ) */
#endif
} ecmrt_q_model_t;

/* the hot helpers of the step: inlined even where the compiler would rather call them,
 * unless the build optimises for size (-Os) */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define ECMRT_Q_HOT static inline __attribute__((always_inline))
#else
#define ECMRT_Q_HOT static inline
#endif
/* helpers used at several places of the step: one copy when optimising for size */
#if defined(__GNUC__) && defined(__OPTIMIZE_SIZE__)
#define ECMRT_Q_SHARED static __attribute__((noinline, unused))
#else
#define ECMRT_Q_SHARED static inline
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

#if ECMRT_RC_UNIFORM || ECMRT_OCV_UNIFORM
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
#endif

/* y[0] + (y[stride] - y[0]) w (y = &table[k]); table values are >= 0, so the difference
 * fits int32 */
ECMRT_Q_SHARED int32_t ecmrt_q_lerp(const int32_t *y, unsigned stride, int32_t w)
{
    return y[0] + (int32_t)ECMRT_RSHR((int64_t)(y[stride] - y[0]) * w, ECMRT_Q30);
}

#if ECMRT_TEMP
#ifndef ECMRT_Q_GT
#error "a model over temperature needs ECMRT_Q_GT"
#endif
/* Bilinear, temperature first: the pairs of a segment at the temperature. y points at SOC
 * point k of temperature row kt of a table with npar values per SOC point and st per row;
 * for each of the np parameters, pc gets (a, b - a) with a, b the values at points k, k+1
 * linear in temperature at weight wt between the rows (values >= 0 and < 2^31: b - a fits).
 * The step then takes a + (b - a) w: pc is kept in the state with the segment, direction
 * and temperature it belongs to (the SOC moves little between steps). */
ECMRT_Q_SHARED void ecmrt_q_segment(const int32_t *y, unsigned npar, unsigned np, unsigned st, int32_t wt,
                            int32_t *pc)
{
    unsigned j;
    for (j = 0u; j < np; j++) {
        const int32_t a = ecmrt_q_lerp(y + j, st, wt);
        pc[2u * j] = a;
        pc[2u * j + 1u] = ecmrt_q_lerp(y + npar + j, st, wt) - a;
    }
}
#define ECMRT_Q_AT(s, p, j, w) ((s)->pc[2u * (j)] + (int32_t)ECMRT_RSHR((int64_t)(s)->pc[2u * (j) + 1u] * (w), ECMRT_Q30))
#define ECMRT_Q_TV(b, j, wt) ecmrt_q_lerp((b) + (j), ECMRT_NB, (wt))
#else
#define ECMRT_Q_AT(s, p, off, w) ecmrt_q_lerp((p) + (off), ECMRT_NPAR, (w))
#define ECMRT_Q_TV(b, j, wt) ((b)[j])
#endif


/* the format of the step's RC coefficients c_fast, c_slow: Q30 when computed at run time
 * (variable dt), Q_CF / Q_CS when they are 1/D (fixed dt) */
#if ECMRT_VARIABLE_DT
#define ECMRT_QC_F ECMRT_Q30
#define ECMRT_QC_S ECMRT_Q30
#else
#define ECMRT_QC_F ECMRT_Q_CF
#define ECMRT_QC_S ECMRT_Q_CS
#endif

/* the reciprocal and 1 - exp(-x) (ecmrt_q_clz32, ecmrt_q_recip, ecmrt_q_horner,
 * ecmrt_q_one_minus_exp_neg_small / _big / _q26) */
#include "ecmrt_q_exp.h"

#if ECMRT_VARIABLE_DT
#if !defined(ECMRT_Q_T) || !defined(ECMRT_SH_RATE)
#error "variable-dt fixed point needs ECMRT_Q_T and ECMRT_SH_RATE"
#endif
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

#if ECMRT_TAU_T
/* c = 1 - exp(-x) in Q30 for x = dt kc, dt >= 0 in Q16 s, kc = 1/tau in Q_KR (the state's
 * coefficient): x in Q30 by one multiply and a constant shift (16 + Q_KR - 30 >= 1) */
ECMRT_Q_HOT int32_t ecmrt_q_c_kr(int32_t dt, int32_t kc)
{
    const int64_t x = ECMRT_RSHR((int64_t)dt * kc, ECMRT_Q_KR - 14);
    if (x < ECMRT_XSMALL_Q30) {
        return ecmrt_q_one_minus_exp_neg_small(x);
    }
    return ecmrt_q_one_minus_exp_neg_big(ECMRT_RSHR(x, 4));
}
#endif

/* c = 1 - exp(-dt/tau) in Q30, dt >= 0 in Q16 s, tau in Q_T s (Q_T <= 21) at least 2^-16 s
 * (2^(Q_T - 16) raw, which the generator checks; interpolated taus are not smaller): x =
 * dt (1/tau) = dt r 2^-sh in Q30 with the shift sh - Q_T - 14 >= 1 */
ECMRT_Q_HOT int32_t ecmrt_q_c_dt_tau(int32_t dt, int32_t tau)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)tau, &sh);
    return ecmrt_q_c_rate(dt, r, sh - (unsigned)(ECMRT_Q_T + 14));
}
#else
#if !defined(ECMRT_Q_DF) || !defined(ECMRT_Q_DS) || !defined(ECMRT_Q_CF) || !defined(ECMRT_Q_CS)
#error "fixed-dt fixed point needs ECMRT_Q_DF, ECMRT_Q_DS, ECMRT_Q_CF and ECMRT_Q_CS"
#endif
/* c = 1/D in Q(qcd - Q_D'), D >= 1 in Q_D' (qcd = Q_C + Q_D' <= 30 + Q_D'): the shift
 * sh - qcd >= 1 because D >= 1 */
static inline int32_t ecmrt_q_inv_d(int32_t dd, unsigned qcd)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)dd, &sh);
    return (int32_t)ECMRT_RSHRV((int64_t)r, sh - qcd);
}
#endif

#if ECMRT_TAU_T
/* the value at the temperature of a per-row value b[0] (next row b[stride]) */
static inline int32_t ecmrt_q_tval(const int32_t *b, unsigned stride, int32_t wt)
{
#if ECMRT_TEMP
    return ecmrt_q_lerp(b, stride, wt);
#else
    (void)stride;
    (void)wt;
    return b[0];
#endif
}

#if ECMRT_VARIABLE_DT
#ifndef ECMRT_Q_KR
#error "ECMRT_TAU_T at variable dt needs ECMRT_Q_KR"
#endif
/* 1/tau in Q_KR (< 2^31: the generator picks Q_KR for the smallest tau of the tables) from
 * tau in Q_T: r 2^-sh = 1/tau_raw, so 1/tau 2^Q_KR = r 2^(Q_T + Q_KR - sh), rounded (the
 * shift of 2 r is >= 1) */
static inline int32_t ecmrt_q_rate(int32_t tau)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)tau, &sh);
    return (int32_t)ECMRT_RSHRV((int64_t)r << 1, sh + 1u - (unsigned)(ECMRT_Q_T + ECMRT_Q_KR));
}
#endif

/* The coefficients of the time constants at the temperature of row kt, weight wt, for both
 * directions (one set with ECMRT_TAU_SAME), into the state: 1/tau in Q_KR (variable dt: x =
 * dt/tau is then dt kc, one multiply) or c = 1/D in Q_C* (fixed dt). A function of the
 * temperature alone: the step recomputes them when the temperature changes, init at the
 * first row. */
#if defined(__GNUC__)
__attribute__((noinline))                   /* out of the step's hot path */
#endif
static void ecmrt_q_coefs(const ecmrt_q_model_t *m, ECMRT_STATE *s, unsigned kt, int32_t wt)
{
    unsigned d;
    for (d = 0u; d < ECMRT_KC_DIRS; d++) {
        const int32_t *tk = m->dir[d].tk + 2u * kt;
#if ECMRT_DIFF
        const int32_t *br = m->dir[d].branch + ECMRT_NB * kt;
#endif
#if ECMRT_VARIABLE_DT
        s->kc[d][ECMRT_K_F] = ecmrt_q_rate(ecmrt_q_tval(tk, 2u, wt));
        s->kc[d][ECMRT_K_S] = ecmrt_q_rate(ecmrt_q_tval(tk + 1u, 2u, wt));
#if ECMRT_DIFF
        s->kc[d][ECMRT_K_D] = ecmrt_q_rate(ecmrt_q_tval(br + ECMRT_B_KD, ECMRT_NB, wt));
#endif
#else
        s->kc[d][ECMRT_K_F] = ecmrt_q_inv_d(ecmrt_q_tval(tk, 2u, wt), ECMRT_Q_CF + ECMRT_Q_DF);
        s->kc[d][ECMRT_K_S] = ecmrt_q_inv_d(ecmrt_q_tval(tk + 1u, 2u, wt), ECMRT_Q_CS + ECMRT_Q_DS);
#if ECMRT_DIFF
        s->kc[d][ECMRT_K_D] = ecmrt_q_inv_d(ecmrt_q_tval(br + ECMRT_B_KD, ECMRT_NB, wt),
                                            ECMRT_Q_CD + ECMRT_Q_DD);
#endif
#endif
    }
}
#endif

#if ECMRT_FX_CDR || ECMRT_BV
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
#endif

#if ECMRT_FX_ARR
#if !defined(ECMRT_FX_ARR_QB) || !defined(ECMRT_FX_ARR_QF)
#error "temperature_dependence needs ECMRT_FX_ARR_QB and ECMRT_FX_ARR_QF"
#endif
#define ECMRT_ARR_TMIN (-40 * 256)
#define ECMRT_ARR_TMAX (85 * 256)
#define ECMRT_ARR_DLO 1193728          /* (-40 + 273.15) * 5120 */
/* f = exp(A (1/(T + 273.15) - 1/(t_ref + 273.15))) in Q(ARR_QF), T (Q8) saturated to
 * [-40, 85] degC: with d = (T + 273.15) 5120 = 20 T_q8 + 1398528 (exact) and d_lo that of
 * -40 degC, f = F exp(-x), x = B (d - d_lo) / d, B = A / 233.15 K, F = f(-40 degC) */
static inline int32_t ecmrt_q_arrhenius(const ecmrt_q_model_t *m, int32_t temp)
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
    return (int32_t)ECMRT_RSHR((int64_t)m->a_fmax * (ECMRT_ONE30 - ecmrt_q_one_minus_exp_neg_q26(
        ECMRT_RSHR((int64_t)m->a_b * z, ECMRT_FX_ARR_QB + 4))), ECMRT_Q30);
}
#endif

#if ECMRT_AGE
#if !defined(ECMRT_Q_GA) || !defined(ECMRT_Q_AR) || !defined(ECMRT_Q_AQ)
#error "ECMRT_AGE needs ECMRT_Q_GA, ECMRT_Q_AR and ECMRT_Q_AQ"
#endif
/* The cell's age, efc equivalent full cycles in Q8 (clamped to the law's breakpoints): the
 * resistance scale and k_soc times 1 / capacity scale (a table: no division), rounded half up
 * and saturated, kept in the state until the next call. The generator chose k_soc's format
 * for the largest 1 / capacity scale, so the saturation is a guard that never acts. */
static inline void ecmrt_q_age(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t efc)
{
    unsigned k = 0u;
    const int32_t w = ecmrt_q_locate(&m->age, efc, &k, ECMRT_Q_GA);
    const int32_t *a = m->age_scale + 2u * k;
    s->age_r = ecmrt_q_lerp(a, 2u, w);
    s->k_soc = ecmrt_q_sat32(ECMRT_RSHR((int64_t)m->k_soc * ecmrt_q_lerp(a + 1u, 2u, w), ECMRT_Q_AQ));
}
#define ECMRT_Q_K_SOC(m, s) ((s)->k_soc)
/* a product r i (Q_V, int64, < 2^31 by Q_V's choice) times the resistance scale */
#define ECMRT_Q_AGED(s, t) ECMRT_RSHR((t) * (s)->age_r, ECMRT_Q_AR)
#else
#define ECMRT_Q_K_SOC(m, s) ((m)->k_soc)
#define ECMRT_Q_AGED(s, t) (t)
#endif

/* soc0 in Q30 (1.0 = 1 << 30) */
static inline void ecmrt_q_init(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t soc0)
{
    s->soc_rem = 0;
    s->soc = soc0;
    ecmrt_state_init_common(s);
#if ECMRT_FX_HYST
    s->h = m->h_init;
#endif
#if ECMRT_TEMP
    s->t_in = INT32_MIN;                    /* below every table: k_t = 0, w_t = 0 */
    s->w_t = 0;
#endif
#if ECMRT_TAU_T
    ecmrt_q_coefs(m, s, 0u, 0);              /* those of k_t = 0, w_t = 0 */
#endif
#if ECMRT_AGE
    ecmrt_q_age(m, s, 0);                    /* fresh: both scales exactly 1 */
#endif
    (void)m;
}

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

#if ECMRT_SURFACE
/* The surface SOC (Q30) the RC tables are read at: soc + sv u_diff (u_diff of the previous
 * step, sv >= 0 in Q_SV at (soc, T), interpolated as the OCV). The product of two int32 is
 * formed in int64 (< 2^62), rounded half up to Q30 (shift Q_SV + Q_V - 30 >= 1, checked by
 * the generator), the sum with soc in int64, then saturated on purpose to [0, 2^30]. */
static inline int32_t ecmrt_q_surface(int32_t soc, int32_t sv, int32_t ud)
{
    const int64_t r = (int64_t)soc + ECMRT_RSHR((int64_t)sv * ud, ECMRT_Q_SV + ECMRT_Q_V - ECMRT_Q30);
    if (r < 0) {
        return 0;
    }
    return r > (int64_t)ECMRT_ONE30 ? ECMRT_ONE30 : (int32_t)r;
}
#endif

#include "ecmrt_q_step.h"  /* the step: its units, one per stage and effect */

#undef ECMRT_Q_AT
#undef ECMRT_Q_TV
#undef ECMRT_Q_K_SOC
#undef ECMRT_Q_AGED
#undef ECMRT_QC_F
#undef ECMRT_QC_S
#endif /* ECMRT_Q_H */
