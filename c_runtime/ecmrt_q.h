/*
 * ecmrt_q.h - ecmgen C runtime, numeric = "fixed": int32 Q formats, int64 intermediates,
 * no floating point anywhere.
 *
 * Included once by a generated <prefix>_ecm.c after it defines (value = raw / 2^Q):
 *     ECMRT_VARIABLE_DT   1: step(state, i, dt) with dt in Q16 s, 1 - exp(-dt/tau) computed
 *                            in integers at run time; 0: step(state, i), D = 1/(1 - exp(-dt/tau))
 *                            tables precomputed, c = 1/D by one integer division
 *     ECMRT_Q_I           current, A
 *     ECMRT_Q_V           voltages: OCV table, RC voltages, output
 *     ECMRT_Q_G           inverse breakpoint spacings inv_dx (w = (soc - x[k]) * inv_dx >> Q_G)
 *     ECMRT_Q_R0, ECMRT_Q_RF, ECMRT_Q_RS   resistance tables, ohm
 *     ECMRT_Q_T           time-constant tables, s                (variable dt)
 *     ECMRT_SH_RATE       shift of i * k_soc to the SOC rate      (variable dt)
 *     ECMRT_Q_DF, ECMRT_Q_DS   D = 1/(1 - exp(-dt/tau)) tables    (fixed dt)
 *     ECMRT_Q_CF, ECMRT_Q_CS   c = 1/D formed at run time           (fixed dt)
 *     ECMRT_SH_DSOC       scale of the SOC increment: 2^SH_DSOC units = 1 LSB of Q30
 * Fixed by the runtime: SOC, breakpoints and interpolation weights Q30; dt Q16 (variable dt);
 * run-time c Q30.
 *
 * Arithmetic: every product is formed in int64 from int32 operands whose ranges the code
 * generator has checked cannot overflow; results are rounded (half up, ECMRT_RSHR) and
 * saturated back to int32 (ecmrt_q_sat32). Right shifts of negative values are arithmetic
 * (implementation-defined in C99, true of GCC, Clang, IAR and Arm Compiler; checked below);
 * nothing left-shifts a negative value. src/ecmgen/cref.py mirrors every operation.
 */
#ifndef ECMRT_Q_H
#define ECMRT_Q_H

#ifndef ECMRT_NEED_Q_STATE
#define ECMRT_NEED_Q_STATE
#endif
#include "ecmrt.h"

#if ECMRT_VERSION != 1
#error "ecmrt_q.h does not match ecmrt.h"
#endif
#if !defined(ECMRT_VARIABLE_DT) || !defined(ECMRT_Q_I) || !defined(ECMRT_Q_V) || \
    !defined(ECMRT_Q_G) || !defined(ECMRT_Q_R0) || !defined(ECMRT_Q_RF) || !defined(ECMRT_Q_RS) || \
    !defined(ECMRT_SH_DSOC)
#error "ecmrt_q.h needs the ECMRT_* configuration macros of a generated <prefix>_ecm.c"
#endif

/* compile-time checks: arithmetic right shift, two's complement int64 */
typedef char ecmrt_q_check_asr[((((int32_t)-1) >> 1) == -1 && (((int64_t)-8) >> 2) == -2) ? 1 : -1];

#define ECMRT_Q30 30
#define ECMRT_ONE30 ((int32_t)1 << 30)
#define ECMRT_Q_D 16

/* x / 2^n rounded half up, n >= 1 a constant; x is int64 and |x| < 2^63 - 2^(n-1) */
#define ECMRT_RSHR(x, n) (((x) + ((int64_t)1 << ((n) - 1))) >> (n))

typedef struct {
    const int32_t *x;        /* Q30 breakpoints */
    const int32_t *inv_dx;   /* 2^(30+Q_G) / (x[k+1] - x[k]), rounded */
    uint8_t n;
} ecmrt_q_grid_t;

/* Parameters of one direction, ECMRT_NPAR values per breakpoint row after row (as in
 * ecmrt_f32.h): r0 (Q_R0), r_fast (Q_RF), k_fast, r_slow (Q_RS), k_slow, where k is tau in
 * Q_T s (variable dt) or D = 1/(1 - exp(-dt/tau)) in Q_DF / Q_DS (fixed dt). */
#define ECMRT_NPAR 5u
#define ECMRT_P_R0 0u
#define ECMRT_P_RF 1u
#define ECMRT_P_KF 2u
#define ECMRT_P_RS 3u
#define ECMRT_P_KS 4u

typedef struct {
    ecmrt_q_grid_t g;
    const int32_t *rows;
} ecmrt_q_dir_t;

typedef struct {
    ecmrt_q_grid_t ocv_g;
    const int32_t *ocv;      /* Q_V */
    ecmrt_q_dir_t dir[2];    /* [ECMRT_DISCHARGE], [ECMRT_CHARGE] */
    int32_t deadband;        /* Q_I, >= 0 */
    int32_t k_soc;           /* 1/(3600 Q) (variable dt) or dt/(3600 Q) (fixed dt), scaled */
} ecmrt_q_model_t;

static inline int32_t ecmrt_q_sat32(int64_t x)
{
    if (x > (int64_t)INT32_MAX) {
        return INT32_MAX;
    }
    if (x < (int64_t)INT32_MIN) {
        return INT32_MIN;
    }
    return (int32_t)x;
}

/* As ecmrt_f32_locate: segment in *hint, returns the weight w in Q30, 0 <= w <= 2^30. */
static inline int32_t ecmrt_q_locate(const ecmrt_q_grid_t *g, int32_t soc, uint8_t *hint)
{
    const int32_t *x = g->x;
    const unsigned last = (unsigned)g->n - 2u;
    unsigned k;
    int64_t w;
    if (soc <= x[0]) {
        *hint = 0u;
        return 0;
    }
    if (soc >= x[last + 1u]) {
        *hint = (uint8_t)last;
        return ECMRT_ONE30;
    }
    k = *hint;
    if (k > last) {
        k = last;
    }
    while (soc < x[k]) {
        k--;
    }
    while (soc >= x[k + 1u]) {
        k++;
    }
    *hint = (uint8_t)k;
    /* here x[k] <= soc < x[k+1] <= 2^30: the difference is in [0, 2^30) */
    w = ECMRT_RSHR((int64_t)(soc - x[k]) * g->inv_dx[k], ECMRT_Q_G);
    return w > (int64_t)ECMRT_ONE30 ? ECMRT_ONE30 : (int32_t)w;
}

/* y[0] + (y[stride] - y[0]) w (y = &table[k]); table values are >= 0, so the difference
 * fits int32 */
static inline int32_t ecmrt_q_lerp(const int32_t *y, unsigned stride, int32_t w)
{
    return y[0] + (int32_t)ECMRT_RSHR((int64_t)(y[stride] - y[0]) * w, ECMRT_Q30);
}

#if ECMRT_VARIABLE_DT
#if !defined(ECMRT_Q_T) || !defined(ECMRT_SH_RATE)
#error "variable-dt fixed point needs ECMRT_Q_T and ECMRT_SH_RATE"
#endif
#if (26 + ECMRT_Q_T - ECMRT_Q_D) < 0 || (26 + ECMRT_Q_T - ECMRT_Q_D) > 31
#error "ECMRT_Q_T out of range (code generator bug)"
#endif
/* x = dt/tau is formed in Q26; exp(-x) < 2^-31 for x >= 21.5 (c = 1 exactly in Q30) */
#define ECMRT_X_SCALE ((int64_t)1 << (26 + ECMRT_Q_T - ECMRT_Q_D))
#define ECMRT_XMAX_Q26 ((int64_t)1442840576)       /* 21.5 * 2^26 */
#define ECMRT_LOG2E_Q30 ((int64_t)1549082005)      /* log2(e) * 2^30 */
#define ECMRT_LN2_Q30 ((int64_t)744261118)         /* ln(2) * 2^30 */

/* c = 1 - exp(-dt/tau) in Q30, dt in Q16 s (>= 0), tau in Q_T s (> 0). */
static inline int32_t ecmrt_q_one_minus_exp_neg(int32_t dt, int32_t tau)
{
    /* 2^(-j/8) in Q30, j = 0..7 */
    static const int32_t exp2_tab[8] = {
        1073741824, 984625594, 902905651, 827968132,
        759250125, 696235434, 638450708, 585461881
    };
    /* (-1)^k / k! in Q30, k = 0..6 */
    static const int32_t poly[7] = {
        1073741824, -1073741824, 536870912, -178956971, 44739243, -8947849, 1491308
    };
    int64_t num, x, p;
    int32_t y, f, r, e;
    unsigned n, j;
    int idx;
    if (dt <= 0 || tau <= 0) {
        return 0;
    }
    num = (int64_t)dt * ECMRT_X_SCALE;                  /* < 2^62 */
    if (num >= (int64_t)tau * ECMRT_XMAX_Q26) {         /* x >= 21.5 */
        return ECMRT_ONE30;
    }
    x = (num + (int64_t)(tau >> 1)) / tau;              /* Q26, < 21.5 * 2^26 */
    /* exp(-x) = 2^-y, y = x log2(e) = n + j/8 + f'/2^26 */
    y = (int32_t)ECMRT_RSHR(x * ECMRT_LOG2E_Q30, ECMRT_Q30);   /* Q26, < 31.1 * 2^26 */
    n = (unsigned)y >> 26;
    j = ((unsigned)y >> 23) & 7u;
    f = y & 0x7FFFFF;
    r = (int32_t)ECMRT_RSHR((int64_t)f * ECMRT_LN2_Q30, 26);  /* f' ln2 in Q30, < 0.0867 */
    /* exp(-r), Taylor to r^6 in Horner form: error < 1e-11 */
    p = poly[6];
    for (idx = 5; idx >= 0; idx--) {
        p = poly[idx] + ECMRT_RSHR((int64_t)r * p, ECMRT_Q30);
    }
    e = (int32_t)ECMRT_RSHR((int64_t)exp2_tab[j] * p, ECMRT_Q30);   /* Q30, in (0.5, 1] */
    if (n > 0u) {
        e = (int32_t)(((uint32_t)e + (1u << (n - 1u))) >> n);
    }
    return ECMRT_ONE30 - e;
}
#endif

#if !ECMRT_VARIABLE_DT
#if !defined(ECMRT_Q_DF) || !defined(ECMRT_Q_DS) || !defined(ECMRT_Q_CF) || !defined(ECMRT_Q_CS)
#error "fixed-dt fixed point needs ECMRT_Q_DF, ECMRT_Q_DS, ECMRT_Q_CF and ECMRT_Q_CS"
#endif
/* c = one / D rounded, D > 0 (the tables hold D >= 1 scaled so that c < 2^30) */
static inline int32_t ecmrt_q_recip(int32_t dd, int64_t one)
{
    return (int32_t)((one + (int64_t)(dd >> 1)) / dd);
}
#endif

/* soc0 in Q30 (1.0 = 1 << 30) */
static inline void ecmrt_q_init(ecmrt_q_state_t *s, int32_t soc0)
{
    s->soc_rem = 0;
    s->soc = soc0;
    s->u_fast = 0;
    s->u_slow = 0;
    s->charging = (uint8_t)ECMRT_DISCHARGE;
    s->k_ocv = 0u;
    s->k_dir[0] = 0u;
    s->k_dir[1] = 0u;
}

/* u + c (t - u) with c in Q_c, saturated */
#define ECMRT_Q_RC(u, c, t, qc) ecmrt_q_sat32((int64_t)(u) + ECMRT_RSHR(((t) - (int64_t)(u)) * (c), (qc)))

/* One step of the discrete 2RC model: i in Q_I A, dt in Q16 s; returns the voltage in Q_V. */
#if ECMRT_VARIABLE_DT
static inline int32_t ecmrt_q_step(const ecmrt_q_model_t *m, ecmrt_q_state_t *s, int32_t i,
                                   int32_t dt)
#else
static inline int32_t ecmrt_q_step(const ecmrt_q_model_t *m, ecmrt_q_state_t *s, int32_t i)
#endif
{
    const ecmrt_q_dir_t *d;
    const int32_t *row;
    unsigned dir;
    int32_t soc, w, cf, cs, uf, us, ocv;
    int64_t acc, dsoc, v;

    /* 0. inputs: the current is saturated by its type (range in the header) */
#if ECMRT_VARIABLE_DT
    if (dt < 0) {
        dt = 0;
    }
#endif
    /* 1. direction */
    if (i > m->deadband) {
        s->charging = (uint8_t)ECMRT_CHARGE;
    } else if (i < -m->deadband) {
        s->charging = (uint8_t)ECMRT_DISCHARGE;
    }
    dir = s->charging;
    /* 2. SOC (Q30, saturated). The increment is formed at full precision (2^-SH_DSOC of
     *    an LSB) and the part below 1 LSB is carried in soc_rem: no rounding drift. */
#if ECMRT_VARIABLE_DT
    {
        const int32_t rate = ecmrt_q_sat32(ECMRT_RSHR((int64_t)i * m->k_soc, ECMRT_SH_RATE));
        acc = s->soc_rem + (int64_t)rate * dt;
    }
#else
    acc = s->soc_rem + (int64_t)i * m->k_soc;
#endif
    dsoc = acc >> ECMRT_SH_DSOC;                                     /* floor */
    s->soc_rem = acc & (((int64_t)1 << ECMRT_SH_DSOC) - 1);          /* in [0, 2^SH_DSOC) */
    soc = ecmrt_q_sat32((int64_t)s->soc + dsoc);
    s->soc = soc;
    /* 3. parameters at the new SOC */
    d = &m->dir[dir];
    w = ecmrt_q_locate(&d->g, soc, &s->k_dir[dir]);
    row = d->rows + ECMRT_NPAR * (unsigned)s->k_dir[dir];
#if ECMRT_VARIABLE_DT
    cf = ecmrt_q_one_minus_exp_neg(dt, ecmrt_q_lerp(row + ECMRT_P_KF, ECMRT_NPAR, w));
    cs = ecmrt_q_one_minus_exp_neg(dt, ecmrt_q_lerp(row + ECMRT_P_KS, ECMRT_NPAR, w));
#define ECMRT_QC_F ECMRT_Q30
#define ECMRT_QC_S ECMRT_Q30
#else
    cf = ecmrt_q_recip(ecmrt_q_lerp(row + ECMRT_P_KF, ECMRT_NPAR, w),
                       (int64_t)1 << (ECMRT_Q_CF + ECMRT_Q_DF));
    cs = ecmrt_q_recip(ecmrt_q_lerp(row + ECMRT_P_KS, ECMRT_NPAR, w),
                       (int64_t)1 << (ECMRT_Q_CS + ECMRT_Q_DS));
#define ECMRT_QC_F ECMRT_Q_CF
#define ECMRT_QC_S ECMRT_Q_CS
#endif
    /* 4. u += c (r i - u) */
    uf = ECMRT_Q_RC(s->u_fast, cf,
                    ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_RF, ECMRT_NPAR, w) * i,
                               ECMRT_Q_RF + ECMRT_Q_I - ECMRT_Q_V), ECMRT_QC_F);
    s->u_fast = uf;
    us = ECMRT_Q_RC(s->u_slow, cs,
                    ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_RS, ECMRT_NPAR, w) * i,
                               ECMRT_Q_RS + ECMRT_Q_I - ECMRT_Q_V), ECMRT_QC_S);
    s->u_slow = us;
#undef ECMRT_QC_F
#undef ECMRT_QC_S
    /* 5. v = ocv + r0 i + u_fast + u_slow */
    v = ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_R0, ECMRT_NPAR, w) * i, ECMRT_Q_R0 + ECMRT_Q_I - ECMRT_Q_V);
    w = ecmrt_q_locate(&m->ocv_g, soc, &s->k_ocv);
    ocv = ecmrt_q_lerp(m->ocv + s->k_ocv, 1u, w);
    v = (((int64_t)ocv + v) + uf) + us;
    return ecmrt_q_sat32(v);
}

#endif /* ECMRT_Q_H */
