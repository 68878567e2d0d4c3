"""The filter's voltage-noise settings from the model's own validation residual.

A validation (the model simulated on a measured cycle from the true start SOC) gives the
model's voltage error e_k = v_sim - v_meas and the overpotential it predicts, eta_k =
v_sim - ocv_sim. The filter's measurement model (:mod:`.ekf`) is
sigma_k^2 = voltage_noise_v^2 + (model_error * eta_k)^2, correlated over
error_correlation_s; this module measures the two model figures:

- ``model_error``: least squares of e^2 - voltage_noise_v^2 on eta^2 over the record,
  i.e. sqrt(mean(e^2 - voltage_noise_v^2) / mean(eta^2)) (>= 0);
- ``error_correlation_s``: the integral time scale of e, 2 * sum of its autocorrelation
  rho (resampled at 1 s, NOT mean-removed, so that a bias over the record counts as the
  long correlation it is) over lags 0 .. ``max_lag_s`` (1000 s, beyond the slowest time
  constant of the models, tau_diff <= 710 s): a correlated error with variance sigma^2
  carries the information of white noise of density sigma^2 * error_correlation_s.

Figures of several cycles pool as the RMS of model_error and the median of the
correlation times (:func:`pooled`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.simulate import Validation


@dataclass(frozen=True)
class ResidualFigures:
    model_error: float
    error_correlation_s: float
    n: int                          # samples behind the figures

    def as_dict(self) -> dict:
        return {"model_error": self.model_error,
                "error_correlation_s": self.error_correlation_s}


def residual_figures(val: Validation, voltage_noise_v: float = 0.005,
                     max_lag_s: float = 1000.0) -> ResidualFigures:
    e = val.sim.voltage_v - val.measured_v
    eta = val.sim.voltage_v - val.sim.ocv_v
    excess = float(np.mean(e * e)) - voltage_noise_v ** 2
    model_error = float(np.sqrt(max(excess, 0.0) / max(float(np.mean(eta * eta)), 1e-12)))
    t = val.sim.time_s
    grid = np.arange(t[0], t[-1], 1.0)
    if grid.size < 3:
        return ResidualFigures(model_error, 1.0, int(e.size))
    eu = np.interp(grid, t, e)
    lags = int(min(max_lag_s, grid.size - 1))
    spec = np.fft.rfft(eu, 2 * grid.size)
    ac = np.fft.irfft(spec * np.conj(spec))[:lags] / grid.size    # biased estimate
    tau = 2.0 * float(ac.sum() / ac[0]) if ac[0] > 0 else 1.0
    return ResidualFigures(model_error, max(tau, 1.0), int(e.size))


def pooled(figures: list[ResidualFigures]) -> ResidualFigures:
    """RMS of the model errors (weighted by samples), median correlation time."""
    n = np.array([f.n for f in figures], dtype=np.float64)
    me = np.array([f.model_error for f in figures])
    return ResidualFigures(float(np.sqrt(np.sum(n * me * me) / np.sum(n))),
                           float(np.median([f.error_correlation_s for f in figures])),
                           int(n.sum()))


def settings_from_cycles(model, cycles, soc0: float | None = None,
                         voltage_noise_v: float = 0.005) -> ResidualFigures | None:
    """Pooled residual figures of ``model`` on measured ``cycles`` (TimeSeries; each
    validated from ``soc0``, or from the OCV of its first rested voltage); None without
    cycles."""
    from ..model.simulate import validate

    figures = [residual_figures(validate(model, s, soc0), voltage_noise_v) for s in cycles]
    return pooled(figures) if figures else None
