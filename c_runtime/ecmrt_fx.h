/*
 * ecmrt_fx.h - ecmgen C runtime: state types of a model that carries diagnose effects
 * (hand-written, model-independent). Copied only beside models with effects; a model
 * without effects uses ecmrt.h alone and never sees this file.
 *
 * The effect state follows the base state field for field (same names, same order), then
 *     h    hysteresis state in [-1, 1] (float; Q30 in fixed point), initial_state at init
 *     u_x  voltage over the extra RC pair (V; Q_V in fixed point), 0 at init
 * Both fields exist whether or not the model has the effect (unused ones keep their
 * initial value). See c_runtime/README.md, "Effects".
 */
#ifndef ECMRT_FX_H
#define ECMRT_FX_H
#include "ecmrt.h"

/* Bumped whenever the layout of these types or the effects' discrete updates change. */
#define ECMRT_FX_VERSION 1
#endif /* ECMRT_FX_H */

#if defined(ECMRT_NEED_F32_STATE) && !defined(ECMRT_F32_FX_STATE_DEFINED)
#define ECMRT_F32_FX_STATE_DEFINED
typedef struct {
    float soc;          /* as ecmrt_f32_state_t */
    float soc_c;
    float u_fast;
    float u_slow;
    uint8_t charging;
    uint8_t k_ocv;
    uint8_t k_dir[2];
    float h;            /* hysteresis state, [-1, 1] */
    float u_x;          /* extra RC pair voltage, V */
} ecmrt_f32_fx_state_t;
#endif

#if defined(ECMRT_NEED_Q_STATE) && !defined(ECMRT_Q_FX_STATE_DEFINED)
#define ECMRT_Q_FX_STATE_DEFINED
typedef struct {
    int64_t soc_rem;    /* as ecmrt_q_state_t */
    int32_t soc;
    int32_t u_fast;
    int32_t u_slow;
    uint8_t charging;
    uint8_t k_ocv;
    uint8_t k_dir[2];
    int32_t h;          /* hysteresis state, Q30 */
    int32_t u_x;        /* extra RC pair voltage, Q_V */
} ecmrt_q_fx_state_t;
#endif
