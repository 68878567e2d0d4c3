"""The fitted model and its one versioned file, ``model.json``.

Everything downstream (simulation, validation, C code, diagnosis) reads an
:class:`EcmModel`; nothing reads the JSON by hand. The file is written with
round-trip float text (``repr``), keys in a fixed order and no timestamps, so the
same fit gives a byte-identical file and therefore byte-identical generated C.

Model (current positive on charge, T the cell temperature in degC)::

    v = ocv_v(soc, T) + i * r0_ohm + u_fast + u_slow
    du_j/dt = -u_j / tau_j + i * r_j / tau_j        (j = fast, slow)

with every parameter a table over (temperature, SOC), one table per current direction
(:class:`RcTable`), and the OCV a table over (temperature, SOC) of its own
(:class:`OcvOverTemperature`). Both interpolate bilinearly and clamp at their ends
(:func:`interp_2d`); a table with one temperature row ignores the temperature, which is
what a model from one pulse test has. The one-temperature OCV table (:class:`OcvTable`)
is made by the OCV stage, :mod:`ecmgen.data.ocv`, and re-exported here.

model.json schema version 2 holds every table as rows (one per temperature breakpoint,
``temperature_c``, null when a one-row table's temperature is unknown); version 1 files
(SOC only) load as one-row tables. The optional ``surface_soc_gain`` (dimensionless; absent
= 0 = off, and omitted when 0 so that older models stay byte-identical) reads the RC tables
at a surface SOC (:func:`surface_soc_per_volt`, :mod:`ecmgen.model.simulate`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..data.ocv import OcvTable, _f64, check_ocv
from ..errors import InputError, reading
from ..files import write_atomic
from .ageing import AgeingLaw, ageing_from_json
from .model_schema import check_model_json, check_model_ranges

SCHEMA = "ecmgen.model"
SCHEMA_VERSION = 2          # 2: tables over (temperature, SOC); version 1 files still load
READS_VERSIONS = (1, 2)
DIRECTIONS = ("charge", "discharge")
RC_FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")
# optional per-temperature values of a direction (one per temperature row; None: absent)
BRANCH_FIELDS = ("r_diff_ohm", "tau_diff_s", "i0_a")
# surface SOC: the OCV slope is held at >= this (V per unit SOC) on the table's flat ends
SURFACE_MIN_SLOPE_V = 0.3
SURFACE_SOC_GAIN_MAX = 10.0     # a sanity bound on [model] surface_soc_gain (0.5 measured)


def _grid_weights(grid: np.ndarray, x) -> tuple[np.ndarray, np.ndarray]:
    """Segment index k (0 <= k <= n-2) and weight w in [0, 1] of grid[k+1] for linear
    interpolation at x, clamped to the grid ends (n >= 2)."""
    x = np.asarray(x, dtype=np.float64)
    k = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, grid.size - 2)
    w = np.clip((x - grid[k]) / (grid[k + 1] - grid[k]), 0.0, 1.0)
    return k, w


def interp_2d(temperature_grid: np.ndarray, soc_grid: np.ndarray, values: np.ndarray,
              soc, temperature_c=None) -> np.ndarray:
    """Bilinear interpolation of ``values`` (n_temperature, n_soc) at (temperature_c, soc),
    clamped to the table ends in both axes: linear in SOC on each temperature row, then
    linear in temperature (degC) between the two rows around ``temperature_c``. A table
    with one temperature row ignores the temperature."""
    soc = np.asarray(soc, dtype=np.float64)
    if values.shape[0] == 1 or temperature_c is None:
        if values.shape[0] > 1:
            raise ValueError("a table over temperature needs the temperature")
        return np.interp(soc, soc_grid, values[0])
    k, w = _grid_weights(temperature_grid, temperature_c)
    k, w = np.broadcast_to(k, soc.shape), np.broadcast_to(w, soc.shape)
    lo, hi = _rows_at(values, k, lambda row: np.interp(soc, soc_grid, row))
    return lo + (hi - lo) * w


def _rows_at(values: np.ndarray, k: np.ndarray, along_soc) -> tuple[np.ndarray, np.ndarray]:
    """``along_soc(row)`` of rows k and k + 1 at every sample, evaluating only the rows
    that some sample uses (a cycle touches a few rows of a fine temperature grid)."""
    lo = np.empty(k.shape)
    hi = np.empty(k.shape)
    if k.size == 0:
        return lo, hi
    first, last = int(k.min()), int(k.max())
    for r in range(first, last + 2):
        at_lo, at_hi = k == r, k == r - 1
        if not (at_lo.any() or at_hi.any()):
            continue
        v = np.broadcast_to(along_soc(values[r]), k.shape)
        lo[at_lo] = v[at_lo]
        hi[at_hi] = v[at_hi]
    return lo, hi


def interp_2d_soc_slope(temperature_grid: np.ndarray, soc_grid: np.ndarray,
                        values: np.ndarray, soc, temperature_c=None) -> np.ndarray:
    """d/dsoc of :func:`interp_2d` at (temperature_c, soc): 0 where the SOC is clamped."""
    soc = np.asarray(soc, dtype=np.float64)

    def row_slope(row):
        j = np.clip(np.searchsorted(soc_grid, soc, side="right") - 1, 0, soc_grid.size - 2)
        slope = (row[j + 1] - row[j]) / (soc_grid[j + 1] - soc_grid[j])
        return np.where((soc < soc_grid[0]) | (soc > soc_grid[-1]), 0.0, slope)

    if soc_grid.size < 2:
        return np.zeros_like(soc)
    if values.shape[0] == 1 or temperature_c is None:
        return row_slope(values[0])
    k, w = _grid_weights(temperature_grid, temperature_c)
    k, w = np.broadcast_to(k, soc.shape), np.broadcast_to(w, soc.shape)
    lo, hi = _rows_at(values, k, row_slope)
    return lo + (hi - lo) * w


def _temperature_axis(temperature_c, n: int, where: str) -> np.ndarray:
    """The temperature breakpoints of a table: strictly increasing degC; a one-row table
    may leave its temperature unknown (NaN, null in model.json)."""
    if temperature_c is None:
        t = np.full(n, np.nan)
    else:
        t = np.atleast_1d(np.asarray(temperature_c, dtype=np.float64))
    if t.shape != (n,):
        raise ValueError(f"{where}: {t.size} temperatures for {n} table rows")
    if n > 1 and (not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0)):
        raise ValueError(f"{where}: temperature_c must be finite and strictly increasing")
    if np.any(np.isfinite(t) & ((t < -100) | (t > 200))):
        raise ValueError(f"{where}: temperature_c outside -100..200 degC")
    return t


@dataclass(frozen=True)
class OcvOverTemperature:
    """OCV over (temperature, SOC): one row per temperature breakpoint on a common SOC grid.

    temperature_c  (n_t,) breakpoints, strictly increasing, degC (one row: may be NaN,
                   the temperature unknown, and then it is ignored)
    soc            (n_soc,) breakpoints, strictly increasing in [0, 1]
    ocv_v          (n_t, n_soc) volts, each row non-decreasing in SOC

    Bilinear and clamped, as the RC tables (:func:`interp_2d`). A 1-D ``ocv_v`` is one row.
    """

    temperature_c: np.ndarray
    soc: np.ndarray
    ocv_v: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.ocv_v, dtype=np.float64)
        v = v[None, :] if v.ndim == 1 else v
        soc = np.asarray(self.soc, dtype=np.float64)
        for row in v:
            check_ocv(soc, row, None)
        object.__setattr__(self, "ocv_v", v)
        object.__setattr__(self, "soc", soc)
        object.__setattr__(self, "temperature_c",
                           _temperature_axis(self.temperature_c, v.shape[0], "ocv"))

    @classmethod
    def from_table(cls, table: OcvTable, temperature_c: float | None = None
                   ) -> "OcvOverTemperature":
        return cls(np.array([np.nan if temperature_c is None else temperature_c]),
                   np.asarray(table.soc), np.asarray(table.ocv_v)[None, :])

    @property
    def n_temperatures(self) -> int:
        return self.ocv_v.shape[0]

    def ocv_at(self, soc, temperature_c=None) -> np.ndarray:
        """OCV in volts at (soc, temperature_c), clamped to the table ends."""
        return interp_2d(self.temperature_c, self.soc, self.ocv_v, soc, temperature_c)

    def soc_slope(self, soc, temperature_c=None) -> np.ndarray:
        """dOCV/dSOC in V per unit SOC at (soc, temperature_c) (0 where clamped)."""
        return interp_2d_soc_slope(self.temperature_c, self.soc, self.ocv_v, soc,
                                   temperature_c)

    def at_temperature(self, temperature_c=None) -> OcvTable:
        """The one-temperature OCV table at ``temperature_c`` (rows interpolated)."""
        if self.n_temperatures == 1:
            return OcvTable(self.soc, self.ocv_v[0])
        k, w = _grid_weights(self.temperature_c, float(temperature_c))
        lo, hi = self.ocv_v[int(k)], self.ocv_v[int(k) + 1]
        return OcvTable(self.soc, lo + (hi - lo) * float(w))

    def soc_at(self, ocv_v, temperature_c=None) -> np.ndarray:
        """Inverse lookup (OCV -> SOC) at one temperature, clamped to the table ends."""
        return self.at_temperature(temperature_c).soc_at(ocv_v)


@dataclass(frozen=True)
class RcTable:
    """2RC parameters over (temperature, SOC) for one current direction.

    temperature_c  (n_t,) breakpoints, strictly increasing, degC (one row: may be NaN,
                   temperature unknown and ignored)
    soc            (n_soc,) breakpoints, strictly increasing in [0, 1]
    r0_ohm         series (ohmic) resistance, (n_t, n_soc)
    r_fast_ohm, tau_fast_s   fast RC pair (charge transfer / double layer), (n_t, n_soc)
    r_slow_ohm, tau_slow_s   slow RC pair (diffusion), tau_fast_s < tau_slow_s, (n_t, n_soc)
    fit_error   the fit's own residual per table cell (units depend on the method)
    converged   False where the fitter did not meet its stopping rule

    Optional, one value per temperature row (None: the branch is absent):
    r_diff_ohm, tau_diff_s   a third, slow "diffusion" RC pair (minutes), same for all SOC
    i0_a        Butler-Volmer current of the fast branch: the fast pair is driven by
                r_fast * g(i) * i with g = asinh(x) / x, x = max(|i| / i0_a, 1e-12), so its
                resistance falls at large currents (strongly so in the cold)

    Parameters between breakpoints are bilinear (:func:`interp_2d`), clamped at the table
    ends; the per-temperature values are linear in temperature, clamped. 1-D columns (with
    ``temperature_c`` a scalar or None) make a one-row table.
    """

    soc: np.ndarray
    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    tau_fast_s: np.ndarray
    r_slow_ohm: np.ndarray
    tau_slow_s: np.ndarray
    fit_error: np.ndarray
    converged: np.ndarray
    temperature_c: np.ndarray | float | None = None
    r_diff_ohm: np.ndarray | None = None
    tau_diff_s: np.ndarray | None = None
    i0_a: np.ndarray | None = None

    def __post_init__(self):
        soc = np.asarray(self.soc, dtype=np.float64)
        object.__setattr__(self, "soc", soc)
        n_t = None
        for k in (*RC_FIELDS, "fit_error", "converged"):
            a = np.asarray(getattr(self, k), dtype=bool if k == "converged" else np.float64)
            a = a[None, :] if a.ndim == 1 else a
            if a.ndim != 2 or a.shape[1] != soc.size:
                raise ValueError(f"RcTable.{k}: shape {a.shape} does not match {soc.size} "
                                 "SOC breakpoints")
            if n_t is not None and a.shape[0] != n_t:
                raise ValueError(f"RcTable.{k}: {a.shape[0]} temperature rows, not {n_t}")
            n_t = a.shape[0]
            object.__setattr__(self, k, a)
        object.__setattr__(self, "temperature_c",
                           _temperature_axis(self.temperature_c, n_t, "rc"))
        if (self.r_diff_ohm is None) != (self.tau_diff_s is None):
            raise ValueError("RcTable: give both r_diff_ohm and tau_diff_s, or neither")
        for k in BRANCH_FIELDS:
            v = getattr(self, k)
            if v is None:
                continue
            a = np.atleast_1d(np.asarray(v, dtype=np.float64))
            if a.shape != (n_t,):
                raise ValueError(f"RcTable.{k}: {a.size} values for {n_t} temperature rows")
            if not np.all(np.isfinite(a)) or np.any(a < 0) or \
                    (k != "r_diff_ohm" and np.any(a <= 0)):
                raise ValueError(f"RcTable.{k} must be finite and positive")
            object.__setattr__(self, k, a)

    @property
    def n_temperatures(self) -> int:
        return self.r0_ohm.shape[0]

    @property
    def has_diffusion(self) -> bool:
        return self.r_diff_ohm is not None

    @property
    def has_butler_volmer(self) -> bool:
        return self.i0_a is not None

    def at(self, soc, temperature_c=None) -> dict[str, np.ndarray]:
        """Interpolated parameters at (soc, temperature_c), clamped to the table ends: the
        RC_FIELDS, and the BRANCH_FIELDS that the table has (same shape as ``soc``)."""
        out = {k: interp_2d(self.temperature_c, self.soc, getattr(self, k), soc,
                            temperature_c) for k in RC_FIELDS}
        shape = np.shape(out["r0_ohm"])
        for k in BRANCH_FIELDS:
            v = getattr(self, k)
            if v is not None:
                out[k] = np.broadcast_to(self.along_temperature(v, temperature_c), shape)
        return out

    def along_temperature(self, values: np.ndarray, temperature_c=None) -> np.ndarray:
        """A per-temperature value (one per row) at ``temperature_c``: linear, clamped."""
        if values.size == 1 or temperature_c is None:
            if values.size > 1:
                raise ValueError("a table over temperature needs the temperature")
            return np.asarray(values[0], dtype=np.float64)
        k, w = _grid_weights(self.temperature_c, temperature_c)
        return values[k] + (values[k + 1] - values[k]) * w

    def soc_slope(self, key: str, soc, temperature_c=None) -> np.ndarray:
        """d/dsoc of parameter ``key`` at (soc, temperature_c) (0 where clamped)."""
        return interp_2d_soc_slope(self.temperature_c, self.soc, getattr(self, key), soc,
                                   temperature_c)

    def row(self, k: int) -> "RcTable":
        """The one-temperature table of temperature row ``k``."""
        extra = {f: None if getattr(self, f) is None else getattr(self, f)[k:k + 1]
                 for f in BRANCH_FIELDS}
        return RcTable(soc=self.soc, temperature_c=self.temperature_c[k:k + 1], **extra,
                       **{f: getattr(self, f)[k:k + 1] for f in (*RC_FIELDS, "fit_error",
                                                                 "converged")})


def stack_rc_tables(tables: list[RcTable], temperatures_c, soc=None) -> RcTable:
    """One table over temperature from one-temperature tables (one per breakpoint,
    increasing temperature). The rows are resampled linearly onto ``soc`` (default: the
    union of the tables' SOC breakpoints), so each row keeps its own values at its own
    breakpoints; ``converged`` is resampled as "both neighbours converged"."""
    if soc is None:
        soc = np.unique(np.concatenate([t.soc for t in tables]))
    soc = np.asarray(soc, dtype=np.float64)
    cols: dict[str, list] = {k: [] for k in (*RC_FIELDS, "fit_error", "converged")}
    extra: dict[str, np.ndarray | None] = {}
    for k in BRANCH_FIELDS:
        have = [getattr(t, k) is not None for t in tables]
        if any(have) and not all(have):
            raise ValueError(f"stack_rc_tables: {k} is in some tables and not in others")
        extra[k] = np.concatenate([getattr(t, k) for t in tables]) if all(have) else None
    for t in tables:
        if t.n_temperatures != 1:
            raise ValueError("stack_rc_tables takes one-temperature tables")
        for k in (*RC_FIELDS, "fit_error"):
            cols[k].append(np.interp(soc, t.soc, getattr(t, k)[0]))
        ok = t.converged[0].astype(np.float64)
        cols["converged"].append(np.interp(soc, t.soc, ok) >= 1.0)
    return RcTable(soc=soc, temperature_c=np.asarray(temperatures_c, dtype=np.float64),
                   **extra, **{k: np.vstack(v) for k, v in cols.items()})


@dataclass(frozen=True)
class InputRecord:
    """Provenance of one input file."""

    role: str        # "pulses", "dcir", "ocv", "cycle", ...
    name: str        # file name as given
    sha256: str


@dataclass(frozen=True)
class EcmModel:
    """A fitted 2RC equivalent-circuit model: what model.json holds."""

    capacity_ah: float
    ocv: OcvOverTemperature            # an OcvTable is taken as one temperature row
    charge: RcTable
    discharge: RcTable
    method: str                          # "ga", "lm" or "curve"
    seed: int | None = None
    inputs: tuple[InputRecord, ...] = ()
    notes: tuple[str, ...] = ()          # e.g. "charge parameters copied from discharge"
    direction_deadband_a: float = 0.0    # |i| at or below this keeps the last direction
    effects: tuple[Any, ...] = ()        # optional effects added by `diagnose`
    tool_version: str = __version__
    # lam of the surface SOC soc + lam * u_diff / max(dOCV/dSOC, 0.3 V) at which the RC
    # tables are read (dimensionless; 0: off); needs the diffusion RC pair
    surface_soc_gain: float = 0.0
    # resistances and capacity over the cell's age (None: a model of one age)
    ageing: AgeingLaw | None = None

    def __post_init__(self):
        if isinstance(self.ocv, OcvTable):
            object.__setattr__(self, "ocv", OcvOverTemperature.from_table(self.ocv))
        for k in BRANCH_FIELDS:
            if (getattr(self.charge, k) is None) != (getattr(self.discharge, k) is None):
                raise ValueError(f"EcmModel: {k} in one direction's table only")
        gain = self.surface_soc_gain
        if isinstance(gain, bool) or not isinstance(gain, (int, float)) or \
                not 0.0 <= gain <= SURFACE_SOC_GAIN_MAX:
            raise ValueError(f"surface_soc_gain must be a number in 0..{SURFACE_SOC_GAIN_MAX:g}"
                             f", got {gain!r}")
        object.__setattr__(self, "surface_soc_gain", float(gain))
        if gain and not self.discharge.has_diffusion:
            raise ValueError("surface_soc_gain needs the diffusion RC pair (r_diff_ohm, "
                             "tau_diff_s), which this model does not have")

    def table(self, direction: str) -> RcTable:
        return self.charge if direction == "charge" else self.discharge

    @property
    def temperatures_c(self) -> np.ndarray:
        """All temperature breakpoints of the model's tables (empty: no temperature axis)."""
        t = np.concatenate([self.ocv.temperature_c, self.charge.temperature_c,
                            self.discharge.temperature_c])
        return np.unique(t[np.isfinite(t)]) if self.needs_temperature else np.array([])

    @property
    def needs_temperature(self) -> bool:
        """True when some table has more than one temperature row: a simulation then needs
        the cell temperature."""
        return max(self.ocv.n_temperatures, self.charge.n_temperatures,
                   self.discharge.n_temperatures) > 1

    def surface_per_volt_rows(self) -> np.ndarray:
        """lam / max(dOCV/dSOC, SURFACE_MIN_SLOPE_V) at every OCV breakpoint, 1/V,
        (n_temperatures, n_soc): dOCV/dSOC over the breakpoint's two neighbours (one-sided
        at the ends), per OCV row."""
        v, x = self.ocv.ocv_v, self.ocv.soc
        ends = np.diff(v, axis=1) / np.diff(x)
        slope = np.concatenate([ends[:, :1], (v[:, 2:] - v[:, :-2]) / (x[2:] - x[:-2]),
                                ends[:, -1:]], axis=1)
        return self.surface_soc_gain / np.maximum(slope, SURFACE_MIN_SLOPE_V)

    def surface_per_volt(self, soc, temperature_c=None) -> np.ndarray:
        """lam / max(dOCV/dSOC, SURFACE_MIN_SLOPE_V) at (soc, temperature_c), per volt: the
        surface SOC is clamp(soc + this * u_diff, 0, 1). The values at the OCV breakpoints
        (:meth:`surface_per_volt_rows`) are bilinear over (temperature, SOC) as the OCV is,
        clamped: continuous in SOC, and a table the C interpolates without a division."""
        return interp_2d(self.ocv.temperature_c, self.ocv.soc, self.surface_per_volt_rows(),
                         soc, temperature_c)

    def at_age(self, equivalent_full_cycles=None) -> "EcmModel":
        """The model of the cell at that age (None: the model as it is): every resistance
        and the capacity scaled by the ageing law, which the result no longer carries. An
        age for a model without a law is an error, not a silent fresh cell."""
        if equivalent_full_cycles is None:
            return self
        if self.ageing is None:
            raise ValueError("this model has no ageing law: an age means nothing to it "
                             "(ecmgen age writes one)")
        k_r, k_q = (float(v) for v in self.ageing.at(float(equivalent_full_cycles)))

        def scaled(t: RcTable) -> RcTable:
            r = {f: k_r * getattr(t, f) for f in ("r0_ohm", "r_fast_ohm", "r_slow_ohm")}
            if t.r_diff_ohm is not None:
                r["r_diff_ohm"] = k_r * t.r_diff_ohm
            return replace(t, **r)

        return replace(self, charge=scaled(self.charge), discharge=scaled(self.discharge),
                       capacity_ah=k_q * self.capacity_ah, ageing=None)

    def with_effects(self, effects) -> "EcmModel":
        return replace(self, effects=tuple(effects))

    # -- serialisation ----------------------------------------------------------------
    def to_json_dict(self) -> dict:
        def table(t: RcTable) -> dict:
            d = {"temperature_c": _temps(t.temperature_c), "soc": _floats(t.soc)}
            for k in RC_FIELDS:
                d[k] = _rows(getattr(t, k))
            for k in BRANCH_FIELDS:
                if getattr(t, k) is not None:
                    d[k] = _floats(getattr(t, k))
            d["fit_error"] = _rows(t.fit_error)
            d["converged"] = [[bool(c) for c in row] for row in t.converged]
            return d

        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "tool_version": self.tool_version,
            "method": self.method,
            "seed": self.seed,
            "capacity_ah": float(self.capacity_ah),
            "direction_deadband_a": float(self.direction_deadband_a),
            **({"surface_soc_gain": self.surface_soc_gain} if self.surface_soc_gain else {}),
            "ocv": {"temperature_c": _temps(self.ocv.temperature_c),
                    "soc": _floats(self.ocv.soc), "ocv_v": _rows(self.ocv.ocv_v)},
            "rc": {"charge": table(self.charge), "discharge": table(self.discharge)},
            **({"ageing": self.ageing.to_json_dict()} if self.ageing is not None else {}),
            "effects": [_effect_to_json(e) for e in self.effects],
            "inputs": [{"role": r.role, "name": r.name, "sha256": r.sha256} for r in self.inputs],
            "notes": list(self.notes),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_json_dict(), indent=1, allow_nan=False) + "\n"

    def sha256(self) -> str:
        """Hash of the canonical JSON text: names this exact model (C banner, reports)."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        write_atomic(path, self.to_json())
        return path


def _floats(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64)]


def _rows(a) -> list[list[float]]:
    return [_floats(row) for row in np.asarray(a, dtype=np.float64)]


def _temps(t) -> list[float | None]:
    """Temperature breakpoints for JSON: an unknown temperature (NaN) is null."""
    return [float(x) if np.isfinite(x) else None for x in np.asarray(t, dtype=np.float64)]


def _effect_to_json(effect) -> dict:
    return effect.to_json_dict()


def load_model(path: str | Path) -> EcmModel:
    """Read and check a model.json; any problem is an InputError naming the file."""
    with reading(path):
        return _load_model(path)


def _load_model(path: str | Path) -> EcmModel:
    path = Path(path)
    try:
        raw = json.loads(path.read_text(), object_pairs_hook=_unique_keys)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    except _DuplicateKey as exc:
        raise InputError(path, f"the key \"{exc}\" appears twice in one object (JSON keeps "
                               "the last silently; which one is meant?)") from None
    return model_from_json_dict(raw, path)


class _DuplicateKey(Exception):
    pass


def _unique_keys(pairs: list) -> dict:
    """json's object hook: a key given twice is an error, not the last one winning."""
    out: dict = {}
    for k, v in pairs:
        if k in out:
            raise _DuplicateKey(k)
        out[k] = v
    return out


def model_from_json_dict(raw: Any, path=None) -> EcmModel:
    """An EcmModel from the parsed JSON of model.json (schema version 1 or 2)."""
    if not isinstance(raw, dict) or raw.get("schema") != SCHEMA:
        raise InputError(path, f"not an ecmgen model (missing \"schema\": \"{SCHEMA}\")")
    version = raw.get("schema_version")
    if isinstance(version, bool) or version not in READS_VERSIONS:   # true == 1 in Python
        raise InputError(path, f"schema_version {version!r} is not supported "
                               f"(this ecmgen reads versions {', '.join(map(str, READS_VERSIONS))})")

    check_model_json(raw, path)
    try:     # the tables' own checks (temperature range, ...) name the file too
        model = _model_from_checked_json(raw, path, version)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    check_model_ranges(model, path)
    return model


class _Reader:
    """Reads a checked model.json's values, naming the file and the key in each error."""

    def __init__(self, path, version: int):
        self.path, self.version = path, version

    def need(self, d, key, where):
        if not isinstance(d, dict) or key not in d:
            raise InputError(self.path, f"missing {where}{key}")
        return d[key]

    def temps(self, d, n_rows: int, where: str) -> np.ndarray:
        """Version 1 has no temperature axis: one row, temperature unknown."""
        if self.version == 1:
            return np.array([np.nan])
        t = self.need(d, "temperature_c", where)
        if not isinstance(t, list) or len(t) != n_rows:
            raise InputError(self.path, f"{where}temperature_c must list one temperature per row "
                                        f"({n_rows} rows)")
        if n_rows == 1 and t[0] is None:
            return np.array([np.nan])
        out = _f64(t, where + "temperature_c", self.path)
        if np.any(np.diff(out) <= 0):
            raise InputError(self.path, f"{where}temperature_c must be strictly increasing")
        return out

    def rows(self, d, key, where, n_soc: int, dtype=np.float64) -> np.ndarray:
        """A (n_t, n_soc) table; version 1 (and a flat list) is one row."""
        path = self.path
        v = self.need(d, key, where)
        if not isinstance(v, list) or not v:
            raise InputError(path, f"{where}{key} must be a non-empty list")
        if not isinstance(v[0], list):
            v = [v]
        if dtype is bool:
            a = np.asarray(v, dtype=bool)
        else:
            lengths = {len(r) if isinstance(r, list) else -1 for r in v}
            if lengths != {n_soc}:
                raise InputError(path, f"{where}{key} must have {n_soc} values per row "
                                       "(one per SOC breakpoint)")
            a = np.vstack([_f64(r, where + key, path) for r in v])
        if a.ndim != 2 or a.shape[1] != n_soc:
            raise InputError(path, f"{where}{key} has shape {a.shape}, expected (rows, {n_soc})")
        return a

    def rc_table(self, rc: dict, direction: str) -> RcTable:
        """One direction's RC table."""
        path, rows = self.path, self.rows
        t = self.need(rc, direction, "rc.")
        where = f"rc.{direction}."
        soc = _f64(self.need(t, "soc", where), where + "soc", path)
        if np.any(np.diff(soc) <= 0) or soc[0] < 0 or soc[-1] > 1:
            raise InputError(path, f"{where}soc must be strictly increasing within [0, 1]")
        cols = {}
        for k in RC_FIELDS:
            cols[k] = rows(t, k, where, soc.size)
            if np.any(cols[k] < 0) or (k.startswith("tau") and np.any(cols[k] <= 0)):
                raise InputError(path, f"{where}{k} must be positive")
        n_t = cols["r0_ohm"].shape[0]
        if any(c.shape[0] != n_t for c in cols.values()):
            raise InputError(path, f"{where}: the parameters have different numbers of rows")
        fit_error = (rows(t, "fit_error", where, soc.size) if "fit_error" in t
                     else np.zeros((n_t, soc.size)))
        converged = (rows(t, "converged", where, soc.size, bool) if "converged" in t
                     else np.ones((n_t, soc.size), bool))
        if fit_error.shape != (n_t, soc.size) or converged.shape != (n_t, soc.size):
            raise InputError(path, f"{where}fit_error/converged do not match the table shape")
        branch = self.branch(t, where, n_t)
        return RcTable(soc=soc, fit_error=fit_error, converged=converged,
                       temperature_c=self.temps(t, n_t, where), **branch, **cols)

    def branch(self, t: dict, where: str, n_t: int) -> dict:
        """The per-temperature values of a direction (diffusion pair, Butler-Volmer i0)."""
        path, branch = self.path, {}
        for k in BRANCH_FIELDS:
            if k in t:
                branch[k] = _f64(t[k] if isinstance(t[k], list) else [t[k]], where + k, path)
                if branch[k].size != n_t:
                    raise InputError(path, f"{where}{k} must have one value per temperature "
                                           f"row ({n_t})")
                if np.any(branch[k] < 0) or (k != "r_diff_ohm" and np.any(branch[k] <= 0)):
                    raise InputError(path, f"{where}{k} must be positive")
        if ("r_diff_ohm" in branch) != ("tau_diff_s" in branch):
            raise InputError(path, f"{where}r_diff_ohm and tau_diff_s go together")
        return branch


def _model_from_checked_json(raw: dict, path, version: int) -> EcmModel:
    """model_from_json_dict once the types and keys are known to be right."""
    read = _Reader(path, version)
    need = read.need
    capacity = float(_f64([need(raw, "capacity_ah", "")], "capacity_ah", path)[0])
    if capacity <= 0:
        raise InputError(path, f"capacity_ah must be positive, got {capacity}")
    ocv_raw = need(raw, "ocv", "")
    ocv_soc = _f64(need(ocv_raw, "soc", "ocv."), "ocv.soc", path)
    ocv_v = read.rows(ocv_raw, "ocv_v", "ocv.", ocv_soc.size)
    for row in ocv_v:
        check_ocv(ocv_soc, row, path)
    ocv = OcvOverTemperature(read.temps(ocv_raw, ocv_v.shape[0], "ocv."), ocv_soc, ocv_v)
    rc = need(raw, "rc", "")
    tables = {direction: read.rc_table(rc, direction) for direction in DIRECTIONS}

    effects_raw = raw.get("effects", [])
    effects: tuple = ()
    if effects_raw:
        from .effects import effect_from_json_dict

        effects = tuple(effect_from_json_dict(e, path) for e in effects_raw)
    inputs = tuple(InputRecord(str(r["role"]), str(r["name"]), str(r["sha256"]))
                   for r in raw.get("inputs", []))
    seed = raw.get("seed")
    ageing = None
    if "ageing" in raw:
        def fail(message):
            raise InputError(path, message)

        ageing = ageing_from_json(raw["ageing"], fail)
    try:     # EcmModel checks what the tables alone cannot (surface_soc_gain among it)
        return EcmModel(
            capacity_ah=capacity,
            ocv=ocv,
            charge=tables["charge"],
            discharge=tables["discharge"],
            method=str(raw.get("method", "")),
            seed=None if seed is None else int(seed),
            inputs=inputs,
            notes=tuple(str(n) for n in raw.get("notes", [])),
            direction_deadband_a=float(raw.get("direction_deadband_a", 0.0)),
            effects=effects,
            tool_version=str(raw.get("tool_version", "")),
            surface_soc_gain=raw.get("surface_soc_gain", 0.0),
            ageing=ageing,
        )
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
