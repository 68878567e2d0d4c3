/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_est_f32_tables.h - ecmgen C runtime: the units of the SOC estimator's table accessor
 * (hand-written, model-independent). Included by ecmrt_est_f32.h. The generated accessor
 * (<prefix>_est_params in <prefix>_est_f32.c) reads the values and SOC slopes of the model's
 * tables that the filter's Jacobians need, of direction dir at a SOC, at the temperature of
 * the model state's last step (its row k_t and weight w_t), by the runtime's own lookup and
 * interpolation (the step's locate, its segment pairs at the temperature from
 * ecmrt_f32_segment or the state's cache of them). A slope is that of the segment the SOC
 * is in (the segment on the right at a breakpoint) and 0 outside the table (clamped), as
 * ecmgen.estimate.process; time constants of the temperature only have none: the filter
 * takes the state's coefficients kc. The state is read, never written. Mirrored by
 * src/ecmgen/c/estref_tables.py (its Tables).
 */
#ifndef ECMRT_EST_F32_TABLES_H
#define ECMRT_EST_F32_TABLES_H

/* value y + dy w and slope dy inv of parameter j from a segment's pairs (y at its start,
 * difference to its end) along SOC at the temperature: a table row of one temperature, else
 * ecmrt_f32_segment's (the state's cache when it is that segment's: the same numbers); w the
 * weight in the segment, inv 1 / its spacing (0 outside the grid) */
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

/* the same on a uniform grid */
static inline float ecmrt_est_f32_uinv(const ecmrt_f32_ugrid_t *g, unsigned k, float v)
{
    const float u = (v - g->x0) * g->inv_h;
    (void)k;
    return (u >= 0.0f && u <= g->um) ? g->inv_h : 0.0f;
}

/* The surface SOC the step read its RC tables at: soc + sv u_diff (up: the u_diff before the
 * step), sv = a + d wo at (soc, T) as the step interpolates it from its OCV segment's pair
 * (a, d) at the temperature, clamped to [0, 1]; its derivatives *ds by soc (1 + dsv/dsoc
 * u_diff, dsv/dsoc = d invo, invo 1 / the OCV segment's spacing) and *du by u_diff (sv), 0
 * where clamped */
static inline float ecmrt_est_f32_surface(float soc, float a, float d, float wo, float invo,
                                          float up, float *ds, float *du)
{
    const float sv = a + d * wo;
    const float dsv = d * invo;
    float socr = soc + sv * up;
    if (!(socr >= 0.0f)) {
        socr = 0.0f;
        *ds = *du = 0.0f;
    } else if (socr > 1.0f) {
        socr = 1.0f;
        *ds = *du = 0.0f;
    } else {
        *ds = 1.0f + dsv * up;
        *du = sv;
    }
    return socr;
}

/* a parameter effect's factor g on a resistance the accessor read and on its SOC slope */
static inline void ecmrt_est_f32_scale(float g, float *r, float *dr)
{
    *r = *r * g;
    *dr = *dr * g;
}

#endif /* ECMRT_EST_F32_TABLES_H */
