/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32.h - ecmgen C runtime: the extended Kalman filter (SOC estimator) on the
 * model's own float32 step, TinyEKF-style (hand-written, model-independent): the generic
 * prediction and iterated Joseph update of ECMRT_EST_N states here, the model's side - its
 * F, Q and H rows, h(x) and R, one small unit per state - in ecmrt_est_f32_rows.h, the
 * table accessor's units in ecmrt_est_f32_tables.h.
 *
 * Included by a generated <prefix>_est_f32.c (`[c] estimator = "ekf"`) after the model's
 * <prefix>_ecm_f32_config.h and the definition of ECMRT_EST_N (the number of states). The
 * generated code calls the units of the states its model has; its <prefix>_est_step_f32()
 *     sanitises i and dt as the step does (ecmrt_est_f32_inputs), keeps the RC voltages;
 *     calls <prefix>_step_f32(), the model's own step: the predicted state and voltage;
 *     linearises that step at the state before it (F, Q), predicts P = F P F^T + Q
 *     (ecmrt_est_f32_predict), and updates with the measured voltage (iterated,
 *     ecmrt_est_f32_gain; Joseph form, ecmrt_est_f32_joseph).
 * The filter is the one of src/ecmgen/estimate/ekf.py (states soc, u_fast, u_slow and, in
 * this order, u_diff, u_x, h, the current offset - those the model has), operation for
 * operation mirrored in float32 by src/ecmgen/c/estref.py (bit-identical results, checked
 * through cffi and under QEMU):
 *
 *   F = d step / d x at the state before the step (a_j = 1 - c_j on the diagonal, the SOC
 *       column through the tables' SOC slopes at the new SOC; u_x and h have no SOC
 *       slope: a_x = 1 - c_x, a_h = 1 - c_h, the step's own coefficients), P = F P F^T + Q;
 *   at the first sample Q also carries the RC voltages' start variance (r_j start_a)^2;
 *   H = [dOCV/dsoc + dr0/dsoc g f i, 1, 1 (, 1) (, 1) (, m_v)] (with ocv_slope_spread
 *       dOCV/dsoc is the secant over soc +- ocv_k sqrt(P_soc) after the predict, clamped
 *       to [0, 1], in every relinearisation too), R from the model error (of the
 *       overpotential, or of the one held in *eta when that is larger: mem_k > 0), the
 *       current offset through the resistances (offset_a (r0 + sum r_j), without the
 *       offset state) and its correlation time (R = 0: the sample carries no
 *       information, e.g. dt = 0; but with start_a = 0 the first sample counts fully, the
 *       cell taken rested); without resistance slopes the RC tables' SOC slopes are taken
 *       as 0 in F and H; the RC noise times pol_s2 / (pol_s2 + P_soc) when pol_s2 > 0; the
 *       resistances and their SOC slopes times the effects' factors
 *       (current_dependent_resistance g on r0 and r_fast, temperature_dependence f on r0,
 *       r_fast and r_slow, as the step);
 *   K = P H^T / (H P H^T + R), iterated (relinearised at the updated SOC, at most 5 times)
 *       while the update moves the SOC by more than 1e-3; Joseph form
 *       P = (I - K H) P (I - K H)^T + R K K^T, then exactly symmetric; SOC to [0, 1], h to
 *       [-1, 1].
 * A reading that is NaN, inf or beyond +-1 kV, and an update that would leave the state or
 * the covariance not finite, are not applied: the sample only predicts.
 *
 * With the offset state the current sensor's offset is a state too (last; the caller's
 * <prefix>_est_t holds it): the step runs on i - offset, F gets the offset column (d x' /
 * d offset = -(d x' / d i), through the effects' and the Butler-Volmer branch's d(i g)/di)
 * and H its entry -r0 d(i g0)/di, as ecmgen.estimate.process.
 * With the surface SOC the step reads its RC tables at soc_s = clamp(soc + sv u_diff, 0, 1)
 * (u_diff before the step): the accessor reads them there too, the tables' SOC slopes are
 * chained through d soc_s / d soc = 1 + dsv/dsoc u_diff, and F gets a u_diff column g
 * (d u_j' / d u_diff = d u_j' / d soc_s * sv; 0 where clamped), as ecmgen.estimate.process.
 * No fixed dt: the generator refuses it (capacity_error is in the step's k_soc and needs
 * nothing here).
 */
#ifndef ECMRT_EST_F32_H
#define ECMRT_EST_F32_H

#include "ecmrt_f32.h"

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

/* a vector over the filter's states */
typedef float ecmrt_est_f32_vec_t[ECMRT_EST_N];

/* What the update needs from before the step. */
typedef struct {
    float u[ECMRT_EST_N];     /* u[0] unused; the RC voltages (and h) before the step */
} ecmrt_est_f32_prior_t;

/* Before the model's step: i and dt sanitised exactly as the step does (so that the filter
 * uses the step's own inputs; the step's sanitising is then a no-op). */
static inline void ecmrt_est_f32_inputs(float i_max, float *i, float *dt)
{
    union {
        uint32_t u;
        float f;
    } bits;
    if (!(*i >= -i_max)) {
        *i = (*i == *i) ? -i_max : 0.0f;
    } else if (*i > i_max) {
        *i = i_max;
    }
    bits.f = *dt;
    if (bits.u - 1u >= 0x46FFFE00u) {
        *dt = (*dt > 0.0f) ? ECMRT_F32_DT_MAX : 0.0f;
    }
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

/* the hysteresis state into [-1, 1] (NaN stays NaN: the finiteness check refuses it) */
static inline float ecmrt_est_f32_clamp_h(float h)
{
    if (h < -1.0f) {
        return -1.0f;
    }
    return h > 1.0f ? 1.0f : h;
}

static inline float ecmrt_est_f32_abs(float x)
{
    return x < 0.0f ? -x : x;
}

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

/* P = F P F^T + Q, F = diag(a) + f e_0^T (+ o e_io^T) (+ g e_ig^T), Q = diag(q), exactly
 * symmetric: o (the offset state's column, io its index) and g (the surface SOC's u_diff
 * column, ig = 3) are the model's extra columns of F, a null pointer where it has none */
static inline void ecmrt_est_f32_predict(float *P, const float *a, const float *f,
                                         const float *q, const float *o, unsigned io,
                                         const float *g, unsigned ig)
{
    float fp[ECMRT_EST_N * ECMRT_EST_N];
    unsigned u, v;
    float r;
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = 0u; v < ECMRT_EST_N; v++) {
            fp[ECMRT_EST_N * u + v] = a[u] * P[ECMRT_EST_N * u + v] + f[u] * P[v];
            if (o) {
                fp[ECMRT_EST_N * u + v] = fp[ECMRT_EST_N * u + v] + o[u] * P[ECMRT_EST_N * io + v];
            }
            if (g) {
                fp[ECMRT_EST_N * u + v] = fp[ECMRT_EST_N * u + v] + g[u] * P[ECMRT_EST_N * ig + v];
            }
        }
    }
    ECMRT_EST_UNROLL
    for (u = 0u; u < ECMRT_EST_N; u++) {
        ECMRT_EST_UNROLL
        for (v = u; v < ECMRT_EST_N; v++) {
            r = a[v] * fp[ECMRT_EST_N * u + v] + f[v] * fp[ECMRT_EST_N * u];
            if (o) {
                r = r + o[v] * fp[ECMRT_EST_N * u + io];
            }
            if (g) {
                r = r + g[v] * fp[ECMRT_EST_N * u + ig];
            }
            if (u == v) {
                r = r + q[u];
            }
            P[ECMRT_EST_N * u + v] = r;
            P[ECMRT_EST_N * v + u] = r;
        }
    }
}

#include "ecmrt_est_f32_tables.h"   /* the table accessor's units */
#include "ecmrt_est_f32_rows.h"     /* the model's rows of F, Q and H, h(x), R: one unit per state */

#endif /* ECMRT_EST_F32_H */
