/* SPDX-License-Identifier: MIT */
/* tests/test_codegen_robust.py: the four variants (fv, fd, qv, qd) of a model under the
 * sanitizers: every input combination and a pseudo-random drive; prints "fails N qfails M".
 * SAN_FX 1: the model has the hysteresis and extra_rc effects (states h and u_x). */
#include <stdio.h>
#include <stdlib.h>
#include <stdint.h>
#include <float.h>
#include "fv_ecm_f32.h"
#include "fd_ecm_f32.h"
#include "qv_ecm_q.h"
#include "qd_ecm_q.h"

/* cell temperatures, every one a legal input (float: NaN and inf too) */
static const float ftemps[8] = {25.0f, -20.0f, -60.0f, 90.0f, 1e30f, -1e30f, 0.5f, 17.3f};
static const int32_t qtemps[8] = {25 * 256, -20 * 256, INT32_MIN, INT32_MAX, 0, 4423, -5000, 30000};
#define FT(r) ftemps[(unsigned)(r) & 7u]
#define QT(r) qtemps[(unsigned)(r) & 7u]

static uint32_t rnd(uint32_t *x) { *x ^= *x << 13; *x ^= *x >> 17; *x ^= *x << 5; return *x; }
static long fails = 0, qfails = 0;
static int bad_f(float v) { return !(v == v) || v > 1e6f || v < -1e6f; }
#ifndef SAN_FX
#error "SAN_FX (0 or 1) is given on the command line"
#endif
/* float state: every field finite, SOC in [-2, 2] (, h in [-1, 1]) */
#define BAD_F2(s) (bad_f((s).soc) || bad_f((s).u_fast) || bad_f((s).u_slow) || \
                   !((s).soc >= -2.0f && (s).soc <= 2.0f))
#if SAN_FX
#define BAD_FS(s) (BAD_F2(s) || bad_f((s).u_x) || !((s).h >= -1.0f && (s).h <= 1.0f))
/* fixed state: h in Q30 [-1, 1] */
#define BAD_QS(s) ((s).h < -(1 << 30) || (s).h > (1 << 30))
#else
#define BAD_FS(s) BAD_F2(s)
#define BAD_QS(s) 0
#endif

#define NQ_SOC (sizeof qsocs / sizeof qsocs[0])
#define NQ_CUR (sizeof qcur / sizeof qcur[0])
#define NQ_DT (sizeof qdts / sizeof qdts[0])

int main(int argc, char **argv)
{
    static const float cur[] = {0.0f, 1e30f, -1e30f, FLT_MAX, -FLT_MAX, 1e-45f, -1e-45f,
                                127.0f, -500.0f, 3.0f, -3.0f, 0.02f};
    static const float dts[] = {0.0f, -1.0f, 1e-45f, 0.1f, 1e30f, FLT_MAX, 32767.0f};
    static const float socs[] = {-1e30f, -2.5f, 0.0f, 0.5f, 1.0f, 3.0f, 1e30f};
    static const int32_t qcur[] = {INT32_MIN, INT32_MAX, 0, 1, -1, 486539, -486539, 1 << 24};
    static const int32_t qdts[] = {INT32_MIN, -1, 0, 1, 6554, INT32_MAX};
    static const int32_t qsocs[] = {INT32_MIN, -1, 0, 1 << 29, 1 << 30, INT32_MAX};
    const float nan = 0.0f / (argc > 99 ? 1.0f : 0.0f);   /* NaN without a constant fold warning */
    const float inf = 1.0f / (argc > 99 ? 1.0f : 0.0f);
    long n = argc > 1 ? atol(argv[1]) : 1000000L;
    size_t a, b, c, n3;
    long k;
    uint32_t x = 2463534242u;
    for (a = 0; a < sizeof socs / sizeof socs[0]; a++)
        for (b = 0; b < sizeof cur / sizeof cur[0]; b++)
            for (c = 0; c < sizeof dts / sizeof dts[0]; c++) {
                fv_state_f32_t s; fd_state_f32_t t;
                int r;
                fv_init_f32(&s, socs[a]); fd_init_f32(&t, socs[a]);
                for (r = 0; r < 20; r++) {
                    fails += bad_f(fv_step_f32(&s, r % 3 ? cur[b] : -cur[b], FT(r + b), dts[c]));
                    fails += bad_f(fv_step_f32(&s, nan, nan, nan)) + bad_f(fv_step_f32(&s, inf, inf, inf));
                    fails += bad_f(fv_step_f32(&s, -inf, -inf, -inf)) + bad_f(fv_step_f32(&s, nan, FT(r), inf));
                    fails += bad_f(fd_step_f32(&t, r % 3 ? cur[b] : -cur[b], FT(r + c))) + bad_f(fd_step_f32(&t, nan, nan));
                    fails += bad_f(fd_step_f32(&t, -inf, -inf)) + bad_f(fd_step_f32(&t, inf, inf));
                    fails += BAD_FS(s) + BAD_FS(t);
                }
            }
    /* every (soc, current, dt) combination of the fixed-point variants, one loop */
    for (n3 = 0; n3 < NQ_SOC * NQ_CUR * NQ_DT; n3++) {
        a = n3 / (NQ_CUR * NQ_DT);
        b = n3 / NQ_DT % NQ_CUR;
        c = n3 % NQ_DT;
        {
            qv_state_q_t s; qd_state_q_t t;
            int r;
            qv_init_q(&s, qsocs[a]); qd_init_q(&t, qsocs[a]);
            for (r = 0; r < 20; r++) {
                (void)qv_step_q(&s, r % 2 ? qcur[b] : -(qcur[b] + 1), QT(r + b), qdts[c]);
                (void)qd_step_q(&t, r % 2 ? qcur[b] : -(qcur[b] + 1), QT(r + c));
                qfails += BAD_QS(s) + BAD_QS(t);
            }
        }
    }
    {
        fv_state_f32_t s; fd_state_f32_t t; qv_state_q_t q; qd_state_q_t u;
        fv_init_f32(&s, 0.5f); fd_init_f32(&t, 0.5f); qv_init_q(&q, 1 << 29); qd_init_q(&u, 1 << 29);
        for (k = 0; k < n; k++) {
            const uint32_t r1 = rnd(&x), r2 = rnd(&x), r3 = rnd(&x);
            float fi = (float)(int32_t)r1 * (1.0f / 8388608.0f);          /* +-256 A */
            float fdt = (float)(r2 >> 8) * (1.0f / 1677721.6f);          /* 0..10 s */
            int32_t qi = (int32_t)r1;
            if ((r3 & 1023u) == 0u) fi = (r3 & 1024u) ? nan : fi * 1e30f;  /* absurd inputs */
            if ((r3 & 4095u) == 1u) fdt = (r3 & 4096u) ? nan : 1e30f;
            if ((r3 & 3u) != 0u) qi >>= (r3 >> 2) % 24u;                   /* mostly moderate */
            fails += bad_f(fv_step_f32(&s, fi, FT(r2 >> 29), fdt)) + bad_f(fd_step_f32(&t, fi, FT(r1 >> 29)));
            (void)qv_step_q(&q, qi, QT(r2 >> 29), (int32_t)(r2 >> 13));
            (void)qd_step_q(&u, qi, QT(r1 >> 29));
            if ((k & 63) == 0) {
                fails += BAD_FS(s) + BAD_FS(t);
                qfails += BAD_QS(q) + BAD_QS(u);
            }
        }
        fails += BAD_FS(s) + BAD_FS(t);
        qfails += BAD_QS(q) + BAD_QS(u);
#if SAN_FX
        printf("state %g %g %g %g %ld %ld %ld %ld\n", (double)s.soc, (double)s.h, (double)s.u_x,
               (double)t.h, (long)q.soc, (long)q.h, (long)q.u_x, (long)u.h);
#else
        printf("soc %g %g %ld %ld\n", (double)s.soc, (double)t.soc, (long)q.soc, (long)u.soc);
#endif
    }
    printf("fails %ld qfails %ld\n", fails, qfails);
    return fails != 0 || qfails != 0;
}
