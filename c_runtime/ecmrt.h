/*
 * ecmrt.h - ecmgen C runtime: shared constants (hand-written, model-independent).
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
 *    fast branch, temperature_dependence, one step for every model, state type per model. */
#define ECMRT_VERSION 2

/* Index of the per-direction tables and value of state.charging. */
#define ECMRT_DISCHARGE 0u
#define ECMRT_CHARGE 1u

/* Fixed point: the temperature input is int32 Q8 degC (value = raw / 256). */
#define ECMRT_Q_TEMP 8

#endif /* ECMRT_H */

/* Shared by both numerics, compiled into a model's .c once the runtime has defined its
 * configuration (ECMRT_STATE and the switches): the state at init and the direction and
 * segment hints at the end of a step. */
#if defined(ECMRT_STATE) && !defined(ECMRT_HINTS_DEFINED)
#define ECMRT_HINTS_DEFINED
/* the hints of the OCV's own grid and of the temperature grid (0 where there is none) */
#if ECMRT_OCV_SHARED
#define ECMRT_HINT_OCV(s) 0u
#else
#define ECMRT_HINT_OCV(s) ((unsigned)(s)->k_ocv)
#endif
#if ECMRT_TEMP
#define ECMRT_HINT_T(s) ((unsigned)(s)->k_t)
#else
#define ECMRT_HINT_T(s) 0u
#endif

static inline void ecmrt_hints_store(ECMRT_STATE *s, unsigned dir, unsigned kd, unsigned ko,
                                     unsigned kt)
{
    s->charging = (uint8_t)dir;
    s->k_dir[dir] = (uint8_t)kd;
#if !ECMRT_OCV_SHARED
    s->k_ocv = (uint8_t)ko;
#endif
#if ECMRT_TEMP
    s->k_t = (uint8_t)kt;
#endif
    (void)ko;
    (void)kt;
}

/* at rest: the RC voltages 0, direction discharge, hints 0 (SOC, h and the temperature
 * cache are set by the numeric's init) */
static inline void ecmrt_state_init_common(ECMRT_STATE *s)
{
    s->u_fast = 0;
    s->u_slow = 0;
#if ECMRT_DIFF
    s->u_diff = 0;
#endif
#if ECMRT_FX_XRC
    s->u_x = 0;
#endif
    s->k_dir[1] = 0u;
    ecmrt_hints_store(s, ECMRT_DISCHARGE, 0u, 0u, 0u);
}
#endif
