"""The `build` chain: config -> measurements -> DC-IR -> fits -> model.json -> validation.

It strings the stages together: :mod:`ecmgen.data` (files, DC-IR table, OCV),
:mod:`ecmgen.fit` (GA, LM, whole-curve), :mod:`ecmgen.model` (model.json, validation),
:mod:`ecmgen.c` (the C of the best model), :mod:`ecmgen.plots` / :mod:`ecmgen.report`;
``run_diagnose`` does the same for :mod:`ecmgen.diagnosis`. Each function is callable
from a notebook; the CLI only parses arguments and prints.
Outputs are staged in a temporary folder and moved into place only when everything
succeeded, so a failure leaves no half-written output.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .config import COLUMN_ROLE_FALLBACK, WINDOW_ROLES, BuildConfig
from .data import dcir as dcir_mod
from .data.measure import ColumnMap, TimeSeries, read_timeseries
from .data.ocv import (OcvTable, looks_like_ocv_table, ocv_from_low_rate, ocv_from_pulse_rests,
                       read_ocv_table)
from .errors import InputError
from .files import file_sha256
from .model.model import RC_FIELDS, EcmModel, InputRecord, RcTable
from .model.simulate import Validation, validate

Progress = Callable[[str], None]

SOC_LEVEL_GAP = 0.025   # pulses closer than this in SOC belong to one pulse set


def _quiet(_msg: str) -> None:
    pass


def stderr_progress(msg: str) -> None:
    print(f"[ecmgen] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Inputs:
    """Everything read and derived from the measurement files, before fitting."""

    capacity_ah: float
    ocv: OcvTable
    dcir: dcir_mod.DcirTable
    pulses_series: TimeSeries | None
    pulses: tuple[dcir_mod.Pulse, ...]
    records: tuple[InputRecord, ...]
    notes: tuple[str, ...]


@dataclass
class BuildResult:
    models: dict[str, EcmModel]
    best: str
    inputs: Inputs
    validations: dict[str, dict[str, Validation]] = field(default_factory=dict)
    curve_fit: object | None = None
    point_fits: dict[str, object] = field(default_factory=dict)
    point_table: dcir_mod.DcirTable | None = None
    out_dir: Path | None = None
    files: list[Path] = field(default_factory=list)
    c_report: dict | None = None


def read_series(cfg: BuildConfig, path: Path, role: str = "") -> TimeSeries:
    """Read a measurement file of the config. ``[data.columns]`` maps CSV columns from
    another cycler, for every CSV; ``[data.columns.<role>]`` extends it for one file role
    (``extra_cycles`` and ``judge`` fall back to ``cycle``'s); .mat files carry their own
    names. A validation file is cut to ``data.cycle_window_s`` when the config gives one."""
    roles = (role, COLUMN_ROLE_FALLBACK[role]) if role in COLUMN_ROLE_FALLBACK else (role,)
    columns = ColumnMap.for_file(cfg.columns, roles, cfg.path, path)
    series = read_timeseries(path, columns, capacity_ah=cfg.capacity_ah)
    window = cfg.window_for(path) if role in WINDOW_ROLES else None
    return series if window is None else series.window(*window)


def prepare(cfg: BuildConfig, progress: Progress = _quiet) -> Inputs:
    """Read the measurement files; extract pulses, the DC-IR table and the OCV."""
    notes: list[str] = []
    records: list[InputRecord] = []
    q = cfg.capacity_ah
    ocv = None
    if cfg.ocv is not None and looks_like_ocv_table(cfg.ocv):
        ocv = read_ocv_table(cfg.ocv)
        records.append(InputRecord("ocv", cfg.ocv.name, file_sha256(cfg.ocv)))
    elif cfg.ocv is not None:
        progress(f"reading low-rate OCV test {cfg.ocv.name}")
        low = read_series(cfg, cfg.ocv, "ocv")
        records.append(InputRecord("ocv", cfg.ocv.name, file_sha256(cfg.ocv)))
        ocv, n = ocv_from_low_rate(low, q, cfg.ocv_soc0, branch=cfg.ocv_branch)
        notes.extend(n)

    series, pulses = None, ()
    if cfg.pulses is not None:
        progress(f"reading pulse test {cfg.pulses.name}")
        series = read_series(cfg, cfg.pulses, "pulses")
        records.append(InputRecord("pulses", cfg.pulses.name, file_sha256(cfg.pulses)))
        soc0 = cfg.pulses_soc0
        if soc0 is None and ocv is not None:
            from .model.simulate import rested_soc

            try:
                soc0 = rested_soc(ocv, q, series)
                notes.append(f"pulse test start SOC {soc0:.3f} from the OCV of its first "
                             "rested voltage (set data.pulses_soc0 to override)")
            except InputError:
                soc0 = 1.0  # a record that never rests has no pulses: find_pulses says so
        elif soc0 is None:
            soc0 = 1.0
            notes.append("pulse test assumed to start at SOC 1.0 (set data.pulses_soc0)")
        pulses = tuple(dcir_mod.find_pulses(series, q, soc0=soc0, min_rest_s=cfg.min_rest_s,
                                            max_pulse_s=cfg.max_pulse_s))
        table = dcir_mod.extract_dcir(series, list(pulses), cfg.times_s)
        notes.extend(table.notes)
        progress(f"{len(pulses)} pulses, {len(table)} DC-IR rows")
        if ocv is None:
            ocv, n = ocv_from_pulse_rests(series, pulses, q, soc0)
            notes.extend(n)
    else:
        table = dcir_mod.read_dcir_csv(cfg.dcir)
        records.append(InputRecord("dcir", cfg.dcir.name, file_sha256(cfg.dcir)))
    return Inputs(q, ocv, table, series, pulses, tuple(records), tuple(notes))


def point_rows(table: dcir_mod.DcirTable, c_rate) -> tuple[dcir_mod.DcirTable, list[str]]:
    """The rows the five-point fits use: one per SOC level and direction.

    ``c_rate="max"``: the highest C-rate of each direction (the paper's choice);
    a number: the nearest C-rate; ``"all"``: R(t) averaged over the C-rates of a level."""
    notes: list[str] = []
    keep = np.zeros(len(table), bool)
    for d in ("charge", "discharge"):
        in_d = table.direction == d
        if not in_d.any():
            continue
        rates = np.unique(table.c_rate[in_d])
        if c_rate == "all":
            keep |= in_d
            continue
        pick = rates.max() if c_rate == "max" else rates[np.argmin(np.abs(rates - c_rate))]
        keep |= in_d & (table.c_rate == pick)
        notes.append(f"five-point fits use the {pick:g}C {d} pulses")
    sel = table.select(keep)
    # merge rows of one SOC level (one pulse set) and direction
    soc, direction, rate, r = [], [], [], []
    for d in ("charge", "discharge"):
        ix = np.flatnonzero(sel.direction == d)
        ix = ix[np.argsort(-sel.soc[ix])]
        groups: list[list[int]] = []
        for k in ix:
            if groups and abs(sel.soc[groups[-1][0]] - sel.soc[k]) <= SOC_LEVEL_GAP:
                groups[-1].append(k)
            else:
                groups.append([k])
        for g in groups:
            soc.append(float(np.mean(sel.soc[g])))
            direction.append(d)
            rate.append(float(np.mean(sel.c_rate[g])))
            r.append(_mean_of_finite(sel.r_ohm[g]))
    if c_rate == "all":
        notes.append("five-point fits use R(t) averaged over all C-rates of each SOC level")
    out = dcir_mod.DcirTable(np.array(soc), np.array(direction), np.array(rate), table.t_s,
                             np.array(r), table.notes)
    return out, notes


def _mean_of_finite(rows: np.ndarray) -> np.ndarray:
    """Column means over the finite values; NaN where a column has none (a DC-IR time no
    pulse of the group reached), without numpy's "Mean of empty slice" warning."""
    ok = np.isfinite(rows)
    n = ok.sum(axis=0)
    total = np.where(ok, rows, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _rc_tables(soc, direction, cols: dict[str, np.ndarray], fit_error, converged,
               source: Path | None = None) -> tuple[RcTable, RcTable, list[str]]:
    """Per-direction RcTables; a direction without data takes the other's, with a note."""
    tables, notes = {}, []
    for d in ("charge", "discharge"):
        ix = np.flatnonzero((direction == d) & np.all(np.isfinite(np.vstack(list(cols.values()))), axis=0))
        if ix.size == 0:
            continue
        ix = ix[np.argsort(soc[ix])]
        s = np.clip(soc[ix], 0.0, 1.0)
        ok = np.concatenate(([True], np.diff(s) > 1e-6))
        ix = ix[ok]
        tables[d] = RcTable(soc=np.clip(soc[ix], 0, 1), fit_error=np.asarray(fit_error)[ix],
                            converged=np.asarray(converged)[ix],
                            **{k: np.asarray(v)[ix] for k, v in cols.items()})
    if not tables:
        raise InputError(source, "no table cell could be fitted: no SOC level has an R(t) "
                                 "value at every [dcir] times_s (pulses cut short, or too "
                                 "short or too slowly logged for those times? [dcir] "
                                 "c_rate = \"all\" uses every C-rate)")
    for d, other in (("charge", "discharge"), ("discharge", "charge")):
        if d not in tables:
            tables[d] = tables[other]
            notes.append(f"the test has {other} pulses only: the {d} parameters are the "
                         f"{other} parameters")
    return tables["charge"], tables["discharge"], notes


def fit_models(cfg: BuildConfig, inputs: Inputs, progress: Progress = _quiet
               ) -> tuple[dict[str, EcmModel], dict]:
    """Fit every method of the config; returns the models and the raw fits (for plots)."""
    from .fit.ga import fit_ga
    from .fit.lm import fit_lm

    models: dict[str, EcmModel] = {}
    raw: dict = {}
    common = dict(capacity_ah=inputs.capacity_ah, ocv=inputs.ocv, seed=cfg.seed,
                  inputs=inputs.records, direction_deadband_a=0.01 * inputs.capacity_ah)
    point_methods = [m for m in cfg.methods if m in ("ga", "lm")]
    if point_methods:
        rows, n = point_rows(inputs.dcir, cfg.c_rate)
        raw["point_table"] = rows
        fits = {}
        if "ga" in point_methods:
            progress(f"GA fit of {len(rows)} table cells (seed {cfg.seed})")
            fits["ga"] = fit_ga(rows.t_s, rows.r_ohm, seed=cfg.seed)
        if "lm" in point_methods:
            # on its own (multi-start), as the paper compares the two methods; started
            # from the GA it would keep the GA's Eq.-5 optimum (fit_lm's guarantee)
            progress("Levenberg-Marquardt fit (casadi Jacobian, multi-start)")
            fits["lm"] = fit_lm(rows.t_s, rows.r_ohm)
        for m in point_methods:
            f = fits[m]
            cols = {k: getattr(f, k) for k in RC_FIELDS}
            ch, dis, n2 = _rc_tables(rows.soc, rows.direction, cols, f.fitness_ohm,
                                     f.converged, cfg.pulses or cfg.dcir)
            bad = int(np.sum(~f.converged))
            n3 = [f"{m}: {bad} of {f.converged.size} table cells did not converge"] if bad else []
            models[m] = EcmModel(charge=ch, discharge=dis, method=m,
                                 notes=inputs.notes + tuple(n) + tuple(n2) + tuple(n3), **common)
        raw["point_fits"] = fits
    if "curve" in cfg.methods:
        from .fit.curve import fit_pulse_curves

        progress(f"whole-curve fit of {len(inputs.pulses)} pulses with {cfg.relax_s:g} s "
                 "of relaxation each")
        cf = fit_pulse_curves(inputs.pulses_series, list(inputs.pulses), inputs.ocv,
                              inputs.capacity_ah, relax_s=cfg.relax_s,
                              progress=lambda k, n: progress(f"  curve fit level {k}/{n}"))
        cols = {k: getattr(cf, k) for k in RC_FIELDS}
        bad = ~cf.converged
        if bad.all():
            raise InputError(cfg.pulses, "the whole-curve fit resolved no SOC level "
                                         "(time constants outside 0.2 s .. 3000 s?)")
        n_bad = [f"curve: SOC level {s:.3f} ({d}) not resolved (a time constant on its "
                 "search bound): left out, its neighbours are interpolated"
                 for s, d in zip(cf.soc[bad], cf.direction[bad])]
        cols = {k: np.where(bad, np.nan, v) for k, v in cols.items()}
        ch, dis, n2 = _rc_tables(cf.soc, cf.direction, cols, cf.rms_error_v, cf.converged,
                                 cfg.pulses)
        n2 = n_bad + n2
        models["curve"] = EcmModel(charge=ch, discharge=dis, method="curve",
                                   notes=inputs.notes + tuple(n2), **common)
        raw["curve_fit"] = cf
    return models, raw


def validate_all(cfg: BuildConfig, models: dict[str, EcmModel], progress: Progress = _quiet
                 ) -> dict[str, dict[str, Validation]]:
    """Each model on the config's validation cycle(s); ``soc0`` applies to every cycle."""
    cycles = ([(cfg.cycle, "cycle")] if cfg.cycle else []) + \
        [(p, "extra_cycles") for p in cfg.extra_cycles]
    out: dict[str, dict[str, Validation]] = {m: {} for m in models}
    for path, role in cycles:
        progress(f"validating on {path.name}")
        series = read_series(cfg, path, role)
        for m, model in models.items():
            out[m][path.name] = validate(model, series, cfg.soc0)
    return out


def build(cfg: BuildConfig, out_dir: str | Path, progress: Progress = _quiet, *,
          plots: bool = True, c_code: bool = True) -> BuildResult:
    """Run the whole chain and write the outputs into ``out_dir``."""
    out_dir = Path(out_dir).resolve()
    given = {p.resolve() for p in (cfg.path, cfg.pulses, cfg.dcir, cfg.ocv, cfg.cycle,
                                   *cfg.extra_cycles) if p is not None}
    inputs = prepare(cfg, progress)
    models, raw = fit_models(cfg, inputs, progress)
    result = BuildResult(models=models, best=cfg.best, inputs=inputs,
                         curve_fit=raw.get("curve_fit"), point_fits=raw.get("point_fits", {}),
                         point_table=raw.get("point_table"))
    result.validations = validate_all(cfg, models, progress)

    with _staged(out_dir, given) as (staging, files):
        inputs.dcir.write_csv(staging / "dcir.csv")
        for m, model in models.items():
            model.save(staging / f"model-{m}.json")
        models[cfg.best].save(staging / "model.json")
        if c_code and cfg.c_numeric:
            result.c_report = _write_c(cfg, result, staging, progress)
        if plots:
            from .plots import write_build_plots

            progress("writing plots")
            write_build_plots(result, staging)
        from .report import write_build_report

        write_build_report(cfg, result, staging)
    result.files = files
    result.out_dir = out_dir
    return result


def _write_c(cfg: BuildConfig, result: BuildResult, staging: Path, progress: Progress):
    """Generate C for the best model (if the code generator is installed) and check it."""
    try:
        from .c.check import build_c_outputs
    except ImportError:
        return None
    return build_c_outputs(cfg, result, staging, progress)


@contextmanager
def _staged(out_dir: Path, given: set[Path]):
    """Yield (staging folder, list of final paths); on success the staged files move into
    out_dir (the list is filled), on any error nothing reaches out_dir."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".ecmgen-staging-", dir=out_dir.parent))
    files: list[Path] = []
    try:
        yield staging, files
        files.extend(_commit(staging, out_dir, given))
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _commit(staging: Path, out_dir: Path, given: set[Path]) -> list[Path]:
    """Move the staged files into out_dir; refuse to replace any file the user gave."""
    staged = [p for p in sorted(staging.rglob("*")) if p.is_file()]
    targets = [out_dir / p.relative_to(staging) for p in staged]
    for t in targets:
        if t.resolve() in given:
            raise InputError(t, "output would overwrite an input file; choose another --out")
    out_dir.mkdir(parents=True, exist_ok=True)
    for src, dst in zip(staged, targets):
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(src), str(dst))
    return targets


def run_diagnose(cfg: BuildConfig, out_dir: str | Path, progress: Progress = _quiet, *,
                 plots: bool = True):
    """`diagnose` from a build config: fit the base model (method ``fit.best``), look for
    missing effects on ``data.cycle`` (judged on ``[diagnose] judge`` or on the held-out
    end of the cycle), and write the augmented model, plots and report into out_dir."""
    from .diagnosis.output import write_diagnose_outputs
    from .diagnosis.search import diagnose, diagnose_options

    options = diagnose_options(cfg.raw.get("diagnose"), cfg.path)
    judge_name = options.pop("judge")
    if cfg.cycle is None:
        raise InputError(cfg.path, "diagnose needs data.cycle (the record to diagnose on)")
    judge_path = None
    if judge_name is not None:
        judge_path = (cfg.path.resolve().parent / judge_name).resolve()
        if not judge_path.is_file():
            raise InputError(cfg.path, f"diagnose.judge names a missing file: {judge_name}")
    out_dir = Path(out_dir).resolve()
    given = {p.resolve() for p in (cfg.path, cfg.pulses, cfg.dcir, cfg.ocv, cfg.cycle,
                                   judge_path, *cfg.extra_cycles) if p is not None}
    inputs = prepare(cfg, progress)
    fit_cfg = cfg if cfg.methods == (cfg.best,) else _only_method(cfg, cfg.best)
    models, _ = fit_models(fit_cfg, inputs, progress)
    base = models[cfg.best]
    fit_series = read_series(cfg, cfg.cycle, "cycle")
    judge = read_series(cfg, judge_path, "judge") if judge_path is not None else None
    result = diagnose(base, fit_series, judge, soc0=cfg.soc0, progress=progress, **options)

    with _staged(out_dir, given) as (staging, files):
        base.save(staging / "model-base.json")
        write_diagnose_outputs(result, staging, plots=plots)
    return result, out_dir, files


def _only_method(cfg: BuildConfig, method: str) -> BuildConfig:
    from dataclasses import replace

    return replace(cfg, methods=(method,))
