"""What ``diagnose`` reads off a residual before it fits anything: each effect's signature
(the share of the residual its first-order voltage sensitivity explains, and the starting
values it implies), the voltage noise of the rests, block averages of a long record, the
held-out samples judged, and the small helpers of the search (:mod:`.search`)."""

from __future__ import annotations

import math

import numpy as np

from ..data.measure import TimeSeries
from ..model import effects as fx
from ..model.effects import KELVIN
from ..model.model import EcmModel
from ..model.rc import rc_recurrence
from ..model.simulate import SimResult
from .problems import _Spec, _neutral
from .result import Signature


# -- small numeric helpers ----------------------------------------------------------------

def _lowpass(dt: np.ndarray, x: np.ndarray, tau: float, x0: float = 0.0) -> np.ndarray:
    a = np.exp(-dt / tau)
    return rc_recurrence(a, (1.0 - a) * x, x0)


def _r2(y: np.ndarray, X: np.ndarray) -> tuple[float, np.ndarray]:
    """Uncentred share of sum(y^2) explained by least squares on the columns of X."""
    ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
    y, X = y[ok], X[ok]
    ss = float(y @ y)
    if ss <= 0 or y.size < X.shape[1] + 2:
        return 0.0, np.zeros(X.shape[1])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ coef
    return max(0.0, 1.0 - float(res @ res) / ss), coef


def noise_std(series: TimeSeries, rest_a: float) -> float:
    """Voltage noise (std, V) from the sample-to-sample changes during rests."""
    i, v = series.current_a, series.voltage_v
    rested = (np.abs(i[1:]) <= rest_a) & (np.abs(i[:-1]) <= rest_a)
    dv = np.diff(v)[rested]
    if dv.size < 20:
        dv = np.diff(v)
    if dv.size == 0:
        return 0.0
    mad = 1.4826 * float(np.median(np.abs(dv - np.median(dv))))
    # quantised records change by one step now and then (MAD = 0): RMS without the
    # largest 2 % (relaxation right after a current edge)
    sq = np.sort(dv * dv)[: max(1, int(0.98 * dv.size))]
    return max(mad, math.sqrt(float(np.mean(sq)))) / math.sqrt(2.0)


def decimate(series: TimeSeries, factor: int) -> TimeSeries:
    """Block averages of ``factor`` samples: time of the block's last sample, the current
    that passes the block's charge over its duration, mean voltage and temperature."""
    if factor <= 1:
        return series
    n = len(series) // factor * factor
    if n == 0:
        return series
    t = series.time_s[:n]
    dt = np.diff(series.time_s, prepend=series.time_s[0])[:n]
    i = series.current_a[:n]
    t_b = t.reshape(-1, factor)[:, -1]
    dt_b = dt.reshape(-1, factor).sum(axis=1)
    q_b = (i * dt).reshape(-1, factor).sum(axis=1)
    i_mean = i.reshape(-1, factor).mean(axis=1)
    i_b = np.where(dt_b > 0, q_b / np.where(dt_b > 0, dt_b, 1.0), i_mean)
    v_b = series.voltage_v[:n].reshape(-1, factor).mean(axis=1)
    temp = None if series.temperature_c is None else \
        series.temperature_c[:n].reshape(-1, factor).mean(axis=1)
    return TimeSeries(t_b, i_b, v_b, temp, None, series.source, series.notes)


# -- signatures ---------------------------------------------------------------------------

def _context(model: EcmModel, series: TimeSeries, stop: int) -> dict:
    tables = (model.charge, model.discharge)
    tau_slow = np.concatenate([t.tau_slow_s.ravel() for t in tables])
    r_total = float(np.median(np.concatenate(
        [(t.r0_ohm + t.r_fast_ohm + t.r_slow_ohm).ravel() for t in tables])))
    dur = float(series.time_s[stop - 1] - series.time_s[0]) if stop > 1 else 0.0
    ctx = {"capacity_ah": model.capacity_ah, "r_total_ohm": r_total,
           "tau_min_s": float(max(30.0, 2.0 * np.median(tau_slow))),
           "tau_max_s": float(max(600.0, min(20000.0, 2.0 * dur)))}
    ctx["tau_min_s"] = min(ctx["tau_min_s"], ctx["tau_max_s"] / 4)
    t = series.temperature_c
    ctx["t_ref_c"] = float(np.median(t[:max(1, min(stop, 10))])) if t is not None else 25.0
    return ctx


def _hysteresis_signature(y: np.ndarray, rows: np.ndarray, q_as: np.ndarray, s: np.ndarray,
                          q: float) -> Signature:
    """The residual ``y`` against h(decay) (the sign and history of the current: ``q_as`` the
    charge moved in each step, A s; ``s`` the direction, +-1) and s, the best of four
    decays."""
    best = (0.0, None, None)
    for frac in (0.01, 0.03, 0.1, 0.3):
        h = rc_recurrence(np.exp(-q_as / (3600.0 * frac * q)),
                          (1 - np.exp(-q_as / (3600.0 * frac * q))) * s, s[0])
        X = np.column_stack([h, s, np.ones_like(h)])[rows]
        r2, coef = _r2(y, X)
        if r2 > best[0] or best[1] is None:
            best = (r2, frac, coef)
    r2, frac, coef = best
    m = float(abs(coef[0])) if coef is not None else 0.005
    m0 = float(max(coef[1], 0.0)) if coef is not None else 0.0
    b = float(np.clip(-(coef[2]) / max(m + m0, 1e-6), -1, 1)) if coef is not None else 0.0
    return Signature(
        fx.Hysteresis.name, True, r2,
        f"residual ~ m*h + m0*s + c with h the direction memory over {frac * q:.3g} Ah: "
        f"m {coef[0] * 1e3:.2f} mV, m0 {coef[1] * 1e3:.2f} mV, c {coef[2] * 1e3:.2f} mV",
        {"m_v": min(max(m, 0.002), 0.2), "decay_ah": frac * q, "m0_v": min(m0, 0.05),
         "ocv_table_state": b, "initial_state": float(s[0])})


def signatures(model: EcmModel, series: TimeSeries, sim: SimResult, rows: np.ndarray,
               ctx: dict, min_temp_span_c: float = 1.0) -> dict[str, Signature]:
    """Each effect's signature in the residual (measured - simulated) on ``rows``."""
    res = (series.voltage_v - sim.voltage_v)
    y = res[rows]
    dt = np.diff(series.time_s, prepend=series.time_s[0])
    i = series.current_a
    q = model.capacity_ah
    s = np.where(sim.charging, 1.0, -1.0)
    out: dict[str, Signature] = {fx.Hysteresis.name: _hysteresis_signature(
        y, rows, np.abs(i) * dt, s, q)}

    # current dependence: residual against the ohmic + fast voltage and its |I| weighting
    v_rf = sim.u_fast_v + (sim.voltage_v - sim.ocv_v - sim.u_fast_v - sim.u_slow_v
                           - (sim.extra_v if sim.extra_v is not None else 0.0))
    X = np.column_stack([v_rf, v_rf * np.abs(i) / q])[rows]
    r2, coef = _r2(y, X)
    out[fx.CurrentDependentResistance.name] = Signature(
        fx.CurrentDependentResistance.name, True, r2,
        f"residual ~ a*(r0 i + u_fast) + b*(r0 i + u_fast)*|I|/Q: a {coef[0]:.3f}, b {coef[1]:.3f}",
        {})

    # slow pole: residual against low-pass-filtered current
    best = (0.0, None, 0.0)
    lo, hi = ctx["tau_min_s"], ctx["tau_max_s"]
    for tau in np.geomspace(lo, hi, 6):
        X = _lowpass(dt, i, float(tau))[rows, None]
        r2, coef = _r2(y, X)
        if r2 > best[0] or best[1] is None:
            best = (r2, float(tau), float(coef[0]))
    r2, tau, r = best
    out[fx.ExtraRc.name] = Signature(
        fx.ExtraRc.name, True, r2,
        f"residual ~ r * lowpass(I, tau) with tau {tau:.0f} s: r {r * 1e3:.2f} mohm",
        {"tau_s": tau, "r_ohm": max(r, 0.0)})

    # capacity: residual against Ah throughput x OCV slope
    slope = model.ocv.soc_slope(sim.soc, series.temperature_c if model.needs_temperature
                                else None)
    qq = np.cumsum(i * dt) / (3600.0 * q)
    X = (slope * qq)[rows, None]
    r2, coef = _r2(y, X)
    # v(scale) ~ v + slope * qq * (1/scale - 1)  ->  1/scale - 1 = coef
    cs = float(np.clip(1.0 / max(1.0 + coef[0], 0.2), 0.75, 1.3))
    out[fx.CapacityError.name] = Signature(
        fx.CapacityError.name, True, r2,
        f"residual ~ k * dOCV/dSOC * Ah throughput / Q: implied capacity scale {cs:.3f}",
        {"capacity_scale": cs})

    # temperature: residual against the resistive voltage x (1/T - 1/T_ref)
    name = fx.TemperatureDependence.name
    temp = series.temperature_c
    if temp is None:
        out[name] = Signature(name, False, 0.0, "the data carry no temperature")
    else:
        span = float(np.ptp(temp[rows]))
        if span < min_temp_span_c:
            out[name] = Signature(name, False, 0.0,
                                  f"temperature varies by only {span:.2f} K in the fit part")
        else:
            v_res = sim.voltage_v - sim.ocv_v - (sim.extra_v if sim.extra_v is not None else 0.0)
            x = v_res * (1.0 / (temp + KELVIN) - 1.0 / (ctx["t_ref_c"] + KELVIN))
            r2, coef = _r2(y, x[rows, None])
            out[name] = Signature(
                name, True, r2,
                f"residual ~ Ea/R * (r i + u) * (1/T - 1/T_ref), T_ref {ctx['t_ref_c']:.2f} degC: "
                f"Ea/R {coef[0]:.0f} K (temperature span {span:.1f} K)",
                {"activation_k": float(np.clip(coef[0], 100.0, 12000.0))})
    return out


def _starts(name: str, sig: Signature, ctx: dict, specs: dict[str, _Spec]) -> list[dict]:
    """Native starting values for a new effect (a few, for the nonconvex shapes)."""
    base = dict(_neutral(name, ctx))
    base.update({k: v for k, v in sig.guess.items() if k in base})
    if name == fx.Hysteresis.name:
        q = ctx["capacity_ah"]
        return [dict(base, decay_ah=d) for d in
                sorted({base["decay_ah"], 0.02 * q, 0.1 * q})]
    if name == fx.ExtraRc.name:
        lo, hi = specs["tau_s"].lo, specs["tau_s"].hi
        taus = sorted({float(np.clip(t, lo, hi)) for t in (base["tau_s"], math.sqrt(lo * hi) / 3,
                                                              math.sqrt(lo * hi) * 3)})
        r0 = base["r_ohm"] if base["r_ohm"] > 0 else 0.2 * ctx["r_total_ohm"]
        return [dict(base, tau_s=t, r_ohm=r0) for t in taus]
    if name == fx.CurrentDependentResistance.name:
        q = ctx["capacity_ah"]
        return [{"scale_at_zero": 1.2, "i0_a": f * q} for f in (0.5, 2.0, 8.0)]
    if name == fx.TemperatureDependence.name:
        return [dict(base, activation_k=base.get("activation_k", 3000.0))]
    return [base]


# -- the search's helpers -----------------------------------------------------------------

def _on_bound(values: dict, specs: dict, rtol: float = 0.01) -> str:
    """The first parameter that ended on a search bound beyond which the effect is not
    physical (either end of a scale: a time constant, a decay, a current; the upper end of a
    magnitude; either end of the capacity scale), as 'name = value', or ''."""
    for k, sp in specs.items():
        v = values.get(k)
        if v is not None and sp.ends_on_limit(v, rtol):
            return f"{k} = {v:.4g}"
    return ""


def _mae(e: np.ndarray) -> float:
    e = e[np.isfinite(e)]
    return float(np.mean(np.abs(e))) if e.size else float("nan")


JUDGE_SOC_MIN = 0.1      # held-out samples at or below this SOC are not judged
MIN_JUDGED = 50          # fewer held-out samples above JUDGE_SOC_MIN: nothing to judge


class NothingToJudge(ValueError):
    """The held-out part never rises above the SOC where diagnose judges."""


def _judged_samples(soc: np.ndarray, soc_min: float) -> tuple[np.ndarray, int]:
    """Indices of the held-out samples judged (SOC above ``soc_min``) and how many were left
    out; :class:`NothingToJudge` when fewer than ``MIN_JUDGED`` are left (a record at the
    end of discharge: its error measures where the cell ends, not a missing effect)."""
    keep = np.flatnonzero(soc > soc_min)
    if keep.size < MIN_JUDGED:
        raise NothingToJudge(
            f"the held-out part is above {100 * soc_min:.0f} % SOC in only {keep.size} of "
            f"{soc.size} samples (simulated from its start SOC): nothing diagnose can judge "
            f"there; diagnose a record that is, or judge on one ([diagnose] cycle, judge)")
    return keep, int(soc.size - keep.size)
