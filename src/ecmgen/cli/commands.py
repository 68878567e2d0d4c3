"""The commands of `ecmgen`: one ``cmd_<name>(args) -> exit code`` each, a thin layer over
the library (:mod:`ecmgen.pipeline` and the stages); :mod:`ecmgen.cli.args` binds them to
their parsers."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from ..errors import InputError, reading
from ..files import json_text
from ..outputs import check_output_file, check_output_folder, refuse_inputs, staged


def _given(cfg) -> set[Path]:
    return cfg.input_files()


# numeric options: (lowest, highest) accepted; NaN and infinities never are. The SOC
# options are fractions; a temperature outside the cell's life is a typo (degF? K?)
NUMBER_OPTIONS = {"soc0": (0.0, 1.0), "soc0_guess": (0.0, 1.0), "soc": (0.0, 1.0),
                  "temperature_c": (-60.0, 100.0), "capacity_ah": (1e-6, 1e5),
                  "current_gain": (1e-3, 1e3), "current_offset_a": (-1e5, 1e5),
                  "dt_s": (1e-6, 3600.0), "times": (1e-6, 1e6), "window_s": (-1e12, 1e12),
                  "ocv_soc_step": (1, 16), "rc_soc_step": (1, 16),
                  "equivalent_full_cycles": (0.0, 1e6)}


def _check_numbers(args) -> None:
    """Every numeric option given: finite and within its range (one line, exit 2)."""
    for name, (lo, hi) in NUMBER_OPTIONS.items():
        value = getattr(args, name, None)
        if value is None:
            continue
        for v in value if isinstance(value, list) else [value]:
            if not (math.isfinite(v) and lo <= v <= hi):
                raise InputError(None, f"--{name.replace('_', '-')} must be a finite number "
                                       f"in [{lo:g}, {hi:g}], got {v!r}")
    if getattr(args, "current_gain", None) is not None and args.current_gain <= 0:
        raise InputError(None, "--current-gain must be positive")
    times = getattr(args, "times", None)
    if times and any(b <= a for a, b in zip(times, times[1:])):
        raise InputError(None, f"--times must be increasing, got {times}")


def _progress(enabled: bool):
    from ..console import StderrProgress, quiet

    return StderrProgress() if enabled else quiet


def cmd_build(args) -> int:
    from ..config import load_config

    cfg = load_config(args.config)
    if len(cfg.pulse_tests) > 1:
        # the build's workers load their modules while this process loads its own
        from ..parallel import start_fork_server

        start_fork_server()
    from ..console import build_summary, cycle_table, note_lines
    from ..pipeline import build
    from ..report import build_json, pulse_test_table, validation_rows

    out = Path(args.out) if args.out else cfg.path.parent / "ecmgen-out"
    check_output_folder(out, _given(cfg))
    progress = _progress(not args.quiet)
    try:
        result = build(cfg, out, progress, plots=not args.no_plots, c_code=not args.no_c,
                       strict=args.strict)
    finally:
        getattr(progress, "close", lambda: None)()
    _warn_kept(result.out_dir)
    if args.json:
        print(json_text(build_json(result), indent=1))
        return 0
    q = result.quality.get(result.best)
    if q is not None and not q.passes:
        from ..fit.quality import quality_words

        print(f"warning: {quality_words(result.best, q)} (build --strict makes this an error)",
              file=sys.stderr)
    notes = note_lines(list(result.models[result.best].notes) + result.notes,
                       str(result.out_dir / "report.md"))
    for line in notes if not args.quiet else [n for n in notes if n.startswith("warning")]:
        print(line, file=sys.stderr)
    if not args.quiet:
        if result.tests:
            print(pulse_test_table(result))
            print()
        print(cycle_table(validation_rows(result), result.best))
        for numeric, r in (result.c_report or {}).items():
            same = {True: "bit-exact to its reference", False: "NOT bit-exact"}.get(
                r.get("bit_exact_vs_reference"), "not checked")
            where = _shown_path(result.out_dir / r["dir"])
            grid = ", ".join(f"{k[:k.index('_')].upper()} on every {r[k]}. SOC breakpoint"
                             for k in ("ocv_soc_step", "rc_soc_step") if r.get(k, 1) > 1)
            print(f"C {numeric}: {r['table_bytes']} bytes of tables (flash"
                  f"{'; ' + grid if grid else ''}), {same}; golden "
                  f"vectors and test in {where}/ (ecmgen verify {where})")
        print(build_summary(result))
    return 0


def _warn_kept(out: Path) -> None:
    """Name the user's edited files a run wrote again (kept beside, as <name>.edited)."""
    from ..outputs import kept_beside

    for name in kept_beside(out):
        print(f"warning: {_shown_path(out / name.rsplit('.edited', 1)[0])} was changed since "
              f"ecmgen wrote it; your version is kept as {_shown_path(out / name)}",
              file=sys.stderr)


def _shown_path(path: Path) -> str:
    """``path`` relative to the working directory where it lies below it."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _dcir_with_config(args):
    """The DC-IR table `build` would write for the config (its column mapping, capacity,
    start SOC and [dcir] settings); a PULSES argument or an option overrides the config."""
    from dataclasses import replace

    from ..config import load_config
    from ..pipeline import prepare

    cfg = load_config(args.config)
    if cfg.pulse_tests:     # [[data.pulse_tests]]: the one named, with its own settings
        from ..pipeline import pulse_test_config

        given = None if args.pulses is None else Path(args.pulses).resolve()
        named = [t for t in cfg.pulse_tests if t.file == given]
        if given is None:
            raise InputError(cfg.path, "the config has pulse tests at several temperatures "
                                       "([[data.pulse_tests]]): name one, ecmgen dcir PULSES "
                                       "--config ...")
        if named:
            cfg = pulse_test_config(cfg, named[0])
    if args.pulses is None and cfg.pulses is None:
        raise InputError(cfg.path, "no data.pulses (a DC-IR table is not a pulse test); "
                                   "give the pulse test file: ecmgen dcir PULSES --config ...")
    over = {}
    if args.pulses is not None:
        over.update(pulses=Path(args.pulses).resolve(), dcir=None)
    if args.capacity_ah is not None:
        over["capacity_ah"] = args.capacity_ah
    if args.soc0 is not None:
        over["pulses_soc0"] = args.soc0
    if args.times is not None:
        over["times_s"] = tuple(args.times)
    cfg = replace(cfg, **over)
    if args.out:            # before the work: every file the config names is an input
        check_output_file(args.out, [*_given(cfg), cfg.pulses])
    return cfg.pulses, prepare(cfg).dcir


def cmd_dcir(args) -> int:
    from ..data.dcir import DEFAULT_TIMES_S, extract_dcir, find_pulses
    from ..data.measure import read_timeseries

    _check_numbers(args)
    if args.config:
        pulses_path, table = _dcir_with_config(args)
    else:
        if args.pulses is None or args.capacity_ah is None:
            raise InputError(args.pulses, "give the pulse test and --capacity-ah (the cell "
                                          "capacity), or --config CONFIG.toml")
        pulses_path = Path(args.pulses)
        series = read_timeseries(pulses_path, capacity_ah=args.capacity_ah)
        soc0 = 1.0 if args.soc0 is None else args.soc0
        pulses = find_pulses(series, args.capacity_ah, soc0=soc0)
        table = extract_dcir(series, pulses, args.times or DEFAULT_TIMES_S)
    for n in () if args.quiet else table.notes:
        print(f"note: {n}", file=sys.stderr)
    if args.out:
        out = check_output_file(args.out, [pulses_path] + ([args.config] if args.config else []))
        table.write_csv(out)
        print(f"wrote {table.counts()} to {out}", file=sys.stderr)
    else:
        sys.stdout.write(table.to_csv_text())
    return 0


def cmd_fit(args) -> int:
    from dataclasses import replace

    from ..config import load_config
    from ..pipeline import fit_all

    cfg = load_config(args.config)
    if args.method:
        cfg = replace(cfg, methods=(args.method,), best=args.method)
    out = check_output_file(args.out, _given(cfg))
    progress = _progress(not args.quiet)
    models, _, _, _ = fit_all(cfg, progress)
    models[cfg.best].save(out)
    print(f"wrote {out} (method {cfg.best})", file=sys.stderr)
    return 0


def cmd_validate(args) -> int:
    from ..data.measure import read_timeseries
    from ..model.model import load_model
    from ..model.simulate import validate

    _check_numbers(args)
    inputs = [args.model, args.cycle, args.config]
    if args.plot:
        check_output_file(args.plot, inputs, "--plot")
    model = load_model(args.model)
    if args.equivalent_full_cycles is not None and model.ageing is None:
        raise InputError(args.model, "has no ageing law: --equivalent-full-cycles needs one "
                                     "(ecmgen age writes it)")
    if args.config:
        # a CSV from another cycler: the config's [data.columns] (or [data.columns.cycle])
        from ..config import load_config
        from ..pipeline import read_series

        cfg = load_config(args.config)
        if args.plot:
            check_output_file(args.plot, _given(cfg), "--plot")
        if args.window_s is not None:   # the option wins over data.cycle_window_s
            from dataclasses import replace

            cfg = replace(cfg, cycle_window_s=None)
        series = read_series(cfg, Path(args.cycle), "cycle")
    else:
        series = read_timeseries(args.cycle, capacity_ah=model.capacity_ah)
    if args.window_s is not None:
        series = series.window(*args.window_s)
    val = validate(model, series, args.soc0, args.temperature_c, args.equivalent_full_cycles)
    if args.plot:
        from ..files import write_atomic
        from ..plots.figures import validation_png

        write_atomic(Path(args.plot), validation_png({"": val}, Path(args.cycle).name))
    if args.json:
        t_range = val.temperature_range_c
        print(json_text(dict(val.overall.as_dict(), soc0=val.soc0, soc0_how=val.soc0_how,
                              soc_above_10=val.soc_above_10.as_dict(),
                              warnings=list(val.warnings),
                              voltage_lag_samples=val.voltage_lag_samples,
                              temperature_c=None if t_range is None else
                              {"min": t_range[0], "max": t_range[1]})))
    else:
        m = val.overall
        src = f"from {val.soc0_how}" if val.soc0_from_ocv else "given"
        print(f"{Path(args.cycle).name}: MAE {m.mae_v * 1e3:.2f} mV  RMSE {m.rmse_v * 1e3:.2f} mV"
              f"  max {m.max_abs_v * 1e3:.1f} mV  (soc0 {val.soc0:.4f} {src}; "
              + (f"MAE at SOC>10 % {val.soc_above_10.mae_v * 1e3:.2f} mV"
                 if math.isfinite(val.soc_above_10.mae_v) else "never above 10 % SOC")
              + ("" if val.temperature_range_c is None else
                 "; cell {:.1f}..{:.1f} degC".format(*val.temperature_range_c)) + ")")
        for w in val.warnings:
            print(f"note: {w}")
    return 0


def cmd_estimate(args) -> int:
    from dataclasses import asdict, replace

    from ..config import EstimatorConfig, load_config, start_settings
    from ..data.measure import read_timeseries
    from ..estimate.run import estimate_csv_text, estimate_json, estimate_record
    from ..files import write_atomic
    from ..model.model import load_model
    from ..model.simulate import opens_settled, start_estimate

    out = None
    if args.out:
        out = check_output_file(args.out, [args.model, args.cycle, args.config])
    _check_numbers(args)
    model = load_model(args.model)
    settings = EstimatorConfig()
    set_keys: set = set()               # the [estimator] keys the config sets
    if args.config:
        from ..pipeline import read_series

        cfg = load_config(args.config)
        set_keys = set(cfg.raw.get("estimator") or {})
        if out is not None:
            check_output_file(out, _given(cfg))
        if args.window_s is not None:   # the option wins over data.cycle_window_s
            cfg = replace(cfg, cycle_window_s=None)
        settings = cfg.estimator
        series = read_series(cfg, Path(args.cycle), "cycle")
        settings, measured = _settings_from_validation(cfg, model, settings,
                                                       Path(args.cycle))
        set_keys |= measured    # measured on the cell's own cycles: wins over a start's too
    else:
        series = read_timeseries(args.cycle, capacity_ah=model.capacity_ah)
    if args.filter:
        settings = replace(settings, filter=args.filter)
    soc0, start = args.soc0, args.start
    if soc0 is None:
        if series.temperature_c is None and args.temperature_c is not None:
            series = replace(series, temperature_c=np.full(series.time_s.size,
                                                           args.temperature_c))
        found = start_estimate(model, series)
        soc0 = found.soc0
        if start is None and not found.settled and not set_keys & {"start",
                                                                   "start_polarization_c"}:
            start = "anywhere"          # it opens under load or mid-relaxation: not rested
    elif start is None and not set_keys & {"start", "start_polarization_c"}:
        if not opens_settled(model, series, args.temperature_c):   # told the SOC only
            start = "anywhere"
    if args.window_s is not None:
        first_t = float(series.time_s[0])
        series, soc0 = _window_start(model, series, soc0, args.window_s)
        if (start is None and float(series.time_s[0]) > first_t
                and not set_keys & {"start", "start_polarization_c"}):
            start = "anywhere"          # a mid-record cut: nothing says the cell rested
    settings = start_settings(settings, start, set_keys)
    start = "anywhere" if settings.start_polarization_c > 0.0 else "rested"
    guess = soc0 if args.soc0_guess is None else args.soc0_guess
    run = estimate_record(model, series, guess, soc0, settings,
                          current_offset_a=args.current_offset_a,
                          current_gain=args.current_gain, temperature_c=args.temperature_c)
    if out is not None:
        write_atomic(out, estimate_csv_text(run))
    f, cc = run.filter, run.coulomb_counting
    if args.json:
        print(json_text(estimate_json(run, soc0=soc0, soc0_guess=guess,
                                       current_offset_a=args.current_offset_a,
                                       current_gain=args.current_gain,
                                       window_s=args.window_s,
                                       filter=settings.filter, start=start,
                                       settings=asdict(settings))))
    else:
        conv = "never" if f.converge_s is None else f"{f.converge_s:.0f} s"
        late = (f"{f.soc_max_abs_after_600s * 100:.2f} % after 600 s" if math.isfinite(
            f.soc_max_abs_after_600s) else "a record shorter than 600 s")
        print(f"{Path(args.cycle).name}: {settings.filter} SOC RMSE {f.soc_rmse * 100:.2f} %, "
              f"max {f.soc_max_abs * 100:.2f} % ({late}), within 2 % from {conv}; coulomb "
              f"counting RMSE "
              f"{cc.soc_rmse * 100:.2f} %, max {cc.soc_max_abs * 100:.2f} % "
              f"(soc0 {soc0:.4f}, guess {guess:.4f}, start {start})")
    return 0


def _window_start(model, series, soc0: float, window_s):
    """The record cut to ``window_s`` and its true SOC at the window's first sample (the
    measured current counted from ``soc0`` at the record's start): a mid-record start,
    under load or mid-relaxation, as a BMS meets it after a reset."""
    from ..estimate.run import coulomb_count

    cut = series.window(*window_s)
    k0 = int(np.searchsorted(series.time_s, cut.time_s[0]))
    ref = coulomb_count(model, series.time_s[:k0 + 1], series.current_a[:k0 + 1], soc0)
    return cut, min(max(float(ref[-1]), 0.0), 1.0)


def _settings_from_validation(cfg, model, settings, cycle: Path):
    """[estimator] model_error / error_correlation_s not set in the config: measured on its
    validation cycles but the one being estimated (its own residual never tunes its
    filter). Returns (settings, the keys measured)."""
    from dataclasses import replace

    from ..estimate.residual import settings_from_cycles
    from ..pipeline import read_series

    given = cfg.raw.get("estimator", {})
    if "model_error" in given and "error_correlation_s" in given:
        return settings, set()
    paths = ([(cfg.cycle, "cycle")] if cfg.cycle else []) + \
        [(p, "extra_cycles") for p in cfg.extra_cycles]
    others = [read_series(cfg, p, role) for p, role in paths
              if p.resolve() != cycle.resolve()]
    figures = settings_from_cycles(model, others, cfg.soc0, settings.voltage_noise_v)
    if figures is None:
        return settings, set()
    measured = {k: v for k, v in figures.as_dict().items() if k not in given}
    return replace(settings, **measured), set(measured)


def cmd_verify(args) -> int:
    from ..c.verify import verify

    verdicts = verify(args.golden, args.csrc, args.cc, args.cflags, args.run)
    for v in verdicts:
        print(v.line)
    failed = [v.name for v in verdicts if not v.passed]
    inexact = failed or any(" 0 differ" not in v.line for v in verdicts)
    if inexact and args.cflags is not None and "-ffp-contract=off" not in args.cflags:
        print("note: the float C is bit-exact only with -ffp-contract=off (and no -ffast-math)")
    print(f"ecmgen verify: {len(verdicts) - len(failed)} of {len(verdicts)} passed"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


AGED_ESTIMATOR = ("the estimator predicts with the fresh cell (age 0: the model's own tables); "
                  "it has no set_age input, the model's step has")


def cmd_codegen(args) -> int:
    from ..c.codegen import file_names, generate_c, prepare
    from ..c.golden import vector_names, write_golden
    from ..c.spec import check_options, coarsen_tables
    from ..model.model import load_model

    _check_numbers(args)
    check_options(args.prefix, args.numeric, args.dt_s, None)     # the options' own words
    out = check_output_folder(args.out, [args.model])
    estimator = None
    if args.estimator != "none":
        from ..config import EstimatorConfig

        estimator = EstimatorConfig()
    model = coarsen_tables(load_model(args.model), args.ocv_soc_step, args.rc_soc_step)
    try:        # what the C cannot represent (or hold: an overflow) is the model's problem
        with reading(args.model):
            spec = prepare(model, numeric=args.numeric, dt_s=args.dt_s, prefix=args.prefix)
        # the files are <prefix>_ecm.* and ecmrt*.h: never the model.json read
        names = file_names(spec.prefix, spec.numeric) | vector_names(spec.prefix, spec.numeric)
        for name in [v for v in names.values() if isinstance(v, str)] + names["runtime"]:
            refuse_inputs(out / name, [args.model])
        # staged as a build's files: none half-written, an edited file kept beside
        with staged(out, {Path(args.model).resolve()}, remove_leftovers=False) as \
                (staging, files):
            generate_c(model, staging, prefix=args.prefix, numeric=args.numeric,
                       dt_s=args.dt_s, estimator=estimator)
            write_golden(spec, staging)         # no cycle here: a drive of pulses and rests
            if estimator is not None:
                from ..c.estc import prepare_estimator
                from ..c.estgolden import write_est_golden
                from ..c.golden import drive_segment

                write_est_golden(spec, prepare_estimator(model, spec, estimator), staging,
                                 drive_segment(spec))
    except InputError as exc:
        if exc.path is not None:
            raise
        raise InputError(args.model, exc.message) from None
    _warn_kept(out)
    if estimator is not None and model.ageing is not None:
        print(f"note: {AGED_ESTIMATOR}", file=sys.stderr)
    if not args.quiet:
        for f in files:
            print(f)
    return 0


def cmd_diagnose(args) -> int:
    from ..config import load_config
    from ..pipeline import run_diagnose

    cfg = load_config(args.config)
    out = Path(args.out) if args.out else cfg.path.parent / "ecmgen-diagnose"
    check_output_folder(out, _given(cfg))
    result, out_dir, files = run_diagnose(cfg, out, _progress(not args.quiet),
                                          plots=not args.no_plots)
    if args.json:
        print(json_text(result.to_json_dict(out_dir / "model.json"), indent=1))
    else:
        for s in result.steps:
            print(f"added {s.name}: held-out MAE {s.mae_before_v * 1e3:.2f} -> "
                  f"{s.mae_after_v * 1e3:.2f} mV")
        print(result.verdict)
        print(f"held-out MAE {result.mae_before_v * 1e3:.2f} mV -> "
              f"{result.mae_after_v * 1e3:.2f} mV; wrote {len(files)} files to {out_dir}")
    return 0


def cmd_fleet(args) -> int:
    from ..fleet import Options, run_fleet

    _check_numbers(args)
    progress = _progress(not args.quiet)
    try:
        result = run_fleet(args.manifest, args.out, scheduler=args.scheduler,
                           workers=args.workers, soc_points=args.soc,
                           temperatures_c=args.temperature_c,
                           options=Options(plots=args.build_plots, c_code=not args.no_c),
                           plots=not args.no_plots, progress=progress)
    finally:
        getattr(progress, "close", lambda: None)()
    if args.json:
        print(json_text(result.as_dict(), indent=1))
    else:
        failed = result.count("failed")
        print(f"{len(result.rows)} rows: {result.count('built')} built, "
              f"{result.count('unchanged')} unchanged, {failed} failed"
              + (f" (see {_shown_path(result.out_dir / 'failures.csv')})" if failed else "")
              + f"; fleet table of {len(result.table)} rows in "
              f"{_shown_path(result.out_dir / 'fleet.csv')} ({result.seconds:.0f} s on "
              f"{result.workers} worker{'s' if result.workers != 1 else ''})")
    return 1 if result.count("failed") else 0


def cmd_age(args) -> int:
    from ..fleet.law import write_aged_model

    notes: list[str] = []
    out, law, base = write_aged_model(args.fleet_dir, args.out, args.base, notes)
    for n in notes:
        print(f"note: {n}", file=sys.stderr)
    x = law.equivalent_full_cycles
    print(f"ageing law over {x[0]:g}..{x[-1]:g} equivalent full cycles ({x.size} check-ups): "
          f"resistance x{law.resistance_scale[-1]:.3f}, capacity x{law.capacity_scale[-1]:.3f} "
          f"at the last; base {_shown_path(base)}; wrote {_shown_path(out)}")
    return 0


def cmd_config(args) -> int:
    from ..config.schema import reference

    sys.stdout.write(reference())
    return 0
