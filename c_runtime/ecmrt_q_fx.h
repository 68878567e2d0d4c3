/*
 * ecmrt_q_fx.h - ecmgen C runtime, numeric = "fixed", for models that carry diagnose
 * effects (src/ecmgen/effects.py). Included by a generated <prefix>_ecm.c instead of
 * ecmrt_q.h (which it includes) after the ecmrt_q.h configuration macros and
 *     ECMRT_FX_HYST  1: hysteresis (state h, Q30)
 *     ECMRT_FX_XRC   1: extra_rc (state u_x, Q_V)
 *     ECMRT_FX_CDR   1: current_dependent_resistance (r0 i, r_fast i scaled by g(|i|))
 * and, per effect present (value = raw / 2^Q):
 *     ECMRT_FX_SH_HR  hysteresis, variable dt: rate = |i| h_k >> SH_HR (x per second)
 *     ECMRT_FX_SH_HX  hysteresis: x in Q26 = rate dt >> SH_HX (variable dt) or
 *                     |i| h_k >> SH_HX (fixed dt)
 *     ECMRT_FX_SH_HM  hysteresis: m (h - h_ref) >> SH_HM is in Q_V (h, h_ref, s in Q30)
 *     ECMRT_FX_SH_XR  extra_rc: r_x i >> SH_XR is in Q_V
 *     ECMRT_FX_SH_GX  current_dependent_resistance: x = |i| g_k >> SH_GX in Q(CDR_QX)
 *     ECMRT_FX_CDR_QX current_dependent_resistance: Q of x (x < 2^(31 - CDR_QX))
 *     ECMRT_FX_CDR_QG current_dependent_resistance: Q of g and of its table g_tab
 * (capacity_error needs no code: it is folded into k_soc by the generator.)
 *
 * Additions to ecmrt_q_step(), in this order (mirrored in ecmgen.cref.simulate_fixed_raw):
 *   3'. current_dependent_resistance: x = sat(rshr(|i| g_k, SH_GX)) in Q(CDR_QX);
 *       g = scale asinh(x)/x in Q(CDR_QG) by linear interpolation in g_tab (64 segments in
 *       [0, 1) and 64 in every binade [2^b, 2^(b+1)), weight in Q30 from the bits below the
 *       segment); r0 i and r_fast i (in Q_V, int64) become rshr(t g, CDR_QG)
 *   4'. hysteresis: s = +-2^30 (the model's direction); c_h = 1 - exp(-x) in Q30 with
 *       x = |i| dt / (3600 decay_ah) in Q26;  h = sat(h + rshr((s - h) c_h, 30));
 *       v_h = rshr(m (h - h_ref), SH_HM) + rshr(m0 (s - h_ref), SH_HM)
 *       extra_rc: u_x = sat(u_x + rshr((rshr(r_x i, SH_XR) - u_x) c_x, 30)) with
 *       c_x = 1 - exp(-dt/tau_x) in Q30 (run time, variable dt; a constant, fixed dt)
 *   5'. v = sat(base + v_h + u_x)   (in int64, each term only when its effect is present)
 */
#ifndef ECMRT_Q_FX_H
#define ECMRT_Q_FX_H

#include "ecmrt_q.h"
#include "ecmrt_fx.h"

#if ECMRT_FX_VERSION != 1
#error "ecmrt_q_fx.h does not match ecmrt_fx.h"
#endif
#if !defined(ECMRT_FX_HYST) || !defined(ECMRT_FX_XRC) || !defined(ECMRT_FX_CDR)
#error "define ECMRT_FX_HYST, ECMRT_FX_XRC and ECMRT_FX_CDR (0 or 1) before including ecmrt_q_fx.h"
#endif
#if ECMRT_FX_CDR && (!defined(ECMRT_FX_SH_GX) || !defined(ECMRT_FX_CDR_QX) || !defined(ECMRT_FX_CDR_QG))
#error "current_dependent_resistance needs ECMRT_FX_SH_GX, ECMRT_FX_CDR_QX and ECMRT_FX_CDR_QG"
#endif

typedef struct {
    ecmrt_q_model_t base;     /* k_soc already includes any capacity_error factor */
    int32_t h_init;           /* hysteresis: initial_state, Q30 */
    int32_t h_k;              /* 1/(3600 decay_ah) per A*s (variable dt) or dt/(3600 decay_ah) per A */
    int32_t h_m;              /* m_v */
    int32_t h_m0;             /* m0_v */
    int32_t h_ref;            /* ocv_table_state, Q30 */
    int32_t x_r;              /* extra_rc: r_ohm */
    int32_t x_k;              /* tau_s in Q_T (variable dt) or c_x = 1 - exp(-dt/tau_s) in Q30 (fixed dt) */
#if ECMRT_FX_CDR
    int32_t g_k;              /* current_dependent_resistance: 1/i0_a */
    const int32_t *g_tab;     /* scale asinh(x)/x in Q(CDR_QG) at the nodes (see cdr_factor) */
#endif
} ecmrt_q_fx_model_t;

#define ECMRT_FX_XMAX_Q26 ((int64_t)1442840576)       /* 21.5 * 2^26 */
#define ECMRT_FX_LOG2E_Q30 ((int64_t)1549082005)      /* log2(e) * 2^30 */
#define ECMRT_FX_LN2_Q30 ((int64_t)744261118)         /* ln(2) * 2^30 */

/* c = 1 - exp(-x) in Q30 for x in Q26 (x <= 0 gives 0, x >= 21.5 gives 1): the same
 * arithmetic as ecmrt_q_one_minus_exp_neg() after its division. */
static inline int32_t ecmrt_q_fx_one_minus_exp_neg_q26(int64_t x)
{
    static const int32_t exp2_tab[8] = {
        1073741824, 984625594, 902905651, 827968132,
        759250125, 696235434, 638450708, 585461881
    };
    static const int32_t poly[7] = {
        1073741824, -1073741824, 536870912, -178956971, 44739243, -8947849, 1491308
    };
    int64_t p;
    int32_t y, f, r, e;
    unsigned n, j;
    int idx;
    if (x <= 0) {
        return 0;
    }
    if (x >= ECMRT_FX_XMAX_Q26) {
        return ECMRT_ONE30;
    }
    y = (int32_t)ECMRT_RSHR(x * ECMRT_FX_LOG2E_Q30, ECMRT_Q30);
    n = (unsigned)y >> 26;
    j = ((unsigned)y >> 23) & 7u;
    f = y & 0x7FFFFF;
    r = (int32_t)ECMRT_RSHR((int64_t)f * ECMRT_FX_LN2_Q30, 26);
    p = poly[6];
    for (idx = 5; idx >= 0; idx--) {
        p = poly[idx] + ECMRT_RSHR((int64_t)r * p, ECMRT_Q30);
    }
    e = (int32_t)ECMRT_RSHR((int64_t)exp2_tab[j] * p, ECMRT_Q30);
    if (n > 0u) {
        e = (int32_t)(((uint32_t)e + (1u << (n - 1u))) >> n);
    }
    return ECMRT_ONE30 - e;
}

#if ECMRT_FX_CDR
#define ECMRT_FX_CDR_K 6u    /* 2^6 segments per binade */

/* g = scale asinh(x)/x in Q(CDR_QG), x = |i| / i0 (ai = |i| in Q_I, 0 <= ai <= 2^31).
 * Nodes: k / 64 for k = 0..63 (x < 1), then 2^b (1 + j / 64) for b = 0.., j = 0..63; the
 * generator sizes the table so that every int32 current lands inside it. */
static inline int32_t ecmrt_q_fx_cdr_factor(const ecmrt_q_fx_model_t *fm, int64_t ai)
{
    const uint32_t x = (uint32_t)ecmrt_q_sat32(ECMRT_RSHR(ai * fm->g_k, ECMRT_FX_SH_GX));
    unsigned s = (unsigned)ECMRT_FX_CDR_QX - ECMRT_FX_CDR_K;
    uint32_t idx = x >> s;
    if (idx >= (1u << ECMRT_FX_CDR_K)) {
        unsigned b = (unsigned)ECMRT_FX_CDR_QX;     /* 2^b <= x < 2^(b+1) */
        while (b < 30u && (x >> (b + 1u)) != 0u) {
            b++;
        }
        s = b - ECMRT_FX_CDR_K;
        idx = ((uint32_t)(b - (unsigned)ECMRT_FX_CDR_QX) << ECMRT_FX_CDR_K) + (x >> s);
    }
    return ecmrt_q_lerp(fm->g_tab + idx, 1u, (int32_t)((x & ((1u << s) - 1u)) << (30u - s)));
}
#define ECMRT_FX_G(t) ECMRT_RSHR((t) * gq, ECMRT_FX_CDR_QG)
#else
#define ECMRT_FX_G(t) (t)
#endif

/* soc0 in Q30 (1.0 = 1 << 30) */
static inline void ecmrt_q_fx_init(const ecmrt_q_fx_model_t *m, ecmrt_q_fx_state_t *s,
                                   int32_t soc0)
{
    s->soc_rem = 0;
    s->soc = soc0;
    s->u_fast = 0;
    s->u_slow = 0;
    s->charging = (uint8_t)ECMRT_DISCHARGE;
    s->k_ocv = 0u;
    s->k_dir[0] = 0u;
    s->k_dir[1] = 0u;
    s->h = m->h_init;
    s->u_x = 0;
}

/* One step with effects: ecmrt_q_step() plus the lines marked fx. */
#if ECMRT_VARIABLE_DT
static inline int32_t ecmrt_q_fx_step(const ecmrt_q_fx_model_t *fm, ecmrt_q_fx_state_t *s,
                                      int32_t i, int32_t dt)
#else
static inline int32_t ecmrt_q_fx_step(const ecmrt_q_fx_model_t *fm, ecmrt_q_fx_state_t *s,
                                      int32_t i)
#endif
{
    const ecmrt_q_model_t *m = &fm->base;
    const ecmrt_q_dir_t *d;
    const int32_t *row;
    unsigned dir;
    int32_t soc, w, cf, cs, uf, us, ocv;
    int64_t acc, dsoc, v;
#if ECMRT_FX_HYST
    int64_t ai, x, vh;
    int32_t sg, ch, h;
#endif
#if ECMRT_FX_XRC
    int32_t ux, cx;
#endif
#if ECMRT_FX_CDR
    int64_t gq;
#endif

#if ECMRT_VARIABLE_DT
    if (dt < 0) {
        dt = 0;
    }
#endif
    if (i > m->deadband) {
        s->charging = (uint8_t)ECMRT_CHARGE;
    } else if (i < -m->deadband) {
        s->charging = (uint8_t)ECMRT_DISCHARGE;
    }
    dir = s->charging;
#if ECMRT_FX_CDR
    gq = ecmrt_q_fx_cdr_factor(fm, i < 0 ? -(int64_t)i : (int64_t)i);   /* fx 3' */
#endif
#if ECMRT_VARIABLE_DT
    {
        const int32_t rate = ecmrt_q_sat32(ECMRT_RSHR((int64_t)i * m->k_soc, ECMRT_SH_RATE));
        acc = s->soc_rem + (int64_t)rate * dt;
    }
#else
    acc = s->soc_rem + (int64_t)i * m->k_soc;
#endif
    dsoc = acc >> ECMRT_SH_DSOC;
    s->soc_rem = acc & (((int64_t)1 << ECMRT_SH_DSOC) - 1);
    soc = ecmrt_q_sat32((int64_t)s->soc + dsoc);
    s->soc = soc;
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
    uf = ECMRT_Q_RC(s->u_fast, cf,
                    ECMRT_FX_G(ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_RF, ECMRT_NPAR, w) * i,
                                          ECMRT_Q_RF + ECMRT_Q_I - ECMRT_Q_V)), ECMRT_QC_F);
    s->u_fast = uf;
    us = ECMRT_Q_RC(s->u_slow, cs,
                    ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_RS, ECMRT_NPAR, w) * i,
                               ECMRT_Q_RS + ECMRT_Q_I - ECMRT_Q_V), ECMRT_QC_S);
    s->u_slow = us;
#undef ECMRT_QC_F
#undef ECMRT_QC_S
    v = ECMRT_FX_G(ECMRT_RSHR((int64_t)ecmrt_q_lerp(row + ECMRT_P_R0, ECMRT_NPAR, w) * i,
                              ECMRT_Q_R0 + ECMRT_Q_I - ECMRT_Q_V));
    w = ecmrt_q_locate(&m->ocv_g, soc, &s->k_ocv);
    ocv = ecmrt_q_lerp(m->ocv + s->k_ocv, 1u, w);
    v = (((int64_t)ocv + v) + uf) + us;
#if ECMRT_FX_HYST
    ai = i < 0 ? -(int64_t)i : (int64_t)i;                          /* fx 4' */
    sg = dir == ECMRT_CHARGE ? ECMRT_ONE30 : -ECMRT_ONE30;
#if ECMRT_VARIABLE_DT
    x = ECMRT_RSHR((int64_t)ecmrt_q_sat32(ECMRT_RSHR(ai * fm->h_k, ECMRT_FX_SH_HR)) * dt,
                   ECMRT_FX_SH_HX);
#else
    x = ECMRT_RSHR(ai * fm->h_k, ECMRT_FX_SH_HX);
#endif
    ch = ecmrt_q_fx_one_minus_exp_neg_q26(x);
    h = ECMRT_Q_RC(s->h, ch, (int64_t)sg, ECMRT_Q30);
    s->h = h;
    vh = ECMRT_RSHR((int64_t)fm->h_m * ((int64_t)h - fm->h_ref), ECMRT_FX_SH_HM) +
         ECMRT_RSHR((int64_t)fm->h_m0 * ((int64_t)sg - fm->h_ref), ECMRT_FX_SH_HM);
    v = v + vh;                                                     /* fx 5' */
#endif
#if ECMRT_FX_XRC
#if ECMRT_VARIABLE_DT
    cx = ecmrt_q_one_minus_exp_neg(dt, fm->x_k);                     /* fx 4' */
#else
    cx = fm->x_k;
#endif
    ux = ECMRT_Q_RC(s->u_x, cx, ECMRT_RSHR((int64_t)fm->x_r * i, ECMRT_FX_SH_XR), ECMRT_Q30);
    s->u_x = ux;
    v = v + ux;                                                     /* fx 5' */
#endif
    return ecmrt_q_sat32(v);
}

#endif /* ECMRT_Q_FX_H */
