/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_f32_step.h - ecmgen C runtime, numeric = "float": the step's units, one static
 * inline function per stage and per effect (hand-written, model-independent).
 *
 * Included by ecmrt_f32.h (after its lookups and maths), never on its own. Each unit takes
 * the tables, constants and state fields it reads as arguments; the generated
 * <prefix>_step_f32() calls those of its model in a fixed order (the order below), so a model
 * without an effect has no trace of it and adding an effect is one unit here and one call in
 * the step's template (templates/ecm_step_f32.c.j2). Mirrored by src/ecmgen/c/cref.py
 * (simulate_f32) operation for operation; src/ecmgen/model/simulate.py and effects.py define
 * the step in float64, in the same order.
 */
#ifndef ECMRT_F32_STEP_H
#define ECMRT_F32_STEP_H

/* 0. the current saturated to [-i_max, i_max] (NaN counts as 0 A) */
static inline float ecmrt_f32_clamp_current(float i, float i_max)
{
    if (!(i >= -i_max)) {
        i = (i == i) ? -i_max : 0.0f;       /* below the range, or NaN */
    } else if (i > i_max) {
        i = i_max;
    }
    return i;
}

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

/* 1. the direction, with a deadband that keeps the last one */
static inline unsigned ecmrt_f32_direction(unsigned dir, float i, float deadband)
{
    if (i > deadband) {
        dir = ECMRT_CHARGE;
    } else if (i < -deadband) {
        dir = ECMRT_DISCHARGE;
    }
    return dir;
}

/* 2. the SOC *soc after charge q (A s, or A with fixed dt) times k_soc: a Kahan-compensated
 *    sum (*soc_c its compensation), so that a long run of equal small increments does not
 *    drift; saturated to [SOC_MIN, SOC_MAX] */
static inline float ecmrt_f32_count(float *soc_p, float *soc_c, float q, float k_soc)
{
    union {
        uint32_t u;
        float f;
    } bits;
    const float y = q * k_soc - *soc_c;
    float soc = *soc_p + y;
    *soc_c = (soc - *soc_p) - y;
    bits.f = soc;
    if ((bits.u & 0x7FFFFFFFu) > 0x40000000u) {     /* |soc| > 2 = ECMRT_F32_SOC_MAX, or NaN */
        if (soc < ECMRT_F32_SOC_MIN) {
            soc = ECMRT_F32_SOC_MIN;
            *soc_c = 0.0f;
        } else if (soc > ECMRT_F32_SOC_MAX) {
            soc = ECMRT_F32_SOC_MAX;
            *soc_c = 0.0f;
        }
    }
    *soc_p = soc;
    return soc;
}

/* 3. the temperature's row (*kt) and weight (*wt) on the grid g: kept with the temperature
 *    they belong to (*t_in its bits, *w_t the weight), so that a temperature read less often
 *    than the step runs is searched once (exact: both are a function of the temperature; a
 *    corrupted k_t is clamped where it is used). Returns 1 for a new temperature: what the
 *    step keeps for the last one (the segment's pairs, the time constants' coefficients) is
 *    then renewed by the caller. */
static inline int ecmrt_f32_temperature(const ecmrt_f32_grid_t *g, float temp, uint32_t *t_in,
                                        float *w_t, unsigned *kt, float *wt)
{
    union {
        uint32_t u;
        float f;
    } bits;
    bits.f = temp;
    if (bits.u == *t_in) {
        *wt = *w_t;
        return 0;
    }
    *wt = ecmrt_f32_locate(g, temp, kt);
    *t_in = bits.u;
    *w_t = *wt;
    return 1;
}

/* 3. the surface SOC the RC tables are read at: soc + sv u_diff (u_diff of the previous
 *    step, sv = lam / max(dOCV/dSOC, 0.3 V) at (soc, T), interpolated as the OCV), clamped
 *    to [0, 1] (NaN: 0) */
static inline float ecmrt_f32_surface(float soc, float sv, float u_diff)
{
    float r = soc + sv * u_diff;
    if (!(r >= 0.0f)) {
        r = 0.0f;
    } else if (r > 1.0f) {
        r = 1.0f;
    }
    return r;
}

/* 3'. parameter effects and the Butler-Volmer branch, in this order */

/* current_dependent_resistance: r0, r_fast times scale asinh(x)/x, x = max(|i| inv_i0, 1e-12) */
static inline void ecmrt_f32_fx_cdr(float scale, float inv_i0, float ai, float *r0, float *rf)
{
    float x = ai * inv_i0;
    float g = scale * ecmrt_f32_asinh(&x);
    g = g / x;
    *r0 = *r0 * g;
    *rf = *rf * g;
}

/* temperature_dependence: r0, r_fast, r_slow times the Arrhenius factor */
static inline void ecmrt_f32_fx_arr(float a_k, float inv_ref, float temp, float *r0, float *rf,
                                    float *rs)
{
    const float f = ecmrt_f32_arrhenius(a_k, inv_ref, temp);
    *r0 = *r0 * f;
    *rf = *rf * f;
    *rs = *rs * f;
}

/* the Butler-Volmer fast branch: r_fast asinh(x)/x, x = max(|i|/i0(T), 1e-12) */
static inline void ecmrt_f32_bv(float i0, float ai, float *rf)
{
    float x = ai / i0;
    const float g = ecmrt_f32_asinh(&x);
    *rf = *rf * (g / x);
}

/* the cell's age (ecmrt_f32_age): every resistance times its scale */
static inline void ecmrt_f32_age_r(float age_r, float *r0, float *rf, float *rs)
{
    *r0 = *r0 * age_r;
    *rf = *rf * age_r;
    *rs = *rs * age_r;
}

/* 3''. the OCV at weight w of segment ko of its own table at the temperature (row kt of the
 *     nt rows, weight wt; n points per row): the segment's pair at the temperature kept in
 *     *oc with its key *oc_key (the SOC moves little between steps) */
static inline float ecmrt_f32_ocv(const float *ocv, unsigned n, unsigned nt, unsigned kt, float wt,
                                  unsigned ko, float w, float *oc, uint8_t *oc_key)
{
    if (ko != *oc_key) {
        ecmrt_f32_segment(ocv + 2u * (n * ECMRT_ROW(kt, nt) + ko), 2u, 2u, wt, oc);
        *oc_key = (uint8_t)ko;
    }
    return ecmrt_f32_lerp(oc, w);
}

/* 4. exact ZOH of one RC pair (the fast, slow and diffusion pairs, extra_rc's): u = a u +
 *    r (1 - a) i, written u + c (r i - u) with c = 1 - a = 1 - exp(-dt/tau) (variable dt, or
 *    the state's coefficient of a time constant of the temperature only) ... */
static inline float ecmrt_f32_zoh(float u, float r, float i, float c)
{
    return u + c * (r * i - u);
}

/* ... or u + (r i - u) / D with D = 1/c from the tables (fixed dt) */
static inline float ecmrt_f32_zoh_d(float u, float r, float i, float d)
{
    return u + (r * i - u) / d;
}

/* 4', 5'. voltage effects: each updates its state and returns its term of the voltage */

/* hysteresis: *h moves towards the direction's sign s by 1 - exp(-x), x the charge moved
 * times h_k (|i| dt / (3600 decay_ah)); the term m (h - ref) + m0 (s - ref) */
static inline float ecmrt_f32_fx_hyst(float *h, unsigned dir, float x, float m, float m0,
                                      float ref)
{
    const float sg = dir == ECMRT_CHARGE ? 1.0f : -1.0f;
    const float ch = ecmrt_f32_one_minus_exp_neg(x);
    float hh = *h;
    hh = hh + ch * (sg - hh);
    *h = hh;
    return m * (hh - ref) + m0 * (sg - ref);
}

/* the hysteresis term m (h - ref) + m0 (s - ref) at a state h (the filter's h(x)) */
static inline float ecmrt_f32_hyst_v(float h, unsigned dir, float m, float m0, float ref)
{
    return m * (h - ref) + m0 * ((dir == ECMRT_CHARGE ? 1.0f : -1.0f) - ref);
}

#endif /* ECMRT_F32_STEP_H */
