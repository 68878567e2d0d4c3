/* SPDX-License-Identifier: MIT */
/* The float runtime's 1 - exp(-x), called directly (tests/test_codegen_equiv.py): the runtime
 * headers compile as they are, with no model's configuration. */
#include <stddef.h>
#include <stdint.h>
#include "ecmrt_f32.h"

void t_f32(const float *x, float *out, size_t n);

void t_f32(const float *x, float *out, size_t n)
{
    size_t k;
    for (k = 0; k < n; k++) {
        out[k] = ecmrt_f32_one_minus_exp_neg(x[k]);
    }
}
