/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_f32_step.h - ecmgen C runtime, numeric = "float": the model's step and its units,
 * one static inline function per stage and per effect, called by the step in a fixed order
 * (hand-written, model-independent).
 *
 * Included by ecmrt_f32.h (after its types, lookups and maths), never on its own. An effect
 * whose switch is 0 is a no-op macro here, so the step itself has no effect switches: adding
 * an effect is one unit below and one call in ecmrt_f32_step. Mirrored by
 * src/ecmgen/c/cref.py (simulate_f32) operation for operation.
 */
#ifndef ECMRT_F32_STEP_H
#define ECMRT_F32_STEP_H

/* The step's units, one per stage and effect, in the order the step calls them. An effect
 * that is off compiles to nothing: a parameter effect leaves its resistances as they are, a
 * voltage effect adds -0.0f (x + -0.0f is x for every x, so the compiler drops the add and
 * the sum keeps its bits). Each unit's reference: src/ecmgen/c/cref.py (float32) and
 * src/ecmgen/model/simulate.py, effects.py (float64), in the same order. */

/* 0. the current saturated to [-i_max_a, i_max_a] (NaN counts as 0 A) */
static inline float ecmrt_f32_clamp_current(const ecmrt_f32_model_t *m, float i)
{
    if (!(i >= -m->i_max_a)) {
        i = (i == i) ? -m->i_max_a : 0.0f;  /* below the range, or NaN */
    } else if (i > m->i_max_a) {
        i = m->i_max_a;
    }
    return i;
}

#if ECMRT_VARIABLE_DT
/* 0. dt saturated to [0, ECMRT_F32_DT_MAX]: +-0, negative and NaN count as 0 */
static inline float ecmrt_f32_clamp_dt(float dt)
{
    union {
        uint32_t u;
        float f;
    } bits;
    bits.f = dt;
    if (bits.u - 1u >= 0x46FFFE00u) {    /* not in (0, ECMRT_F32_DT_MAX] (= 0x46FFFE00) */
        dt = (dt > 0.0f) ? ECMRT_F32_DT_MAX : 0.0f;
    }
    return dt;
}
#define ECMRT_F32_Q(i, dt) ((i) * (dt))     /* the charge moved in the step, A s */
#else
#define ECMRT_F32_Q(i, dt) (i)              /* fixed dt: folded into k_soc */
#endif

/* 1. the direction, with a deadband that keeps the last one */
static inline unsigned ecmrt_f32_direction(const ecmrt_f32_model_t *m, unsigned dir, float i)
{
    if (i > m->deadband_a) {
        dir = ECMRT_CHARGE;
    } else if (i < -m->deadband_a) {
        dir = ECMRT_DISCHARGE;
    }
    return dir;
}

/* 2. the SOC after charge q (A s, or A with fixed dt): a Kahan-compensated sum, so that a
 *    long run of equal small increments does not drift; saturated to [SOC_MIN, SOC_MAX] */
static inline float ecmrt_f32_count(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float q)
{
    union {
        uint32_t u;
        float f;
    } bits;
    const float y = q * ECMRT_F32_K_SOC(m, s) - s->soc_c;
    float soc = s->soc + y;
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
    (void)m;
    return soc;
}

#if ECMRT_TEMP
/* 3. the temperature's row (*kt) and weight: kept with the temperature they belong to, so
 *    that a temperature read less often than the step runs is searched once (exact: both
 *    are a function of the temperature; a corrupted k_t is clamped where it is used) */
static inline float ecmrt_f32_temperature(const ecmrt_f32_model_t *m, ECMRT_STATE *s,
                                          float temp, unsigned *kt)
{
    union {
        uint32_t u;
        float f;
    } bits;
    float wt;
    bits.f = temp;
    if (bits.u == s->t_in) {
        wt = s->w_t;
    } else {
        wt = ecmrt_f32_locate(&m->t, temp, kt);
        s->t_in = bits.u;
        s->w_t = wt;
        ECMRT_CACHE_CLEAR(s);
#if ECMRT_TAU_T
        ecmrt_f32_coefs(m, s, *kt, wt);
#endif
    }
    return wt;
}
#endif

/* 3. the SOC the RC tables are read at: the surface SOC (ECMRT_SURFACE; *wo the OCV's
 *    weight at the mean SOC, located here for step 3''), else the SOC itself */
#if ECMRT_SURFACE && ECMRT_TEMP
static inline float ecmrt_f32_rc_soc(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                     float soc, unsigned kt, float wt, unsigned *ko, float *wo)
{
    const float *sp;
    float sa;
    *wo = ECMRT_F32_OCV_LOCATE(&m->ocv_g, soc, ko);
    sp = m->sv + 2u * ((unsigned)m->ocv_g.n * ECMRT_KT(m, kt) + *ko);  /* as ecmrt_f32_segment */
    sa = sp[0] + sp[1] * wt;
    return ecmrt_f32_surface(s, soc, sa + ((sp[2] + sp[3] * wt) - sa) * *wo);
}
#elif ECMRT_SURFACE
static inline float ecmrt_f32_rc_soc(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                     float soc, unsigned kt, float wt, unsigned *ko, float *wo)
{
    *wo = ECMRT_F32_OCV_LOCATE(&m->ocv_g, soc, ko);
    (void)kt;
    (void)wt;
    return ecmrt_f32_surface(s, soc, ecmrt_f32_lerp(m->sv + 2u * *ko, *wo));
}
#endif

/* 3'. parameter effects and the Butler-Volmer branch, in this order */
#if ECMRT_FX_CDR
/* current_dependent_resistance: r0, r_fast times scale asinh(x)/x, x = max(|i|/i0, 1e-12) */
static inline void ecmrt_f32_fx_cdr(const ecmrt_f32_model_t *m, float ai, float *r0, float *rf)
{
    float x = ai * m->g_inv_i0;
    float g = m->g_scale * ecmrt_f32_asinh(&x);
    g = g / x;
    *r0 = *r0 * g;
    *rf = *rf * g;
}
#else
#define ecmrt_f32_fx_cdr(m, ai, r0, rf) ((void)0)
#endif

#if ECMRT_FX_ARR
/* temperature_dependence: r0, r_fast, r_slow times the Arrhenius factor */
static inline void ecmrt_f32_fx_arr(const ecmrt_f32_model_t *m, float temp, float *r0,
                                    float *rf, float *rs)
{
    const float f = ecmrt_f32_arrhenius(m, temp);
    *r0 = *r0 * f;
    *rf = *rf * f;
    *rs = *rs * f;
}
#else
#define ecmrt_f32_fx_arr(m, temp, r0, rf, rs) ((void)0)
#endif

#if ECMRT_BV
/* the Butler-Volmer fast branch: r_fast asinh(x)/x, x = max(|i|/i0(T), 1e-12) */
static inline void ecmrt_f32_bv(const float *br, float wt, float ai, float *rf)
{
    float x = ai / ECMRT_F32_TV(br, ECMRT_B_I0, wt);
    const float g = ecmrt_f32_asinh(&x);
    *rf = *rf * (g / x);
    (void)wt;
}
#else
#define ecmrt_f32_bv(br, wt, ai, rf) ((void)0)
#endif

#if ECMRT_AGE
/* the cell's age (ecmrt_f32_age): every resistance times its scale */
static inline void ecmrt_f32_age_r(const ECMRT_STATE *s, float *r0, float *rf, float *rs)
{
    *r0 = *r0 * s->age_r;
    *rf = *rf * s->age_r;
    *rs = *rs * s->age_r;
}
#define ECMRT_F32_AGE_R(s, r) ((r) * (s)->age_r)
#else
#define ecmrt_f32_age_r(s, r0, rf, rs) ((void)0)
#define ECMRT_F32_AGE_R(s, r) (r)
#endif

/* 4. exact ZOH of one RC pair: u = a u + r (1 - a) i, written u + c (r i - u) with
 *    c = 1 - a (variable dt or ECMRT_TAU_T), or (r i - u) / D with D = 1/c (fixed dt) */
#if ECMRT_VARIABLE_DT || ECMRT_TAU_T
#define ECMRT_F32_ZOH(u, r, i, k) ((u) + (k) * ((r) * (i) - (u)))
#else
#define ECMRT_F32_ZOH(u, r, i, k) ((u) + ((r) * (i) - (u)) / (k))
#endif
/* the coefficient k of ECMRT_F32_ZOH: kc_j the state's 1/tau or c (ECMRT_TAU_T), p the
 * time constant (variable dt) or D in the rows */
#if ECMRT_TAU_T && ECMRT_VARIABLE_DT
#define ECMRT_F32_COEF(s, row, w, dir, dt, kc_j, p) \
    ecmrt_f32_one_minus_exp_neg((dt) * ECMRT_KC(s, dir, kc_j))
#elif ECMRT_TAU_T
#define ECMRT_F32_COEF(s, row, w, dir, dt, kc_j, p) ECMRT_KC(s, dir, kc_j)
#elif ECMRT_VARIABLE_DT
#define ECMRT_F32_COEF(s, row, w, dir, dt, kc_j, p) \
    ecmrt_f32_one_minus_exp_neg((dt) / ECMRT_F32_AT(s, row, p, w))
#else
#define ECMRT_F32_COEF(s, row, w, dir, dt, kc_j, p) ECMRT_F32_AT(s, row, p, w)
#endif

#if ECMRT_DIFF
/* 4, 5. the diffusion pair, as the others (its time constant from the branch table); its
 *    voltage */
static inline float ecmrt_f32_diffusion(ECMRT_STATE *s, unsigned dir, const float *br, float wt,
                                        float i, float dt)
{
    const float rd = ECMRT_F32_AGE_R(s, ECMRT_F32_TV(br, ECMRT_B_RD, wt));
    float ud = s->u_diff;
#if ECMRT_TAU_T
    ud = ECMRT_F32_ZOH(ud, rd, i, ECMRT_F32_COEF(s, br, wt, dir, dt, ECMRT_K_D, 0u));
#elif ECMRT_VARIABLE_DT
    ud = ECMRT_F32_ZOH(ud, rd, i, ecmrt_f32_one_minus_exp_neg(dt / ECMRT_F32_TV(br, ECMRT_B_KD, wt)));
#else
    ud = ECMRT_F32_ZOH(ud, rd, i, ECMRT_F32_TV(br, ECMRT_B_KD, wt));
#endif
    s->u_diff = ud;
    (void)dir;
    (void)wt;
    (void)dt;
    return ud;
}
#else
#define ecmrt_f32_diffusion(s, dir, br, wt, i, dt) (-0.0f)
#endif

/* 3''. the OCV at the mean SOC: the last parameter of the RC rows (ECMRT_OCV_SHARED), else
 *    its own table (located at soc unless ECMRT_SURFACE located it as wo) */
static inline float ecmrt_f32_ocv(const ecmrt_f32_model_t *m, ECMRT_STATE *s, const float *row,
                                  float w, float soc, float wo, unsigned kt, float wt,
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
    return ECMRT_F32_AT(s, row, ECMRT_P_OCV, w);
#else
#if ECMRT_SURFACE
    w = wo;
    (void)soc;
#else
    w = ECMRT_F32_OCV_LOCATE(&m->ocv_g, soc, ko);
    (void)wo;
#endif
    (void)row;
#if ECMRT_TEMP
    if (*ko != s->oc_key) {
        ecmrt_f32_segment(m->ocv + 2u * ((unsigned)m->ocv_g.n * ECMRT_KT(m, kt) + *ko), 2u, 2u, wt, s->oc);
        s->oc_key = (uint8_t)*ko;
    }
    return s->oc[0] + s->oc[1] * w;
#else
    (void)s;
    (void)kt;
    (void)wt;
    return ecmrt_f32_lerp(m->ocv + 2u * *ko, w);
#endif
#endif
}

/* 4', 5'. voltage effects: each updates its state and returns its term of the voltage */
#if ECMRT_FX_HYST
/* hysteresis: h moves towards the direction's sign with the charge moved */
static inline float ecmrt_f32_fx_hyst(const ecmrt_f32_model_t *m, ECMRT_STATE *s, unsigned dir,
                                      float ai, float dt)
{
    const float sg = dir == ECMRT_CHARGE ? 1.0f : -1.0f;
    const float ch = ecmrt_f32_one_minus_exp_neg(ECMRT_F32_Q(ai, dt) * m->h_k);
    float h = s->h;
    h = h + ch * (sg - h);
    s->h = h;
    (void)dt;
    return m->h_m * (h - m->h_ref) + m->h_m0 * (sg - m->h_ref);
}
#else
#define ecmrt_f32_fx_hyst(m, s, dir, ai, dt) (-0.0f)
#endif

#if ECMRT_FX_XRC
/* extra_rc: one more RC pair with constant r and tau */
static inline float ecmrt_f32_fx_xrc(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float i,
                                     float dt)
{
    float ux = s->u_x;
#if ECMRT_VARIABLE_DT
    ux = ux + ecmrt_f32_one_minus_exp_neg(dt / m->x_k) * (m->x_r * i - ux);
#else
    ux = ux + (m->x_r * i - ux) / m->x_k;
#endif
    s->u_x = ux;
    (void)dt;
    return ux;
}
#else
#define ecmrt_f32_fx_xrc(m, s, i, dt) (-0.0f)
#endif

/* One step of the discrete model (src/ecmgen/model/simulate.py and, for the effects,
 * model/effects.py): current i in A (positive = charge) held over the step, cell
 * temperature temp in degC; returns the terminal voltage in V. */
#if ECMRT_VARIABLE_DT
static inline float ecmrt_f32_step(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float i,
                                   float temp, float dt)
#else
static inline float ecmrt_f32_step(const ecmrt_f32_model_t *m, ECMRT_STATE *s, float i,
                                   float temp)
#endif
{
    const ecmrt_f32_dir_t *d;
    const float *row = 0;                   /* ECMRT_TEMP: the segment is cached in s->pc */
    const float *br = 0;                    /* the branch table's row (ECMRT_BRANCHES) */
    unsigned dir, kd, ko = ECMRT_HINT_OCV(s), kt = ECMRT_HINT_T(s);
    float soc, socr, ai, w, wo = 0.0f, wt = 0.0f, r0, rf, rs, kf, ks, uf, us, ocv, v, vh, ux;
#if !ECMRT_VARIABLE_DT
    const float dt = 0.0f;                  /* the build's dt is folded into the tables */
#endif

    /* 0. saturate the inputs; 1. direction; 2. SOC first (the parameters are looked up at
     *    the new SOC) */
    i = ecmrt_f32_clamp_current(m, i);
#if ECMRT_VARIABLE_DT
    dt = ecmrt_f32_clamp_dt(dt);
#endif
    ai = i < 0.0f ? -i : i;
    dir = ecmrt_f32_direction(m, s->charging, i);
    soc = ecmrt_f32_count(m, s, ECMRT_F32_Q(i, dt));
    /* 3. parameters of that direction, linear in SOC (and in temperature), clamped at the
     *    table ends; below the first temperature breakpoint or NaN: the first row */
    d = &m->dir[dir];
    kd = ECMRT_HINT_DIR(s, dir);
#if ECMRT_TEMP
    wt = ecmrt_f32_temperature(m, s, temp, &kt);
#endif
#if ECMRT_SURFACE
    socr = ecmrt_f32_rc_soc(m, s, soc, kt, wt, &ko, &wo);
#else
    socr = soc;
#endif
    w = ECMRT_F32_RC_LOCATE(&d->g, socr, &kd);
#if ECMRT_TEMP
    if (((kd << 1) | dir) != s->pc_key) {
        ecmrt_f32_segment(d->rows + ECMRT_NPAR * ((unsigned)d->g.n * ECMRT_KT(m, kt) + kd), ECMRT_NPAR,
                          ECMRT_NPAR, wt, s->pc);
        s->pc_key = (uint16_t)((kd << 1) | dir);
    }
#else
    row = d->rows + ECMRT_NPAR * kd;
#endif
#if ECMRT_BRANCHES && ECMRT_TEMP
    kt = ECMRT_KT(m, kt);
    br = d->branch + 2u * ECMRT_NB * kt;
#elif ECMRT_BRANCHES
    br = d->branch;
#endif
    r0 = ECMRT_F32_AT(s, row, ECMRT_P_R0, w);
    rf = ECMRT_F32_AT(s, row, ECMRT_P_RF, w);
    rs = ECMRT_F32_AT(s, row, ECMRT_P_RS, w);
    kf = ECMRT_F32_COEF(s, row, w, dir, dt, ECMRT_K_F, ECMRT_P_KF);
    ks = ECMRT_F32_COEF(s, row, w, dir, dt, ECMRT_K_S, ECMRT_P_KS);
    /* 3'. parameter effects, in this order */
    ecmrt_f32_fx_cdr(m, ai, &r0, &rf);
    ecmrt_f32_fx_arr(m, temp, &r0, &rf, &rs);
    ecmrt_f32_bv(br, wt, ai, &rf);
    ecmrt_f32_age_r(s, &r0, &rf, &rs);
    /* 3''. the OCV at the mean SOC */
    ocv = ecmrt_f32_ocv(m, s, row, w, soc, wo, kt, wt, &ko);
    /* 4. the two pairs; 5. the terminal voltage, then the diffusion pair's */
    uf = ECMRT_F32_ZOH(s->u_fast, rf, i, kf);
    us = ECMRT_F32_ZOH(s->u_slow, rs, i, ks);
    s->u_fast = uf;
    s->u_slow = us;
    v = ((ocv + r0 * i) + uf) + us;
    v = v + ecmrt_f32_diffusion(s, dir, br, wt, i, dt);
    /* 4', 5'. voltage effects, their terms summed first */
    vh = ecmrt_f32_fx_hyst(m, s, dir, ai, dt);
    ux = ecmrt_f32_fx_xrc(m, s, i, dt);
    v = v + (vh + ux);
    ecmrt_hints_store(s, dir, kd, ko, kt);   /* last (see ecmrt_f32_locate) */
    (void)row;
    (void)br;
    (void)wo;
    (void)ai;
    (void)wt;
    (void)temp;                             /* one temperature row: not looked up */
    (void)dt;
    return v;
}

#endif /* ECMRT_F32_STEP_H */
