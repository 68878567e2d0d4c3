/* SPDX-License-Identifier: MIT */
/* tests/test_codegen.py: two models, float and fixed point, under two prefixes in one
 * program. */
#include <stdio.h>
#include "cellA_ecm_f32.h"
#include "cellB_ecm_q.h"
int main(void)
{
    cellA_state_f32_t a;
    cellB_state_q_t b;
    float va = 0.0f;
    int32_t vb = 0;
    int k;
    cellA_init_f32(&a, 0.8f);
    cellB_init_q(&b, (int32_t)(0.8 * 1073741824.0));
    for (k = 0; k < 100; k++) {
        va = cellA_step_f32(&a, -2.0f, 25.0f, 0.1f);
        vb = cellB_step_q(&b, (int32_t)(-2.0 * (double)(1L << CELLB_ECM_Q_I)), 25 << CELLB_ECM_Q_TEMP);
    }
    printf("%.6f %.6f\n", (double)va, (double)vb / (double)(1L << CELLB_ECM_Q_V));
    return 0;
}
