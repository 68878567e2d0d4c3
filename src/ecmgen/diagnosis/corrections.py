"""Candidates of ``diagnose`` that are faults of the record or of its OCV table, not effects
of the model: a current sensor's offset and gain, an OCV table that is off, and one that
lacks the OCV's move with temperature. Each looks like a model effect on
a cycle (a gain or an OCV table's SOC scale moves the SOC as a capacity error does; an OCV
offset or an offset current shifts the voltage as a hysteresis band can), so diagnose
fits them as candidates beside the effects and names one only where the held-out test
tells it from the rest.

A sensor fault is corrected in the data, never in the model (model.json and the C stay
as they are; the verdict says how the current reads). An OCV error corrects the OCV table
model.json carries (and an entropic term makes it an OCV over temperature). Measured =
what the logger wrote:

- ``current_offset``  measured current = true + offset_a
- ``current_gain``    measured current = true * (1 + gain)
- ``ocv_error``       true OCV(soc) = table(1 - (1 - soc) * soc_scale) + offset_v (the
                      SOC scale anchored at full, where a charge ends)
- ``entropic_ocv``    the table lacks the OCV's move with temperature: true OCV(soc, T) =
                      table(soc) + dOCV/dT(soc) (T - t_ref_c), dOCV/dT linear between its
                      values at nodes spread over the SOC the fit part covers, constant
                      beyond (a node outside it would have nothing to pin it down, and a
                      fit drifts it to its bound); model.json carries
                      it as an OCV over temperature (rows at ENTROPIC_T_C, linear between)

Each has a few parameters: they are fitted by scipy's bounded least squares (the
soft-L1 loss of the effects' fits) on the simulator itself, with finite differences.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from ..data.measure import TimeSeries
from ..model.model import EcmModel, OcvOverTemperature
from ..model.rc import rc_recurrence
from ..model.simulate import simulate
from .problems import _Spec


class _Correction:
    name: ClassVar[str] = ""
    kind: ClassVar[str] = ""          # "sensor" (the data corrected) or "ocv" (the table)

    def params(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def summary(self) -> str:
        return f"{self.name}(" + ", ".join(f"{k}={v:.4g}" for k, v in self.params().items()) + ")"


@dataclass(frozen=True)
class CurrentOffset(_Correction):
    offset_a: float
    name: ClassVar[str] = "current_offset"
    kind: ClassVar[str] = "sensor"

    def words(self) -> str:
        return f"the current reads {1e3 * self.offset_a:+.0f} mA off (an offset at any current)"


@dataclass(frozen=True)
class CurrentGain(_Correction):
    gain: float
    name: ClassVar[str] = "current_gain"
    kind: ClassVar[str] = "sensor"

    def words(self) -> str:
        return (f"the current reads {100 * abs(self.gain):.1f} % "
                f"{'high' if self.gain > 0 else 'low'}")


@dataclass(frozen=True)
class VoltageLag(_Correction):
    delay_s: float
    tau_s: float
    name: ClassVar[str] = "voltage_lag"
    kind: ClassVar[str] = "sensor"

    def words(self) -> str:
        return (f"the voltage channel lags the current: {self.delay_s:.2g} s late and "
                f"filtered with a {self.tau_s:.2g} s time constant")

    def channel(self, time_s: np.ndarray, voltage_v: np.ndarray) -> np.ndarray:
        """What a channel with this lag records of ``voltage_v``: ``delay_s`` late (linear
        between samples, the first value before the start), then first-order filtered."""
        v = np.asarray(voltage_v, dtype=np.float64)
        if self.delay_s > 0:
            v = np.interp(time_s - self.delay_s, time_s, v)
        if self.tau_s > 0:
            a = np.exp(-np.diff(time_s, prepend=time_s[0]) / self.tau_s)
            v = rc_recurrence(a, (1.0 - a) * v, float(v[0]))
        return v


@dataclass(frozen=True)
class OcvError(_Correction):
    offset_v: float
    soc_scale: float
    name: ClassVar[str] = "ocv_error"
    kind: ClassVar[str] = "ocv"

    def words(self) -> str:
        return (f"the OCV table is off: {1e3 * self.offset_v:+.1f} mV and its SOC axis "
                f"scaled by {self.soc_scale:.3f} from full")


@dataclass(frozen=True)
class EntropicOcv(_Correction):
    soc_lo: float
    soc_hi: float
    at1_v_per_k: float
    at2_v_per_k: float
    at3_v_per_k: float
    at4_v_per_k: float
    t_ref_c: float
    name: ClassVar[str] = "entropic_ocv"
    kind: ClassVar[str] = "ocv"

    def words(self) -> str:
        lo, hi = self.d_v_per_k(np.array([self.soc_lo, self.soc_hi]))
        return (f"the OCV moves with temperature: {1e3 * lo:+.3f} mV/K at "
                f"{100 * self.soc_lo:.0f} % SOC, {1e3 * hi:+.3f} at {100 * self.soc_hi:.0f} %")

    def soc_nodes(self) -> np.ndarray:
        return np.linspace(self.soc_lo, self.soc_hi, len(ENTROPIC_KEYS))

    def d_v_per_k(self, soc) -> np.ndarray:
        return np.interp(soc, self.soc_nodes(), [getattr(self, k) for k in ENTROPIC_KEYS])


# the temperature rows of an OCV with an entropic term (linear between: a cell's range), and
# its dOCV/dT's values: at nodes spread evenly over the SOC the fit part covers (a node
# outside it has no data to pin it down), linear between, constant beyond
ENTROPIC_T_C = (-40.0, 80.0)
ENTROPIC_KEYS = ("at1_v_per_k", "at2_v_per_k", "at3_v_per_k", "at4_v_per_k")

CORRECTION_TYPES: dict[str, type] = {c.name: c for c in (CurrentOffset, CurrentGain, OcvError,
                                                          EntropicOcv, VoltageLag)}
CORRECTION_NAMES: tuple[str, ...] = tuple(CORRECTION_TYPES)
MAX_LAG_S = 10.0

def specs(name: str, capacity_ah: float) -> dict[str, _Spec]:
    """Free parameters and bounds: beyond them the fault is not a sensor's or a table's
    (a 20 % gain, an offset of 5 % of 1C, 50 mV or a 20 % SOC scale are a wrong record)."""
    if name == CurrentOffset.name:
        q = 0.05 * capacity_ah
        return {"offset_a": _Spec(-q, q, False, limit_lo=True, limit_hi=True)}
    if name == CurrentGain.name:
        return {"gain": _Spec(-0.2, 0.2, False, limit_lo=True, limit_hi=True)}
    if name == OcvError.name:
        return {"offset_v": _Spec(-0.05, 0.05, False, limit_lo=True, limit_hi=True),
                "soc_scale": _Spec(0.8, 1.25, False, limit_lo=True, limit_hi=True)}
    if name == VoltageLag.name:
        # a logger's channels are misaligned by samples, not by the seconds of a cell's
        # polarisation: a lag of 10 s is an RC pair's, not a channel's
        return {k: _Spec(0.0, MAX_LAG_S, False, limit_hi=True) for k in ("delay_s", "tau_s")}
    if name == EntropicOcv.name:
        # the entropic dOCV/dT of Li-ion cells is within a mV/K at any SOC
        return {k: _Spec(-1.5e-3, 1.5e-3, False, limit_lo=True, limit_hi=True)
                for k in ENTROPIC_KEYS}
    raise ValueError(name)


def applicable(name: str, model: EcmModel, temperature_applies: bool) -> bool:
    """An entropic term needs a record whose temperature moves and an OCV table without a
    temperature axis; the others apply to any record."""
    if name == EntropicOcv.name:
        return temperature_applies and model.ocv.n_temperatures == 1
    return True


def corrected_series(series: TimeSeries, corr: _Correction) -> TimeSeries:
    """The record with a sensor fault taken out (an OCV error leaves it as it is)."""
    q = series.charge_ah
    if isinstance(corr, CurrentOffset):
        if q is not None:
            q = q - corr.offset_a * (series.time_s - series.time_s[0]) / 3600.0
        return replace(series, current_a=series.current_a - corr.offset_a, charge_ah=q)
    if isinstance(corr, CurrentGain):
        return replace(series, current_a=series.current_a / (1.0 + corr.gain),
                       charge_ah=None if q is None else q / (1.0 + corr.gain))
    return series


def unresolved(corr: _Correction, sample_s: float) -> str:
    """Why a fitted lag is not one the record can show, or ''. The simulation holds each
    logged current over its sample; whether a logger writes the current at the start, the
    end or as the mean of its sample moves the simulated voltage by up to a sample, so a
    lag (delay plus filter) shorter than one sample cannot be told from that."""
    if not isinstance(corr, VoltageLag) or corr.delay_s + corr.tau_s >= sample_s:
        return ""
    return (f"a lag of {corr.delay_s + corr.tau_s:.2g} s, less than the record's "
            f"{sample_s:.2g} s sample: not told from where in a sample the current is logged")


def channel_voltage(corrections, time_s: np.ndarray, voltage_v: np.ndarray) -> np.ndarray:
    """A simulated voltage as the record's voltage channel shows it (its lag, where one is
    among ``corrections``): the lag is compared on the model's side, never taken out of
    the record (undoing a filter would multiply the noise)."""
    for corr in corrections:
        if isinstance(corr, VoltageLag):
            voltage_v = corr.channel(time_s, voltage_v)
    return voltage_v


def apply_all(series: TimeSeries, corrections) -> TimeSeries:
    """The record with every sensor fault among ``corrections`` taken out, in order."""
    for corr in corrections:
        series = corrected_series(series, corr)
    return series


def corrected_model(model: EcmModel, corrections) -> EcmModel:
    """The model with its OCV table corrected by the ``ocv_error`` among ``corrections``
    (on the table's own SOC grid, each row kept non-decreasing)."""
    for corr in corrections:
        if isinstance(corr, EntropicOcv):
            o = model.ocv
            d_v_per_k = corr.d_v_per_k(o.soc)
            rows = [np.maximum.accumulate(o.ocv_v[0] + d_v_per_k * (t - corr.t_ref_c))
                    for t in ENTROPIC_T_C]
            model = replace(model, ocv=OcvOverTemperature(np.array(ENTROPIC_T_C), o.soc,
                                                          np.vstack(rows)))
        if isinstance(corr, OcvError):
            o = model.ocv
            shifted = 1.0 - (1.0 - o.soc) * corr.soc_scale
            rows = [o.ocv_at(shifted, None if o.n_temperatures == 1 else o.temperature_c[k])
                    + corr.offset_v for k in range(o.n_temperatures)]
            rows = [np.maximum.accumulate(r) for r in rows]
            model = replace(model, ocv=OcvOverTemperature(o.temperature_c, o.soc,
                                                          np.vstack(rows)))
    return model


def starts(name: str, capacity_scale: float) -> list[dict[str, float]]:
    """Starting values: neutral, and where SOC moves as the capacity signature implies."""
    k = float(np.clip(capacity_scale, 0.85, 1.15))
    if name == CurrentOffset.name:
        return [{"offset_a": 0.0}]
    if name == CurrentGain.name:
        return [{"gain": 0.0}, {"gain": k - 1.0}]
    if name == EntropicOcv.name:
        return [dict.fromkeys(ENTROPIC_KEYS, 0.0)]
    return [{"offset_v": 0.0, "soc_scale": 1.0}, {"offset_v": 0.0, "soc_scale": 1.0 / k}]


# a rest: a run of at least REST_MIN_S whose current stays within the offset's bound (5 % of
# 1C, with a margin) and changes by at most REST_STEP of 1C (or 5 sigmas of its noise) a sample
REST_MIN_S = 60.0
REST_STEP = 0.002


def rest_current(series: TimeSeries, capacity_ah: float) -> float | None:
    """The current the record logs where the cell rests: the mean over its rests (runs of
    at least REST_MIN_S of a small, flat current), or None where it has none or logs them
    as exactly zero (a logger that zeroes small currents shows no offset).

    A current sensor's offset is what it reads at zero current: a record with rests shows
    it there, whatever the voltage does (an OCV that moves with temperature drifts the
    voltage of a rest as an offset's SOC drift does, but its rests read zero)."""
    t, i = series.time_s, series.current_a
    small = np.abs(i) <= 1.2 * 0.05 * capacity_ah
    di = np.abs(np.diff(i))
    low = small[1:] & small[:-1]
    if not low.any():
        return None
    noise = 1.4826 * float(np.median(di[low])) / np.sqrt(2.0)
    step = max(REST_STEP * capacity_ah, 5 * noise)
    flat = np.concatenate([[False], low & (di <= step)])
    # runs of flat steps, each with the sample before its first step; a slow taper (a
    # constant-voltage end of charge) is no rest: its current drifts by more than a step
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flat.astype(int), [0]])))
    runs = [i[a - 1:b] for a, b in zip(edges[::2], edges[1::2])
            if t[b - 1] - t[a - 1] >= REST_MIN_S and np.ptp(i[a - 1:b]) <= 2 * step]
    if not runs:
        return None
    rested = np.concatenate(runs)
    return float(np.mean(rested)) if np.any(rested) else None


def fit(name: str, model: EcmModel, data: TimeSeries, soc0: float, rows: np.ndarray,
        capacity_scale: float, f_scale: float, max_nfev: int = 40,
        t_ref_c: float = 25.0, soc_range: tuple[float, float] = (0.0, 1.0)) -> _Correction:
    """The correction ``name`` that best fits ``data`` (its ``rows``) with ``model``
    (an entropic term about ``t_ref_c``, its nodes over ``soc_range``)."""
    from scipy.optimize import least_squares

    if name == VoltageLag.name:
        return _fit_lag(model, data, soc0, rows, f_scale, max_nfev)
    sp = specs(name, model.capacity_ah)
    keys = list(sp)
    lo = np.array([sp[k].lo for k in keys])
    hi = np.array([sp[k].hi for k in keys])
    span = hi - lo
    cls = CORRECTION_TYPES[name]

    fixed = {"t_ref_c": t_ref_c, "soc_lo": float(soc_range[0]),
             "soc_hi": float(max(soc_range[1], soc_range[0] + 0.01))} \
        if name == EntropicOcv.name else {}

    def make(z):
        return cls(**dict(zip(keys, lo + span * np.asarray(z, dtype=np.float64))), **fixed)

    def residual(z):
        corr = make(z)
        s = corrected_series(data, corr)
        sim = simulate(corrected_model(model, [corr]), s.time_s, s.current_a, soc0,
                       s.temperature_c)
        r = (sim.voltage_v - data.voltage_v)[rows]
        return np.where(np.isfinite(r), r, 1.0)

    best = None
    for st in starts(name, capacity_scale):
        z0 = np.clip((np.array([st[k] for k in keys]) - lo) / span, 1e-6, 1 - 1e-6)
        sol = least_squares(residual, z0, bounds=(0.0, 1.0), method="trf", loss="soft_l1",
                            f_scale=f_scale, max_nfev=max_nfev, diff_step=1e-4,
                            xtol=1e-8, ftol=1e-8)
        if best is None or sol.cost < best.cost:
            best = sol
    return make(best.x)


def _fit_lag(model: EcmModel, data: TimeSeries, soc0: float, rows: np.ndarray, f_scale: float,
             max_nfev: int) -> VoltageLag:
    """The lag does not change what the model simulates, only what the channel shows of
    it: one simulation, then the two lags fitted on it from the best of a grid (the filter's
    gradient vanishes at a zero time constant)."""
    from scipy.optimize import least_squares

    sim = simulate(model, data.time_s, data.current_a, soc0, data.temperature_c)
    t, v = data.time_s, data.voltage_v

    def residual(z):
        r = (VoltageLag(float(z[0]), float(z[1])).channel(t, sim.voltage_v) - v)[rows]
        return np.where(np.isfinite(r), r, 1.0)

    grid = [(d, tau) for d in (0.0, 0.5, 1.0, 2.0, 4.0) for tau in (0.0, 0.5, 1.0, 2.0, 4.0)]
    cost = [float(np.sum(np.minimum(np.abs(residual(g)), f_scale))) for g in grid]
    z0 = np.clip(np.array(grid[int(np.argmin(cost))]) + 0.05, 0.0, MAX_LAG_S - 0.1)
    sol = least_squares(residual, z0, bounds=(0.0, MAX_LAG_S), method="trf", loss="soft_l1",
                        f_scale=f_scale, max_nfev=max_nfev, diff_step=1e-3, xtol=1e-8,
                        ftol=1e-8)
    return VoltageLag(float(sol.x[0]), float(sol.x[1]))
