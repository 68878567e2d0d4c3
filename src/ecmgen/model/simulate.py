"""Discrete 2RC simulation on measured (non-uniform) time stamps, and validation metrics.

The discrete step is defined here once; the generated C implements exactly this
(see templates/ and c_runtime/). For sample k (k = 0 .. n-1), dt_k = t_k - t_{k-1}
(dt_0 = 0), current i_k held over (t_{k-1}, t_k] (zero-order hold):

1. direction: charge if i_k > deadband, discharge if i_k < -deadband, else unchanged
   (starts as discharge unless i_0 > deadband);
2. soc_k = soc_{k-1} + i_k * dt_k / (3600 * capacity_ah)       (soc_{-1} = soc0);
3. parameters of that direction interpolated at (soc_k, T_k), bilinear and clamped to
   the table ends (T_k = the cell temperature of sample k, degC; ignored by one-row tables);
4. a_j = exp(-dt_k / tau_j);  u_j = a_j * u_j + r_j * (1 - a_j) * i_k   (exact ZOH),
   j = fast, slow and, where the table has it, diff (r_diff, tau_diff per temperature,
   linear in T_k); with a Butler-Volmer fast branch (i0 per temperature, linear in T_k)
   r_fast becomes r_fast * g_k, g_k = asinh(x_k) / x_k, x_k = max(|i_k| / i0, 1e-12);
5. v_k = ocv(soc_k, T_k) + r0 * i_k + u_fast + u_slow [+ u_diff].

With ``surface_soc_gain`` lam > 0 (a model with the diffusion pair) step 3 reads the SOC
tables (r0, r_fast, tau_fast, r_slow, tau_slow; not the OCV, not the per-temperature
r_diff, tau_diff, i0) at the surface SOC instead of soc_k:

3'. soc_s,k = clamp(soc_k + lam * u_diff,k-1 / max(dOCV/dSOC, 0.3 V), 0, 1), with
    u_diff,k-1 the diffusion pair's voltage after the previous sample (u_diff,-1 = 0);
    lam / max(dOCV/dSOC, 0.3 V) is a table over the OCV's breakpoints (the slope over each
    breakpoint's neighbours), bilinear at (soc_k, T_k) as the OCV is
    (EcmModel.surface_per_volt): continuous in SOC.

A discharge depletes the particles' surface (u_diff < 0), so the resistances are read at
a lower SOC than the coulomb count's (bench/cold_surface_soc.py, docs/results.md).

A model with ``effects`` (added by ``ecmgen diagnose``) changes steps 2, 3 and 5 as
defined in :mod:`ecmgen.model.effects`; without effects the step above is untouched.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..data.measure import TimeSeries, charging_direction, voltage_lag
from ..errors import InputError
from .model import RC_FIELDS, EcmModel
from .rc import rc_recurrence


# a current above this (A) is driving the cell; below it, a rest or a soak
DRIVE_CURRENT_A = 0.05


@dataclass(frozen=True)
class SimResult:
    """Simulated trajectory, one value per input sample."""

    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    soc: np.ndarray
    ocv_v: np.ndarray
    u_fast_v: np.ndarray
    u_slow_v: np.ndarray
    charging: np.ndarray          # bool, the direction used at each step
    extra_v: np.ndarray | None = None   # voltage added by effects (diagnose), if any
    u_diff_v: np.ndarray | None = None  # voltage over the diffusion RC pair, if any
    soc_surface: np.ndarray | None = None   # the SOC the RC tables were read at (step 3')


def butler_volmer_factor(current_a, i0_a) -> np.ndarray:
    """g = asinh(x) / x, x = max(|i| / i0, 1e-12): the fast branch's resistance factor
    (1 at small currents, falling like log(x)/x at large ones)."""
    x = np.maximum(np.abs(np.asarray(current_a, dtype=np.float64)) / i0_a, 1e-12)
    return np.arcsinh(x) / x


def step_inputs(model: EcmModel, time_s: np.ndarray, current_a: np.ndarray, soc0: float,
                temperature_c=None):
    """Quantities of steps 1-3 for every sample: dt, soc, direction and parameters."""
    dt = np.diff(time_s, prepend=time_s[0])
    soc = soc0 + np.cumsum(current_a * dt) / (3600.0 * model.capacity_ah)
    charging = charging_direction(current_a, model.direction_deadband_a)
    # each direction's table at its own samples only (the same values as evaluating both
    # everywhere and choosing; a cycle without regeneration never reads the charge table)
    temps = None if temperature_c is None else np.broadcast_to(
        np.asarray(temperature_c, dtype=np.float64), soc.shape)
    params: dict[str, np.ndarray] = {}
    for table, mask in ((model.charge, charging), (model.discharge, ~charging)):
        if not mask.any():
            continue
        p = table.at(soc[mask], None if temps is None else temps[mask])
        for k, v in p.items():
            params.setdefault(k, np.empty(soc.shape))[mask] = v
    if not params:      # no samples
        params = {k: np.empty(0) for k in model.discharge.at(soc, temps)}
    return dt, soc, charging, params


def surface_soc(model: EcmModel, dt: np.ndarray, current_a: np.ndarray, soc: np.ndarray,
                params: dict, temperature_c=None) -> np.ndarray:
    """Step 3': the surface SOC of every sample (the diffusion pair's r_diff, tau_diff in
    ``params``, which depend on the temperature only)."""
    a = np.exp(-dt / params["tau_diff_s"])
    u_diff = rc_recurrence(a, params["r_diff_ohm"] * (1.0 - a) * current_a)
    previous = np.concatenate([[0.0], u_diff[:-1]])[:soc.size]
    temps = temperature_c if model.ocv.n_temperatures > 1 else None
    return np.clip(soc + model.surface_per_volt(soc, temps) * previous, 0.0, 1.0)


def at_surface(model: EcmModel, soc_surface: np.ndarray, charging: np.ndarray,
               current_a: np.ndarray, params: dict, temperature_c=None) -> dict:
    """``params`` with the SOC tables' fields read at ``soc_surface`` (each direction at
    its own samples), the parameter effects applied as at the coulombic SOC."""
    out = dict(params)
    temps = None if temperature_c is None else np.broadcast_to(
        np.asarray(temperature_c, dtype=np.float64), soc_surface.shape)
    for table, mask in ((model.charge, charging), (model.discharge, ~charging)):
        if not mask.any():
            continue
        p = table.at(soc_surface[mask], None if temps is None else temps[mask])
        for k in RC_FIELDS:
            if out[k] is params[k]:
                out[k] = np.array(params[k], dtype=np.float64)
            out[k][mask] = p[k]
    if model.effects:
        from .effects import parameter_effects

        out = parameter_effects(model, current_a, out, temperature_c)
    return out


def sample_temperatures(model: EcmModel, n: int, temperature_c=None, source=None,
                        column: str = "temperature_c"):
    """The cell temperature of each of ``n`` samples for a simulation: ``temperature_c``
    (an array, or one number for the whole record); None is fine for a model without a
    temperature axis, else an InputError naming ``source`` and the missing column."""
    if temperature_c is None:
        if model.needs_temperature:
            raise InputError(source, f"no cell temperature ({column} column): this model has "
                                     "tables over temperature; give --temperature-c T")
        return None
    t = np.asarray(temperature_c, dtype=np.float64)
    t = np.full(n, float(t)) if t.ndim == 0 else t
    if t.shape != (n,):
        raise InputError(source, f"{t.size} temperatures for {n} samples")
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(source, f"cell temperature is not finite at sample {k}")
    return t


def _rc_state(dt, tau_s, r_ohm, current_a) -> np.ndarray:
    """One RC pair's voltage: u_k = a_k u_{k-1} + r_k (1 - a_k) i_k, a_k = exp(-dt_k /
    tau_k), the products formed in place (the same operations, in the same order, as
    r (1 - a) i)."""
    a = np.exp(-dt / tau_s)
    drive = 1.0 - a
    np.multiply(r_ohm, drive, out=drive)
    drive *= current_a
    return rc_recurrence(a, drive)


def simulate(model: EcmModel, time_s, current_a, soc0: float,
             temperature_c=None, equivalent_full_cycles=None) -> SimResult:
    """Simulate the model over a current profile (A, positive = charge) from ``soc0``.
    ``temperature_c``: the cell temperature per sample (degC) or one number; needed when
    the model has tables over temperature. ``equivalent_full_cycles``: the cell's age for
    a model with an ageing law (None: the model's own tables, the fresh cell)."""
    model = model.at_age(equivalent_full_cycles)
    time_s = np.asarray(time_s, dtype=np.float64)
    current_a = np.asarray(current_a, dtype=np.float64)
    temperature_c = sample_temperatures(model, time_s.size, temperature_c)
    dt, soc, charging, p = step_inputs(model, time_s, current_a, soc0, temperature_c)
    if model.effects:
        # SOC and parameter effects (capacity_error, current_dependent_resistance,
        # temperature_dependence) change steps 2-3; see ecmgen.model.effects.
        from .effects import effects_inputs

        soc, p = effects_inputs(model, time_s, current_a, soc0, dt, soc, charging, p,
                                temperature_c)
    soc_s = None
    if model.surface_soc_gain:
        soc_s = surface_soc(model, dt, current_a, soc, p, temperature_c)
        p = at_surface(model, soc_s, charging, current_a, p, temperature_c)
    r_fast = p["r_fast_ohm"]
    if "i0_a" in p:
        r_fast = r_fast * butler_volmer_factor(current_a, p["i0_a"])
    u_fast = _rc_state(dt, p["tau_fast_s"], r_fast, current_a)
    u_slow = _rc_state(dt, p["tau_slow_s"], p["r_slow_ohm"], current_a)
    ocv = model.ocv.ocv_at(soc, temperature_c)
    # ocv + r0 i + u_fast + u_slow, summed in that order in place (a long record holds
    # one array for it, not four)
    v = p["r0_ohm"] * current_a
    v += ocv
    v += u_fast
    v += u_slow
    u_diff = None
    if "r_diff_ohm" in p:
        a_diff = np.exp(-dt / p["tau_diff_s"])
        u_diff = rc_recurrence(a_diff, p["r_diff_ohm"] * (1.0 - a_diff) * current_a)
        v = v + u_diff
    extra = None
    if model.effects:
        from .effects import effects_voltage  # diagnose stage, only when effects present

        extra = effects_voltage(model, time_s, current_a, soc, charging, temperature_c, p)
        v = v + extra
    return SimResult(time_s, current_a, v, soc, ocv, u_fast, u_slow, charging, extra, u_diff,
                     soc_s)


@dataclass(frozen=True)
class StartSoc:
    """The start SOC of a record for a model: the value, its standard uncertainty (0 where
    the record's opening tells it without the model) and how it was found."""

    soc0: float
    sigma: float
    settled: bool          # the record opens rested (or with a CV charge): no model needed
    how: str

    @property
    def uncertain(self) -> bool:
        return self.sigma > START_SOC_TOLERANCE


# the voltage over the first START_WINDOW_S of a record that opens unsettled, against the
# model, tells its start SOC. bench/start_soc.py, the demo model on the shared cycles cut
# under load, in a stop and mid-relaxation: on the 25 and 0 degC cuts the mean |error| is
# 1.01 / 0.98 / 0.85 / 0.56 % SOC for 600 / 1200 / 1800 / 2400 s; on the -10 and -20 degC
# cuts, held out, 4.62 / 2.60 / 2.11 / 1.65 %. A start whose standard uncertainty is above
# START_SOC_TOLERANCE is said to be uncertain.
START_WINDOW_S = 2400.0
START_SOC_TOLERANCE = 0.005
# the samples weighted by their expected error: START_NOISE_V (a rested voltage's scatter,
# as ecmgen.data.soc) and START_MODEL_ERROR of the model's overpotential (the estimator's
# default model error). Weighted, the 25 / 0 degC cuts' mean |error| is 0.49 % against
# 0.56 % unweighted (the -10 / -20 degC ones 1.46 against 1.65 %)
START_NOISE_V = 0.002
START_MODEL_ERROR = 0.19


def initial_soc(model: EcmModel, series: TimeSeries) -> float:
    """SOC at the start of a record (:func:`start_estimate`)."""
    return start_estimate(model, series).soc0


def start_soc(model: EcmModel, series: TimeSeries) -> tuple[float, str]:
    """(start SOC, how it was found) of a record for ``model`` (:func:`start_estimate`)."""
    got = start_estimate(model, series)
    return got.soc0, got.how


def start_estimate(model: EcmModel, series: TimeSeries) -> StartSoc:
    """The start SOC of a record for ``model``. A record that opens settled (a rest whose
    voltage has stopped moving, a charge ending in a constant-voltage phase or above the
    top of the OCV: :func:`ecmgen.data.soc.settled_opening`) is read
    from its voltage (:func:`ecmgen.data.soc.record_start_soc`; a model over temperature
    uses its OCV at the record's first temperature). Any other opening -- under load, in a
    stop of a few seconds, mid-relaxation -- is read from the voltage over its first
    START_WINDOW_S against the model (:func:`window_start_soc`), with its uncertainty."""
    from ..data.soc import record_start_soc

    settled, ocv, rest_a = _opening(model, series)
    if settled:
        soc0, how = record_start_soc(ocv, model.capacity_ah, series, rest_a)
        return StartSoc(float(soc0), 0.0, True, how)
    return window_start_soc(model, series)


def opens_settled(model: EcmModel, series: TimeSeries, temperature_c=None) -> bool:
    """Whether the record opens settled for ``model`` (as :func:`start_estimate` judges
    it; ``temperature_c`` where the record has no temperature column), without reading
    the start SOC: a filter told the start SOC still needs to know whether the first
    voltage is the OCV."""
    if series.temperature_c is None and temperature_c is not None:
        series = replace(series, temperature_c=np.full(series.time_s.size, temperature_c))
    return _opening(model, series)[0]


def _opening(model: EcmModel, series: TimeSeries):
    """(settled, the OCV at the record's first temperature, the rest current)."""
    from ..data.soc import settled_opening

    rest_a = max(model.direction_deadband_a, model.capacity_ah / 100.0)
    temps = sample_temperatures(model, series.time_s.size, series.temperature_c,
                                series.source)
    ocv = model.ocv.at_temperature(None if temps is None or model.ocv.n_temperatures == 1
                                   else float(temps[0]))
    return settled_opening(series, model.capacity_ah, rest_a, float(ocv.ocv_v[-1])), ocv, rest_a


def window_start_soc(model: EcmModel, series: TimeSeries,
                     window_s: float = START_WINDOW_S) -> StartSoc:
    """The start SOC that makes the model's voltage over the record's first ``window_s``
    match the measured one best (each sample weighted by its expected error), each RC
    pair's unknown starting voltage fitted with it (its free decay is linear in it), so
    that an opening under load or mid-relaxation counts as what it is. The uncertainty:
    the weighted residual RMS over the OCV's slope there (a model error that size moves
    the start SOC that much)."""
    t = series.time_s
    n = max(int(np.searchsorted(t, t[0] + window_s, side="right")), 2)
    part = series.slice(0, n)
    temps = sample_temperatures(model, n, part.temperature_c, part.source)

    def misfit(soc0: float) -> float:
        return _window_residual(model, part, temps, soc0)[0]

    grid = np.linspace(0.0, 1.0, 51)
    costs = np.array([misfit(s) for s in grid])
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    for _ in range(30):                       # golden section about the grid's best
        m1, m2 = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        if misfit(m1) <= misfit(m2):
            hi = m2
        else:
            lo = m1
    soc0 = float(np.clip(0.5 * (lo + hi), 0.0, 1.0))
    cost, rms = _window_residual(model, part, temps, soc0)
    if costs[k] < cost:
        soc0 = float(grid[k])
        cost, rms = _window_residual(model, part, temps, soc0)
    t0 = None if temps is None else float(temps[0])
    slope = float(np.interp(soc0, *_ocv_slope(model, t0)))
    # the larger of two: the residual over the OCV's slope (what a model error that size
    # moves), and the profile's half width (how far the start SOC moves, the RC voltages
    # refitted, before the weighted misfit grows by one: a short window or one under load
    # says little however well it is fitted)
    sigma = max(rms / max(slope, 1e-3),
                _profile_half_width(misfit, grid, costs, soc0, cost + 1.0))
    how = (f"the voltage over its first {t[n - 1] - t[0]:.0f} s against the model (it opens "
           f"unsettled: under load, or in a rest too short to read), each RC pair's starting "
           f"voltage fitted with it: {soc0:.3f} +- {sigma:.3f} (residual {rms * 1e3:.1f} mV RMS "
           f"over an OCV slope of {slope:.2f} V per unit SOC)")
    if sigma > START_SOC_TOLERANCE:
        how += "; warning: the start SOC is uncertain: give soc0 where it is known"
    return StartSoc(soc0, float(sigma), False, how)


def _profile_half_width(misfit, grid: np.ndarray, costs: np.ndarray, soc0: float,
                        limit: float, steps: int = 16) -> float:
    """Half the width of the SOC interval about ``soc0`` where ``misfit`` stays below
    ``limit``: on each side the nearest grid point above it (its cost known) brackets the
    edge, found by bisection; a side with none ends at 0 or 1."""
    widths = []
    for side in (-1.0, 1.0):
        beyond = grid[(side * (grid - soc0) > 0) & (costs > limit)]
        if beyond.size == 0:
            widths.append(soc0 if side < 0 else 1.0 - soc0)
            continue
        near, far = soc0, float(beyond[-1] if side < 0 else beyond[0])
        for _ in range(steps):
            mid = 0.5 * (near + far)
            near, far = (mid, far) if misfit(mid) <= limit else (near, mid)
        widths.append(abs(0.5 * (near + far) - soc0))
    return 0.5 * (widths[0] + widths[1])


def _window_residual(model: EcmModel, part: TimeSeries, temps, soc0: float
                     ) -> tuple[float, float]:
    """(sum of squares, RMS) of measured minus simulated voltage over ``part`` from
    ``soc0``, after fitting each RC pair's starting voltage (the pair's free decay)."""
    sim = simulate(model, part.time_s, part.current_a, soc0, temps)
    dt, _, _, p = step_inputs(model, part.time_s, part.current_a, soc0, temps)
    decays = np.column_stack([np.cumprod(np.exp(-dt / p[k]))
                              for k in ("tau_fast_s", "tau_slow_s", "tau_diff_s") if k in p])
    r = part.voltage_v - sim.voltage_v
    # a sample's weight: 1 / its expected error, the noise of a rested voltage and the
    # model's error as a share of its overpotential (under load it errs most)
    w = 1.0 / np.hypot(START_NOISE_V, START_MODEL_ERROR * (sim.voltage_v - sim.ocv_v))
    c = np.linalg.lstsq(decays * w[:, None], r * w, rcond=None)[0]
    rw = (r - decays @ c) * w
    sse = float(rw @ rw)
    return sse, float(np.sqrt(sse / float(w @ w)))


def _ocv_slope(model: EcmModel, temperature_c) -> tuple[np.ndarray, np.ndarray]:
    """(soc, dOCV/dSOC) of the model's OCV at ``temperature_c`` (central differences)."""
    ocv = model.ocv.at_temperature(temperature_c if model.ocv.n_temperatures > 1 else None)
    soc, v = np.asarray(ocv.soc), np.asarray(ocv.ocv_v)
    return soc, np.gradient(v, soc)


SOC_RANGE_TOLERANCE = 0.005   # simulated SOC this far outside [0, 1] is warned about
# a current step moves a cell's voltage the same way (charge positive: up) at once; steps
# of the record's current and voltage correlating below this at once, with none positive
# beyond its opposite at a later lag (a logger that samples the voltage late), say the
# current column counts the other way (measured at lag 0: +0.99 as recorded, -0.99 with
# the sign flipped, on the synthetic cycle of the tests)
FLIPPED_SIGN_CORRELATION = -0.5
# a record's rests read for whether the model's cell could rest there: those the start-SOC
# fit reads (ecmgen.data.soc.record_start_soc), at the start SOC's rest current
FOREIGN_REST_S = 300.0
# with fewer rests than that to judge by, an MAE above this is taken for a record the
# model does not describe (its own cell's drive cycles, without rests: 10-57 mV from 25
# to -20 degC; every shared record of another cell without rests: 173-796 mV)
FOREIGN_MAE_V = 0.15


def flipped_sign_warning(name: str, correlation: float) -> str:
    return (f"{name}: the current's sign looks flipped: the voltage steps the other way "
            f"from the current (correlation of their steps {correlation:.2f}); ecmgen "
            "counts charge positive: set current_sign = \"discharge_positive\" in "
            "[data.columns] (the error and the SOC range follow from it) (warning)")


def soc_range_warning(soc: np.ndarray, source: str = "") -> str | None:
    """A warning when a simulated SOC leaves [0, 1] (where the OCV and the parameters
    are held at their end values)."""
    lo, hi = float(np.min(soc)), float(np.max(soc))
    if lo >= -SOC_RANGE_TOLERANCE and hi <= 1.0 + SOC_RANGE_TOLERANCE:
        return None
    where = f"{source}: " if source else ""
    return (f"{where}simulated SOC runs {lo:.3f}..{hi:.3f}, outside [0, 1]; the OCV and "
            "the parameters are held at their end values there (check the start SOC, soc0, "
            "and cell.capacity_ah) (warning)")


@dataclass(frozen=True)
class Metrics:
    """Voltage error statistics in volts (names end in _v)."""

    mae_v: float
    rmse_v: float
    max_abs_v: float
    n: int

    @staticmethod
    def of(error_v: np.ndarray) -> "Metrics":
        e = np.abs(np.asarray(error_v, dtype=np.float64))
        if e.size == 0:
            return Metrics(float("nan"), float("nan"), float("nan"), 0)
        return Metrics(float(e.mean()), float(np.sqrt(np.mean(e * e))), float(e.max()), int(e.size))

    def as_dict(self) -> dict:
        return {"mae_v": self.mae_v, "rmse_v": self.rmse_v, "max_abs_v": self.max_abs_v}


@dataclass(frozen=True)
class Validation:
    """Model vs a measured record."""

    source: str
    soc0: float
    soc0_from_ocv: bool
    overall: Metrics
    soc_above_10: Metrics        # samples with simulated SOC > 10 %
    sim: SimResult
    measured_v: np.ndarray
    temperature_c: np.ndarray | None = None   # the cell temperature simulated on, degC
    soc0_how: str = ""               # how the start SOC was found ("given" if given)
    warnings: tuple[str, ...] = ()   # e.g. the simulated SOC left [0, 1]
    voltage_lag_samples: int = 0     # the record's voltage lags its current (not corrected)

    @property
    def temperature_range_c(self) -> tuple[float, float] | None:
        """(min, max) cell temperature over the drive, degC: from the first to the last
        sample under current, so that a soak or cool-down before it does not count (the
        whole record when it never draws current; None: no temperature)."""
        if self.temperature_c is None:
            return None
        t = np.asarray(self.temperature_c)
        driven = np.flatnonzero(np.abs(self.sim.current_a) > DRIVE_CURRENT_A)
        if driven.size:
            t = t[driven[0]:driven[-1] + 1]
        return float(np.min(t)), float(np.max(t))

    @property
    def error_v(self) -> np.ndarray:
        return self.sim.voltage_v - self.measured_v


def validate(model: EcmModel, series: TimeSeries, soc0: float | None = None,
             temperature_c: float | None = None,
             equivalent_full_cycles: float | None = None) -> Validation:
    """Simulate ``series``' current and compare with its voltage. The cell temperature is
    the record's own column, else ``temperature_c`` (one value for the whole record); a
    model over temperature needs one of the two. ``equivalent_full_cycles``: the cell's
    age, for a model with an ageing law (None: fresh)."""
    model = model.at_age(equivalent_full_cycles)
    if series.temperature_c is None and temperature_c is not None:
        series = replace(series, temperature_c=np.full(series.time_s.size, float(temperature_c)))
    temps = sample_temperatures(model, series.time_s.size, series.temperature_c,
                                series.source)
    from_ocv = soc0 is None
    how = "given"
    if from_ocv:
        soc0, how = start_soc(model, series)
    sim = simulate(model, series.time_s, series.current_a, float(soc0), temps)
    err = sim.voltage_v - series.voltage_v
    name = Path(series.source).name if series.source else ""
    lag = voltage_lag(series)
    lag_samples = 0 if lag is None else lag.samples
    overall = Metrics.of(err)
    if lag is not None and lag.correlation[0] < FLIPPED_SIGN_CORRELATION and \
            max(lag.correlation) < -FLIPPED_SIGN_CORRELATION:    # and no lagging logger
        # the cause, not its consequences (a SOC out of range, a "lag", a large error)
        warns = [flipped_sign_warning(name, lag.correlation[0])]
    else:
        warns = [soc_range_warning(sim.soc, name)]
        if from_ocv and "warning" in how:
            warns.append(f"{name}: start SOC {soc0:.3f} from {how}")
        if lag_samples:
            warns.append(lag.note(series.source))
        judged, foreign = foreign_rests_warning(model, series, sim, float(soc0), temps, name)
        if judged:
            warns.append(foreign)
        elif overall.mae_v > FOREIGN_MAE_V:
            warns.append(f"{name}: MAE {overall.mae_v * 1e3:.0f} mV is far beyond a model's "
                         f"error on the cell it was fitted on (tens of mV), and the record "
                         f"has no rests to tell: a record of another cell, or in other "
                         f"units? (warning)")
    return Validation(series.source, float(soc0), from_ocv, overall,
                      Metrics.of(err[sim.soc > 0.10]), sim, series.voltage_v, temps, how,
                      tuple(w for w in warns if w), lag_samples)


def foreign_rests_warning(model: EcmModel, series: TimeSeries, sim: SimResult, soc0: float,
                          temperature_c=None, name: str = "") -> tuple[bool, str | None]:
    """(whether the record has rests to judge by, a warning or None).

    The warning comes when most of the record's rests (after the one it opens with; two
    at least) sit where the model's cell cannot rest: the rested voltage, less the
    overpotential the model still has there, is more than OFFSET_WARN_V (the largest
    hysteresis the start-SOC fit accepts) from the model's OCV at the SOC the record's
    own charge count gives, for every capacity in the range the start-SOC fit tries
    (CAPACITY_SCALES); beyond the table's ends only a voltage on the wrong side of the
    end counts. The evidence is the cell's, not the size of the error: a record of the
    model's own cell at -20 degC has a large error and rests where its OCV says."""
    from ..data.soc import CAPACITY_SCALES, OFFSET_WARN_V, find_rests

    rest_a = max(model.direction_deadband_a, model.capacity_ah / 100.0)
    rests = find_rests(series, rest_a, FOREIGN_REST_S)
    if len(rests) < 3:
        return False, None
    temps = temperature_c if model.ocv.n_temperatures > 1 else None
    capacity = model.capacity_ah * np.linspace(CAPACITY_SCALES.min(), CAPACITY_SCALES.max(), 29)
    off = 0
    for k, charge in zip(rests.index[1:], rests.charge_ah[1:]):
        t = None if temps is None else np.full(capacity.size, float(temps[k]))
        now = model.ocv.ocv_at(np.clip(sim.soc[k:k + 1], 0.0, 1.0),
                               None if t is None else t[:1])
        rested = series.voltage_v[k] - (sim.voltage_v[k] - float(now[0]))
        soc = soc0 + charge / capacity
        ocv = model.ocv.ocv_at(np.clip(soc, 0.0, 1.0), t)
        fits = np.where(soc < 0.0, rested <= ocv + OFFSET_WARN_V,
                        np.where(soc > 1.0, rested >= ocv - OFFSET_WARN_V,
                                 np.abs(rested - ocv) <= OFFSET_WARN_V))
        off += not fits.any()
    n = len(rests) - 1
    if 2 * off <= n:
        return True, None
    return True, (f"{name}: {off} of its {n} rests of {FOREIGN_REST_S:.0f} s or more sit over "
            f"{OFFSET_WARN_V * 1e3:.0f} mV from the model's OCV at the SOC its charge count "
            f"gives (any capacity {CAPACITY_SCALES.min():.2f}-{CAPACITY_SCALES.max():.2f}x): "
            "a record of another cell? (warning)")
