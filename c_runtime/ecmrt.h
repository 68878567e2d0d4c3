/* SPDX-License-Identifier: MIT */
/*
 * ecmrt.h - ecmgen C runtime: shared constants (hand-written, model-independent).
 *
 * The generated <prefix>_ecm_<s>.h includes this file and declares the model's own state type
 * (<prefix>_state_<s>_t, exactly the fields the model needs); the generated <prefix>_ecm_<s>.c
 * writes the model's step from the building blocks of ecmrt_f32.h (numeric = "float") or
 * ecmrt_q.h (numeric = "fixed"): lookups, maths and one static inline unit per stage and
 * effect, each taking what it needs as arguments, so that every header compiles as it is for
 * every model and the generator alone chooses what a model's step calls. Nothing here has
 * external linkage, so any number of models (each with its own prefix) link into one firmware.
 * C99, freestanding (stdint.h, stddef.h, float.h), no malloc, no mutable globals: the caller
 * owns the state. See c_runtime/README.md.
 */
#ifndef ECMRT_H
#define ECMRT_H

#include <stddef.h>
#include <stdint.h>

/* Bumped whenever the runtime's behaviour, the state fields or the meaning of a unit's
 * arguments changes; generated code checks it.
 * 2: temperature input and tables over (temperature, SOC), diffusion pair, Butler-Volmer
 *    fast branch, temperature_dependence, one step for every model, state type per model.
 * 3: uniform SOC grids (O(1) lookup), time constants over temperature only (their
 *    coefficients in the state), tables interpolated in temperature first with the
 *    segment's pairs kept in the state, 1 - exp(-x) by one polynomial below x = 1/4.
 * 4: no compile-time switches: the units take their tables, constants and formats as
 *    arguments, the generated code calls those of its model. */
#define ECMRT_VERSION 4

/* Index of the per-direction tables and value of state.charging. */
#define ECMRT_DISCHARGE 0u
#define ECMRT_CHARGE 1u

/* Fixed point: the temperature input is int32 Q8 degC (value = raw / 256). */
#define ECMRT_Q_TEMP 8

/* the key of no cached segment (pc_key; oc_key: ECMRT_OC_NONE): the cache is empty */
#define ECMRT_KEY_NONE 0xFFFFu
#define ECMRT_OC_NONE 0xFFu

/* the temperature row kt of a state, clamped to the n - 1 segments of the temperature grid
 * (a corrupted value costs no wild read) */
#define ECMRT_ROW(kt, n) ((kt) > (unsigned)(n) - 2u ? (unsigned)(n) - 2u : (kt))

#endif /* ECMRT_H */
