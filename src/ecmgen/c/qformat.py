"""Q-format arithmetic of the fixed-point C: the formats, the one quantiser, and the
integer asinh(x)/x table of ``current_dependent_resistance``.

Shared by the code generator (:mod:`ecmgen.c.codegen`, which picks the formats and
quantises the tables) and the bit-true reference (:mod:`ecmgen.c.cref`); the float
saturation limits the references mirror live here too.
"""

from __future__ import annotations

import math

import numpy as np

CDR_SEG_BITS = 6            # fixed point: 2^6 linear segments in [0, 1) and in every binade of x
CDR_E_MAX = 16              # fixed point: |i| / i0_a must stay below 2^16 (table size)
Q30 = 30
Q_D = 16                    # dt input of the variable-dt fixed-point step
Q_TEMP = 8                  # temperature input of the fixed-point step, degC
DT_MAX_S = 32767.0          # dt saturation (float); Q16 int32 range (fixed)
SOC_LIM = 2.0               # SOC saturates at +-2 (float) / int32 Q30 range (fixed)
INT32_MAX = 2**31 - 1


def _q_fit(vmax: float, bits: int = 31, cap: int = 62) -> int:
    """Largest Q (<= cap) with round(vmax * 2^Q) <= 2^bits - 1."""
    limit = 2**bits - 1
    ratio = limit / vmax if vmax > 0 else math.inf
    if ratio >= 2.0**cap:       # 0, or so small (1e-300) that limit / vmax overflows
        return cap
    q = min(cap, math.floor(math.log2(ratio)))
    while math.floor(math.ldexp(vmax, q) + 0.5) > limit:
        q -= 1
    return q


def quantize(values, q: int) -> np.ndarray:
    """round(v * 2^q) half up, saturated to int32, as int64 (the one quantiser of ecmgen)."""
    v = np.ldexp(np.asarray(values, dtype=np.float64), q)
    v = np.floor(v + 0.5)
    return np.clip(v, -2**31, INT32_MAX).astype(np.int64)


def cdr_nodes(e_bins: int, k: int = CDR_SEG_BITS) -> np.ndarray:
    """x of the fixed-point g table: 2^k uniform segments in [0, 1), then 2^k uniform
    segments in each binade [2^b, 2^(b+1)), b = 0 .. e_bins - 1 (last node 2^e_bins)."""
    idx = np.arange((e_bins + 1) * 2**k + 1)
    return np.where(idx < 2**k, idx / 2.0**k,
                    np.ldexp(1.0 + (idx % 2**k) / 2.0**k, np.maximum(idx // 2**k - 1, 0)))


def cdr_table(scale: float, e_bins: int, k: int = CDR_SEG_BITS) -> np.ndarray:
    """scale * asinh(x)/x at cdr_nodes (float64), each node moved by minus a quarter of the
    chord errors at the midpoints of its two segments (half at the ends), which roughly halves
    the error of linear interpolation (max relative error ~2.3e-5 with k = 6)."""
    def f(x):
        x = np.asarray(x, dtype=np.float64)
        safe = np.where(x > 1e-6, x, 1.0)
        return np.where(x > 1e-6, np.arcsinh(safe) / safe, 1.0 - x * x / 6.0)

    x = cdr_nodes(e_bins, k)
    y = f(x)
    e = 0.5 * (y[1:] + y[:-1]) - f(0.5 * (x[1:] + x[:-1]))
    adj = y.copy()
    adj[1:-1] -= 0.25 * (e[1:] + e[:-1])
    adj[0] -= 0.5 * e[0]
    adj[-1] -= 0.5 * e[-1]
    return scale * adj


# seed of ecmrt_q_recip: 2^31 / (1 + j/64), j = 0..64, rounded
RECIP_TAB = np.array([round(2**37 / (64 + j)) for j in range(65)], dtype=np.int64)


def bit_length(x) -> np.ndarray:
    """Bit length of non-negative int64 values below 2^53 (0 for 0)."""
    x = np.asarray(x, dtype=np.int64)
    return np.frexp(x.astype(np.float64))[1].astype(np.int64)


def recip_q(d):
    """ecmrt_q_recip: (r, sh) with 1/d ~ r 2^-sh, r in (2^30, 2^31], for 1 <= d < 2^31:
    d normalised to m in [2^30, 2^31), a linearly interpolated seed of 2^61/m and one
    Newton step, in integers (int64 arrays)."""
    d = np.asarray(d, dtype=np.int64)
    s = 32 - bit_length(d)
    m = d << (s - 1)
    j = (m >> 24) - 64
    r = RECIP_TAB[j] - (((RECIP_TAB[j] - RECIP_TAB[j + 1]) * (m & 0xFFFFFF)) >> 24)
    e = (np.int64(1) << np.int64(62)) - m * r
    return (r * (e >> 30)) >> 31, 62 - s


def rate_q(tau_raw, q_t: int, q_kr: int) -> np.ndarray:
    """ecmrt_q_rate: 1/tau in Q_KR from tau in Q_T (> 0): with r 2^-sh = 1/tau_raw,
    round(2 r 2^-(sh + 1 - Q_T - Q_KR)) (int64 arrays)."""
    r, sh = recip_q(np.asarray(tau_raw, dtype=np.int64))
    k = sh + 1 - (q_t + q_kr)
    return ((r << 1) + (np.int64(1) << (k - 1))) >> k
