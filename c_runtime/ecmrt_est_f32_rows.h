/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32_rows.h - ecmgen C runtime: the filter's model side, TinyEKF-style - the
 * arithmetic of the linearisation of one step of the model (F's rows and Q per state, H),
 * of h(x) and of R, in small static inline units (hand-written, model-independent).
 *
 * Included by ecmrt_est_f32.h, never on its own. The generated <prefix>_est_f32.c writes
 * its model's rows from these units, one state after another (soc, the RC pairs, u_diff,
 * u_x, h, the offset: those the model has); the prediction and the update are generic.
 * Mirrored by src/ecmgen/c/estref.py.
 */
#ifndef ECMRT_EST_F32_ROWS_H
#define ECMRT_EST_F32_ROWS_H

/* an RC pair's a = exp(-dt / tau(soc)): its SOC slope (a dt / tau^2) dtau, dtau the slope of
 * tau (a time constant of the temperature only has none) */
static inline float ecmrt_est_f32_da(float a, float dt, float tau, float dtau)
{
    return ((a * dt) / (tau * tau)) * dtau;
}

/* an RC pair's SOC column of F: u' = a u + r g (1 - a) i, c = 1 - a, da and dr the SOC slopes
 * of a and r (g the current's factor on r, 1 without) */
static inline float ecmrt_est_f32_col_rc(float da, float u, float dr, float c, float r, float g,
                                         float i)
{
    return da * u + ((dr * c - r * da) * g) * i;
}

/* an RC pair's noise: (pol r i)^2 (1 - a^2) times ps (polarization_error pol, the pair's
 * resistance r with its factors, ps the RC noise's factor s^2 / (s^2 + P_soc)) */
static inline float ecmrt_est_f32_q_rc(float pol, float r, float i, float a, float ps)
{
    const float e = (pol * r) * i;
    return ((e * e) * (1.0f - a * a)) * ps;
}

/* the first sample: an RC voltage is unknown (a record may start under load or
 * mid-relaxation), its noise q plus (r start_a)^2 with its resistance r at the start */
static inline float ecmrt_est_f32_q_start(float q, float r, float start_a)
{
    const float e = r * start_a;
    return q + e * e;
}

/* the hysteresis state's noise: sigma_h^2 (1 - a_h^2), 1 - a_h^2 written c_h (2 - c_h) */
static inline float ecmrt_est_f32_q_hyst(float p0_h, float ch)
{
    return p0_h * (ch * (2.0f - ch));
}

/* the hysteresis state's offset column: h' = a_h h + (1 - a_h) s, d h' / d i = -(h - s)
 * sign(i) c a_h, c = dt h_k = dt / (3600 decay_ah), h before the step; -(d h' / d i) */
static inline float ecmrt_est_f32_o_hyst(float h, unsigned dir, float i, float c, float a)
{
    return (((h - (dir == ECMRT_CHARGE ? 1.0f : -1.0f)) *
             (i > 0.0f ? 1.0f : (i < 0.0f ? -1.0f : 0.0f))) * c) * a;
}

/* the SOC's noise for dt > 0: the sensor's bias b = gain |i| (+ offset_a without the
 * offset state) over the drift horizon, (b k dt)^2 (horizon / dt) written (b k)^2 (dt
 * horizon) (no 0 * inf for a denormal dt), and white current noise (noise_a k dt)^2 */
static inline float ecmrt_est_f32_q_soc(float b, float k_soc, float dt, float horizon,
                                        float noise_a)
{
    const float e = b * k_soc;
    const float r = noise_a * (dt * k_soc);
    return (e * e) * (dt * horizon) + r * r;
}

/* H's SOC entry: the OCV's slope dv plus r0's dr0 (at the surface SOC: times d soc_s /
 * d soc) times i */
static inline float ecmrt_est_f32_h_soc(float dv, float dr0, float i)
{
    return dv + dr0 * i;
}

/* the OCV's secant over soc +- k sqrt(p_soc), clamped to [0, 1] (ecmgen.estimate.ekf
 * spread_slope): its ends in *lo, *hi, or 0 when H takes the tangent instead (k = 0, a
 * settled SOC, a secant narrower than ECMRT_EST_SPREAD_MIN) */
#define ECMRT_EST_SPREAD_MIN 1e-6f    /* a narrower secant (in SOC) is the tangent */
#define ECMRT_EST_P_SOC_MIN 1e-12f    /* ... and so is one of a smaller SOC variance */
static inline int ecmrt_est_f32_spread(float soc, float p_soc, float k, float *lo, float *hi)
{
    float d;
    if (!(k > 0.0f && p_soc > ECMRT_EST_P_SOC_MIN)) {
        return 0;
    }
    d = k * ecmrt_f32_sqrt(p_soc);
    *lo = soc - d;
    *hi = soc + d;
    *lo = *lo < 0.0f ? 0.0f : *lo;
    *hi = *hi > 1.0f ? 1.0f : *hi;
    return *hi - *lo > ECMRT_EST_SPREAD_MIN;
}

/* R, the model's part: the model error of the overpotential |vp - ocv| (or, mem_k > 0, of
 * the one held in *eta from before, decayed by exp(-dt / error_memory_s), when that is
 * larger; eta may be a null pointer when mem_k is 0) and the voltage noise vn2 */
static inline float ecmrt_est_f32_r_model(float vp, float ocv, float mem_k, float model_error,
                                          float vn2, float *eta, float dt)
{
    float e = vp - ocv, r;
    e = e < 0.0f ? -e : e;
    if (mem_k > 0.0f) {
        r = *eta - *eta * ecmrt_f32_one_minus_exp_neg(dt * mem_k);
        if (r > e) {
            e = r;
        }
        *eta = e;
    }
    e = model_error * e;
    return vn2 + e * e;
}

/* R plus the sensor's offset offset_a through rs, the resistance a steady error in the
 * current sees (r0 g0 + sum r_j g_j; without the offset state: with it, it is a state) */
static inline float ecmrt_est_f32_r_offset(float r, float offset_a, float rs)
{
    const float e = offset_a * rs;
    return r + e * e;
}

/* R over the error's correlation time corr_s; 0 for no measurement (vm NaN, inf, absurd). A
 * record taken to start rested (start_a = 0, or *first 2) counts its first sample fully. */
static inline float ecmrt_est_f32_r_time(float r, float corr_s, float start_a, uint8_t *first,
                                         float dt, float vm)
{
    if (!(*first == 2u || (*first != 0u && start_a == 0.0f)) && dt < corr_s) {
        r = dt > 0.0f ? r * (corr_s / dt) : 0.0f;
    }
    *first = 0u;
    if (!(vm >= -ECMRT_EST_V_MAX && vm <= ECMRT_EST_V_MAX)) {
        r = 0.0f;                                     /* no measurement (NaN, inf, absurd) */
    }
    return r;
}

#endif /* ECMRT_EST_F32_ROWS_H */
