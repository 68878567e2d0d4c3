/*
 * ecmrt_f32_fx.h - ecmgen C runtime, numeric = "float", for models that carry diagnose
 * effects (src/ecmgen/effects.py). Included by a generated <prefix>_ecm.c instead of
 * ecmrt_f32.h (which it includes) after it defines ECMRT_VARIABLE_DT and
 *     ECMRT_FX_HYST  1: hysteresis (state h)
 *     ECMRT_FX_XRC   1: extra_rc (state u_x)
 *     ECMRT_FX_CDR   1: current_dependent_resistance (r0, r_fast scaled by g(|i|))
 * (capacity_error needs no code: it is folded into k_soc by the generator.)
 *
 * The step is ecmrt_f32_step() with these additions, in this order of operations
 * (mirrored line by line in ecmgen.cref.simulate_f32):
 *   3'. g = scale * asinh(x) / x, x = max(|i| inv_i0, 1e-12);  r0 = r0 g;  r_fast = r_fast g
 *   4'. hysteresis: s = +1 charging / -1 discharging (the model's direction);
 *       c_h = 1 - exp(-(|i| dt) k_h)  (variable dt; k_h = 1/(3600 decay_ah))
 *       c_h = 1 - exp(-|i| k_h)       (fixed dt;    k_h = dt/(3600 decay_ah));
 *       h = h + c_h (s - h);  v_h = m (h - h_ref) + m0 (s - h_ref)
 *       extra_rc: u_x = u_x + c_x (r_x i - u_x), c_x = 1 - exp(-dt/tau_x) (variable dt)
 *       or u_x = u_x + (r_x i - u_x) / D_x, D_x = 1/(1 - exp(-dt/tau_x)) (fixed dt)
 *   5'. v = base + (v_h + u_x)   (each term only when its effect is present)
 * Only + - * / on float; exp, log and sqrt are built from them here (no libm).
 */
#ifndef ECMRT_F32_FX_H
#define ECMRT_F32_FX_H

#include "ecmrt_f32.h"
#include "ecmrt_fx.h"

#if ECMRT_FX_VERSION != 1
#error "ecmrt_f32_fx.h does not match ecmrt_fx.h"
#endif
#if !defined(ECMRT_FX_HYST) || !defined(ECMRT_FX_XRC) || !defined(ECMRT_FX_CDR)
#error "define ECMRT_FX_HYST, ECMRT_FX_XRC and ECMRT_FX_CDR (0 or 1) before including ecmrt_f32_fx.h"
#endif

typedef struct {
    ecmrt_f32_model_t base;   /* k_soc already includes any capacity_error factor */
    float h_init;             /* hysteresis: initial_state */
    float h_k;                /* 1/(3600 decay_ah) per A*s (variable dt) or dt/(3600 decay_ah) per A */
    float h_m;                /* m_v, V */
    float h_m0;               /* m0_v, V */
    float h_ref;              /* ocv_table_state */
    float x_r;                /* extra_rc: r_ohm */
    float x_k;                /* tau_s (variable dt) or D = 1/(1 - exp(-dt/tau_s)) (fixed dt) */
    float g_scale;            /* current_dependent_resistance: scale_at_zero */
    float g_inv_i0;           /* 1 / i0_a */
} ecmrt_f32_fx_model_t;

#if ECMRT_FX_CDR
/* sqrt(w) for 1 <= w < 2^100: bit-trick start, four Newton steps (deterministic, <= 1 ulp) */
static inline float ecmrt_f32_fx_sqrt(float w)
{
    union {
        uint32_t u;
        float f;
    } bits;
    float r;
    bits.f = w;
    bits.u = (bits.u >> 1) + 0x1FBD1DF5u;
    r = bits.f;
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    r = 0.5f * (r + w / r);
    return r;
}

/* log(1 + y) for 0 <= y < 2^100: 1 + y = 2^n m, m in [sqrt(1/2), sqrt(2)) (n = 0 and
 * m - 1 = y exactly below sqrt(2) - 1), log = n ln2 + 2 atanh(f / (2 + f)), f = m - 1,
 * atanh by its series to t^13 (|t| < 0.172: error < 1e-9 relative). */
static inline float ecmrt_f32_fx_log1p(float y)
{
    union {
        uint32_t u;
        float f;
    } bits;
    int32_t n;
    float f, t, t2, p;
    if (y < 0.414213568f) {
        n = 0;
        f = y;
    } else {
        bits.f = 1.0f + y;
        n = (int32_t)((bits.u >> 23) & 0xFFu) - 127;
        bits.u = (bits.u & 0x007FFFFFu) | 0x3F800000u;   /* m in [1, 2) */
        f = bits.f;
        if (f > 1.41421354f) {
            f = f * 0.5f;
            n = n + 1;
        }
        f = f - 1.0f;
    }
    t = f / (2.0f + f);
    t2 = t * t;
    p = 7.69230798e-02f;                    /* 1/13 */
    p = 9.09090936e-02f + t2 * p;           /* 1/11 */
    p = 1.11111112e-01f + t2 * p;           /* 1/9 */
    p = 1.42857149e-01f + t2 * p;           /* 1/7 */
    p = 2.00000003e-01f + t2 * p;           /* 1/5 */
    p = 3.33333343e-01f + t2 * p;           /* 1/3 */
    p = (2.0f * t) + (2.0f * t) * (t2 * p);
    if (n == 0) {
        return p;
    }
    return ((float)n * 0.693145752f + p) + (float)n * 1.42860677e-06f;
}

/* g = scale asinh(x) / x, x = max(|i| inv_i0, 1e-12); asinh(x) = log1p(x + x^2/(sqrt(x^2+1)+1)) */
static inline float ecmrt_f32_fx_cdr_factor(const ecmrt_f32_fx_model_t *m, float ai)
{
    float x = ai * m->g_inv_i0;
    float x2, y;
    if (!(x > 1.0e-12f)) {
        x = 1.0e-12f;
    }
    x2 = x * x;
    y = x + x2 / (ecmrt_f32_fx_sqrt(x2 + 1.0f) + 1.0f);
    return (m->g_scale * ecmrt_f32_fx_log1p(y)) / x;
}
#endif

static inline void ecmrt_f32_fx_init(const ecmrt_f32_fx_model_t *m, ecmrt_f32_fx_state_t *s,
                                     float soc0)
{
    if (soc0 != soc0) {
        soc0 = 0.0f;
    } else if (soc0 < ECMRT_F32_SOC_MIN) {
        soc0 = ECMRT_F32_SOC_MIN;
    } else if (soc0 > ECMRT_F32_SOC_MAX) {
        soc0 = ECMRT_F32_SOC_MAX;
    }
    s->soc = soc0;
    s->soc_c = 0.0f;
    s->u_fast = 0.0f;
    s->u_slow = 0.0f;
    s->charging = (uint8_t)ECMRT_DISCHARGE;
    s->k_ocv = 0u;
    s->k_dir[0] = 0u;
    s->k_dir[1] = 0u;
    s->h = m->h_init;
    s->u_x = 0.0f;
}

/* One step of the 2RC model with effects; as ecmrt_f32_step() plus the lines marked fx. */
#if ECMRT_VARIABLE_DT
static inline float ecmrt_f32_fx_step(const ecmrt_f32_fx_model_t *fm, ecmrt_f32_fx_state_t *s,
                                      float i, float dt)
#else
static inline float ecmrt_f32_fx_step(const ecmrt_f32_fx_model_t *fm, ecmrt_f32_fx_state_t *s,
                                      float i)
#endif
{
    const ecmrt_f32_model_t *m = &fm->base;
    const ecmrt_f32_dir_t *d;
    const float *row;
    unsigned dir;
    float soc, y, w, r0, rf, rs, uf, us, ocv, v;
#if ECMRT_VARIABLE_DT
    float cf, cs;
#else
    float df, ds;
#endif
#if ECMRT_FX_HYST || ECMRT_FX_CDR
    float ai;
#endif
#if ECMRT_FX_HYST
    float sg, ch, h, vh;
#endif
#if ECMRT_FX_XRC
    float ux;
#endif
#if ECMRT_FX_CDR
    float g;
#endif

    if (i != i) {
        i = 0.0f;
    } else if (i > m->i_max_a) {
        i = m->i_max_a;
    } else if (i < -m->i_max_a) {
        i = -m->i_max_a;
    }
#if ECMRT_VARIABLE_DT
    if (!(dt > 0.0f)) {
        dt = 0.0f;
    } else if (dt > ECMRT_F32_DT_MAX) {
        dt = ECMRT_F32_DT_MAX;
    }
#endif
#if ECMRT_FX_HYST || ECMRT_FX_CDR
    ai = i < 0.0f ? -i : i;                                        /* fx */
#endif
    if (i > m->deadband_a) {
        s->charging = (uint8_t)ECMRT_CHARGE;
    } else if (i < -m->deadband_a) {
        s->charging = (uint8_t)ECMRT_DISCHARGE;
    }
    dir = s->charging;
#if ECMRT_VARIABLE_DT
    y = (i * dt) * m->k_soc - s->soc_c;
#else
    y = i * m->k_soc - s->soc_c;
#endif
    soc = s->soc + y;
    s->soc_c = (soc - s->soc) - y;
    if (soc < ECMRT_F32_SOC_MIN) {
        soc = ECMRT_F32_SOC_MIN;
        s->soc_c = 0.0f;
    } else if (soc > ECMRT_F32_SOC_MAX) {
        soc = ECMRT_F32_SOC_MAX;
        s->soc_c = 0.0f;
    }
    s->soc = soc;
    d = &m->dir[dir];
    w = ecmrt_f32_locate(&d->g, soc, &s->k_dir[dir]);
    row = d->rows + ECMRT_NPAR * (unsigned)s->k_dir[dir];
    r0 = ecmrt_f32_lerp(row + ECMRT_P_R0, w);
    rf = ecmrt_f32_lerp(row + ECMRT_P_RF, w);
    rs = ecmrt_f32_lerp(row + ECMRT_P_RS, w);
#if ECMRT_FX_CDR
    g = ecmrt_f32_fx_cdr_factor(fm, ai);                           /* fx 3' */
    r0 = r0 * g;
    rf = rf * g;
#endif
#if ECMRT_VARIABLE_DT
    cf = ecmrt_f32_one_minus_exp_neg(dt / ecmrt_f32_lerp(row + ECMRT_P_KF, w));
    cs = ecmrt_f32_one_minus_exp_neg(dt / ecmrt_f32_lerp(row + ECMRT_P_KS, w));
#else
    df = ecmrt_f32_lerp(row + ECMRT_P_KF, w);
    ds = ecmrt_f32_lerp(row + ECMRT_P_KS, w);
#endif
    w = ecmrt_f32_locate(&m->ocv_g, soc, &s->k_ocv);
    ocv = ecmrt_f32_lerp(m->ocv + 2u * (unsigned)s->k_ocv, w);
    uf = s->u_fast;
    us = s->u_slow;
#if ECMRT_VARIABLE_DT
    uf = uf + cf * (rf * i - uf);
    us = us + cs * (rs * i - us);
#else
    uf = uf + (rf * i - uf) / df;
    us = us + (rs * i - us) / ds;
#endif
    s->u_fast = uf;
    s->u_slow = us;
#if ECMRT_FX_HYST
    sg = dir == ECMRT_CHARGE ? 1.0f : -1.0f;                       /* fx 4' */
#if ECMRT_VARIABLE_DT
    ch = ecmrt_f32_one_minus_exp_neg((ai * dt) * fm->h_k);
#else
    ch = ecmrt_f32_one_minus_exp_neg(ai * fm->h_k);
#endif
    h = s->h;
    h = h + ch * (sg - h);
    s->h = h;
    vh = fm->h_m * (h - fm->h_ref) + fm->h_m0 * (sg - fm->h_ref);
#endif
#if ECMRT_FX_XRC
    ux = s->u_x;
#if ECMRT_VARIABLE_DT
    ux = ux + ecmrt_f32_one_minus_exp_neg(dt / fm->x_k) * (fm->x_r * i - ux);
#else
    ux = ux + (fm->x_r * i - ux) / fm->x_k;
#endif
    s->u_x = ux;
#endif
    v = ((ocv + r0 * i) + uf) + us;
#if ECMRT_FX_HYST && ECMRT_FX_XRC
    v = v + (vh + ux);                                             /* fx 5' */
#elif ECMRT_FX_HYST
    v = v + vh;
#elif ECMRT_FX_XRC
    v = v + ux;
#endif
    return v;
}

#endif /* ECMRT_F32_FX_H */
