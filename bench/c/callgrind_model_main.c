/* SPDX-License-Identifier: MIT */
/* bench/bench_c.py: n steps of one generated model over inputs read from a file, for
 * callgrind's count of the step's instructions. The model comes from the command line:
 * ECMB_HEADER ("<prefix>_ecm_<s>.h"), ECMB_T (float or int32_t), ECMB_STATE, ECMB_INIT,
 * ECMB_STEP, ECMB_SOC0, ECMB_VDT (1: the step takes dt). */
#include <stdio.h>
#include <stdlib.h>
#include ECMB_HEADER

int main(int argc, char **argv)
{
    FILE *f = fopen(argv[1], "rb");
    size_t n = (size_t)atol(argv[2]), k;
    ECMB_T *i = malloc(n * sizeof *i), *dt = malloc(n * sizeof *dt), *t = malloc(n * sizeof *t);
    ECMB_STATE s;
    double acc = 0.0;
    if (!f || !i || !dt || !t || fread(i, sizeof *i, n, f) != n ||
        fread(dt, sizeof *dt, n, f) != n || fread(t, sizeof *t, n, f) != n) {
        return 1;
    }
    ECMB_INIT(&s, ECMB_SOC0);
    for (k = 0; k < n; k++) {
#if ECMB_VDT
        acc += (double)ECMB_STEP(&s, i[k], t[k], dt[k]);
#else
        acc += (double)ECMB_STEP(&s, i[k], t[k]);
#endif
    }
    printf("%g\n", acc);
    (void)argc;
    return 0;
}
