/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_state.h - ecmgen C runtime: what both numerics do with the model's state, the
 * state at init and the direction and segment hints at the end of a step (hand-written,
 * model-independent). Included by ecmrt_f32.h and ecmrt_q.h once a generated
 * <prefix>_ecm_<s>_config.h has defined ECMRT_STATE and the switches (ecmrt_config.h).
 */
#ifndef ECMRT_STATE_H
#define ECMRT_STATE_H

#include "ecmrt.h"

#include "ecmrt_config.h"  /* the switches */

/* the hints of the searched grids (0 where there is none: a uniform grid is not searched) */
#if ECMRT_RC_UNIFORM
#define ECMRT_HINT_DIR(s, dir) 0u
#else
#define ECMRT_HINT_DIR(s, dir) ((unsigned)(s)->k_dir[dir])
#endif
#if ECMRT_OCV_SHARED || ECMRT_OCV_UNIFORM
#define ECMRT_HINT_OCV(s) 0u
#else
#define ECMRT_HINT_OCV(s) ((unsigned)(s)->k_ocv)
#endif
#if ECMRT_TEMP
#define ECMRT_HINT_T(s) ((unsigned)(s)->k_t)
#define ECMRT_KEY_NONE 0xFFFFu      /* pc_key of no segment (oc_key: 0xFF) */
/* the cached segment pairs belong to another temperature (or to none yet) */
#if ECMRT_OCV_SHARED
#define ECMRT_CACHE_CLEAR(s) ((s)->pc_key = ECMRT_KEY_NONE)
#else
#define ECMRT_CACHE_CLEAR(s) ((s)->pc_key = ECMRT_KEY_NONE, (s)->oc_key = 0xFFu)
#endif
/* the temperature row k_t of the state, clamped (a corrupted value costs no wild read) */
#define ECMRT_KT(m, kt) ((kt) > (unsigned)(m)->t.n - 2u ? (unsigned)(m)->t.n - 2u : (kt))
#else
#define ECMRT_HINT_T(s) 0u
#endif

#if ECMRT_TAU_T
/* the time constants' coefficients kept in the state: kc[direction][ECMRT_K_*], one
 * direction's set with ECMRT_TAU_SAME */
#define ECMRT_NK (2u + (unsigned)ECMRT_DIFF)
#define ECMRT_K_F 0u
#define ECMRT_K_S 1u
#define ECMRT_K_D 2u
#if ECMRT_TAU_SAME
#define ECMRT_KC_DIRS 1u
#define ECMRT_KC(s, dir, j) ((s)->kc[0][j])
#else
#define ECMRT_KC_DIRS 2u
#define ECMRT_KC(s, dir, j) ((s)->kc[dir][j])
#endif
#endif

static inline void ecmrt_hints_store(ECMRT_STATE *s, unsigned dir, unsigned kd, unsigned ko,
                                     unsigned kt)
{
    s->charging = (uint8_t)dir;
#if !ECMRT_RC_UNIFORM
    s->k_dir[dir] = (uint8_t)kd;
#endif
#if !ECMRT_OCV_SHARED && !ECMRT_OCV_UNIFORM
    s->k_ocv = (uint8_t)ko;
#endif
#if ECMRT_TEMP
    s->k_t = (uint8_t)kt;
#endif
    (void)kd;
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
#if !ECMRT_RC_UNIFORM
    s->k_dir[1] = 0u;
#endif
#if ECMRT_TEMP
    ECMRT_CACHE_CLEAR(s);
#endif
    ecmrt_hints_store(s, ECMRT_DISCHARGE, 0u, 0u, 0u);
}

#endif /* ECMRT_STATE_H */
