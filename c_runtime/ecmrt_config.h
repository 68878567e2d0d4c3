/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_config.h - ecmgen C runtime: the one list of the runtime's compile-time switches
 * (hand-written, model-independent). The generator reads the list from this file
 * (ecmgen.c.spec.SWITCHES), so it is written down once.
 *
 * A generated <prefix>_ecm_<s>_config.h defines ECMRT_STATE (the model's state type,
 * <prefix>_state_<s>_t) and every switch below to 0 or 1, then includes ecmrt_f32.h or
 * ecmrt_q.h, which include this file first. A switch that is 0 compiles its code away, so
 * a plain model (all 0 but ECMRT_VARIABLE_DT) compiles to the 2RC step alone.
 *
 *   switch             1 means                                       state fields it adds
 *   ECMRT_VARIABLE_DT  step(state, i, T, dt), c = 1 - exp(-dt/tau) at run time; 0: step(state,
 *                      i, T), D = 1/(1 - exp(-dt/tau)) precomputed for the build's dt
 *   ECMRT_TEMP         tables over (temperature, SOC), one temperature grid m->t
 *                                                     t_in, w_t, k_t, pc[], pc_key (+ oc[2],
 *                                                     oc_key unless ECMRT_OCV_SHARED)
 *   ECMRT_OCV_SHARED   the OCV is the last parameter of the RC tables' rows (their SOC grid,
 *                      segment and weight)                           (no k_ocv)
 *   ECMRT_RC_UNIFORM   both directions' SOC grids are uniform: O(1) lookup (no k_dir[])
 *   ECMRT_OCV_UNIFORM  the OCV's own SOC grid is uniform: likewise    (no k_ocv)
 *   ECMRT_TAU_T        every time constant depends on the temperature only: one value per
 *                      temperature row (table tk), the step's coefficients kept in the state
 *                                                                    kc[2][2 or 3]
 *   ECMRT_TAU_SAME     (with ECMRT_TAU_T) both directions have the same time constants
 *                                                                    kc[1][2 or 3]
 *   ECMRT_DIFF         diffusion RC pair, r_diff and tau_diff per temperature   u_diff
 *   ECMRT_BV           Butler-Volmer fast branch: r_fast times asinh(x)/x, x = |i| / i0(T)
 *   ECMRT_FX_HYST      effect hysteresis                                        h
 *   ECMRT_FX_XRC       effect extra_rc                                          u_x
 *   ECMRT_FX_CDR       effect current_dependent_resistance
 *   ECMRT_FX_ARR       effect temperature_dependence (Arrhenius factor on r0, r_fast, r_slow)
 *   ECMRT_SURFACE      (with ECMRT_DIFF, never ECMRT_OCV_SHARED) the RC tables read at the
 *                      surface SOC clamp(soc + sv u_diff, 0, 1), sv = lam / max(dOCV/dSOC,
 *                      0.3 V) a table on the OCV's grid (fixed point: ECMRT_Q_SV, ecmrt_q.h)
 *   ECMRT_AGE          (optional: 0 unless defined) an ageing law: set_age(state, equivalent
 *                      full cycles) scales every resistance and the capacity  age_r, k_soc
 * capacity_error needs no switch: the generator folds it into k_soc.
 */
#ifndef ECMRT_CONFIG_H
#define ECMRT_CONFIG_H

#include "ecmrt.h"

#if !defined(ECMRT_STATE)
#error "ECMRT_STATE (the model's state type) is defined by a generated <prefix>_ecm_<s>_config.h"
#endif
/* the switches, in the generator's order */
#if !defined(ECMRT_VARIABLE_DT) || !defined(ECMRT_TEMP) || !defined(ECMRT_OCV_SHARED) || \
    !defined(ECMRT_RC_UNIFORM) || !defined(ECMRT_OCV_UNIFORM) || !defined(ECMRT_TAU_T) || \
    !defined(ECMRT_TAU_SAME) || !defined(ECMRT_DIFF) || !defined(ECMRT_BV) || \
    !defined(ECMRT_FX_HYST) || !defined(ECMRT_FX_XRC) || !defined(ECMRT_FX_CDR) || \
    !defined(ECMRT_FX_ARR) || !defined(ECMRT_SURFACE)
#error "the runtime needs every ECMRT_* switch of a generated <prefix>_ecm_<s>_config.h"
#endif
/* the optional switches: 0 where a generated config does not define them (the generator
 * writes them only when 1, so that the C of a model without them stays as it was) */
#if !defined(ECMRT_AGE)
#define ECMRT_AGE 0
#endif
#if ECMRT_SURFACE && (!ECMRT_DIFF || ECMRT_OCV_SHARED)
#error "ECMRT_SURFACE needs ECMRT_DIFF and the OCV's own grid"
#endif
#if ECMRT_TAU_SAME && !ECMRT_TAU_T
#error "ECMRT_TAU_SAME needs ECMRT_TAU_T"
#endif

#endif /* ECMRT_CONFIG_H */
