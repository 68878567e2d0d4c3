/* SPDX-License-Identifier: MIT */
/* The fixed-point runtime's c = 1 - exp(-dt/tau) and reciprocal, called directly
 * (tests/test_codegen_equiv.py). The switches come from the compiler's command line (all
 * 0 but ECMRT_VARIABLE_DT); the formats are those of a typical model. */
#include <stddef.h>
#include <stdint.h>

typedef struct {
    int64_t soc_rem;
    int32_t soc, u_fast, u_slow;
    uint8_t charging, k_ocv, k_dir[2];
} qstate_t;
#define ECMRT_STATE qstate_t
#define ECMRT_Q_I 24
#define ECMRT_Q_V 27
#define ECMRT_Q_G 27
#define ECMRT_Q_R0 36
#define ECMRT_Q_RF 36
#define ECMRT_Q_RS 36
#define ECMRT_Q_T 21
#define ECMRT_SH_RATE 31
#define ECMRT_SH_DSOC 23
#include "ecmrt_q.h"

void t_q(const int32_t *dt, const int32_t *tau, int32_t *out, size_t n);
void t_recip(const uint32_t *d, uint32_t *r, uint32_t *sh, size_t n);

void t_q(const int32_t *dt, const int32_t *tau, int32_t *out, size_t n)
{
    size_t k;
    for (k = 0; k < n; k++) {
        out[k] = ecmrt_q_c_dt_tau(dt[k], tau[k]);
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
