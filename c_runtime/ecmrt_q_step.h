/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_q_step.h - ecmgen C runtime, numeric = "fixed": the model's step and its units, one
 * static inline function per stage and per effect, called by the step in a fixed order
 * (hand-written, model-independent).
 *
 * Included by ecmrt_q.h (after its formats, lookups and maths), never on its own. An effect
 * whose switch is 0 is a no-op macro here (a parameter effect leaves r i as it is, a voltage
 * effect adds 0), so the step itself has no effect switches: adding an effect is one unit
 * below and one call in ecmrt_q_step. Mirrored by src/ecmgen/c/cref.py (simulate_fixed_raw)
 * operation for operation; the same units as ecmrt_f32_step.h.
 */
#ifndef ECMRT_Q_STEP_H
#define ECMRT_Q_STEP_H

/* 1. the direction, with a deadband that keeps the last one */
static inline unsigned ecmrt_q_direction(const ecmrt_q_model_t *m, unsigned dir, int32_t i)
{
    if (i > m->deadband) {
        dir = ECMRT_CHARGE;
    } else if (i < -m->deadband) {
        dir = ECMRT_DISCHARGE;
    }
    return dir;
}

/* 2. SOC (Q30, saturated). The increment is formed at full precision (2^-SH_DSOC of an LSB)
 *    and the part below 1 LSB is carried in soc_rem: no rounding drift. */
static inline int32_t ecmrt_q_count(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t i,
                                    int32_t dt)
{
    int64_t acc, dsoc;
    int32_t soc;
#if ECMRT_VARIABLE_DT
    /* |i k_soc| < 2^31 after the shift: Q_RATE holds i_max k_soc */
    const int32_t rate = (int32_t)ECMRT_RSHR((int64_t)i * ECMRT_Q_K_SOC(m, s), ECMRT_SH_RATE);
    acc = s->soc_rem + (int64_t)rate * dt;
#else
    acc = s->soc_rem + (int64_t)i * ECMRT_Q_K_SOC(m, s);
    (void)dt;
#endif
    dsoc = acc >> ECMRT_SH_DSOC;                                     /* floor */
    s->soc_rem = acc & (((int64_t)1 << ECMRT_SH_DSOC) - 1);          /* in [0, 2^SH_DSOC) */
    soc = ecmrt_q_sat32((int64_t)s->soc + dsoc);
    s->soc = soc;
    (void)m;
    return soc;
}

#if ECMRT_TEMP
/* 3. the temperature's row (*kt) and weight, kept with the temperature (see
 *    ecmrt_f32_temperature; a corrupted k_t is clamped where it is used) */
static inline int32_t ecmrt_q_temperature(const ecmrt_q_model_t *m, ECMRT_STATE *s,
                                          int32_t temp, unsigned *kt)
{
    int32_t wt;
    if (temp == s->t_in) {
        wt = s->w_t;
    } else {
        wt = ecmrt_q_locate(&m->t, temp, kt, ECMRT_Q_GT);
        s->t_in = temp;
        s->w_t = wt;
        ECMRT_CACHE_CLEAR(s);
#if ECMRT_TAU_T
        ecmrt_q_coefs(m, s, *kt, wt);
#endif
    }
    return wt;
}
#endif

#if ECMRT_SURFACE
/* 3. the surface SOC the RC tables are read at: the OCV located first (*wo, *ko, for step
 *    3''); sv bilinear as the OCV (temperature first) */
static inline int32_t ecmrt_q_rc_soc(const ecmrt_q_model_t *m, const ECMRT_STATE *s,
                                     int32_t soc, unsigned kt, int32_t wt, unsigned *ko,
                                     int32_t *wo)
{
#if ECMRT_TEMP
    const int32_t *sp;
    int32_t sa;
    *wo = ECMRT_Q_OCV_LOCATE(&m->ocv_g, soc, ko);
    sp = m->sv + (unsigned)m->ocv_g.n * ECMRT_KT(m, kt) + *ko;
    sa = ecmrt_q_lerp(sp, (unsigned)m->ocv_g.n, wt);
    return ecmrt_q_surface(soc, sa + (int32_t)ECMRT_RSHR((int64_t)(ecmrt_q_lerp(sp + 1u,
        (unsigned)m->ocv_g.n, wt) - sa) * *wo, ECMRT_Q30), s->u_diff);
#else
    *wo = ECMRT_Q_OCV_LOCATE(&m->ocv_g, soc, ko);
    (void)kt;
    (void)wt;
    return ecmrt_q_surface(soc, ecmrt_q_lerp(m->sv + *ko, 1u, *wo), s->u_diff);
#endif
}
#endif

/* 3. the coefficient c of ECMRT_Q_RC for the pair with state coefficient kc_j (ECMRT_TAU_T)
 *    or table column p (the time constant at variable dt, D at fixed dt; c = 1/D in Q qcd) */
#if ECMRT_TAU_T && ECMRT_VARIABLE_DT
#define ECMRT_Q_COEF(s, row, w, dir, dt, kc_j, p, qcd) ecmrt_q_c_kr(dt, ECMRT_KC(s, dir, kc_j))
#elif ECMRT_TAU_T
#define ECMRT_Q_COEF(s, row, w, dir, dt, kc_j, p, qcd) ECMRT_KC(s, dir, kc_j)
#elif ECMRT_VARIABLE_DT
#define ECMRT_Q_COEF(s, row, w, dir, dt, kc_j, p, qcd) ecmrt_q_c_dt_tau(dt, ECMRT_Q_AT(s, row, p, w))
#else
#define ECMRT_Q_COEF(s, row, w, dir, dt, kc_j, p, qcd) ecmrt_q_inv_d(ECMRT_Q_AT(s, row, p, w), qcd)
#endif

/* 3'. parameter effects and the Butler-Volmer branch, each scaling r i (Q_V, int64) */
#if ECMRT_FX_CDR
/* current_dependent_resistance: r0 i, r_fast i times the g table at |i| / i0 */
static inline void ecmrt_q_fx_cdr(const ecmrt_q_model_t *m, int64_t ai, int64_t *t0, int64_t *tf)
{
    const int64_t g = ecmrt_q_gtab(m->g_tab, (uint32_t)ecmrt_q_sat32(ECMRT_RSHR(ai * m->g_k,
                                                                               ECMRT_FX_SH_GX)),
                                   ECMRT_FX_CDR_QX);
    *t0 = ECMRT_RSHR(*t0 * g, ECMRT_FX_CDR_QG);
    *tf = ECMRT_RSHR(*tf * g, ECMRT_FX_CDR_QG);
}
#else
#define ecmrt_q_fx_cdr(m, ai, t0, tf) ((void)0)
#endif

#if ECMRT_FX_ARR
/* temperature_dependence: r0 i, r_fast i, r_slow i times the Arrhenius factor */
static inline void ecmrt_q_fx_arr(const ecmrt_q_model_t *m, int32_t temp, int64_t *t0,
                                  int64_t *tf, int64_t *ts)
{
    const int64_t g = ecmrt_q_arrhenius(m, temp);
    *t0 = ECMRT_RSHR(*t0 * g, ECMRT_FX_ARR_QF);
    *tf = ECMRT_RSHR(*tf * g, ECMRT_FX_ARR_QF);
    *ts = ECMRT_RSHR(*ts * g, ECMRT_FX_ARR_QF);
}
#else
#define ecmrt_q_fx_arr(m, temp, t0, tf, ts) ((void)0)
#endif

#if ECMRT_BV
/* the Butler-Volmer fast branch: r_fast i times asinh(x)/x, x = |i| / i0(T) */
static inline void ecmrt_q_bv(const ecmrt_q_model_t *m, const int32_t *br, int32_t wt,
                              int64_t ai, int64_t *tf)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)ECMRT_Q_TV(br, ECMRT_B_I0, wt), &sh);
    const int64_t g = ecmrt_q_gtab(m->bv_tab, (uint32_t)ecmrt_q_sat32(ECMRT_RSHRV(ai * (int64_t)r,
                                                                               sh - ECMRT_BV_K)),
                                   ECMRT_BV_QX);
    *tf = ECMRT_RSHR(*tf * g, ECMRT_Q30);
    (void)wt;
}
#else
#define ecmrt_q_bv(m, br, wt, ai, tf) ((void)0)
#endif

#if ECMRT_AGE
/* the cell's age (ecmrt_q_age): every r i times its scale */
static inline void ecmrt_q_age_r(const ECMRT_STATE *s, int64_t *t0, int64_t *tf, int64_t *ts)
{
    *t0 = ECMRT_Q_AGED(s, *t0);
    *tf = ECMRT_Q_AGED(s, *tf);
    *ts = ECMRT_Q_AGED(s, *ts);
}
#else
#define ecmrt_q_age_r(s, t0, tf, ts) ((void)0)
#endif

/* 3''. the OCV at the mean SOC: the last parameter of the RC rows (ECMRT_OCV_SHARED), else
 *    its own table (located at soc unless ECMRT_SURFACE located it as wo) */
static inline int32_t ecmrt_q_ocv(const ecmrt_q_model_t *m, ECMRT_STATE *s, const int32_t *row,
                                  int32_t w, int32_t soc, int32_t wo, unsigned kt, int32_t wt,
                                  unsigned *ko)
{
#if ECMRT_OCV_SHARED
    (void)m;
    (void)s;
    (void)row;
    (void)soc;
    (void)wo;
    (void)kt;
    (void)wt;
    (void)ko;
    return ECMRT_Q_AT(s, row, ECMRT_P_OCV, w);
#else
#if ECMRT_SURFACE
    w = wo;
    (void)soc;
#else
    w = ECMRT_Q_OCV_LOCATE(&m->ocv_g, soc, ko);
    (void)wo;
#endif
    (void)row;
#if ECMRT_TEMP
    if (*ko != s->oc_key) {
        ecmrt_q_segment(m->ocv + (unsigned)m->ocv_g.n * ECMRT_KT(m, kt) + *ko, 1u, 1u,
                        (unsigned)m->ocv_g.n, wt, s->oc);
        s->oc_key = (uint8_t)*ko;
    }
    return s->oc[0] + (int32_t)ECMRT_RSHR((int64_t)s->oc[1] * w, ECMRT_Q30);
#else
    (void)s;
    (void)kt;
    (void)wt;
    return ecmrt_q_lerp(m->ocv + *ko, 1u, w);
#endif
#endif
}

#if ECMRT_DIFF
/* 4, 5. the diffusion pair, as the others (its time constant and r_diff from the branch
 *    table); its voltage */
static inline int32_t ecmrt_q_diffusion(ECMRT_STATE *s, unsigned dir, const int32_t *br,
                                        int32_t wt, int32_t i, int32_t dt)
{
    const int64_t td = ECMRT_Q_AGED(s, ECMRT_RSHR((int64_t)ECMRT_Q_TV(br, ECMRT_B_RD, wt) * i,
                                                  ECMRT_Q_RD + ECMRT_Q_I - ECMRT_Q_V));
    int32_t cd, ud;
#if ECMRT_VARIABLE_DT && ECMRT_TAU_T
    cd = ecmrt_q_c_kr(dt, ECMRT_KC(s, dir, ECMRT_K_D));
#elif ECMRT_VARIABLE_DT
    cd = ecmrt_q_c_dt_tau(dt, ECMRT_Q_TV(br, ECMRT_B_KD, wt));
#elif ECMRT_TAU_T
    cd = ECMRT_KC(s, dir, ECMRT_K_D);
#else
    cd = ecmrt_q_inv_d(ECMRT_Q_TV(br, ECMRT_B_KD, wt), ECMRT_Q_CD + ECMRT_Q_DD);
#endif
#if ECMRT_VARIABLE_DT
    ud = ECMRT_Q_RC(s->u_diff, cd, td, ECMRT_Q30);
#else
    ud = ECMRT_Q_RC(s->u_diff, cd, td, ECMRT_Q_CD);
#endif
    s->u_diff = ud;
    (void)dir;
    (void)wt;
    (void)dt;
    return ud;
}
#else
#define ecmrt_q_diffusion(s, dir, br, wt, i, dt) 0
#endif

/* 4', 5'. voltage effects: each updates its state and returns its term of the voltage */
#if ECMRT_FX_HYST
/* hysteresis: h moves towards the direction's sign with the charge moved */
static inline int64_t ecmrt_q_fx_hyst(const ecmrt_q_model_t *m, ECMRT_STATE *s, unsigned dir,
                                      int64_t ai, int32_t dt)
{
    const int32_t sg = dir == ECMRT_CHARGE ? ECMRT_ONE30 : -ECMRT_ONE30;
    int64_t x;
    int32_t h;
#if ECMRT_VARIABLE_DT
    x = ECMRT_RSHR((int64_t)ecmrt_q_sat32(ECMRT_RSHR(ai * m->h_k, ECMRT_FX_SH_HR)) * dt,
                   ECMRT_FX_SH_HX);
#else
    x = ECMRT_RSHR(ai * m->h_k, ECMRT_FX_SH_HX);
    (void)dt;
#endif
    h = ECMRT_Q_RC(s->h, ecmrt_q_one_minus_exp_neg_q26(x), (int64_t)sg, ECMRT_Q30);
    s->h = h;
    return ECMRT_RSHR((int64_t)m->h_m * ((int64_t)h - m->h_ref), ECMRT_FX_SH_HM) +
           ECMRT_RSHR((int64_t)m->h_m0 * ((int64_t)sg - m->h_ref), ECMRT_FX_SH_HM);
}
#else
#define ecmrt_q_fx_hyst(m, s, dir, ai, dt) 0
#endif

#if ECMRT_FX_XRC
/* extra_rc: one more RC pair with constant r and tau */
static inline int32_t ecmrt_q_fx_xrc(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t i,
                                     int32_t dt)
{
#if ECMRT_VARIABLE_DT
    const int32_t cx = ecmrt_q_c_dt_tau(dt, m->x_k);
#else
    const int32_t cx = m->x_k;
    (void)dt;
#endif
    const int32_t ux = ECMRT_Q_RC(s->u_x, cx, ECMRT_RSHR((int64_t)m->x_r * i, ECMRT_FX_SH_XR),
                                  ECMRT_Q30);
    s->u_x = ux;
    return ux;
}
#else
#define ecmrt_q_fx_xrc(m, s, i, dt) 0
#endif

/* One step: i in Q_I A, temp in Q8 degC, dt in Q16 s; returns the voltage in Q_V. */
#if ECMRT_VARIABLE_DT
static inline int32_t ecmrt_q_step(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t i,
                                   int32_t temp, int32_t dt)
#else
static inline int32_t ecmrt_q_step(const ecmrt_q_model_t *m, ECMRT_STATE *s, int32_t i,
                                   int32_t temp)
#endif
{
    const ecmrt_q_dir_t *d;
    const int32_t *row = 0;                 /* ECMRT_TEMP: the segment is cached in s->pc */
    const int32_t *br = 0;                  /* the branch table's row (ECMRT_BRANCHES) */
    const int64_t ai = i < 0 ? -(int64_t)i : (int64_t)i;
    unsigned dir, kd, ko = ECMRT_HINT_OCV(s), kt = ECMRT_HINT_T(s);
    int32_t soc, w, wo = 0, wt = 0, cf, cs, uf, us, ocv;
    int64_t v, t0, tf, ts;
#if !ECMRT_VARIABLE_DT
    const int32_t dt = 0;                   /* the build's dt is folded into the tables */
#endif

    /* 0. inputs: the current is saturated by its type (range in the header); 1. direction;
     * 2. SOC first (the parameters are looked up at the new SOC) */
#if ECMRT_VARIABLE_DT
    if (dt < 0) {
        dt = 0;
    }
#endif
    dir = ecmrt_q_direction(m, s->charging, i);
    soc = ecmrt_q_count(m, s, i, dt);
    /* 3. parameters at the new SOC (and temperature) */
    d = &m->dir[dir];
    kd = ECMRT_HINT_DIR(s, dir);
#if !ECMRT_SURFACE
    w = ECMRT_Q_RC_LOCATE(&d->g, soc, &kd);
#endif
#if ECMRT_TEMP
    wt = ecmrt_q_temperature(m, s, temp, &kt);
#endif
#if ECMRT_SURFACE
    w = ECMRT_Q_RC_LOCATE(&d->g, ecmrt_q_rc_soc(m, s, soc, kt, wt, &ko, &wo), &kd);
#endif
#if ECMRT_TEMP
    if (((kd << 1) | dir) != s->pc_key) {
        ecmrt_q_segment(d->rows + ECMRT_NPAR * ((unsigned)d->g.n * ECMRT_KT(m, kt) + kd), ECMRT_NPAR,
                        ECMRT_NPAR, ECMRT_NPAR * (unsigned)d->g.n, wt, s->pc);
        s->pc_key = (uint16_t)((kd << 1) | dir);
    }
#else
    row = d->rows + ECMRT_NPAR * kd;
#endif
#if ECMRT_BRANCHES && ECMRT_TEMP
    kt = ECMRT_KT(m, kt);
    br = d->branch + ECMRT_NB * kt;
#elif ECMRT_BRANCHES
    br = d->branch;
#endif
    cf = ECMRT_Q_COEF(s, row, w, dir, dt, ECMRT_K_F, ECMRT_P_KF, ECMRT_Q_CF + ECMRT_Q_DF);
    cs = ECMRT_Q_COEF(s, row, w, dir, dt, ECMRT_K_S, ECMRT_P_KS, ECMRT_Q_CS + ECMRT_Q_DS);
    /* r i in Q_V (int64) */
    t0 = ECMRT_RSHR((int64_t)ECMRT_Q_AT(s, row, ECMRT_P_R0, w) * i, ECMRT_Q_R0 + ECMRT_Q_I - ECMRT_Q_V);
    tf = ECMRT_RSHR((int64_t)ECMRT_Q_AT(s, row, ECMRT_P_RF, w) * i, ECMRT_Q_RF + ECMRT_Q_I - ECMRT_Q_V);
    ts = ECMRT_RSHR((int64_t)ECMRT_Q_AT(s, row, ECMRT_P_RS, w) * i, ECMRT_Q_RS + ECMRT_Q_I - ECMRT_Q_V);
    /* 3'. parameter effects, in this order */
    ecmrt_q_fx_cdr(m, ai, &t0, &tf);
    ecmrt_q_fx_arr(m, temp, &t0, &tf, &ts);
    ecmrt_q_bv(m, br, wt, ai, &tf);
    ecmrt_q_age_r(s, &t0, &tf, &ts);
    /* 4. u += c (r i - u) */
    uf = ECMRT_Q_RC(s->u_fast, cf, tf, ECMRT_QC_F);
    s->u_fast = uf;
    us = ECMRT_Q_RC(s->u_slow, cs, ts, ECMRT_QC_S);
    s->u_slow = us;
    /* 5. v = ocv + r0 i + u_fast + u_slow (+ u_diff), then the voltage effects' terms */
    ocv = ecmrt_q_ocv(m, s, row, w, soc, wo, kt, wt, &ko);
    v = (((int64_t)ocv + t0) + uf) + us;
    v = v + ecmrt_q_diffusion(s, dir, br, wt, i, dt);
    v = v + ecmrt_q_fx_hyst(m, s, dir, ai, dt);
    v = v + ecmrt_q_fx_xrc(m, s, i, dt);
    ecmrt_hints_store(s, dir, kd, ko, kt);   /* last (see ecmrt_f32_locate) */
    (void)row;
    (void)br;
    (void)wo;
    (void)wt;
    (void)ai;
    (void)temp;                             /* one temperature row: not looked up */
    (void)dt;
    return ecmrt_q_sat32(v);
}

#endif /* ECMRT_Q_STEP_H */
