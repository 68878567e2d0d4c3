"""Optional effects added to the 2RC model by ``ecmgen diagnose``.

An effect is a small, frozen set of scalar parameters (units in the names) that changes
the discrete 2RC step of :mod:`ecmgen.model.simulate` in one precisely defined way. Effects
live in ``EcmModel.effects`` in the order diagnose added them and are stored in
``model.json`` as flat objects ``{"name": ..., <parameter>: <number>, ...}``.

The augmented discrete step
---------------------------
For sample k with dt_k = t_k - t_{k-1} (dt_0 = 0) and current i_k (A, positive = charge)
held over (t_{k-1}, t_k], the base step of :mod:`ecmgen.model.simulate` becomes:

1. direction d_k exactly as in the base step; s_k = +1 when charging, -1 otherwise.
2. SOC.  With ``capacity_error`` effects, Q_eff = capacity_ah * prod(capacity_scale)
   (else Q_eff = capacity_ah):  soc_k = soc_{k-1} + i_k * dt_k / (3600 * Q_eff).
3. Base parameters of direction d_k interpolated at soc_k (tables clamped), then
   modified ("parameter effects", all factors multiply; order does not matter):

   - ``current_dependent_resistance``:  g_k = scale_at_zero * asinh(x_k) / x_k with
     x_k = max(|i_k| / i0_a, 1e-12);  r0 *= g_k, r_fast *= g_k.
   - ``temperature_dependence`` (only when a temperature T_k in degC is supplied;
     otherwise the factor is 1):  f_k = exp(activation_k * (1/(T_k + 273.15)
     - 1/(t_ref_c + 273.15)));  r0 *= f_k, r_fast *= f_k, r_slow *= f_k.

4. Base RC states with the modified parameters (unchanged formulas):
   a_j = exp(-dt_k / tau_j);  u_j = a_j * u_j + r_j * (1 - a_j) * i_k.
5. v_k = ocv(soc_k) + r0 * i_k + u_fast + u_slow + sum of the "voltage effects":

   - ``hysteresis`` (one-state, Plett type, with an optional instantaneous term):
     a_h = exp(-|i_k| * dt_k / (3600 * decay_ah));
     h_k = a_h * h_{k-1} + (1 - a_h) * s_k        (h_{-1} = initial_state);
     v_k += m_v * (h_k - ocv_table_state) + m0_v * (s_k - ocv_table_state).
   - ``extra_rc`` (a further slow RC pair, same zero-order-hold form as the base pairs):
     a = exp(-dt_k / tau_s);  u_k = a * u_{k-1} + r_ohm * (1 - a) * i_k  (u_{-1} = 0);
     v_k += u_k.

Every effect may appear at most once in a model written by diagnose; if a hand-made
model repeats one, the factors multiply and the voltages add (as defined above).

For C code generation: every parameter is one scalar double. Extra state per instance:
``hysteresis`` one float h (initialised to initial_state), ``extra_rc`` one float u
(initialised to 0); the others are stateless. ``capacity_error`` only changes the
constant 1/(3600 * Q_eff); ``current_dependent_resistance`` needs one asinh per step,
``temperature_dependence`` one exp per step and a temperature input (1/(t_ref_c +
273.15) is a constant). The hysteresis direction s_k is the model's own direction
state (deadband ``direction_deadband_a``), not sign(i_k).
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar

import numpy as np

from ..errors import InputError
from .rc import rc_recurrence

KELVIN = 273.15


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ValueError(msg)


def _finite(**kw) -> None:
    for k, v in kw.items():
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
            raise ValueError(f"{k} must be a finite number, got {v!r}")


class _Effect:
    """Shared (de)serialisation. Subclasses are frozen dataclasses of float fields."""

    name: ClassVar[str] = ""
    kind: ClassVar[str] = ""            # "soc", "parameter" or "voltage"
    description: ClassVar[str] = ""

    def to_json_dict(self) -> dict:
        d: dict[str, Any] = {"name": self.name}
        for f in fields(self):
            d[f.name] = float(getattr(self, f.name))
        return d

    def params(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def summary(self) -> str:
        return f"{self.name}(" + ", ".join(f"{k}={v:.4g}" for k, v in self.params().items()) + ")"


@dataclass(frozen=True)
class Hysteresis(_Effect):
    """One-state hysteresis (Plett), optionally with an instantaneous term.

    Discrete update for sample k (s_k = +1 charging / -1 discharging, the model's
    direction with its deadband)::

        a_h = exp(-|i_k| * dt_k / (3600 * decay_ah))
        h_k = a_h * h_{k-1} + (1 - a_h) * s_k            h_{-1} = initial_state
        v_k += m_v * (h_k - ocv_table_state) + m0_v * (s_k - ocv_table_state)

    m_v            half-width of the slow (throughput-driven) hysteresis band, V (>= 0)
    decay_ah       charge throughput over which h moves 1/e of the way to s_k, Ah (> 0)
    m0_v           instantaneous hysteresis that flips with the current direction, V (>= 0)
    ocv_table_state  the state h at which the model's OCV table was measured: 0 = the
                   mean of the charge and discharge branches, +1 = charge branch,
                   -1 = discharge branch (in [-1, 1])
    initial_state  h before the first sample (in [-1, 1]; +1 after a full charge; diagnose
                   fits it on the fit cycle)
    """

    m_v: float
    decay_ah: float
    m0_v: float = 0.0
    ocv_table_state: float = 0.0
    initial_state: float = 0.0
    name: ClassVar[str] = "hysteresis"
    kind: ClassVar[str] = "voltage"
    description: ClassVar[str] = "OCV hysteresis that follows the sign and history of the current"

    def __post_init__(self):
        _finite(m_v=self.m_v, decay_ah=self.decay_ah, m0_v=self.m0_v,
                ocv_table_state=self.ocv_table_state, initial_state=self.initial_state)
        _check(0 <= self.m_v <= 1.0, f"m_v must be in [0, 1] V, got {self.m_v}")
        _check(0 <= self.m0_v <= 1.0, f"m0_v must be in [0, 1] V, got {self.m0_v}")
        _check(self.decay_ah > 0, f"decay_ah must be positive, got {self.decay_ah}")
        _check(-1 <= self.ocv_table_state <= 1, "ocv_table_state must be in [-1, 1]")
        _check(-1 <= self.initial_state <= 1, "initial_state must be in [-1, 1]")


@dataclass(frozen=True)
class CurrentDependentResistance(_Effect):
    """Resistance falling with |I| (Butler-Volmer-like charge transfer).

    For sample k, with the (direction, SOC) parameters of the base step::

        x_k = max(|i_k| / i0_a, 1e-12)
        g_k = scale_at_zero * asinh(x_k) / x_k
        r0_k *= g_k;  r_fast_k *= g_k

    i.e. the ohmic + charge-transfer voltage r * i becomes r * scale_at_zero * i0_a *
    asinh(i / i0_a): linear at small currents, logarithmic at large ones.

    scale_at_zero  resistance factor at vanishing current (> 0)
    i0_a           current at which the curvature sets in, A (> 0)
    """

    scale_at_zero: float
    i0_a: float
    name: ClassVar[str] = "current_dependent_resistance"
    kind: ClassVar[str] = "parameter"
    description: ClassVar[str] = ("series and charge-transfer resistance falling with |I| "
                                  "(Butler-Volmer)")

    def __post_init__(self):
        _finite(scale_at_zero=self.scale_at_zero, i0_a=self.i0_a)
        _check(0 < self.scale_at_zero <= 100, "scale_at_zero must be in (0, 100]")
        _check(self.i0_a > 0, f"i0_a must be positive, got {self.i0_a}")

    def factor(self, current_a: np.ndarray) -> np.ndarray:
        x = np.maximum(np.abs(np.asarray(current_a, dtype=np.float64)) / self.i0_a, 1e-12)
        return self.scale_at_zero * np.arcsinh(x) / x


@dataclass(frozen=True)
class ExtraRc(_Effect):
    """A further slow RC pair (polarisation over minutes that 10 s pulses cannot see).

    For sample k (zero-order hold, as the base pairs)::

        a = exp(-dt_k / tau_s)
        u_k = a * u_{k-1} + r_ohm * (1 - a) * i_k        u_{-1} = 0
        v_k += u_k

    r_ohm   resistance of the pair, ohm (>= 0), the same for both directions and all SOC
    tau_s   time constant, s (> 0)
    """

    r_ohm: float
    tau_s: float
    name: ClassVar[str] = "extra_rc"
    kind: ClassVar[str] = "voltage"
    description: ClassVar[str] = "a slow RC pair (time constant of minutes)"

    def __post_init__(self):
        _finite(r_ohm=self.r_ohm, tau_s=self.tau_s)
        _check(0 <= self.r_ohm <= 10, f"r_ohm must be in [0, 10] ohm, got {self.r_ohm}")
        _check(self.tau_s > 0, f"tau_s must be positive, got {self.tau_s}")


@dataclass(frozen=True)
class CapacityError(_Effect):
    """The capacity used for coulomb counting is off.

    The SOC of the base step uses Q_eff = capacity_ah * capacity_scale::

        soc_k = soc_{k-1} + i_k * dt_k / (3600 * capacity_ah * capacity_scale)

    capacity_scale  true capacity / model capacity_ah (> 0)
    """

    capacity_scale: float
    name: ClassVar[str] = "capacity_error"
    kind: ClassVar[str] = "soc"
    description: ClassVar[str] = "the capacity used for coulomb counting is off"

    def __post_init__(self):
        _finite(capacity_scale=self.capacity_scale)
        _check(0.2 <= self.capacity_scale <= 5, "capacity_scale must be in [0.2, 5]")


@dataclass(frozen=True)
class TemperatureDependence(_Effect):
    """Resistances scale with cell temperature (Arrhenius).

    For sample k with cell temperature T_k in degC (factor 1 when no temperature is
    supplied to the simulation)::

        f_k = exp(activation_k * (1 / (T_k + 273.15) - 1 / (t_ref_c + 273.15)))
        r0_k *= f_k;  r_fast_k *= f_k;  r_slow_k *= f_k

    activation_k  activation energy over the gas constant, Ea / R, K (>= 0)
    t_ref_c       temperature at which the base tables hold, degC
    """

    activation_k: float
    t_ref_c: float
    name: ClassVar[str] = "temperature_dependence"
    kind: ClassVar[str] = "parameter"
    description: ClassVar[str] = "resistances falling as the cell warms (Arrhenius)"

    def __post_init__(self):
        _finite(activation_k=self.activation_k, t_ref_c=self.t_ref_c)
        _check(0 <= self.activation_k <= 50000, "activation_k must be in [0, 50000] K")
        _check(-60 <= self.t_ref_c <= 150, "t_ref_c must be in [-60, 150] degC")

    def factor(self, temperature_c: np.ndarray) -> np.ndarray:
        t = np.asarray(temperature_c, dtype=np.float64)
        return np.exp(self.activation_k * (1.0 / (t + KELVIN) - 1.0 / (self.t_ref_c + KELVIN)))


EFFECT_TYPES: dict[str, type] = {
    cls.name: cls for cls in (Hysteresis, CurrentDependentResistance, ExtraRc,
                              CapacityError, TemperatureDependence)
}
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECT_TYPES)


def effect_from_json_dict(d: Any, path=None):
    """One effect from its model.json object; InputError (naming ``path``) if unusable."""
    if not isinstance(d, dict):
        raise InputError(path, f"effect entry must be an object, got {type(d).__name__}")
    name = d.get("name")
    cls = EFFECT_TYPES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise InputError(path, f"unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)})")
    known = {f.name: f for f in fields(cls)}
    extra = sorted(set(d) - set(known) - {"name"})
    if extra:
        raise InputError(path, f"effect {name}: unknown parameter(s) {', '.join(extra)}")
    kw = {}
    for key, f in known.items():
        if key not in d:
            if f.default is MISSING:
                raise InputError(path, f"effect {name}: missing parameter {key}")
            continue
        v = d[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(path, f"effect {name}: {key} must be a number, got {v!r}")
        kw[key] = float(v)
    try:
        return cls(**kw)
    except ValueError as exc:
        raise InputError(path, f"effect {name}: {exc}") from None


def make_effect(name: str, **params):
    """Construct an effect by name (ValueError on bad values)."""
    if name not in EFFECT_TYPES:
        raise ValueError(f"unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)})")
    return EFFECT_TYPES[name](**params)


# -- simulation (called by ecmgen.model.simulate) --------------------------------------------

def capacity_factor(effects) -> float:
    """prod(capacity_scale) over the capacity_error effects (1.0 when there are none)."""
    f = 1.0
    for e in effects:
        if isinstance(e, CapacityError):
            f *= e.capacity_scale
    return f


def effects_inputs(model, time_s, current_a, soc0, dt, soc, charging, params,
                   temperature_c=None):
    """Steps 2-3 of the augmented step: the SOC trajectory and the (direction, SOC)
    parameters after the SOC and parameter effects. Returns ``(soc, params)``; the
    inputs are not modified."""
    current_a = np.asarray(current_a, dtype=np.float64)
    scale = capacity_factor(model.effects)
    params = dict(params)
    if scale != 1.0:
        soc = soc0 + np.cumsum(current_a * dt) / (3600.0 * model.capacity_ah * scale)
        temps = temperature_c if model.needs_temperature else None
        pc, pd = model.charge.at(soc, temps), model.discharge.at(soc, temps)
        params = {k: np.where(charging, pc[k], pd[k]) for k in pc}
    return soc, parameter_effects(model, current_a, params, temperature_c)


def parameter_effects(model, current_a, params, temperature_c=None) -> dict:
    """Step 3's parameter effects (current_dependent_resistance, temperature_dependence)
    applied to the table values ``params`` (a new dict; the input is not modified)."""
    current_a = np.asarray(current_a, dtype=np.float64)
    params = dict(params)
    for e in model.effects:
        if isinstance(e, CurrentDependentResistance):
            g = e.factor(current_a)
            params["r0_ohm"] = params["r0_ohm"] * g
            params["r_fast_ohm"] = params["r_fast_ohm"] * g
        elif isinstance(e, TemperatureDependence) and temperature_c is not None:
            f = e.factor(temperature_c)
            for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
                params[k] = params[k] * f
    return params


def effects_voltage(model, time_s, current_a, soc, charging, temperature_c, params):
    """Step 5's voltage effects (hysteresis, extra_rc) summed, one value per sample."""
    time_s = np.asarray(time_s, dtype=np.float64)
    current_a = np.asarray(current_a, dtype=np.float64)
    dt = np.diff(time_s, prepend=time_s[0])
    extra = np.zeros_like(current_a)
    for e in model.effects:
        if isinstance(e, Hysteresis):
            extra += hysteresis_voltage(e, time_s, current_a, charging)
        elif isinstance(e, ExtraRc):
            a = np.exp(-dt / e.tau_s)
            extra += rc_recurrence(a, e.r_ohm * (1.0 - a) * current_a)
    return extra


def hysteresis_voltage(effect: Hysteresis, time_s, current_a, charging) -> np.ndarray:
    """The voltage a hysteresis effect adds over a record (step 5)."""
    s = np.where(np.asarray(charging, dtype=bool), 1.0, -1.0)
    h = hysteresis_state(effect, time_s, current_a, charging)
    return effect.m_v * (h - effect.ocv_table_state) + effect.m0_v * (s - effect.ocv_table_state)


def hysteresis_state(effect: Hysteresis, time_s, current_a, charging) -> np.ndarray:
    """h_k of a hysteresis effect over a record (for plots and reports)."""
    time_s = np.asarray(time_s, dtype=np.float64)
    current_a = np.asarray(current_a, dtype=np.float64)
    dt = np.diff(time_s, prepend=time_s[0])
    s = np.where(np.asarray(charging, dtype=bool), 1.0, -1.0)
    a = np.exp(-np.abs(current_a) * dt / (3600.0 * effect.decay_ah))
    return rc_recurrence(a, (1.0 - a) * s, effect.initial_state)
