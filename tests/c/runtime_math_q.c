/* SPDX-License-Identifier: MIT */
/* The fixed-point runtime's c = 1 - exp(-dt/tau) and reciprocal, called directly
 * (tests/test_codegen_equiv.py): the runtime headers compile as they are, with no model's
 * configuration; the time constants' format is a typical model's. */
#include <stddef.h>
#include <stdint.h>
#include "ecmrt_q.h"

#define T_Q_T 21    /* tau in Q21 s */

void t_q(const int32_t *dt, const int32_t *tau, int32_t *out, size_t n);
void t_recip(const uint32_t *d, uint32_t *r, uint32_t *sh, size_t n);

void t_q(const int32_t *dt, const int32_t *tau, int32_t *out, size_t n)
{
    size_t k;
    for (k = 0; k < n; k++) {
        out[k] = ecmrt_q_c_dt_tau(dt[k], tau[k], T_Q_T);
    }
}

void t_recip(const uint32_t *d, uint32_t *r, uint32_t *sh, size_t n)
{
    size_t k;
    unsigned s;
    for (k = 0; k < n; k++) {
        r[k] = ecmrt_q_recip(d[k], &s);
        sh[k] = s;
    }
}
