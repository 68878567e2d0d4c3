"""Fixed-point spec of the generated C: the Q formats chosen from the model's value ranges
and every table and constant quantised once (see c_runtime/ecmrt_q.h for what each format
means; :mod:`ecmgen.c.spec` for the float32 spec and what both share).

Range rules: every int64 product is formed from int32 operands whose ranges are checked
here, so none overflows; the voltage format Q_V holds the largest voltage the saturated
current can produce (OCV + i_max times every resistance with its largest factor, plus the
hysteresis and extra RC terms). A model the formats cannot carry is refused with one line
that names what does not fit and suggests numeric = "float".
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from ..errors import InputError
from .qformat import (CDR_E_MAX, INT32_MAX, Q30, Q_D, Q_TEMP, _q_fit, cdr_table, quantize, rate_q,
                      recip_q)
from .spec import (ARR_T_RANGE_C, KELVIN, CDir, CGrid, CSpec, _coef, _inv_coef, arrhenius_range,
                   uniform_inverse)


def _one(v: float, qf: int) -> int:
    return int(quantize([v], qf)[0])


def _grid_shift(xs: list[np.ndarray], what: str) -> int:
    """Q_G of inverse spacings 2^(30 + Q_G) / dx that fit int32 for every grid of ``xs``."""
    dx_min = min(int(np.min(np.diff(x))) for x in xs)
    if dx_min < 2:
        raise InputError(None, f"{what} breakpoints too close for the fixed-point format")
    g = math.floor(math.log2(INT32_MAX * dx_min)) - 30
    while math.floor(math.ldexp(1.0, 30 + g) / dx_min + 0.5) > INT32_MAX:
        g -= 1
    return g


def _qgrid(xq: np.ndarray, g: int, uniform: tuple[float, int] | None = None) -> CGrid:
    """``uniform`` (inv, shift): located in O(1), u = ((v - x0) inv_h) >> shift in Q30 with
    inv_h = round(inv 2^shift) (exact when inv = 1/h is an integer: shift 0)."""
    dx = np.diff(xq).astype(np.float64)
    grid = CGrid(xq, np.floor(np.ldexp(1.0, 30 + g) / dx + 0.5).astype(np.int64))
    if uniform is None:
        return grid
    inv, shift = uniform
    return CGrid(grid.x, grid.inv_dx, x0=int(xq[0]), inv_h=int(round(math.ldexp(inv, shift))),
                 shift=shift)


def _uniform_shift(socs: list[np.ndarray]) -> tuple[list[float], int] | None:
    """1/h of each SOC grid and one shift for all of them (0 when every 1/h is an integer),
    or None unless every grid is uniform to Q30 resolution."""
    invs = [uniform_inverse(x, 2.0**-29) for x in socs]
    if any(v is None for v in invs):
        return None
    if all(v == round(v) for v in invs):
        return invs, 0
    return invs, min(math.floor(math.log2(INT32_MAX / v)) for v in invs)


def _g_table_bins(i_lim: float, i0_min: float, x_raw) -> int:
    """Binades E of an asinh(x)/x table for x = |i| / i0 < 2^E over every int32 current:
    ``x_raw(e)`` gives the largest raw x the C forms with x in Q(31 - e)."""
    e_bins = max(1, math.ceil(math.log2(i_lim / i0_min)))
    while True:
        if e_bins > CDR_E_MAX:
            return -1
        x = x_raw(e_bins)
        if x is not None and x < 2**31:
            return e_bins
        e_bins += 1


def _fx_fixed(by_name: dict, q: dict, dt_s: float | None, i_lim: float) -> dict:
    """Constants (raw integers) and shifts of the effects in <prefix>_model_q_t."""
    q_i, q_v = q["Q_I"], q["Q_V"]
    fx = {"hyst": 0, "xrc": 0, "cdr": 0, "arr": 0}
    hyst, xrc = by_name.get("hysteresis"), by_name.get("extra_rc")
    cdr, arr = by_name.get("current_dependent_resistance"), by_name.get("temperature_dependence")
    if hyst is not None:
        k = 1.0 / (3600.0 * hyst.decay_ah) if dt_s is None else dt_s / (3600.0 * hyst.decay_ah)
        q_hk = _q_fit(k)
        if dt_s is None:
            q_hr = _q_fit(i_lim * k * 1.001)
            fx["SH_HR"] = q_i + q_hk - q_hr
            fx["SH_HX"] = q_hr + Q_D - 26
        else:
            fx["SH_HX"] = q_i + q_hk - 26
        vm = max(hyst.m_v, hyst.m0_v)
        q_hm = min(_q_fit(vm), 40) if vm > 0 else 30
        fx["SH_HM"] = q_hm + Q30 - q_v
        for name in ("SH_HR", "SH_HX", "SH_HM"):
            if name in fx and not 1 <= fx[name] <= 62:
                raise InputError(None, f"[c] effect hysteresis (decay_ah = {hyst.decay_ah:g} Ah) does "
                                       f"not fit the fixed-point formats ({name} = {fx[name]}); "
                                       "use numeric=\"float\"")
        fx.update(hyst=1, h_init=_one(hyst.initial_state, Q30), h_k=_one(k, q_hk),
                  h_m=_one(hyst.m_v, q_hm), h_m0=_one(hyst.m0_v, q_hm),
                  h_ref=_one(hyst.ocv_table_state, Q30), Q_HK=q_hk, Q_HM=q_hm)
        if fx["h_k"] <= 0:
            raise InputError(None, "[c] effect hysteresis: decay_ah too large for fixed point; "
                                   "use numeric=\"float\"")
    if xrc is not None:
        q_xr = min(_q_fit(xrc.r_ohm), 62 - q_i + q_v, 40 if xrc.r_ohm == 0 else 62)
        fx["SH_XR"] = q_xr + q_i - q_v
        if not 1 <= fx["SH_XR"] <= 62:
            raise InputError(None, f"[c] effect extra_rc: r_ohm = {xrc.r_ohm:g} does not fit the "
                                   "fixed-point formats; use numeric=\"float\"")
        x_k = _one(xrc.tau_s, q["Q_T"]) if dt_s is None else _one(_coef(dt_s, xrc.tau_s), Q30)
        if x_k <= 0:
            raise InputError(None, f"[c] effect extra_rc: tau_s = {xrc.tau_s:g} s does not fit the "
                                   "fixed-point formats; use numeric=\"float\"")
        fx.update(xrc=1, x_r=_one(xrc.r_ohm, q_xr), x_k=x_k, Q_XR=q_xr)
    if cdr is not None:
        # x = |i| / i0 = rshr(|i| g_k, SH_GX) in Q(CDR_QX) with CDR_QX = 31 - E: x < 2^E
        # for every int32 current (|i| <= 2^31), so x fits int31 and indexes the table
        q_k = _q_fit(1.0 / cdr.i0_a)
        g_k = _one(1.0 / cdr.i0_a, q_k)

        def x_raw(e):
            sh = q_i + q_k - (31 - e)
            return None if not 1 <= sh <= 62 or g_k <= 0 else (2**31 * g_k + (1 << (sh - 1))) >> sh

        e_bins = _g_table_bins(i_lim, cdr.i0_a, x_raw)
        if e_bins < 0:
            raise InputError(None, f"[c] effect current_dependent_resistance: i0_a = "
                                   f"{cdr.i0_a:g} A is too small for the fixed-point current "
                                   f"range {i_lim:g} A (|i|/i0_a must stay below "
                                   f"2^{CDR_E_MAX}); use numeric=\"float\"")
        tab = cdr_table(cdr.scale_at_zero, e_bins)
        q_g = min(Q30, _q_fit(float(np.max(tab))))
        fx.update(cdr=1, g_k=g_k, g_tab=quantize(tab, q_g), SH_GX=q_i + q_k - (31 - e_bins),
                  CDR_QX=31 - e_bins, CDR_QG=q_g, Q_GK=q_k, CDR_E=e_bins,
                  g_max=float(np.max(tab)))
    if arr is not None:
        f_max, f_min = arrhenius_range(arr)
        if f_max / f_min > 2.0**20:
            raise InputError(None, f"[c] effect temperature_dependence: activation_k = "
                                   f"{arr.activation_k:g} K changes the resistances by more than "
                                   f"2^20 over {ARR_T_RANGE_C[0]:g}..{ARR_T_RANGE_C[1]:g} degC; "
                                   "use numeric=\"float\"")
        b = arr.activation_k / (ARR_T_RANGE_C[0] + KELVIN)
        q_b = min(_q_fit(b), 40)
        q_f = min(_q_fit(f_max), 40)
        fx.update(arr=1, a_b=_one(b, q_b), a_fmax=_one(f_max, q_f), ARR_QB=q_b, ARR_QF=q_f,
                  f_max=f_max)
    return fx if any(fx[k] for k in ("hyst", "xrc", "cdr", "arr")) else {}


def _vmax(dirs_raw, key: str) -> float:
    return max(float(np.max(c[key])) for _, c, _ in dirs_raw)


def _bmax(dirs_raw, key: str, f=np.max) -> float:
    return float(f([f(b[key]) for _, _, b in dirs_raw]))


def _q_voltage_and_resistances(ctx: SimpleNamespace, q: dict, diff: bool) -> None:
    """Q_V (holding the OCV plus every drop the largest current makes, with the effects'
    largest factors and the age's) and the resistances' formats."""
    dirs_raw, by_name, q_i, i_lim = ctx.src.dirs, ctx.by_name, ctx.q_i, ctx.i_lim
    hyst, xrc = by_name.get("hysteresis"), by_name.get("extra_rc")
    cdr, arr = by_name.get("current_dependent_resistance"), by_name.get("temperature_dependence")
    # largest factors of r0 / r_fast (current_dependent_resistance) and of every resistance
    # (temperature_dependence); the Butler-Volmer factor is <= 1
    g_max = max(1.0, float(np.max(cdr_table(cdr.scale_at_zero, 1)))) if cdr is not None else 1.0
    f_max = max(1.0, arrhenius_range(arr)[0]) if arr is not None else 1.0
    law = ctx.model.ageing      # its largest scales widen Q_V and k_soc's formats
    r_age = 1.0 if law is None else float(np.max(law.resistance_scale))
    r0_max, rf_max, rs_max = (_vmax(dirs_raw, k) for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"))
    v_bound = float(np.max(ctx.src.ocv_v)) + i_lim * (
        ((r0_max + rf_max) * g_max * f_max + rs_max * f_max
         + (_bmax(dirs_raw, "r_diff_ohm") if diff else 0.0)) * r_age + (xrc.r_ohm if xrc is not None else 0.0))
    if hyst is not None:
        v_bound += 2.0 * (hyst.m_v + hyst.m0_v)
    q["Q_V"] = min(30, _q_fit(v_bound * 1.001))
    keys = [("r0_ohm", "Q_R0", r0_max), ("r_fast_ohm", "Q_RF", rf_max),
            ("r_slow_ohm", "Q_RS", rs_max)]
    if diff:
        keys.append(("r_diff_ohm", "Q_RD", _bmax(dirs_raw, "r_diff_ohm")))
    for key, name, top in keys:
        q[name] = min(_q_fit(top), 62 - q_i + q["Q_V"], 40 if top == 0 else 62)
        sh = q[name] + q_i - q["Q_V"]
        if not 1 <= sh <= 62:
            raise InputError(None, f"cannot choose a fixed-point format for {key} (shift {sh})")


def _q_time_and_soc(ctx: SimpleNamespace, q: dict, diff: bool, q_age: float) -> int:
    """The time constants' (variable dt) or D's and c's (fixed dt) formats and the SOC
    update's; returns k_soc in Q_K."""
    dirs_raw, by_name, dt_s, q_i, i_lim = ctx.src.dirs, ctx.by_name, ctx.dt_s, ctx.q_i, ctx.i_lim
    variable_dt, notes, xrc = ctx.variable_dt, ctx.notes, by_name.get("extra_rc")
    k_soc64 = ctx.k_soc64
    k_top = k_soc64 * q_age     # the largest k_soc of the step: at the most faded capacity
    taus = [("tau_fast_s", "Q_DF", "Q_CF"), ("tau_slow_s", "Q_DS", "Q_CS")]
    if variable_dt:
        tau_all = [c[k] for _, c, _ in dirs_raw for k in ("tau_fast_s", "tau_slow_s")]
        tau_all += [b["tau_diff_s"] for _, _, b in dirs_raw if diff]
        tau_all += [np.array([xrc.tau_s])] if xrc is not None else []
        tau_max = max(float(np.max(t)) for t in tau_all)
        tau_min = min(float(np.min(t)) for t in tau_all)
        q["Q_T"] = min(21, _q_fit(tau_max))
        if q["Q_T"] < -10:
            raise InputError(None, "time constants too large for the fixed-point format")
        # ecmrt_q_c_dt_tau: the shift sh - Q_T - 14 >= 1 needs tau >= 2^(Q_T - 16) raw (2^-16 s)
        if int(quantize([tau_min], q["Q_T"])[0]) < 2 ** max(0, q["Q_T"] - 16):
            raise InputError(None, "time constants too small for the fixed-point format")
        if math.ldexp(tau_min, q["Q_T"]) < 1024:
            notes.append(f"the smallest time constant {tau_min:.3g} s has under 10 bits in Q{q['Q_T']}")

        q["Q_K"] = _q_fit(k_top)
        q["Q_RATE"] = _q_fit(i_lim * k_top * 1.001)
        q["SH_RATE"] = q_i + q["Q_K"] - q["Q_RATE"]
        q["SH_DSOC"] = q["Q_RATE"] + Q_D - Q30
    else:
        q["Q_K"] = _q_fit(k_top)
        q["SH_DSOC"] = q_i + q["Q_K"] - Q30
        if diff:
            taus.append(("tau_diff_s", "Q_DD", "Q_CD"))
        for key, qd, qc in taus:
            vals = [_inv_coef(dt_s, (b if key == "tau_diff_s" else c)[key]) for _, c, b in dirs_raw]
            dmax, dmin = max(float(np.max(v)) for v in vals), min(float(np.min(v)) for v in vals)
            q[qd] = _q_fit(dmax)
            q[qc] = min(_q_fit(1.0 / dmin, bits=30), 62 - q[qd])
            if q[qd] < 0 or q[qc] < 2:
                raise InputError(None, f"dt_s = {dt_s} s is too small for the time constants in fixed point")
    k_soc = int(quantize([k_soc64], q["Q_K"])[0])
    for name in ("SH_RATE", "SH_DSOC"):
        if name in q and not 1 <= q[name] <= (62 if name == "SH_RATE" else 61):
            raise InputError(None, f"capacity {ctx.common['capacity_ah']} Ah with current range "
                                   f"{i_lim} A does not fit the fixed-point SOC update "
                                   f"({name} = {q[name]})")
    # the C takes the SOC rate i k_soc (shifted) as int32 without saturation
    if "SH_RATE" in q:
        k_raw = int(quantize([k_top], q["Q_K"])[0])
        assert (2**31 * k_raw + (1 << (q["SH_RATE"] - 1))) >> q["SH_RATE"] <= INT32_MAX
    return k_soc


def _bv_fixed(ctx: SimpleNamespace, q: dict) -> dict:
    """The Butler-Volmer branch's i0 format and asinh(x)/x table."""
    dirs_raw, q_i, i_lim = ctx.src.dirs, ctx.q_i, ctx.i_lim
    i0_min = _bmax(dirs_raw, "i0_a", np.min)
    q["Q_I0"] = _q_fit(_bmax(dirs_raw, "i0_a"))
    i0_raw_min = int(quantize([i0_min], q["Q_I0"])[0])
    r_max, sh_min = recip_q(i0_raw_min)

    def x_raw(e):
        k = int(sh_min) - (q["Q_I0"] - q_i + 31 - e)
        return None if not 1 <= k <= 62 else (2**31 * int(r_max) + (1 << (k - 1))) >> k

    e_bins = _g_table_bins(i_lim, i0_min, x_raw)
    if e_bins < 0:
        raise InputError(None, f"Butler-Volmer i0_a = {i0_min:g} A is too small for the "
                               f"fixed-point current range {i_lim:g} A (|i|/i0_a must stay "
                               f"below 2^{CDR_E_MAX}); use numeric=\"float\"")
    tab = cdr_table(1.0, e_bins)
    bv_spec = {"tab": quantize(tab, Q30), "QX": 31 - e_bins, "E": e_bins,
               "K": q["Q_I0"] - q_i + 31 - e_bins}
    return bv_spec


def _dirs_fixed(ctx: SimpleNamespace, q: dict, diff: bool, bv: bool, u_rc) -> list:
    """Each direction's tables in their formats."""
    dt_s, variable_dt = ctx.dt_s, ctx.variable_dt
    dirs = []
    for soc, cols, br in ctx.src.dirs:
        if variable_dt:
            kf, ks = quantize(cols["tau_fast_s"], q["Q_T"]), quantize(cols["tau_slow_s"], q["Q_T"])
            if np.any(kf <= 0) or np.any(ks <= 0):
                raise InputError(None, "time constants too small for the fixed-point format")
        else:
            kf = quantize(_inv_coef(dt_s, cols["tau_fast_s"]), q["Q_DF"])
            ks = quantize(_inv_coef(dt_s, cols["tau_slow_s"]), q["Q_DS"])
        extra = {}
        if diff:
            extra["r_diff"] = quantize(br["r_diff_ohm"], q["Q_RD"])
            extra["k_diff"] = (quantize(br["tau_diff_s"], q["Q_T"]) if variable_dt else
                               quantize(_inv_coef(dt_s, br["tau_diff_s"]), q["Q_DD"]))
        if bv:
            extra["i0"] = quantize(br["i0_a"], q["Q_I0"])
        dirs.append(CDir(_qgrid(quantize(soc, Q30), q["Q_G"],
                               None if u_rc is None else (u_rc[0][len(dirs)], u_rc[1])),
                         quantize(cols["r0_ohm"], q["Q_R0"]),
                         quantize(cols["r_fast_ohm"], q["Q_RF"]), kf,
                         quantize(cols["r_slow_ohm"], q["Q_RS"]), ks, **extra))
    return dirs


def _q_kr(q: dict, dirs: list, diff: bool) -> int:
    """CSpec.tau_t: the state holds 1/tau in Q_KR, the largest Q with 1/tau of the smallest
    quantised tau below 2^31 (interpolated taus are not smaller)."""
    ks = [k for d in dirs for k in (d.k_fast, d.k_slow) + ((d.k_diff,) if diff else ())]
    tau_raw_min = min(int(np.min(k)) for k in ks)
    q_kr = min(62, math.floor(math.log2(INT32_MAX * tau_raw_min)) - q["Q_T"])
    while int(rate_q(tau_raw_min, q["Q_T"], q_kr)) > INT32_MAX:
        q_kr -= 1
    if q_kr < 15:
        raise InputError(None, "time constants too small for the fixed-point format")
    return q_kr


def prepare_fixed(ctx: SimpleNamespace) -> CSpec:
    """The fixed-point spec (ctx from :func:`ecmgen.c.spec.begin`)."""
    src, by_name, dt_s, variable_dt = ctx.src, ctx.by_name, ctx.dt_s, ctx.variable_dt
    q_i, i_lim, notes = ctx.q_i, ctx.i_lim, ctx.notes
    dirs_raw = src.dirs
    diff, bv = "r_diff_ohm" in dirs_raw[0][2], "i0_a" in dirs_raw[0][2]
    law = ctx.model.ageing      # its largest scales widen Q_V and k_soc's formats
    q_age = 1.0 if law is None else float(np.max(1.0 / law.capacity_scale))
    q = {"Q_I": q_i}
    _q_voltage_and_resistances(ctx, q, diff)
    if src.surface is not None:
        # sv = lam / max(dOCV/dSOC, 0.3 V) in [0, lam / 0.3 V] (1/V): the largest Q holding
        # its largest value; the product sv u_diff (Q_SV + Q_V) is rounded to the Q30 SOC
        q["Q_SV"] = _q_fit(float(np.max(src.surface)), cap=62 - q["Q_V"] + Q30)
        if q["Q_SV"] + q["Q_V"] - Q30 < 1:
            raise InputError(None, "cannot choose a fixed-point format for the surface SOC "
                                   f"table (surface_soc_gain {ctx.model.surface_soc_gain:g})")
    xs = [quantize(src.ocv_soc, Q30)] + [quantize(soc, Q30) for soc, _, _ in dirs_raw]
    q["Q_G"] = _grid_shift(xs, "SOC")
    u_rc = _uniform_shift([soc for soc, _, _ in dirs_raw])
    shared = src.surface is None and all(np.array_equal(x, xs[0]) for x in xs[1:])  # CSpec.ocv_shared
    u_ocv = None if shared else _uniform_shift([src.ocv_soc])
    if u_rc is not None:
        q["Q_GU"] = u_rc[1]
    if u_ocv is not None:
        q["Q_GUO"] = u_ocv[1]
    temp_grid = None
    if src.temps is not None:
        tq = quantize(src.temps, Q_TEMP)
        q["Q_GT"] = _grid_shift([tq], "temperature")
        temp_grid = _qgrid(tq, q["Q_GT"])

    k_soc = _q_time_and_soc(ctx, q, diff, q_age)
    bv_spec = _bv_fixed(ctx, q) if bv else {}
    dirs = _dirs_fixed(ctx, q, diff, bv, u_rc)
    if variable_dt and all(np.all(k == k[:, :1]) for d in dirs for k in (d.k_fast, d.k_slow)):
        q["Q_KR"] = _q_kr(q, dirs, diff)
    db = int(quantize([ctx.model.direction_deadband_a], q_i)[0])
    fx = _fx_fixed(by_name, q, dt_s, i_lim)
    return CSpec(ocv_grid=_qgrid(xs[0], q["Q_G"], None if u_ocv is None else (u_ocv[0][0], u_ocv[1])),
                 ocv=quantize(src.ocv_v, q["Q_V"]),
                 dirs=tuple(dirs), deadband=db, k_soc=k_soc, temp_grid=temp_grid, q=q,
                 notes=tuple(notes), fx=fx, bv=bv_spec,
                 surface=None if src.surface is None else quantize(src.surface, q["Q_SV"]),
                 age=_age_fixed(law, q), **ctx.common)


def _age_fixed(law, q: dict) -> dict | None:
    """The ageing law as the fixed-point C holds it (CSpec.age), its formats into ``q``:
    the age in Q8 equivalent full cycles, the scales in the largest Q holding their largest
    value (1 exactly at the first breakpoint: 2^Q)."""
    if law is None:
        return None
    x = quantize(law.equivalent_full_cycles, Q_TEMP)
    q["Q_GA"] = _grid_shift([x], "ageing.equivalent_full_cycles")
    inv = 1.0 / law.capacity_scale
    q["Q_AR"] = min(30, _q_fit(float(np.max(law.resistance_scale))))
    q["Q_AQ"] = min(30, _q_fit(float(np.max(inv))))
    return {"grid": _qgrid(x, q["Q_GA"]), "r": quantize(law.resistance_scale, q["Q_AR"]),
            "iq": quantize(inv, q["Q_AQ"])}
