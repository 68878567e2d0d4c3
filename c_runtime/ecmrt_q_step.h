/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_q_step.h - ecmgen C runtime, numeric = "fixed": the step's units, one static inline
 * function per stage and per effect, the same ones as ecmrt_f32_step.h in int32 Q formats
 * (hand-written, model-independent).
 *
 * Included by ecmrt_q.h (after its lookups and maths), never on its own. Each unit takes the
 * tables, constants, formats and state fields it reads as arguments; the generated
 * <prefix>_step_q() calls those of its model in a fixed order (templates/ecm_step_q.c.j2).
 * Mirrored by src/ecmgen/c/cref.py (simulate_fixed_raw) operation for operation.
 */
#ifndef ECMRT_Q_STEP_H
#define ECMRT_Q_STEP_H

/* 1. the direction, with a deadband that keeps the last one */
static inline unsigned ecmrt_q_direction(unsigned dir, int32_t i, int32_t deadband)
{
    if (i > deadband) {
        dir = ECMRT_CHARGE;
    } else if (i < -deadband) {
        dir = ECMRT_DISCHARGE;
    }
    return dir;
}

/* 2. the SOC's rate i k_soc (variable dt: times dt is the increment), |i k_soc| < 2^31
 *    after the shift sh_rate (Q_RATE holds i_max k_soc) */
static inline int32_t ecmrt_q_soc_rate(int32_t i, int32_t k_soc, int sh_rate)
{
    return (int32_t)ECMRT_RSHR((int64_t)i * k_soc, sh_rate);
}

/* 2. the SOC *soc (Q30, saturated) after the increment q, 2^sh_dsoc units = 1 LSB: formed at
 *    full precision, the part below 1 LSB carried in *soc_rem (no rounding drift) */
static inline int32_t ecmrt_q_count(int64_t *soc_rem, int32_t *soc_p, int64_t q, int sh_dsoc)
{
    const int64_t acc = *soc_rem + q;
    const int64_t dsoc = acc >> sh_dsoc;                             /* floor */
    int32_t soc;
    *soc_rem = acc & (((int64_t)1 << sh_dsoc) - 1);                  /* in [0, 2^SH_DSOC) */
    soc = ecmrt_q_sat32((int64_t)*soc_p + dsoc);
    *soc_p = soc;
    return soc;
}

/* 3. the temperature's row (*kt) and weight (*wt) on the grid g (spacings in Q(q_gt)), kept
 *    with the temperature (see ecmrt_f32_temperature; a corrupted k_t is clamped where it is
 *    used); returns 1 for a new temperature */
static inline int ecmrt_q_temperature(const ecmrt_q_grid_t *g, int32_t temp, int32_t *t_in,
                                      int32_t *w_t, unsigned *kt, int32_t *wt, int q_gt)
{
    if (temp == *t_in) {
        *wt = *w_t;
        return 0;
    }
    *wt = ecmrt_q_locate(g, temp, kt, q_gt);
    *t_in = temp;
    *w_t = *wt;
    return 1;
}

/* 3. the surface SOC (Q30) the RC tables are read at: soc + sv u_diff (u_diff of the previous
 *    step, sv >= 0 in Q_SV at (soc, T), interpolated as the OCV). The product of two int32 is
 *    formed in int64 (< 2^62), rounded half up to Q30 (shift sh = Q_SV + Q_V - 30 >= 1,
 *    checked by the generator), the sum with soc in int64, then saturated on purpose to
 *    [0, 2^30]. */
static inline int32_t ecmrt_q_surface(int32_t soc, int32_t sv, int32_t ud, int sh)
{
    const int64_t r = (int64_t)soc + ECMRT_RSHR((int64_t)sv * ud, sh);
    if (r < 0) {
        return 0;
    }
    return r > (int64_t)ECMRT_ONE30 ? ECMRT_ONE30 : (int32_t)r;
}

/* 3'. parameter effects and the Butler-Volmer branch, each scaling r i (Q_V, int64) */

/* current_dependent_resistance: r0 i, r_fast i times the g table (scale asinh(x)/x in
 * Q(q_g)) at x = |i| g_k = |i| / i0 (shifted by sh_gx to Q(q_x)) */
static inline void ecmrt_q_fx_cdr(const int32_t *g_tab, int32_t g_k, int64_t ai, int64_t *t0,
                                  int64_t *tf, int sh_gx, unsigned q_x, int q_g)
{
    const int64_t g = ecmrt_q_gtab(g_tab, (uint32_t)ecmrt_q_sat32(ECMRT_RSHR(ai * g_k, sh_gx)),
                                   q_x);
    *t0 = ECMRT_RSHR(*t0 * g, q_g);
    *tf = ECMRT_RSHR(*tf * g, q_g);
}

/* temperature_dependence: r0 i, r_fast i, r_slow i times the Arrhenius factor (Q(q_f)) */
static inline void ecmrt_q_fx_arr(int32_t a_b, int32_t a_fmax, int32_t temp, int64_t *t0,
                                  int64_t *tf, int64_t *ts, int q_b, int q_f)
{
    const int64_t g = ecmrt_q_arrhenius(a_b, a_fmax, temp, q_b);
    *t0 = ECMRT_RSHR(*t0 * g, q_f);
    *tf = ECMRT_RSHR(*tf * g, q_f);
    *ts = ECMRT_RSHR(*ts * g, q_f);
}

/* the Butler-Volmer fast branch: r_fast i times asinh(x)/x (the table bv_tab, Q30), x =
 * |i| / i0(T) in Q(q_x) (bv_k = Q_I0 - Q_I + q_x) */
static inline void ecmrt_q_bv(const int32_t *bv_tab, int32_t i0, int64_t ai, int64_t *tf,
                              unsigned bv_k, unsigned q_x)
{
    unsigned sh;
    const uint32_t r = ecmrt_q_recip((uint32_t)i0, &sh);
    const int64_t g = ecmrt_q_gtab(bv_tab, (uint32_t)ecmrt_q_sat32(ECMRT_RSHRV(ai * (int64_t)r,
                                                                               sh - bv_k)),
                                   q_x);
    *tf = ECMRT_RSHR(*tf * g, ECMRT_Q30);
}

/* the cell's age (ecmrt_q_age): every r i times its scale */
static inline void ecmrt_q_age_r(int32_t age_r, int64_t *t0, int64_t *tf, int64_t *ts,
                                 int q_ar)
{
    *t0 = ECMRT_Q_AGED(*t0, age_r, q_ar);
    *tf = ECMRT_Q_AGED(*tf, age_r, q_ar);
    *ts = ECMRT_Q_AGED(*ts, age_r, q_ar);
}

/* 3''. the OCV at weight w of segment ko of its own table at the temperature (row kt of the
 *     nt rows, weight wt; n points per row): the segment's pair at the temperature kept in
 *     *oc with its key *oc_key (the SOC moves little between steps) */
static inline int32_t ecmrt_q_ocv(const int32_t *ocv, unsigned n, unsigned nt, unsigned kt, int32_t wt,
                                  unsigned ko, int32_t w, int32_t *oc, uint8_t *oc_key)
{
    if (ko != *oc_key) {
        ecmrt_q_segment(ocv + n * ECMRT_ROW(kt, nt) + ko, 1u, 1u, n, wt, oc);
        *oc_key = (uint8_t)ko;
    }
    return ECMRT_Q_PAIR(oc, w);
}

/* 4', 5'. voltage effects: each updates its state and returns its term of the voltage */

/* hysteresis's x in Q26 at variable dt: the charge moved |i| dt times h_k = 1/(3600 decay_ah),
 * |i| h_k shifted by sh_hr and saturated, then times dt shifted by sh_hx (at fixed dt, dt is in
 * h_k and x is |i| h_k shifted by sh_hx) */
static inline int64_t ecmrt_q_hyst_x(int64_t ai, int32_t h_k, int32_t dt, int sh_hr, int sh_hx)
{
    return ECMRT_RSHR((int64_t)ecmrt_q_sat32(ECMRT_RSHR(ai * h_k, sh_hr)) * dt, sh_hx);
}

/* hysteresis: *h (Q30) moves towards the direction's sign by 1 - exp(-x), x in Q26 the charge
 *    moved times h_k; the term m (h - ref) + m0 (s - ref) in Q_V (shift sh_hm) */
static inline int64_t ecmrt_q_fx_hyst(int32_t *h, unsigned dir, int64_t x, int32_t m,
                                      int32_t m0, int32_t ref, int sh_hm)
{
    const int32_t sg = dir == ECMRT_CHARGE ? ECMRT_ONE30 : -ECMRT_ONE30;
    const int32_t hh = ECMRT_Q_RC(*h, ecmrt_q_one_minus_exp_neg_q26(x), (int64_t)sg, ECMRT_Q30);
    *h = hh;
    return ECMRT_RSHR((int64_t)m * ((int64_t)hh - ref), sh_hm) +
           ECMRT_RSHR((int64_t)m0 * ((int64_t)sg - ref), sh_hm);
}

#endif /* ECMRT_Q_STEP_H */
