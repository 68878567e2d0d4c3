/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32_tables.h - ecmgen C runtime: the SOC estimator's table accessor (hand-written,
 * model-independent). Included by ecmrt_est_f32.h: the values and SOC slopes of the model's
 * tables that the filter's Jacobians need, read by the step's own lookup and interpolation
 * (ecmrt_f32.h), and the parameter effects' factors on them. Mirrored by
 * src/ecmgen/c/estref.py (its _Tables).
 */
#ifndef ECMRT_EST_F32_TABLES_H
#define ECMRT_EST_F32_TABLES_H

#if !defined(ECMRT_F32_H)
#error "ecmrt_est_f32_tables.h is included by ecmrt_est_f32.h after the model's configuration"
#endif

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

/* a per-temperature branch value (r_diff, tau_diff, i0) at the temperature weight wt
 * between the pair b[j], b[j + 1] (value, difference to the next row); one row: b[j] */
static inline float ecmrt_est_f32_tv(const float *b, unsigned j, float wt)
{
#if ECMRT_TEMP
    return b[j] + b[j + 1u] * wt;
#else
    (void)wt;
    return b[j];
#endif
}

/* value y + dy w and slope dy inv of parameter j from a segment's pairs (y at its start,
 * difference to its end) along SOC at the temperature: a table row without ECMRT_TEMP,
 * else ecmrt_f32_segment's (the state's cache when it is that segment's: the same numbers);
 * w the weight in the segment, inv 1 / its spacing (0 outside the grid) */
static inline void ecmrt_est_f32_vs(const float *row, unsigned j, float w, float inv,
                                    float *v, float *sl)
{
    *v = row[j] + row[j + 1u] * w;
    *sl = row[j + 1u] * inv;
}

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
    float wo, invo, sv, dsv;
    const float *sp;
#endif
    float socr = soc;               /* the SOC the RC tables are read at */
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
    ecmrt_est_f32_vs(row, ECMRT_P_R0, w, inv, &p->r0, &p->dr0);
    if (all) {
        ecmrt_est_f32_vs(row, ECMRT_P_RF, w, inv, &p->rf, &p->drf);
        ecmrt_est_f32_vs(row, ECMRT_P_RS, w, inv, &p->rs, &p->drs);
#if ECMRT_TAU_T
        p->tf = p->dtf = p->ts = p->dts = 0.0f;         /* the state's kc serve instead */
#else
        ecmrt_est_f32_vs(row, ECMRT_P_KF, w, inv, &p->tf, &p->dtf);
        ecmrt_est_f32_vs(row, ECMRT_P_KS, w, inv, &p->ts, &p->dts);
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
    ecmrt_est_f32_vs(row, ECMRT_P_OCV, w, inv, &p->ocv, &p->docv);
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
        ecmrt_est_f32_vs(row, 0u, w, inv, &p->ocv, &p->docv);
    }
#endif
}


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

#endif /* ECMRT_EST_F32_TABLES_H */
