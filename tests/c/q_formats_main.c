/* SPDX-License-Identifier: MIT */
/* tests/test_verify.py: the fixed-point conversion macros are exact, and code written for
 * other formats does not compile. QI and QV (the formats this code was written for) come
 * from the command line (-DQI=24 -DQV=24). */
#include "pan_ecm_q.h"

#define ECMT_CAT(a, b, c) a##b##c
#define ECMT_XCAT(a, b, c) ECMT_CAT(a, b, c)
#define AMP_T ECMT_XCAT(pan_amp_q, QI, _t)
#define VOLT_T ECMT_XCAT(pan_volt_q, QV, _t)
#define AMP_FROM ECMT_XCAT(PAN_ECM_Q_AMP_Q, QI, _FROM)
#define VOLT_FROM ECMT_XCAT(PAN_ECM_Q_VOLT_Q, QV, _FROM)
#define AMP_TO_MILLI ECMT_XCAT(PAN_ECM_Q_AMP_Q, QI, _TO_MILLI)
#define VOLT_TO_MILLI ECMT_XCAT(PAN_ECM_Q_VOLT_Q, QV, _TO_MILLI)

PAN_ECM_Q_ASSERT_FORMATS(QI, QV);

int main(void)
{
    const AMP_T i = AMP_FROM(-2.5);
    const VOLT_T v = VOLT_FROM(3);
    const pan_degc_q8_t t = PAN_ECM_Q_DEGC_Q8_FROM(-10.25);
    const pan_soc_q30_t s = PAN_ECM_Q_SOC_Q30_FROM(0.5);
    return (i == -(int32_t)(5 << (QI - 1)) && v == (int32_t)(3 << QV) && t == -2624 &&
            s == (1 << 29) && VOLT_TO_MILLI(v) == 3000 && AMP_TO_MILLI(i) == -2500 &&
            PAN_ECM_Q_DEGC_Q8_TO_MILLI(t) == -10250) ? 0 : 1;
}
