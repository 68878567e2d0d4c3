/* SPDX-License-Identifier: MIT */
/*
 * ecmrt_q_exp.h - ecmgen C runtime, numeric = "fixed": the integer reciprocal and
 * 1 - exp(-x) in Q30, without division (hand-written, model-independent).
 *
 * Included by ecmrt_q.h (after its rounding macros ECMRT_RSHR / ECMRT_RSHRV, ECMRT_Q30,
 * ECMRT_ONE30 and the inlining macros ECMRT_Q_HOT / ECMRT_Q_SHARED), never on its own.
 * Mirrored by src/ecmgen/c/cref.py (recip_q in qformat.py, _omexp_small_q, _omexp_big_q).
 */
#ifndef ECMRT_Q_EXP_H
#define ECMRT_Q_EXP_H

#if !defined(ECMRT_Q_H)
#error "ecmrt_q_exp.h is included by ecmrt_q.h"
#endif

/* number of leading zero bits of x != 0 */
static inline unsigned ecmrt_q_clz32(uint32_t x)
{
#if defined(__GNUC__) && defined(__SIZEOF_INT__) && __SIZEOF_INT__ == 4
    return (unsigned)__builtin_clz(x);
#else
    unsigned n = 0u;
    if (x < 0x10000u) { n += 16u; x <<= 16; }
    if (x < 0x1000000u) { n += 8u; x <<= 8; }
    if (x < 0x10000000u) { n += 4u; x <<= 4; }
    if (x < 0x40000000u) { n += 2u; x <<= 2; }
    if (x < 0x80000000u) { n += 1u; }
    return n;
#endif
}

/* 1/d for 1 <= d < 2^31, without division: d = m 2^-(s-1) with m in [2^30, 2^31) (s the
 * leading zeros of d), 1/m from a seed table of 2^31/(1 + j/64) interpolated linearly
 * (relative error < 6.2e-5) and one Newton step r (2 - m r) (relative error < 1e-8, the
 * result never above 1/m); returns r in (2^30, 2^31] with 1/d = r 2^-sh, sh = 62 - s. */
ECMRT_Q_HOT uint32_t ecmrt_q_recip(uint32_t d, unsigned *sh)
{
    static const uint32_t tab[65] = {
        2147483648u, 2114445438u, 2082408386u, 2051327664u, 2021161080u, 1991868891u,
        1963413621u, 1935759908u, 1908874354u, 1882725390u, 1857283155u, 1832519380u,
        1808407283u, 1784921474u, 1762037865u, 1739733588u, 1717986918u, 1696777203u,
        1676084798u, 1655891006u, 1636178018u, 1616928864u, 1598127366u, 1579758086u,
        1561806289u, 1544257904u, 1527099483u, 1510318170u, 1493901668u, 1477838209u,
        1462116526u, 1446725826u, 1431655765u, 1416896428u, 1402438301u, 1388272257u,
        1374389535u, 1360781718u, 1347440720u, 1334358772u, 1321528399u, 1308942414u,
        1296593901u, 1284476201u, 1272582903u, 1260907830u, 1249445032u, 1238188770u,
        1227133513u, 1216273925u, 1205604855u, 1195121335u, 1184818564u, 1174691910u,
        1164736894u, 1154949189u, 1145324612u, 1135859120u, 1126548799u, 1117389866u,
        1108378657u, 1099511628u, 1090785345u, 1082196484u, 1073741824u
    };
    const unsigned s = ecmrt_q_clz32(d);
    const uint32_t m = d << (s - 1u);
    const unsigned j = (unsigned)(m >> 24) - 64u;
    const uint32_t r = tab[j] - (uint32_t)(((uint64_t)(tab[j] - tab[j + 1u]) * (m & 0xFFFFFFu)) >> 24);
    const uint64_t e = ((uint64_t)1 << 62) - (uint64_t)m * r;     /* (2 - m r) in Q61 */
    *sh = 62u - s;
    return (uint32_t)(((uint64_t)r * (e >> 30)) >> 31);
}

/* exp(-x) < 2^-31 for x >= 21.5 in Q26 (c = 1 exactly in Q30) */
#define ECMRT_XMAX_Q26 ((int64_t)1442840576)       /* 21.5 * 2^26 */
#define ECMRT_LOG2E_Q30 ((int64_t)1549082005)      /* log2(e) * 2^30 */
#define ECMRT_LN2_Q30 ((int64_t)744261118)         /* ln(2) * 2^30 */
#define ECMRT_XSMALL_Q26 ((int64_t)1 << 24)        /* 1/4 */
#define ECMRT_XSMALL_Q30 ((int64_t)1 << 28)

/* c[0] + x (c[1] + x (... + x c[n-1])) by Horner from c[n-1], each product rounded to Q30
 * (|x p| < 2^63 for the callers' x and coefficients) */
ECMRT_Q_SHARED int64_t ecmrt_q_horner(const int32_t *c, int n, int64_t x)
{
    int64_t p = c[n - 1];
    int k;
    for (k = n - 2; k >= 0; k--) {
        p = c[k] + ECMRT_RSHR(x * p, ECMRT_Q30);
    }
    return p;
}

/* c = 1 - exp(-x) in Q30 for 0 <= x < 1/4 given in Q30 (the dt/tau of a 10 Hz task, tau >
 * 0.4 s): c = x P(x), P(x) = 1 + a1 x + a2 x^2 + a3 x^3 + a4 x^4 the minimax polynomial of
 * (1 - exp(-x))/x on [0, 1/4] with P(0) = 1 (relative error < 2^-28.4), coefficients in Q30;
 * c within 1.3 LSB of Q30. Horner on (0, 1, a1 .. a4): the last step x (1 + x q) rounds as
 * x + x q, since x 2^30 is a multiple of 2^30. Unrolled unless optimising for size. */
ECMRT_Q_HOT int32_t ecmrt_q_one_minus_exp_neg_small(int64_t x30)
{
#if defined(__OPTIMIZE_SIZE__)
    static const int32_t c[6] = {0, ECMRT_ONE30, -536870529, 178942183, -44560426, 8085459};
    return (int32_t)ecmrt_q_horner(c, 6, x30);
#else
    int64_t q;
    q = 8085459;
    q = -44560426 + ECMRT_RSHR(x30 * q, ECMRT_Q30);
    q = 178942183 + ECMRT_RSHR(x30 * q, ECMRT_Q30);
    q = -536870529 + ECMRT_RSHR(x30 * q, ECMRT_Q30);
    q = ECMRT_RSHR(x30 * q, ECMRT_Q30);
    return (int32_t)(x30 + ECMRT_RSHR(x30 * q, ECMRT_Q30));
#endif
}

/* c = 1 - exp(-x) in Q30 for 1/4 <= x given in Q26 (x >= 21.5 gives 1): exp(-x) = 2^-y,
 * y = x log2(e) = n + j/8 + f: 2^-(j/8) from a table, 2^-f by its Taylor series to r^6
 * (r = f ln2, error < 1e-11) */
static inline int32_t ecmrt_q_one_minus_exp_neg_big(int64_t x)
{
    /* 2^(-j/8) in Q30, j = 0..7 */
    static const int32_t exp2_tab[8] = {
        1073741824, 984625594, 902905651, 827968132,
        759250125, 696235434, 638450708, 585461881
    };
#if defined(__OPTIMIZE_SIZE__)
    /* (-1)^k / k! in Q30, k = 0..6 */
    static const int32_t poly[7] = {
        1073741824, -1073741824, 536870912, -178956971, 44739243, -8947849, 1491308
    };
#endif
    int64_t p;
    int32_t y, f, r, e;
    unsigned n, j;
    if (x >= ECMRT_XMAX_Q26) {
        return ECMRT_ONE30;
    }
    y = (int32_t)ECMRT_RSHR(x * ECMRT_LOG2E_Q30, ECMRT_Q30);   /* Q26, < 31.1 * 2^26 */
    n = (unsigned)y >> 26;
    j = ((unsigned)y >> 23) & 7u;
    f = y & 0x7FFFFF;
    r = (int32_t)ECMRT_RSHR((int64_t)f * ECMRT_LN2_Q30, 26);  /* f ln2 in Q30, < 0.0867 */
#if defined(__OPTIMIZE_SIZE__)
    p = ecmrt_q_horner(poly, 7, r);
#else
    /* the same Horner steps unrolled, on constants */
    p = 1491308;
    p = -8947849 + ECMRT_RSHR(r * p, ECMRT_Q30);
    p = 44739243 + ECMRT_RSHR(r * p, ECMRT_Q30);
    p = -178956971 + ECMRT_RSHR(r * p, ECMRT_Q30);
    p = 536870912 + ECMRT_RSHR(r * p, ECMRT_Q30);
    p = -1073741824 + ECMRT_RSHR(r * p, ECMRT_Q30);
    p = 1073741824 + ECMRT_RSHR(r * p, ECMRT_Q30);
#endif
    e = (int32_t)ECMRT_RSHR((int64_t)exp2_tab[j] * p, ECMRT_Q30);   /* Q30, in (0.5, 1] */
    if (n > 0u) {
        e = (int32_t)(((uint32_t)e + (1u << (n - 1u))) >> n);
    }
    return ECMRT_ONE30 - e;
}

/* c = 1 - exp(-x) in Q30 for x in Q26 (x <= 0 gives 0, x >= 21.5 gives 1) */
static inline int32_t ecmrt_q_one_minus_exp_neg_q26(int64_t x)
{
    if (x <= 0) {
        return 0;
    }
    if (x < ECMRT_XSMALL_Q26) {
        return ecmrt_q_one_minus_exp_neg_small(x << 4);
    }
    return ecmrt_q_one_minus_exp_neg_big(x);
}

#endif /* ECMRT_Q_EXP_H */
