/* SPDX-License-Identifier: MIT */
/* The float runtime's 1 - exp(-x), called directly (tests/test_codegen_equiv.py). The
 * switches come from the compiler's command line (all 0 but ECMRT_VARIABLE_DT, from
 * ecmgen.c.runtime.switches()): a plain model's configuration. */
#include <stddef.h>
#include <stdint.h>

typedef struct {
    float soc, soc_c, u_fast, u_slow;
    uint8_t charging, k_ocv, k_dir[2];
} fstate_t;
#define ECMRT_STATE fstate_t
#include "ecmrt_f32.h"

void t_f32(const float *x, float *out, size_t n);

void t_f32(const float *x, float *out, size_t n)
{
    size_t k;
    for (k = 0; k < n; k++) {
        out[k] = ecmrt_f32_one_minus_exp_neg(x[k]);
    }
}
