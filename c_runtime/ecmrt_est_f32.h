/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32.h - ecmgen C runtime: the extended Kalman filter (SOC estimator) on the
 * model's own float32 step (hand-written, model-independent).
 *
 * Included by a generated <prefix>_ecm.c built with `[c] estimator = "ekf"`, after
 * ecmrt_f32.h (whose configuration it reuses), with ECMRT_EST_T defined as the estimator's
 * state type (<prefix>_est_t of <prefix>_est.h: the model's state `m`, the covariance
 * `p[ECMRT_EST_N * ECMRT_EST_N]` and `first`). The generated <prefix>_est_step() calls
 *     ecmrt_est_f32_prior()   sanitise i and dt as the step does, keep the RC voltages;
 *     <prefix>_step()         the model's own step: the predicted state and voltage;
 *     ecmrt_est_f32_update()  Jacobians, covariance prediction, measurement update.
 * The filter is the one of src/ecmgen/estimate/ekf.py (states soc, u_fast, u_slow and,
 * in this order, u_diff with ECMRT_DIFF, u_x with ECMRT_FX_XRC, h with ECMRT_FX_HYST),
 * operation for operation mirrored in float32 by src/ecmgen/c/estref.py (bit-identical
 * results, checked through cffi and under QEMU):
 *
 *   F = d step / d x at the state before the step (a_j = 1 - c_j on the diagonal, the SOC
 *       column through the tables' SOC slopes at the new SOC; u_x and h have no SOC
 *       slope: a_x = 1 - c_x, a_h = 1 - c_h, the step's own coefficients), P = F P F^T + Q;
 *   at the first sample Q also carries the RC voltages' start variance (r_j start_a)^2;
 *   H = [dOCV/dsoc + dr0/dsoc g f i, 1, 1 (, 1) (, 1) (, m_v)], R from the model error (of
 *       the overpotential, or of the one held in *eta when that is larger: mem_k > 0) and
 *       its correlation time (R = 0: the sample carries no information, e.g. dt = 0; but
 *       with start_a = 0 the first sample counts fully, the cell taken rested); with
 *       ECMRT_EST_SLOPES 0 the RC tables' SOC slopes are taken as 0 in F and H; the RC
 *       noise times pol_s2 / (pol_s2 + P_soc) when pol_s2 > 0; the resistances and their
 *       SOC slopes times the effects' factors
 *       (current_dependent_resistance g on r0 and r_fast, temperature_dependence f on r0,
 *       r_fast and r_slow, as the step);
 *   K = P H^T / (H P H^T + R), iterated (relinearised at the updated SOC, at most 5 times)
 *       while the update moves the SOC by more than 1e-3; Joseph form
 *       P = (I - K H) P (I - K H)^T + R K K^T, then exactly symmetric; SOC to [0, 1], h to
 *       [-1, 1].
 * A reading that is NaN, inf or beyond +-1 kV, and an update that would leave the state or
 * the covariance not finite, are not applied: the sample only predicts.
 *
 * With ECMRT_EST_OFFSET the current sensor's offset is a state too (last; the caller's
 * <prefix>_est_t holds it): the step runs on i - offset, F gets the offset column (d x' /
 * d offset = -(d x' / d i), through the effects' and the Butler-Volmer branch's d(i g)/di)
 * and H its entry -r0 d(i g0)/di, as ecmgen.estimate.process.
 * With ECMRT_SURFACE the step reads its RC tables at the surface SOC soc_s = clamp(soc +
 * sv u_diff, 0, 1) (u_diff before the step): the accessor reads them there too, the tables'
 * SOC slopes are chained through d soc_s / d soc = 1 + dsv/dsoc u_diff, and F gets a u_diff
 * column g (d u_j' / d u_diff = d u_j' / d soc_s * sv; 0 where clamped), as
 * ecmgen.estimate.process.
 * Noise constants (ecmrt_est_f32_noise_t) come from the [estimator] settings, baked into
 * the generated .c. No fixed dt: the generator refuses it (capacity_error is in the step's
 * k_soc and needs nothing here).
 */
#ifndef ECMRT_EST_F32_H
#define ECMRT_EST_F32_H

#if ECMRT_VERSION != 3
#error "ecmrt_est_f32.h does not match ecmrt.h"
#endif
#if !defined(ECMRT_F32_H) || !defined(ECMRT_EST_T)
#error "ecmrt_est_f32.h is included by a generated <prefix>_ecm.c after ecmrt_f32.h"
#endif
#if !ECMRT_VARIABLE_DT
#error "the estimator needs the variable-dt step"
#endif
#if !defined(ECMRT_EST_OFFSET)
#error "ECMRT_EST_OFFSET (the current-offset state, 0 or 1) is defined by the generated .c"
#endif
#if !defined(ECMRT_EST_SLOPES)
#define ECMRT_EST_SLOPES 1        /* the Jacobians carry the RC tables' SOC slopes */
#endif

/* soc, u_fast, u_slow (, u_diff) (, u_x) (, h) (, offset_a) */
#define ECMRT_EST_N (3u + (unsigned)ECMRT_DIFF + (unsigned)ECMRT_FX_XRC + \
                     (unsigned)ECMRT_FX_HYST + (unsigned)ECMRT_EST_OFFSET)
#define ECMRT_EST_IX (3u + (unsigned)ECMRT_DIFF)      /* u_x's index (with ECMRT_FX_XRC) */
#define ECMRT_EST_IH (ECMRT_EST_IX + (unsigned)ECMRT_FX_XRC)  /* h's (with ECMRT_FX_HYST) */
#define ECMRT_EST_IB (ECMRT_EST_N - 1u)               /* the offset's (with ECMRT_EST_OFFSET) */

#define ECMRT_EST_ITER 5                              /* relinearisations at most */
#define ECMRT_EST_ITER_SOC 1.0e-3f                    /* ... when the update moves the SOC more */
#define ECMRT_EST_ITER_TOL 1.0e-5f                    /* ... until an iteration moves it less */
#define ECMRT_EST_V_MAX 1000.0f      /* a reading beyond +-1 kV is no cell voltage: no update */

/* the N x N loops unrolled when optimising for speed (GCC 8+, not -Os: the same operations
 * in the same order, the same bits; GCC -O2 unrolls them by itself for 4 states but not for
 * the 5 or 6 of a model with effects: 2655 -> 1669 instructions per step with hysteresis,
 * bench/bench_estimator_c.py) */
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 8 && !defined(__OPTIMIZE_SIZE__)
#define ECMRT_EST_UNROLL _Pragma("GCC unroll 8")
#else
#define ECMRT_EST_UNROLL
#endif

/* the filter's settings (ecmgen.estimate.ekf.NoiseModel), float32 */
typedef struct {
    float p0_soc;             /* initial SOC variance, soc0_sigma^2 */
    float p0_u;               /* initial RC voltage variance, u0_sigma_v^2, V^2 */
    float offset_a;           /* current sensor offset, 1 sigma, A */
    float gain;               /* current sensor gain error, 1 sigma */
    float noise_a;            /* white current noise per sample, A */
    float horizon_s;          /* drift horizon of the sensor bias, s */
    float pol;                /* polarization_error */
    float vn2;                /* voltage_noise_v^2, V^2 */
    float model_error;        /* model voltage error / model overpotential */
    float corr_s;             /* error_correlation_s */
    float start_a;            /* the RC voltages' start sigma is r_j times this current, A */
    float mem_k;              /* 1 / error_memory_s (0: the model error has no memory), 1/s */
    float pol_s2;             /* polarization_soc_sigma^2 (0: the RC noise is not scaled) */
#if ECMRT_FX_HYST
    float p0_h;               /* hysteresis_sigma^2: h's initial variance and its noise scale */
#endif
#if ECMRT_EST_OFFSET
    float p0_b;               /* offset_a^2: the offset state's initial variance, A^2 */
#endif
} ecmrt_est_f32_noise_t;

/* What the update needs from before the step. */
typedef struct {
    float u[ECMRT_EST_N];     /* u[0] unused; the RC voltages before the step */
} ecmrt_est_f32_prior_t;

/* The table accessor: the values and SOC slopes (d/dsoc) the Jacobians need, of direction
 * dir at SOC soc, at the temperature of the model state's last step (its row k_t and weight
 * w_t), by the runtime's own lookup and interpolation (the step's locate, its segment pairs
 * at the temperature from ecmrt_f32_segment or the state's cache of them). A slope is that
 * of the segment the SOC is in (the segment on the right at a breakpoint) and 0 outside the
 * table (clamped), as ecmgen.estimate.process; time constants of the temperature only
 * (ECMRT_TAU_T) have none: the filter takes the state's coefficients kc. The state is read,
 * never written. all = 0: only r0 and the OCV. */
typedef struct {
    float r0, dr0, rf, drf, tf, dtf, rs, drs, ts, dts, ocv, docv;
#if ECMRT_SURFACE
    float up;                 /* in: u_diff before the step (the surface SOC reads it) */
    float ds, du;             /* out: d soc_s / d soc, d soc_s / d u_diff (0 where clamped) */
#endif
} ecmrt_est_f32_par_t;

/* a per-temperature branch value (r_diff, tau_diff, i0) at the state's temperature */
#if ECMRT_TEMP
#define ECMRT_EST_TV(b, j) ((b)[j] + (b)[(j) + 1u] * wt)
#else
#define ECMRT_EST_TV(b, j) ((b)[j])
#endif

/* value y + dy w and slope dy / spacing of parameter j from a segment's pairs (y at its
 * start, difference to its end) along SOC at the temperature: a table row without
 * ECMRT_TEMP, else ecmrt_f32_segment's (the state's cache pc when it is that segment's:
 * the same numbers) */
#define ECMRT_EST_VS(row, j, v, sl)                                                         \
    do {                                                                                    \
        (v) = (row)[j] + (row)[(j) + 1u] * w;                                               \
        (sl) = (row)[(j) + 1u] * inv;                                                       \
    } while (0)

/* 1 / spacing of segment k, or 0 when v is outside the grid (or NaN) */
static inline float ecmrt_est_f32_inv(const ecmrt_f32_grid_t *g, unsigned k, float v)
{
    return (v >= g->x[0] && v <= g->x[(unsigned)g->n - 1u]) ? g->inv_dx[k] : 0.0f;
}

static inline float ecmrt_est_f32_uinv(const ecmrt_f32_ugrid_t *g, unsigned k, float v)
{
    const float u = (v - g->x0) * g->inv_h;
    (void)k;
    return (u >= 0.0f && u <= g->um) ? g->inv_h : 0.0f;
}
#if ECMRT_RC_UNIFORM
#define ECMRT_EST_RC_INV ecmrt_est_f32_uinv
#else
#define ECMRT_EST_RC_INV ecmrt_est_f32_inv
#endif
#if ECMRT_OCV_UNIFORM
#define ECMRT_EST_OCV_INV ecmrt_est_f32_uinv
#else
#define ECMRT_EST_OCV_INV ecmrt_est_f32_inv
#endif

static inline void ecmrt_est_f32_params(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                        unsigned dir, float soc, ecmrt_est_f32_par_t *p,
                                        int all)
{
    const ecmrt_f32_dir_t *d = &m->dir[dir];
    const float *row;
    unsigned kd = ECMRT_HINT_DIR(s, dir);
    float w, inv;
#if ECMRT_TEMP
    float pc[ECMRT_NPAR];
    unsigned kt = s->k_t;
    const float wt = s->w_t;
#endif
#if ECMRT_SURFACE
    unsigned ko = ECMRT_HINT_OCV(s);
    float wo, invo, socr, sv, dsv;
    const float *sp;
#else
#define socr soc
#endif
    (void)s;                        /* (uniform grids, one row, shared OCV: no hint, no cache) */
#if ECMRT_TEMP
    if (kt > (unsigned)m->t.n - 2u) {
        kt = (unsigned)m->t.n - 2u;
    }
#endif
#if ECMRT_SURFACE
    /* the surface SOC the step read its RC tables at: soc + sv u_diff (the u_diff before the
     * step), sv at (soc, T) as the step interpolates it, clamped to [0, 1]; its derivatives
     * by soc (1 + dsv/dsoc u_diff) and by u_diff (sv), 0 where clamped */
    wo = ECMRT_F32_OCV_LOCATE(&m->ocv_g, soc, &ko);
    invo = ECMRT_EST_OCV_INV(&m->ocv_g, ko, soc);
#if ECMRT_TEMP
    sp = m->sv + 2u * ((unsigned)m->ocv_g.n * kt + ko);
    sv = sp[0] + sp[1] * wt;
    dsv = (sp[2] + sp[3] * wt) - sv;
    sv = sv + dsv * wo;
    dsv = dsv * invo;
#else
    sp = m->sv + 2u * ko;
    sv = sp[0] + sp[1] * wo;
    dsv = sp[1] * invo;
#endif
    socr = soc + sv * p->up;
    if (!(socr >= 0.0f)) {
        socr = 0.0f;
        p->ds = p->du = 0.0f;
    } else if (socr > 1.0f) {
        socr = 1.0f;
        p->ds = p->du = 0.0f;
    } else {
        p->ds = 1.0f + dsv * p->up;
        p->du = sv;
    }
#endif
    w = ECMRT_F32_RC_LOCATE(&d->g, socr, &kd);
    inv = ECMRT_EST_RC_INV(&d->g, kd, socr);
#if ECMRT_TEMP
    if (((kd << 1) | dir) == (unsigned)s->pc_key) {
        row = s->pc;
    } else {
        ecmrt_f32_segment(d->rows + ECMRT_NPAR * ((unsigned)d->g.n * kt + kd), ECMRT_NPAR,
                          ECMRT_NPAR, wt, pc);
        row = pc;
    }
#else
    row = d->rows + ECMRT_NPAR * kd;
#endif
    ECMRT_EST_VS(row, ECMRT_P_R0, p->r0, p->dr0);
    if (all) {
        ECMRT_EST_VS(row, ECMRT_P_RF, p->rf, p->drf);
        ECMRT_EST_VS(row, ECMRT_P_RS, p->rs, p->drs);
#if ECMRT_TAU_T
        p->tf = p->dtf = p->ts = p->dts = 0.0f;         /* the state's kc serve instead */
#else
        ECMRT_EST_VS(row, ECMRT_P_KF, p->tf, p->dtf);
        ECMRT_EST_VS(row, ECMRT_P_KS, p->ts, p->dts);
#endif
    }
#if !ECMRT_EST_SLOPES
    /* the Jacobians take the RC tables as flat in SOC: the SOC is read from the OCV alone */
    p->dr0 = 0.0f;
    if (all) {
        p->drf = p->dtf = p->drs = p->dts = 0.0f;
    }
#endif
#if ECMRT_OCV_SHARED
    ECMRT_EST_VS(row, ECMRT_P_OCV, p->ocv, p->docv);
#else
    {
#if ECMRT_SURFACE
        w = wo;                     /* the OCV at the mean SOC, located above */
        inv = invo;
#else
        unsigned ko = ECMRT_HINT_OCV(s);
        w = ECMRT_F32_OCV_LOCATE(&m->ocv_g, soc, &ko);
        inv = ECMRT_EST_OCV_INV(&m->ocv_g, ko, soc);
#endif
#if ECMRT_TEMP
        if (ko == (unsigned)s->oc_key) {
            row = s->oc;
        } else {
            ecmrt_f32_segment(m->ocv + 2u * ((unsigned)m->ocv_g.n * kt + ko), 2u, 2u, wt, pc);
            row = pc;
        }
#else
        row = m->ocv + 2u * ko;
#endif
        ECMRT_EST_VS(row, 0u, p->ocv, p->docv);
    }
#endif
}
#undef socr


/* Before the model's step: i and dt sanitised exactly as the step does (so that the filter
 * uses the step's own inputs; the step's sanitising is then a no-op), the RC voltages kept. */
static inline void ecmrt_est_f32_prior(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                       float *i, float *dt, ecmrt_est_f32_prior_t *pr)
{
    union {
        uint32_t u;
        float f;
    } bits;
    if (!(*i >= -m->i_max_a)) {
        *i = (*i == *i) ? -m->i_max_a : 0.0f;
    } else if (*i > m->i_max_a) {
        *i = m->i_max_a;
    }
    bits.f = *dt;
    if (bits.u - 1u >= 0x46FFFE00u) {
        *dt = (*dt > 0.0f) ? ECMRT_F32_DT_MAX : 0.0f;
    }
    pr->u[0] = 0.0f;
    pr->u[1] = s->u_fast;
    pr->u[2] = s->u_slow;
#if ECMRT_DIFF
    pr->u[3] = s->u_diff;
#endif
#if ECMRT_FX_HYST && ECMRT_EST_OFFSET
    pr->u[ECMRT_EST_IH] = s->h;                       /* for d h' / d offset */
#endif
}

/* y . h, summed from the first entry on */
static inline float ecmrt_est_f32_dot(const float *y, const float *h)
{
    unsigned b;
    float sum = y[0] * h[0];
    ECMRT_EST_UNROLL
    for (b = 1u; b < ECMRT_EST_N; b++) {
        sum = sum + y[b] * h[b];
    }
    return sum;
}

/* gain: c = P h, K = c / (h c + R), x = x0 + K e; returns 0 when h P h^T + R is not > 0 */
static inline int ecmrt_est_f32_gain(const float *P, const float *h, float r, const float *x0,
                                     float e, float *c, float *k, float *x)
{
    unsigned a;
    float sum;
    ECMRT_EST_UNROLL
    for (a = 0u; a < ECMRT_EST_N; a++) {
        c[a] = ecmrt_est_f32_dot(P + ECMRT_EST_N * a, h);
    }
    sum = ecmrt_est_f32_dot(h, c) + r;
    if (!(sum > 0.0f) || sum > FLT_MAX) {
        return 0;
    }
    ECMRT_EST_UNROLL
    for (a = 0u; a < ECMRT_EST_N; a++) {
        k[a] = c[a] / sum;
        x[a] = x0[a] + k[a] * e;
    }
    return 1;
}

/* the SOC into [0, 1] (NaN: 0) */
static inline float ecmrt_est_f32_clamp(float soc)
{
    if (!(soc >= 0.0f)) {
        return 0.0f;
    }
    return soc > 1.0f ? 1.0f : soc;
}

#if ECMRT_FX_HYST
/* the hysteresis state into [-1, 1] (NaN stays NaN: the finiteness check refuses it) */
static inline float ecmrt_est_f32_clamp_h(float h)
{
    if (h < -1.0f) {
        return -1.0f;
    }
    return h > 1.0f ? 1.0f : h;
}
#endif

#if ECMRT_FX_CDR || ECMRT_FX_ARR
/* a parameter effect's factor g on the accessor's r0 (and r_fast with fast, r_slow with
 * slow) and their SOC slopes */
static inline void ecmrt_est_f32_scale(ecmrt_est_f32_par_t *p, float g, int fast, int slow)
{
    p->r0 = p->r0 * g;
    p->dr0 = p->dr0 * g;
    if (fast) {
        p->rf = p->rf * g;
        p->drf = p->drf * g;
    }
    if (slow) {
        p->rs = p->rs * g;
        p->drs = p->drs * g;
    }
}

/* the parameter effects' factors, in the step's order: current_dependent_resistance g on
 * r0, r_fast; temperature_dependence f on r0, r_fast, r_slow; all = 0: r0 only */
static inline void ecmrt_est_f32_fx(ecmrt_est_f32_par_t *p, float g, float f, int all)
{
#if ECMRT_FX_CDR
    ecmrt_est_f32_scale(p, g, all, 0);
#endif
#if ECMRT_FX_ARR
    ecmrt_est_f32_scale(p, f, all, all);
#endif
    (void)g;
    (void)f;
}
#endif

static inline float ecmrt_est_f32_abs(float x)
{
    return x < 0.0f ? -x : x;
}

/* After the model's step s (current i, dt as sanitised by ecmrt_est_f32_prior, the cell
 * temperature temp as given to the step, predicted voltage vp): the covariance prediction
 * and the update with the measured voltage vm (not finite: no update). P is the N x N
 * covariance, row-major, exactly symmetric. */
static inline void ecmrt_est_f32_update(const ecmrt_f32_model_t *m,
                                        const ecmrt_est_f32_noise_t *nz, ECMRT_STATE *s,
                                        float *P, uint8_t *first, float *eta,
                                        const ecmrt_est_f32_prior_t *pr, float i, float temp,
                                        float dt, float vp, float vm, float *ob)
{
#define N ECMRT_EST_N
    const unsigned dir = s->charging;
    float a[N], f[N], q[N], h[N], x0[N], xu[N], xn[N], c[N], k[N], d[N], fp[N * N];
    const float ai = i < 0.0f ? -i : i;
    float r, e, kk, b, one_a, da, rg, vi, ps;
    float gf = 1.0f;
    ecmrt_est_f32_par_t p;
    unsigned u, v;
    int it, ok;
#if ECMRT_BV || ECMRT_DIFF
#if ECMRT_TEMP
    unsigned kt = s->k_t;
    const float wt = s->w_t;
    const float *br;
#else
    const float *br = m->dir[dir].branch;
#endif
#endif
#if ECMRT_BV
    float xb;
#endif
#if ECMRT_DIFF
    float rd, ad;
#endif
#if ECMRT_FX_CDR || ECMRT_FX_ARR
    float gc = 1.0f, fa = 1.0f;
#endif
#if ECMRT_FX_CDR
    float xc;
#endif
#if ECMRT_FX_HYST
    const float sg = dir == ECMRT_CHARGE ? 1.0f : -1.0f;
    float ch, vx;
#endif
#if ECMRT_EST_OFFSET
    /* the offset column o of F (d x' / d offset: the filter's current is i_seen - offset),
     * the resistances before the current's factors, d(i g)/di of those factors */
    float o[N], ds_di, rb0, rbf, dg0 = 1.0f, dgf = 1.0f;
#endif
#if ECMRT_SURFACE
    /* the u_diff column g of F (d x' / d u_diff through the surface SOC, besides a_diff) */
    float g[N];
#endif
#if !ECMRT_FX_ARR
    (void)temp;
#endif
#if !ECMRT_EST_OFFSET
    (void)ob;
#endif
#if ECMRT_TEMP && (ECMRT_BV || ECMRT_DIFF)
    if (kt > (unsigned)m->t.n - 2u) {
        kt = (unsigned)m->t.n - 2u;
    }
    br = m->dir[dir].branch + 2u * ECMRT_NB * kt;
#endif

    /* 1. the Jacobian of the step, at the new SOC (where the step looked its tables up) */
    x0[0] = s->soc;
    x0[1] = s->u_fast;
    x0[2] = s->u_slow;
#if ECMRT_DIFF
    x0[3] = s->u_diff;
#endif
#if ECMRT_FX_XRC
    x0[ECMRT_EST_IX] = s->u_x;
#endif
#if ECMRT_FX_HYST
    x0[ECMRT_EST_IH] = s->h;
#endif
#if ECMRT_EST_OFFSET
    x0[ECMRT_EST_IB] = *ob;
#endif
#if ECMRT_SURFACE
    p.up = pr->u[3];
    for (u = 0u; u < N; u++) {
        g[u] = 0.0f;
    }
#endif
    ecmrt_est_f32_params(m, s, dir, x0[0], &p, 1);
    /* the parameter effects' factors, as the step computes them */
#if ECMRT_FX_CDR
    xc = ai * m->g_inv_i0;
    gc = m->g_scale * ecmrt_f32_asinh(&xc);
    gc = gc / xc;
#endif
#if ECMRT_FX_ARR
    fa = ecmrt_f32_arrhenius(m, temp);
#endif
#if ECMRT_EST_OFFSET
    rb0 = p.r0;
    rbf = p.rf;
#if ECMRT_FX_ARR
    rb0 = rb0 * fa;
    rbf = rbf * fa;
#endif
#if ECMRT_FX_CDR
    dg0 = m->g_scale / ecmrt_f32_sqrt(xc * xc + 1.0f);  /* d(i g)/di = scale / sqrt(1 + x^2) */
    dgf = dg0;
#endif
    ds_di = dt * m->k_soc;           /* d x' / d offset = -(d x' / d i), d soc' / d i = dt k */
    o[0] = -ds_di;
#endif
#if ECMRT_FX_CDR || ECMRT_FX_ARR
    ecmrt_est_f32_fx(&p, gc, fa, 1);
#endif
#if ECMRT_BV
    xb = ai / ECMRT_EST_TV(br, ECMRT_B_I0);           /* the step's factor asinh(x)/x */
    gf = ecmrt_f32_asinh(&xb);
    gf = gf / xb;
#if ECMRT_EST_OFFSET && ECMRT_FX_CDR
    /* d(i gc gf)/di, the product rule as ecmgen.estimate.process.current_factors */
    dgf = (gc * (1.0f / ecmrt_f32_sqrt(xb * xb + 1.0f)) + gf * dg0) - gc * gf;
#elif ECMRT_EST_OFFSET
    dgf = 1.0f / ecmrt_f32_sqrt(xb * xb + 1.0f);
#endif
#endif
    a[0] = 1.0f;
    f[0] = 0.0f;
    q[0] = 0.0f;
    /* fast and slow pairs: u' = a u + r g (1 - a) i, a = exp(-dt / tau(soc)); da/dsoc */
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_F));
    a[1] = 1.0f - one_a;
    da = 0.0f;                                        /* tau of the temperature only */
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / p.tf);
    a[1] = 1.0f - one_a;
    da = ((a[1] * dt) / (p.tf * p.tf)) * p.dtf;
#endif
    f[1] = da * pr->u[1] + ((p.drf * one_a - p.rf * da) * gf) * i;
#if ECMRT_SURFACE
    g[1] = f[1] * p.du;                               /* by the tables' SOC, then chained */
    f[1] = f[1] * p.ds;
#endif
#if ECMRT_EST_OFFSET
    o[1] = -((rbf * one_a) * dgf) - f[1] * ds_di;
#endif
    /* the RC noise's factor: s^2 / (s^2 + P_soc) with polarization_soc_sigma s (pol_s2 = s^2),
     * 1 without: while the SOC is far less certain than s, a slow voltage offset is taken
     * as SOC error rather than as polarisation */
    ps = nz->pol_s2 > 0.0f ? nz->pol_s2 / (nz->pol_s2 + P[0]) : 1.0f;
    rg = p.rf * gf;
    e = (nz->pol * rg) * i;
    q[1] = ((e * e) * (1.0f - a[1] * a[1])) * ps;
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_S));
    a[2] = 1.0f - one_a;
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / p.ts);
    a[2] = 1.0f - one_a;
    da = ((a[2] * dt) / (p.ts * p.ts)) * p.dts;
#endif
    f[2] = da * pr->u[2] + (p.drs * one_a - p.rs * da) * i;
#if ECMRT_SURFACE
    g[2] = f[2] * p.du;
    f[2] = f[2] * p.ds;
#endif
#if ECMRT_EST_OFFSET
    o[2] = -(p.rs * one_a) - f[2] * ds_di;
#endif
    e = (nz->pol * p.rs) * i;
    q[2] = ((e * e) * (1.0f - a[2] * a[2])) * ps;
#if ECMRT_DIFF
    rd = ECMRT_EST_TV(br, ECMRT_B_RD);                /* r_diff, tau_diff: no SOC slope */
#if ECMRT_TAU_T
    one_a = ecmrt_f32_one_minus_exp_neg(dt * ECMRT_KC(s, dir, ECMRT_K_D));
#else
    one_a = ecmrt_f32_one_minus_exp_neg(dt / ECMRT_EST_TV(br, ECMRT_B_KD));
#endif
    ad = 1.0f - one_a;
    a[3] = ad;
#if ECMRT_EST_OFFSET
    o[3] = -(rd * one_a);
#endif
    f[3] = 0.0f;
    e = (nz->pol * rd) * i;
    q[3] = ((e * e) * (1.0f - ad * ad)) * ps;
#endif
#if ECMRT_FX_XRC
    /* extra_rc: u_x' = a_x u_x + r_x (1 - a_x) i, no SOC slope */
    one_a = ecmrt_f32_one_minus_exp_neg(dt / m->x_k);
    a[ECMRT_EST_IX] = 1.0f - one_a;
#if ECMRT_EST_OFFSET
    o[ECMRT_EST_IX] = -(m->x_r * one_a);
#endif
    f[ECMRT_EST_IX] = 0.0f;
    e = (nz->pol * m->x_r) * i;
    q[ECMRT_EST_IX] = ((e * e) * (1.0f - a[ECMRT_EST_IX] * a[ECMRT_EST_IX])) * ps;
#endif
#if ECMRT_FX_HYST
    /* hysteresis: h' = a_h h + (1 - a_h) s, a_h = exp(-|i| dt / (3600 decay_ah)); its noise
     * sigma_h^2 (1 - a_h^2), 1 - a_h^2 written c_h (2 - c_h) */
    ch = ecmrt_f32_one_minus_exp_neg((ai * dt) * m->h_k);
    a[ECMRT_EST_IH] = 1.0f - ch;
    f[ECMRT_EST_IH] = 0.0f;
    q[ECMRT_EST_IH] = nz->p0_h * (ch * (2.0f - ch));
#endif
#if ECMRT_EST_OFFSET
#if ECMRT_FX_HYST
    /* d h' / d i = -(h - s) sign(i) c a_h, c = dt / (3600 decay_ah) */
    o[ECMRT_EST_IH] = (((pr->u[ECMRT_EST_IH] - sg) * (i > 0.0f ? 1.0f : (i < 0.0f ? -1.0f : 0.0f)))
                       * (dt * m->h_k)) * a[ECMRT_EST_IH];
#endif
    o[ECMRT_EST_IB] = 0.0f;
    a[ECMRT_EST_IB] = 1.0f;
    f[ECMRT_EST_IB] = 0.0f;
#endif
    /* SOC: the sensor's bias over the drift horizon, (b k dt)^2 (horizon / dt) written
     * (b k)^2 (dt horizon) (no 0 * inf for a denormal dt), and white current noise; with
     * the offset state the offset is a state (a random walk over the horizon) instead */
    if (dt > 0.0f) {
        kk = dt * m->k_soc;
#if ECMRT_EST_OFFSET
        b = nz->gain * ai;
        q[ECMRT_EST_IB] = (nz->p0_b * dt) / nz->horizon_s;
#else
        b = nz->gain * ai + nz->offset_a;
#endif
        e = b * m->k_soc;
        r = nz->noise_a * kk;
        q[0] = (e * e) * (dt * nz->horizon_s) + r * r;
    } else {
        for (u = 0u; u < N; u++) {
            q[u] = 0.0f;
        }
    }
    /* the first sample: the RC voltages are unknown (a record may start under load or
     * mid-relaxation), sigma r_j start_a with the resistances at the start */
    if (*first) {
        e = rg * nz->start_a;
        q[1] = q[1] + e * e;
        e = p.rs * nz->start_a;
        q[2] = q[2] + e * e;
#if ECMRT_DIFF
        e = rd * nz->start_a;
        q[3] = q[3] + e * e;
#endif
#if ECMRT_FX_XRC
        e = m->x_r * nz->start_a;
        q[ECMRT_EST_IX] = q[ECMRT_EST_IX] + e * e;
#endif
    }
    /* 2. P = F P F^T + Q (F: diagonal a, SOC column f, offset column o) */
    ECMRT_EST_UNROLL
    for (u = 0u; u < N; u++) {
        ECMRT_EST_UNROLL
        for (v = 0u; v < N; v++) {
            fp[N * u + v] = a[u] * P[N * u + v] + f[u] * P[v];
#if ECMRT_EST_OFFSET
            fp[N * u + v] = fp[N * u + v] + o[u] * P[N * ECMRT_EST_IB + v];
#endif
#if ECMRT_SURFACE
            fp[N * u + v] = fp[N * u + v] + g[u] * P[N * 3u + v];
#endif
        }
    }
    ECMRT_EST_UNROLL
    for (u = 0u; u < N; u++) {
        ECMRT_EST_UNROLL
        for (v = u; v < N; v++) {
            r = a[v] * fp[N * u + v] + f[v] * fp[N * u];
#if ECMRT_EST_OFFSET
            r = r + o[v] * fp[N * u + ECMRT_EST_IB];
#endif
#if ECMRT_SURFACE
            r = r + g[v] * fp[N * u + 3u];
#endif
            if (u == v) {
                r = r + q[u];
            }
            P[N * u + v] = r;
            P[N * v + u] = r;
        }
    }
    /* 3. the measurement: h = dv/dx, R */
#if ECMRT_SURFACE
    h[0] = p.docv + (p.dr0 * p.ds) * i;               /* r0 at the surface SOC */
#else
    h[0] = p.docv + p.dr0 * i;
#endif
    for (u = 1u; u < N; u++) {
        h[u] = 1.0f;
    }
#if ECMRT_FX_HYST
    h[ECMRT_EST_IH] = m->h_m;
#endif
#if ECMRT_EST_OFFSET
    h[ECMRT_EST_IB] = -(rb0 * dg0);                   /* d v / d offset = -r0 d(i g0)/di */
#endif
    /* the overpotential the model's error scales with: |vp - ocv|, or (mem_k > 0) the one
     * held in *eta from before, decayed by exp(-dt / error_memory_s), when that is larger
     * (eta may be a null pointer when mem_k is 0) */
    e = vp - p.ocv;
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
    /* a record taken to start rested (start_a = 0): its first sample counts fully */
    if (!(*first && nz->start_a == 0.0f) && dt < nz->corr_s) {
        r = dt > 0.0f ? r * (nz->corr_s / dt) : 0.0f;
    }
    *first = 0u;
    if (!(vm >= -ECMRT_EST_V_MAX && vm <= ECMRT_EST_V_MAX)) {
        r = 0.0f;                                     /* no measurement (NaN, inf, absurd) */
    }
    /* 4. the update, iterated while it moves the SOC */
    if (r > 0.0f) {
        ok = ecmrt_est_f32_gain(P, h, r, x0, vm - vp, c, k, xu);
        for (it = 0; ok && it < ECMRT_EST_ITER; it++) {
            xu[0] = ecmrt_est_f32_clamp(xu[0]);
#if ECMRT_FX_HYST
            xu[ECMRT_EST_IH] = ecmrt_est_f32_clamp_h(xu[ECMRT_EST_IH]);
#endif
            if (ecmrt_est_f32_abs(xu[0] - x0[0]) < ECMRT_EST_ITER_SOC) {
                break;
            }
            ecmrt_est_f32_params(m, s, dir, xu[0], &p, 0);
#if ECMRT_EST_OFFSET
            rb0 = p.r0;
#if ECMRT_FX_ARR
            rb0 = rb0 * fa;
#endif
            h[ECMRT_EST_IB] = -(rb0 * dg0);
#endif
#if ECMRT_FX_CDR || ECMRT_FX_ARR
            ecmrt_est_f32_fx(&p, gc, fa, 0);
#endif
            vi = ((p.ocv + p.r0 * i) + xu[1]) + xu[2];
#if ECMRT_DIFF
            vi = vi + xu[3];
#endif
#if ECMRT_FX_HYST
            vx = m->h_m * (xu[ECMRT_EST_IH] - m->h_ref) + m->h_m0 * (sg - m->h_ref);
#if ECMRT_FX_XRC
            vx = vx + xu[ECMRT_EST_IX];
#endif
            vi = vi + vx;
#elif ECMRT_FX_XRC
            vi = vi + xu[ECMRT_EST_IX];
#endif
#if ECMRT_SURFACE
            h[0] = p.docv + (p.dr0 * p.ds) * i;
#else
            h[0] = p.docv + p.dr0 * i;
#endif
            e = vm - vi;
            for (u = 0u; u < N; u++) {
                e = e - h[u] * (x0[u] - xu[u]);
            }
            ok = ecmrt_est_f32_gain(P, h, r, x0, e, c, k, xn);
            if (ok) {
                da = ecmrt_est_f32_abs(xn[0] - xu[0]);
                for (u = 0u; u < N; u++) {
                    xu[u] = xn[u];
                }
                if (da < ECMRT_EST_ITER_TOL) {
                    break;
                }
            }
        }
        if (ok) {
            /* Joseph form: M = P - K c^T, d = M h, P = M - d K^T + R K K^T, symmetrised
             * (M, then the new P before symmetrising, in fp) */
            ECMRT_EST_UNROLL
            for (u = 0u; u < N; u++) {
                ECMRT_EST_UNROLL
                for (v = 0u; v < N; v++) {
                    fp[N * u + v] = P[N * u + v] - k[u] * c[v];
                }
                d[u] = ecmrt_est_f32_dot(fp + N * u, h);
            }
            e = 0.0f;                  /* x * 0 is 0 for a finite x, NaN for inf or NaN */
            ECMRT_EST_UNROLL
            for (u = 0u; u < N; u++) {
                ECMRT_EST_UNROLL
                for (v = 0u; v < N; v++) {
                    fp[N * u + v] = (fp[N * u + v] - d[u] * k[v]) + r * (k[u] * k[v]);
                    e = e + fp[N * u + v] * 0.0f;
                }
                e = e + xu[u] * 0.0f;
            }
            ok = e == 0.0f;
        }
        if (ok) {                      /* applied only when all of it is finite */
            ECMRT_EST_UNROLL
            for (u = 0u; u < N; u++) {
                ECMRT_EST_UNROLL
                for (v = u; v < N; v++) {
                    e = 0.5f * (fp[N * u + v] + fp[N * v + u]);
                    P[N * u + v] = e;
                    P[N * v + u] = e;
                }
            }
            s->u_fast = xu[1];
            s->u_slow = xu[2];
#if ECMRT_DIFF
            s->u_diff = xu[3];
#endif
#if ECMRT_FX_XRC
            s->u_x = xu[ECMRT_EST_IX];
#endif
#if ECMRT_FX_HYST
            s->h = ecmrt_est_f32_clamp_h(xu[ECMRT_EST_IH]);
#endif
#if ECMRT_EST_OFFSET
            *ob = xu[ECMRT_EST_IB];
#endif
            x0[0] = xu[0];
        }
    }
    s->soc = ecmrt_est_f32_clamp(x0[0]);
    s->soc_c = 0.0f;          /* the filter's SOC is its estimate, not a compensated sum */
#undef N
}

#undef ECMRT_EST_VS
#undef ECMRT_EST_TV
#endif /* ECMRT_EST_F32_H */
