"""Running a filter over a measured record, and judging it against coulomb counting.

``estimate_record`` is what ``ecmgen estimate`` does: the filter sees the measured current
with the stated sensor errors (i_seen = current_gain * i + current_offset_a) and starts
from ``soc0_guess``; the reference SOC counts the measured current, unchanged, from the
true start ``soc0`` (the same zero-order hold as the model's step); plain coulomb
counting from the guess, with the same sensor errors, is what the filter must beat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import EstimatorConfig
from ..data.measure import TimeSeries
from ..data.sign import check_sign
from ..errors import InputError
from ..model.model import EcmModel
from ..model.simulate import sample_temperatures
from ..parallel import one_blas_thread
from .ekf import Ekf
from .process import StepModel

CONVERGED_SOC = 0.02       # converge_s: from when on |SOC error| stays within 2 %
SETTLE_S = 600.0           # soc_max_abs_after_600s


@dataclass(frozen=True)
class Estimate:
    """A filter's output, one value per sample."""

    time_s: np.ndarray
    soc: np.ndarray
    soc_sigma: np.ndarray
    voltage_pred_v: np.ndarray
    states: np.ndarray             # (n_samples, n_states) after each update
    state_names: tuple[str, ...]


@dataclass(frozen=True)
class SocMetrics:
    """SOC error statistics (fractions of full, not %)."""

    soc_rmse: float
    soc_mae: float
    soc_max_abs: float
    soc_max_abs_after_600s: float
    converge_s: float | None      # None: never stays within CONVERGED_SOC

    @staticmethod
    def of(time_s: np.ndarray, soc: np.ndarray, reference: np.ndarray) -> "SocMetrics":
        e = np.abs(np.asarray(soc) - np.asarray(reference))
        late = e[time_s - time_s[0] >= SETTLE_S]
        out = np.flatnonzero(e > CONVERGED_SOC)
        if out.size == 0:
            converge = 0.0
        elif out[-1] == e.size - 1:
            converge = None
        else:
            converge = float(time_s[out[-1] + 1] - time_s[0])
        return SocMetrics(float(np.sqrt(np.mean(e * e))), float(e.mean()), float(e.max()),
                          float(late.max()) if late.size else float("nan"), converge)

    def as_dict(self) -> dict:
        return {"soc_rmse": self.soc_rmse, "soc_mae": self.soc_mae,
                "soc_max_abs": self.soc_max_abs,
                "soc_max_abs_after_600s": self.soc_max_abs_after_600s,
                "converge_s": self.converge_s}


@dataclass(frozen=True)
class EstimateRun:
    """The filter, the reference and plain coulomb counting over one record."""

    source: str
    estimate: Estimate
    soc_ref: np.ndarray
    soc_cc: np.ndarray
    filter: SocMetrics
    coulomb_counting: SocMetrics


def coulomb_count(model: EcmModel, time_s, current_a, soc0: float) -> np.ndarray:
    """SOC by counting the current, the model's zero-order hold and capacity (with a
    capacity_error effect, its effective capacity)."""
    step = StepModel(model)
    dt = np.diff(np.asarray(time_s, dtype=np.float64), prepend=time_s[0])
    return soc0 + np.cumsum(np.asarray(current_a, dtype=np.float64) * dt) * step.soc_per_as


@one_blas_thread
def run_filter(model: EcmModel, time_s, current_a, voltage_v, soc0: float,
               cfg: EstimatorConfig | None = None, temperature_c=None) -> Estimate:
    """Run the configured filter over a record: ``current_a`` is the current the filter
    sees (sensor errors included), ``temperature_c`` the cell temperature per sample (or
    one number; None for a model without a temperature axis)."""
    cfg = cfg or EstimatorConfig()
    time_s = np.asarray(time_s, dtype=np.float64)
    n = time_s.size
    temps = sample_temperatures(model, n, temperature_c)
    if cfg.filter == "ukf":
        from .ukf import Ukf

        filt = Ukf(model, cfg, soc0)
    else:
        filt = Ekf(model, cfg, soc0)
    sm = filt.step_model
    inp = sm.inputs(time_s, current_a, temps)
    v_meas = np.asarray(voltage_v, dtype=np.float64).tolist()
    states = np.empty((n, sm.n))
    sigma = np.empty(n)
    v_pred = np.empty(n)
    for k in range(n):
        v_pred[k] = filt.step(inp.dt[k], inp.i_seen[k], inp.t_rc[k], inp.t_ocv[k],
                              inp.temperature_factor[k], v_meas[k])
        states[k] = filt.x
        sigma[k] = math.sqrt(max(filt.P[0][0], 0.0))
    return Estimate(time_s, states[:, 0].copy(), sigma, v_pred, states, sm.layout.names)


@one_blas_thread
def estimate_record(model: EcmModel, series: TimeSeries, soc0_guess: float,
                    soc0: float = 1.0, cfg: EstimatorConfig | None = None, *,
                    current_offset_a: float = 0.0, current_gain: float = 1.0,
                    temperature_c: float | None = None) -> EstimateRun:
    """The filter from ``soc0_guess`` on ``series`` with the given sensor errors, the
    reference from ``soc0`` with the measured current, and coulomb counting from the
    guess with the sensor errors."""
    for name, v in (("soc0_guess", soc0_guess), ("soc0", soc0)):
        if not (math.isfinite(v) and 0.0 <= v <= 1.0):
            raise InputError(None, f"{name} must be a SOC in [0, 1], got {v!r}")
    if not (math.isfinite(current_offset_a) and math.isfinite(current_gain)
            and current_gain > 0):
        raise InputError(None, "the current offset must be finite and the gain positive")
    check_sign(series)          # a flipped current drifts the filter off without a word
    if series.temperature_c is None and temperature_c is not None:
        series = replace(series, temperature_c=np.full(series.time_s.size,
                                                       float(temperature_c)))
    temps = sample_temperatures(model, series.time_s.size, series.temperature_c,
                                series.source)
    seen = current_gain * series.current_a + current_offset_a
    est = run_filter(model, series.time_s, seen, series.voltage_v, soc0_guess, cfg, temps)
    ref = coulomb_count(model, series.time_s, series.current_a, soc0)
    cc = coulomb_count(model, series.time_s, seen, soc0_guess)
    return EstimateRun(series.source, est, ref, cc, SocMetrics.of(series.time_s, est.soc, ref),
                       SocMetrics.of(series.time_s, cc, ref))


def estimate_csv_text(run: EstimateRun) -> str:
    """``time_s,soc,soc_sigma,voltage_pred_v,soc_ref``, one row per sample (round-trip
    float text)."""
    e = run.estimate
    rows = ["time_s,soc,soc_sigma,voltage_pred_v,soc_ref"]
    for row in zip(e.time_s.tolist(), e.soc.tolist(), e.soc_sigma.tolist(),
                   e.voltage_pred_v.tolist(), run.soc_ref.tolist()):
        rows.append(",".join(repr(v) for v in row))
    return "\n".join(rows) + "\n"


def calibration(run: EstimateRun) -> dict:
    """How honest the filter's SOC sigma is against the reference: the share of samples
    with |error| <= 1, 2, 3 sigma (0.68, 0.95, 0.997 for an honest Gaussian sigma) and the
    mean normalised squared error (NEES, 1 for an honest sigma; above 1: overconfident)."""
    e = np.abs(run.estimate.soc - run.soc_ref)
    z = e / np.maximum(run.estimate.soc_sigma, 1e-12)
    return {"within_1_sigma": float(np.mean(z <= 1.0)),
            "within_2_sigma": float(np.mean(z <= 2.0)),
            "within_3_sigma": float(np.mean(z <= 3.0)),
            "nees": float(np.mean(z * z))}


def estimate_json(run: EstimateRun, **context) -> dict:
    """The filter's SOC figures at the top level, their sigma's calibration under
    ``calibration``, plain coulomb counting's under ``coulomb_counting``, and the run's
    context (start SOCs, sensor errors, filter)."""
    return dict(run.filter.as_dict(), calibration=calibration(run),
                coulomb_counting=run.coulomb_counting.as_dict(), **context)
