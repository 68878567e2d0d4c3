"""Find where simulation and measurement disagree, name the missing effect, add it.

``diagnose(base_model, fit_series, judge_series=None)``:

1. simulate the base model over the measured cycle and take the residual
   (measured - simulated voltage);
2. test each effect's *signature* on the fit part: the least-squares share of the
   residual explained by the effect's first-order voltage sensitivity (residual against
   the sign and history of the current for ``hysteresis``, against |I| for
   ``current_dependent_resistance``, against low-pass-filtered current for ``extra_rc``,
   against Ah throughput for ``capacity_error``, against temperature for
   ``temperature_dependence``);
3. greedily, one effect at a time: add each remaining candidate, fit its parameters on
   the fit part (least squares on the voltage time series with a soft-L1 loss; casadi
   forward sensitivities of the discrete step of :mod:`ecmgen.model.effects` give the exact
   Jacobian, scipy's bounded trust-region Gauss-Newton the steps; a few starts from
   the signature regressions for the nonconvex shape parameters), and judge every candidate on
   the held-out part, simulated at full resolution with :func:`ecmgen.model.simulate.simulate`.
   A candidate passes when the held-out MAE falls by at least ``min_rel_gain`` (relative),
   by at least ``min_gain_noise`` times the voltage noise (estimated from the rests) and
   by more than noise explains: the lower ``confidence`` bound of a circular block
   bootstrap of the per-sample gain |e_before| - |e_after| must be positive. Of the
   passing candidates the one with the lowest MAE over all the data (fit and held-out
   parts) is added, and all added effects are refitted jointly; when none passes, the
   search stops and nothing more is named.

Besides the model's effects, the faults of the record are candidates
(:mod:`ecmgen.diagnosis.corrections`: a current sensor's offset and gain, an OCV table
that is off); one that is added corrects the data the later rounds fit and judge. A
candidate is named only where it beats its look-alikes (the other candidates that passed
in its round, each judged again in its place among all that was added at the end) by the
held-out test; otherwise the verdict is "X or Y - the data cannot tell them apart"
(:mod:`ecmgen.diagnosis.lookalike`).

The held-out part is ``judge_series`` when given (a second cycle), else the last
``1 - split`` of the fit cycle's duration (the model is simulated over the whole cycle;
only the first part is fitted).

The candidate problems of step 3 are :mod:`ecmgen.diagnosis.problems`; what diagnose
writes (model, report, plots) is :mod:`ecmgen.diagnosis.output`.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..data.measure import TimeSeries
from ..model import effects as fx
from ..model.effects import KELVIN
from ..model.model import EcmModel
from ..model.rc import rc_recurrence
from ..model.simulate import SimResult, initial_soc, simulate
from ..parallel import one_blas_thread
from . import corrections as cx
from .options import CANDIDATE_NAMES, diagnose_options  # noqa: F401
from .lookalike import block_bootstrap_low, lookalikes, rivals, told_apart  # noqa: F401
from .prune import Fitted, still_needed
from .problems import _Problem, _Spec, _fit, _fixed, _neutral, _specs
from .refits import PulseRefit, hysteresis_on_refitted_base
from .result import (UNEXPLAINED_RATIO, Candidate, DiagnoseResult, DiagnoseStep,  # noqa: F401
                     Signature, explained_floor)


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


def signatures(model: EcmModel, series: TimeSeries, sim: SimResult, rows: np.ndarray,
               ctx: dict, min_temp_span_c: float = 1.0) -> dict[str, Signature]:
    """Each effect's signature in the residual (measured - simulated) on ``rows``."""
    res = (series.voltage_v - sim.voltage_v)
    y = res[rows]
    dt = np.diff(series.time_s, prepend=series.time_s[0])
    i = series.current_a
    q = model.capacity_ah
    s = np.where(sim.charging, 1.0, -1.0)
    out: dict[str, Signature] = {}

    # hysteresis: residual against h(decay) (the sign and history of the current) and s
    best = (0.0, None, None)
    for frac in (0.01, 0.03, 0.1, 0.3):
        h = rc_recurrence(np.exp(-np.abs(i) * dt / (3600.0 * frac * q)),
                          (1 - np.exp(-np.abs(i) * dt / (3600.0 * frac * q))) * s, s[0])
        X = np.column_stack([h, s, np.ones_like(h)])[rows]
        r2, coef = _r2(y, X)
        if r2 > best[0] or best[1] is None:
            best = (r2, frac, coef)
    r2, frac, coef = best
    m = float(abs(coef[0])) if coef is not None else 0.005
    m0 = float(max(coef[1], 0.0)) if coef is not None else 0.0
    b = float(np.clip(-(coef[2]) / max(m + m0, 1e-6), -1, 1)) if coef is not None else 0.0
    out[fx.Hysteresis.name] = Signature(
        fx.Hysteresis.name, True, r2,
        f"residual ~ m*h + m0*s + c with h the direction memory over {frac * q:.3g} Ah: "
        f"m {coef[0] * 1e3:.2f} mV, m0 {coef[1] * 1e3:.2f} mV, c {coef[2] * 1e3:.2f} mV",
        {"m_v": min(max(m, 0.002), 0.2), "decay_ah": frac * q, "m0_v": min(m0, 0.05),
         "ocv_table_state": b, "initial_state": float(s[0])})

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


# -- the greedy search ----------------------------------------------------------------------

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


@one_blas_thread
def diagnose(base_model: EcmModel, fit_series: TimeSeries,
             judge_series: TimeSeries | None = None, soc0: float | None = None,
             judge_soc0: float | None = None, *, split: float = 0.6,
             candidates=CANDIDATE_NAMES, max_effects: int = 4, min_rel_gain: float = 0.08,
             min_gain_noise: float = 1.0, min_gain_v: float = 2e-4, confidence: float = 0.99,
             block_s: float | None = None, judge_soc_min: float = JUDGE_SOC_MIN,
             max_fit_samples: int = 12000, max_nfev: int = 40,
             loss_scale_v: float | None = None, seed: int = 0,
             progress: Callable[[str], None] | None = None,
             base_refits: dict | None = None,
             pulse_refit: PulseRefit | None = None) -> DiagnoseResult:
    """Find the effects missing from ``base_model`` on ``fit_series`` (see module doc).

    judge_series     a second cycle to judge on; None: the last ``1 - split`` of the
                     fit cycle's duration is held out
    soc0, judge_soc0 start SOC of the cycles (default: from the OCV of the first rested
                     voltage, :func:`ecmgen.model.simulate.initial_soc`)
    candidates       effect names to try (default all five); effects already in
                     ``base_model`` are kept as they are and not tried again
    max_effects      at most this many effects are added
    min_rel_gain, min_gain_noise, min_gain_v, confidence
                     the held-out test (module doc); ``block_s`` is the bootstrap block
                     length (default: 1/20 of the held-out duration, at least 60 s)
    judge_soc_min    held-out samples where the base model's SOC is at or below this are
                     not judged (the end-of-discharge knee of the OCV: there the error
                     measures where the cell ends, not the effect; the validation's MAE
                     above 10 % SOC leaves them out for the same reason);
                     :class:`NothingToJudge` when fewer than ``MIN_JUDGED`` are above
    max_fit_samples  longer fit parts are block-averaged to this many samples for the
                     parameter fits (judging is always at full resolution)
    max_nfev         Gauss-Newton iterations per fit
    loss_scale_v     scale of the soft-L1 loss of the fits (default: max(3 x noise,
                     half the base MAE on the fit part, 1 mV))
    progress         called with one line of text per step
    base_refits      effect name -> callable returning (base model refitted with the
                     effect, the effect, a note) or None: the candidate is that model, judged
                     as it is (the test that made the base shows the effect's parameters
                     better than the cycle's fit part); None: fitted on the cycle as others
    pulse_refit      the pulse test that made the base: a hysteresis is also tried on the
                     base refitted there with it taken out (:mod:`.refits`), and kept so
                     where that fits the cycle's fit part better
    Raises ValueError for unknown candidates, a bad split or too short records."""
    t_start = _time.perf_counter()
    say = progress or (lambda _m: None)
    base0 = base_model
    refits = dict(base_refits or {})
    refitted: dict = {}
    base_notes: dict[str, str] = {}
    unknown = [c for c in candidates if c not in CANDIDATE_NAMES]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {list(CANDIDATE_NAMES)}")
    if soc0 is None:
        soc0 = initial_soc(base_model, fit_series)
    soc0 = float(soc0)
    t = fit_series.time_s
    if judge_series is None:
        if not 0.1 <= split <= 0.9:
            raise ValueError("split must be in [0.1, 0.9]")
        t_cut = t[0] + split * (t[-1] - t[0])
        fit_stop = int(np.searchsorted(t, t_cut, side="right"))
        judge_start = fit_stop
        judge = fit_series
        judge_soc0 = soc0
        name = Path(fit_series.source).name or "the cycle"
        split_words = (f"the last {100 * (1 - split):.0f} % of {name} (from t = "
                       f"{t[fit_stop]:.0f} s; the first {100 * split:.0f} % was fitted)")
    else:
        fit_stop = len(fit_series)
        judge_start = 0
        judge = judge_series
        if judge_soc0 is None:
            judge_soc0 = initial_soc(base_model, judge_series)
        judge_soc0 = float(judge_soc0)
        split_words = (f"all of {Path(judge_series.source).name or 'the judge cycle'} "
                       f"(all of {Path(fit_series.source).name or 'the fit cycle'} was fitted)")
    if fit_stop < 50 or len(judge) - judge_start < 50:
        raise ValueError("too few samples to fit and judge on")
    rest_a = max(base_model.direction_deadband_a, base_model.capacity_ah / 100.0)
    sample_s = float(np.median(np.diff(t)))
    noise = noise_std(fit_series, rest_a)
    floor_v = max(min_gain_v, min_gain_noise * noise)
    same = judge_series is None
    tj = judge.time_s[judge_start:]
    if block_s is None:
        block_s = max(60.0, (tj[-1] - tj[0]) / 20.0)
    block = max(1, int(round(block_s / max(np.median(np.diff(tj)), 1e-6))))

    def sim_judge(model, series=None):
        s = judge if series is None else series
        return simulate(model, s.time_s, s.current_a, judge_soc0, s.temperature_c)

    def sim_fit(model, series=None):
        s = fit_series if series is None else series
        return simulate(model, s.time_s, s.current_a, soc0, s.temperature_c)

    fit_record, judge_record = fit_series, judge      # as read (the faults found are not)
    base_fit_sim = sim_fit(base_model)
    base_judge_sim = base_fit_sim if same else sim_judge(base_model)
    keep, below = _judged_samples(base_judge_sim.soc[judge_start:], judge_soc_min)
    if below:
        split_words += f", above {100 * judge_soc_min:.0f} % SOC ({below} samples below left out)"
    vj = judge.voltage_v[judge_start:][keep]
    e_fit0 = base_fit_sim.voltage_v[:fit_stop] - fit_series.voltage_v[:fit_stop]
    e_j0 = base_judge_sim.voltage_v[judge_start:][keep] - vj
    mae0 = _mae(e_j0)
    fit_mae0 = _mae(e_fit0)
    say(f"base model: held-out MAE {mae0 * 1e3:.2f} mV, fit-part MAE {fit_mae0 * 1e3:.2f} mV, "
        f"noise {noise * 1e3:.2f} mV")

    ctx = _context(base_model, fit_series, fit_stop)
    sigs = signatures(base_model, fit_series, base_fit_sim, np.arange(fit_stop), ctx)
    existing = {e.name for e in base_model.effects}
    order = [n for n in sorted(sigs, key=lambda n: -sigs[n].r2)
             if n in candidates and sigs[n].applicable and n not in existing]
    order += [n for n in cx.CORRECTION_NAMES if n in candidates and cx.applicable(
        n, base_model, sigs[fx.TemperatureDependence.name].applicable)]
    for n in sorted(sigs, key=lambda n: -sigs[n].r2):
        say(f"signature {n}: {sigs[n].r2:.3f}  {sigs[n].detail}")

    # fitting data: the fit part, block-averaged when long
    fit_part = fit_series.slice(0, fit_stop)
    factor = max(1, int(math.ceil(fit_stop / max_fit_samples)))
    fit_data = decimate(fit_part, factor)
    rows = np.arange(len(fit_data))
    f_scale = (loss_scale_v if loss_scale_v is not None
               else max(3.0 * noise, 0.5 * fit_mae0, 1e-3))

    cap_scale = sigs[fx.CapacityError.name].guess.get("capacity_scale", 1.0)
    # effects already in the base model stay as they are (fixed parameters)
    fixed_effects = [(e.name, e.params(), {}) for e in base_model.effects]
    added: list[tuple[str, dict, dict]] = []       # (name, values, specs) fitted so far
    current = base_model
    e_cur, ef_cur = e_j0, e_fit0
    mae_cur = mae0
    steps: list[DiagnoseStep] = []
    cands: list[Candidate] = []
    judge_sim = base_judge_sim
    fit_mae_cur = fit_mae0
    rnd = 0
    notes: list[str] = []
    applied: list = []       # the record's faults found so far (corrected in the data)
    alikes: list = []        # per step: (its look-alikes in its round, on a refitted base)

    def refit_on(base, layout, name, start):
        """``name`` fitted on ``base`` from ``start`` (an effect): (the effect, the fit
        part's MAE, (values, effects, specs) and what :func:`judged` gives)."""
        ctx_b = _context(base, fit_series, fit_stop)
        specs_b, fixed_b = _specs(name, base, ctx_b), _fixed(name, ctx_b)
        vals_b, effects_b = fitted(layout + [(name, None, specs_b)], [start.params()],
                                   fixed_b, base=base)
        j = judged(effects_b, base)
        return effects_b[-1], j[4], ((vals_b, effects_b, specs_b), j)

    def judged(effects, base=None, fixes=None):
        """The model with ``effects`` on ``base``, the record's faults ``fixes`` (default:
        those found so far) corrected, simulated on the held-out and fit parts: (model,
        held-out simulation, held-out error, its MAE, the fit part's MAE)."""
        fixes = applied if fixes is None else fixes
        model = cx.corrected_model(base_model if base is None else base,
                                   fixes).with_effects(effects)
        sj = sim_judge(model, cx.apply_all(judge_record, fixes))
        # a lagging voltage channel is compared on the model's side
        sj = replace(sj, voltage_v=cx.channel_voltage(fixes, judge.time_s, sj.voltage_v))
        e1 = sj.voltage_v[judge_start:][keep] - vj
        if same:
            v_fit = sj.voltage_v
        else:
            v_fit = cx.channel_voltage(fixes, fit_record.time_s, sim_fit(
                model, cx.apply_all(fit_record, fixes)).voltage_v)
        ef = v_fit[:fit_stop] - fit_record.voltage_v[:fit_stop]
        return model, sj, e1, _mae(e1), _mae(ef), ef

    def fit_data_for(fixes):
        s = cx.apply_all(fit_record, fixes).slice(0, fit_stop)
        if any(isinstance(c, cx.VoltageLag) for c in fixes):
            # what the lag shows of the model as it is, taken out of the record's voltage
            # for the later fits (judging compares on the model's side)
            v = sim_fit(cx.corrected_model(base_model, fixes).with_effects(current.effects),
                        s).voltage_v
            s = replace(s, voltage_v=s.voltage_v - cx.channel_voltage(fixes, s.time_s, v) + v)
        return decimate(s, factor)

    def fit_fault(name, model, fixes):
        """The record's fault ``name`` fitted with ``model`` on the record with ``fixes``
        corrected (a lag at full resolution: block averages would hide it)."""
        if name == cx.VoltageLag.name:
            data, at = cx.apply_all(fit_record, fixes).slice(0, fit_stop), np.arange(fit_stop)
        else:
            data, at = fit_data_for(fixes), rows
        return cx.fit(name, model, data, soc0, at, cap_scale, f_scale, max_nfev, ctx["t_ref_c"])

    def fitted(layout, starts_native, fixed, base=None, fixes=None):
        """Fit the free parameters of the last layout entry (and of any other entry
        that has specs) from the best of the starts, on the record with ``fixes``
        (default: the faults found so far) corrected; returns the effects."""
        name, _, specs = layout[-1]
        prob = _Problem(cx.corrected_model(base or base_model,
                                           applied if fixes is None else fixes
                                           ).with_effects(()),
                        fit_data if fixes is None else fit_data_for(fixes), soc0,
                        layout[:-1] + [(name, dict(starts_native[0], **fixed), specs)])
        z_starts = []
        for st in starts_native:
            prob.values[-1] = dict(st, **fixed)
            z_starts.append(prob.z0())
        z, _ = _fit(prob, rows, z_starts, max_nfev, f_scale)
        return prob.native(z, snap=True), prob.effects_of(z)

    while order and len(steps) < max_effects:
        rnd += 1
        tried = []
        for name in order:
            t0 = _time.perf_counter()
            # the effects added so far keep their parameters while a candidate is fitted
            layout = fixed_effects + [(n, dict(v), {}) for n, v, _ in added]
            if name in refits and name not in refitted:
                refitted[name] = refits[name]()
            new_base = corr = None
            try:
                if name in cx.CORRECTION_TYPES:
                    corr = fit_fault(name, current, applied)
                    specs = cx.specs(name, base_model.capacity_ah)
                    vals = [dict(v) for _, v, _ in layout] + [corr.params()]
                    effects = list(current.effects)
                elif refitted.get(name) is not None:
                    new_base, effect, note = refitted[name]
                    specs = {}
                    vals = [dict(v) for _, v, _ in layout] + [effect.params()]
                    effects = list(current.effects) + [effect]
                else:
                    specs, fixed = _specs(name, base_model, ctx), _fixed(name, ctx)
                    vals, effects = fitted(layout + [(name, None, specs)],
                                           _starts(name, sigs[name], ctx, specs), fixed)
            except (ValueError, ArithmeticError, RuntimeError) as exc:
                cands.append(Candidate(rnd, name, None, float("nan"), float("nan"), float("nan"),
                                       float("nan"), float("nan"), False,
                                       _time.perf_counter() - t0, f"fit failed: {exc}"))
                continue
            model, sj, e1, mae1, fit_mae1, ef1 = judged(
                effects, new_base, None if corr is None else applied + [corr])
            if name == fx.Hysteresis.name and pulse_refit is not None and base_model is base0:
                alt = hysteresis_on_refitted_base(
                    pulse_refit, base0.ocv, effects[-1],
                    lambda b, start: refit_on(b, layout, name, start))
                if alt is not None and alt[2][1][4] < fit_mae1:
                    new_base, base_notes[name] = alt[0], alt[1]
                    (vals, effects, specs), (model, sj, e1, mae1, fit_mae1, ef1) = alt[2]
            d = np.abs(e_cur) - np.abs(e1)
            d = np.where(np.isfinite(d), d, 0.0)
            low = block_bootstrap_low(d, block, confidence, seed=seed + rnd)
            gain = mae_cur - mae1
            rel = gain / mae_cur if mae_cur > 0 else 0.0
            bound = _on_bound(vals[-1], specs)
            short = "" if corr is None else cx.unresolved(corr, sample_s)
            ok = bool(np.isfinite(mae1) and rel >= min_rel_gain and low > 0.0
                      and gain >= floor_v and not bound and not short)
            if ok:
                why = ""
            elif short:
                why = short
            elif bound:
                why = (f"{bound} on its bound: the effect's best fit lies outside what it "
                       "can be, so it does not explain the residual")
            elif not np.isfinite(mae1) or gain <= 0:
                why = "held-out error did not fall"
            elif low <= 0.0:
                why = "held-out gain within what noise explains (bootstrap)"
            elif gain < floor_v:
                why = f"held-out gain below {floor_v * 1e3:.2f} mV (noise level)"
            else:
                why = f"held-out gain {100 * rel:.1f} % < {100 * min_rel_gain:.0f} %"
            new = corr if corr is not None else effects[-1]
            cands.append(Candidate(rnd, name, new, fit_mae1, mae1, gain, rel, low, ok,
                                   _time.perf_counter() - t0, why))
            say(f"round {rnd} {name}: held-out MAE {mae1 * 1e3:.2f} mV (gain "
                f"{gain * 1e3:.2f} mV, {100 * rel:.1f} %, lower bound {low * 1e3:.2f} mV), "
                f"fit MAE {fit_mae1 * 1e3:.2f} mV [{_time.perf_counter() - t0:.1f} s] "
                f"{new.summary()}")
            tried.append((ok, mae1, name, vals, specs, model, sj, e1, low, fit_mae1, new_base,
                          new, ef1))
        passing = [c for c in tried if c[0]]
        if not passing:
            break
        # of the candidates that pass the held-out test, the one with the lowest MAE over
        # all the data (fit part and held-out part, weighted by their samples)
        n_fit, n_judge = fit_stop, len(vj)
        passing.sort(key=lambda c: (n_judge * c[1] + n_fit * c[9]) / (n_judge + n_fit))
        plain = [c for c in passing if c[10] is None]
        if passing[0][10] is not None and plain and block_bootstrap_low(
                np.abs(plain[0][7]) - np.abs(passing[0][7]), block, confidence,
                seed=seed + rnd) <= 0.0:
            # a candidate on a base refitted for it has the pulse test's freedom too: it
            # wins over one on the base as it is only by the held-out test any candidate
            # must pass
            passing.insert(0, plain[0])
        _, mae1, name, vals, specs, model, sj, e1, low, fit_mae1, new_base, new, ef1 = passing[0]
        # the others that passed are judged again at the end, each in the winner's place
        # among all that was added (a winner on a refitted base: its look-alikes here)
        alikes.append((lookalikes(passing, block, confidence, seed + rnd) if new_base
                       is not None else rivals(passing), new_base is not None))
        if new_base is not None:
            # the effect came with its own base tables: later candidates build on them
            base_model = new_base
            notes.append(base_notes.get(name) or refitted[name][2])
        n_fixed = len(fixed_effects)
        if name in cx.CORRECTION_TYPES:
            # a fault of the record: the data corrected, later candidates fitted on it
            applied.append(new)
            fit_data = fit_data_for(applied)
            new_added = [(n, v, sp) for (n, _, sp), v in zip(added, vals[n_fixed:])]
        else:
            new_added = [(n, v, sp) for (n, _, sp), v in
                         zip(added + [(name, None, specs)], vals[n_fixed:])]
        if added:
            # refit all added effects jointly, from where they are; kept if the held-out
            # error does not get worse
            try:
                layout = fixed_effects + [(n, dict(v), sp) for n, v, sp in new_added]
                last = layout[-1]
                vals_j, effects_j = fitted(layout, [last[1]], {})
                judged_j = judged(effects_j)
                # kept only where it leaves no parameter on its search bound (a candidate
                # that ends there does not pass either)
                bound_j = any(_on_bound(v, sp) for (_, _, sp), v in
                              zip(new_added, vals_j[n_fixed:]))
                if judged_j[3] <= mae1 and not bound_j:
                    model, sj, e1, mae1, fit_mae1, ef1 = judged_j
                    new_added = [(n, v, sp) for (n, _, sp), v in
                                 zip(new_added, vals_j[n_fixed:])]
                    say(f"joint refit: held-out MAE {mae1 * 1e3:.2f} mV")
            except (ValueError, ArithmeticError, RuntimeError):
                pass
        added = new_added
        steps.append(DiagnoseStep(name, new if name in cx.CORRECTION_TYPES
                                  else model.effects[-1], mae_cur, mae1, low))
        say(f"added {name}: held-out MAE {mae_cur * 1e3:.2f} -> {mae1 * 1e3:.2f} mV")
        current, e_cur, mae_cur, judge_sim, fit_mae_cur = model, e1, mae1, sj, fit_mae1
        ef_cur = ef1
        order = [n for n in order if n != name]

    def without(state, drop):
        """``state`` with the named ``drop`` taken out: each fault left refitted on the
        record without it, then the effects left jointly; None where a fit fails or ends on
        a bound."""
        fixes = [c for c in state.fixes if c.name != drop]
        kept = [(n, dict(v), sp) for n, v, sp in state.added if n != drop]
        effects = [e for e in state.model.effects if e.name != drop]
        try:
            for k, c in enumerate(fixes):
                others = fixes[:k] + fixes[k + 1:]
                fixes[k] = fit_fault(c.name, cx.corrected_model(base_model, others).with_effects(
                    effects), others)
                if _on_bound(fixes[k].params(), cx.specs(c.name, base_model.capacity_ah)) or \
                        cx.unresolved(fixes[k], sample_s):
                    return None
            if kept:
                vals, effects = fitted(fixed_effects + kept, [kept[-1][1]], {}, fixes=fixes)
                vals = vals[len(fixed_effects):]
                if any(_on_bound(v, sp) for (_, _, sp), v in zip(kept, vals)):
                    return None
                kept = [(n, v, sp) for (n, _, sp), v in zip(kept, vals)]
        except (ValueError, ArithmeticError, RuntimeError):
            return None
        model, sj, e1, mae1, fit_mae1, ef1 = judged(effects, None, fixes)
        say(f"without {drop}, the rest refitted: held-out MAE {mae1 * 1e3:.2f} mV "
            f"(with it {state.mae_v * 1e3:.2f})")
        return Fitted(fixes, kept, model, sj, e1, mae1, fit_mae1, ef1)

    def needed(state, alt):
        """Whether ``state`` needs what ``alt`` lacks: it beats ``alt`` on the held-out part
        by the test a candidate passes ("needed", or "tie" where ``alt`` beats it on the fit
        part by the bootstrap: the data favour each on one part), else "not needed"."""
        gain = alt.mae_v - state.mae_v
        d = np.abs(alt.e_judge) - np.abs(state.e_judge)
        low = block_bootstrap_low(np.where(np.isfinite(d), d, 0.0), block, confidence,
                                  seed=seed + 50)
        if not (np.isfinite(alt.mae_v) and gain >= floor_v and low > 0.0
                and gain >= min_rel_gain * alt.mae_v):
            return "not needed"
        d = np.abs(state.e_fit) - np.abs(alt.e_fit)
        low = block_bootstrap_low(np.where(np.isfinite(d), d, 0.0), block, confidence,
                                  seed=seed + 51)
        return "tie" if low > 0.0 else "needed"

    dropped: list = []
    prune_ties: list = []
    if len(steps) >= 2:
        # an effect named early must still be needed once the later ones joined
        state, left, dropped, prune_ties = still_needed(
            [st.name for st in steps], Fitted(list(applied), list(added), current, judge_sim,
                                              e_cur, mae_cur, fit_mae_cur, ef_cur),
            without, needed, {st.name for st, (_, rb) in zip(steps, alikes) if rb})
        if dropped:
            applied, added, current = state.fixes, state.added, state.model
            judge_sim, e_cur, mae_cur = state.judge_sim, state.e_judge, state.mae_v
            fit_mae_cur, ef_cur = state.fit_mae_v, state.e_fit
            gone = {d.name for d in dropped}
            alikes = [(names + [g for g in sorted(gone) if g not in names], rb) if not rb
                      else (names, rb) for st, (names, rb) in zip(steps, alikes)
                      if st.name not in gone]
            steps = [st for st in steps if st.name not in gone]
            for d in dropped:
                notes.append(f"{d.name}: not needed with {', '.join(left)}: dropped, the rest "
                             f"refitted without it leave {d.mae_without_v * 1e3:.2f} mV held "
                             f"out ({d.mae_with_v * 1e3:.2f} with it)")
                say(notes[-1])

    # each step reports the effect as it is in the final model (parameters refitted jointly)
    final = {e.name: e for e in current.effects}
    steps = [replace(st, effect=final.get(st.name, st.effect)) for st in steps]
    if factor > 1:
        notes.append(f"fit on {len(fit_data)} samples (block averages of {factor})")
    misfit = None if pulse_refit is None else pulse_refit.rms_v
    not_named: tuple = ()
    cannot_tell: list = []
    if steps and misfit is not None and mae_cur > UNEXPLAINED_RATIO * explained_floor(noise,
                                                                                      misfit):
        # what was added lowers the error but does not explain it: naming it would send a
        # user after the wrong physics (a look-alike of an effect without a candidate)
        not_named, steps = tuple(steps), []
        current, mae_cur, fit_mae_cur, judge_sim = base0, mae0, fit_mae0, base_judge_sim
        say(f"not named: {', '.join(st.name for st in not_named)} left "
            f"{not_named[-1].mae_after_v * 1e3:.2f} mV, above {UNEXPLAINED_RATIO:g}x "
            f"max(noise, the base's misfit on its pulse test)")

    def swapped(k, other):
        """(held-out error, fit part's error) with step k's effect replaced by ``other``,
        refitted with the other effects added (a fault of the record: fitted with them as
        they are, then they refitted on the record it corrects); None where a fit fails or
        ends on a bound."""
        drop = steps[k].name
        fixes = [c for c in applied if c.name != drop]
        kept = [e for e in current.effects if e.name != drop]
        layout = fixed_effects + [(n, dict(v), sp) for n, v, sp in added if n != drop]
        try:
            if other in cx.CORRECTION_TYPES:
                corr = fit_fault(other, cx.corrected_model(base_model, fixes).with_effects(kept),
                                 fixes)
                if _on_bound(corr.params(), cx.specs(other, base_model.capacity_ah)) or \
                        cx.unresolved(corr, sample_s):
                    return None
                fixes = fixes + [corr]
                if any(sp for _, _, sp in layout):
                    vals, kept = fitted(layout, [layout[-1][1]], {}, fixes=fixes)
                    if any(_on_bound(v, sp) for (_, _, sp), v in zip(layout, vals)):
                        return None
                return judged(kept, None, fixes)[2::3]
            specs = _specs(other, base_model, ctx)
            layout = layout + [(other, None, specs)]
            vals, effects = fitted(layout, _starts(other, sigs[other], ctx, specs),
                                   _fixed(other, ctx), fixes=fixes)
        except (ValueError, ArithmeticError, RuntimeError):
            return None
        if any(_on_bound(v, sp) for (_, _, sp), v in zip(layout, vals)):
            return None
        return judged(effects, None, fixes)[2::3]

    if steps:
        named = {st.name for st in steps}
        cannot_tell = told_apart(steps, alikes, swapped, (e_cur, ef_cur), block, confidence,
                                 seed) + [g for g in prune_ties if g[0] in named]
        for group in cannot_tell:
            say(f"{' or '.join(group)}: the data cannot tell them apart")
    if cannot_tell:
        # nothing named singly: model.json is the base (what was named beside them was
        # fitted with one of them)
        left_v = mae_cur
        current, mae_cur, fit_mae_cur, judge_sim = base0, mae0, fit_mae0, base_judge_sim
        tied = {n for g in cannot_tell for n in g}
        steps = [st for st in steps if st.name not in tied]
    return DiagnoseResult(
        base_model=base0, model=current, steps=tuple(steps), candidates=tuple(cands),
        signatures=sigs, mae_before_v=mae0, mae_after_v=mae_cur, fit_mae_before_v=fit_mae0,
        fit_mae_after_v=fit_mae_cur, noise_v=noise, split=split_words, fit_series=fit_record,
        judge_series=judge_record, fit_stop=fit_stop, judge_start=judge_start, soc0=soc0,
        judge_soc0=judge_soc0, base_fit_sim=base_fit_sim, base_judge_sim=base_judge_sim,
        judge_sim=judge_sim, seconds=_time.perf_counter() - t_start, notes=tuple(notes),
        misfit_v=misfit, not_named=not_named, cannot_tell=tuple(cannot_tell),
        dropped=tuple(dropped),
        cannot_tell_mae_v=left_v if cannot_tell else None)
