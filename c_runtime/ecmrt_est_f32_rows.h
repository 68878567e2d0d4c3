/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32_rows.h - ecmgen C runtime: the filter's model side, TinyEKF-style - the
 * linearisation of one step of the model (F's rows and Q per state, H, R and h(x)), one
 * static inline unit per state (soc, the RC pairs, u_diff, u_x, h, the offset), a no-op
 * macro where the model lacks the state (hand-written, model-independent).
 *
 * Included by ecmrt_est_f32.h (after the table accessor), never on its own; its generic
 * prediction and update call these. Mirrored by src/ecmgen/c/estref.py.
 */
#ifndef ECMRT_EST_F32_ROWS_H
#define ECMRT_EST_F32_ROWS_H

/* The linearisation of one step, TinyEKF-style: F = diag(a) + f e_soc^T (+ o e_offset^T)
 * (+ g e_u_diff^T), Q = diag(q), H = h; each state's rows are written by its own unit below
 * (a unit whose state the model lacks is a no-op), the prediction and the update are
 * generic. The rows share the step's tables at the new SOC (p, kept apart: the accessor
 * takes its address) and its factors. */
typedef struct {
    ecmrt_est_f32_vec_t a, f, q, h;
#if ECMRT_FX_CDR || ECMRT_FX_ARR
    float gc, fa;             /* current_dependent_resistance's g, temperature_dependence's f */
#endif
    float gf;                 /* the Butler-Volmer factor of r_fast (1 without) */
    float rg;                 /* r_fast gf */
    float ps;                 /* the RC noise's factor s^2 / (s^2 + P_soc) */
    float rd;                 /* r_diff (ECMRT_DIFF) */
#if ECMRT_EST_OFFSET
    float ds_di;              /* d soc' / d i = dt k_soc */
    ecmrt_est_f32_vec_t o;    /* d x' / d offset = -(d x' / d i) */
    float rb0, rbf;           /* r0, r_fast before the current's factors */
    float dg0, dgf;           /* d(i g)/di of those factors */
#endif
#if ECMRT_SURFACE
    ecmrt_est_f32_vec_t g;    /* d x' / d u_diff through the surface SOC, besides a_diff */
#endif
} ecmrt_est_f32_lin_t;

#if ECMRT_EST_OFFSET
#define ECMRT_EST_O(L, j, v) ((L)->o[j] = (v))
#else
#define ECMRT_EST_O(L, j, v) ((void)0)
#endif

/* the state vector from the model's state (and the offset) */
static inline void ecmrt_est_f32_state(const ECMRT_STATE *s, const float *ob, float *x)
{
    x[0] = s->soc;
    x[1] = s->u_fast;
    x[2] = s->u_slow;
#if ECMRT_DIFF
    x[3] = s->u_diff;
#endif
#if ECMRT_FX_XRC
    x[ECMRT_EST_IX] = s->u_x;
#endif
#if ECMRT_FX_HYST
    x[ECMRT_EST_IH] = s->h;
#endif
#if ECMRT_EST_OFFSET
    x[ECMRT_EST_IB] = *ob;
#endif
    (void)ob;
}

/* the branch table's row at the step's temperature (ECMRT_BV, ECMRT_DIFF) and its weight */
static inline const float *ecmrt_est_f32_branch(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                                unsigned dir, float *wt)
{
#if (ECMRT_BV || ECMRT_DIFF) && ECMRT_TEMP
    unsigned kt = s->k_t;
    *wt = s->w_t;
    if (kt > (unsigned)m->t.n - 2u) {
        kt = (unsigned)m->t.n - 2u;
    }
    return m->dir[dir].branch + 2u * ECMRT_NB * kt;
#elif ECMRT_BV || ECMRT_DIFF
    *wt = 0.0f;                     /* one row: no weight */
    (void)s;
    return m->dir[dir].branch;
#else
    *wt = 0.0f;
    (void)m;
    (void)s;
    (void)dir;
    return 0;
#endif
}

/* the tables at the SOC x0 and the step's factors at the current (as the step computes
 * them); with the offset state the resistances before them and d(i g)/di */
static inline void ecmrt_est_f32_factors(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                         unsigned dir, float soc, float ai, float temp,
                                         float dt, const float *br, float wt,
                                         ecmrt_est_f32_par_t *p, ecmrt_est_f32_lin_t *L)
{
    float x;
#if ECMRT_FX_CDR || ECMRT_FX_ARR
    L->gc = 1.0f;
    L->fa = 1.0f;
#endif
    L->gf = 1.0f;
    ecmrt_est_f32_params(m, s, dir, soc, p, 1);
#if ECMRT_FX_CDR
    x = ai * m->g_inv_i0;
    L->gc = m->g_scale * ecmrt_f32_asinh(&x);
    L->gc = L->gc / x;
#endif
#if ECMRT_FX_ARR
    L->fa = ecmrt_f32_arrhenius(m, temp);
#endif
#if ECMRT_EST_OFFSET
    L->rb0 = p->r0;
    L->rbf = p->rf;
#if ECMRT_FX_ARR
    L->rb0 = L->rb0 * L->fa;
    L->rbf = L->rbf * L->fa;
#endif
    L->dg0 = 1.0f;
#if ECMRT_FX_CDR
    L->dg0 = m->g_scale / ecmrt_f32_sqrt(x * x + 1.0f);  /* d(i g)/di = scale / sqrt(1 + x^2) */
#endif
    L->dgf = L->dg0;
    L->ds_di = dt * m->k_soc;        /* d x' / d offset = -(d x' / d i), d soc' / d i = dt k */
#endif
#if ECMRT_FX_CDR || ECMRT_FX_ARR
    ecmrt_est_f32_fx(p, L->gc, L->fa, 1);
#endif
#if ECMRT_BV
    x = ai / ecmrt_est_f32_tv(br, ECMRT_B_I0, wt);          /* the step's factor asinh(x)/x */
    L->gf = ecmrt_f32_asinh(&x);
    L->gf = L->gf / x;
#if ECMRT_EST_OFFSET && ECMRT_FX_CDR
    /* d(i gc gf)/di, the product rule as ecmgen.estimate.process.current_factors */
    L->dgf = (L->gc * (1.0f / ecmrt_f32_sqrt(x * x + 1.0f)) + L->gf * L->dg0) - L->gc * L->gf;
#elif ECMRT_EST_OFFSET
    L->dgf = 1.0f / ecmrt_f32_sqrt(x * x + 1.0f);
#endif
#endif
    (void)x;
    (void)ai;
    (void)temp;
    (void)dt;
    (void)br;
    (void)wt;
}

/* the rows of u_fast and u_slow: u' = a u + r g (1 - a) i, a = exp(-dt / tau(soc)), the SOC
 * column through da/dsoc and dr/dsoc; the RC noise (polarization_error), times ps */
static inline void ecmrt_est_f32_rows_rc(const ecmrt_est_f32_noise_t *nz, const ECMRT_STATE *s,
                                         unsigned dir, const ecmrt_est_f32_prior_t *pr, float i,
                                         float dt, const ecmrt_est_f32_par_t *p,
                                         ecmrt_est_f32_lin_t *L)
{
    float one_a, da, e;
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_F));
    L->a[1] = 1.0f - one_a;
    da = 0.0f;                                        /* tau of the temperature only */
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / p->tf);
    L->a[1] = 1.0f - one_a;
    da = ((L->a[1] * dt) / (p->tf * p->tf)) * p->dtf;
#endif
    L->f[1] = da * pr->u[1] + ((p->drf * one_a - p->rf * da) * L->gf) * i;
#if ECMRT_SURFACE
    L->g[1] = L->f[1] * p->du;                        /* by the tables' SOC, then chained */
    L->f[1] = L->f[1] * p->ds;
#endif
    ECMRT_EST_O(L, 1, -((L->rbf * one_a) * L->dgf) - L->f[1] * L->ds_di);
    L->rg = p->rf * L->gf;
    e = (nz->pol * L->rg) * i;
    L->q[1] = ((e * e) * (1.0f - L->a[1] * L->a[1])) * L->ps;
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_S));
    L->a[2] = 1.0f - one_a;
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / p->ts);
    L->a[2] = 1.0f - one_a;
    da = ((L->a[2] * dt) / (p->ts * p->ts)) * p->dts;
#endif
    L->f[2] = da * pr->u[2] + (p->drs * one_a - p->rs * da) * i;
#if ECMRT_SURFACE
    L->g[2] = L->f[2] * p->du;
    L->f[2] = L->f[2] * p->ds;
#endif
    ECMRT_EST_O(L, 2, -(p->rs * one_a) - L->f[2] * L->ds_di);
    e = (nz->pol * p->rs) * i;
    L->q[2] = ((e * e) * (1.0f - L->a[2] * L->a[2])) * L->ps;
    (void)s;
    (void)dir;
}

#if ECMRT_DIFF
/* the row of u_diff: r_diff and tau_diff depend on the temperature only (no SOC column) */
static inline void ecmrt_est_f32_row_diff(const ecmrt_est_f32_noise_t *nz, const ECMRT_STATE *s,
                                          unsigned dir, const float *br, float wt, float i,
                                          float dt, ecmrt_est_f32_lin_t *L)
{
    float one_a, e;
    L->rd = ecmrt_est_f32_tv(br, ECMRT_B_RD, wt);
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_D));
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / ecmrt_est_f32_tv(br, ECMRT_B_KD, wt));
#endif
    L->a[3] = 1.0f - one_a;
    ECMRT_EST_O(L, 3, -(L->rd * one_a));
    L->f[3] = 0.0f;
    e = (nz->pol * L->rd) * i;
    L->q[3] = ((e * e) * (1.0f - L->a[3] * L->a[3])) * L->ps;
    (void)s;
    (void)dir;
}
#else
#define ecmrt_est_f32_row_diff(nz, s, dir, br, wt, i, dt, L) ((void)0)
#endif

#if ECMRT_FX_XRC
/* the row of u_x (extra_rc): u_x' = a_x u_x + r_x (1 - a_x) i, no SOC column */
static inline void ecmrt_est_f32_row_xrc(const ecmrt_f32_model_t *m,
                                         const ecmrt_est_f32_noise_t *nz, float i, float dt,
                                         ecmrt_est_f32_lin_t *L)
{
    const float one_a = ecmrt_f32_one_minus_exp_neg(dt / m->x_k);
    float e;
    L->a[ECMRT_EST_IX] = 1.0f - one_a;
    ECMRT_EST_O(L, ECMRT_EST_IX, -(m->x_r * one_a));
    L->f[ECMRT_EST_IX] = 0.0f;
    e = (nz->pol * m->x_r) * i;
    L->q[ECMRT_EST_IX] = ((e * e) * (1.0f - L->a[ECMRT_EST_IX] * L->a[ECMRT_EST_IX])) * L->ps;
}
#else
#define ecmrt_est_f32_row_xrc(m, nz, i, dt, L) ((void)0)
#endif

#if ECMRT_FX_HYST
/* the row of h: h' = a_h h + (1 - a_h) s, a_h = exp(-|i| dt / (3600 decay_ah)); its noise
 * sigma_h^2 (1 - a_h^2), 1 - a_h^2 written c_h (2 - c_h); with the offset state
 * d h' / d i = -(h - s) sign(i) c a_h, c = dt / (3600 decay_ah) */
static inline void ecmrt_est_f32_row_hyst(const ecmrt_f32_model_t *m,
                                          const ecmrt_est_f32_noise_t *nz, unsigned dir,
                                          const ecmrt_est_f32_prior_t *pr, float i, float ai,
                                          float dt, ecmrt_est_f32_lin_t *L)
{
    const float ch = ecmrt_f32_one_minus_exp_neg((ai * dt) * m->h_k);
    L->a[ECMRT_EST_IH] = 1.0f - ch;
    L->f[ECMRT_EST_IH] = 0.0f;
    L->q[ECMRT_EST_IH] = nz->p0_h * (ch * (2.0f - ch));
    ECMRT_EST_O(L, ECMRT_EST_IH,
                (((pr->u[ECMRT_EST_IH] - (dir == ECMRT_CHARGE ? 1.0f : -1.0f)) *
                  (i > 0.0f ? 1.0f : (i < 0.0f ? -1.0f : 0.0f))) * (dt * m->h_k)) *
                L->a[ECMRT_EST_IH]);
    (void)dir;
    (void)pr;
    (void)i;
}
#else
#define ecmrt_est_f32_row_hyst(m, nz, dir, pr, i, ai, dt, L) ((void)0)
#endif

/* the row of the SOC: the sensor's bias over the drift horizon, (b k dt)^2 (horizon / dt)
 * written (b k)^2 (dt horizon) (no 0 * inf for a denormal dt), and white current noise;
 * with the offset state the offset is a state (its row: a random walk over the horizon)
 * instead; no noise at all for dt <= 0 */
static inline void ecmrt_est_f32_rows_soc(const ecmrt_f32_model_t *m,
                                          const ecmrt_est_f32_noise_t *nz, float ai, float dt,
                                          ecmrt_est_f32_lin_t *L)
{
    unsigned u;
    float b, e, r;
    L->a[0] = 1.0f;
    L->f[0] = 0.0f;
    L->q[0] = 0.0f;
    ECMRT_EST_O(L, 0, -L->ds_di);
#if ECMRT_EST_OFFSET
    L->o[ECMRT_EST_IB] = 0.0f;
    L->a[ECMRT_EST_IB] = 1.0f;
    L->f[ECMRT_EST_IB] = 0.0f;
#endif
    if (dt > 0.0f) {
#if ECMRT_EST_OFFSET
        b = nz->gain * ai;
        L->q[ECMRT_EST_IB] = (nz->p0_b * dt) / nz->horizon_s;
#else
        b = nz->gain * ai + nz->offset_a;
#endif
        e = b * m->k_soc;
        r = nz->noise_a * (dt * m->k_soc);
        L->q[0] = (e * e) * (dt * nz->horizon_s) + r * r;
    } else {
        for (u = 0u; u < ECMRT_EST_N; u++) {
            L->q[u] = 0.0f;
        }
    }
}

/* the first sample: the RC voltages are unknown (a record may start under load or
 * mid-relaxation), sigma r_j start_a with the resistances at the start */
static inline void ecmrt_est_f32_start_noise(const ecmrt_f32_model_t *m,
                                             const ecmrt_est_f32_noise_t *nz,
                                             const ecmrt_est_f32_par_t *p,
                                             ecmrt_est_f32_lin_t *L)
{
    float e = L->rg * nz->start_a;
    L->q[1] = L->q[1] + e * e;
    e = p->rs * nz->start_a;
    L->q[2] = L->q[2] + e * e;
#if ECMRT_DIFF
    e = L->rd * nz->start_a;
    L->q[3] = L->q[3] + e * e;
#endif
#if ECMRT_FX_XRC
    e = m->x_r * nz->start_a;
    L->q[ECMRT_EST_IX] = L->q[ECMRT_EST_IX] + e * e;
#endif
    (void)m;
}

/* H's SOC entry at the tables in p: the OCV's slope (with ECMRT_EST_SPREAD the secant
 * over the SOC's spread, P the predicted covariance) plus r0's, at the surface SOC; with the
 * offset state its entry d v / d offset = -r0 d(i g0)/di */
static inline void ecmrt_est_f32_h_soc(const ecmrt_f32_model_t *m,
                                       const ecmrt_est_f32_noise_t *nz, const ECMRT_STATE *s,
                                       unsigned dir, float soc, const float *P, float i,
                                       const ecmrt_est_f32_par_t *p, ecmrt_est_f32_lin_t *L)
{
#if ECMRT_EST_SPREAD
    const float dv = ecmrt_est_f32_ocv_slope(m, s, dir, soc, P[0], nz->ocv_k, p);
#else
    const float dv = p->docv;
#endif
#if ECMRT_SURFACE
    L->h[0] = dv + (p->dr0 * p->ds) * i;          /* r0 at the surface SOC */
#else
    L->h[0] = dv + p->dr0 * i;
#endif
#if ECMRT_EST_OFFSET
    L->h[ECMRT_EST_IB] = -(L->rb0 * L->dg0);
#endif
    (void)m;
    (void)nz;
    (void)s;
    (void)dir;
    (void)soc;
    (void)P;
}

/* the model's voltage at state x (h(x), for the relinearisation): as the step, with the
 * tables in p at x's SOC */
static inline float ecmrt_est_f32_voltage(const ecmrt_f32_model_t *m, unsigned dir,
                                          const ecmrt_est_f32_par_t *p, float i, const float *x)
{
    float v = ((p->ocv + p->r0 * i) + x[1]) + x[2];
    float vh = -0.0f, vx = -0.0f;       /* an effect that is off adds -0.0 (see the step) */
#if ECMRT_DIFF
    v = v + x[3];
#endif
#if ECMRT_FX_HYST
    vh = m->h_m * (x[ECMRT_EST_IH] - m->h_ref) +
         m->h_m0 * ((dir == ECMRT_CHARGE ? 1.0f : -1.0f) - m->h_ref);
#endif
#if ECMRT_FX_XRC
    vx = x[ECMRT_EST_IX];
#endif
    (void)m;
    (void)dir;
    return v + (vh + vx);
}

/* R: the model error of the overpotential |vp - ocv| (or, mem_k > 0, of the one held in
 * *eta from before, decayed by exp(-dt / error_memory_s), when that is larger; eta may be a
 * null pointer when mem_k is 0), the voltage noise, without the offset state the offset
 * through the resistances; over the error's correlation time; 0 for no measurement */
static inline float ecmrt_est_f32_r(const ecmrt_f32_model_t *m, const ecmrt_est_f32_noise_t *nz,
                                    const ecmrt_est_f32_par_t *p, const ecmrt_est_f32_lin_t *L,
                                    uint8_t *first, float *eta,
                                    float dt, float vp, float vm)
{
    float e = vp - p->ocv, r;
    e = e < 0.0f ? -e : e;
    if (nz->mem_k > 0.0f) {
        r = *eta - *eta * ecmrt_f32_one_minus_exp_neg(dt * nz->mem_k);
        if (r > e) {
            e = r;
        }
        *eta = e;
    }
    e = nz->model_error * e;
    r = nz->vn2 + e * e;
#if !ECMRT_EST_OFFSET
    /* the resistance a steady error in the current sees, r0 g0 + sum r_j g_j: the sensor's
     * offset through it joins the model's error in R (with the offset state it is a state) */
    e = p->r0 + L->rg;
    e = e + p->rs;
#if ECMRT_DIFF
    e = e + L->rd;
#endif
#if ECMRT_FX_XRC
    e = e + m->x_r;
#endif
    e = nz->offset_a * e;
    r = r + e * e;
#endif
    /* a record taken to start rested (start_a = 0, or first 2): its first sample counts fully */
    if (!(*first == 2u || (*first != 0u && nz->start_a == 0.0f)) && dt < nz->corr_s) {
        r = dt > 0.0f ? r * (nz->corr_s / dt) : 0.0f;
    }
    *first = 0u;
    if (!(vm >= -ECMRT_EST_V_MAX && vm <= ECMRT_EST_V_MAX)) {
        r = 0.0f;                                     /* no measurement (NaN, inf, absurd) */
    }
    (void)L;
    (void)m;
    return r;
}

#endif /* ECMRT_EST_F32_ROWS_H */
