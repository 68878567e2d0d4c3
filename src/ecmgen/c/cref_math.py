"""The float32 maths of ``c_runtime/ecmrt_f32.h`` without libm, operation for operation:
1 - exp(-x), the Arrhenius factor, sqrt, log1p, asinh (numpy float32 arithmetic is IEEE
binary32 with one rounding per operation, as is the C built with -ffp-contract=off). The
constants have the C's decimal text, hence the same float32. Re-exported by
:mod:`ecmgen.c.cref`."""

from __future__ import annotations

import numpy as np

F32 = np.float32

# --- constants of ecmrt_f32.h (same decimal text, hence the same float32) -------------
F_INVLN2 = F32("1.44269502")
F_LN2_HI = F32("0.693145752")
F_LN2_LO = F32("1.42860677e-06")
F_TAYLOR = tuple(F32(s) for s in ("1.98412701e-04", "1.38888892e-03", "8.33333377e-03",
                                  "4.16666679e-02", "1.66666672e-01", "0.5", "1.0"))
F_XMAX = F32(87.0)
F_HALF_LN2 = F32("0.346573591")
F_SERIES_X = F32("0.25")           # bits 0x3E800000: below, the polynomial F_SMALL
# 1 - exp(-x) = x (1 - b1 x + b2 x^2 - b3 x^3 + b4 x^4) on [0, 1/4]: (b4, b3, b2, b1)
F_SMALL = tuple(F32(s) for s in ("7.53017003e-03", "4.15001325e-02", "1.66652888e-01",
                                 "4.99999642e-01"))
F_KELVIN = F32("273.149994")
F_ARR_T = (F32(-40.0), F32(85.0))


def _exp_neg_parts_f32(x):
    """ecmrt_f32_exp_neg_parts: (q, s) with exp(-x) = s (1 + q), 0 <= x < 87."""
    x = np.asarray(x, dtype=F32)
    with np.errstate(all="ignore"):
        n = np.where(x < F_HALF_LN2, 0, (x * F_INVLN2 + F32(0.5)).astype(np.int32))
        n = np.where((x >= 0) & (x < F_XMAX), n, 0).astype(np.int32)
        fn = n.astype(F32)
        r = np.where(n == 0, x, (x - fn * F_LN2_HI) - fn * F_LN2_LO).astype(F32)
        t = -r
        q = np.full_like(t, F_TAYLOR[0])
        for c in F_TAYLOR[1:]:
            q = c + t * q
        q = t * q
    return q.astype(F32), np.ldexp(F32(1.0), -n).astype(F32)


def one_minus_exp_neg_f32(x) -> np.ndarray:
    """ecmrt_f32_one_minus_exp_neg: 1 - exp(-x) for float32 x >= 0."""
    x = np.asarray(x, dtype=F32)
    q, s = _exp_neg_parts_f32(x)
    with np.errstate(all="ignore"):
        out = (F32(1.0) - s) - s * q
        # +0 <= x < 1/4: the minimax polynomial, as in C
        b4, b3, b2, b1 = F_SMALL
        q = x * b4 - b3
        q = x * q + b2
        q = x * q - b1
        q = x * q + F32(1.0)
        small = x * q
    out = np.where((x < F_SERIES_X) & (x >= 0), small, out)    # -0 and x < 0 give 0 below
    out = np.where(x >= F_XMAX, F32(1.0), out)
    return np.where(x > 0, out, F32(0.0)).astype(F32)


def arrhenius_f32(temp, a_k, a_inv_ref) -> np.ndarray:
    """ecmrt_f32_arrhenius: exp(a_k (1/(T + 273.15) - inv_ref)), T saturated to [-40, 85]."""
    t = np.asarray(temp, dtype=F32)
    t = np.where(t >= F_ARR_T[0], t, F_ARR_T[0])
    t = np.where(t > F_ARR_T[1], F_ARR_T[1], t).astype(F32)
    y = ((F32(1.0) / (t + F_KELVIN)) - F32(a_inv_ref)) * F32(a_k)
    pos = y > 0
    q, s = _exp_neg_parts_f32(np.where(pos, y, -y))
    e = s + s * q
    with np.errstate(all="ignore"):
        return np.where(pos, F32(1.0) / e, e).astype(F32)


# --- asinh (ecmrt_f32.h, effects and Butler-Volmer) ----------------------------------------
F_SQRT_MAGIC = np.uint32(0x1FBD1DF5)
F_LOG1P_SPLIT = F32("0.414213568")
F_SQRT2 = F32("1.41421354")
F_ATANH = tuple(F32(s) for s in ("0.0769230798", "0.0909090936", "0.111111112", "0.142857149",
                                 "0.200000003", "0.333333343"))
F_X_MIN = F32("1.0e-12")


def sqrt_f32(w) -> np.ndarray:
    """ecmrt_f32_sqrt: bit-trick start and four Newton steps, for 1 <= w and 1e-12 < w <= 1."""
    w = np.asarray(w, dtype=F32)
    r = ((w.view(np.uint32) >> np.uint32(1)) + F_SQRT_MAGIC).astype(np.uint32).view(F32)
    half = F32(0.5)
    for _ in range(4):
        r = half * (r + w / r)
    return r.astype(F32)


def log1p_f32(y) -> np.ndarray:
    """ecmrt_f32_log1p: log(1 + y) for y >= 0."""
    y = np.atleast_1d(np.asarray(y, dtype=F32))
    z = (F32(1.0) + y).astype(F32)
    zb = z.view(np.uint32)
    n = ((zb >> np.uint32(23)) & np.uint32(0xFF)).astype(np.int32) - 127
    m = ((zb & np.uint32(0x007FFFFF)) | np.uint32(0x3F800000)).astype(np.uint32).view(F32)
    big = m > F_SQRT2
    m = np.where(big, m * F32(0.5), m).astype(F32)
    n = np.where(big, n + 1, n)
    f = (m - F32(1.0)).astype(F32)
    small = y < F_LOG1P_SPLIT
    f = np.where(small, y, f).astype(F32)
    n = np.where(small, 0, n).astype(np.int32)
    t = f / (F32(2.0) + f)
    t2 = t * t
    p = np.full_like(t, F_ATANH[0])
    for c in F_ATANH[1:]:
        p = c + t2 * p
    tt = F32(2.0) * t
    p = tt + tt * (t2 * p)
    fn = n.astype(F32)
    big_out = (fn * F_LN2_HI + p) + fn * F_LN2_LO
    return np.where(n == 0, p, big_out).astype(F32)


def asinh_f32(x):
    """ecmrt_f32_asinh: (asinh(x'), x') with x' = max(x, 1e-12)."""
    x = np.asarray(x, dtype=F32)
    x = np.where(x > F_X_MIN, x, F_X_MIN).astype(F32)
    x2 = x * x
    return log1p_f32(x + x2 / (sqrt_f32(x2 + F32(1.0)) + F32(1.0))), x


def cdr_factor_f32(ai, g_scale, g_inv_i0) -> np.ndarray:
    """current_dependent_resistance, float: scale * asinh(x) / x, x = max(|i| / i0, 1e-12)."""
    a, x = asinh_f32(np.asarray(ai, dtype=F32) * F32(g_inv_i0))
    return ((F32(g_scale) * a) / x).astype(F32)
