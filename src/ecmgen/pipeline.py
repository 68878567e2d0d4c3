"""The `build` chain: config -> measurements -> DC-IR -> fits -> model.json -> validation.

It strings the stages together: :mod:`ecmgen.data` (files, DC-IR table, OCV),
:mod:`ecmgen.fit` (GA, LM, whole-curve), :mod:`ecmgen.model` (model.json, validation),
:mod:`ecmgen.c` (the C of the best model), :mod:`ecmgen.plots` / :mod:`ecmgen.report`;
``run_diagnose`` does the same for :mod:`ecmgen.diagnosis`. Each function is callable
from a notebook; the CLI only parses arguments and prints. Outputs are staged in a
temporary folder and moved into place only when all succeeded: no half-written output.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .config import SURFACE_SOC_GAIN_OVER_TEMPERATURE, BuildConfig, PulseTest
from .data import dcir as dcir_mod
from .data.dynamic import dynamic_levels
from .data.measure import TimeSeries
from .data.sign import check_sign
from .data.sources import (check_column_maps, check_pulse_label, check_temperature_logs,
                           ocv_file_curves, pulse_file_names, pulse_test_records, read_series)
from .data import ocv as ocv_mod
from .data.ocv import OcvTable
from .console import detail_of
from .errors import InputError
from .files import file_sha256, temperature_label
from .model.model import RC_FIELDS, EcmModel, InputRecord, RcTable
from .model.tables import copied_directions, level_tables
from .model.simulate import Validation
from .outputs import check_output_folder, staged
from .parallel import Workers, one_blas_thread
from .validation import (plot_files, record_usage, submit_c, validate_all, validation_plots,
                         validation_png_name)

Progress = Callable[[str], None]

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
    steps: TimeSeries | None = None     # SOC steps the pulse test left out (curve fit)
    ocv_report: ocv_mod.OcvReport | None = None
    soc_capacity_ah: float | None = None   # the pulse test's SOC axis (None: capacity_ah)


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
    tests: list["TestFit"] = field(default_factory=list)   # [[data.pulse_tests]]: per test
    timings: dict[str, float] = field(default_factory=dict)   # wall seconds per stage
    fit_flags: dict[str, list] = field(default_factory=dict)   # method -> [FitFlag]
    usage: dict[str, dict[str, dict]] = field(default_factory=dict)  # method -> cycle -> use
    notes: list[str] = field(default_factory=list)   # of the validation (SOC range, spans)
    quality: dict = field(default_factory=dict)      # method -> fit.quality.ModelQuality


def pulse_test_soc0(cfg: BuildConfig, series: TimeSeries, rests, reference: OcvTable | None,
                    given: float | None) -> tuple[float, str, float]:
    """Start SOC of one pulse test and the capacity of its SOC axis: ``given``
    (data.pulses_soc0) wins; else SOC 1.0 at the end of a constant-voltage charge it opens
    with; else both fitted on all its rests against ``reference`` (the OCV of the other
    sources); else 1.0. Returns (soc0, note, axis capacity in Ah)."""
    from .data.soc import opening_cv_charge, pulse_test_start_soc_and_capacity

    q = cfg.capacity_ah
    if given is not None:
        return given, "", q
    cv = opening_cv_charge(series, cfg.capacity_ah, max(0.02 * cfg.capacity_ah, 1e-3),
                           after_discharge=True)
    if cv is not None:
        return cv[0], (f"pulse test start SOC {cv[0]:.3f}: {cv[1]} (set data.pulses_soc0 "
                       f"to override)"), q
    if reference is not None and len(rests) >= 2:
        fit, q = pulse_test_start_soc_and_capacity(reference, q, rests, series.source)
        return fit.soc0, f"pulse test {fit.note} (set data.pulses_soc0 to override)", q
    return 1.0, "pulse test assumed to start at SOC 1.0 (set data.pulses_soc0)", q


def prepare(cfg: BuildConfig, progress: Progress = _quiet) -> Inputs:
    """Read the measurement files; extract pulses, the DC-IR table and the OCV."""
    from .data.soc import find_rests

    notes: list[str] = []
    records: list[InputRecord] = []
    q = cfg.capacity_ah
    sources = cfg.ocv_sources or (("pulses",) if cfg.ocv is None else (cfg.ocv,))
    for src in sources:
        if src != "pulses":
            records.append(InputRecord("ocv", src.name, file_sha256(src)))
    sources, file_curves, joined = ocv_file_curves(cfg, sources, progress)
    notes.extend(joined)
    reference = None
    if file_curves:
        reference = ocv_mod.merge_curves([file_curves[s] for s in sources if s != "pulses"])[0]

    series, pulses, rests, soc0, q_axis = None, (), None, None, q
    if cfg.pulses is not None:
        progress(f"reading pulse test {cfg.pulses.name}")
        series = read_series(cfg, cfg.pulses, "pulses")
        records.append(InputRecord("pulses", cfg.pulses.name, file_sha256(cfg.pulses)))
        rests = find_rests(series, max(0.02 * q, 1e-3), ocv_mod.MIN_OCV_REST_S)
        soc0, n, q_axis = pulse_test_soc0(cfg, series, rests, reference, cfg.pulses_soc0)
        if n:
            notes.append(n)
        if cfg.dynamic:
            pulses, table, n = dynamic_levels(series, q_axis, soc0, cfg.times_s)
            notes.append(n)
            progress(n)
        else:
            pulses = tuple(dcir_mod.find_pulses(series, q_axis, soc0=soc0,
                                                min_rest_s=cfg.min_rest_s,
                                                max_pulse_s=cfg.max_pulse_s))
            table = dcir_mod.extract_dcir(series, list(pulses), cfg.times_s).measured_times()
            notes.extend(table.notes)
            progress(f"{len(pulses)} pulses, {len(table)} DC-IR rows")
    else:
        table = dcir_mod.read_dcir_csv(cfg.dcir)
        records.append(InputRecord("dcir", cfg.dcir.name, file_sha256(cfg.dcir)))

    steps = None
    steps_file = cfg.pulse_tests[0].steps if len(cfg.pulse_tests) == 1 else None
    if steps_file is not None and series is not None:
        # the SOC steps between the pulse sets, logged apart (the curve fit merges them)
        progress(f"reading SOC steps {steps_file.name}")
        steps = read_series(cfg, steps_file, "pulses")      # the pulse test's cycler
        records.append(InputRecord("steps", steps_file.name, file_sha256(steps_file)))
    paths = {s: (cfg.pulses if s == "pulses" else s) for s in sources}
    ocv, n, report = ocv_mod.assemble(sources, file_curves, paths, rests, soc0, q_axis,
                                      auto=cfg.ocv_branch == "auto", series=series,
                                      rests_first=cfg.ocv_rests_first)
    notes.extend(n)
    return Inputs(q, ocv, table, series, pulses, tuple(records), tuple(notes), steps, report,
                  q_axis)


def fit_models(cfg: BuildConfig, inputs: Inputs, progress: Progress = _quiet,
               neighbour_taus: dict | None = None, searches: list | None = None
               ) -> tuple[dict[str, EcmModel], dict]:
    """Fit every method of the config; returns the models and the raw fits (for plots).
    ``neighbour_taus``: the curve method's time constants from the tests on either side
    in temperature; ``searches``: those of its earlier fit of this test
    (:func:`ecmgen.fit.curve.fit_pulse_curves`)."""
    from .fit.checks import flag_notes, point_fit_flags
    from .fit.ga import fit_ga
    from .fit.lm import fit_lm
    from .fit.points import five_point_rows
    from .model.spans import model_span_notes

    models: dict[str, EcmModel] = {}
    raw: dict = {"flags": {}}
    common = _common(cfg, inputs)
    point_methods = [m for m in cfg.methods if m in ("ga", "lm")]
    if point_methods:
        from .fit.smooth import smooth_point_fit      # scipy.optimize: only when used

        rows, n = five_point_rows(inputs.dcir, cfg.c_rate)
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
            # five points fix a level's four parameters exactly: smoothed over the levels
            fits[m], smooth_notes = smooth_point_fit(rows.t_s, rows.r_ohm, rows.soc,
                                                     rows.direction, fits[m])
            f = fits[m]
            cols = {k: getattr(f, k) for k in RC_FIELDS}
            ch, dis, n2 = level_tables(rows.soc, rows.direction, cols, f.fitness_ohm,
                                     f.converged, cfg.pulses or cfg.dcir)
            bad = int(np.sum(~f.converged))
            n3 = [f"{m}: {bad} of {f.converged.size} table cells did not converge"] if bad else []
            flags = point_fit_flags(m, f, rows)
            raw["flags"][m] = flags
            model = EcmModel(charge=ch, discharge=dis, method=m, **common)
            n3 += flag_notes(flags) + model_span_notes(model, copied_directions(n2))
            n3 = smooth_notes + n2 + n3
            models[m] = replace(model, notes=inputs.notes + tuple(n) + tuple(n3))
        raw["point_fits"] = fits
    if "curve" in cfg.methods:
        models["curve"], raw["curve_fit"], raw["flags"]["curve"] = curve_model(
            cfg, inputs, common, progress, neighbour_taus=neighbour_taus, searches=searches)
    return models, raw


def _common(cfg: BuildConfig, inputs: Inputs) -> dict:
    """The EcmModel fields every method's model of a prepared test shares."""
    return dict(capacity_ah=inputs.capacity_ah, ocv=inputs.ocv, seed=cfg.seed,
                inputs=inputs.records, direction_deadband_a=0.01 * inputs.capacity_ah)


def curve_model(cfg: BuildConfig, inputs: Inputs, common: dict, progress: Progress = _quiet,
                current_factor=None, tau_ranges: dict | None = None,
                neighbour_taus: dict | None = None, searches: list | None = None,
                butler_volmer: bool = True):
    """The curve method's model of a prepared test: (model, its CurveFit, its flags).
    ``current_factor``: a current-dependent resistance the fit takes as given
    (:func:`ecmgen.fit.curve.fit_pulse_curves`; then no Butler-Volmer branch);
    ``tau_ranges``: time-constant search ranges in place of the defaults;
    ``butler_volmer`` False: the diffusion pair of ``cfg.curve_branches`` alone."""
    from .fit.checks import curve_fit_flags, flag_notes
    from .fit.curve import CurveOptions, fit_pulse_curves
    from .data.dynamic import DYNAMIC_TAU_RANGES
    from .fit.rate import fit_exchange_current
    from .model.spans import model_span_notes

    # the diffusion pair and the Butler-Volmer fast branch: [fit] curve_branches
    branches = cfg.curve_branches
    # i0 comes from the C-rates of pulses at one level: a dynamic test has no DC-IR
    bv = fit_exchange_current(inputs.dcir, inputs.capacity_ah) if branches and butler_volmer \
        and len(inputs.dcir) and current_factor is None else None
    relax = dcir_mod.relaxation_s(inputs.pulses_series,
                                  [p for p in inputs.pulses if not p.cut_short], cfg.relax_s)
    progress(f"whole-test fit of the pulse test ({len(inputs.pulses)} pulses, "
             f"{dcir_mod.relaxation_words(relax, cfg.relax_s)}"
             f"{', SOC steps merged' if inputs.steps is not None else ''})")
    options = CurveOptions(diffusion=branches, relax_s=cfg.relax_s,
                           direction_deadband_a=common["direction_deadband_a"],
                           blocks_both_ways=cfg.dynamic,
                           **{**(DYNAMIC_TAU_RANGES if cfg.dynamic else {}),
                              **(tau_ranges or {})})
    cf = fit_pulse_curves(inputs.pulses_series, list(inputs.pulses), inputs.ocv,
                          inputs.soc_capacity_ah or inputs.capacity_ah, options,
                          i0_a=bv.i0_a if bv else None, steps=inputs.steps,
                          current_factor=current_factor, neighbour_taus=neighbour_taus,
                          searches=searches)
    flags = curve_fit_flags(cf, float(relax.max()) if relax.size else None)
    model = EcmModel(charge=RcTable(**cf.rc_columns("charge")),
                     discharge=RcTable(**cf.rc_columns("discharge")), method="curve", **common)
    copied = set() if len(cf.directions) > 1 else {"charge", "discharge"} - set(cf.directions)
    extra = tuple(flag_notes(flags)) + tuple(model_span_notes(model, copied))
    return (replace(model, notes=inputs.notes + (bv.notes if bv else ()) + cf.notes + extra),
            cf, flags)


@dataclass
class TestFit:
    """One pulse test of a build over temperature: what its fits gave (a worker's result)."""

    test: PulseTest
    label: str                     # e.g. "25.8degC", "n9.9degC" (file names, notes)
    temperature_c: float           # its table temperature (NaN: unknown, one test only)
    temperature_from: str          # "configured" | "median cell temperature in its pulses"
    inputs: Inputs                 # without the pulse-test record itself
    models: dict[str, EcmModel]    # one-temperature models, per method
    raw: dict                      # the raw fits (plots)
    seconds: float                 # wall time of its fits
    timings: dict[str, float] = field(default_factory=dict)   # seconds per step
    pngs: dict[str, bytes] = field(default_factory=dict)      # its plots, if asked for


def pulse_test_config(cfg: BuildConfig, test: PulseTest) -> BuildConfig:
    """The one-test config of a [[data.pulse_tests]] entry: what prepare and fit_models
    read (``pulse_tests`` then holds that one test, e.g. for its ``steps`` file). The
    test's OCV sources are data.ocv's unless the entry names its own ``ocv``."""
    own = test.ocv != cfg.ocv
    sources = (("pulses",) if test.ocv is None else (test.ocv,)) if own else cfg.ocv_sources
    return replace(cfg, pulses=test.file, pulses_soc0=test.soc0, ocv=test.ocv,
                   ocv_sources=sources, pulse_tests=(test,), dynamic=test.dynamic)


def pulses_temperature_c(inputs: Inputs) -> float | None:
    """The median cell temperature over the samples of the complete pulses (None: the
    record has no temperature column)."""
    series = inputs.pulses_series
    if series is None or series.temperature_c is None:
        return None
    ps = [p for p in inputs.pulses if not p.cut_short] or list(inputs.pulses)
    ix = np.concatenate([np.arange(p.start, p.stop) for p in ps])
    return float(np.median(series.temperature_c[ix]))


def one_test_c(tests, inputs: Inputs | None) -> float | None:
    """The temperature of a build's one pulse test (None: several tests, or unknown)."""
    if tests:
        return tests[0].temperature_c if len(tests) == 1 else None
    return pulses_temperature_c(inputs) if inputs is not None else None


def fit_pulse_test(cfg: BuildConfig, k: int, plots: bool = False,
                   neighbour_taus: dict | None = None, curve_plot: bool = True,
                   searches: list | None = None, progress: Progress = _quiet) -> TestFit:
    """Read, extract and fit pulse test ``k`` of the config, every method of the config
    (and draw its fit plots, as PNG bytes, with ``plots``: the whole-test fit's with
    ``curve_plot``); ``neighbour_taus``, ``searches``: see :func:`fit_models` (the fit
    again with them draws only the whole-test fit's plot)."""
    import time

    t0 = time.perf_counter()
    test = cfg.pulse_tests[k]
    try:
        fit = _fit_pulse_test(cfg, test, progress, t0, neighbour_taus, searches)
    except InputError as exc:
        if exc.path is None:    # say which test it was
            raise InputError(test.file, exc.message) from None
        raise
    if plots:
        from .plots.figures import fit_pngs, ocv_png
        from .plots.style import degrees

        t1 = time.perf_counter()
        at = degrees(fit.temperature_c)
        raw = fit.raw if curve_plot else {k: v for k, v in fit.raw.items() if k != "curve_fit"}
        fit.pngs = fit_pngs(raw, f"-{fit.label}", at=at)
        if neighbour_taus is None:
            fit.pngs[f"ocv-{fit.label}.png"] = ocv_png(fit.inputs, at=at)
        fit.timings["plots"] = time.perf_counter() - t1
    fit.seconds = time.perf_counter() - t0
    return fit


def _fit_pulse_test(cfg: BuildConfig, test: PulseTest, progress: Progress, t0: float,
                    neighbour_taus: dict | None = None, searches: list | None = None
                    ) -> TestFit:
    import time

    sub = pulse_test_config(cfg, test)
    inputs = prepare(sub, progress)
    if test.temperature_c is not None:
        temp, source = float(test.temperature_c), "configured"
        check_pulse_label(cfg, test, pulses_temperature_c(inputs))
    else:
        measured = pulses_temperature_c(inputs)
        if measured is None and len(cfg.pulse_tests) > 1:
            raise InputError(test.file, "no cell temperature column to take the test's "
                                        "temperature from: give temperature_c in its "
                                        "[[data.pulse_tests]] table")
        temp = np.nan if measured is None else measured
        source = "median cell temperature in its pulses"
    inputs = replace(inputs, records=pulse_test_records(cfg, test, inputs.records))
    timings = {"read, pulses, DC-IR, OCV": time.perf_counter() - t0}
    models, raw = {}, {}
    for m in cfg.methods:   # one at a time, for the timings
        t1 = time.perf_counter()
        got, got_raw = fit_models(replace(sub, methods=(m,)), inputs, progress, neighbour_taus,
                                  searches)
        models.update(got)
        for key, value in got_raw.items():
            if isinstance(value, dict) and isinstance(raw.get(key), dict):
                raw[key].update(value)
            else:
                raw[key] = value
        timings[m] = time.perf_counter() - t1
    return TestFit(test=test, label=temperature_label(temp), temperature_c=temp,
                   temperature_from=source, inputs=replace(inputs, pulses_series=None),
                   models=models, raw=raw, seconds=time.perf_counter() - t0, timings=timings)


def _workers_for(cfg: BuildConfig, workers: int) -> Workers:
    """The processes of a build: ``workers`` for several pulse tests, else this one."""
    return Workers(workers if len(cfg.pulse_tests) > 1 else 1)


def fit_pulse_tests(cfg: BuildConfig, progress: Progress = _quiet,
                    workers: Workers | int = 2, plots: bool = False,
                    png_tasks: dict | None = None) -> list[TestFit]:
    """fit_pulse_test for every [[data.pulse_tests]] entry, in config order, on the
    ``workers`` (or that many processes; see ecmgen.parallel): each test is fitted whole
    by one process, so the results do not depend on scheduling. ``png_tasks``: where
    given, the plots still being drawn when the fits are in go there ({file name: task}),
    not waited for (a build takes them when it writes its plots)."""
    if not isinstance(workers, Workers):
        with _workers_for(cfg, workers) as pool:
            return fit_pulse_tests(cfg, progress, pool, plots)
    n = len(cfg.pulse_tests)
    if workers.parallel:
        progress(f"fitting {n} pulse tests on {workers.processes} processes")
    # the whole-test fit's plots are drawn once that fit is final (after its neighbours')
    later = plots and "curve" in cfg.methods
    tasks = [workers.submit(fit_pulse_test, cfg, k, plots, None, not later) for k in range(n)]
    detail = detail_of(progress)
    out = []
    try:
        for k, task in enumerate(tasks):
            label = f"pulse test {k + 1}"
            fit = task.result(lambda msg: detail(f"[{label}] {msg}"))
            detail(f"[{label}] {cfg.pulse_tests[k].file.name}: {fit.label}, fitted in "
                   f"{fit.seconds:.1f} s")
            out.append(fit)
    except BaseException:
        workers.cancel(tasks)
        raise
    return _with_neighbour_taus(cfg, out, workers, plots, detail, png_tasks)


def _with_neighbour_taus(cfg: BuildConfig, fits: list[TestFit], workers: Workers,
                         plots: bool, detail, png_tasks: dict | None = None
                         ) -> list[TestFit]:
    """The curve fits of the tests between two others in temperature again, offered their
    time constants (:func:`ecmgen.model.temperature.neighbour_time_constants`)."""
    from .model.temperature import neighbour_time_constants

    if "curve" not in cfg.methods:
        return fits
    offer = neighbour_time_constants([f.temperature_c for f in fits],
                                     [f.raw.get("curve_fit") for f in fits])
    curve_only = replace(cfg, methods=("curve",))
    # the fit again takes the first fit's time-constant searches (the same test and settings)
    tasks = {k: workers.submit(fit_pulse_test, curve_only, k, plots, taus, True,
                               fits[k].raw["curve_fit"].searches)
             for k, taus in enumerate(offer) if taus is not None}
    # the plots of the whole-test fits that stand, beside the fits again
    plot_tasks = {f"curve-fit-{f.label}.png": (k, workers.submit(
        curve_fit_png, f.raw["curve_fit"], f.label, f.temperature_c))
        for k, f in enumerate(fits) if plots and k not in tasks}
    for name, (k, task) in plot_tasks.items():
        if png_tasks is None:
            fits[k].pngs[name] = task.result()
        else:
            png_tasks[name] = task
    for k, task in tasks.items():
        label = f"pulse test {k + 1}"
        try:
            again = task.result(lambda msg: detail(f"[{label}] {msg}"))
        except BaseException:
            workers.cancel(list(tasks.values()))
            raise
        detail(f"[{label}] fitted again, offered its neighbours' time constants")
        fit = fits[k]
        fit.models["curve"] = again.models["curve"]
        fit.raw["curve_fit"] = again.raw["curve_fit"]
        fit.raw["flags"]["curve"] = again.raw["flags"]["curve"]
        fit.pngs.update(again.pngs)
        fit.timings["curve, neighbours' time constants"] = again.timings["curve"]
        fit.seconds += again.seconds
    return fits


def curve_fit_png(curve_fit, label: str, temperature_c: float,
                  progress: Progress = _quiet) -> bytes:
    """The whole-test fit's plot of a pulse test (curve-fit-<label>.png), PNG bytes."""
    from .plots.figures import fit_pngs
    from .plots.style import degrees

    return fit_pngs({"curve_fit": curve_fit}, f"-{label}",
                    at=degrees(temperature_c))[f"curve-fit-{label}.png"]


@one_blas_thread
def fit_all(cfg: BuildConfig, progress: Progress = _quiet, *, workers: Workers | int = 2,
            plots: bool = False, png_tasks: dict | None = None):
    """Every method's model of the config: (models, raw fits, inputs, tests), every
    file's column map checked first (a wrong one said before the fits, not after them).
    The data.pulses / data.dcir form: one model per method as prepare + fit_models give it
    (``tests`` empty). [[data.pulse_tests]]: every test fitted (fit_pulse_tests, its fit
    plots drawn there with ``plots``) and each method's models joined over temperature
    (model.temperature); ``inputs`` and ``raw``: the warmest test's; ``tests``: all.
    ``png_tasks``: see fit_pulse_tests."""
    check_column_maps(cfg)
    if not cfg.over_temperature:
        inputs = prepare(cfg, progress)
        models, raw = fit_models(cfg, inputs, progress)
        models = with_activation(cfg, with_surface_soc(cfg, models), one_test_c([], inputs))
        return models, raw, inputs, []
    from .model.temperature import assemble_over_temperature

    tests = fit_pulse_tests(cfg, progress, workers, plots, png_tasks)
    temps = [t.temperature_c for t in tests]
    names = pulse_file_names(cfg)
    labels = [names[t.test.file] for t in tests]
    models = {}
    for m in cfg.methods:
        try:
            models[m] = assemble_over_temperature(
                [t.models[m] for t in tests], temps, step_c=cfg.temperature_step_c,
                warm_c=cfg.warm_row_c, labels=labels, ocv_spans=[
                    t.inputs.ocv_report.span if t.inputs.ocv_report else (0.0, 1.0)
                    for t in tests])
        except ValueError as exc:
            raise InputError(cfg.path, str(exc)) from None
    warm = tests[int(np.nanargmax(temps))] if np.isfinite(temps).any() else tests[0]
    models = with_activation(cfg, with_surface_soc(cfg, models), one_test_c(tests, None))
    return models, warm.raw, warm.inputs, tests


def with_activation(cfg: BuildConfig, models: dict[str, EcmModel],
                    test_c: float | None) -> dict[str, EcmModel]:
    """[model] activation_k: each model from one pulse test becomes a model over temperature
    whose resistances follow the cell temperature by Arrhenius about the test's
    (model.temperature.derive_over_temperature)."""
    if not cfg.activation_k:
        return models
    if test_c is None or not np.isfinite(test_c):
        raise InputError(cfg.pulses or cfg.path, "model.activation_k needs the pulse test's "
                         "cell temperature: a temperature column in it, or data.temperature_c")
    from .model.temperature import derive_over_temperature

    label = Path(cfg.pulses or cfg.pulse_tests[0].file).name
    return {m: derive_over_temperature(model, test_c, cfg.activation_k,
                                       step_c=cfg.temperature_step_c, warm_c=cfg.warm_row_c,
                                       label=label)
            for m, model in models.items()}


def with_surface_soc(cfg: BuildConfig, models: dict[str, EcmModel]) -> dict[str, EcmModel]:
    """[model] surface_soc_gain on every model that has the diffusion RC pair (the surface
    SOC needs its voltage). Unset, it is SURFACE_SOC_GAIN_OVER_TEMPERATURE for a model from
    several pulse tests over temperature and 0 for a model from one: there the cell's
    warming, which one test's tables do not follow, is what the cycles show, and a gain
    adds to that error (docs/results.md, "The surface SOC"). A model without the pair keeps
    0, said in its notes where the config asked for a gain."""
    given = cfg.surface_soc_gain is not None
    if given:
        gain = cfg.surface_soc_gain
    else:
        gain = SURFACE_SOC_GAIN_OVER_TEMPERATURE if len(cfg.pulse_tests) > 1 else 0.0
    if not gain:
        return models
    out = {}
    for m, model in models.items():
        if model.discharge.has_diffusion:
            out[m] = replace(model, surface_soc_gain=gain)
        elif given:
            out[m] = replace(model, notes=(*model.notes, f"surface_soc_gain = {gain:g} not "
                                           "applied: the model has no diffusion RC pair"))
        else:
            out[m] = model
    return out


@one_blas_thread
def build(cfg: BuildConfig, out_dir: str | Path, progress: Progress = _quiet, *,
          plots: bool = True, c_code: bool = True, workers: int = 2,
          strict: bool = False) -> BuildResult:
    """Run the whole chain and write the outputs into ``out_dir``. ``workers``: processes
    for a build over temperature (the pulse tests, the validation cycles and their plots;
    1: all here, one after the other); see ecmgen.parallel for scripts. ``strict``: a best
    model that fails the table checks (:mod:`ecmgen.fit.quality`) is an InputError, raised
    before anything is written."""
    import time

    clock = {"t": time.perf_counter()}
    timings: dict[str, float] = {}

    def lap(stage: str) -> None:
        now = time.perf_counter()
        timings[stage] = timings.get(stage, 0.0) + now - clock["t"]
        clock["t"] = now

    out_dir = Path(out_dir).resolve()
    given = cfg.input_files()      # outputs must never replace one
    check_output_folder(out_dir, given)     # before the fit, not after it
    check_temperature_logs(cfg)
    with _workers_for(cfg, workers) as pool:
        plot_tasks: dict = {}       # {file name: task}, the plots still being drawn
        models, raw, inputs, tests = fit_all(cfg, progress, workers=pool, plots=plots,
                                             png_tasks=plot_tasks)
        lap("fit")
        result = BuildResult(models=models, best=cfg.best, inputs=inputs,
                             curve_fit=raw.get("curve_fit"),
                             point_fits=raw.get("point_fits", {}),
                             point_table=raw.get("point_table"), tests=tests,
                             timings=timings)
        result.quality = _quality(models, raw.get("flags", {}))
        if strict and not result.quality[cfg.best].passes:
            from .fit.quality import quality_words

            raise InputError(cfg.path, "build --strict: "
                                       + quality_words(cfg.best, result.quality[cfg.best]))
        # the validations first: the C check, the longest tasks left, waits for them; the
        # parameter plots (the models alone) behind them
        result.validations = validate_all(
            cfg, models, progress, workers=pool,
            meanwhile=lambda: plot_tasks.update(
                _parameter_plots(pool, cfg, models, tests, inputs) if plots else {}))
        result.fit_flags = raw.get("flags", {})
        record_usage(result, one_test_c(tests, inputs))
        lap("validate")

        with staged(out_dir, given) as (staging, files):
            # the C check of the best model on the workers first, the plots beside and after
            c_task = submit_c(pool, cfg, result, staging) if c_code and cfg.c_numeric else None
            if plots:
                plot_tasks.update((validation_png_name(label), task) for label, task in
                                  validation_plots(pool, result.validations, cfg.best).items())
            if tests:
                for t in tests:
                    t.inputs.dcir.write_csv(staging / f"dcir-{t.label}.csv")
            else:
                inputs.dcir.write_csv(staging / "dcir.csv")
            for m, model in models.items():
                model.save(staging / f"model-{m}.json")
            models[cfg.best].save(staging / "model.json")
            lap("write")
            if c_task is not None:
                result.c_report = c_task.result(progress)
                lap("c")
            if plots:
                progress("writing plots")
                for name, png in plot_files(raw, inputs, tests, plot_tasks, progress).items():
                    (staging / name).write_bytes(png)
                lap("plots")
            from .report import write_build_report

            write_build_report(cfg, result, staging)
    lap("write")
    result.files = files
    result.out_dir = out_dir
    return result


def _parameter_plots(pool: Workers, cfg: BuildConfig, models: dict[str, EcmModel], tests,
                     inputs: Inputs) -> dict:
    """parameters-<method>.png of every model, as tasks of ``pool``: {file name: task}."""
    from .plots.figures import parameters_png

    measured = sorted(t.temperature_c for t in tests) if tests else \
        ([one_test_c(tests, inputs)] if cfg.activation_k else None)
    return {f"parameters-{m}.png": pool.submit(parameters_png, model, measured)
            for m, model in models.items()}


def _quality(models: dict[str, EcmModel], flags: dict) -> dict:
    from .fit.quality import model_quality

    return {m: model_quality(model, flags.get(m, ())) for m, model in models.items()}


def run_diagnose(cfg: BuildConfig, out_dir: str | Path, progress: Progress = _quiet, *,
                 plots: bool = True):
    """`diagnose` from a build config: fit the base model (method ``fit.best``), look for
    missing effects on ``data.cycle`` (judged on ``[diagnose] judge`` or on the held-out
    end of the cycle), and write the augmented model, plots and report into out_dir."""
    from .diagnosis.output import write_diagnose_outputs
    from .diagnosis.search import NothingToJudge, diagnose, diagnose_options

    options = diagnose_options(cfg.raw.get("diagnose"), cfg.path)
    judge_path = _diagnose_file(cfg, "judge", options.pop("judge"))
    base_path = _diagnose_file(cfg, "base", options.pop("base"))
    cycle_path = _diagnose_file(cfg, "cycle", options.pop("cycle")) or cfg.cycle
    if cycle_path is None:
        raise InputError(cfg.path, "diagnose needs data.cycle or diagnose.cycle (the record "
                                   "to diagnose on)")
    soc0 = options.pop("soc0", cfg.soc0 if cycle_path == cfg.cycle else None)
    out_dir = Path(out_dir).resolve()
    given = cfg.input_files() | {p for p in (judge_path, cycle_path, base_path) if p}
    check_output_folder(out_dir, given)
    fit_series = read_series(cfg, cycle_path, "cycle")     # read and checked before the fit
    judge = read_series(cfg, judge_path, "judge") if judge_path is not None else None
    for record in (fit_series, judge):  # a flipped current is "unexplained" otherwise
        if record is not None:
            check_sign(record)
    base, refits, pulse_refit = (_load_base(base_path, progress) if base_path is not None
                                 else _fit_base(cfg, progress))
    try:
        result = diagnose(base, fit_series, judge, soc0=soc0, progress=progress,
                          base_refits=refits, pulse_refit=pulse_refit, **options)
    except NothingToJudge as exc:
        raise InputError(judge_path or cycle_path, str(exc)) from None

    with staged(out_dir, given) as (staging, files):
        base.save(staging / "model-base.json")
        write_diagnose_outputs(result, staging, plots=plots)
    return result, out_dir, files


def _fit_base(cfg: BuildConfig, progress: Progress):
    """The base of a diagnosis fitted from the config's data (method ``fit.best``), the
    refits of it that a candidate may ask for, and the pulse test to refit it on (or None)."""
    fit_cfg = replace(cfg, methods=(cfg.best,))
    if "curve_branches" not in (cfg.raw.get("fit") or {}):
        # the base of a diagnosis is the plain 2RC: the diffusion pair and the Butler-Volmer
        # branch are what extra_rc and current_dependent_resistance would name
        fit_cfg = replace(fit_cfg, curve_branches=False)
        progress("base model: the plain 2RC (no diffusion pair, no Butler-Volmer branch; "
                 "[fit] curve_branches = true fits them into the base)")
    models, raw, inputs, _ = fit_all(fit_cfg, progress)
    refits, pulse_refit = {}, None
    if cfg.best == "curve" and not cfg.over_temperature:
        refits["current_dependent_resistance"] = lambda: _refit_with_current_dependence(
            fit_cfg, inputs, raw["curve_fit"], progress)
        pulse_refit = _pulse_refit(fit_cfg, inputs, raw["curve_fit"], models[cfg.best])
    return models[cfg.best], refits, pulse_refit


def _pulse_refit(cfg: BuildConfig, inputs: Inputs, base_fit, base: EcmModel):
    """The pulse test that made a diagnosis's base, and the whole-test fit of it with a
    voltage taken out (:mod:`ecmgen.diagnosis.refits`)."""
    from .diagnosis.refits import PulseRefit

    common = _common(cfg, inputs)
    series = inputs.pulses_series

    def refit(voltage_v, third_pair: bool = False):
        # third_pair: with the diffusion pair (a third RC pair), no Butler-Volmer branch
        inp = replace(inputs, pulses_series=replace(series,
                                                    voltage_v=series.voltage_v - voltage_v))
        model, cf, _ = (curve_model(replace(cfg, curve_branches=True), inp, common,
                                    butler_volmer=False) if third_pair
                        else curve_model(cfg, inp, common))
        return model, cf.rms_error_v

    return PulseRefit(series, base_fit.rms_error_v, refit, inputs.capacity_ah,
                      base.direction_deadband_a, inputs.pulses, inputs.soc_capacity_ah)


def _load_base(path: Path, progress: Progress):
    """[diagnose] base: the user's model as it is, and no refits (the data that made it is
    not at hand)."""
    from .model.model import load_model

    progress(f"base model: {path.name} as given ([diagnose] base)")
    return load_model(path), {}, None


def _diagnose_file(cfg: BuildConfig, key: str, name: str | None) -> Path | None:
    """The file ``[diagnose] key`` names, resolved beside the config (None: not set)."""
    if name is None:
        return None
    path = (cfg.path.resolve().parent / name).resolve()
    if not path.is_file():
        raise InputError(cfg.path, f"diagnose.{key} names a missing file: {name}")
    return path


def _refit_with_current_dependence(cfg: BuildConfig, inputs: Inputs, base_fit, progress):
    """The pulse test refitted with a current-dependent resistance (g = asinh(x) / x on r0
    and r_fast, i0 searched with the base fit's time constants, then all refitted): (model,
    effect, note), or None when the test fits no better with it (1 % of its RMS)."""
    from .fit.rate import best_exchange_current
    from .model.effects import CurrentDependentResistance

    common = _common(cfg, inputs)
    near = {f"tau_{k}_s": (t / 1.02, t * 1.02) for k, t in
            (("fast", base_fit.tau_fast_s), ("slow", base_fit.tau_slow_s))}

    def rms_at(i0_a):
        effect = CurrentDependentResistance(scale_at_zero=1.0, i0_a=i0_a)
        return curve_model(cfg, inputs, common, current_factor=effect.factor,
                           tau_ranges=near)[1].rms_error_v, effect

    i0_a, rms, effect = best_exchange_current(rms_at, inputs.capacity_ah)
    if not rms < 0.99 * base_fit.rms_error_v:
        return None
    model, cf, _ = curve_model(cfg, inputs, common, current_factor=effect.factor)
    progress(f"pulse test refitted with a current-dependent resistance, i0 {i0_a:.3g} A: "
             f"fit RMS {1e3 * base_fit.rms_error_v:.2f} -> {1e3 * cf.rms_error_v:.2f} mV")
    return model, effect, (f"current_dependent_resistance: the base tables refitted on the "
                           f"pulse test with it (i0 {i0_a:.3g} A; fit RMS "
                           f"{1e3 * base_fit.rms_error_v:.2f} -> {1e3 * cf.rms_error_v:.2f} mV)")
