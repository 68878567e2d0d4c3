/* Sanitizer driver of the C SOC estimator (tests/test_codegen_estimator_robust.py): every
 * combination of absurd inputs, then random steps; after each step the state must be sane. */
#include <stdio.h>
#include <stdlib.h>
#include <stdint.h>
#include <float.h>
#include "fe_est_f32.h"

static uint32_t rnd(uint32_t *x) { *x ^= *x << 13; *x ^= *x >> 17; *x ^= *x << 5; return *x; }
static long fails = 0;
static int finite(float v) { return v == v && v <= FLT_MAX && v >= -FLT_MAX; }
static void check(const fe_est_f32_t *e, float vp)
{
    unsigned a, b;
    int bad = !(e->m.soc >= 0.0f && e->m.soc <= 1.0f) || !finite(e->m.u_fast) ||
              !finite(e->m.u_slow) || !finite(e->m.u_diff) || !(vp == vp);
#if defined(FE_FX) && FE_FX     /* effects and offset state: h in [-1, 1], u_x, offset finite */
    bad |= !(e->m.h >= -1.0f && e->m.h <= 1.0f) || !finite(e->m.u_x) || !finite(e->offset_a);
#endif
    for (a = 0; a < FE_EST_F32_STATES; a++) {
        bad |= !(e->p[a * FE_EST_F32_STATES + a] >= 0.0f);
        for (b = 0; b < FE_EST_F32_STATES; b++) {
            bad |= !finite(e->p[a * FE_EST_F32_STATES + b]);
            bad |= e->p[a * FE_EST_F32_STATES + b] != e->p[b * FE_EST_F32_STATES + a];
        }
    }
    if (bad && fails < 5) {
        printf("bad: soc %g u %g %g %g vp %g p00 %g p11 %g\n", (double)e->m.soc, (double)e->m.u_fast,
               (double)e->m.u_slow, (double)e->m.u_diff, (double)vp, (double)e->p[0], (double)e->p[5]);
    }
    fails += bad;
}

int main(int argc, char **argv)
{
    const float nan = 0.0f / (argc > 99 ? 1.0f : 0.0f);
    const float inf = 1.0f / (argc > 99 ? 1.0f : 0.0f);
    const float cur[] = {0.0f, 1e30f, -1e30f, FLT_MAX, -FLT_MAX, 1e-45f, 127.0f, -500.0f, 3.0f, -3.0f, nan, inf, -inf};
    const float dts[] = {0.0f, -1.0f, 1e-45f, 0.1f, 1e30f, FLT_MAX, 32767.0f, nan, inf};
    const float tmp[] = {25.0f, -20.0f, -60.0f, 90.0f, 1e30f, -1e30f, nan, inf, -inf};
    const float vs[] = {3.7f, 0.0f, -5.0f, 4.2f, 1e30f, -1e30f, FLT_MAX, nan, inf, -inf, 2.5f};
    const float socs[] = {-1e30f, -2.5f, 0.0f, 0.5f, 1.0f, 3.0f, 1e30f, nan};
    long n = argc > 1 ? atol(argv[1]) : 100000L, k;
    size_t a, b, c, d, s;
    uint32_t x = 2463534242u;
    fe_est_f32_t e;
    float vp;
    (void)argv;
    for (s = 0; s < sizeof socs / sizeof socs[0]; s++)
      for (a = 0; a < sizeof cur / sizeof cur[0]; a++)
        for (b = 0; b < sizeof dts / sizeof dts[0]; b++) {
            fe_est_init_f32(&e, socs[s]);
            for (c = 0; c < sizeof tmp / sizeof tmp[0]; c++)
                for (d = 0; d < sizeof vs / sizeof vs[0]; d++) {
                    vp = fe_est_step_f32(&e, (c + d) % 2 ? cur[a] : -cur[a], tmp[c], dts[b], vs[d]);
                    check(&e, vp);
                    vp = fe_est_step_f32(&e, 1.0f, 25.0f, 0.1f, 3.7f);
                    check(&e, vp);
                }
        }
    fe_est_init_f32(&e, 0.5f);
    for (k = 0; k < n; k++) {
        const uint32_t r1 = rnd(&x), r2 = rnd(&x), r3 = rnd(&x);
        const float fi = (float)(int32_t)r1 * (1.0f / 67108864.0f);       /* +-32 A */
        const float fdt = (r3 & 255u) == 0u ? (float)(r2 >> 16) : (float)(r2 >> 8) * (1.0f / 16777216.0f);
        const float ft = (float)(r3 >> 8) * (1.0f / 167772.16f) - 40.0f;   /* -40 .. 60 degC */
        const float fv = 2.5f + (float)(r3 >> 16) * (1.7f / 65536.0f);
        vp = fe_est_step_f32(&e, fi, ft, fdt, (r2 & 1023u) == 0u ? nan : fv);
        check(&e, vp);
    }
    printf("soc %g p00 %g fails %ld\n", (double)e.m.soc, (double)e.p[0], fails);
    return fails != 0;
}
