/* SPDX-License-Identifier: MIT */
/* bench/bench_estimator_c.py: n samples of the generated estimator (prefix bench), or of
 * its model step alone (argv[3] 0), over inputs read from a file, for callgrind. */
#include <stdio.h>
#include <stdlib.h>
#include "bench_est_f32.h"
int main(int argc, char **argv)
{
    FILE *f = fopen(argv[1], "rb");
    size_t n = (size_t)atol(argv[2]), k;
    int est = atoi(argv[3]);
    float *i = malloc(4 * n * sizeof *i), *t = i + n, *dt = i + 2 * n, *v = i + 3 * n;
    bench_est_f32_t e;
    double acc = 0.0;
    if (!f || fread(i, sizeof *i, 4 * n, f) != 4 * n) return 1;
    bench_est_init_f32(&e, 0.8f);
    for (k = 0; k < n; k++) {
        acc += est ? (double)bench_est_step_f32(&e, i[k], t[k], dt[k], v[k])
                   : (double)bench_step_f32(&e.m, i[k], t[k], dt[k]);
    }
    printf("%g %g\n", acc, (double)e.m.soc);
    (void)argc;
    return 0;
}
