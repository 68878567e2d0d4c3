/* SPDX-License-Identifier: MIT */
/*
 * ecmrt.h - ecmgen C runtime: shared constants (hand-written, model-independent); what
 * both numerics do with the model's state is ecmrt_state.h.
 *
 * The generated <prefix>_ecm.h includes this file and declares the model's own state type
 * (<prefix>_state_t, exactly the fields the model needs); the generated <prefix>_ecm.c
 * includes ecmrt_f32.h (numeric = "float") or ecmrt_q.h (numeric = "fixed"), which hold
 * the one discrete step as static inline functions, configured by macros for the
 * branches and effects the model has. Nothing here has external linkage, so any number
 * of models (each with its own prefix) link into one firmware. C99, freestanding
 * (stdint.h, stddef.h, float.h), no malloc, no mutable globals: the caller owns the state.
 * See c_runtime/README.md.
 */
#ifndef ECMRT_H
#define ECMRT_H

#include <stddef.h>
#include <stdint.h>

/* Bumped whenever the runtime's behaviour, the state fields or the meaning of a
 * configuration macro changes; generated code checks it.
 * 2: temperature input and tables over (temperature, SOC), diffusion pair, Butler-Volmer
 *    fast branch, temperature_dependence, one step for every model, state type per model.
 * 3: ECMRT_RC_UNIFORM / ECMRT_OCV_UNIFORM (O(1) lookup on uniform SOC grids), ECMRT_TAU_T /
 *    ECMRT_TAU_SAME (time constants over temperature only, their coefficients in the state),
 *    tables interpolated in temperature first with the segment's pairs kept in the state,
 *    1 - exp(-x) by one polynomial below x = 1/4. */
#define ECMRT_VERSION 3

/* Index of the per-direction tables and value of state.charging. */
#define ECMRT_DISCHARGE 0u
#define ECMRT_CHARGE 1u

/* Fixed point: the temperature input is int32 Q8 degC (value = raw / 256). */
#define ECMRT_Q_TEMP 8

#endif /* ECMRT_H */
