"""The build config's schema: every section and every key, with its type, unit, range,
default and meaning, in one table.

ecmgen.config.loader checks a config against it first: unknown sections and keys
are refused in every section, with the nearest known name ("did you mean"), and each
value's type and range are checked here, so that the loader is left with what ties keys
together (exactly one of data.pulses / data.dynamic / data.dcir / [[data.pulse_tests]], fit.best among
fit.methods, files that exist). ``ecmgen config --explain`` prints :func:`reference`,
and docs/config.md's reference is that same text (a test keeps them equal).

A key added to the config is one row here (and its use in the loader). A small table of
our own rather than pydantic or attrs+cattrs: the checks are types and ranges of a dozen
kinds, the messages must be ecmgen's one line naming the file and the key (pydantic's are
several lines of its own wording, re-worded anyway), and the same rows print the
reference; a dependency would add more code than this module.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any

# value kinds; a key may take several ("number|false")
NUMBER, INTEGER, BOOL, TEXT, FILE, FALSE = "number", "integer", "bool", "string", "file", "false"
CHOICE = "choice"                 # one of Key.choices
NUMBERS, FILES, CHOICES = "list of number", "list of file", "list of choice"
WINDOW, TABLE, COLUMN = "[t0, t1]", "table", "column"    # COLUMN: a name or a 1-based position


@dataclass(frozen=True)
class Key:
    name: str
    kind: str                     # one of the kinds above, alternatives joined by "|"
    help: str
    default: str = ""             # as the reference shows it ("" with required: none)
    unit: str = ""
    range: tuple[float, float] | None = None     # for numbers (each, in a list)
    choices: tuple = ()
    required: bool = False
    out_of_range: str = ""        # the range message, if plainer words say it better
    keys_of: str = ""             # a TABLE of that section's keys (per_file: one per file)
    per_file: bool = False


@dataclass(frozen=True)
class Section:
    name: str                     # "fit", "data.pulse_tests", "data.columns"
    help: str
    keys: tuple[Key, ...]
    array: bool = False           # [[name]]: a list of tables
    roles: tuple[str, ...] = ()   # sub-tables of the same keys ([data.columns.<role>])

    def key(self, name: str) -> Key | None:
        return next((k for k in self.keys if k.name == name), None)


SOC = (0.0, 1.0)
TEMPERATURE_C = (-60.0, 100.0)    # a pulse test's or a derived row's temperature
METHODS = ("ga", "lm", "curve")
EFFECTS = ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error",
           "temperature_dependence")
COLUMN_ROLES = ("pulses", "ocv", "cycle", "extra_cycles", "judge")

SECTIONS: tuple[Section, ...] = (
    Section("cell", "the cell", (
        Key("capacity_ah", NUMBER, "rated capacity", unit="Ah", range=(1e-3, 1e5),
            required=True),
    )),
    Section("data", "the measurement files (paths relative to the config)", (
        Key("pulses", FILE, "a pulse/HPPC test (or data.dcir, data.dynamic, or "
            "[[data.pulse_tests]])"),
        Key("dynamic", FILE, "a dynamic test instead of a pulse test: a drive profile in "
            "blocks with rests of 300 s or more between them; the rests give the SOC levels, "
            "the blocks and their relaxations the RC tables (fit method curve only; start "
            "SOC as data.pulses_soc0, \"pulses\" in data.ocv means its rests)"),
        Key("dcir", FILE, "a soc,direction,c_rate,t_s,r_ohm table instead of a pulse test"),
        Key("pulses_soc0", NUMBER, "SOC at the start of the pulse test", range=SOC,
            unit="SOC", default="from all its rests against the OCV, else 1.0"),
        Key("pulse_tests", TABLE, "pulse tests at several temperatures: [[data.pulse_tests]]"),
        Key("ocv", f"{FILE}|{FILES}", "a soc,ocv_v table, a low-rate test, \"pulses\" (the "
            "pulse test's rests), or a list of them merged in order",
            default='"pulses" with [[data.pulse_tests]]'),
        Key("ocv_cycle", INTEGER, "the discharge + charge cycle of a low-rate test (from 1)",
            range=(1, 1e6), default="the last complete one",
            out_of_range="must be a cycle number from 1"),
        Key("ocv_branch", CHOICE, "the OCV branch: both (their average), charge, discharge, "
            "auto (with a pulse test the one closest to its rests, else both)",
            choices=("auto", "both", "charge", "discharge"), default='"auto"'),
        Key("ocv_rests_first", CHOICE, "auto: where data.ocv's files, measured at the pulse "
            "test's own temperature, differ from its relaxed rests beyond the OCV check, the "
            "rests lead and the files fill the SOC they do not cover; never: the files as "
            "given", choices=("auto", "never"), default='"auto"'),
        Key("ocv_soc0", NUMBER, "SOC at the low-rate test's first sample: count SOC with "
            "cell.capacity_ah instead of normalising each branch", unit="SOC", range=SOC),
        Key("cycle", FILE, "the validation drive cycle"),
        Key("soc0", NUMBER, "start SOC of every validation cycle", unit="SOC", range=SOC,
            default="from the rests each cycle opens with"),
        Key("extra_cycles", FILES, "further validation cycles", default="[]"),
        Key("cycle_window_s", f"{WINDOW}|{TABLE}", "validate on t0 <= time <= t1 of each "
            "validation file, or per file: {\"us06.mat\" = [0, 3600]} (a path, or the "
            "name of one file of the config)", unit="s",
            range=(-1e12, 1e12)),
        Key("temperature_c", f"{NUMBER}|{TABLE}", "the cell temperature of files without a "
            "temperature column, or per file: {\"us06.csv\" = 25}, or a time-stamped log "
            "on the file's clock: {\"us06.csv\" = \"us06-temp.csv\"} (time and temp "
            "columns by name; a log without times is refused) (a pulse test's own "
            "temperature_c applies to its files)", unit="degC", range=TEMPERATURE_C,
            default="the file's column"),
        Key("columns", TABLE, "column mapping of CSVs from other cyclers: [data.columns]"),
    )),
    Section("data.pulse_tests", "one pulse test of a model over temperature", (
        Key("file", FILE, "the pulse test", required=True),
        Key("soc0", NUMBER, "as data.pulses_soc0", unit="SOC", range=SOC),
        Key("temperature_c", NUMBER, "its table temperature, and its files' cell "
            "temperature where they have no column", unit="degC",
            range=TEMPERATURE_C, default="the median cell temperature in its pulses"),
        Key("steps", FILE, "the SOC steps between its pulse sets, logged apart"),
        Key("ocv", FILE, "this test's OCV (a file, or \"pulses\")", default="data.ocv"),
        Key("dynamic", BOOL, "the file is a dynamic test, as data.dynamic (its table "
            "temperature: the median cell temperature in its blocks)", default="false"),
        Key("columns", TABLE, "this test's own column map for its file and steps: the keys "
            "of [data.columns], over [data.columns] and [data.columns.pulses] key by key",
            keys_of="data.columns"),
    ), array=True),
    Section("data.columns", "CSV columns, units and current sign (every CSV of the "
            "config; [data.columns.<role>] extends it for one role's files: "
            + ", ".join(COLUMN_ROLES) + ")", (
        Key("time", COLUMN, "time column: its name, or 1-based position", default='"time_s"'),
        Key("current", COLUMN, "current column", default='"current_a"'),
        Key("voltage", COLUMN, "voltage column", default='"voltage_v"'),
        Key("temperature", COLUMN, "cell temperature column (degC)"),
        Key("charge", COLUMN, "the cycler's Ah counter: cumulative, or restarting per step "
            "or cycle (joined on reading); with discharge: its charge counter"),
        Key("discharge", COLUMN, "a discharge counter counting up beside charge (Arbin "
            "Discharge_Capacity, disAh)"),
        Key("time_unit", CHOICE, "unit of the time column", choices=("s", "min", "h"),
            default='"s"'),
        Key("current_unit", CHOICE, "unit of the current column", choices=("A", "mA"),
            default='"A"'),
        Key("voltage_unit", CHOICE, "unit of the voltage column", choices=("V", "mV"),
            default='"V"'),
        Key("charge_unit", CHOICE, "unit of the charge column", choices=("Ah", "mAh"),
            default='"Ah"'),
        Key("current_sign", CHOICE, "which direction is positive (current and charge)",
            choices=("charge_positive", "discharge_negative", "discharge_positive",
                     "charge_negative"), default='"charge_positive"'),
        Key("header", BOOL, "false: no header line, columns given by position",
            default="true"),
        Key("files", TABLE, "per file, its own column map: {\"us06.csv\" = {header = "
            "false, time = 2, ...}} (a path, or the name of one file of the config), over "
            "[data.columns] and its role's table key by key", keys_of="data.columns",
            per_file=True),
    ), roles=COLUMN_ROLES),
    Section("dcir", "the DC-IR table of the pulse test", (
        Key("times_s", NUMBERS, "DC-IR times after each pulse's start (4 or more, "
            "increasing)", unit="s", range=(1e-6, 1e6), default="[0.1, 1, 3, 6, 10]"),
        Key("c_rate", f"{NUMBER}|{CHOICE}", "the five-point fits' C-rate: \"max\" (the "
            "highest), \"all\" (averaged) or a C-rate", choices=("max", "all"),
            range=(1e-6, 1e3), default='"max"'),
        Key("min_rest_s", NUMBER, "a pulse follows at least this much rest", unit="s",
            range=(0.0, 1e6), default="30"),
        Key("max_pulse_s", NUMBER, "and lasts at most this long", unit="s",
            range=(1e-6, 1e6), default="120"),
    )),
    Section("fit", "the fits", (
        Key("methods", CHOICES, "the methods fitted", choices=METHODS,
            default='["ga", "lm", "curve"] (["ga", "lm"] with data.dcir, ["curve"] with '
            'data.dynamic)'),
        Key("seed", INTEGER, "the GA's random seed", range=(0, 2**63 - 1), default="0"),
        Key("relax_s", NUMBER, "at most this much relaxation after each pulse in the "
            "whole-test fit", unit="s", range=(1e-6, 1e7), default="1800"),
        Key("best", CHOICE, "the method that becomes model.json", choices=METHODS,
            default='"curve" if fitted, else the last of fit.methods'),
        Key("curve_branches", BOOL, "the whole-test fit's diffusion pair and Butler-Volmer "
            "branch (diagnose fits its base model without them unless this is set)",
            default="true"),
    )),
    Section("model", "the model's tables over temperature", (
        Key("temperature_step_c", NUMBER, "the tables' uniform temperature grid (0: the "
            "tests' own rows)", unit="K", range=(0.0, 50.0), default="5"),
        Key("warm_row_c", f"{NUMBER}|{FALSE}", "a derived row above the warmest test "
            "(false: none)", unit="degC", range=TEMPERATURE_C, default="45"),
        Key("surface_soc_gain", NUMBER, "the RC tables read at the surface SOC (models "
            "with the diffusion pair; 0: off)", range=(0.0, 10.0),
            default="0.3 over temperature, 0 from one test"),
        Key("activation_k", NUMBER, "Ea/R: a model from one pulse test scales its "
            "resistances by exp(Ea/R (1/T - 1/T_test)) at the cell temperature T (0: off)",
            unit="K", range=(0.0, 50000.0), default="0"),
    )),
    Section("report", "the verdicts of report.md", (
        Key("max_mae_mv", NUMBER, "the validation passes when model.json's MAE on every "
            "cycle is at most this", unit="mV", range=(1e-3, 1e4), default="50"),
    )),
    Section("c", "the generated C", (
        Key("prefix", TEXT, "symbol and file prefix: a C identifier of 1-32 characters, "
            "not beginning with ecmrt", default='"ecm"'),
        Key("numeric", f"{CHOICE}|{CHOICES}", "float32 and/or fixed point",
            choices=("float", "fixed"), default='["float", "fixed"]'),
        Key("dt_s", NUMBER, "a fixed step (unset: the step takes the measured dt)",
            unit="s", range=(1e-6, 3600.0), default="variable"),
        Key("estimator", CHOICE, "the SOC filter next to the float step",
            choices=("none", "ekf"), default='"none"'),
        Key("ocv_soc_step", INTEGER, "flash: the C's OCV keeps every n-th SOC breakpoint "
            "(and the last); model.json keeps them all", range=(1, 16), default="1"),
        Key("rc_soc_step", INTEGER, "flash: the C's RC tables keep every n-th SOC "
            "breakpoint (and the last)", range=(1, 16), default="1"),
    )),
    Section("estimator", "the SOC filter (ecmgen estimate, [c] estimator); the sensor "
            "figures are one sigma", (
        Key("filter", CHOICE, "the filter", choices=("ekf", "ukf"), default='"ekf"'),
        Key("start", CHOICE, "how a record starts: rested (its first voltage the OCV) or "
            "anywhere (the start-anywhere settings under the keys set here)",
            choices=("rested", "anywhere"), default='"rested"'),
        Key("offset_state", BOOL, "the current sensor's offset as a state", default="false"),
        Key("soc0_sigma", NUMBER, "how uncertain the start SOC is told to be", unit="SOC",
            range=(1e-9, 1.0), default="0.3"),
        Key("u0_sigma_v", NUMBER, "the RC voltages at the start", unit="V",
            range=(0.0, 10.0), default="0.002"),
        Key("current_offset_a", NUMBER, "current sensor offset", unit="A",
            range=(0.0, 1e4), default="C/100"),
        Key("current_gain_error", NUMBER, "current sensor gain error (fraction)",
            range=(0.0, 1.0), default="0.01"),
        Key("current_noise_a", NUMBER, "white current noise per sample", unit="A",
            range=(0.0, 1e4), default="0.01"),
        Key("drift_horizon_s", NUMBER, "time over which the sensor bias is counted",
            unit="s", range=(1e-6, 1e9), default="3600"),
        Key("voltage_noise_v", NUMBER, "voltage sensor + OCV table error at rest", unit="V",
            range=(0.0, 10.0), default="0.005"),
        Key("model_error", NUMBER, "the model's voltage error / the overpotential it "
            "predicts", range=(0.0, 100.0), default="0.19 (measured on the config's "
                                                    "cycles where it has them)"),
        Key("error_correlation_s", NUMBER, "how long that error stays correlated",
            unit="s", range=(1e-6, 1e9), default="800 (as model_error)"),
        Key("polarization_error", NUMBER, "RC-state process noise, fraction of r |i|",
            range=(0.0, 100.0), default="1.5"),
        Key("start_polarization_c", NUMBER, "0: the record starts rested; above: it may "
            "start anywhere, the RC voltages unknown within r times this current", unit="C",
            range=(0.0, 100.0), default="0"),
        Key("error_memory_s", NUMBER, "0: the model error scales with the overpotential "
            "of the sample; above: with the largest since, decayed over this time", unit="s",
            range=(0.0, 1e6), default="0"),
        Key("resistance_slopes", BOOL, "the Jacobians carry the RC tables' SOC slopes; "
            "false: the SOC is read from the OCV alone", default="true"),
        Key("polarization_soc_sigma", NUMBER, "0: off; above: the RC-state process noise "
            "scaled by s^2 / (s^2 + SOC variance), s this SOC sigma", unit="SOC",
            range=(0.0, 1.0), default="0"),
        Key("ocv_slope_spread", NUMBER, "0: the EKF takes the OCV's slope at its SOC; "
            "k above: the secant over the SOC +- k of its sigma", unit="sigma",
            range=(0.0, 10.0), default="0"),
    )),
    Section("diagnose", "ecmgen diagnose: missing effects found on data.cycle", (
        Key("cycle", FILE, "the record to diagnose on", default="data.cycle"),
        Key("cycle_soc0", NUMBER, "its start SOC", unit="SOC", range=SOC,
            default="data.soc0 for data.cycle, else from its first rested voltage"),
        Key("judge", FILE, "a second cycle to judge on",
            default="the held-out end of data.cycle"),
        Key("judge_soc0", NUMBER, "its start SOC", unit="SOC", range=SOC,
            default="from its first rested voltage"),
        Key("base", FILE, "the model.json to start from (e.g. what build wrote)",
            default="the plain 2RC fitted from the config's data"),
        Key("split", NUMBER, "fraction of the cycle fitted without a judge",
            range=(0.1, 0.9), default="0.6"),
        Key("effects", CHOICES, "the candidates", choices=EFFECTS, default="all five"),
        Key("max_effects", INTEGER, "at most this many added", range=(1, 5), default="4"),
        Key("min_rel_gain", NUMBER, "the held-out MAE must fall by at least this fraction",
            range=(0.0, 1.0), default="0.08"),
        Key("confidence", NUMBER, "of the block-bootstrap bound on the held-out gain",
            range=(0.5, 0.9999), default="0.99"),
    )),
)

BY_NAME = {s.name: s for s in SECTIONS}
TOP_SECTIONS = tuple(s.name for s in SECTIONS if "." not in s.name)


# --------------------------------------------------------------------------- checking

class SchemaError(ValueError):
    """A config value or key the schema refuses; the loader names the file."""


def _did_you_mean(name: str, known) -> str:
    near = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
    return f" (did you mean {near[0]!r}?)" if near else ""


def _unknown(table: dict, known, label: str) -> None:
    unknown = sorted(str(k) for k in table if k not in known)
    if unknown:
        raise SchemaError(f"{label}: unknown key(s) {unknown}{_did_you_mean(unknown[0], known)}"
                          f"; known: {', '.join(known)}")


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _accepts(kind: str, v: Any, key: Key) -> bool:
    if kind == NUMBER:
        return _is_number(v)
    if kind == INTEGER:
        return isinstance(v, int) and not isinstance(v, bool)
    if kind == BOOL:
        return isinstance(v, bool)
    if kind == FALSE:
        return v is False
    if kind in (TEXT, FILE):
        return isinstance(v, str) and v != ""
    if kind == CHOICE:
        return isinstance(v, str) and v in key.choices
    if kind == COLUMN:
        return (isinstance(v, str) and v != "") or (isinstance(v, int) and
                                                    not isinstance(v, bool) and v >= 1)
    if kind == TABLE:
        return isinstance(v, (dict, list))
    if kind == WINDOW:
        return isinstance(v, list) and len(v) == 2 and all(_is_number(x) for x in v)
    if kind.startswith("list of "):
        item = kind[len("list of "):]
        return isinstance(v, list) and all(_accepts(item, x, key) for x in v)
    raise AssertionError(f"unknown kind {kind!r} in the config schema")


WORDS = {NUMBER: "a number", INTEGER: "an integer", BOOL: "true or false", FALSE: "false",
         TEXT: "a string", FILE: "a file name", COLUMN: "a column name or 1-based position",
         TABLE: "a table", WINDOW: "[t0, t1], two times in s", NUMBERS: "a list of numbers",
         FILES: "a list of file names"}


def _words(kind: str, key: Key) -> str:
    if kind in (CHOICE, CHOICES):
        listed = ", ".join(f'"{c}"' for c in key.choices)
        return f"one of {listed}" if kind == CHOICE else f"a list from {listed}"
    return WORDS[kind]


def check_value(key: Key, v: Any, where: str) -> None:
    """SchemaError unless ``v`` is of one of the key's kinds and its numbers in range."""
    kinds = key.kind.split("|")
    if not any(_accepts(k, v, key) for k in kinds):
        what = " or ".join(_words(k, key) for k in kinds)
        raise SchemaError(f"{where} must be {what}, got {v!r}"[:300])
    if key.range is None:
        return
    numbers = [v] if _is_number(v) else [x for x in v if _is_number(x)] \
        if isinstance(v, list) else []
    lo, hi = key.range
    for x in numbers:
        if not math.isfinite(x):
            raise SchemaError(f"{where} must be a number, got {x!r}")
        if not lo <= x <= hi:
            if key.out_of_range:
                raise SchemaError(f"{where} {key.out_of_range}, got {x!r}")
            if key.unit == "SOC":
                raise SchemaError(f"{where} is a SOC and must lie in [0, 1], got {x!r}")
            unit = f" {key.unit}" if key.unit else ""
            raise SchemaError(f"{where} must lie in {lo:g}..{hi:g}{unit}, got {x:g}")


def _check_table(section: Section, table: Any, label: str, where: str) -> None:
    """One table of ``section``: a table, known keys, each value of its kind and range."""
    if not isinstance(table, dict):
        raise SchemaError(f"{label} must be a table")
    known = [k.name for k in section.keys] + list(section.roles)
    _unknown(table, known, label)
    for name, v in table.items():
        if name in section.roles and isinstance(v, dict):
            _check_table(section, v, f"[{section.name}.{name}]", f"{where}.{name}")
            continue
        key = section.key(name)
        if key is None:          # a role name given a plain value
            raise SchemaError(f"{where}.{name} must be a table ([{section.name}.{name}])")
        if key.kind == TABLE and f"{section.name}.{name}" in BY_NAME:
            continue             # its own section, checked by check_config
        if key.keys_of:
            _check_keys_of(key, v, f"{where}.{name}")
            continue
        check_value(key, v, f"{where}.{name}")


def _check_keys_of(key: Key, v: Any, where: str) -> None:
    """A table of another section's keys (its sub-tables of roles not allowed), or with
    ``per_file`` a table of such tables by file name."""
    of = BY_NAME[key.keys_of]
    plain = Section(of.name, of.help, tuple(k for k in of.keys if not k.keys_of))
    tables = v if key.per_file and isinstance(v, dict) else {None: v}
    for name, table in tables.items():
        label = where if name is None else f"{where}.{name!r}"
        if not isinstance(table, dict):
            raise SchemaError(f"{label} must be a table of [{of.name}] keys")
        _check_table(plain, table, label, label)


def check_config(raw: dict) -> None:
    """Check a parsed config against SECTIONS: SchemaError (one line) on the first
    unknown section or key, wrong type, or value out of range."""
    unknown = sorted(str(k) for k in raw if k not in TOP_SECTIONS)
    if unknown:
        raise SchemaError(f"unknown section(s) {unknown}{_did_you_mean(unknown[0], TOP_SECTIONS)}"
                          f"; known: {', '.join(TOP_SECTIONS)}")
    for section in SECTIONS:
        parts = section.name.split(".")
        table: Any = raw
        for p in parts[:-1]:
            table = table.get(p, {}) if isinstance(table, dict) else {}
        if not isinstance(table, dict) or parts[-1] not in table:
            continue
        value = table[parts[-1]]
        if section.array:
            if not isinstance(value, list) or not value or \
                    not all(isinstance(e, dict) for e in value):
                raise SchemaError(f"{section.name} must be one or more [[{section.name}]] "
                                  "tables")
            for n, entry in enumerate(value, 1):
                where = f"{section.name}[{n}]"
                _check_table(section, entry, where, where)
        else:
            _check_table(section, value, f"[{section.name}]", section.name)


# --------------------------------------------------------------------------- reference

def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def reference() -> str:
    """The config reference (markdown): one table per section, every key."""
    lines = ["Every key of the build config (`ecmgen config --explain` prints this). Unknown "
             "sections and keys are refused, with the nearest known name.", ""]
    for s in SECTIONS:
        head = f"[[{s.name}]]" if s.array else f"[{s.name}]"
        roles = f" (also [{s.name}.<role>])" if s.roles else ""
        lines += [f"`{head}`{roles}: {s.help}", "",
                  "| key | type | unit | range | default | meaning |",
                  "|---|---|---|---|---|---|"]
        for k in s.keys:
            kind = " or ".join(_words(x, k) for x in k.kind.split("|"))
            rng = "" if k.range is None else f"{k.range[0]:g} .. {k.range[1]:g}"
            default = "required" if k.required else k.default
            lines.append(f"| `{k.name}` | {_cell(kind)} | {k.unit} | {rng} | "
                         f"{_cell(default)} | {_cell(k.help)} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"
