"""Python references of exactly what the generated C computes.

``simulate_f32``    float32, operation for operation as ``c_runtime/ecmrt_f32.h``
                    (numpy float32 arithmetic is IEEE binary32 with one rounding per
                    operation, as is the C built with -ffp-contract=off);
``simulate_fixed``  bit-true integers (numpy int64 / Python int) as ``c_runtime/ecmrt_q.h``,
                    with the same rounding (half up) and saturation.

Both read a :class:`ecmgen.c.codegen.CSpec` - the very numbers written into the C - so a
difference between C and reference is a bug in one of them, never in the constants.
Vectorised where the C has no recurrence (inputs, direction, lookups, coefficients); the
SOC and RC recurrences run sequentially (SOC vectorised when no saturation occurs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .codegen import CSpec
from .qformat import DT_MAX_S, Q30, Q_D, SOC_LIM, quantize

F32 = np.float32
PARAMS = ("r0", "r_fast", "r_slow", "k_fast", "k_slow")

# --- constants of ecmrt_f32.h (same decimal text, hence the same float32) -------------
F_INVLN2 = F32("1.44269502")
F_LN2_HI = F32("0.693145752")
F_LN2_LO = F32("1.42860677e-06")
F_TAYLOR = tuple(F32(s) for s in ("1.98412701e-04", "1.38888892e-03", "8.33333377e-03",
                                  "4.16666679e-02", "1.66666672e-01", "0.5", "1.0"))
F_XMAX = F32(87.0)
F_HALF_LN2 = F32("0.346573591")
F_SERIES_X = F32("0.03125")        # 2^-5 (bits 0x3D000000): below, a short series

# --- constants of ecmrt_q.h --------------------------------------------------------------
ONE30 = 1 << 30
INT32_MIN, INT32_MAX = -2**31, 2**31 - 1
Q_LOG2E = 1549082005
Q_LN2 = 744261118
Q_XMAX26 = 1442840576
Q_EXP2_TAB = (1073741824, 984625594, 902905651, 827968132, 759250125, 696235434, 638450708,
              585461881)
Q_POLY = (1073741824, -1073741824, 536870912, -178956971, 44739243, -8947849, 1491308)


@dataclass(frozen=True)
class RefResult:
    """Per-step outputs of a reference run (float32 values, or int64 raw integers)."""

    v: np.ndarray
    soc: np.ndarray
    u_fast: np.ndarray
    u_slow: np.ndarray
    charging: np.ndarray
    h: np.ndarray | None = None        # hysteresis state (models with effects only)
    u_x: np.ndarray | None = None      # extra RC pair voltage (models with effects only)


def dt_from_time(time_s) -> np.ndarray:
    """dt_k = t_k - t_{k-1}, dt_0 = 0 (as simulate.py)."""
    t = np.asarray(time_s, dtype=np.float64)
    return np.diff(t, prepend=t[:1])


def _direction(i, deadband) -> np.ndarray:
    """1 = charge, 0 = discharge; the deadband keeps the previous one; starts discharge."""
    code = np.where(i > deadband, 1, np.where(i < -deadband, 0, -1)).astype(np.int8)
    idx = np.where(code >= 0, np.arange(code.size), -1)
    np.maximum.accumulate(idx, out=idx)
    return np.where(idx >= 0, code[np.maximum(idx, 0)], 0).astype(np.uint8)


def _segments(x: np.ndarray, soc: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(x, soc, side="right") - 1, 0, x.size - 2)


# =====================================================================================
# float32
# =====================================================================================

def one_minus_exp_neg_f32(x) -> np.ndarray:
    """ecmrt_f32_one_minus_exp_neg: 1 - exp(-x) for float32 x >= 0."""
    x = np.asarray(x, dtype=F32)
    with np.errstate(all="ignore"):
        n = (x * F_INVLN2 + F32(0.5)).astype(np.int32)
        fast = x < F_HALF_LN2                      # no range reduction: n = 0, r = x
        n = np.where((x > 0) & (x < F_XMAX) & ~fast, n, 0)
        fn = n.astype(F32)
        r = np.where(fast, x, (x - fn * F_LN2_HI) - fn * F_LN2_LO)
        t = -r
        q = np.full_like(t, F_TAYLOR[0])
        for c in F_TAYLOR[1:]:
            q = c + t * q
        q = t * q
        s = np.ldexp(F32(1.0), -n).astype(F32)
        big = (F32(1.0) - s) - s * q
        # +0 <= x < 2^-5: x (1 - x (1/2 - x (1/6 - x/24))), alternating signs as in C
        small = -(x * (x * (F32(0.5) + x * (x * F_TAYLOR[3] - F_TAYLOR[4])) - F32(1.0)))
    out = np.where(n == 0, -q, big)
    out = np.where((x < F_SERIES_X) & (x >= 0), small, out)    # -0 and x < 0 give 0 below
    out = np.where(x >= F_XMAX, F32(1.0), out)
    return np.where(x > 0, out, F32(0.0)).astype(F32)


# --- effects (ecmrt_f32_fx.h) -------------------------------------------------------------
F_SQRT_MAGIC = np.uint32(0x1FBD1DF5)
F_LOG1P_SPLIT = F32("0.414213568")
F_SQRT2 = F32("1.41421354")
F_ATANH = tuple(F32(s) for s in ("0.0769230798", "0.0909090936", "0.111111112", "0.142857149",
                                 "0.200000003", "0.333333343"))
F_X_MIN = F32("1.0e-12")


def sqrt_f32(w) -> np.ndarray:
    """ecmrt_f32_fx_sqrt: bit-trick start and four Newton steps, for 1 <= w."""
    w = np.asarray(w, dtype=F32)
    r = ((w.view(np.uint32) >> np.uint32(1)) + F_SQRT_MAGIC).astype(np.uint32).view(F32)
    half = F32(0.5)
    for _ in range(4):
        r = half * (r + w / r)
    return r.astype(F32)


def log1p_f32(y) -> np.ndarray:
    """ecmrt_f32_fx_log1p: log(1 + y) for y >= 0."""
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


def cdr_factor_f32(ai, g_scale, g_inv_i0) -> np.ndarray:
    """ecmrt_f32_fx_cdr_factor: scale * asinh(x) / x, x = max(|i| / i0, 1e-12)."""
    x = np.asarray(ai, dtype=F32) * F32(g_inv_i0)
    x = np.where(x > F_X_MIN, x, F_X_MIN).astype(F32)
    x2 = x * x
    y = x + x2 / (sqrt_f32(x2 + F32(1.0)) + F32(1.0))
    return ((F32(g_scale) * log1p_f32(y)) / x).astype(F32)


def _lerp_f32(y, k, w):
    return y[k] + (y[k + 1] - y[k]) * w


def _weight_f32(grid, soc):
    k = _segments(grid.x, soc)
    with np.errstate(all="ignore"):
        w = (soc - grid.x[k]) * grid.inv_dx[k]
    w = np.where(soc <= grid.x[0], F32(0.0), np.where(soc >= grid.x[-1], F32(1.0), w))
    return k, w.astype(F32)


def _soc_f32(soc0: np.float32, d: np.ndarray) -> np.ndarray:
    """Kahan-compensated, saturated SOC sum, as ecmrt_f32_step step 2."""
    lo, hi, zero = F32(-SOC_LIM), F32(SOC_LIM), F32(0.0)
    out = np.empty_like(d)
    s, c = F32(soc0), zero
    for k, dk in enumerate(d):          # numpy float32 scalars: f32 arithmetic
        y = dk - c
        t = s + y
        c = (t - s) - y
        if t < lo:
            t, c = lo, zero
        elif t > hi:
            t, c = hi, zero
        s = t
        out[k] = s
    return out


def _rc_f32(c: np.ndarray, t: np.ndarray, divide: bool = False, u0=0.0) -> np.ndarray:
    """u += c (t - u), or u += (t - u) / D with divide=True (fixed-dt tables hold D)."""
    out = np.empty_like(t)
    u = F32(u0)
    if divide:
        for k, (dk, tk) in enumerate(zip(c, t)):  # numpy float32 scalars: f32 arithmetic
            u = u + (tk - u) / dk
            out[k] = u
    else:
        for k, (ck, tk) in enumerate(zip(c, t)):
            u = u + ck * (tk - u)
            out[k] = u
    return out


def simulate_f32(spec: CSpec, current_a, dt_s=None, soc0: float = 1.0) -> RefResult:
    """Float32 reference of a numeric="float" spec. ``dt_s``: per-step dt array (variable-dt
    spec; e.g. dt_from_time(t)) or None (fixed-dt spec)."""
    if spec.fixed:
        raise ValueError("simulate_f32 needs a numeric='float' spec")
    i = np.asarray(current_a, dtype=np.float64).astype(F32)
    imax = F32(spec.i_lim_a)
    i = np.where(np.isnan(i), F32(0.0), np.clip(i, -imax, imax)).astype(F32)
    if spec.variable_dt:
        if dt_s is None:
            raise ValueError("this spec has a variable dt: give dt_s per step")
        dt = np.asarray(dt_s, dtype=np.float64).astype(F32)
        if dt.shape != i.shape:
            raise ValueError("current and dt differ in length")
        dt = np.where(dt > 0, np.minimum(dt, F32(DT_MAX_S)), F32(0.0)).astype(F32)
        dsoc = (i * dt) * spec.k_soc
    else:
        dt = None
        dsoc = i * spec.k_soc
    chg = _direction(i, spec.deadband)
    s0 = F32(soc0)
    s0 = F32(0.0) if np.isnan(s0) else np.clip(s0, F32(-SOC_LIM), F32(SOC_LIM))
    soc = _soc_f32(F32(s0), dsoc.astype(F32))

    per_dir = []
    for d in spec.dirs:
        k, w = _weight_f32(d.grid, soc)
        p = {name: _lerp_f32(getattr(d, name), k, w) for name in PARAMS}
        per_dir.append(p)
    p = {name: np.where(chg == 1, per_dir[1][name], per_dir[0][name]).astype(F32) for name in per_dir[0]}
    fx = spec.fx
    ai = np.abs(i).astype(F32)
    if fx and fx["cdr"]:
        g = cdr_factor_f32(ai, fx["g_scale"], fx["g_inv_i0"])
        p["r0"] = (p["r0"] * g).astype(F32)
        p["r_fast"] = (p["r_fast"] * g).astype(F32)
    if spec.variable_dt:
        with np.errstate(all="ignore"):
            cf = one_minus_exp_neg_f32(dt / p["k_fast"])
            cs = one_minus_exp_neg_f32(dt / p["k_slow"])
        uf = _rc_f32(cf, p["r_fast"] * i)
        us = _rc_f32(cs, p["r_slow"] * i)
    else:
        uf = _rc_f32(p["k_fast"], p["r_fast"] * i, divide=True)
        us = _rc_f32(p["k_slow"], p["r_slow"] * i, divide=True)
    k, w = _weight_f32(spec.ocv_grid, soc)
    ocv = _lerp_f32(spec.ocv, k, w)
    v = ((ocv + p["r0"] * i) + uf) + us
    if not fx:
        return RefResult(v.astype(F32), soc, uf, us, chg)
    n = i.size
    h = np.full(n, F32(fx["h_init"]), dtype=F32)
    ux = np.zeros(n, dtype=F32)
    if fx["hyst"]:
        sg = np.where(chg == 1, F32(1.0), F32(-1.0)).astype(F32)
        x = (ai * dt) * F32(fx["h_k"]) if spec.variable_dt else ai * F32(fx["h_k"])
        ch = one_minus_exp_neg_f32(x)
        h = _rc_f32(ch, sg, u0=fx["h_init"])
        vh = F32(fx["h_m"]) * (h - F32(fx["h_ref"])) + F32(fx["h_m0"]) * (sg - F32(fx["h_ref"]))
    if fx["xrc"]:
        t = F32(fx["x_r"]) * i
        if spec.variable_dt:
            with np.errstate(all="ignore"):
                ux = _rc_f32(one_minus_exp_neg_f32(dt / F32(fx["x_k"])), t)
        else:
            ux = _rc_f32(np.full(n, F32(fx["x_k"]), dtype=F32), t, divide=True)
    if fx["hyst"] and fx["xrc"]:
        v = v + (vh + ux)
    elif fx["hyst"]:
        v = v + vh
    else:
        v = v + ux
    return RefResult(v.astype(F32), soc, uf, us, chg, h.astype(F32), ux.astype(F32))


# =====================================================================================
# fixed point (bit-true)
# =====================================================================================

def _rshr(x, n: int):
    """(x + 2^(n-1)) >> n on int64 arrays (arithmetic shift: floor)."""
    return (x + (np.int64(1) << np.int64(n - 1))) >> np.int64(n)


def _sat32(x):
    return np.clip(x, INT32_MIN, INT32_MAX)


def one_minus_exp_neg_q(dt_raw, tau_raw, q_t: int) -> np.ndarray:
    """ecmrt_q_one_minus_exp_neg: 1 - exp(-dt/tau) in Q30; dt in Q16, tau in Q_T."""
    dt = np.asarray(dt_raw, dtype=np.int64)
    tau = np.asarray(tau_raw, dtype=np.int64)
    dt, tau = np.broadcast_arrays(dt, tau)
    num = dt * (np.int64(1) << np.int64(26 + q_t - Q_D))
    big = num >= tau * Q_XMAX26
    zero = (dt <= 0) | (tau <= 0)
    safe_tau = np.where(zero | big, 1, tau)
    x = np.where(zero | big, 0, (num + (safe_tau >> 1)) // safe_tau)
    return _one_minus_exp_q26(x, zero, big)


def one_minus_exp_neg_q26(x_raw) -> np.ndarray:
    """ecmrt_q_fx_one_minus_exp_neg_q26: 1 - exp(-x) in Q30 for x in Q26 (int64)."""
    x = np.asarray(x_raw, dtype=np.int64)
    zero = x <= 0
    big = x >= Q_XMAX26
    return _one_minus_exp_q26(np.where(zero | big, 0, x), zero, big)


def _one_minus_exp_q26(x, zero, big) -> np.ndarray:
    """The shared core of both C routines: 1 - exp(-x) in Q30, x in Q26 (0 where
    zero | big), as 2^-n * table[j] * poly(r); 0 where ``zero``, 1.0 where ``big``."""
    y = _rshr(x * Q_LOG2E, 30)
    n = y >> 26
    j = (y >> 23) & 7
    f = y & 0x7FFFFF
    r = _rshr(f * Q_LN2, 26)
    p = np.full_like(r, Q_POLY[6])
    for c in Q_POLY[5::-1]:
        p = c + _rshr(r * p, 30)
    e = _rshr(np.asarray(Q_EXP2_TAB, dtype=np.int64)[j] * p, 30)
    e = np.where(n > 0, (e + (np.int64(1) << np.maximum(n - 1, 0))) >> n, e)
    return np.where(zero, 0, np.where(big, ONE30, ONE30 - e)).astype(np.int64)


CDR_K = 6          # ECMRT_FX_CDR_K: 2^6 table segments per binade


def cdr_factor_q(ai, fx: dict) -> np.ndarray:
    """ecmrt_q_fx_cdr_factor: g = scale asinh(x)/x in Q(CDR_QG) for ai = |i| (Q_I, int64)."""
    ai = np.asarray(ai, dtype=np.int64)
    x = _sat32(_rshr(ai * np.int64(fx["g_k"]), fx["SH_GX"]))
    qx = int(fx["CDR_QX"])
    big = x >= (1 << qx)
    b = np.frexp(np.maximum(x, 1).astype(np.float64))[1].astype(np.int64) - 1   # exact: x < 2^31
    s = np.where(big, b - CDR_K, qx - CDR_K).astype(np.int64)
    idx = np.where(big, ((b - qx) << CDR_K) + (x >> s), x >> s)
    w = (x & ((np.int64(1) << s) - 1)) << (30 - s)
    tab = np.asarray(fx["g_tab"], dtype=np.int64)
    return _lerp_q(tab, idx, w)


def _rc_q_fx(c: np.ndarray, t: np.ndarray, u0: int = 0) -> np.ndarray:
    """ECMRT_Q_RC with Q30 coefficients from u0 (c and t arrays of Python ints)."""
    out = np.empty(len(t), dtype=np.int64)
    u = int(u0)
    half = 1 << 29
    for k, (ck, tk) in enumerate(zip(c.tolist(), t.tolist())):
        u = min(INT32_MAX, max(INT32_MIN, u + (((tk - u) * ck + half) >> 30)))
        out[k] = u
    return out


def _weight_q(grid, soc, g: int):
    k = _segments(grid.x, soc)
    w = _rshr((soc - grid.x[k]) * grid.inv_dx[k], g)
    w = np.minimum(w, ONE30)
    w = np.where(soc <= grid.x[0], 0, np.where(soc >= grid.x[-1], ONE30, w))
    return k, w.astype(np.int64)


def _lerp_q(y, k, w):
    return y[k] + _rshr((y[k + 1] - y[k]) * w, 30)


def _soc_q(soc0: int, inc: np.ndarray, sh: int) -> np.ndarray:
    """SOC with the sub-LSB remainder carried (ecmrt_q_step step 2): without saturation
    soc_k = soc0 + floor(sum(inc[:k+1]) / 2^sh) exactly."""
    n = inc.size
    if n and int(np.max(np.abs(inc))) < 2**62 // n:
        cum = np.cumsum(inc)
        soc = soc0 + (cum >> sh)
        if np.all(soc >= INT32_MIN) and np.all(soc <= INT32_MAX):
            return soc
    out = np.empty(n, dtype=np.int64)
    s, rem = int(soc0), 0
    for k, d in enumerate(inc.tolist()):
        acc = rem + d
        rem = acc & ((1 << sh) - 1)
        s = min(INT32_MAX, max(INT32_MIN, s + (acc >> sh)))
        out[k] = s
    return out


def _rc_q(c: np.ndarray, t: np.ndarray, qc: int) -> np.ndarray:
    out = np.empty_like(t)
    u = 0
    half = 1 << (qc - 1)
    for k, (ck, tk) in enumerate(zip(c.tolist(), t.tolist())):
        u = min(INT32_MAX, max(INT32_MIN, u + (((tk - u) * ck + half) >> qc)))
        out[k] = u
    return out


def simulate_fixed_raw(spec: CSpec, i_raw, dt_raw=None, soc0_raw: int = ONE30) -> RefResult:
    """Bit-true reference of a numeric="fixed" spec on raw integers: i in Q_I, dt in Q16
    (variable dt), soc0 in Q30. Returns raw int64 arrays (v in Q_V)."""
    if not spec.fixed:
        raise ValueError("simulate_fixed_raw needs a numeric='fixed' spec")
    q = spec.q
    i = _sat32(np.asarray(i_raw, dtype=np.int64))
    if spec.variable_dt:
        if dt_raw is None:
            raise ValueError("this spec has a variable dt: give dt per step")
        dt = np.maximum(_sat32(np.asarray(dt_raw, dtype=np.int64)), 0)
        if dt.shape != i.shape:
            raise ValueError("current and dt differ in length")
        rate = _sat32(_rshr(i * spec.k_soc, q["SH_RATE"]))
        inc = rate * dt
    else:
        dt = None
        inc = i * spec.k_soc
    chg = _direction(i, spec.deadband)
    soc = _soc_q(int(np.clip(soc0_raw, INT32_MIN, INT32_MAX)), inc, q["SH_DSOC"])

    per_dir = []
    for d in spec.dirs:
        k, w = _weight_q(d.grid, soc, q["Q_G"])
        per_dir.append({name: _lerp_q(getattr(d, name), k, w) for name in PARAMS})
    p = {name: np.where(chg == 1, per_dir[1][name], per_dir[0][name]) for name in per_dir[0]}
    if spec.variable_dt:
        cf = one_minus_exp_neg_q(dt, p["k_fast"], q["Q_T"])
        cs = one_minus_exp_neg_q(dt, p["k_slow"], q["Q_T"])
        qcf = qcs = Q30
    else:
        qcf, qcs = q["Q_CF"], q["Q_CS"]
        cf = ((1 << (qcf + q["Q_DF"])) + (p["k_fast"] >> 1)) // p["k_fast"]
        cs = ((1 << (qcs + q["Q_DS"])) + (p["k_slow"] >> 1)) // p["k_slow"]
    q_i, q_v = q["Q_I"], q["Q_V"]
    fx = spec.fx
    tf = _rshr(p["r_fast"] * i, q["Q_RF"] + q_i - q_v)
    r0i = _rshr(p["r0"] * i, q["Q_R0"] + q_i - q_v)
    if fx and fx["cdr"]:
        g = cdr_factor_q(np.abs(i), fx)
        tf = _rshr(tf * g, fx["CDR_QG"])
        r0i = _rshr(r0i * g, fx["CDR_QG"])
    uf = _rc_q(cf, tf, qcf)
    us = _rc_q(cs, _rshr(p["r_slow"] * i, q["Q_RS"] + q_i - q_v), qcs)
    k, w = _weight_q(spec.ocv_grid, soc, q["Q_G"])
    ocv = _lerp_q(spec.ocv, k, w)
    v = ((ocv + r0i) + uf) + us
    if not fx:
        return RefResult(_sat32(v).astype(np.int64), soc, uf, us, chg)
    n = i.size
    h = np.full(n, fx["h_init"], dtype=np.int64)
    ux = np.zeros(n, dtype=np.int64)
    if fx["hyst"]:
        ai = np.abs(i)
        sg = np.where(chg == 1, ONE30, -ONE30).astype(np.int64)
        if spec.variable_dt:
            x = _rshr(_sat32(_rshr(ai * fx["h_k"], fx["SH_HR"])) * dt, fx["SH_HX"])
        else:
            x = _rshr(ai * fx["h_k"], fx["SH_HX"])
        h = _rc_q_fx(one_minus_exp_neg_q26(x), sg, fx["h_init"])
        vh = (_rshr(fx["h_m"] * (h - fx["h_ref"]), fx["SH_HM"])
              + _rshr(fx["h_m0"] * (sg - fx["h_ref"]), fx["SH_HM"]))
        v = v + vh
    if fx["xrc"]:
        if spec.variable_dt:
            cx = one_minus_exp_neg_q(dt, np.full(n, fx["x_k"], dtype=np.int64), q["Q_T"])
        else:
            cx = np.full(n, fx["x_k"], dtype=np.int64)
        ux = _rc_q_fx(cx, _rshr(np.int64(fx["x_r"]) * i, fx["SH_XR"]))
        v = v + ux
    return RefResult(_sat32(v).astype(np.int64), soc, uf, us, chg, h, ux)


# --- conversions between SI values and the fixed-point API ----------------------------

def current_to_raw(spec: CSpec, current_a) -> np.ndarray:
    i = np.nan_to_num(np.asarray(current_a, dtype=np.float64), nan=0.0)
    return quantize(i, spec.q["Q_I"])


def dt_to_raw(dt_s) -> np.ndarray:
    dt = np.nan_to_num(np.asarray(dt_s, dtype=np.float64), nan=0.0)
    return quantize(dt, Q_D)


def soc_to_raw(soc) -> int:
    return int(quantize([soc], Q30)[0])


def volts(spec: CSpec, v_raw) -> np.ndarray:
    return np.ldexp(np.asarray(v_raw, dtype=np.float64), -spec.q["Q_V"])


def simulate_fixed(spec: CSpec, current_a, dt_s=None, soc0: float = 1.0):
    """Quantise SI inputs as the C caller would, run the bit-true reference.
    Returns (RefResult of raw integers, voltage in V as float64)."""
    i_raw = current_to_raw(spec, current_a)
    dt_raw = dt_to_raw(dt_s) if spec.variable_dt else None
    ref = simulate_fixed_raw(spec, i_raw, dt_raw, soc_to_raw(soc0))
    return ref, volts(spec, ref.v)
