/* SPDX-License-Identifier: MIT */
/* tests/test_verify.py: the float model, the fixed-point model and the estimator of one
 * model under one prefix (pan) in one program. QI and QV, the fixed point's current and
 * voltage formats, come from the command line (-DQI=24 -DQV=24): the typed names carry
 * them. */
#include "pan_ecm_f32.h"
#include "pan_ecm_q.h"
#include "pan_est_f32.h"

#define ECMT_CAT(a, b, c) a##b##c
#define ECMT_XCAT(a, b, c) ECMT_CAT(a, b, c)
#define AMP_FROM ECMT_XCAT(PAN_ECM_Q_AMP_Q, QI, _FROM)
#define VOLT_TO_MILLI ECMT_XCAT(PAN_ECM_Q_VOLT_Q, QV, _TO_MILLI)

PAN_ECM_Q_ASSERT_FORMATS(PAN_ECM_Q_I, PAN_ECM_Q_V);

int main(void)
{
    pan_state_f32_t f;
    pan_state_q_t q;
    pan_est_f32_t e;
    float vf = 0.0f, ve = 0.0f;
    int32_t vq = 0;
    int k;
    pan_init_f32(&f, 0.8f);
    pan_init_q(&q, PAN_ECM_Q_SOC_Q30_FROM(0.8));
    pan_est_init_f32(&e, 0.7f);
    for (k = 0; k < 50; k++) {
        vf = pan_step_f32(&f, -2.0f, 25.0f, 1.0f);
        vq = pan_step_q(&q, AMP_FROM(-2), PAN_ECM_Q_DEGC_Q8_FROM(25), PAN_ECM_Q_SEC_Q16_FROM(1));
        ve = pan_est_step_f32(&e, -2.0f, 25.0f, 1.0f, vf);
    }
    /* the three agree to a millivolt or so, and the fixed output reads in mV */
    return (vf > 2.5f && vf < 4.5f && ve > 2.5f && ve < 4.5f &&
            VOLT_TO_MILLI(vq) > 2500 && VOLT_TO_MILLI(vq) < 4500) ? 0 : 1;
}
