"""The build configuration (one TOML file; paths are relative to it): the loader.

What each section and key means, its type, unit, range and default are the rows of
ecmgen.config.schema (``ecmgen config --explain`` prints them; docs/config.md's reference is
that text). :func:`load_config` checks a config against the schema first (unknown keys,
types, ranges), then what ties keys together: exactly one of data.pulses, data.dcir or
[[data.pulse_tests]]; fit.best among fit.methods; the files it names exist; the C
estimator with the float numeric and a variable step. A key added to the config is a row
of the schema and its use here.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from .schema import COLUMN_ROLES, METHODS, SchemaError, check_config
from .schema import TEMPERATURE_C as TEMPERATURE_RANGE_C
from ..errors import InputError, reading

SURFACE_SOC_GAIN_MAX = 10.0     # [model] surface_soc_gain's upper bound (0.5 measured)
# its default for a model over temperature (docs/results.md, "The surface SOC"): the
# largest gain that leaves the SOC-step discharges no model chose it on as good as without
SURFACE_SOC_GAIN_OVER_TEMPERATURE = 0.3

# [data.columns.<role>] maps the CSV columns of one file of the config (it extends the
# global [data.columns]); a role without its own table takes its fallback's
COLUMN_ROLE_FALLBACK = {"extra_cycles": "cycle", "judge": "cycle"}
# the validation files, which data.cycle_window_s cuts
WINDOW_ROLES = ("cycle", "extra_cycles", "judge")


@dataclass(frozen=True)
class EstimatorConfig:
    """``[estimator]``: the SOC filter's settings (ecmgen.estimate). The sensor specs are
    one-sigma figures of the BMS's own sensors; the model-error figures describe how far
    the model's voltage is off, as measured on validation cycles (bench/bench_estimator.py).
    """

    filter: str = "ekf"                 # "ekf" or "ukf"
    offset_state: bool = False          # estimate the current sensor's offset as a state
    soc0_sigma: float = 0.3             # how uncertain the start SOC is told to be
    u0_sigma_v: float = 0.002           # the RC voltages at the start (a rested cell: ~0)
    current_offset_a: float | None = None   # current sensor offset, A (1 sigma; None: C/100)
    current_gain_error: float = 0.01    # current sensor gain error, fraction (1 sigma)
    current_noise_a: float = 0.01       # white current noise per sample, A
    drift_horizon_s: float = 3600.0     # the time over which the sensor bias is counted
    voltage_noise_v: float = 0.005      # voltage sensor + OCV-table error at rest, V
    # the model's voltage error: rms(error) / rms(overpotential the model predicts), and its
    # integral correlation time; measured on the Panasonic validation cycles (pooled 0.187
    # and 826 s, leave-one-cycle-out 0.177..0.197 and 711..941 s: bench_estimator.py)
    model_error: float = 0.19
    error_correlation_s: float = 800.0
    # RC-state process noise, fraction of the branch's steady voltage r |i|: chosen
    # leave-one-cycle-out on the same cycles (the smallest meeting the full-cell targets)
    polarization_error: float = 1.5
    # 0: a record starts from a rested cell (its first sample counts fully). Above 0 it may
    # start anywhere (under load, mid-relaxation): the RC voltages start unknown, sigma r_j
    # times this current in C, and no sample counts fully. For a start anywhere 0.5, with
    # the other START_ANYWHERE settings below
    start_polarization_c: float = 0.0
    # 0: the model error scales with the sample's overpotential; T > 0: with the largest
    # since, decayed by exp(-dt / T) (the error outlasts a current step)
    error_memory_s: float = 0.0
    # the EKF's Jacobians carry the RC tables' SOC slopes (r0, r_fast, tau ... over SOC):
    # False reads the SOC from the OCV alone (the resistances' SOC slopes are fitted, not
    # validated; in the cold they made the filter confident and wrong)
    resistance_slopes: bool = True
    # 0: off; s > 0: the RC-state process noise times s^2 / (s^2 + P_soc), so that a slow
    # voltage offset is taken as SOC error while the SOC is far less certain than s
    polarization_soc_sigma: float = 0.0
    # 0: the EKF linearises the OCV at its SOC estimate (the tangent); k > 0: over the SOC
    # it still holds possible, the secant over soc +- k sigma_soc (far from the truth on a
    # curved OCV the tangent moves the SOC by the wrong amount per millivolt)
    ocv_slope_spread: float = 0.0

    def __post_init__(self):
        if self.filter not in ESTIMATOR_FILTERS:
            raise ValueError(f"filter must be one of {', '.join(ESTIMATOR_FILTERS)}, "
                             f"got {self.filter!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type.startswith("float") and v is not None and \
                    not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v!r}")
        for k in ("soc0_sigma", "drift_horizon_s", "error_correlation_s"):
            if getattr(self, k) <= 0:
                raise ValueError(f"{k} must be positive, got {getattr(self, k)!r}")


# [c] prefix: the generated symbols are <prefix>_init, <prefix>_step, <prefix>_state_t,
# ...; the runtime headers' own symbols all begin with "ecmrt" (a test reads them all),
# so a prefix beginning with it could define one of them twice. fullmatch: a "$" would
# let a trailing newline through into file names and C.
C_PREFIX_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,31}")
C_RUNTIME_NAMESPACE = "ecmrt"
C_RESERVED = {"int", "float", "double", "char", "void", "static", "const", "return", "long",
              "short", "signed", "unsigned", "struct", "union", "enum", "typedef", "extern",
              "if", "else", "for", "while", "do", "switch", "case", "default", "break",
              "continue", "goto", "sizeof", "volatile", "register", "auto", "inline",
              "restrict"}


def c_prefix_problem(prefix) -> str | None:
    """Why ``prefix`` cannot prefix the generated C's symbols, or None when it can."""
    if not isinstance(prefix, str) or not C_PREFIX_RE.fullmatch(prefix):
        return (f"prefix {prefix!r} is not usable: it must be a C identifier of 1-32 letters, "
                "digits or '_' starting with a letter")
    if prefix.lower().startswith(C_RUNTIME_NAMESPACE):
        return (f"prefix {prefix!r} is not usable: names beginning with "
                f"{C_RUNTIME_NAMESPACE!r} are the runtime headers' own symbols")
    if prefix.lower() in C_RESERVED:
        return f"prefix {prefix!r} is not usable: it is a C keyword"
    return None


ESTIMATOR_FILTERS = ("ekf", "ukf")
# The settings of a start anywhere (under load, mid-relaxation), chosen on the Panasonic 25
# and 0 degC cycles cut to start at SOC 0.3-0.7 (bench/estimate_any_start.py,
# docs/estimator.md): `ecmgen estimate --start anywhere`, the default of a mid-record window
START_ANYWHERE = dict(start_polarization_c=0.5, resistance_slopes=False, model_error=0.06,
                      error_correlation_s=1600.0, polarization_error=0.5,
                      polarization_soc_sigma=0.01, ocv_slope_spread=1.0)

ESTIMATOR_STARTS = ("rested", "anywhere")


def start_settings(settings: EstimatorConfig, start: str | None,
                   set_keys=frozenset()) -> EstimatorConfig:
    """``settings`` for ``start``: "anywhere" takes START_ANYWHERE under every key not in
    ``set_keys`` (those a config sets or a measurement gave), and a start polarisation of 0
    becomes theirs; "rested" a start polarisation of 0; None: as they are."""
    if start == "rested":
        return replace(settings, start_polarization_c=0.0)
    if start == "anywhere":
        new = {k: v for k, v in START_ANYWHERE.items() if k not in set_keys}
        if settings.start_polarization_c <= 0.0:
            new["start_polarization_c"] = START_ANYWHERE["start_polarization_c"]
        return replace(settings, **new)
    return settings


C_ESTIMATORS = ("none", "ekf")      # [c] estimator: the filter generated into the float C


def estimator_config(table: dict, path: Path | None) -> EstimatorConfig:
    """The ``[estimator]`` table (every key optional), checked; InputError names ``path``."""
    if not isinstance(table, dict):
        raise InputError(path, "[estimator] must be a table")
    known = {f.name: f for f in fields(EstimatorConfig)}
    unknown = sorted(set(table) - set(known) - {"start"})
    if unknown:
        raise InputError(path, f"estimator: unknown key(s) {unknown}; "
                               f"known: {sorted(set(known) | {'start'})}")
    table = dict(table)
    start = table.pop("start", "rested")
    if start not in ESTIMATOR_STARTS:
        raise InputError(path, f"estimator.start must be \"rested\" or \"anywhere\", "
                               f"got {start!r}")
    if start == "anywhere" and table.get("start_polarization_c", 1.0) == 0:
        raise InputError(path, "estimator.start = \"anywhere\" needs "
                               "start_polarization_c above 0")
    kw: dict[str, Any] = {}
    for key, value in table.items():
        kind = known[key].type
        if kind == "bool":
            if not isinstance(value, bool):
                raise InputError(path, f"estimator.{key} must be true or false, got {value!r}")
        elif kind == "str":
            if not isinstance(value, str):
                raise InputError(path, f"estimator.{key} must be a string, got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(path, f"estimator.{key} must be a number, got {value!r}")
        kw[key] = float(value) if kind.startswith("float") else value
    try:        # the start-anywhere settings under the keys set here
        return start_settings(EstimatorConfig(**kw), start if start == "anywhere" else None,
                              set(kw))
    except ValueError as exc:
        raise InputError(path, f"estimator: {exc}") from None


@dataclass(frozen=True)
class BuildConfig:
    path: Path
    capacity_ah: float
    pulses: Path | None
    dcir: Path | None
    pulses_soc0: float | None     # None: from the OCV of the first rest (or 1.0)
    # [[data.pulse_tests]] (a model over temperature); the data.pulses form is one test
    # at an unknown temperature (and leaves this empty)
    pulse_tests: tuple["PulseTest", ...]
    ocv: Path | None              # the first OCV file; None: from the pulse-test rests
    ocv_soc0: float | None
    ocv_branch: str               # "auto" | "both" | "charge" | "discharge"
    cycle: Path | None
    soc0: float | None
    extra_cycles: tuple[Path, ...]
    columns: dict[str, Any] | None     # raw [data.columns] table, parsed by measure
    times_s: tuple[float, ...]
    c_rate: str | float           # "max", "all" or a C-rate
    min_rest_s: float             # a pulse follows at least this much rest
    max_pulse_s: float            # and lasts at most this long
    methods: tuple[str, ...]
    seed: int
    relax_s: float
    best: str
    ocv_sources: tuple = ()       # in merge order: "pulses" or a Path (data.ocv)
    ocv_cycle: int | None = None  # cycle of the low-rate test (1-based); None: the last
    ocv_rests_first: bool = True  # data.ocv_rests_first auto (ecmgen.data.ocv.rests_should_lead)
    c_prefix: str = "ecm"
    c_numeric: tuple[str, ...] = ("float", "fixed")
    c_dt_s: float | None = None
    c_estimator: str | None = None     # [c] estimator = "ekf": the SOC filter in the float C
    c_ocv_soc_step: int = 1            # [c]: the C's OCV on every n-th SOC breakpoint
    c_rc_soc_step: int = 1             # [c]: the C's RC tables likewise
    curve_branches: bool = False       # [fit]: curve fit with diffusion pair + Butler-Volmer
    temperature_step_c: float = 5.0    # [model]: 0 = the measured breakpoints as they are
    warm_row_c: float | None = 45.0    # [model]: derived warm row (None: none)
    surface_soc_gain: float | None = None   # [model]: lam of the surface SOC (0: off; None:
    #                                         the default, surface_soc_default)
    activation_k: float = 0.0          # [model]: Ea/R of a one-test model's resistances (0: off)
    max_mae_mv: float = 50.0           # [report]: the validation verdict's threshold
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    raw: dict = field(default_factory=dict, repr=False)
    # data.cycle_window_s: (t0, t1) for every validation file, or resolved file -> (t0, t1)
    cycle_window_s: tuple[float, float] | dict[Path, tuple[float, float]] | None = None
    # data.temperature_c: the cell temperature (degC) of files without a temperature
    # column, one for all or resolved file -> degC
    temperature_c: float | dict[Path, float] | None = None
    dynamic: bool = False         # data.dynamic: ``pulses`` is a dynamic test (its blocks)
    # a file's own column map, resolved file -> (its section, the table): a pulse test's
    # columns (for its file and steps), [data.columns.files] (over those)
    file_columns: dict[Path, tuple[str, dict]] = field(default_factory=dict)

    def window_for(self, path: Path) -> tuple[float, float] | None:
        """The time window (s, the file's own time axis) for a validation file, if any."""
        w = self.cycle_window_s
        if isinstance(w, dict):
            return w.get(Path(path).resolve())
        return w

    def temperature_for(self, path: Path) -> float | Path | None:
        """The configured cell temperature of a file without a temperature column: its
        entry in data.temperature_c (a number, or the Path of its time-stamped temperature
        log), data.temperature_c itself, or the temperature_c of the [[data.pulse_tests]]
        table it belongs to (None: none given)."""
        p = Path(path).resolve()
        t = self.temperature_c
        if isinstance(t, dict):
            if p in t:
                return t[p]
        elif t is not None:
            return t
        return next((test.temperature_c for test in self.pulse_tests
                     if p in (test.file, test.steps)), None)

    def input_files(self) -> set[Path]:
        """Every file the config names, itself included, resolved (outputs must never
        replace one)."""
        files = [self.path, self.pulses, self.dcir, self.ocv, self.cycle, *self.extra_cycles,
                 *(p for p in self.ocv_sources if p != "pulses"),
                 *(self.cycle_window_s if isinstance(self.cycle_window_s, dict) else ()),
                 *(self.temperature_c if isinstance(self.temperature_c, dict) else ()),
                 *(v for v in (self.temperature_c.values() if isinstance(
                     self.temperature_c, dict) else ()) if isinstance(v, Path))]
        for t in self.pulse_tests:
            files += [t.file, t.steps, t.ocv]
        judge = (self.raw.get("diagnose") or {}).get("judge") if isinstance(
            self.raw.get("diagnose"), dict) else None
        if isinstance(judge, str) and judge:
            files.append(self.path.resolve().parent / judge)
        return {Path(p).resolve() for p in files if p is not None}

    @property
    def over_temperature(self) -> bool:
        """True for the [[data.pulse_tests]] form (tables over temperature)."""
        return bool(self.pulse_tests)


@dataclass(frozen=True)
class PulseTest:
    """One ``[[data.pulse_tests]]`` entry: a pulse test at one temperature."""

    file: Path
    soc0: float | None            # None: from the OCV of its first rest (or 1.0)
    temperature_c: float | None   # None: the median cell temperature during its pulses
    steps: Path | None            # the SOC-step record between its pulse sets, if any
    ocv: Path | None              # None: from its own rests
    dynamic: bool = False         # a dynamic test (as data.dynamic), not a pulse test
    columns: dict | None = None   # its own column map (its file and steps)


def _table(d: dict, key: str, path: Path) -> dict:
    v = d.get(key, {})
    if not isinstance(v, dict):
        raise InputError(path, f"[{key}] must be a table")
    return v


def _number(d: dict, key: str, path: Path, where: str, default=None, *, positive=False,
            unit_interval=False):
    if key not in d:
        if default is None and positive:
            raise InputError(path, f"missing {where}.{key}")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(path, f"{where}.{key} must be a number, got {v!r}")
    if positive and v <= 0:
        raise InputError(path, f"{where}.{key} must be positive, got {v!r}")
    if unit_interval and not 0.0 <= v <= 1.0:
        raise InputError(path, f"{where}.{key} is a SOC and must lie in [0, 1], got {v!r}")
    return float(v)


def _file(base: Path, d: dict, key: str, path: Path, where: str = "data") -> Path | None:
    if key not in d:
        return None
    v = d[key]
    if not isinstance(v, str) or not v:
        raise InputError(path, f"{where}.{key} must be a file name")
    p = (base / v).resolve()
    if p.is_dir():
        raise InputError(path, f"{where}.{key} names a folder, not a file: {v} ({p})")
    if not p.is_file():
        raise InputError(path, f"{where}.{key} names a missing file: {v} (looked for {p})")
    return p


def _window(value, path: Path, where: str) -> tuple[float, float]:
    ok = (isinstance(value, list) and len(value) == 2 and
          all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
              for v in value))
    if not ok:
        raise InputError(path, f"{where} must be [t0, t1], two times in s, got {value!r}")
    t0, t1 = float(value[0]), float(value[1])
    if not t0 < t1:
        raise InputError(path, f"{where} = [{t0:g}, {t1:g}]: the start must come before "
                               f"the end")
    return t0, t1


def _named_file(name: str, base: Path, path: Path, key: str, known: list[Path]) -> Path:
    """The file a per-file table's key names: a path relative to the config, or else the
    base name of exactly one of the files the config names elsewhere (``known``), so a
    key need not repeat a path exactly as written in another key."""
    p = (base / name).resolve()
    if p.is_file():
        return p
    same = {k.resolve() for k in known if k is not None and k.name == Path(name).name}
    if len(same) == 1:
        return same.pop()
    why = (f"{len(same)} files of the config are named {Path(name).name}: give the path"
           if same else f"looked for {p}")
    raise InputError(path, f"{key} names a missing file: {name} ({why})")


def _cycle_windows(data: dict, base: Path, path: Path, known: list[Path]):
    """data.cycle_window_s: [t0, t1] for every validation file, or a table naming files."""
    if "cycle_window_s" not in data:
        return None
    value = data["cycle_window_s"]
    if not isinstance(value, dict):
        return _window(value, path, "data.cycle_window_s")
    windows = {}
    for name, w in value.items():
        p = _named_file(name, base, path, "data.cycle_window_s", known)
        windows[p] = _window(w, path, f"data.cycle_window_s.{name!r}")
    return windows


def _temperatures(data: dict, base: Path, path: Path, known: list[Path]):
    """data.temperature_c: the cell temperature of every file without a temperature
    column, or a table of them by file."""
    value = data.get("temperature_c")
    if value is None or not isinstance(value, dict):
        return value if value is None else float(value)
    lo, hi = TEMPERATURE_RANGE_C
    temps = {}
    for name, t in value.items():
        where = f"data.temperature_c.{name!r}"
        if isinstance(t, str) and t:        # a time-stamped temperature log of that file
            temps[_named_file(name, base, path, "data.temperature_c", known)] = \
                _file(base, {name: t}, name, path, "data.temperature_c")
            continue
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not lo <= t <= hi:
            raise InputError(path, f"{where} must be a temperature in {lo:g}..{hi:g} degC "
                                   f"or a temperature log (a file name), got {t!r}")
        temps[_named_file(name, base, path, "data.temperature_c", known)] = float(t)
    return temps




def _file_columns(columns: dict | None, tests: tuple[PulseTest, ...], base: Path,
                  path: Path, known: list[Path]) -> dict[Path, tuple[str, dict]]:
    """Each file's own column map: a pulse test's columns for its file and steps, then
    [data.columns.files] by file name (over a test's)."""
    own: dict[Path, tuple[str, dict]] = {}
    for n, test in enumerate(tests, 1):
        if test.columns is not None:
            for p in (test.file, test.steps):
                if p is not None:
                    own[p] = (f"data.pulse_tests[{n}].columns", test.columns)
    for name, table in ((columns or {}).get("files") or {}).items():
        p = _named_file(name, base, path, "[data.columns.files]", known)
        own[p] = (f"[data.columns.files.{name!r}]", table)
    return own


def _pulse_tests(data: dict, base: Path, path: Path, ocv: Path | None
                 ) -> tuple[PulseTest, ...]:
    """The [[data.pulse_tests]] entries (``ocv``: the data.ocv file, None for "pulses")."""
    raw = data["pulse_tests"]
    if not isinstance(raw, list) or not raw or not all(isinstance(e, dict) for e in raw):
        raise InputError(path, "data.pulse_tests must be one or more [[data.pulse_tests]] "
                               "tables (file = \"hppc.mat\", ...)")
    tests: list[PulseTest] = []
    for n, entry in enumerate(raw, 1):
        where = f"data.pulse_tests[{n}]"
        if "file" not in entry:
            raise InputError(path, f"{where}: missing file (the pulse test)")
        file = _file(base, entry, "file", path, where)
        temp = _number(entry, "temperature_c", path, where)
        lo, hi = TEMPERATURE_RANGE_C
        if temp is not None and not lo <= temp <= hi:
            raise InputError(path, f"{where}.temperature_c must lie in {lo:g}..{hi:g} degC, "
                                   f"got {temp:g}")
        test_ocv = ocv
        if "ocv" in entry:
            test_ocv = None if entry["ocv"] == "pulses" else _file(base, entry, "ocv", path,
                                                                   where)
        test = PulseTest(file=file, soc0=_number(entry, "soc0", path, where,
                                                 unit_interval=True),
                         temperature_c=temp, steps=_file(base, entry, "steps", path, where),
                         ocv=test_ocv, dynamic=entry.get("dynamic", False),
                         columns=entry.get("columns"))
        for k, other in enumerate(tests, 1):
            if other.file == file:
                raise InputError(path, f"{where} names the same file as "
                                       f"data.pulse_tests[{k}]: {entry['file']}")
            if temp is not None and other.temperature_c is not None and \
                    abs(other.temperature_c - temp) < 0.5:
                raise InputError(path, f"{where}.temperature_c = {temp:g} is within 0.5 K of "
                                       f"data.pulse_tests[{k}]: one test per temperature")
        tests.append(test)
    return tuple(tests)


def load_config(path: str | Path) -> BuildConfig:
    """Read and check a build config; any problem is an InputError naming the file."""
    with reading(path):
        return _load_config(Path(path))


def _load_config(path: Path) -> BuildConfig:
    """The config's sections in a fixed order (the first problem found is the one named):
    the schema, [cell], [data], [dcir], [fit], [c], [model], then the files and tables
    that name other files."""
    raw = _parsed(path)
    base = path.resolve().parent
    cell, data = _table(raw, "cell", path), _table(raw, "data", path)
    dcir_t, fit, c = _table(raw, "dcir", path), _table(raw, "fit", path), _table(raw, "c", path)
    model_t = _table(raw, "model", path)
    capacity = _number(cell, "capacity_ah", path, "cell", positive=True)
    inputs = _data_inputs(data, base, path)
    settings = _dcir_settings(dcir_t, path)
    settings.update(_fit_settings(fit, inputs, path))
    settings.update(_c_settings(c, path))
    settings.update(_model_settings(model_t, inputs["pulse_tests"], path))
    cycle = _file(base, data, "cycle", path)
    known = [inputs["pulses"], inputs["ocv"], cycle, *inputs["extra_cycles"],
             *(p for t in inputs["pulse_tests"] for p in (t.file, t.steps, t.ocv)),
             *(s for s in inputs["ocv_sources"] if s != "pulses")]
    return BuildConfig(
        path=path, capacity_ah=capacity, cycle=cycle, **inputs, **settings,
        max_mae_mv=_number(raw.get("report", {}), "max_mae_mv", path, "report", 50.0,
                           positive=True),
        estimator=estimator_config(raw.get("estimator", {}), path),
        raw=raw, cycle_window_s=_cycle_windows(data, base, path, known),
        temperature_c=_temperatures(data, base, path, known),
        file_columns=_file_columns(inputs["columns"], inputs["pulse_tests"], base, path,
                                   known))


def _parsed(path: Path) -> dict:
    """The config file read as TOML and checked against the schema (every section and key
    known, of its type and in its range)."""
    if path.is_dir():
        raise InputError(path, "is a folder; give the config file (a .toml)")
    try:
        # utf-8-sig: a byte order mark (Windows editors write one) is not TOML's error
        raw = tomllib.loads(path.read_bytes().decode("utf-8-sig"))
    except FileNotFoundError:
        raise InputError(path, "no such config file") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                               f"{exc.start}); TOML files are UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from None
    try:
        check_config(raw)
    except SchemaError as exc:
        raise InputError(path, str(exc)) from None
    return raw


def _data_inputs(data: dict, base: Path, path: Path) -> dict[str, Any]:
    """[data] but the validation cycle and the per-file tables: the pulse test (or DC-IR
    table, dynamic test, pulse tests over temperature), the OCV sources, the extra cycles
    and the column map, as BuildConfig's fields."""
    pulses = _file(base, data, "pulses", path)
    dcir = _file(base, data, "dcir", path)
    dynamic = _file(base, data, "dynamic", path)
    several = "pulse_tests" in data
    if (pulses is not None) + (dcir is not None) + (dynamic is not None) + several != 1:
        raise InputError(path, "give exactly one of data.pulses (a pulse test), "
                               "[[data.pulse_tests]] (pulse tests at several temperatures), "
                               "data.dynamic (a drive profile with rests) or data.dcir (a "
                               "soc,direction,c_rate,t_s,r_ohm table)")
    if dynamic is not None:         # read and fitted as the pulse test is, by its blocks
        pulses = dynamic
    if several and "pulses_soc0" in data:
        raise InputError(path, "data.pulses_soc0 goes with data.pulses; give soc0 in each "
                               "[[data.pulse_tests]] table")
    sources = _ocv_sources(data, base, path, pulses, several)
    ocv = next((s for s in sources if s != "pulses"), None)
    ocv_cycle = data.get("ocv_cycle")
    if ocv_cycle is not None and (isinstance(ocv_cycle, bool) or not isinstance(ocv_cycle, int)
                                  or ocv_cycle < 1):
        raise InputError(path, f"data.ocv_cycle must be a cycle number from 1, got {ocv_cycle!r}")
    pulse_tests = _pulse_tests(data, base, path, ocv) if several else ()
    branch = data.get("ocv_branch", "auto")
    if branch not in ("auto", "both", "charge", "discharge"):
        raise InputError(path, "data.ocv_branch must be auto, both, charge or discharge, "
                               f"got {branch!r}")
    rests_first = data.get("ocv_rests_first", "auto")
    if rests_first not in ("auto", "never"):
        raise InputError(path, f"data.ocv_rests_first must be auto or never, got {rests_first!r}")
    extra = data.get("extra_cycles", [])
    if not isinstance(extra, list):
        raise InputError(path, "data.extra_cycles must be a list of file names")
    extra_paths = tuple(_file(base, {"extra_cycles": e}, "extra_cycles", path) for e in extra)
    return dict(
        pulses=pulses, dcir=dcir, dynamic=dynamic is not None,
        pulses_soc0=_number(data, "pulses_soc0", path, "data", None, unit_interval=True),
        pulse_tests=pulse_tests, ocv=ocv, ocv_sources=tuple(sources), ocv_cycle=ocv_cycle,
        ocv_soc0=_number(data, "ocv_soc0", path, "data", unit_interval=True),
        ocv_branch=branch, ocv_rests_first=rests_first == "auto",
        soc0=_number(data, "soc0", path, "data", unit_interval=True),
        extra_cycles=extra_paths, columns=_columns(data, path))


def _ocv_sources(data: dict, base: Path, path: Path, pulses: Path | None, several: bool
                 ) -> list:
    """data.ocv in merge order: "pulses" (the pulse tests' rests) or a file."""
    ocv_raw = data.get("ocv", "pulses" if several else None)
    if ocv_raw is None:
        raise InputError(path, "missing data.ocv (a soc,ocv_v table, a low-rate test, "
                               "\"pulses\" for the rests of the pulse test, or a list of them)")
    names = ocv_raw if isinstance(ocv_raw, list) else [ocv_raw]
    if not names or not all(isinstance(n, str) and n for n in names):
        raise InputError(path, "data.ocv must be a file name, \"pulses\" or a non-empty list "
                               "of them")
    if len(set(names)) != len(names):
        raise InputError(path, "data.ocv names a source twice")
    sources: list = []
    for name in names:
        if name == "pulses":
            if pulses is None and not several:
                raise InputError(path, "data.ocv = \"pulses\" needs data.pulses")
            sources.append("pulses")
        else:
            sources.append(_file(base, {"ocv": name}, "ocv", path))
    return sources


def _columns(data: dict, path: Path) -> dict | None:
    """The raw [data.columns] table (ecmgen.data.columns reads it); its sub-tables are file
    roles (or [data.columns.files])."""
    columns = data.get("columns")
    if columns is not None and not isinstance(columns, dict):
        raise InputError(path, "[data.columns] must be a table")
    for key, value in (columns or {}).items():
        if isinstance(value, dict) and key not in COLUMN_ROLES and key != "files":
            raise InputError(path, f"[data.columns.{key}]: {key!r} is not a file role "
                                   f"(one of {', '.join(COLUMN_ROLES)})")
    return columns


def _dcir_settings(dcir_t: dict, path: Path) -> dict[str, Any]:
    """[dcir]: the DC-IR times, the five-point fits' C-rate, how pulses are found."""
    times = dcir_t.get("times_s", [0.1, 1.0, 3.0, 6.0, 10.0])
    if (not isinstance(times, list) or len(times) < 4 or
            not all(isinstance(t, (int, float)) and t > 0 for t in times) or
            any(b <= a for a, b in zip(times, times[1:]))):
        raise InputError(path, "dcir.times_s must be at least 4 increasing positive times in s")
    c_rate = dcir_t.get("c_rate", "max")
    if not (c_rate in ("max", "all") or (isinstance(c_rate, (int, float)) and c_rate > 0)):
        raise InputError(path, f"dcir.c_rate must be \"max\", \"all\" or a C-rate, got {c_rate!r}")
    return dict(times_s=tuple(float(t) for t in times),
                c_rate=c_rate if isinstance(c_rate, str) else float(c_rate),
                min_rest_s=_number(dcir_t, "min_rest_s", path, "dcir", 30.0),
                max_pulse_s=_number(dcir_t, "max_pulse_s", path, "dcir", 120.0, positive=True))


def _fit_settings(fit: dict, inputs: dict[str, Any], path: Path) -> dict[str, Any]:
    """[fit]: the methods (their defaults from what [data] gives), the seed, the curve
    fit's branches and relaxation, the best method."""
    # the whole-curve fit needs the pulse test itself, a DC-IR table is not enough
    has_pulses = inputs["pulses"] is not None or bool(inputs["pulse_tests"])
    any_dynamic = inputs["dynamic"] or any(t.dynamic for t in inputs["pulse_tests"])
    methods = fit.get("methods", (["curve"] if any_dynamic else list(METHODS))
                      if has_pulses else ["ga", "lm"])
    if not isinstance(methods, list) or not methods or any(m not in METHODS for m in methods):
        raise InputError(path, f"fit.methods must be a non-empty list from {list(METHODS)}")
    if any_dynamic and methods != ["curve"]:
        # ga and lm fit DC-IR points of pulse edges from rest; a drive profile has none
        raise InputError(path, "fit.methods: a dynamic test (data.dynamic, or dynamic = true "
                               "in [[data.pulse_tests]]) is fitted by the curve method only "
                               "(ga and lm need the pulses of a pulse test)")
    if "curve" in methods and not has_pulses:
        raise InputError(path, "fit method \"curve\" needs the pulse test (data.pulses), "
                               "not only a DC-IR table")
    seed = fit.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise InputError(path, f"fit.seed must be a non-negative integer, got {seed!r}")
    branches = fit.get("curve_branches", True)
    if not isinstance(branches, bool):
        raise InputError(path, f"fit.curve_branches must be true or false, got {branches!r}")
    best = fit.get("best", "curve" if "curve" in methods else methods[-1])
    if best not in methods:
        raise InputError(path, f"fit.best = {best!r} is not one of fit.methods {methods}")
    return dict(methods=tuple(methods), seed=seed, curve_branches=branches, best=best,
                relax_s=_number(fit, "relax_s", path, "fit", 1800.0, positive=True))


def _c_settings(c: dict, path: Path) -> dict[str, Any]:
    """[c]: the numerics, the symbol prefix, the step, the estimator, the tables' grids."""
    numeric = c.get("numeric", ["float", "fixed"])
    if isinstance(numeric, str):
        numeric = [numeric]
    if not isinstance(numeric, list) or any(n not in ("float", "fixed") for n in numeric):
        raise InputError(path, "c.numeric must be \"float\", \"fixed\" or a list of them")
    prefix = c.get("prefix", "ecm")
    problem = c_prefix_problem(prefix)
    if problem:
        raise InputError(path, f"c.{problem}")
    c_estimator = c.get("estimator", "none")
    if c_estimator not in C_ESTIMATORS:
        raise InputError(path, f"c.estimator must be one of {', '.join(map(repr, C_ESTIMATORS))}, "
                               f"got {c_estimator!r}")
    if c_estimator != "none":
        if "float" not in numeric:
            raise InputError(path, "c.estimator needs c.numeric \"float\": the C estimator "
                                   "is float32 only")
        if c.get("dt_s") is not None:
            raise InputError(path, "c.estimator needs the variable-dt step: leave c.dt_s unset")
    return dict(c_prefix=prefix, c_numeric=tuple(numeric),
                c_dt_s=_number(c, "dt_s", path, "c", None),
                c_estimator=None if c_estimator == "none" else c_estimator,
                c_ocv_soc_step=int(c.get("ocv_soc_step", 1)),
                c_rc_soc_step=int(c.get("rc_soc_step", 1)))


def _model_settings(model_t: dict, pulse_tests: tuple[PulseTest, ...], path: Path
                    ) -> dict[str, Any]:
    """[model]: the temperature grid, the derived warm row, the surface SOC, Ea/R."""
    step = _number(model_t, "temperature_step_c", path, "model", 5.0)
    if not 0.0 <= step <= 50.0:
        raise InputError(path, f"model.temperature_step_c must lie in 0..50 K (0: the "
                               f"measured breakpoints), got {step:g}")
    warm = model_t.get("warm_row_c", 45.0)
    if warm is not False:
        warm = _number(model_t, "warm_row_c", path, "model", 45.0)
        lo, hi = TEMPERATURE_RANGE_C
        if not lo <= warm <= hi:
            raise InputError(path, f"model.warm_row_c must lie in {lo:g}..{hi:g} degC (or "
                                   f"false: no derived warm row), got {warm:g}")
    gain = _number(model_t, "surface_soc_gain", path, "model", None)
    # the model stage's bound (ecmgen.model.model.SURFACE_SOC_GAIN_MAX; the config is
    # below it in the pipeline, a test holds the two equal)
    if gain is not None and not 0.0 <= gain <= SURFACE_SOC_GAIN_MAX:
        raise InputError(path, f"model.surface_soc_gain must lie in 0..{SURFACE_SOC_GAIN_MAX:g} "
                               f"(0: off), got {gain:g}")
    activation = _number(model_t, "activation_k", path, "model", 0.0)  # range: the schema's
    if activation and len(pulse_tests) > 1:
        raise InputError(path, "model.activation_k is for a model from one pulse test: over "
                               "temperature the tables follow the tests")
    return dict(temperature_step_c=step, warm_row_c=None if warm is False else warm,
                surface_soc_gain=gain, activation_k=activation)
