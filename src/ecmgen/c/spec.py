"""The spec of the generated C: every number it holds, for one (model, numeric, dt) choice.

:func:`begin` checks a model and its options and puts every table on one temperature grid;
:func:`prepare_float` (and :func:`ecmgen.c.qspec.prepare_fixed`) compute every constant the
C uses once (float64 maths, then rounded once to float32
or quantised once to an integer, :mod:`ecmgen.c.qformat`) into a :class:`CSpec`. The
renderer (:mod:`ecmgen.c.codegen`, whose ``prepare`` is the entry point) and the Python
references (:mod:`ecmgen.c.cref`) both read that spec, so "what the C does" has one
definition.

Temperature: the C has one temperature grid, the union of the breakpoints of every table
with more than one temperature row (OCV, charge, discharge); each table is resampled onto
it linearly in temperature at its own SOC breakpoints. A bilinear table resampled onto a
finer grid that keeps its breakpoints is the same function (in exact arithmetic), so this
changes nothing but rounding; for the usual model (every table on the fitter's one grid) it
changes nothing at all. A model whose every table has one row has no temperature axis: its
C ignores the temperature input (unless it carries temperature_dependence).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .._version import __version__
from ..config import c_prefix_problem
from ..errors import InputError
from ..model.model_schema import check_model_ranges
from ..model.model import DIRECTIONS, RC_FIELDS, EcmModel, _grid_weights, load_model
from .qformat import Q_TEMP, quantize

NUMERICS = ("float", "fixed")
# effects (ecmgen.model.effects) the generated C implements, per numeric
C_EFFECTS = {"float": ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error",
                       "temperature_dependence"),
             "fixed": ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error",
                       "temperature_dependence")}
CDR_X_MAX = 1e9             # largest |i| / i0_a the float asinh handles (x^2 must stay finite)
MAX_POINTS = 255            # segment hints are uint8_t
DEFAULT_I_MAX_C = 32.0      # default current range: 32 C, rounded up to a power of two
ARR_T_RANGE_C = (-40.0, 85.0)   # temperature_dependence: the C saturates T to this range
KELVIN = 273.15
# What a model's C may have, chosen when it is generated (CSpec.switches): the name, what 1
# means (and the state fields it adds). The generated C of a model holds the tables, the
# state fields and the unit calls of its features, and nothing of the others.
SWITCHES = {
    "VARIABLE_DT": "variable dt: step(state, i, T, dt), c = 1 - exp(-dt/tau) at run time (else "
                   "step(state, i, T), D = 1/(1 - exp(-dt/tau)) precomputed for the build's dt)",
    "TEMP": "temperature rows: tables over (temperature, SOC) on one temperature grid (t_in, w_t, "
            "k_t, pc[], pc_key, and oc[2], oc_key unless OCV_SHARED)",
    "OCV_SHARED": "the OCV is the last parameter of the RC tables' rows (their SOC grid, segment "
                  "and weight; no k_ocv)",
    "RC_UNIFORM": "uniform RC SOC grids: O(1) lookup (no k_dir[])",
    "OCV_UNIFORM": "the OCV's own SOC grid is uniform: O(1) lookup (no k_ocv)",
    "TAU_T": "time constants of the temperature only: one value per temperature row (table tk), "
             "their coefficients kept in the state (kc[2][2 or 3])",
    "TAU_SAME": "with TAU_T, both directions have the same time constants (kc[1][2 or 3])",
    "DIFF": "the diffusion RC pair, r_diff and tau_diff per temperature (u_diff)",
    "BV": "the Butler-Volmer fast branch: r_fast times asinh(x)/x, x = |i| / i0(T)",
    "FX_HYST": "effect hysteresis (h)",
    "FX_XRC": "effect extra_rc (u_x)",
    "FX_CDR": "effect current_dependent_resistance",
    "FX_ARR": "effect temperature_dependence (Arrhenius factor on r0, r_fast, r_slow)",
    "SURFACE": "(with DIFF, never OCV_SHARED) the RC tables read at the surface SOC clamp(soc + "
               "sv u_diff, 0, 1), sv = lam / max(dOCV/dSOC, 0.3 V) a table on the OCV's grid",
    "AGE": "an ageing law: set_age(state, equivalent full cycles) scales every resistance and "
           "the capacity (age_r, k_soc)",
}
# capacity_error needs no switch: the generator folds it into k_soc.
# the features as the generated config names them (switches that are 1)
FEATURE_NAMES = {"VARIABLE_DT": "variable dt", "TEMP": "temperature rows",
                 "OCV_SHARED": "OCV on the RC grid", "RC_UNIFORM": "uniform RC grids",
                 "OCV_UNIFORM": "uniform OCV grid", "TAU_T": "time constants of T only",
                 "TAU_SAME": "the same in both directions", "DIFF": "diffusion pair",
                 "BV": "Butler-Volmer branch", "FX_HYST": "hysteresis", "FX_XRC": "extra_rc",
                 "FX_CDR": "current_dependent_resistance", "FX_ARR": "temperature_dependence",
                 "SURFACE": "surface SOC", "AGE": "ageing law"}



@dataclass(frozen=True)
class CGrid:
    """Breakpoints and 1/spacing, as emitted (float32 values or int64 raw integers). A
    uniform SOC grid (``inv_h`` set) is located in O(1) by the C: u = (v - x0) inv_h (fixed
    point: times inv_h, then shifted right by ``shift``), segment floor(u), weight u - k;
    its ``x`` and ``inv_dx`` are not emitted."""

    x: np.ndarray
    inv_dx: np.ndarray
    x0: object = None        # uniform: first breakpoint (float32, or Q30 raw)
    inv_h: object = None     # uniform: 1 / spacing (float32, or raw = round(2^shift / h))
    shift: int = 0

    @property
    def n(self) -> int:
        return int(self.x.size)

    @property
    def uniform(self) -> bool:
        return self.inv_h is not None


def uniform_inverse(x, tol: float) -> float | None:
    """1/h of breakpoints x[0] + k h, where |x[k] - (x[0] + k h)| <= tol, else None; an
    integer when 1/h is one to 1e-9 relative (the fitter's grids: 1/0.05, 1/0.01), so that
    the uniform lookup is exact in fixed point."""
    x = np.asarray(x, dtype=np.float64)
    if x.size < 2:
        return None
    h = (x[-1] - x[0]) / (x.size - 1)
    if not h > 0:
        return None
    inv = 1.0 / h
    if abs(inv - round(inv)) <= 1e-9 * inv:
        inv = float(round(inv))
    if np.max(np.abs(x - (x[0] + np.arange(x.size) / inv))) > tol:
        return None
    return inv


@dataclass(frozen=True)
class CDir:
    """Tables of one current direction, each (n_t, n_soc) (one row per temperature of
    ``CSpec.temp_grid``, one row without it). k_fast/k_slow: tau (variable dt) or
    D = 1/(1 - exp(-dt/tau)) (fixed dt). The branches, one value per temperature row (None
    when absent): r_diff, k_diff (tau_diff or D_diff), i0 (Butler-Volmer)."""

    grid: CGrid
    r0: np.ndarray
    r_fast: np.ndarray
    k_fast: np.ndarray
    r_slow: np.ndarray
    k_slow: np.ndarray
    r_diff: np.ndarray | None = None
    k_diff: np.ndarray | None = None
    i0: np.ndarray | None = None


@dataclass(frozen=True)
class CSpec:
    """Everything the generated C holds, for one (model, numeric, dt) choice.

    numeric "float": arrays are np.float32, scalars np.float32.
    numeric "fixed": arrays are np.int64 holding int32 raw values; ``q`` the formats."""

    prefix: str
    numeric: str
    variable_dt: bool
    dt_s: float | None
    ocv_grid: CGrid
    ocv: np.ndarray                    # (n_t, n_ocv)
    dirs: tuple[CDir, CDir]            # (discharge, charge), index = state.charging
    deadband: object                   # float32 A or int Q_I
    k_soc: object                      # float32 or int (scaled by the formats in q)
    i_lim_a: float                     # saturation of the current (power of two)
    temp_grid: CGrid | None = None     # temperature breakpoints (degC float32 / Q8); None: one row
    q: dict = field(default_factory=dict)
    model_sha256: str = ""
    tool_version: str = __version__
    capacity_ah: float = 0.0
    notes: tuple[str, ...] = ()
    fx: dict = field(default_factory=dict)   # effects: "hyst"/"xrc"/"cdr"/"arr" flags and
                                             # their constants ({} for a model without)
    bv: dict = field(default_factory=dict)   # fixed point, Butler-Volmer: table and formats
    # surface SOC (model.surface_soc_gain): lam / max(dOCV/dSOC, 0.3 V) at the OCV's
    # breakpoints, (n_t, n_ocv), 1/V; None: off (switch SURFACE)
    surface: np.ndarray | None = None
    # ageing law (model.ageing): {"grid": CGrid of equivalent full cycles (float32, or Q8 raw),
    # "r": resistance scales, "iq": 1 / capacity scales (float32, or raw in Q_AR / Q_AQ)};
    # None: off (switch AGE)
    age: dict | None = None

    @property
    def fixed(self) -> bool:
        return self.numeric == "fixed"

    @property
    def temp(self) -> bool:
        """The tables have a temperature axis (switch TEMP)."""
        return self.temp_grid is not None

    @property
    def ocv_shared(self) -> bool:
        """The OCV is on the SOC grid of both directions' tables (switch OCV_SHARED: it takes
        their segment and weight)."""
        x = self.ocv_grid.x
        return self.surface is None and all(d.grid.x.shape == x.shape and
                                            np.array_equal(d.grid.x, x) for d in self.dirs)

    @property
    def tau_t(self) -> bool:
        """Every time constant (tau, or D at fixed dt) depends on the temperature only: each
        table row is constant along SOC, in both directions (the curve fit's tables).
        Switch TAU_T: one value per temperature row, and the step's coefficients kept in the
        state per temperature. Exact: a bilinear interpolation of such a table is the linear
        one in temperature, bit for bit in both numerics."""
        return all(np.all(k == k[:, :1]) for d in self.dirs for k in (d.k_fast, d.k_slow))

    @property
    def tau_same(self) -> bool:
        """Switch TAU_SAME: with tau_t, both directions have the same time constants (the
        curve fit's): one set of coefficients in the state."""
        d0, d1 = self.dirs
        return self.tau_t and all(
            np.array_equal(a[:, 0] if a.ndim == 2 else a, b[:, 0] if b.ndim == 2 else b)
            for a, b in ((d0.k_fast, d1.k_fast), (d0.k_slow, d1.k_slow))
            + (((d0.k_diff, d1.k_diff),) if self.diff else ()))

    @property
    def rc_uniform(self) -> bool:
        """Switch RC_UNIFORM: both directions' SOC grids are uniform (O(1) lookup)."""
        return all(d.grid.uniform for d in self.dirs)

    @property
    def ocv_uniform(self) -> bool:
        """Switch OCV_UNIFORM: the OCV has its own SOC grid, uniform (O(1) lookup)."""
        return not self.ocv_shared and self.ocv_grid.uniform

    @property
    def diff(self) -> bool:
        return self.dirs[0].r_diff is not None

    @property
    def has_bv(self) -> bool:
        return self.dirs[0].i0 is not None

    @property
    def has_fx(self) -> bool:
        """The model carries a diagnose effect with code (not capacity_error alone)."""
        return any(self.fx.get(k) for k in ("hyst", "xrc", "cdr", "arr"))

    @property
    def uses_temperature(self) -> bool:
        """The step reads its temperature argument."""
        return self.temp or bool(self.fx.get("arr"))

    @property
    def switches(self) -> dict[str, int]:
        """What this model's C has (:data:`SWITCHES`, in its order), each 0 or 1: the
        generator renders the tables, state fields and unit calls of those that are 1."""
        fx = self.fx
        on = {"VARIABLE_DT": int(self.variable_dt), "TEMP": int(self.temp), "OCV_SHARED": int(self.ocv_shared),
                "RC_UNIFORM": int(self.rc_uniform), "OCV_UNIFORM": int(self.ocv_uniform),
                "TAU_T": int(self.tau_t), "TAU_SAME": int(self.tau_same),
                "DIFF": int(self.diff), "BV": int(self.has_bv),
                "FX_HYST": int(bool(fx.get("hyst"))), "FX_XRC": int(bool(fx.get("xrc"))),
                "FX_CDR": int(bool(fx.get("cdr"))), "FX_ARR": int(bool(fx.get("arr"))),
                "SURFACE": int(self.surface is not None), "AGE": int(self.age is not None)}
        return {k: on[k] for k in SWITCHES}

    @property
    def features(self) -> list[str]:
        """The switches that are 1, in words (the generated config lists them)."""
        return [FEATURE_NAMES[k] for k, v in self.switches.items() if v]


def state_fields(spec: CSpec) -> list[tuple[str, str, str]]:
    """(C type, name, comment) of the model's state struct, in order: what the generated
    header declares, the cffi harness reads and the target firmware records."""
    t = "int32_t" if spec.fixed else "float"
    v = " Q_V" if spec.fixed else ""
    out = ([("int64_t", "soc_rem", "SOC below 1 LSB of Q30, carried: exact Coulomb count"),
            ("int32_t", "soc", "state of charge, Q30, saturated to [-2, 2)")] if spec.fixed else
           [("float", "soc", "state of charge (1 = full), saturated to [-2, 2]"),
            ("float", "soc_c", "Kahan compensation of the SOC sum")])
    out += [(t, "u_fast", f"voltage over the fast RC pair,{v} V"),
            (t, "u_slow", f"voltage over the slow RC pair,{v} V")]
    if spec.diff:
        out.append((t, "u_diff", f"voltage over the diffusion RC pair,{v} V"))
    if spec.fx.get("hyst"):
        out.append((t, "h", "hysteresis state in [-1, 1]" + (", Q30" if spec.fixed else "")))
    if spec.fx.get("xrc"):
        out.append((t, "u_x", f"voltage over the extra_rc pair,{v} V"))
    if spec.age is not None:
        out += [(t, "age_r", "resistance scale at the cell's age" + (", Q_AR" if spec.fixed else "")),
                (t, "k_soc", "k_soc over the capacity at the cell's age")]
    if spec.temp:
        out += [("int32_t" if spec.fixed else "uint32_t", "t_in",
                 "temperature of the last step" + ("" if spec.fixed else " (its bits)")),
                (t, "w_t", "its weight between rows k_t and k_t + 1" +
                 (", Q30" if spec.fixed else "")),
                (t, f"pc[{2 * n_rc_params(spec)}]", "the segment's parameter pairs at the "
                 "temperature (a cache)")]
        if not spec.ocv_shared:
            out.append((t, "oc[2]", "the OCV segment's pair at the temperature (a cache)"))
    if spec.tau_t:
        dims = f"[{1 if spec.tau_same else 2}][{3 if spec.diff else 2}]"
        which = ("per direction " if not spec.tau_same else "") + "(fast, slow" + \
                (", diff" if spec.diff else "") + ") at the temperature"
        if not spec.fixed:
            out.append(("float", "kc" + dims, ("1/tau " if spec.variable_dt else "c = 1/D ") + which))
        elif spec.variable_dt:
            out.append(("int32_t", "kc" + dims, "1/tau in Q_KR " + which))
        else:
            out.append(("int32_t", "kc" + dims, "c = 1/D " + which))
    if spec.temp:
        out.append(("uint16_t", "pc_key", "pc's segment * 2 + direction (0xFFFF: none)"))
    out.append(("uint8_t", "charging", "direction of the last step: 1 charge, 0 discharge"))
    if not spec.rc_uniform:
        out.append(("uint8_t", "k_dir[2]", "table segment hints: speed only, never change a result"))
    if spec.temp and not spec.ocv_shared:
        out.append(("uint8_t", "oc_key", "oc's segment (0xFF: none)"))
    if not spec.ocv_shared and not spec.ocv_uniform:
        out.append(("uint8_t", "k_ocv", "segment hint of the OCV's own SOC grid"))
    if spec.temp:
        out.append(("uint8_t", "k_t", "temperature row of the last step"))
    return out


def n_rc_params(spec: CSpec) -> int:
    """Parameters per SOC point of a direction's table: r0, r_fast, r_slow (and tau_fast,
    tau_slow unless tau_t; the OCV when it shares the grid)."""
    return (3 if spec.tau_t else 5) + int(spec.ocv_shared)


def state_bytes(spec: CSpec) -> int:
    """sizeof(<prefix>_state_t) on a 32-bit target (int64 aligned to 8, as AAPCS)."""
    size = {"int64_t": 8, "int32_t": 4, "uint32_t": 4, "float": 4, "uint16_t": 2, "uint8_t": 1}
    n = sum(size[t] * math.prod(int(k) for k in re.findall(r"\[(\d+)\]", name))
            for t, name, _ in state_fields(spec))
    align = 8 if spec.fixed else 4
    return -(-n // align) * align


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------

def _as_model(model) -> EcmModel:
    if isinstance(model, EcmModel):
        return model
    if isinstance(model, (str, Path)):
        return load_model(model)
    raise TypeError(f"expected an EcmModel or a model.json path, got {type(model).__name__}")


def check_options(prefix: str, numeric: str, dt_s, i_max_a) -> None:
    problem = c_prefix_problem(prefix)
    if problem:
        raise InputError(None, f"[c] {problem}")
    if numeric not in NUMERICS:
        raise InputError(None, f"[c] numeric must be \"float\" or \"fixed\", got {numeric!r}")
    if dt_s is not None:
        if not isinstance(dt_s, (int, float)) or not math.isfinite(dt_s) or not 0 < dt_s <= 3600:
            raise InputError(None, f"[c] dt_s must be a number of seconds in (0, 3600], got {dt_s!r}")
    if i_max_a is not None:
        if not isinstance(i_max_a, (int, float)) or not math.isfinite(i_max_a) or not 0 < i_max_a <= 1e5:
            raise InputError(None, f"[c] i_max_a must be a current in (0, 1e5] A, got {i_max_a!r}")


def check_effects(model: EcmModel, numeric: str, i_lim_a: float | None = None) -> None:
    """Refuse, with one clear line, an effect the C of ``numeric`` does not implement."""
    seen = set()
    for e in getattr(model, "effects", ()) or ():
        name = e.name
        if name not in C_EFFECTS.get(numeric, ()):
            other = [n for n in NUMERICS if name in C_EFFECTS[n]]
            hint = f"; use numeric=\"{other[0]}\"" if other else ""
            raise InputError(None, f"[c] effect {name} is not supported in numeric={numeric!r} "
                                   f"yet{hint}")
        if name in seen and name != "capacity_error":
            raise InputError(None, f"[c] effect {name} appears more than once; the C supports "
                                   "each effect once")
        seen.add(name)
        if name == "current_dependent_resistance" and i_lim_a is not None \
                and i_lim_a / e.i0_a > CDR_X_MAX:
            raise InputError(None, f"[c] effect current_dependent_resistance: i0_a = {e.i0_a:g} A "
                                   f"is too small for the current range {i_lim_a:g} A")


def validate_for_c(model: EcmModel, path=None) -> None:
    """Refuse, with one clear line, a model the C cannot represent. (load_model already
    refuses bad schema versions, missing tables and non-finite values in model.json; this
    repeats the checks for models built in memory and adds the C limits.)"""
    def arr(a, name, ndim=2):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != ndim or a.size == 0:
            raise InputError(path, f"{name} must be a non-empty {ndim}-D table")
        if not np.all(np.isfinite(a)):
            raise InputError(path, f"{name} has non-finite values (NaN or inf)")
        return a

    cap = float(model.capacity_ah)
    if not math.isfinite(cap) or cap <= 0:
        raise InputError(path, f"capacity_ah must be a positive number, got {model.capacity_ah!r}")
    db = float(model.direction_deadband_a)
    if not math.isfinite(db) or db < 0:
        raise InputError(path, f"direction_deadband_a must be >= 0, got {model.direction_deadband_a!r}")
    grids = {"ocv": arr(model.ocv.soc, "ocv.soc", 1)}
    ocv = arr(model.ocv.ocv_v, "ocv.ocv_v")
    if ocv.shape[1] != grids["ocv"].size:
        raise InputError(path, "ocv.soc and ocv.ocv_v differ in length")
    if np.any(ocv <= 0) or np.any(ocv > 100):
        raise InputError(path, "ocv.ocv_v must lie in (0, 100] V")
    for d in DIRECTIONS:
        t = model.table(d)
        grids[d] = arr(t.soc, f"rc.{d}.soc", 1)
        for k in RC_FIELDS:
            a = arr(getattr(t, k), f"rc.{d}.{k}")
            if a.shape[1] != grids[d].size:
                raise InputError(path, f"rc.{d}.{k} has {a.shape[1]} values, soc has {grids[d].size}")
            if k.startswith("tau"):
                if np.any(a <= 0) or np.any(a > 1e6):
                    raise InputError(path, f"rc.{d}.{k} must lie in (0, 1e6] s")
                if np.any(a < 1e-3):
                    raise InputError(path, f"rc.{d}.{k} has time constants below 1 ms")
            elif np.any(a < 0) or np.any(a > 100):
                raise InputError(path, f"rc.{d}.{k} must lie in [0, 100] ohm")
        for k, lo, hi, unit in (("r_diff_ohm", 0.0, 100.0, "ohm"), ("tau_diff_s", 1e-3, 1e6, "s"),
                                ("i0_a", 1e-6, 1e5, "A")):
            v = getattr(t, k)
            if v is not None and (np.any(~np.isfinite(v)) or np.any(v < lo) or np.any(v > hi)):
                raise InputError(path, f"rc.{d}.{k} must lie in [{lo:g}, {hi:g}] {unit}")
    for name, x in grids.items():
        where = "ocv.soc" if name == "ocv" else f"rc.{name}.soc"
        if x.size > MAX_POINTS:
            raise InputError(path, f"{where} has {x.size} points; the C supports at most {MAX_POINTS}")
        if x[0] < 0 or x[-1] > 1:
            raise InputError(path, f"{where} must lie within [0, 1]")
        if x.size > 1 and np.min(np.diff(x)) < 1e-6:
            raise InputError(path, f"{where} breakpoints must be strictly increasing, at least 1e-6 apart")
    tg = temperature_grid(model)
    if tg is not None:
        if tg.size > MAX_POINTS:
            raise InputError(path, f"the tables have {tg.size} temperature breakpoints together; "
                                   f"the C supports at most {MAX_POINTS}")
        if np.min(np.diff(quantize(tg, Q_TEMP))) < 1:
            raise InputError(path, "temperature breakpoints closer than 1/256 K (the fixed-point "
                                   "temperature resolution)")
    # the physical ranges load_model applies: validate and codegen accept the same models
    check_model_ranges(model, path)


# --------------------------------------------------------------------------------------
# the tables on one temperature grid (float64)
# --------------------------------------------------------------------------------------

def temperature_grid(model: EcmModel) -> np.ndarray | None:
    """The C's temperature breakpoints: the union of those of every table with more than
    one row (None: no table depends on temperature)."""
    ts = [t.temperature_c for t in (model.ocv, model.charge, model.discharge)
          if t.n_temperatures > 1]
    return np.unique(np.concatenate(ts)) if ts else None


def _on_grid(table_t: np.ndarray, values: np.ndarray, grid: np.ndarray | None) -> np.ndarray:
    """Rows (or per-row values) of a table at the breakpoints ``grid``: its own rows where
    they are breakpoints, linear in temperature between them, clamped (one row: repeated)."""
    values = np.asarray(values, dtype=np.float64)
    if grid is None:
        return values[:1]
    if values.shape[0] == 1:
        return np.repeat(values[:1], grid.size, axis=0)
    out = []
    for t in grid:
        j = np.flatnonzero(table_t == t)
        if j.size:
            out.append(values[j[0]])
        else:
            k, w = _grid_weights(table_t, float(t))
            out.append(values[k] + (values[k + 1] - values[k]) * float(w))
    return np.stack(out)


def _expand(soc: np.ndarray, cols: list[np.ndarray]):
    """A one-point table is constant: give it the grid [0, 1] (same as np.interp)."""
    if soc.size >= 2:
        return soc, cols
    return np.array([0.0, 1.0]), [np.repeat(c, 2, axis=-1) for c in cols]


def source_tables(model: EcmModel) -> SimpleNamespace:
    """float64 tables of the model on the C's temperature grid: ``temps`` (None: one row),
    ``ocv_soc``, ``ocv_v`` (n_t, n), ``dirs`` [(soc, {RC field: (n_t, n)}, {branch: (n_t,)})]
    for (discharge, charge)."""
    temps = temperature_grid(model)
    ocv_soc, (ocv_v,) = _expand(np.asarray(model.ocv.soc, float),
                                [_on_grid(model.ocv.temperature_c, model.ocv.ocv_v, temps)])
    dirs = []
    for d in ("discharge", "charge"):
        t = model.table(d)
        soc, cols = _expand(np.asarray(t.soc, float),
                            [_on_grid(t.temperature_c, getattr(t, k), temps) for k in RC_FIELDS])
        branch = {k: _on_grid(t.temperature_c, getattr(t, k), temps)
                  for k in ("r_diff_ohm", "tau_diff_s", "i0_a") if getattr(t, k) is not None}
        dirs.append((soc, dict(zip(RC_FIELDS, cols)), branch))
    surface = None
    if getattr(model, "surface_soc_gain", 0.0):
        # at the OCV's breakpoints (EcmModel.surface_per_volt), linear in T onto the grid
        surface = _on_grid(model.ocv.temperature_c, model.surface_per_volt_rows(), temps)
    return SimpleNamespace(temps=temps, ocv_soc=ocv_soc, ocv_v=ocv_v, dirs=dirs, surface=surface)


def _coef(dt_s: float, tau: np.ndarray) -> np.ndarray:
    """c = 1 - exp(-dt/tau), computed without cancellation."""
    return -np.expm1(-dt_s / np.asarray(tau, dtype=np.float64))


def _inv_coef(dt_s: float, tau: np.ndarray) -> np.ndarray:
    """D = 1 / (1 - exp(-dt/tau)) >= 1: the fixed-dt tables."""
    return 1.0 / _coef(dt_s, tau)


def arrhenius_range(effect) -> tuple[float, float]:
    """(largest, smallest) temperature_dependence factor over the C's temperature range."""
    lo, hi = ARR_T_RANGE_C
    ref = 1.0 / (effect.t_ref_c + KELVIN)
    f = [math.exp(effect.activation_k * (1.0 / (t + KELVIN) - ref)) for t in (lo, hi)]
    return f[0], f[1]


# --------------------------------------------------------------------------------------
# spec preparation
# --------------------------------------------------------------------------------------

def _f32(values, name: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise InputError(None, f"{name} does not fit float32")
    return a


# fields of the effects in <prefix>_model_f32_t / <prefix>_model_q_t, per effect, in order
FX_FLOAT_KEYS = {"hyst": ("h_init", "h_k", "h_m", "h_m0", "h_ref"), "xrc": ("x_r", "x_k"),
                 "cdr": ("g_scale", "g_inv_i0"), "arr": ("a_k", "a_inv_ref")}
FX_FIXED_KEYS = {"hyst": ("h_init", "h_k", "h_m", "h_m0", "h_ref"), "xrc": ("x_r", "x_k"),
                 "cdr": ("g_k", "g_tab"), "arr": ("a_b", "a_fmax")}


def _fx_float(by_name: dict, dt_s: float | None) -> dict:
    """Constants of the effects in <prefix>_model_f32_t ({} when the model has none with code)."""
    fx = {"hyst": 0, "xrc": 0, "cdr": 0, "arr": 0}
    h = by_name.get("hysteresis")
    if h is not None:
        k = 1.0 / (3600.0 * h.decay_ah) if dt_s is None else dt_s / (3600.0 * h.decay_ah)
        fx.update(hyst=1, h_init=np.float32(h.initial_state), h_k=_f32(k, "hysteresis decay_ah"),
                  h_m=np.float32(h.m_v), h_m0=np.float32(h.m0_v), h_ref=np.float32(h.ocv_table_state))
    x = by_name.get("extra_rc")
    if x is not None:
        k = x.tau_s if dt_s is None else float(_inv_coef(dt_s, np.array([x.tau_s]))[0])
        k32 = _f32(k, "extra_rc tau_s")
        if not k32 > 0:
            raise InputError(None, "[c] effect extra_rc: tau_s underflows float32")
        fx.update(xrc=1, x_r=np.float32(x.r_ohm), x_k=k32)
    g = by_name.get("current_dependent_resistance")
    if g is not None:
        fx.update(cdr=1, g_scale=np.float32(g.scale_at_zero), g_inv_i0=_f32(1.0 / g.i0_a, "1/i0_a"))
    a = by_name.get("temperature_dependence")
    if a is not None:
        fx.update(arr=1, a_k=np.float32(a.activation_k),
                  a_inv_ref=np.float32(1.0 / (a.t_ref_c + KELVIN)))
    return fx if any(fx.values()) else {}


def _float_grid(x, name: str, uniform: bool = False) -> CGrid:
    """``uniform``: an SOC grid, located in O(1) by the C when its breakpoints are uniform
    to float32 resolution (the C's grid is then x0 + k / inv_h)."""
    x32 = _f32(x, name)
    dx = np.diff(x32.astype(np.float64))
    if np.any(dx <= 0):
        raise InputError(None, f"{name} breakpoints collapse in float32")
    inv = uniform_inverse(x, 2.0**-25) if uniform else None
    if inv is None:
        return CGrid(x32, _f32(1.0 / dx, name + " spacing"))
    return CGrid(x32, _f32(1.0 / dx, name + " spacing"), x0=x32[0], inv_h=np.float32(inv))


def _every(n: int, step: int) -> np.ndarray:
    """Indices 0, step, 2 step, ... and the last of n breakpoints."""
    idx = np.arange(0, n, step)
    return idx if idx[-1] == n - 1 else np.append(idx, n - 1)


def coarsen_tables(model, ocv_soc_step: int = 1, rc_soc_step: int = 1):
    """The model with its OCV and RC tables on every n-th SOC breakpoint (ends kept): the
    flash options ``[c] ocv_soc_step`` / ``rc_soc_step``. The C and its references are made
    from what this returns; model.json keeps every breakpoint. Steps of 1: ``model``."""
    from dataclasses import replace

    model = _as_model(model)
    if ocv_soc_step > 1:
        idx = _every(np.size(model.ocv.soc), ocv_soc_step)
        model = replace(model, ocv=replace(model.ocv, soc=np.asarray(model.ocv.soc)[idx],
                                           ocv_v=np.asarray(model.ocv.ocv_v)[..., idx]))
    if rc_soc_step > 1:
        def one(t):
            idx = _every(np.size(t.soc), rc_soc_step)
            cols = {f: np.asarray(getattr(t, f))[..., idx] for f in (*RC_FIELDS, "fit_error",
                                                                     "converged")
                    if getattr(t, f, None) is not None}
            return replace(t, soc=np.asarray(t.soc)[idx], **cols)
        model = replace(model, charge=one(model.charge), discharge=one(model.discharge))
    return model


def begin(model, numeric: str, dt_s: float | None, prefix: str, i_max_a: float | None
          ) -> SimpleNamespace:
    """Checks and what both numerics start from: the tables on one temperature grid
    (``src``), the effects by name, the current range, the CSpec fields they share."""
    model = _as_model(model)
    check_options(prefix, numeric, dt_s, i_max_a)
    validate_for_c(model)
    dt_s = None if dt_s is None else float(dt_s)
    cap = float(model.capacity_ah)
    if i_max_a is None:
        i_max_a = DEFAULT_I_MAX_C * cap
    q_i = int(min(30, max(0, 31 - math.ceil(math.log2(i_max_a)))))
    i_lim = math.ldexp(1.0, 31 - q_i)
    notes = []
    check_effects(model, numeric, i_lim)
    effects = tuple(getattr(model, "effects", ()) or ())
    by_name = {e.name: e for e in effects}
    cap_scale = 1.0
    for e in effects:
        if e.name == "capacity_error":
            cap_scale *= float(e.capacity_scale)
    q_eff = cap * cap_scale if cap_scale != 1.0 else cap
    if cap_scale != 1.0:
        notes.append(f"effect capacity_error: the SOC counts against capacity_ah * {cap_scale:.6g} "
                     f"= {q_eff:.6g} Ah")
    if "temperature_dependence" in by_name:
        lo, hi = ARR_T_RANGE_C
        notes.append(f"effect temperature_dependence: the C saturates the temperature to "
                     f"[{lo:g}, {hi:g}] degC for its factor")
    if model.ageing is not None:
        x = model.ageing.equivalent_full_cycles
        notes.append(f"ageing law over {x[0]:g}..{x[-1]:g} equivalent full cycles: set the "
                     "cell's age with set_age() (init: fresh); the estimator, if generated, "
                     "runs the fresh cell")
    common = dict(prefix=prefix, numeric=numeric, variable_dt=dt_s is None, dt_s=dt_s,
                  i_lim_a=i_lim, model_sha256=model.sha256(), capacity_ah=cap)
    return SimpleNamespace(
        model=model, src=source_tables(model), by_name=by_name, common=common, notes=notes,
        dt_s=dt_s, variable_dt=dt_s is None, q_i=q_i, i_lim=i_lim,
        k_soc64=1.0 / (3600.0 * q_eff) if dt_s is None else dt_s / (3600.0 * q_eff))


def aged_efc(breakpoints) -> float:
    """The age the checks and golden vectors run an aged cell at: 70 % along the law's
    breakpoints (equivalent full cycles), in whole cycles (between breakpoints as a rule, so
    the interpolation is exercised)."""
    x = np.asarray(breakpoints, dtype=np.float64)
    return float(round(x[0] + 0.7 * (x[-1] - x[0])))


def age_float(law) -> dict | None:
    """The ageing law as the float C holds it (CSpec.age); None without one."""
    if law is None:
        return None
    return {"grid": _float_grid(law.equivalent_full_cycles, "ageing.equivalent_full_cycles"),
            "r": _f32(law.resistance_scale, "ageing.resistance_scale"),
            "iq": _f32(1.0 / law.capacity_scale, "ageing.capacity_scale")}


def prepare_float(ctx: SimpleNamespace) -> CSpec:
    """The float32 spec (ctx from :func:`begin`)."""
    src, dt_s, variable_dt = ctx.src, ctx.dt_s, ctx.variable_dt

    def k_table(tau, name):
        k = tau if variable_dt else _inv_coef(dt_s, tau)
        k32 = _f32(k, name)
        if variable_dt and np.any(k32 <= 0):
            raise InputError(None, f"{name} time constants underflow float32")
        return k32

    dirs = []
    for (soc, cols, br), name in zip(src.dirs, ("discharge", "charge")):
        extra = {}
        if "r_diff_ohm" in br:
            extra["r_diff"] = _f32(br["r_diff_ohm"], name)
            extra["k_diff"] = k_table(br["tau_diff_s"], f"rc.{name}.tau_diff_s")
        if "i0_a" in br:
            extra["i0"] = _f32(br["i0_a"], name)
        dirs.append(CDir(_float_grid(soc, f"rc.{name}.soc", True), _f32(cols["r0_ohm"], name),
                         _f32(cols["r_fast_ohm"], name), k_table(cols["tau_fast_s"], f"rc.{name}"),
                         _f32(cols["r_slow_ohm"], name), k_table(cols["tau_slow_s"], f"rc.{name}"),
                         **extra))
    tg = None if src.temps is None else _float_grid(src.temps, "temperature_c")
    return CSpec(ocv_grid=_float_grid(src.ocv_soc, "ocv.soc", True), ocv=_f32(src.ocv_v, "ocv_v"),
                 dirs=tuple(dirs), deadband=np.float32(ctx.model.direction_deadband_a),
                 k_soc=np.float32(ctx.k_soc64), temp_grid=tg, q={}, notes=tuple(ctx.notes),
                 fx=_fx_float(ctx.by_name, dt_s),
                 surface=None if src.surface is None else _f32(src.surface, "surface_soc_gain"),
                 age=age_float(ctx.model.ageing), **ctx.common)
