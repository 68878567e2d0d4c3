/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32.h - ecmgen C runtime: the extended Kalman filter (SOC estimator) on the
 * model's own float32 step (hand-written, model-independent).
 *
 * Included by a generated <prefix>_est_f32.c (`[c] estimator = "ekf"`) after the model's
 * <prefix>_ecm_f32_config.h (ecmrt_f32.h as the model's .c configures it, and the model's
 * tables), with ECMRT_EST_OFFSET 0 or 1. The generated <prefix>_est_step_f32() calls
 *     ecmrt_est_f32_prior()   sanitise i and dt as the step does, keep the RC voltages;
 *     <prefix>_step_f32()     the model's own step: the predicted state and voltage;
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
 *   H = [dOCV/dsoc + dr0/dsoc g f i, 1, 1 (, 1) (, 1) (, m_v)] (with ECMRT_EST_SPREAD
 *       dOCV/dsoc is the secant over soc +- ocv_k sqrt(P_soc) after the predict, clamped
 *       to [0, 1], in every relinearisation too), R from the model error (of
 *       the overpotential, or of the one held in *eta when that is larger: mem_k > 0), the
 *       current offset through the resistances (offset_a (r0 + sum r_j), without the
 *       offset state) and its correlation time (R = 0: the sample carries no
 *       information, e.g. dt = 0; but with start_a = 0 the first sample counts fully, the
 *       cell taken rested); with
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
#if !defined(ECMRT_F32_H)
#error "ecmrt_est_f32.h is included by a generated <prefix>_est_f32.c after the model's configuration"
#endif
#if !ECMRT_VARIABLE_DT
#error "the estimator needs the variable-dt step"
#endif
#if !defined(ECMRT_EST_OFFSET)
#error "ECMRT_EST_OFFSET (the current-offset state, 0 or 1) is defined by the generated <prefix>_est_f32.c"
#endif
#if !defined(ECMRT_EST_SLOPES)
#define ECMRT_EST_SLOPES 1        /* the Jacobians carry the RC tables' SOC slopes */
#endif
#if !defined(ECMRT_EST_SPREAD)
#define ECMRT_EST_SPREAD 0        /* H's OCV slope: the tangent (1: the secant, ocv_k) */
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
#if ECMRT_EST_SPREAD
    float ocv_k;              /* ocv_slope_spread: H's OCV slope is the secant over soc +- k sigma */
#endif
#if ECMRT_FX_HYST
    float p0_h;               /* hysteresis_sigma^2: h's initial variance and its noise scale */
#endif
#if ECMRT_EST_OFFSET
    float p0_b;               /* offset_a^2: the offset state's initial variance, A^2 */
#endif
} ecmrt_est_f32_noise_t;

/* a vector over the filter's states */
typedef float ecmrt_est_f32_vec_t[ECMRT_EST_N];

/* What the update needs from before the step. */
typedef struct {
    float u[ECMRT_EST_N];     /* u[0] unused; the RC voltages before the step */
} ecmrt_est_f32_prior_t;

#include "ecmrt_est_f32_tables.h"   /* the table accessor */

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

static inline float ecmrt_est_f32_abs(float x)
{
    return x < 0.0f ? -x : x;
}

#if ECMRT_EST_SPREAD
/* the OCV slope H takes (ecmgen.estimate.ekf.spread_slope): the tangent p->docv, or with
 * k = ocv_slope_spread > 0 the secant over soc +- k sqrt(p_soc), clamped to [0, 1], by the
 * accessor's own OCV (p: the accessor's values at soc, its u_diff for the surface SOC) */
#define ECMRT_EST_SPREAD_MIN 1e-6f    /* a narrower secant (in SOC) is the tangent */
#define ECMRT_EST_P_SOC_MIN 1e-12f    /* ... and so is one of a smaller SOC variance */
static inline float ecmrt_est_f32_ocv_slope(const ecmrt_f32_model_t *m, const ECMRT_STATE *s,
                                            unsigned dir, float soc, float p_soc, float k,
                                            const ecmrt_est_f32_par_t *p)
{
    ecmrt_est_f32_par_t q;
    float d, lo, hi, v_lo;
    if (!(k > 0.0f && p_soc > ECMRT_EST_P_SOC_MIN)) {
        return p->docv;
    }
    d = k * ecmrt_f32_sqrt(p_soc);
    lo = soc - d;
    hi = soc + d;
    lo = lo < 0.0f ? 0.0f : lo;
    hi = hi > 1.0f ? 1.0f : hi;
    if (!(hi - lo > ECMRT_EST_SPREAD_MIN)) {
        return p->docv;
    }
    q = *p;
    ecmrt_est_f32_params(m, s, dir, lo, &q, 0);
    v_lo = q.ocv;
    ecmrt_est_f32_params(m, s, dir, hi, &q, 0);
    return (q.ocv - v_lo) / (hi - lo);
}
#endif

/* The covariance update in Joseph form: M = P - K c^T, d = M h, P = M - d K^T + R K K^T,
 * symmetrised; written to P, and 1 returned, only when it and the updated state xu are
 * finite (M, then the new P before symmetrising, in fp) */
static inline int ecmrt_est_f32_joseph(float *P, const float *k, const float *c,
                                       const float *h, float r, const float *xu)
{
    float fp[ECMRT_EST_N * ECMRT_EST_N];
    ecmrt_est_f32_vec_t d;
    unsigned u, v;
    float e;
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = 0u; v < ECMRT_EST_N; v++) {
            fp[ECMRT_EST_N * u + v] = P[ECMRT_EST_N * u + v] - k[u] * c[v];
        }
        d[u] = ecmrt_est_f32_dot(fp + ECMRT_EST_N * u, h);
    }
    e = 0.0f;                          /* x * 0 is 0 for a finite x, NaN for inf or NaN */
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = 0u; v < ECMRT_EST_N; v++) {
            e = (fp[ECMRT_EST_N * u + v] - d[u] * k[v]) + r * (k[u] * k[v]);
            fp[ECMRT_EST_N * u + v] = e;
        }
    }
    e = 0.0f;
    for (u = 0u; u < ECMRT_EST_N * ECMRT_EST_N; u++) {
        e = e + fp[u] * 0.0f;
    }
    for (u = 0u; u < ECMRT_EST_N; u++) {
        e = e + xu[u] * 0.0f;
    }
    if (!(e == 0.0f)) {
        return 0;
    }
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = u; v < ECMRT_EST_N; v++) {
            e = 0.5f * (fp[ECMRT_EST_N * u + v] + fp[ECMRT_EST_N * v + u]);
            P[ECMRT_EST_N * u + v] = e;
            P[ECMRT_EST_N * v + u] = e;
        }
    }
    return 1;
}

#include "ecmrt_est_f32_rows.h"   /* the model's rows of F, Q and H, one unit per state */

/* P = F P F^T + Q, F = diag(a) + f e_0^T (+ o e_offset^T) (+ g e_3^T), exactly symmetric */
static inline void ecmrt_est_f32_predict(float *P, const ecmrt_est_f32_lin_t *L)
{
    float fp[ECMRT_EST_N * ECMRT_EST_N];
    unsigned u, v;
    float r;
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = 0u; v < ECMRT_EST_N; v++) {
            fp[ECMRT_EST_N * u + v] = L->a[u] * P[ECMRT_EST_N * u + v] + L->f[u] * P[v];
#if ECMRT_EST_OFFSET
            fp[ECMRT_EST_N * u + v] = fp[ECMRT_EST_N * u + v] + L->o[u] * P[ECMRT_EST_N * ECMRT_EST_IB + v];
#endif
#if ECMRT_SURFACE
            fp[ECMRT_EST_N * u + v] = fp[ECMRT_EST_N * u + v] + L->g[u] * P[ECMRT_EST_N * 3u + v];
#endif
        }
    }
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = u; v < ECMRT_EST_N; v++) {
            r = L->a[v] * fp[ECMRT_EST_N * u + v] + L->f[v] * fp[ECMRT_EST_N * u];
#if ECMRT_EST_OFFSET
            r = r + L->o[v] * fp[ECMRT_EST_N * u + ECMRT_EST_IB];
#endif
#if ECMRT_SURFACE
            r = r + L->g[v] * fp[ECMRT_EST_N * u + 3u];
#endif
            if (u == v) {
                r = r + L->q[u];
            }
            P[ECMRT_EST_N * u + v] = r;
            P[ECMRT_EST_N * v + u] = r;
        }
    }
}

/* The update with innovation vm - vp, iterated (relinearised at the updated SOC, at most
 * ECMRT_EST_ITER times) while it moves the SOC, then the Joseph form; the updated state in
 * xu and 1 returned only when all of it is finite. */
static inline int ecmrt_est_f32_correct(const ecmrt_f32_model_t *m,
                                        const ecmrt_est_f32_noise_t *nz, const ECMRT_STATE *s,
                                        unsigned dir, float *P, ecmrt_est_f32_par_t *p,
                                        ecmrt_est_f32_lin_t *L,
                                        const float *x0, float i, float r, float vp, float vm,
                                        float *xu)
{
    ecmrt_est_f32_vec_t c, k, xn;
    unsigned u;
    float e, da;
    int it, ok = ecmrt_est_f32_gain(P, L->h, r, x0, vm - vp, c, k, xu);
    for (it = 0; ok && it < ECMRT_EST_ITER; it++) {
        xu[0] = ecmrt_est_f32_clamp(xu[0]);
#if ECMRT_FX_HYST
        xu[ECMRT_EST_IH] = ecmrt_est_f32_clamp_h(xu[ECMRT_EST_IH]);
#endif
        if (ecmrt_est_f32_abs(xu[0] - x0[0]) < ECMRT_EST_ITER_SOC) {
            break;
        }
        ecmrt_est_f32_params(m, s, dir, xu[0], p, 0);
#if ECMRT_EST_OFFSET
        L->rb0 = p->r0;
#if ECMRT_FX_ARR
        L->rb0 = L->rb0 * L->fa;
#endif
#endif
#if ECMRT_FX_CDR || ECMRT_FX_ARR
        ecmrt_est_f32_fx(p, L->gc, L->fa, 0);
#endif
        ecmrt_est_f32_h_soc(m, nz, s, dir, xu[0], P, i, p, L);
        e = vm - ecmrt_est_f32_voltage(m, dir, p, i, xu);
        for (u = 0u; u < ECMRT_EST_N; u++) {
            e = e - L->h[u] * (x0[u] - xu[u]);
        }
        ok = ecmrt_est_f32_gain(P, L->h, r, x0, e, c, k, xn);
        if (ok) {
            da = ecmrt_est_f32_abs(xn[0] - xu[0]);
            for (u = 0u; u < ECMRT_EST_N; u++) {
                xu[u] = xn[u];
            }
            if (da < ECMRT_EST_ITER_TOL) {
                break;
            }
        }
    }
    return ok && ecmrt_est_f32_joseph(P, k, c, L->h, r, xu);
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
    const unsigned dir = s->charging;
    const float ai = i < 0.0f ? -i : i;
    ecmrt_est_f32_lin_t L;
    ecmrt_est_f32_par_t p;
    ecmrt_est_f32_vec_t x0, xu;
    const float *br;
    float wt, r;
    unsigned u;

    /* 1. F and Q, at the new SOC (where the step looked its tables up), row by row */
    ecmrt_est_f32_state(s, ob, x0);
    br = ecmrt_est_f32_branch(m, s, dir, &wt);
#if ECMRT_SURFACE
    p.up = pr->u[3];
    for (u = 0u; u < ECMRT_EST_N; u++) {
        L.g[u] = 0.0f;
    }
#endif
    ecmrt_est_f32_factors(m, s, dir, x0[0], ai, temp, dt, br, wt, &p, &L);
    /* the RC noise's factor: s^2 / (s^2 + P_soc) with polarization_soc_sigma s (pol_s2 =
     * s^2), 1 without: while the SOC is far less certain than s, a slow voltage offset is
     * taken as SOC error rather than as polarisation */
    L.ps = nz->pol_s2 > 0.0f ? nz->pol_s2 / (nz->pol_s2 + P[0]) : 1.0f;
    ecmrt_est_f32_rows_rc(nz, s, dir, pr, i, dt, &p, &L);
    ecmrt_est_f32_row_diff(nz, s, dir, br, wt, i, dt, &L);
    ecmrt_est_f32_row_xrc(m, nz, i, dt, &L);
    ecmrt_est_f32_row_hyst(m, nz, dir, pr, i, ai, dt, &L);
    ecmrt_est_f32_rows_soc(m, nz, ai, dt, &L);        /* last: no noise at all for dt <= 0 */
    if (*first == 1u) {             /* (2: a rested start, as start_a = 0) */
        ecmrt_est_f32_start_noise(m, nz, &p, &L);
    }
    /* 2. P = F P F^T + Q */
    ecmrt_est_f32_predict(P, &L);
    /* 3. the measurement: h = dv/dx (its SOC entry at the predicted P), R */
    for (u = 1u; u < ECMRT_EST_N; u++) {
        L.h[u] = 1.0f;
    }
#if ECMRT_FX_HYST
    L.h[ECMRT_EST_IH] = m->h_m;
#endif
    ecmrt_est_f32_h_soc(m, nz, s, dir, x0[0], P, i, &p, &L);
    r = ecmrt_est_f32_r(m, nz, &p, &L, first, eta, dt, vp, vm);
    /* 4. the update, iterated while it moves the SOC; applied only when all of it is finite */
    if (r > 0.0f && ecmrt_est_f32_correct(m, nz, s, dir, P, &p, &L, x0, i, r, vp, vm, xu)) {
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
    s->soc = ecmrt_est_f32_clamp(x0[0]);
    s->soc_c = 0.0f;          /* the filter's SOC is its estimate, not a compensated sum */
    (void)temp;
    (void)ob;
}

#endif /* ECMRT_EST_F32_H */
