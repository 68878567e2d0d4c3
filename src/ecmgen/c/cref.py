"""Python references of exactly what the generated C computes.

``simulate_f32``    float32, operation for operation as the generated step (the units of
                    ``c_runtime/ecmrt_f32_step.h`` it calls, by the same names; the maths in :mod:`ecmgen.c.cref_math`)
                    (numpy float32 arithmetic is IEEE binary32 with one rounding per
                    operation, as is the C built with -ffp-contract=off);
``simulate_fixed``  bit-true integers (numpy int64 / Python int) as the generated fixed-point
                    step (``c_runtime/ecmrt_q_step.h``'s units), with the same rounding (half up) and saturation.

Both read a :class:`ecmgen.c.spec.CSpec` - the very numbers written into the C - so a
difference between C and reference is a bug in one of them, never in the constants.
Vectorised where the C has no recurrence (inputs, direction, lookups, coefficients); the
SOC and RC recurrences run sequentially (SOC vectorised when no saturation occurs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cref_math import (  # noqa: F401  (the float32 maths, re-exported)
    F_INVLN2, F_LN2_HI, F_LN2_LO, F_TAYLOR, F_XMAX, F_HALF_LN2, F_SERIES_X, F_SMALL, F_KELVIN,
    F_ARR_T, F_SQRT_MAGIC, F_LOG1P_SPLIT, F_SQRT2, F_ATANH, F_X_MIN, _exp_neg_parts_f32,
    one_minus_exp_neg_f32, arrhenius_f32, sqrt_f32, log1p_f32, asinh_f32, cdr_factor_f32)
from .qformat import DT_MAX_S, Q30, Q_D, Q_TEMP, SOC_LIM, quantize, rate_q, recip_q  # noqa: F401
from .spec import CSpec


F32 = np.float32
PARAMS = ("r0", "r_fast", "r_slow", "k_fast", "k_slow")
RESISTANCES = ("r0", "r_fast", "r_slow")

# --- constants of ecmrt_q.h --------------------------------------------------------------
ONE30 = 1 << 30
INT32_MIN, INT32_MAX = -2**31, 2**31 - 1
Q_LOG2E = 1549082005
Q_LN2 = 744261118
Q_XMAX26 = 1442840576
Q_XSMALL26 = 1 << 24                        # 1/4 in Q26
Q_XSMALL30 = 1 << 28
Q_SMALL = (8085459, -44560426, 178942183, -536870529)   # the same polynomial, Q30 (a4 .. a1)
Q_EXP2_TAB = (1073741824, 984625594, 902905651, 827968132, 759250125, 696235434, 638450708,
              585461881)
Q_POLY = (1073741824, -1073741824, 536870912, -178956971, 44739243, -8947849, 1491308)
Q_ARR_T = (-40 * 256, 85 * 256)
Q_ARR_D0, Q_ARR_DLO = 1398528, 1193728      # 273.15 * 5120, (273.15 - 40) * 5120


@dataclass(frozen=True)
class RefResult:
    """Per-step outputs of a reference run (float32 values, or int64 raw integers); a state
    the model does not have is None."""

    v: np.ndarray
    soc: np.ndarray
    u_fast: np.ndarray
    u_slow: np.ndarray
    charging: np.ndarray
    h: np.ndarray | None = None        # hysteresis state
    u_x: np.ndarray | None = None      # extra RC pair voltage
    u_diff: np.ndarray | None = None   # diffusion pair voltage


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


def _segments(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(x, v, side="right") - 1, 0, x.size - 2)


def _temperatures(spec: CSpec, temperature_c, n: int, dtype):
    if temperature_c is None:
        if spec.uses_temperature:
            raise ValueError("this spec reads the cell temperature: give temperature_c")
        return np.zeros(n, dtype=dtype)
    t = np.asarray(temperature_c)
    t = np.full(n, t) if t.ndim == 0 else t
    if t.shape != (n,):
        raise ValueError("current and temperature differ in length")
    return t


# =====================================================================================
# float32
# =====================================================================================

def _weight_f32(grid, v, uniform: bool = False):
    if uniform:          # ecmrt_f32_ulocate
        with np.errstate(all="ignore"):
            u = ((v - grid.x0) * grid.inv_h).astype(F32)
            below, above = ~(u >= 0), ~(u < F32(grid.n - 1))
            k = np.where(below | above, 0, u).astype(np.int64)
            w = (u - k.astype(F32)).astype(F32)
        k = np.where(above & ~below, grid.n - 2, k)
        w = np.where(below, F32(0.0), np.where(above, F32(1.0), w))
        return k, w.astype(F32)
    k = _segments(grid.x, v)
    with np.errstate(all="ignore"):
        w = (v - grid.x[k]) * grid.inv_dx[k]
    w = np.where(v < grid.x[0], F32(0.0), np.where(v >= grid.x[-1], F32(1.0), w))
    return k, w.astype(F32)


def _lerp_f32(y, k, w, kt=None, wt=None):
    """ecmrt_f32_lerp (y 1-D, or a row y[0] of a table), or over temperature the segment
    pairs of ecmrt_f32_segment (a, b at points k, k + 1, linear in temperature) then SOC."""
    if kt is None:
        y = y[0] if y.ndim == 2 else y
        return y[k] + (y[k + 1] - y[k]) * w
    a = y[kt, k] + (y[kt + 1, k] - y[kt, k]) * wt
    b = y[kt, k + 1] + (y[kt + 1, k + 1] - y[kt, k + 1]) * wt
    return a + (b - a) * w


def _tv_f32(b, kt, wt):
    """A per-temperature value at T: b[kt] + (b[kt+1] - b[kt]) wt, or b[0] (one row)."""
    if kt is None:
        return b[0]
    return b[kt] + (b[kt + 1] - b[kt]) * wt


def _soc_f32(soc0: np.float32, d: np.ndarray) -> np.ndarray:
    """Kahan-compensated, saturated SOC sum, as ecmrt_f32_count (the step's stage 2)."""
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
    c = np.broadcast_to(np.asarray(c, dtype=F32), t.shape)
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


def _pick(chg, per_dir, name):
    return np.where(chg == 1, per_dir[1][name], per_dir[0][name])


def _branch_f32(spec: CSpec, d, kt, wt) -> dict:
    """A direction's per-temperature values at the temperature (k_diff as 1/tau or 1/D
    with time constants of the temperature only, as <prefix>_coefs_f32 keeps it)."""
    p = {name: _tv_f32(getattr(d, name), kt, wt) for name in ("r_diff", "k_diff", "i0")
         if getattr(d, name) is not None}
    if spec.tau_t and "k_diff" in p:
        with np.errstate(all="ignore"):
            p["k_diff"] = F32(1.0) / p["k_diff"]
    return p


def age_f32(spec: CSpec, efc):
    """ecmrt_f32_age: (resistance scale, k_soc) at efc equivalent full cycles (None: 0)."""
    g = spec.age["grid"]
    e = F32(0.0 if efc is None else efc)
    k, w = _weight_f32(g, np.array([e if e >= g.x[0] else g.x[0]], dtype=F32))
    return (_lerp_f32(spec.age["r"], k, w)[0],
            (spec.k_soc * _lerp_f32(spec.age["iq"], k, w))[0])


def _u_diff_f32(spec: CSpec, per_dir, chg, i, dt, age_r=None) -> np.ndarray:
    """The diffusion pair's voltage after every step (its values depend on T only)."""
    rd = _pick(chg, per_dir, "r_diff").astype(F32)
    t = ((rd if age_r is None else (rd * age_r).astype(F32)) * i).astype(F32)
    kd = _pick(chg, per_dir, "k_diff").astype(F32)
    with np.errstate(all="ignore"):
        if spec.tau_t:
            return _rc_f32(one_minus_exp_neg_f32(dt * kd) if spec.variable_dt else kd, t)
        if spec.variable_dt:
            return _rc_f32(one_minus_exp_neg_f32(dt / kd), t)
    return _rc_f32(kd, t, divide=True)


# The step's units (c_runtime/ecmrt_f32_step.h, called by the generated step of a model
# that has them, templates/ecm_step_f32.c.j2), one per stage and effect, over the whole
# record at once; an effect that is off leaves p as it is or gives -0.0 (NO_TERM_F32).
NO_TERM_F32 = F32(-0.0)


def _fx_cdr_f32(fx: dict, ai, p: dict) -> None:
    """ecmrt_f32_fx_cdr: r0, r_fast times scale asinh(x)/x (current_dependent_resistance)."""
    if fx.get("cdr"):
        g = cdr_factor_f32(ai, fx["g_scale"], fx["g_inv_i0"])
        p["r0"], p["r_fast"] = (p["r0"] * g).astype(F32), (p["r_fast"] * g).astype(F32)


def _fx_arr_f32(fx: dict, temp, p: dict) -> None:
    """ecmrt_f32_fx_arr: r0, r_fast, r_slow times the Arrhenius factor."""
    if fx.get("arr"):
        f = arrhenius_f32(temp, fx["a_k"], fx["a_inv_ref"])
        for name in ("r0", "r_fast", "r_slow"):
            p[name] = (p[name] * f).astype(F32)


def _bv_f32(spec: CSpec, ai, p: dict) -> None:
    """ecmrt_f32_bv: r_fast times asinh(x)/x, x = |i| / i0(T)."""
    if spec.has_bv:
        with np.errstate(all="ignore"):
            a, x = asinh_f32(ai / p["i0"])
            p["r_fast"] = (p["r_fast"] * (a / x)).astype(F32)


def _age_r_f32(age_r, p: dict) -> None:
    """ecmrt_f32_age_r: every resistance times the age's scale."""
    if age_r is not None:
        for name in RESISTANCES:
            p[name] = (p[name] * age_r).astype(F32)


def _rc_pair_f32(spec: CSpec, k, t, dt) -> np.ndarray:
    """ecmrt_f32_zoh (or _zoh_d) with the step's coefficient: one pair's voltage after every
    step, k its 1/tau or c (time constants of the temperature only), its tau (variable dt) or
    its D."""
    if spec.tau_t:
        if spec.variable_dt:
            with np.errstate(all="ignore"):
                k = one_minus_exp_neg_f32(dt * k)
        return _rc_f32(k, t)
    if spec.variable_dt:
        with np.errstate(all="ignore"):
            return _rc_f32(one_minus_exp_neg_f32(dt / k), t)
    return _rc_f32(k, t, divide=True)


def _fx_hyst_f32(spec: CSpec, fx: dict, chg, ai, dt, out: dict):
    """ecmrt_f32_fx_hyst: the hysteresis term (its state into out["h"])."""
    if not fx.get("hyst"):
        return NO_TERM_F32
    sg = np.where(chg == 1, F32(1.0), F32(-1.0)).astype(F32)
    x = (ai * dt) * F32(fx["h_k"]) if spec.variable_dt else ai * F32(fx["h_k"])
    h = out["h"] = _rc_f32(one_minus_exp_neg_f32(x), sg, u0=fx["h_init"])
    return F32(fx["h_m"]) * (h - F32(fx["h_ref"])) + F32(fx["h_m0"]) * (sg - F32(fx["h_ref"]))


def _fx_xrc_f32(spec: CSpec, fx: dict, i, dt, out: dict):
    """ecmrt_f32_fx_xrc: the extra pair's voltage (into out["u_x"] too)."""
    if not fx.get("xrc"):
        return NO_TERM_F32
    t = F32(fx["x_r"]) * i
    if spec.variable_dt:
        with np.errstate(all="ignore"):
            ux = _rc_f32(one_minus_exp_neg_f32(dt / F32(fx["x_k"])), t)
    else:
        ux = _rc_f32(np.full(i.size, F32(fx["x_k"]), dtype=F32), t, divide=True)
    out["u_x"] = ux
    return ux



def simulate_f32(spec: CSpec, current_a, dt_s=None, soc0: float = 1.0,
                 temperature_c=None, efc=None) -> RefResult:
    """Float32 reference of a numeric="float" spec. ``dt_s``: per-step dt array (variable-dt
    spec; e.g. dt_from_time(t)) or None (fixed-dt spec); ``temperature_c``: the cell
    temperature per step or one value (needed when the spec reads it); ``efc``: the age set
    after init (a spec with an ageing law; None: fresh)."""
    if spec.fixed:
        raise ValueError("simulate_f32 needs a numeric='float' spec")
    age_r, k_soc = age_f32(spec, efc) if spec.age is not None else (None, spec.k_soc)
    i = np.asarray(current_a, dtype=np.float64).astype(F32)
    n = i.size
    imax = F32(spec.i_lim_a)
    i = np.where(np.isnan(i), F32(0.0), np.clip(i, -imax, imax)).astype(F32)
    temp = _temperatures(spec, temperature_c, n, np.float64).astype(F32)
    if spec.variable_dt:
        if dt_s is None:
            raise ValueError("this spec has a variable dt: give dt_s per step")
        dt = np.asarray(dt_s, dtype=np.float64).astype(F32)
        if dt.shape != i.shape:
            raise ValueError("current and dt differ in length")
        dt = np.where(dt > 0, np.minimum(dt, F32(DT_MAX_S)), F32(0.0)).astype(F32)
        dsoc = (i * dt) * k_soc
    else:
        dt = None
        dsoc = i * k_soc
    chg = _direction(i, spec.deadband)
    s0 = F32(soc0)
    s0 = F32(0.0) if np.isnan(s0) else np.clip(s0, F32(-SOC_LIM), F32(SOC_LIM))
    soc = _soc_f32(F32(s0), dsoc.astype(F32))
    kt = wt = None
    if spec.temp:
        x0 = spec.temp_grid.x[0]
        kt, wt = _weight_f32(spec.temp_grid, np.where(temp >= x0, temp, x0).astype(F32))

    soc_rc = soc
    if spec.surface is not None:        # ecmrt_f32_surface: u_diff needs no SOC
        ud = _u_diff_f32(spec, [_branch_f32(spec, d, kt, wt) for d in spec.dirs], chg, i, dt,
                         age_r)
        ko, wo = _weight_f32(spec.ocv_grid, soc, spec.ocv_uniform)
        sv = _lerp_f32(spec.surface, ko, wo, kt, wt)
        r = (soc + sv * np.concatenate([[F32(0.0)], ud[:-1]]).astype(F32)).astype(F32)
        soc_rc = np.where(~(r >= 0), F32(0.0), np.where(r > 1, F32(1.0), r)).astype(F32)
    per_dir = []
    for d in spec.dirs:
        k, w = _weight_f32(d.grid, soc_rc, spec.rc_uniform)
        p = {name: _lerp_f32(getattr(d, name), k, w, kt, wt)
             for name in (RESISTANCES if spec.tau_t else PARAMS)}
        p.update(_branch_f32(spec, d, kt, wt))
        if spec.tau_t:       # ecmrt_f32_coefs: 1/tau or 1/D at the temperature
            with np.errstate(all="ignore"):
                for name in ("k_fast", "k_slow"):
                    p[name] = F32(1.0) / _tv_f32(getattr(d, name)[:, 0], kt, wt)
        per_dir.append(p)
    p = {name: _pick(chg, per_dir, name).astype(F32) for name in per_dir[0]}
    fx = spec.fx
    ai = np.abs(i).astype(F32)
    # 3'. parameter effects, in the generated step's order
    _fx_cdr_f32(fx, ai, p)
    _fx_arr_f32(fx, temp, p)
    _bv_f32(spec, ai, p)
    _age_r_f32(age_r, p)
    # 4. the two pairs
    uf = _rc_pair_f32(spec, p["k_fast"], p["r_fast"] * i, dt)
    us = _rc_pair_f32(spec, p["k_slow"], p["r_slow"] * i, dt)
    # 3''. the OCV at the mean SOC; 5. the voltage, the diffusion pair's, the effects' terms
    k, w = (_weight_f32(spec.dirs[0].grid, soc, spec.rc_uniform) if spec.ocv_shared else
            _weight_f32(spec.ocv_grid, soc, spec.ocv_uniform))
    ocv = _lerp_f32(spec.ocv, k, w, kt, wt)
    v = ((ocv + p["r0"] * i) + uf) + us
    out = {}
    if spec.diff:
        out["u_diff"] = _u_diff_f32(spec, per_dir, chg, i, dt, age_r)
        v = v + out["u_diff"]
    vh = _fx_hyst_f32(spec, fx, chg, ai, dt, out)
    ux = _fx_xrc_f32(spec, fx, i, dt, out)
    v = v + (vh + ux)           # an effect that is off adds -0.0 (x + -0.0 is x, bit for bit)
    return RefResult(v.astype(F32), soc, uf, us, chg, **out)


# =====================================================================================
# fixed point (bit-true)
# =====================================================================================

def _rshr(x, n):
    """(x + 2^(n-1)) >> n on int64 arrays (arithmetic shift: floor); n >= 1 (may be an array)."""
    n = np.asarray(n, dtype=np.int64)
    return (x + (np.int64(1) << (n - 1))) >> n


def _sat32(x):
    return np.clip(x, INT32_MIN, INT32_MAX)


def _omexp_small_q(x30):
    """ecmrt_q_one_minus_exp_neg_small: the polynomial, x in Q30 (< 2^28)."""
    x30 = np.asarray(x30, dtype=np.int64)
    q = np.full_like(x30, Q_SMALL[0])
    for c in Q_SMALL[1:]:
        q = c + _rshr(x30 * q, 30)
    q = _rshr(x30 * q, 30)
    return x30 + _rshr(x30 * q, 30)


def _omexp_big_q(x):
    """ecmrt_q_one_minus_exp_neg_big: x in Q26, 2^-5 <= x (>= 21.5 gives 1)."""
    big = x >= Q_XMAX26
    y = _rshr(np.where(big, 0, x) * Q_LOG2E, 30)
    n = y >> 26
    j = (y >> 23) & 7
    f = y & 0x7FFFFF
    r = _rshr(f * Q_LN2, 26)
    p = np.full_like(r, Q_POLY[6])
    for c in Q_POLY[5::-1]:
        p = c + _rshr(r * p, 30)
    e = _rshr(np.asarray(Q_EXP2_TAB, dtype=np.int64)[j] * p, 30)
    e = np.where(n > 0, (e + (np.int64(1) << np.maximum(n - 1, 0))) >> n, e)
    return np.where(big, ONE30, ONE30 - e)


def one_minus_exp_neg_q26(x_raw) -> np.ndarray:
    """ecmrt_q_one_minus_exp_neg_q26: 1 - exp(-x) in Q30 for x in Q26 (int64)."""
    x = np.asarray(x_raw, dtype=np.int64)
    small = x < Q_XSMALL26
    c = np.where(small, _omexp_small_q(np.where(small, np.maximum(x, 0), 0) << 4),
                 _omexp_big_q(np.where(small, Q_XSMALL26, x)))
    return np.where(x <= 0, 0, c).astype(np.int64)


def c_kr_q(dt_raw, kc, q_kr: int) -> np.ndarray:
    """ecmrt_q_c_kr: 1 - exp(-x) in Q30, x = dt kc (dt >= 0 in Q16, kc = 1/tau in Q_KR)."""
    x30 = _rshr(np.asarray(dt_raw, dtype=np.int64) * np.asarray(kc, dtype=np.int64), q_kr - 14)
    small = x30 < Q_XSMALL30
    return np.where(small, _omexp_small_q(np.where(small, x30, 0)),
                    _omexp_big_q(np.where(small, Q_XSMALL26, _rshr(x30, 4)))).astype(np.int64)


def c_rate_q(dt_raw, r, sh) -> np.ndarray:
    """ecmrt_q_c_rate: 1 - exp(-x) in Q30, x = dt r 2^-sh in Q30 (dt >= 0 in Q16)."""
    x30 = _rshr(np.asarray(dt_raw, dtype=np.int64) * np.asarray(r, dtype=np.int64), sh)
    small = x30 < Q_XSMALL30
    return np.where(small, _omexp_small_q(np.where(small, x30, 0)),
                    _omexp_big_q(np.where(small, Q_XSMALL26, _rshr(x30, 4)))).astype(np.int64)


def c_dt_tau_q(dt_raw, tau_raw, q_t: int) -> np.ndarray:
    """ecmrt_q_c_dt_tau: 1 - exp(-dt/tau) in Q30; dt >= 0 in Q16, tau >= 2^(q_t - 16) in
    Q(q_t) (the generator's bound: the shift of c_rate_q is >= 1)."""
    dt, tau = np.broadcast_arrays(np.asarray(dt_raw, dtype=np.int64),
                                  np.asarray(tau_raw, dtype=np.int64))
    r, sh = recip_q(tau)
    return c_rate_q(dt, r, sh - (q_t + 14))


def inv_d_q(d_raw, qcd: int) -> np.ndarray:
    """ecmrt_q_inv_d: 1/D in Q(qcd - Q_D) for D in Q_D (>= 1)."""
    r, sh = recip_q(np.asarray(d_raw, dtype=np.int64))
    return _rshr(r, sh - qcd)


CDR_K = 6          # ECMRT_G_K (ecmrt_q.h): 2^6 table segments per binade


def gtab_q(tab, x, qx: int) -> np.ndarray:
    """ecmrt_q_gtab: the table at x (Q(qx), 0 <= x < 2^31) by linear interpolation."""
    x = np.asarray(x, dtype=np.int64)
    big = x >= (1 << qx)
    b = np.frexp(np.maximum(x, 1).astype(np.float64))[1].astype(np.int64) - 1   # exact: x < 2^31
    s = np.where(big, b - CDR_K, qx - CDR_K).astype(np.int64)
    idx = np.where(big, ((b - qx) << CDR_K) + (x >> s), x >> s)
    w = (x & ((np.int64(1) << s) - 1)) << (30 - s)
    return _lerp_q(np.asarray(tab, dtype=np.int64), idx, w)


def cdr_factor_q(ai, fx: dict) -> np.ndarray:
    """current_dependent_resistance, fixed: g = scale asinh(x)/x in Q(CDR_QG), ai = |i| (Q_I)."""
    ai = np.asarray(ai, dtype=np.int64)
    return gtab_q(fx["g_tab"], _sat32(_rshr(ai * np.int64(fx["g_k"]), fx["SH_GX"])), fx["CDR_QX"])


def arrhenius_q(temp_raw, fx: dict) -> np.ndarray:
    """ecmrt_q_arrhenius: the factor in Q(ARR_QF) for T in Q8."""
    t = np.clip(np.asarray(temp_raw, dtype=np.int64), *Q_ARR_T)
    d = 20 * t + Q_ARR_D0
    r, sh = recip_q(d)
    z = _rshr((d - Q_ARR_DLO) * r, sh - 30)
    e = ONE30 - one_minus_exp_neg_q26(_rshr(np.int64(fx["a_b"]) * z, fx["ARR_QB"] + 4))
    return _rshr(np.int64(fx["a_fmax"]) * e, 30)


def _rc_q(c: np.ndarray, t: np.ndarray, qc: int, u0: int = 0) -> np.ndarray:
    """ECMRT_Q_RC from u0 over arrays of coefficients (Q(qc)) and targets."""
    c = np.broadcast_to(np.asarray(c, dtype=np.int64), np.shape(t))
    out = np.empty(len(t), dtype=np.int64)
    u = int(u0)
    half = 1 << (qc - 1)
    for k, (ck, tk) in enumerate(zip(c.tolist(), np.asarray(t).tolist())):
        u = u + (((tk - u) * ck + half) >> qc)      # between u and t: no saturation (ecmrt_q_rc)
        out[k] = u
    return out


def _weight_q(grid, v, g: int, uniform: bool = False):
    if uniform:          # ecmrt_q_ulocate
        u = ((np.asarray(v, dtype=np.int64) - grid.x0) * grid.inv_h) >> grid.shift
        below, above = u < 0, u >= (grid.n - 1) << 30
        k = np.where(below, 0, np.where(above, grid.n - 2, u >> 30))
        w = np.where(below, 0, np.where(above, ONE30, u & (ONE30 - 1)))
        return k.astype(np.int64), w.astype(np.int64)
    k = _segments(grid.x, v)
    w = _rshr((v - grid.x[k]) * grid.inv_dx[k], g)
    w = np.minimum(w, ONE30)
    w = np.where(v <= grid.x[0], 0, np.where(v >= grid.x[-1], ONE30, w))
    return k, w.astype(np.int64)


def _lerp_q(y, k, w):
    return y[k] + _rshr((y[k + 1] - y[k]) * w, 30)


def _lerp2_q(y, k, w, kt=None, wt=None):
    """ecmrt_q_lerp (one row), or over temperature the segment pairs of ecmrt_q_segment (a, b
    at points k, k + 1, linear in temperature) then a + (b - a) w."""
    if kt is None:
        return _lerp_q(y[0] if y.ndim == 2 else y, k, w)
    a = y[kt, k] + _rshr((y[kt + 1, k] - y[kt, k]) * wt, 30)
    b = y[kt, k + 1] + _rshr((y[kt + 1, k + 1] - y[kt, k + 1]) * wt, 30)
    return a + _rshr((b - a) * w, 30)


def _tv_q(b, kt, wt):
    return b[0] if kt is None else _lerp_q(b, kt, wt)


def _soc_q(soc0: int, inc: np.ndarray, sh: int) -> np.ndarray:
    """SOC with the sub-LSB remainder carried (ecmrt_q_count, the step's stage 2): without saturation
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


def _branch_q(spec: CSpec, d, kt, wt) -> dict:
    """A direction's per-temperature values at the temperature (k_diff as 1/tau in Q_KR with
    time constants of the temperature only at variable dt, as <prefix>_coefs_q keeps it)."""
    p = {name: _tv_q(getattr(d, name), kt, wt) for name in ("r_diff", "k_diff", "i0")
         if getattr(d, name) is not None}
    if spec.tau_t and spec.variable_dt and "k_diff" in p:
        p["k_diff"] = rate_q(p["k_diff"], spec.q["Q_T"], spec.q["Q_KR"])
    return p


def age_q(spec: CSpec, efc_raw):
    """ecmrt_q_age: (resistance scale in Q_AR, k_soc) at efc (Q8 raw; None: 0)."""
    q = spec.q
    k, w = _weight_q(spec.age["grid"], np.array([0 if efc_raw is None else efc_raw],
                                                dtype=np.int64), q["Q_GA"])
    iq = _lerp_q(np.asarray(spec.age["iq"], dtype=np.int64), k, w)[0]
    return (int(_lerp_q(np.asarray(spec.age["r"], dtype=np.int64), k, w)[0]),
            int(_sat32(_rshr(np.int64(spec.k_soc) * iq, q["Q_AQ"]))))


def _aged_q(spec: CSpec, t, age_r):
    return t if age_r is None else _rshr(t * np.int64(age_r), spec.q["Q_AR"])


def _u_diff_q(spec: CSpec, per_dir, chg, i, dt, age_r=None) -> np.ndarray:
    """The diffusion pair's voltage (Q_V) after every step (its values depend on T only)."""
    q = spec.q
    k_diff = _pick(chg, per_dir, "k_diff")
    if spec.tau_t and spec.variable_dt:
        cd, qcd = c_kr_q(dt, k_diff, q["Q_KR"]), Q30
    elif spec.variable_dt:
        cd, qcd = c_dt_tau_q(dt, k_diff, q["Q_T"]), Q30
    else:
        qcd = q["Q_CD"]
        cd = inv_d_q(k_diff, qcd + q["Q_DD"])
    t = _rshr(_pick(chg, per_dir, "r_diff") * i, q["Q_RD"] + q["Q_I"] - q["Q_V"])
    return _rc_q(cd, _aged_q(spec, t, age_r), qcd)


# The fixed-point step's units (c_runtime/ecmrt_q_step.h, templates/ecm_step_q.c.j2), over the whole record; an
# effect that is off leaves r i as it is or adds 0.

def _coef_q(spec: CSpec, p: dict, dt, name: str, pair: str):
    """ECMRT_Q_COEF: the pair's coefficient c of ECMRT_Q_RC and its Q (1/tau in the state
    of time constants of the temperature only, the time constant at variable dt, c = 1/D at
    fixed dt)."""
    q = spec.q
    if spec.tau_t and spec.variable_dt:
        return c_kr_q(dt, p[name], q["Q_KR"]), Q30
    if spec.variable_dt:
        return c_dt_tau_q(dt, p[name], q["Q_T"]), Q30
    qc = q[f"Q_C{pair}"]
    return inv_d_q(p[name], qc + q[f"Q_D{pair}"]), qc


def _fx_cdr_q(fx: dict, ai, t0, tf):
    """ecmrt_q_fx_cdr: r0 i, r_fast i times the g table at |i| / i0."""
    if not fx.get("cdr"):
        return t0, tf
    g = cdr_factor_q(ai, fx)
    return _rshr(t0 * g, fx["CDR_QG"]), _rshr(tf * g, fx["CDR_QG"])


def _fx_arr_q(fx: dict, temp, t0, tf, ts):
    """ecmrt_q_fx_arr: r0 i, r_fast i, r_slow i times the Arrhenius factor."""
    if not fx.get("arr"):
        return t0, tf, ts
    g = arrhenius_q(temp, fx)
    return tuple(_rshr(t * g, fx["ARR_QF"]) for t in (t0, tf, ts))


def _bv_q(spec: CSpec, ai, p: dict, tf):
    """ecmrt_q_bv: r_fast i times asinh(x)/x, x = |i| / i0(T)."""
    if not spec.has_bv:
        return tf
    r, sh = recip_q(p["i0"])
    x = _sat32(_rshr(ai * r, sh - spec.bv["K"]))
    return _rshr(tf * gtab_q(spec.bv["tab"], x, spec.bv["QX"]), 30)


def _fx_hyst_q(spec: CSpec, fx: dict, chg, ai, dt, out: dict):
    """ecmrt_q_fx_hyst: the hysteresis term in Q_V (its state into out["h"]), or 0."""
    if not fx.get("hyst"):
        return 0
    sg = np.where(chg == 1, ONE30, -ONE30).astype(np.int64)
    if spec.variable_dt:
        x = _rshr(_sat32(_rshr(ai * fx["h_k"], fx["SH_HR"])) * dt, fx["SH_HX"])
    else:
        x = _rshr(ai * fx["h_k"], fx["SH_HX"])
    h = out["h"] = _rc_q(one_minus_exp_neg_q26(x), sg, Q30, fx["h_init"])
    return (_rshr(fx["h_m"] * (h - fx["h_ref"]), fx["SH_HM"])
            + _rshr(fx["h_m0"] * (sg - fx["h_ref"]), fx["SH_HM"]))


def _fx_xrc_q(spec: CSpec, fx: dict, i, dt, out: dict):
    """ecmrt_q_fx_xrc: the extra pair's voltage in Q_V (into out["u_x"] too), or 0."""
    if not fx.get("xrc"):
        return 0
    cx = (c_dt_tau_q(dt, np.full(i.size, fx["x_k"]), spec.q["Q_T"]) if spec.variable_dt
          else fx["x_k"])
    ux = out["u_x"] = _rc_q(cx, _rshr(np.int64(fx["x_r"]) * i, fx["SH_XR"]), Q30)
    return ux


def simulate_fixed_raw(spec: CSpec, i_raw, dt_raw=None, soc0_raw: int = ONE30,
                       temp_raw=None, efc_raw=None) -> RefResult:
    """Bit-true reference of a numeric="fixed" spec on raw integers: i in Q_I, dt in Q16
    (variable dt), soc0 in Q30, temperature in Q8 degC, the age set after init in Q8
    equivalent full cycles (None: fresh). Returns raw int64 arrays (v in Q_V)."""
    if not spec.fixed:
        raise ValueError("simulate_fixed_raw needs a numeric='fixed' spec")
    q = spec.q
    age_r, k_soc = age_q(spec, efc_raw) if spec.age is not None else (None, spec.k_soc)
    i = _sat32(np.asarray(i_raw, dtype=np.int64))
    n = i.size
    temp = _sat32(_temperatures(spec, temp_raw, n, np.int64).astype(np.int64))
    if spec.variable_dt:
        if dt_raw is None:
            raise ValueError("this spec has a variable dt: give dt per step")
        dt = np.maximum(_sat32(np.asarray(dt_raw, dtype=np.int64)), 0)
        if dt.shape != i.shape:
            raise ValueError("current and dt differ in length")
        inc = _rshr(i * k_soc, q["SH_RATE"]) * dt    # < 2^31 before * dt (Q_RATE)
    else:
        dt = None
        inc = i * k_soc
    chg = _direction(i, spec.deadband)
    soc = _soc_q(int(np.clip(soc0_raw, INT32_MIN, INT32_MAX)), inc, q["SH_DSOC"])
    kt = wt = None
    if spec.temp:
        kt, wt = _weight_q(spec.temp_grid, temp, q["Q_GT"])

    branches = [_branch_q(spec, d, kt, wt) for d in spec.dirs]
    soc_rc = soc
    if spec.surface is not None:        # ecmrt_q_surface: u_diff needs no SOC
        ud = _u_diff_q(spec, branches, chg, i, dt, age_r)
        ko, wo = _weight_q(spec.ocv_grid, soc, q["Q_G"], spec.ocv_uniform)
        sv = _lerp2_q(spec.surface, ko, wo, kt, wt)
        prev = np.concatenate([[0], ud[:-1]]).astype(np.int64)
        soc_rc = np.clip(soc + _rshr(sv * prev, q["Q_SV"] + q["Q_V"] - Q30), 0, ONE30)
    per_dir = []
    for d, br in zip(spec.dirs, branches):
        k, w = _weight_q(d.grid, soc_rc, q["Q_G"], spec.rc_uniform)
        p = {name: _lerp2_q(getattr(d, name), k, w, kt, wt)
             for name in (RESISTANCES if spec.tau_t else PARAMS)}
        p.update(br)
        if spec.tau_t:
            for name in ("k_fast", "k_slow"):
                p[name] = _tv_q(getattr(d, name)[:, 0], kt, wt)
            if spec.variable_dt:      # ecmrt_q_coefs: 1/tau in Q_KR
                for name in ("k_fast", "k_slow"):
                    p[name] = rate_q(p[name], q["Q_T"], q["Q_KR"])
        per_dir.append(p)
    p = {name: _pick(chg, per_dir, name) for name in per_dir[0]}
    (cf, qcf), (cs, qcs) = _coef_q(spec, p, dt, "k_fast", "F"), _coef_q(spec, p, dt, "k_slow", "S")
    q_i, q_v = q["Q_I"], q["Q_V"]
    fx = spec.fx
    ai = np.abs(i)
    t0 = _rshr(p["r0"] * i, q["Q_R0"] + q_i - q_v)
    tf = _rshr(p["r_fast"] * i, q["Q_RF"] + q_i - q_v)
    ts = _rshr(p["r_slow"] * i, q["Q_RS"] + q_i - q_v)
    # 3'. parameter effects, in the generated step's order, each scaling r i
    t0, tf = _fx_cdr_q(fx, ai, t0, tf)
    t0, tf, ts = _fx_arr_q(fx, temp, t0, tf, ts)
    tf = _bv_q(spec, ai, p, tf)
    t0, tf, ts = (_aged_q(spec, t, age_r) for t in (t0, tf, ts))
    # 4. the two pairs; 3''. the OCV; 5. the voltage and the voltage effects' terms
    uf = _rc_q(cf, tf, qcf)
    us = _rc_q(cs, ts, qcs)
    k, w = (_weight_q(spec.dirs[0].grid, soc, q["Q_G"], spec.rc_uniform) if spec.ocv_shared else
            _weight_q(spec.ocv_grid, soc, q["Q_G"], spec.ocv_uniform))
    ocv = _lerp2_q(spec.ocv, k, w, kt, wt)
    v = ((ocv + t0) + uf) + us
    out = {}
    if spec.diff:
        out["u_diff"] = _u_diff_q(spec, per_dir, chg, i, dt, age_r)
        v = v + out["u_diff"]
    v = v + _fx_hyst_q(spec, fx, chg, ai, dt, out)
    v = v + _fx_xrc_q(spec, fx, i, dt, out)
    return RefResult(_sat32(v).astype(np.int64), soc, uf, us, chg, **out)


# --- conversions between SI values and the fixed-point API ----------------------------

def current_to_raw(spec: CSpec, current_a) -> np.ndarray:
    i = np.nan_to_num(np.asarray(current_a, dtype=np.float64), nan=0.0)
    return quantize(i, spec.q["Q_I"])


def dt_to_raw(dt_s) -> np.ndarray:
    dt = np.nan_to_num(np.asarray(dt_s, dtype=np.float64), nan=0.0)
    return quantize(dt, Q_D)


def temperature_to_raw(temperature_c) -> np.ndarray:
    """degC -> the fixed-point temperature input (Q8, saturated to int32; NaN -> -2^31)."""
    t = np.nan_to_num(np.asarray(temperature_c, dtype=np.float64), nan=-1e9)
    return quantize(t, Q_TEMP)


def soc_to_raw(soc) -> int:
    return int(quantize([soc], Q30)[0])


def volts(spec: CSpec, v_raw) -> np.ndarray:
    return np.ldexp(np.asarray(v_raw, dtype=np.float64), -spec.q["Q_V"])


def efc_to_raw(efc) -> int | None:
    """Equivalent full cycles -> the fixed-point age input (Q8); None stays None."""
    return None if efc is None else int(quantize([efc], Q_TEMP)[0])


def simulate_fixed(spec: CSpec, current_a, dt_s=None, soc0: float = 1.0, temperature_c=None,
                   efc=None):
    """Quantise SI inputs as the C caller would, run the bit-true reference.
    Returns (RefResult of raw integers, voltage in V as float64)."""
    i_raw = current_to_raw(spec, current_a)
    dt_raw = dt_to_raw(dt_s) if spec.variable_dt else None
    t_raw = None
    if temperature_c is not None:
        t_raw = temperature_to_raw(np.broadcast_to(np.asarray(temperature_c, dtype=np.float64),
                                                   np.shape(i_raw)))
    ref = simulate_fixed_raw(spec, i_raw, dt_raw, soc_to_raw(soc0), t_raw, efc_to_raw(efc))
    return ref, volts(spec, ref.v)
