/* SPDX-License-Identifier: MIT */
/* tests/test_codegen_robust.py: the four variants (fv, fd, qv, qd) of a model under the
 * sanitizers: every input combination and a pseudo-random drive; prints "fails N". */
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
static int bad_f(float v) { return !(v == v) || v > 1e6f || v < -1e6f; }
static long fails = 0;

#define NQ_SOC (sizeof qsocs / sizeof qsocs[0])
#define NQ_CUR (sizeof qcur / sizeof qcur[0])
#define NQ_DT (sizeof qdts / sizeof qdts[0])

int main(int argc, char **argv)
{
    static const float cur[] = {0.0f, 1e30f, -1e30f, FLT_MAX, -FLT_MAX, 1e-45f, -1e-45f,
                                127.0f, -500.0f, 3.0f, -3.0f};
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
    int32_t lo = INT32_MAX, hi = INT32_MIN;
    (void)argv;
    for (a = 0; a < sizeof socs / sizeof socs[0]; a++)
        for (b = 0; b < sizeof cur / sizeof cur[0]; b++)
            for (c = 0; c < sizeof dts / sizeof dts[0]; c++) {
                fv_state_f32_t s; fd_state_f32_t t;
                int r;
                fv_init_f32(&s, socs[a]); fd_init_f32(&t, socs[a]);
                for (r = 0; r < 20; r++) {
                    fails += bad_f(fv_step_f32(&s, r % 3 ? cur[b] : -cur[b], FT(r + b), dts[c]));
                    fails += bad_f(fv_step_f32(&s, nan, nan, nan)) + bad_f(fv_step_f32(&s, inf, inf, inf));
                    fails += bad_f(fv_step_f32(&s, -inf, -inf, -inf));
                    fails += bad_f(fd_step_f32(&t, cur[b], FT(r + c))) + bad_f(fd_step_f32(&t, nan, nan));
                    fails += bad_f(fd_step_f32(&t, -inf, -inf));
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
                int32_t v = qv_step_q(&s, r % 2 ? qcur[b] : -(qcur[b] + 1), QT(r + b), qdts[c]);
                int32_t w = qd_step_q(&t, qcur[b], QT(r + c));
                if (v < lo) lo = v;
                if (v > hi) hi = v;
                (void)w;
            }
        }
    }
    {
        fv_state_f32_t s; fd_state_f32_t t; qv_state_q_t q; qd_state_q_t u;
        fv_init_f32(&s, 0.5f); fd_init_f32(&t, 0.5f); qv_init_q(&q, 1 << 29); qd_init_q(&u, 1 << 29);
        for (k = 0; k < n; k++) {
            const uint32_t r1 = rnd(&x), r2 = rnd(&x);
            const float fi = (float)(int32_t)r1 * (1.0f / 8388608.0f);     /* +-256 A */
            const float fdt = (float)(r2 >> 8) * (1.0f / 1677721.6f);     /* 0..10 s */
            fails += bad_f(fv_step_f32(&s, fi, FT(r2 >> 29), fdt)) + bad_f(fd_step_f32(&t, fi, FT(r1 >> 29)));
            (void)qv_step_q(&q, (int32_t)r1, QT(r2 >> 29), (int32_t)(r2 >> 13));
            (void)qd_step_q(&u, (int32_t)r2, QT(r1 >> 29));
        }
        printf("soc %g %g %ld %ld\n", (double)s.soc, (double)t.soc, (long)q.soc, (long)u.soc);
    }
    printf("fails %ld range %ld %ld\n", fails, (long)lo, (long)hi);
    return fails != 0;
}
