/*
 * ecmrt.h - ecmgen C runtime: shared types (hand-written, model-independent).
 *
 * The generated <prefix>_ecm.h includes this file for the state types; the generated
 * <prefix>_ecm.c includes ecmrt_f32.h (numeric = "float") or ecmrt_q.h
 * (numeric = "fixed"), which hold the discrete 2RC step as static inline functions.
 * Nothing here has external linkage, so any number of models (each with its own
 * prefix) link into one firmware. C99, freestanding (stdint.h, stddef.h, float.h),
 * no malloc, no mutable globals: the caller owns the state.
 * See c_runtime/README.md.
 */
#ifndef ECMRT_H
#define ECMRT_H

#include <stddef.h>
#include <stdint.h>

/* Bumped whenever the runtime's behaviour or the layout of these types changes;
 * generated code checks it. */
#define ECMRT_VERSION 1

/* Index of the per-direction tables and value of state.charging. */
#define ECMRT_DISCHARGE 0u
#define ECMRT_CHARGE 1u

#endif /* ECMRT_H */

/* The state types, each only where asked for (ECMRT_NEED_F32_STATE / ECMRT_NEED_Q_STATE),
 * so that a fixed-point translation unit contains no floating-point type at all. */
#if defined(ECMRT_NEED_F32_STATE) && !defined(ECMRT_F32_STATE_DEFINED)
#define ECMRT_F32_STATE_DEFINED
/* State of one cell model, numeric = "float". Owned by the caller; set with
 * <prefix>_init(), then only touched by <prefix>_step(). */
typedef struct {
    float soc;          /* state of charge (1 = full), saturated to [-2, 2] */
    float soc_c;        /* Kahan compensation of the SOC sum (rounding carried to the next step) */
    float u_fast;       /* voltage over the fast RC pair, V */
    float u_slow;       /* voltage over the slow RC pair, V */
    uint8_t charging;   /* direction of the last step: ECMRT_CHARGE or ECMRT_DISCHARGE */
    uint8_t k_ocv;      /* table segment hints: speed only, never change a result */
    uint8_t k_dir[2];
} ecmrt_f32_state_t;
#endif

#if defined(ECMRT_NEED_Q_STATE) && !defined(ECMRT_Q_STATE_DEFINED)
#define ECMRT_Q_STATE_DEFINED
/* State of one cell model, numeric = "fixed" (Q formats in <prefix>_ecm.h). */
typedef struct {
    int64_t soc_rem;    /* SOC below 1 LSB of Q30, carried to the next step: exact Coulomb count */
    int32_t soc;        /* Q30, saturated to the int32 range [-2, 2) */
    int32_t u_fast;     /* Q_V volts */
    int32_t u_slow;     /* Q_V volts */
    uint8_t charging;
    uint8_t k_ocv;
    uint8_t k_dir[2];
} ecmrt_q_state_t;
#endif
