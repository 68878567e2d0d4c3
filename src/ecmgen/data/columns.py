"""Column maps: which columns of a measurement file hold what, in which units and with
which current sign (:class:`ColumnMap`), and the layouts recognised by their names when a
file comes without one (:data:`CSV_LAYOUTS`, :data:`MAT_LAYOUT`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from ..errors import InputError
from .native import native_columns

TIME_UNITS_S = {"s": 1.0, "min": 60.0, "h": 3600.0}
CURRENT_UNITS_A = {"A": 1.0, "mA": 1e-3}
VOLTAGE_UNITS_V = {"V": 1.0, "mV": 1e-3}
CHARGE_UNITS_AH = {"Ah": 1.0, "mAh": 1e-3}
# current_sign: both names of each convention; the first of each pair is the one used inside
CURRENT_SIGNS = {"charge_positive": "charge_positive", "discharge_negative": "charge_positive",
                 "discharge_positive": "discharge_positive",
                 "charge_negative": "discharge_positive"}

# Canonical CSV column order; the names are also TimeSeries' field names.
CANONICAL_HEADER = ("time_s", "current_a", "voltage_v", "temperature_c", "charge_ah")

_UNIT_CHOICES = {"time_unit": TIME_UNITS_S, "current_unit": CURRENT_UNITS_A,
                 "voltage_unit": VOLTAGE_UNITS_V, "charge_unit": CHARGE_UNITS_AH,
                 "current_sign": CURRENT_SIGNS}
_NAME_KEYS = ("time", "current", "voltage", "temperature", "charge", "discharge")
_REQUIRED_KEYS = ("time", "current", "voltage")


@dataclass(frozen=True)
class ColumnMap:
    """Which columns (CSV header names or 1-based positions, .mat field names) hold what,
    in which units.

    time, current, voltage  required: a column name, or its position (1 = first column)
    temperature             optional column (degC)
    charge                  optional charge counter (Ah): cumulative, or restarting per
                            step or cycle; counts up on charge after ``current_sign`` is
                            applied to it too; with ``discharge``: the charge counter
    discharge               optional discharge counter beside ``charge``, counting up
                            on discharge (Arbin's Discharge_Capacity, Plett's disAh)
    time_unit     "s" | "min" | "h"
    current_unit  "A" | "mA"
    voltage_unit  "V" | "mV"
    charge_unit   "Ah" | "mAh"
    current_sign  "charge_positive" = "discharge_negative" (ecmgen's own convention;
                  Arbin, CALCE, Digatron .mat) or "discharge_positive" = "charge_negative"
                  (current AND charge are negated on reading); stored as the first name
    header        False: the CSV has no header line, every line is data and the columns
                  are given by position
    """

    time: str | int = "time_s"
    current: str | int = "current_a"
    voltage: str | int = "voltage_v"
    temperature: str | int | None = None
    charge: str | int | None = None
    discharge: str | int | None = None
    time_unit: str = "s"
    current_unit: str = "A"
    voltage_unit: str = "V"
    charge_unit: str = "Ah"
    current_sign: str = "charge_positive"
    header: bool = True

    def __post_init__(self):
        problem = self._problem()
        if problem:
            raise InputError(None, problem)
        object.__setattr__(self, "current_sign", CURRENT_SIGNS[self.current_sign])

    def _problem(self) -> str | None:
        if not isinstance(self.header, bool):
            return f"header must be true or false, got {self.header!r}"
        for key in _NAME_KEYS:
            value = getattr(self, key)
            if value is None and key not in _REQUIRED_KEYS:
                continue
            if isinstance(value, int) and not isinstance(value, bool):
                if value < 1:
                    return (f"{key} = {value}: a column position counts from 1 (or give "
                            f"the column name)")
            elif not isinstance(value, str) or not value.strip():
                return (f"{key} must be a non-empty column name or a 1-based column "
                        f"position, got {value!r}")
            elif not self.header:
                return (f"{key} = {value!r}: with header = false the columns are given by "
                        f"position ({key} = 1 for the first column)")
        if self.discharge is not None and self.charge is None:
            return "discharge (a discharge counter) needs charge (its charge counter) too"
        for key, choices in _UNIT_CHOICES.items():
            value = getattr(self, key)
            if value not in choices:
                allowed = ", ".join(repr(c) for c in choices)
                return f"{key} = {value!r} is not one of {allowed}"
        return None

    @classmethod
    def from_toml(cls, table: Any, path: str | Path | None,
                  section: str = "[data.columns]") -> "ColumnMap":
        """Build from a parsed TOML table such as
        ``{time="Test_Time(s)", current="Current(A)", voltage="Voltage(V)", current_unit="mA"}``.

        Any unknown key, missing required key or bad value is an InputError naming ``path``
        (the config file) and ``section``.
        """
        if not isinstance(table, dict):
            raise InputError(path, f"{section} must be a table, got {type(table).__name__}")
        allowed = [f.name for f in fields(cls)]
        unknown = [k for k in table if k not in allowed]
        if unknown:
            raise InputError(path, f"{section}: unknown key {unknown[0]!r} "
                                   f"(allowed: {', '.join(allowed)})")
        missing = [k for k in _REQUIRED_KEYS if k not in table]
        if missing:
            raise InputError(path, f"{section}: missing key {missing[0]!r} "
                                   f"(the name of the {missing[0]} column)")
        try:
            return cls(**table)
        except InputError as exc:
            raise InputError(path, f"{section}: {exc.message}") from None

    from_table = from_toml  # alias: the pipeline passes the parsed [data.columns] table

    @classmethod
    def for_file(cls, table: dict | None, roles: tuple[str, ...], config_path,
                 file: str | Path, own: tuple[str, dict] | None = None
                 ) -> "ColumnMap | None":
        """The mapping of one file of a config, from its parsed ``[data.columns]`` table.

        The global keys (``[data.columns]`` itself) apply to every CSV file; the first of
        ``roles`` (e.g. ``("extra_cycles", "cycle")``) with its own
        ``[data.columns.<role>]`` table extends them, key by key, and the file's ``own``
        table (its section's name and the table: a pulse test's columns, [data.columns.
        files]) extends that; either applies to a .mat file too (whose fields the global
        CSV names would not match). A cycler's own file (ecmgen.data.native) takes only
        those, over its reader's names. None: no mapping, the file's layout is recognised
        by its names."""
        table = table or {}
        common = {k: v for k, v in table.items() if not isinstance(v, dict)}
        role = next((r for r in roles if isinstance(table.get(r), dict)), None)
        layers = ([(f"[data.columns.{role}]", table[role])] if role is not None else []) + \
            ([own] if own is not None else [])
        base = native_columns(file)
        if base is None:
            base = common
            if common and layers:
                layers = [("[data.columns]", {})] + layers
        elif not layers:
            return None
        if layers:
            merged = dict(base)
            for _, keys in layers:
                merged.update(keys)
            section = " with ".join(name for name, _ in reversed(layers))
            return cls.from_toml(merged, config_path, section)
        if common and not (Path(file).is_file() and _is_mat(Path(file))):
            return cls.from_toml(common, config_path)
        return None

    def by_position(self) -> bool:
        """True when every column of the map is given by its position."""
        return all(isinstance(v, int) for v in self.names().values())

    def names(self) -> dict[str, str | int]:
        """role -> column name (or 1-based position), for the columns this map uses."""
        return {k: getattr(self, k) for k in _NAME_KEYS if getattr(self, k) is not None}


@dataclass(frozen=True)
class _Layout:
    """A known set of column names: required names in ``columns``, optional ones picked if
    present. ``name`` says what the names look like, not which machine wrote the file
    (other cyclers' exports, e.g. Bitrode, can use the same names)."""

    name: str
    columns: ColumnMap
    temperature: tuple[str, ...] = ()
    charge: tuple[str, ...] = ()
    discharge: tuple[str, ...] = ()     # with charge: the split counters, both needed
    counters_required: bool = False     # generic names: the layout is its counters' too

    def describe(self) -> str:
        c = self.columns
        return f"{self.name} ({c.time}, {c.current}, {c.voltage})"

    def resolve(self, found: list[str]) -> ColumnMap | None:
        if not all(n in found for n in (self.columns.time, self.columns.current,
                                         self.columns.voltage)):
            return None
        if self.counters_required and not all(
                any(n in found for n in names) for names in (self.charge, self.discharge)):
            return None
        temp = next((n for n in self.temperature if n in found), None)
        charge = next((n for n in self.charge if n in found), None)
        discharge = next((n for n in self.discharge if n in found), None)
        if self.discharge and (charge is None or discharge is None):
            charge = discharge = None
        return ColumnMap(self.columns.time, self.columns.current, self.columns.voltage,
                         temp, charge, discharge, current_sign=self.columns.current_sign)

    def present(self, found: list[str]) -> int:
        return sum(n in found for n in (self.columns.time, self.columns.current,
                                        self.columns.voltage))


# CSV layouts tried in order when no mapping is given. Arbin (and the CALCE exports, which
# come from Arbin testers) log current negative on discharge, i.e. already charge-positive;
# a file with these names is read that way, whichever cycler wrote it (the note says so).
# Their Charge/Discharge_Capacity counters (restarting every cycle) are joined into one
# (ecmgen.data.counters). Bitrode's exports log discharge negative too, with an Ah counter
# that restarts at every step.
CSV_LAYOUTS = (
    _Layout("ecmgen's own columns", ColumnMap("time_s", "current_a", "voltage_v"),
            ("temperature_c",), ("charge_ah",)),
    _Layout("Arbin/CALCE-style columns", ColumnMap("Test_Time(s)", "Current(A)", "Voltage(V)"),
            ("Temperature (C)_1",), ("Charge_Capacity(Ah)",), ("Discharge_Capacity(Ah)",)),
    _Layout("Bitrode-style columns", ColumnMap("Time(s)", "Current(A)", "Voltage(V)"),
            (), ("Capacity(Ah)",)),
    # Plett's ESC toolbox CSVs log discharge POSITIVE; their names are generic, so only
    # with both counters, which would refuse a wrong sign (_check_charge_sign)
    _Layout("Plett ESC-toolbox-style columns (discharge positive)",
            ColumnMap("time", "current", "voltage", current_sign="discharge_positive"),
            (), ("chgAh",), ("disAh",), counters_required=True),
    # CALCE low-rate OCV export: a single step, so Step_Time(s) is the only clock.
    _Layout("Arbin/CALCE-style single-step columns",
            ColumnMap("Step_Time(s)", "Current(A)", "Voltage(V)"), ("Temperature (C)_1",)),
)

# Panasonic 18650PF (Digatron) `meas` struct: current and Ah are negative on discharge.
MAT_LAYOUT = _Layout("Panasonic/Digatron-style meas struct",
                     ColumnMap("Time", "Current", "Voltage"), ("Battery_Temp_degC",), ("Ah",))


def _is_mat(path: Path) -> bool:
    if path.suffix.lower() == ".mat":
        return True
    with open(path, "rb") as fh:
        return fh.read(6) == b"MATLAB"
