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
   forward sensitivities of the discrete step of :mod:`ecmgen.effects` give the exact
   Jacobian, scipy's bounded trust-region Gauss-Newton the steps; a few starts from
   the signature regressions for the nonconvex shape parameters), and judge every candidate on
   the held-out part, simulated at full resolution with :func:`ecmgen.simulate.simulate`.
   A candidate passes when the held-out MAE falls by at least ``min_rel_gain`` (relative),
   by at least ``min_gain_noise`` times the voltage noise (estimated from the rests) and
   by more than noise explains: the lower ``confidence`` bound of a circular block
   bootstrap of the per-sample gain |e_before| - |e_after| must be positive. Of the
   passing candidates the one with the lowest MAE over all the data (fit and held-out
   parts) is added, and all added effects are refitted jointly; when none passes, the
   search stops and nothing more is named.

The held-out part is ``judge_series`` when given (a second cycle), else the last
``1 - split`` of the fit cycle's duration (the model is simulated over the whole cycle;
only the first part is fitted).
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from . import effects as fx
from .measure import TimeSeries
from .model import RC_FIELDS, EcmModel, write_atomic
from .simulate import SimResult, initial_soc, rc_recurrence, simulate, step_inputs

KELVIN = fx.KELVIN


# -- results ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Signature:
    """How much of the base residual (fit part) one effect's signature explains."""

    name: str
    applicable: bool
    r2: float                 # share of the residual's sum of squares explained (0..1)
    detail: str               # what was regressed on what, best shape parameter
    guess: dict = field(default_factory=dict)   # starting values for the fit (native units)


@dataclass(frozen=True)
class Candidate:
    """One effect tried in one greedy round."""

    round: int
    name: str
    effect: object | None
    fit_mae_v: float          # MAE on the fit part with the candidate added
    judge_mae_v: float        # MAE on the held-out part
    gain_v: float             # held-out MAE before - after
    rel_gain: float           # gain_v / held-out MAE before
    ci_low_v: float           # lower confidence bound of gain_v (block bootstrap)
    passed: bool
    seconds: float
    message: str = ""


@dataclass(frozen=True)
class DiagnoseStep:
    """One effect added, with the held-out MAE before and after adding it."""

    name: str
    effect: object
    mae_before_v: float
    mae_after_v: float
    ci_low_v: float


@dataclass
class DiagnoseResult:
    base_model: EcmModel
    model: EcmModel                    # base + the effects added (in order)
    steps: tuple[DiagnoseStep, ...]
    candidates: tuple[Candidate, ...]
    signatures: dict[str, Signature]
    mae_before_v: float                # held-out MAE of the base model
    mae_after_v: float                 # held-out MAE of the augmented model
    fit_mae_before_v: float
    fit_mae_after_v: float
    noise_v: float                     # voltage noise (std) estimated from the rests
    split: str                         # how the held-out part was chosen, in words
    fit_series: TimeSeries
    judge_series: TimeSeries
    fit_stop: int                      # fit_series[:fit_stop] was fitted
    judge_start: int                   # judge_series[judge_start:] was judged
    soc0: float
    judge_soc0: float
    base_fit_sim: SimResult
    base_judge_sim: SimResult
    judge_sim: SimResult               # augmented model on the judge series
    seconds: float
    notes: tuple[str, ...] = ()

    @property
    def effects(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.steps)

    def to_json_dict(self, model_path: str | Path | None = None) -> dict:
        def f(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "effects": [{"name": s.name, "mae_before_v": f(s.mae_before_v),
                         "mae_after_v": f(s.mae_after_v), "gain_ci_low_v": f(s.ci_low_v),
                         "params": s.effect.params()} for s in self.steps],
            "mae_before_v": f(self.mae_before_v),
            "mae_after_v": f(self.mae_after_v),
            "fit_mae_before_v": f(self.fit_mae_before_v),
            "fit_mae_after_v": f(self.fit_mae_after_v),
            "noise_v": f(self.noise_v),
            "held_out": self.split,
            "signatures": {k: {"applicable": s.applicable, "r2": f(s.r2), "detail": s.detail}
                           for k, s in self.signatures.items()},
            "candidates": [{"round": c.round, "name": c.name, "judge_mae_v": f(c.judge_mae_v),
                            "gain_v": f(c.gain_v), "rel_gain": f(c.rel_gain),
                            "gain_ci_low_v": f(c.ci_low_v), "passed": c.passed,
                            "message": c.message} for c in self.candidates],
            "seconds": round(self.seconds, 2),
            "model": None if model_path is None else str(model_path),
        }


# -- small numeric helpers ----------------------------------------------------------------

def _interp_slope(x, xp, fp) -> np.ndarray:
    """d/dx of np.interp(x, xp, fp) (0 where np.interp clamps)."""
    xp = np.asarray(xp, dtype=np.float64)
    fp = np.asarray(fp, dtype=np.float64)
    if xp.size < 2:
        return np.zeros_like(x)
    j = np.clip(np.searchsorted(xp, x, side="right") - 1, 0, xp.size - 2)
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    return np.where((x < xp[0]) | (x > xp[-1]), 0.0, slope)


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


def block_bootstrap_low(d: np.ndarray, block: int, confidence: float, n_boot: int = 2000,
                        seed: int = 0) -> float:
    """Lower ``confidence`` bound of mean(d) by a circular block bootstrap."""
    n = d.size
    if n == 0:
        return float("nan")
    block = int(min(max(block, 1), n))
    nb = int(math.ceil(n / block))
    ext = np.concatenate([d, d[:block]])
    csum = np.concatenate([[0.0], np.cumsum(ext)])
    block_sum = csum[block:block + n] - csum[:n]          # sum of d[s:s+block] (circular)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n, size=(n_boot, nb))
    means = block_sum[starts].sum(axis=1) / (nb * block)
    return float(np.quantile(means, 1.0 - confidence))


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


# -- parameter layout ---------------------------------------------------------------------

@dataclass(frozen=True)
class _Spec:
    lo: float
    hi: float
    log: bool


def _specs(name: str, model: EcmModel, ctx: dict) -> dict[str, _Spec]:
    """Free parameters of an effect and their bounds (native units)."""
    q = model.capacity_ah
    if name == fx.Hysteresis.name:
        return {"m_v": _Spec(0.0, 0.3, False), "decay_ah": _Spec(0.002 * q, 0.5 * q, True),
                "m0_v": _Spec(0.0, 0.1, False), "ocv_table_state": _Spec(-1.0, 1.0, False),
                "initial_state": _Spec(-1.0, 1.0, False)}
    if name == fx.CurrentDependentResistance.name:
        return {"scale_at_zero": _Spec(0.2, 5.0, True), "i0_a": _Spec(0.02 * q, 50.0 * q, True)}
    if name == fx.ExtraRc.name:
        r_hi = max(0.5, 20.0 * ctx["r_total_ohm"])
        return {"r_ohm": _Spec(0.0, r_hi, False),
                "tau_s": _Spec(ctx["tau_min_s"], ctx["tau_max_s"], True)}
    if name == fx.CapacityError.name:
        return {"capacity_scale": _Spec(0.7, 1.4, False)}
    if name == fx.TemperatureDependence.name:
        return {"activation_k": _Spec(0.0, 15000.0, False)}
    raise ValueError(name)


def _fixed(name: str, ctx: dict) -> dict[str, float]:
    """Parameters that are set from the data, not fitted."""
    if name == fx.TemperatureDependence.name:
        return {"t_ref_c": ctx["t_ref_c"]}
    return {}


def _neutral(name: str, ctx: dict) -> dict[str, float]:
    """Parameter values at which the effect changes nothing (used as fallback start)."""
    return {
        fx.Hysteresis.name: {"m_v": 0.005, "decay_ah": 0.05 * ctx["capacity_ah"], "m0_v": 0.0,
                             "ocv_table_state": 0.0, "initial_state": 0.0},
        fx.CurrentDependentResistance.name: {"scale_at_zero": 1.0, "i0_a": ctx["capacity_ah"]},
        fx.ExtraRc.name: {"r_ohm": 0.0, "tau_s": 600.0},
        fx.CapacityError.name: {"capacity_scale": 1.0},
        fx.TemperatureDependence.name: {"activation_k": 0.0},
    }[name]


# -- the casadi model with forward sensitivities ---------------------------------------------

class _Problem:
    """Residual (simulated - measured) and its Jacobian for a set of effects whose
    parameters are partly free. Mirrors ecmgen.simulate + ecmgen.effects exactly."""

    def __init__(self, model: EcmModel, data: TimeSeries, soc0: float,
                 effects: list[tuple[str, dict[str, float], dict[str, _Spec]]]):
        import casadi as ca

        self.ca = ca
        self.model = model
        self.soc0 = float(soc0)
        self.t = data.time_s
        self.i = data.current_a
        self.v = data.voltage_v
        self.temp = data.temperature_c
        self.n = len(data)
        # effects: (name, values of all parameters, free parameter specs)
        self.effects = effects
        self.names = [e[0] for e in effects]
        self.free: list[tuple[int, str, _Spec]] = []
        self.const: list[tuple[int, str]] = []
        for k, (name, values, specs) in enumerate(effects):
            for pname in values:
                if pname in specs:
                    self.free.append((k, pname, specs[pname]))
                else:
                    self.const.append((k, pname))
        self.values = [dict(v) for _, v, _ in effects]
        dt, soc, charging, _ = step_inputs(model, self.t, self.i, self.soc0)
        self.dt = dt
        self.charging = charging
        self.s = np.where(charging, 1.0, -1.0)
        self.q_as = np.cumsum(self.i * dt)
        self.has_cap = fx.CapacityError.name in self.names
        self.has_temp = fx.TemperatureDependence.name in self.names and self.temp is not None
        self._build()

    # z <-> native ---------------------------------------------------------------------
    def z0(self) -> np.ndarray:
        out = []
        for k, pname, sp in self.free:
            v = min(max(self.values[k][pname], sp.lo), sp.hi)
            out.append(math.log(max(v, 1e-300)) if sp.log else v)
        return np.array(out, dtype=np.float64)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = [math.log(sp.lo) if sp.log else sp.lo for _, _, sp in self.free]
        hi = [math.log(sp.hi) if sp.log else sp.hi for _, _, sp in self.free]
        return np.array(lo), np.array(hi)

    def native(self, z, snap: bool = False) -> list[dict[str, float]]:
        """Parameter values of z; ``snap``: values within 1e-6 of the span of a bound are
        set to the bound (a term the fit switched off reads as exactly 0)."""
        vals = [dict(v) for v in self.values]
        for zk, (k, pname, sp) in zip(np.asarray(z, dtype=np.float64), self.free):
            x = float(math.exp(zk) if sp.log else zk)
            if snap:
                tol = 1e-6 * (sp.hi - sp.lo)
                x = sp.lo if x - sp.lo < tol else sp.hi if sp.hi - x < tol else x
            vals[k][pname] = x
        return vals

    def effects_of(self, z) -> list:
        return [fx.make_effect(name, **vals)
                for name, vals in zip(self.names, self.native(z, snap=True))]

    # casadi step ----------------------------------------------------------------------
    def _build(self) -> None:
        ca = self.ca
        nf, nc = len(self.free), len(self.const)
        pf = ca.SX.sym("pf", nf)
        pc = ca.SX.sym("pc", nc)
        par = [dict() for _ in self.names]
        for j, (k, pname, _) in enumerate(self.free):
            par[k][pname] = pf[j]
        for j, (k, pname) in enumerate(self.const):
            par[k][pname] = pc[j]
        rows = ["dt", "i", "s", "ocv"] + list(RC_FIELDS)
        if self.has_cap:
            rows += ["q", "soc"] + ["d_ocv"] + ["d_" + k for k in RC_FIELDS]
        if self.has_temp:
            rows += ["temp"]
        self.rows = rows
        u = ca.SX.sym("u", len(rows))
        U = {r: u[j] for j, r in enumerate(rows)}
        states = ["u_fast", "u_slow"]
        for k, name in enumerate(self.names):
            if name in (fx.Hysteresis.name, fx.ExtraRc.name):
                states.append(f"{name}#{k}")
        self.states = states
        x = ca.SX.sym("x", len(states))
        X = {s: x[j] for j, s in enumerate(states)}

        dt, i, s = U["dt"], U["i"], U["s"]
        ocv = U["ocv"]
        p = {k: U[k] for k in RC_FIELDS}
        if self.has_cap:
            scale = 1
            for k, name in enumerate(self.names):
                if name == fx.CapacityError.name:
                    scale = scale * par[k]["capacity_scale"]
            soc_sym = self.soc0 + U["q"] / (3600.0 * self.model.capacity_ah * scale)
            dsoc = soc_sym - U["soc"]
            ocv = ocv + U["d_ocv"] * dsoc
            p = {k: p[k] + U["d_" + k] * dsoc for k in RC_FIELDS}
        for k, name in enumerate(self.names):
            if name == fx.CurrentDependentResistance.name:
                xx = ca.fmax(ca.fabs(i) / par[k]["i0_a"], 1e-12)
                g = par[k]["scale_at_zero"] * ca.asinh(xx) / xx
                p["r0_ohm"] = p["r0_ohm"] * g
                p["r_fast_ohm"] = p["r_fast_ohm"] * g
            elif name == fx.TemperatureDependence.name and self.has_temp:
                f = ca.exp(par[k]["activation_k"] * (1.0 / (U["temp"] + KELVIN)
                                                    - 1.0 / (par[k]["t_ref_c"] + KELVIN)))
                for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
                    p[key] = p[key] * f
        a_f = ca.exp(-dt / p["tau_fast_s"])
        a_s = ca.exp(-dt / p["tau_slow_s"])
        nxt = {"u_fast": a_f * X["u_fast"] + p["r_fast_ohm"] * (1 - a_f) * i,
               "u_slow": a_s * X["u_slow"] + p["r_slow_ohm"] * (1 - a_s) * i}
        v = ocv + p["r0_ohm"] * i + nxt["u_fast"] + nxt["u_slow"]
        for k, name in enumerate(self.names):
            key = f"{name}#{k}"
            if name == fx.Hysteresis.name:
                e = par[k]
                a_h = ca.exp(-ca.fabs(i) * dt / (3600.0 * e["decay_ah"]))
                nxt[key] = a_h * X[key] + (1 - a_h) * s
                v = v + e["m_v"] * (nxt[key] - e["ocv_table_state"]) \
                    + e["m0_v"] * (s - e["ocv_table_state"])
            elif name == fx.ExtraRc.name:
                a3 = ca.exp(-dt / par[k]["tau_s"])
                nxt[key] = a3 * X[key] + par[k]["r_ohm"] * (1 - a3) * i
                v = v + nxt[key]
        xn = ca.vertcat(*[nxt[s_] for s_ in states])
        S = ca.SX.sym("S", len(states), nf)
        Sn = ca.jacobian(xn, x) @ S + ca.jacobian(xn, pf)
        dv = ca.jacobian(v, x) @ S + ca.jacobian(v, pf)
        xa = ca.vertcat(x, ca.vec(S))
        xan = ca.vertcat(xn, ca.vec(Sn))
        self.F = ca.Function("F", [xa, u, pf, pc], [xan, ca.vertcat(v, dv.T)])
        self.Fm = self.F.mapaccum("Fm", self.n)
        # initial state (h_{-1} = initial_state) and its sensitivity
        self._x0_index = {}
        for k, name in enumerate(self.names):
            if name == fx.Hysteresis.name:
                self._x0_index[k] = states.index(f"{name}#{k}")

    def _inputs(self, vals) -> np.ndarray:
        m = self.model
        i = self.i
        scale = 1.0
        for name, v in zip(self.names, vals):
            if name == fx.CapacityError.name:
                scale *= v["capacity_scale"]
        soc = self.soc0 + self.q_as / (3600.0 * m.capacity_ah * scale)
        ch = self.charging
        pc_, pd_ = m.charge.at(soc), m.discharge.at(soc)
        cols = {"dt": self.dt, "i": i, "s": self.s, "ocv": m.ocv.ocv_at(soc)}
        for k in RC_FIELDS:
            cols[k] = np.where(ch, pc_[k], pd_[k])
        if self.has_cap:
            cols["q"] = self.q_as
            cols["soc"] = soc
            cols["d_ocv"] = _interp_slope(soc, m.ocv.soc, m.ocv.ocv_v)
            for k in RC_FIELDS:
                dc = _interp_slope(soc, m.charge.soc, getattr(m.charge, k))
                dd = _interp_slope(soc, m.discharge.soc, getattr(m.discharge, k))
                cols["d_" + k] = np.where(ch, dc, dd)
        if self.has_temp:
            cols["temp"] = self.temp
        return np.vstack([cols[r] for r in self.rows])

    def simulate(self, z) -> tuple[np.ndarray, np.ndarray]:
        """Simulated voltage and its Jacobian with respect to z."""
        vals = self.native(z)
        nf = len(self.free)
        xa0 = np.zeros(len(self.states) * (1 + nf))
        for k, j in self._x0_index.items():
            xa0[j] = vals[k]["initial_state"]
            for col, (kk, pname, _) in enumerate(self.free):
                if kk == k and pname == "initial_state":
                    xa0[len(self.states) + col * len(self.states) + j] = 1.0
        pf = np.array([vals[k][p] for k, p, _ in self.free])
        pc = np.array([vals[k][p] for k, p in self.const])
        _, out = self.Fm(xa0, self._inputs(vals), pf, pc)
        out = np.asarray(out)
        v = out[0]
        jac = out[1:].T.copy() if nf else np.zeros((self.n, 0))
        for col, (k, pname, sp) in enumerate(self.free):
            if sp.log:
                jac[:, col] *= vals[k][pname]
        return v, jac


def _fit(problem: _Problem, rows: np.ndarray, starts: list[np.ndarray], max_nfev: int,
         f_scale: float) -> tuple[np.ndarray, float]:
    """Bounded Gauss-Newton (scipy TRF, casadi Jacobian) from the best of ``starts``."""
    from scipy.optimize import least_squares

    lo, hi = problem.bounds()
    span = np.maximum(hi - lo, 1e-12)
    cache: dict = {}

    def both(z):
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            v, jac = problem.simulate(z)
            r = (v - problem.v)[rows]
            jr = jac[rows]
            bad = ~np.isfinite(r)
            if bad.any():
                r = np.where(bad, 1.0, r)
                jr = np.where(bad[:, None], 0.0, jr)
            cache[key] = (r, np.nan_to_num(jr))
        return cache[key]

    def clip(z):
        return np.clip(z, lo + 1e-9 * span, hi - 1e-9 * span)

    best = None
    n_start_nfev = 6 if len(starts) > 1 else max_nfev
    for z in starts:
        sol = least_squares(lambda z: both(z)[0], clip(z), jac=lambda z: both(z)[1],
                            bounds=(lo, hi), method="trf", x_scale="jac", loss="soft_l1",
                            f_scale=f_scale, max_nfev=n_start_nfev, xtol=1e-6, ftol=1e-7)
        if best is None or sol.cost < best.cost:
            best = sol
    if len(starts) > 1:
        best = least_squares(lambda z: both(z)[0], clip(best.x), jac=lambda z: both(z)[1],
                             bounds=(lo, hi), method="trf", x_scale="jac", loss="soft_l1",
                             f_scale=f_scale, max_nfev=max_nfev, xtol=1e-6, ftol=1e-7)
    return best.x, float(best.cost)


# -- signatures ---------------------------------------------------------------------------

def _context(model: EcmModel, series: TimeSeries, stop: int) -> dict:
    tables = (model.charge, model.discharge)
    tau_slow = np.concatenate([t.tau_slow_s for t in tables])
    r_total = float(np.median(np.concatenate(
        [t.r0_ohm + t.r_fast_ohm + t.r_slow_ohm for t in tables])))
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
    slope = _interp_slope(sim.soc, model.ocv.soc, model.ocv.ocv_v)
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

def _mae(e: np.ndarray) -> float:
    e = e[np.isfinite(e)]
    return float(np.mean(np.abs(e))) if e.size else float("nan")


def diagnose(base_model: EcmModel, fit_series: TimeSeries,
             judge_series: TimeSeries | None = None, soc0: float | None = None,
             judge_soc0: float | None = None, *, split: float = 0.6,
             candidates=fx.EFFECT_NAMES, max_effects: int = 4, min_rel_gain: float = 0.08,
             min_gain_noise: float = 1.0, min_gain_v: float = 2e-4, confidence: float = 0.99,
             block_s: float | None = None, max_fit_samples: int = 12000, max_nfev: int = 40,
             loss_scale_v: float | None = None, seed: int = 0,
             progress: Callable[[str], None] | None = None) -> DiagnoseResult:
    """Find the effects missing from ``base_model`` on ``fit_series`` (see module doc).

    judge_series     a second cycle to judge on; None: the last ``1 - split`` of the
                     fit cycle's duration is held out
    soc0, judge_soc0 start SOC of the cycles (default: from the OCV of the first rested
                     voltage, :func:`ecmgen.simulate.initial_soc`)
    candidates       effect names to try (default all five); effects already in
                     ``base_model`` are kept as they are and not tried again
    max_effects      at most this many effects are added
    min_rel_gain, min_gain_noise, min_gain_v, confidence
                     the held-out test (module doc); ``block_s`` is the bootstrap block
                     length (default: 1/20 of the held-out duration, at least 60 s)
    max_fit_samples  longer fit parts are block-averaged to this many samples for the
                     parameter fits (judging is always at full resolution)
    max_nfev         Gauss-Newton iterations per fit
    loss_scale_v     scale of the soft-L1 loss of the fits (default: max(3 x noise,
                     half the base MAE on the fit part, 1 mV))
    progress         called with one line of text per step
    Raises ValueError for unknown candidates, a bad split or too short records."""
    t_start = _time.perf_counter()
    say = progress or (lambda _m: None)
    unknown = [c for c in candidates if c not in fx.EFFECT_TYPES]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {list(fx.EFFECT_NAMES)}")
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
    noise = noise_std(fit_series, rest_a)
    floor_v = max(min_gain_v, min_gain_noise * noise)
    same = judge_series is None
    tj = judge.time_s[judge_start:]
    if block_s is None:
        block_s = max(60.0, (tj[-1] - tj[0]) / 20.0)
    block = max(1, int(round(block_s / max(np.median(np.diff(tj)), 1e-6))))

    def sim_judge(model):
        return simulate(model, judge.time_s, judge.current_a, judge_soc0, judge.temperature_c)

    def sim_fit(model):
        return simulate(model, fit_series.time_s, fit_series.current_a, soc0,
                        fit_series.temperature_c)

    vj = judge.voltage_v[judge_start:]
    base_fit_sim = sim_fit(base_model)
    base_judge_sim = base_fit_sim if same else sim_judge(base_model)
    e_fit0 = base_fit_sim.voltage_v[:fit_stop] - fit_series.voltage_v[:fit_stop]
    e_j0 = base_judge_sim.voltage_v[judge_start:] - vj
    mae0 = _mae(e_j0)
    fit_mae0 = _mae(e_fit0)
    say(f"base model: held-out MAE {mae0 * 1e3:.2f} mV, fit-part MAE {fit_mae0 * 1e3:.2f} mV, "
        f"noise {noise * 1e3:.2f} mV")

    ctx = _context(base_model, fit_series, fit_stop)
    sigs = signatures(base_model, fit_series, base_fit_sim, np.arange(fit_stop), ctx)
    existing = {e.name for e in base_model.effects}
    order = [n for n in sorted(sigs, key=lambda n: -sigs[n].r2)
             if n in candidates and sigs[n].applicable and n not in existing]
    for n in sorted(sigs, key=lambda n: -sigs[n].r2):
        say(f"signature {n}: {sigs[n].r2:.3f}  {sigs[n].detail}")

    # fitting data: the fit part, block-averaged when long
    fit_part = fit_series.slice(0, fit_stop)
    factor = max(1, int(math.ceil(fit_stop / max_fit_samples)))
    fit_data = decimate(fit_part, factor)
    rows = np.arange(len(fit_data))
    f_scale = (loss_scale_v if loss_scale_v is not None
               else max(3.0 * noise, 0.5 * fit_mae0, 1e-3))

    # effects already in the base model stay as they are (fixed parameters)
    fixed_effects = [(e.name, e.params(), {}) for e in base_model.effects]
    added: list[tuple[str, dict, dict]] = []       # (name, values, specs) fitted so far
    current = base_model
    e_cur = e_j0
    mae_cur = mae0
    steps: list[DiagnoseStep] = []
    cands: list[Candidate] = []
    judge_sim = base_judge_sim
    fit_mae_cur = fit_mae0
    rnd = 0

    def judged(effects):
        model = base_model.with_effects(effects)
        sj = sim_judge(model)
        e1 = sj.voltage_v[judge_start:] - vj
        sf = sj if same else sim_fit(model)
        fit_mae1 = _mae(sf.voltage_v[:fit_stop] - fit_series.voltage_v[:fit_stop])
        return model, sj, e1, _mae(e1), fit_mae1

    def fitted(layout, starts_native, fixed):
        """Fit the free parameters of the last layout entry (and of any other entry
        that has specs) from the best of the starts; returns the effects."""
        name, _, specs = layout[-1]
        prob = _Problem(base_model.with_effects(()), fit_data, soc0,
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
            specs = _specs(name, base_model, ctx)
            fixed = _fixed(name, ctx)
            starts = _starts(name, sigs[name], ctx, specs)
            # the effects added so far keep their parameters while a candidate is fitted
            layout = fixed_effects + [(n, dict(v), {}) for n, v, _ in added]
            try:
                vals, effects = fitted(layout + [(name, None, specs)], starts, fixed)
            except (ValueError, ArithmeticError, RuntimeError) as exc:
                cands.append(Candidate(rnd, name, None, float("nan"), float("nan"), float("nan"),
                                       float("nan"), float("nan"), False,
                                       _time.perf_counter() - t0, f"fit failed: {exc}"))
                continue
            model, sj, e1, mae1, fit_mae1 = judged(effects)
            d = np.abs(e_cur) - np.abs(e1)
            d = np.where(np.isfinite(d), d, 0.0)
            low = block_bootstrap_low(d, block, confidence, seed=seed + rnd)
            gain = mae_cur - mae1
            rel = gain / mae_cur if mae_cur > 0 else 0.0
            ok = bool(np.isfinite(mae1) and rel >= min_rel_gain and low > 0.0
                      and gain >= floor_v)
            if ok:
                why = ""
            elif not np.isfinite(mae1) or gain <= 0:
                why = "held-out error did not fall"
            elif low <= 0.0:
                why = "held-out gain within what noise explains (bootstrap)"
            elif gain < floor_v:
                why = f"held-out gain below {floor_v * 1e3:.2f} mV (noise level)"
            else:
                why = f"held-out gain {100 * rel:.1f} % < {100 * min_rel_gain:.0f} %"
            new = effects[-1]
            cands.append(Candidate(rnd, name, new, fit_mae1, mae1, gain, rel, low, ok,
                                   _time.perf_counter() - t0, why))
            say(f"round {rnd} {name}: held-out MAE {mae1 * 1e3:.2f} mV (gain "
                f"{gain * 1e3:.2f} mV, {100 * rel:.1f} %, lower bound {low * 1e3:.2f} mV), "
                f"fit MAE {fit_mae1 * 1e3:.2f} mV [{_time.perf_counter() - t0:.1f} s] "
                f"{new.summary()}")
            tried.append((ok, mae1, name, vals, specs, model, sj, e1, low, fit_mae1))
        passing = [c for c in tried if c[0]]
        if not passing:
            break
        # of the candidates that pass the held-out test, the one with the lowest MAE over
        # all the data (fit part and held-out part, weighted by their samples)
        n_fit, n_judge = fit_stop, len(vj)
        _, mae1, name, vals, specs, model, sj, e1, low, fit_mae1 = min(
            passing, key=lambda c: (n_judge * c[1] + n_fit * c[9]) / (n_judge + n_fit))
        n_fixed = len(fixed_effects)
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
                if judged_j[3] <= mae1:
                    model, sj, e1, mae1, fit_mae1 = judged_j
                    new_added = [(n, v, sp) for (n, _, sp), v in
                                 zip(new_added, vals_j[n_fixed:])]
                    say(f"joint refit: held-out MAE {mae1 * 1e3:.2f} mV")
            except (ValueError, ArithmeticError, RuntimeError):
                pass
        added = new_added
        steps.append(DiagnoseStep(name, model.effects[-1], mae_cur, mae1, low))
        say(f"added {name}: held-out MAE {mae_cur * 1e3:.2f} -> {mae1 * 1e3:.2f} mV")
        current, e_cur, mae_cur, judge_sim, fit_mae_cur = model, e1, mae1, sj, fit_mae1
        order = [n for n in order if n != name]

    # each step reports the effect as it is in the final model (parameters refitted jointly)
    final = {e.name: e for e in current.effects}
    steps = [replace(st, effect=final.get(st.name, st.effect)) for st in steps]
    return DiagnoseResult(
        base_model=base_model, model=current, steps=tuple(steps), candidates=tuple(cands),
        signatures=sigs, mae_before_v=mae0, mae_after_v=mae_cur, fit_mae_before_v=fit_mae0,
        fit_mae_after_v=fit_mae_cur, noise_v=noise, split=split_words, fit_series=fit_series,
        judge_series=judge, fit_stop=fit_stop, judge_start=judge_start, soc0=soc0,
        judge_soc0=judge_soc0, base_fit_sim=base_fit_sim, base_judge_sim=base_judge_sim,
        judge_sim=judge_sim, seconds=_time.perf_counter() - t_start,
        notes=(f"fit on {len(fit_data)} samples (block averages of {factor})",)
        if factor > 1 else ())


# -- the [diagnose] section of the build config ----------------------------------------------

def diagnose_options(table, path=None) -> dict:
    """Check the optional ``[diagnose]`` table of a build config and turn it into keyword
    arguments of :func:`diagnose` (plus ``"judge"``: the judge cycle's file name as
    written, relative to the config, or None). Unknown keys or bad values raise
    InputError naming ``path``::

        [diagnose]
        judge = "hwfet-a.mat"     # a second cycle to judge on (default: the last part of
                                  # data.cycle, see split)
        judge_soc0 = 1.0          # its start SOC (default: from its first rested voltage)
        split = 0.6               # fraction of data.cycle that is fitted without a judge
        effects = ["hysteresis", "extra_rc"]   # candidates (default: all five)
        max_effects = 4
        min_rel_gain = 0.08       # held-out MAE must fall by at least this fraction
        confidence = 0.99         # of the block-bootstrap bound on the held-out gain
    """
    from .errors import InputError

    table = {} if table is None else table
    if not isinstance(table, dict):
        raise InputError(path, "[diagnose] must be a table")
    known = {"judge", "judge_soc0", "split", "effects", "max_effects", "min_rel_gain",
             "confidence"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise InputError(path, f"unknown key(s) in [diagnose]: {', '.join(unknown)}; "
                               f"known: {', '.join(sorted(known))}")

    def number(key, lo, hi, integer=False):
        v = table[key]
        ok = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok or not (lo <= v <= hi):
            kind = "an integer" if integer else "a number"
            raise InputError(path, f"diagnose.{key} must be {kind} in [{lo}, {hi}], got {v!r}")
        return int(v) if integer else float(v)

    out: dict = {"judge": None}
    if "judge" in table:
        if not isinstance(table["judge"], str) or not table["judge"]:
            raise InputError(path, "diagnose.judge must be a file name")
        out["judge"] = table["judge"]
    if "judge_soc0" in table:
        out["judge_soc0"] = number("judge_soc0", 0.0, 1.0)
    if "split" in table:
        out["split"] = number("split", 0.1, 0.9)
    if "effects" in table:
        eff = table["effects"]
        if not isinstance(eff, list) or not eff or any(e not in fx.EFFECT_TYPES for e in eff):
            raise InputError(path, f"diagnose.effects must be a non-empty list from "
                                   f"{list(fx.EFFECT_NAMES)}, got {eff!r}")
        out["candidates"] = tuple(eff)
    if "max_effects" in table:
        out["max_effects"] = number("max_effects", 1, len(fx.EFFECT_NAMES), integer=True)
    if "min_rel_gain" in table:
        out["min_rel_gain"] = number("min_rel_gain", 0.0, 0.9)
    if "confidence" in table:
        out["confidence"] = number("confidence", 0.5, 0.9999)
    return out


# -- outputs: model.json, plots, report.md ---------------------------------------------------

EFFECT_WORDS = {
    fx.Hysteresis.name: "OCV hysteresis: the voltage depends on the sign and history of the "
                        "current (one-state Plett model)",
    fx.CurrentDependentResistance.name: "resistance falling with |I| (Butler-Volmer-like "
                                        "charge transfer)",
    fx.ExtraRc.name: "a slow polarisation (a further RC pair with a time constant of minutes) "
                     "that 10 s pulses cannot see",
    fx.CapacityError.name: "the capacity used for coulomb counting is off",
    fx.TemperatureDependence.name: "resistances falling as the cell warms (Arrhenius)",
}


def _signature_x(name: str, result: DiagnoseResult):
    """x values and label of an effect's signature plot over the fit part."""
    s = result.fit_series
    sim = result.base_fit_sim
    stop = result.fit_stop
    dt = np.diff(s.time_s, prepend=s.time_s[0])
    i = s.current_a
    q = result.base_model.capacity_ah
    g = result.signatures[name].guess
    if name == fx.Hysteresis.name:
        ch = np.where(sim.charging, 1.0, -1.0)
        a = np.exp(-np.abs(i) * dt / (3600.0 * g.get("decay_ah", 0.05 * q)))
        x = rc_recurrence(a, (1 - a) * ch, ch[0])
        return x[:stop], f"direction memory h (decay {g.get('decay_ah', 0.05 * q):.3g} Ah)"
    if name == fx.CurrentDependentResistance.name:
        return i[:stop], "current [A]"
    if name == fx.ExtraRc.name:
        tau = g.get("tau_s", 600.0)
        return _lowpass(dt, i, tau)[:stop], f"current low-pass filtered, tau {tau:.0f} s [A]"
    if name == fx.CapacityError.name:
        return (np.cumsum(i * dt) / 3600.0)[:stop], "charge throughput [Ah]"
    if name == fx.TemperatureDependence.name:
        if s.temperature_c is None:
            return None, "temperature (not in the data)"
        return s.temperature_c[:stop], "cell temperature [degC]"
    raise ValueError(name)


def _binned(x, y, n=25):
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 10 or np.ptp(x) <= 0:
        return np.array([]), np.array([])
    edges = np.quantile(x, np.linspace(0, 1, n + 1))
    edges = np.unique(edges)
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    sy = np.bincount(k, weights=y, minlength=edges.size - 1)
    sx = np.bincount(k, weights=x, minlength=edges.size - 1)
    m = cnt > 0
    return sx[m] / cnt[m], sy[m] / cnt[m]


def plot_signatures(result: DiagnoseResult, path: Path) -> Path:
    """Residual of the base model (fit part) against each effect's signature."""
    from .plots import _plt

    plt = _plt()
    res = (result.fit_series.voltage_v - result.base_fit_sim.voltage_v)[:result.fit_stop] * 1e3
    names = list(fx.EFFECT_NAMES)
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5))
    rng = np.random.default_rng(0)
    pick = rng.choice(res.size, size=min(res.size, 4000), replace=False)
    for ax, name in zip(axes.flat, names):
        sig = result.signatures[name]
        x, label = _signature_x(name, result)
        if x is None:
            ax.text(0.5, 0.5, sig.detail, ha="center", va="center", transform=ax.transAxes,
                    fontsize=9, wrap=True)
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.plot(x[pick], res[pick], ".", ms=2, alpha=0.25, color="0.5")
            bx, by = _binned(x, res)
            ax.plot(bx, by, "o-", color="C3", ms=3, lw=1.2, label="binned mean")
            ax.axhline(0, color="k", lw=0.6)
            lo, hi = np.percentile(res, [1, 99])
            pad = 0.1 * (hi - lo + 1e-3)
            ax.set_ylim(lo - pad, hi + pad)
        added = name in result.effects
        ax.set_title(f"{name}  (explains {100 * sig.r2:.0f} %)" + ("  ADDED" if added else ""),
                     fontsize=9, color="C2" if added else "k")
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel("measured - base [mV]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    t = result.fit_series.time_s[:result.fit_stop]
    ax = axes.flat[5]
    ax.plot(t, res, lw=0.5, color="C0")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_title("residual over time (fit part)", fontsize=9)
    ax.set_xlabel("time [s]", fontsize=8)
    ax.set_ylabel("measured - base [mV]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    fig.suptitle("Where the base model misses: residual against each effect's signature",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_comparison(result: DiagnoseResult, path: Path) -> Path:
    """Held-out part: measured vs base vs augmented voltage, the errors, MAE per step."""
    from .plots import _plt

    plt = _plt()
    a = result.judge_start
    s = result.judge_series
    t = s.time_s[a:]
    vm = s.voltage_v[a:]
    vb = result.base_judge_sim.voltage_v[a:]
    va = result.judge_sim.voltage_v[a:]
    fig = plt.figure(figsize=(13, 9))
    gs = fig.add_gridspec(3, 4)
    ax0 = fig.add_subplot(gs[0, :])
    ax0.plot(t, vm, lw=0.8, color="k", label="measured")
    ax0.plot(t, vb, lw=0.7, color="C1", label=f"base (MAE {result.mae_before_v * 1e3:.2f} mV)")
    ax0.plot(t, va, lw=0.7, color="C2",
             label=f"with {', '.join(result.effects) or 'no effects'} "
                   f"(MAE {result.mae_after_v * 1e3:.2f} mV)")
    ax0.set_ylabel("voltage [V]")
    ax0.legend(fontsize=8, loc="lower left")
    ax0.set_title(f"held out: {result.split}", fontsize=9)
    ax0.grid(alpha=0.3)
    ax1 = fig.add_subplot(gs[1, :], sharex=ax0)
    ax1.plot(t, (vb - vm) * 1e3, lw=0.5, color="C1", label="base")
    ax1.plot(t, (va - vm) * 1e3, lw=0.5, color="C2", label="augmented")
    ax1.axhline(0, color="k", lw=0.6)
    e = np.concatenate([vb - vm, va - vm]) * 1e3
    lo, hi = np.percentile(e, [0.5, 99.5])
    ax1.set_ylim(lo - 0.1 * (hi - lo + 1), hi + 0.1 * (hi - lo + 1))
    ax1.set_ylabel("simulated - measured [mV]")
    ax1.set_xlabel("time [s]")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2 = fig.add_subplot(gs[2, :2])
    labels = ["base"] + [f"+ {st.name}" for st in result.steps]
    maes = [result.mae_before_v * 1e3] + [st.mae_after_v * 1e3 for st in result.steps]
    ax2.bar(range(len(maes)), maes, color=["C1"] + ["C2"] * len(result.steps))
    ax2.set_xticks(range(len(maes)))
    ax2.set_xticklabels(labels, fontsize=8, rotation=15)
    ax2.set_ylabel("held-out MAE [mV]")
    ax2.grid(alpha=0.3, axis="y")
    ax3 = fig.add_subplot(gs[2, 2:])
    rounds = sorted({c.round for c in result.candidates})
    for r in rounds:
        cs = [c for c in result.candidates if c.round == r and math.isfinite(c.judge_mae_v)]
        ax3.plot([c.judge_mae_v * 1e3 for c in cs], [c.name for c in cs], "o",
                 label=f"round {r}")
    ax3.axvline(result.mae_before_v * 1e3, color="C1", lw=0.8, ls="--")
    ax3.set_xlabel("held-out MAE with the candidate [mV]")
    ax3.tick_params(labelsize=7)
    ax3.legend(fontsize=7)
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def report_text(result: DiagnoseResult, model_name: str = "model.json") -> str:
    """report.md: what is missing, in words, with the numbers behind it."""
    mv = lambda x: f"{x * 1e3:.2f} mV"  # noqa: E731
    lines = ["# ecmgen diagnose", ""]
    fit_name = Path(result.fit_series.source).name or "the cycle"
    lines += [f"Fitted on: {fit_name} (first {result.fit_stop} samples)",
              f"Held out: {result.split}",
              f"Start SOC {result.soc0:.4f} (held-out record {result.judge_soc0:.4f}); "
              f"voltage noise {mv(result.noise_v)} (std, from the rests); "
              f"run time {result.seconds:.1f} s", ""]
    lines += ["## Verdict", ""]
    if result.steps:
        lines.append(f"The base model misses {len(result.steps)} effect(s); each was added "
                     "only because it lowered the error on data the fit did not see by more "
                     "than noise explains:")
        lines.append("")
        for k, st in enumerate(result.steps, 1):
            lines.append(f"{k}. **{st.name}** - {EFFECT_WORDS[st.name]}. Held-out MAE "
                         f"{mv(st.mae_before_v)} -> {mv(st.mae_after_v)} "
                         f"({100 * (1 - st.mae_after_v / st.mae_before_v):.0f} % lower; "
                         f"99 % lower bound of the gain {mv(st.ci_low_v)}).")
        lines += ["", f"Held-out MAE of the base model {mv(result.mae_before_v)}, of the "
                      f"augmented model ({model_name}) {mv(result.mae_after_v)}."]
    else:
        lines.append(f"Nothing is missing that this data can show: no effect lowered the "
                     f"held-out MAE ({mv(result.mae_before_v)}) by more than noise explains. "
                     f"{model_name} is the base model unchanged.")
    lines += ["", "## Signatures in the base residual (fit part)", "",
              "| effect | explains | what was regressed |", "|---|---|---|"]
    for name, sig in sorted(result.signatures.items(), key=lambda kv: -kv[1].r2):
        share = f"{100 * sig.r2:.1f} %" if sig.applicable else "n/a"
        lines.append(f"| {name} | {share} | {sig.detail} |")
    lines += ["", "## Candidates tried", "",
              "| round | effect | held-out MAE | gain | gain lower bound | kept | why not |",
              "|---|---|---|---|---|---|---|"]
    kept = {(k + 1, st.name) for k, st in enumerate(result.steps)}
    for c in result.candidates:
        yes = (c.round, c.name) in kept
        why = c.message or ("" if yes else "passed, but another candidate did better")
        lines.append(f"| {c.round} | {c.name} | {mv(c.judge_mae_v)} | {mv(c.gain_v)} "
                     f"({100 * c.rel_gain:.1f} %) | {mv(c.ci_low_v)} | "
                     f"{'yes' if yes else 'no'} | {why} |")
    if result.steps:
        lines += ["", "## Effect parameters (as in the augmented model)", ""]
        for st in result.steps:
            params = ", ".join(f"{k} = {v:.6g}" for k, v in st.effect.params().items())
            lines.append(f"- {st.name}: {params}")
    lines += ["", "## Plots", "", "- diagnose-signatures.png: the base residual against each "
              "effect's signature", "- diagnose-comparison.png: measured vs base vs augmented "
              "on the held-out part, and the MAE per step"]
    for n in result.notes:
        lines.append(f"- note: {n}")
    return "\n".join(lines) + "\n"


def write_diagnose_outputs(result: DiagnoseResult, out_dir: str | Path, *, plots: bool = True,
                           model_name: str = "model.json") -> list[Path]:
    """Write the augmented model, report.md, diagnose.json and the plots into ``out_dir``."""
    import json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [result.model.save(out / model_name)]
    report = out / "report.md"
    write_atomic(report, report_text(result, model_name))
    files.append(report)
    js = out / "diagnose.json"
    write_atomic(js, json.dumps(result.to_json_dict(out / model_name), indent=1) + "\n")
    files.append(js)
    if plots:
        files.append(plot_signatures(result, out / "diagnose-signatures.png"))
        files.append(plot_comparison(result, out / "diagnose-comparison.png"))
    return files
