"""The extended Kalman filter over the model's step (and the noise model it shares with
the sigma-point filter).

Per sample k (inputs dt_k, the current the filter sees, the cell temperature, the measured
terminal voltage v_k):

1. predict   x = f(x, i_k, T_k, dt_k) and F = df/dx (:meth:`StepModel.predict`);
             P = F P F^T + Q_k, using that every row of F has at most three non-zeros
             (itself, the SOC column, the offset column);
2. measure   v_pred = h(x), H = dh/dx (:meth:`StepModel.measure`);
3. update    (scalar measurement) S = H P H^T + R_k, c = P H^T, K = c / S,
             x += K (v_k - v_pred); when that moves the SOC by more than 0.1 %, the update
             is iterated (relinearised at the updated state, at most 5 times: a large
             first correction on the curved OCV); Joseph form
             P = (I - K H) P (I - K H)^T + R_k K K^T, evaluated as M = P - K c^T,
             d = M H^T, P = M - d K^T + R_k K K^T (products, no use of K being optimal),
             then symmetrised; SOC clamped to [0, 1], h to [-1, 1].

Noise (:class:`NoiseModel`, from the ``[estimator]`` settings):

- SOC: the current sensor's offset and gain error drift the coulomb count. They are
  biases, not white noise, so their variance is spread over ``drift_horizon_s``:
  Q_soc = ((offset + gain |i|) dt / (3600 Q))^2 * drift_horizon_s / dt, plus white current
  noise. With the offset state the offset is a state instead (random walk over the
  same horizon) and leaves Q_soc.
- RC states: the model's polarisation is uncertain by ``polarization_error`` of itself:
  Q_uj = (polarization_error r_j g |i_k|)^2 (1 - a_j^2) (stationary standard deviation that
  fraction of the branch's steady voltage). At rest the states decay as the model says.
- Voltage: the model's voltage error is sigma_k^2 = voltage_noise_v^2 + (model_error *
  |v_pred - ocv|)^2 (it grows with the overpotential the model predicts: large under load,
  in the cold and near empty, small at rest) + (offset r_dc)^2, the current sensor's
  offset through the model's resistances (r_dc = r0 g0 + sum r_j g_j; without the offset
  state: with it the offset is a state). At rest in the cold a 29 mA offset is 5-18 mV
  of voltage the overpotential term does not cover, which the filter would otherwise read
  as SOC (docs/estimator.md). The error is correlated over
  ``error_correlation_s``: one sample of length dt_k carries the information of
  dt_k / error_correlation_s independent samples, so R_k = sigma_k^2 * error_correlation_s
  / dt_k (at least sigma_k^2; a sample with dt = 0 is skipped).
- Start (``start_polarization_c``): 0 (the default) takes a record to start from a rested
  cell: the RC states start at 0 +- ``u0_sigma_v`` and the first sample counts fully
  (R = sigma^2), its voltage being the OCV. Above 0 the record may start anywhere, under
  load or while the cell relaxes: the RC voltages are unknown at the first sample (each
  gets the variance (r_j g_j start_current_a)^2, start_current_a = start_polarization_c
  times the capacity, the branch's resistance at the first sample's SOC guess and
  temperature, as process noise of the first step) and R carries the error's correlation
  from the first sample on, so one sample never sets the SOC; the SOC sigma stays as wide
  as the voltage cannot yet tell the SOC from the polarisation. A hysteresis state starts
  at 0 with the variance of a uniform [-1, 1] (1/3): which way the cell last ran is as
  unknown as its polarisation (a rested start takes the effect's ``initial_state``).
  ``model_error`` and ``error_correlation_s`` are measured on validation cycles by
  :mod:`.residual`.
- The OCV's slope in H: the tangent at the SOC estimate, or with ``ocv_slope_spread`` k > 0
  the secant over soc +- k sqrt(P_soc) (P after the predict; clamped to [0, 1]), in the
  first update and in every relinearisation (:func:`spread_slope`).
- Options for a start anywhere (docs/estimator.md): ``error_memory_s`` T > 0 scales the
  model error with the largest overpotential since, decayed by exp(-dt / T), instead of
  the sample's own; ``polarization_soc_sigma`` s > 0 scales the RC states' Q by
  s^2 / (s^2 + P_soc) (P_soc before the step); ``resistance_slopes`` False takes the RC
  tables as flat in SOC in F and H (:class:`.process.StepModel`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import EstimatorConfig
from ..model.model import EcmModel
from .process import StepModel

SOC_MIN, SOC_MAX = 0.0, 1.0
MAX_ITERATIONS = 5       # iterated measurement update: at most this many relinearisations
ITERATE_SOC = 1e-3       # ... only when the update moves the SOC by more than this
ITERATE_TOL = 1e-5       # ... and until an iteration moves it by less than this


@dataclass(frozen=True)
class NoiseModel:
    """The filter's noise settings in its own units (see the module docstring)."""

    soc0_sigma: float
    u0_sigma_v: float
    offset_sigma_a: float          # current sensor offset (1 sigma), A
    gain_sigma: float              # current sensor gain error (1 sigma), fraction
    current_noise_a: float         # white current noise per sample, A
    drift_horizon_s: float
    polarization_error: float
    voltage_noise_v: float
    model_error: float
    error_correlation_s: float
    start_current_a: float = 0.0   # the RC voltages' start sigma is r_j times this current
    hysteresis_sigma: float = 0.1
    error_memory_s: float = 0.0    # the model error's overpotential decays over this
    polarization_soc_sigma: float = 0.0   # RC noise scaled by s^2 / (s^2 + P_soc); 0: off
    ocv_slope_spread: float = 0.0  # H's OCV slope: the secant over soc +- k sigma; 0: tangent

    @staticmethod
    def from_config(cfg: EstimatorConfig, capacity_ah: float) -> "NoiseModel":
        offset = capacity_ah / 100.0 if cfg.current_offset_a is None else cfg.current_offset_a
        return NoiseModel(cfg.soc0_sigma, cfg.u0_sigma_v, offset,
                          cfg.current_gain_error, cfg.current_noise_a, cfg.drift_horizon_s,
                          cfg.polarization_error, cfg.voltage_noise_v, cfg.model_error,
                          cfg.error_correlation_s, cfg.start_polarization_c * capacity_ah,
                          error_memory_s=cfg.error_memory_s,
                          polarization_soc_sigma=cfg.polarization_soc_sigma,
                          ocv_slope_spread=cfg.ocv_slope_spread)

    @property
    def anywhere(self) -> bool:
        """A record that may start anywhere (under load, mid-relaxation), not rested."""
        return self.start_current_a > 0.0

    def error_overpotential(self, v_pred: float, ocv: float, dt: float, held: float
                            ) -> float:
        """The overpotential the model error scales with: |v_pred - ocv|, or with
        ``error_memory_s`` the largest of it and the one held from before, decayed by
        exp(-dt / error_memory_s) (after a current step the model's error outlasts the
        overpotential it came with)."""
        eta = abs(v_pred - ocv)
        if self.error_memory_s > 0.0:
            held = held * math.exp(-dt / self.error_memory_s)
            if held > eta:
                return held
        return eta

    def measurement_variance(self, eta: float, dt: float, first: bool, r_dc: float = 0.0
                             ) -> float:
        """R_k for the overpotential ``eta`` (:meth:`error_overpotential`) and the model's
        resistance ``r_dc`` to the current offset (0 with the offset state), or 0.0 for a
        sample that carries no information (dt = 0, but for the first sample of a record
        taken to start rested)."""
        eta = self.model_error * eta
        var = self.voltage_noise_v * self.voltage_noise_v + eta * eta
        w = self.offset_sigma_a * r_dc
        var = var + w * w
        if (first and not self.anywhere) or dt >= self.error_correlation_s:
            return var
        if dt <= 0.0:
            return 0.0
        return var * (self.error_correlation_s / dt)


HYSTERESIS_START_VAR = 1.0 / 3.0   # a start anywhere: h uniform over [-1, 1]


def initial_covariance(step: StepModel, noise: NoiseModel) -> np.ndarray:
    n = step.n
    P = np.zeros((n, n))
    P[0][0] = noise.soc0_sigma ** 2
    for s in range(1, n):
        P[s][s] = noise.u0_sigma_v ** 2
    if step.i_h >= 0:
        P[step.i_h][step.i_h] = (HYSTERESIS_START_VAR if noise.anywhere
                                 else noise.hysteresis_sigma ** 2)
    if step.i_b >= 0:
        P[step.i_b][step.i_b] = noise.offset_sigma_a ** 2
    return P


def initial_state(step: StepModel, soc0: float, noise: NoiseModel) -> list[float]:
    """The start: the SOC guess, the RC voltages 0, a hysteresis state at the effect's
    ``initial_state`` (rested start) or at 0 (a start anywhere: direction unknown)."""
    x = [0.0] * step.n
    x[0] = soc0
    if step.i_h >= 0:
        x[step.i_h] = 0.0 if noise.anywhere else step.hyst.initial_state
    return x


def process_noise(step: StepModel, noise: NoiseModel, aux, dt: float, first: bool = False,
                  p_soc: float = 0.0) -> list[float]:
    """Diagonal Q_k of one step (``aux`` from :meth:`StepModel.predict`, ``p_soc`` the SOC
    variance before it); at the first sample also the RC voltages' start variance
    (:func:`start_polarization`)."""
    q = [0.0] * step.n
    if dt <= 0.0:
        return start_polarization(noise, aux, q) if first else q
    i = aux.i
    k = dt * step.soc_per_as
    bias = noise.gain_sigma * abs(i) + (noise.offset_sigma_a if step.i_b < 0 else 0.0)
    q[0] = (bias * k) ** 2 * (noise.drift_horizon_s / dt) + (noise.current_noise_a * k) ** 2
    ps = polarization_scale(noise, p_soc)
    for s, a, rg in aux.rc:
        e = noise.polarization_error * rg * i
        q[s] = e * e * (1.0 - a * a) * ps
    if step.i_h >= 0:
        c = abs(i) * dt / (3600.0 * step.hyst.decay_ah)
        q[step.i_h] = noise.hysteresis_sigma ** 2 * (1.0 - math.exp(-2.0 * c))  # 1 - a_h^2
    if step.i_b >= 0:
        q[step.i_b] = noise.offset_sigma_a ** 2 * dt / noise.drift_horizon_s
    return start_polarization(noise, aux, q) if first else q


def polarization_scale(noise: NoiseModel, p_soc: float) -> float:
    """The RC process noise's factor: 1, or with ``polarization_soc_sigma`` s > 0,
    s^2 / (s^2 + P_soc): while the SOC is far less certain than s, a slow voltage offset is
    taken as SOC error rather than as polarisation."""
    s2 = noise.polarization_soc_sigma ** 2
    return s2 / (s2 + p_soc) if s2 > 0.0 else 1.0


def start_polarization(noise: NoiseModel, aux, q: list[float]) -> list[float]:
    """Adds the RC voltages' start variance to ``q``: a record may start under load or
    while the cell relaxes, so each branch voltage is unknown within what the branch
    carries at ``start_current_a`` (sigma r_j g_j start_current_a, the resistances at the
    first sample's SOC and temperature)."""
    for s, _a, rg in aux.rc:
        e = rg * noise.start_current_a
        q[s] = q[s] + e * e
    return q


class Filter:
    """What every filter on the model's step holds: the step, the noise model, the state
    x (list), its covariance P (n x n), the direction and whether the next sample is the
    first. Subclasses define ``step(dt, i_seen, tw, tw_ocv, tfac, v_meas) -> v_pred``."""

    def __init__(self, model: EcmModel, cfg: EstimatorConfig, soc0: float):
        self.step_model = StepModel(model, cfg.offset_state, cfg.resistance_slopes)
        self.noise = NoiseModel.from_config(cfg, model.capacity_ah)
        self.x = initial_state(self.step_model, soc0, self.noise)
        self.P = initial_covariance(self.step_model, self.noise)
        self.charging = False
        self.first = True
        self.eta_held = 0.0

    def variance(self, v_pred: float, ocv: float, dt: float, x, aux, tw, tw_ocv,
                 tfac: float) -> float:
        """R of this sample at the predicted state ``x`` (and the held overpotential
        updated); clears ``first``."""
        sm = self.step_model
        self.eta_held = self.noise.error_overpotential(v_pred, ocv, dt, self.eta_held)
        r_dc = sm.dc_resistance(x, aux, tw, tw_ocv, tfac) if sm.i_b < 0 else 0.0
        R = self.noise.measurement_variance(self.eta_held, dt, self.first, r_dc)
        self.first = False
        return R


class Ekf(Filter):
    """Extended Kalman filter on ``model``; :meth:`step` takes one sample."""

    def step(self, dt: float, i_seen: float, tw, tw_ocv, tfac: float, v_meas: float
             ) -> float:
        """One sample; returns the voltage predicted before the update."""
        sm, n = self.step_model, self.step_model.n
        x, self.charging, F, aux = sm.predict(self.x, self.charging, dt, i_seen, tw, tfac,
                                              tw_ocv=tw_ocv)
        F = np.array(F)
        P = F @ self.P @ F.T
        P.flat[::n + 1] += process_noise(sm, self.noise, aux, dt, self.first, self.P[0, 0])
        p_soc = float(P[0, 0])
        v_pred, H, ocv = sm.measure(x, aux, tw, tw_ocv, tfac,
                                    ocv_slope=spread_slope(sm, self.noise, x[0], p_soc, tw_ocv))
        R = self.variance(v_pred, ocv, dt, x, aux, tw, tw_ocv, tfac)
        if R > 0.0:
            x0 = np.array(x)
            H = np.array(H)
            xu, K, c = gain_update(x0, P, H, R, v_meas - v_pred)
            # iterated update: relinearise the measurement where the update lands while
            # that moves the SOC (a large first correction on a curved OCV)
            for _ in range(MAX_ITERATIONS):
                xu = clamp_state(sm, xu.tolist())
                if abs(xu[0] - x0[0]) < ITERATE_SOC:
                    xu = np.array(xu)
                    break
                v_i, H_i, _ = sm.measure(xu, aux, tw, tw_ocv, tfac, ocv_slope=spread_slope(
                    sm, self.noise, xu[0], p_soc, tw_ocv))
                H = np.array(H_i)
                xu = np.array(xu)
                x_next, K, c = gain_update(x0, P, H, R, v_meas - v_i - H @ (x0 - xu))
                done = abs(x_next[0] - xu[0]) < ITERATE_TOL
                xu = x_next
                if done:
                    break
            x = xu.tolist()
            P = joseph_covariance(P, H, R, K, c)
        self.x, self.P = clamp_state(sm, x), P
        return v_pred


SPREAD_MIN = 1e-6     # a secant narrower than this (in SOC) is taken as the tangent
P_SOC_MIN = 1e-12    # ... and so is one of an SOC variance at or below this


def spread_slope(step: StepModel, noise: NoiseModel, soc: float, p_soc: float, tw_ocv
                 ) -> float | None:
    """The OCV slope H takes: the secant over soc +- k sigma_soc (clamped to [0, 1]; k =
    ``ocv_slope_spread``), or None for the tangent at soc (k = 0, or a secant too narrow).
    The update then weighs the voltage by how much the OCV moves over the SOC the filter
    still holds possible; far from the truth on a curved OCV the tangent (the slope where
    the estimate is) moves the SOC by the wrong amount per millivolt."""
    k = noise.ocv_slope_spread
    if not (k > 0.0 and p_soc > P_SOC_MIN):
        return None
    d = k * math.sqrt(p_soc)
    lo, hi = max(soc - d, 0.0), min(soc + d, 1.0)
    if not hi - lo > SPREAD_MIN:
        return None
    return (step.ocv(hi, tw_ocv)[0] - step.ocv(lo, tw_ocv)[0]) / (hi - lo)


def gain_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: float, innovation: float):
    """x + K innovation with K = P H^T / (H P H^T + R); returns (x, K, P H^T)."""
    c = P @ H
    K = c / (H @ c + R)
    return x + K * innovation, K, c


def joseph_covariance(P: np.ndarray, H: np.ndarray, R: float, K: np.ndarray,
                      c: np.ndarray | None = None) -> np.ndarray:
    """Joseph form (I - K H) P (I - K H)^T + R K K^T, as products of rank-one updates:
    M = P - K c^T (c = P H^T, given or computed), d = M H^T, P = M - d K^T + R K K^T;
    symmetrised. (The outer products by broadcasting: np.outer's products, without its
    overhead, which in a filter's per-sample loop is most of the time.)"""
    if c is None:
        c = P @ H
    kc = K[:, None]
    M = P - kc * c
    Pn = M - (M @ H)[:, None] * K + R * (kc * K)
    return 0.5 * (Pn + Pn.T)


def clamp_state(step: StepModel, x: list[float]) -> list[float]:
    """SOC into [0, 1] and h into [-1, 1] (in place; returns ``x``)."""
    if x[0] < SOC_MIN:
        x[0] = SOC_MIN
    elif x[0] > SOC_MAX:
        x[0] = SOC_MAX
    if step.i_h >= 0:
        x[step.i_h] = min(1.0, max(-1.0, x[step.i_h]))
    return x
