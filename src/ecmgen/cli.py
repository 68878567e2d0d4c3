"""`ecmgen` command line: a thin layer over the library (see ecmgen.pipeline)."""

from __future__ import annotations

import argparse
import contextlib
import errno
import math
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

from .parallel import ONE_BLAS_THREAD

# The command line owns its process: one BLAS thread unless the caller sets another,
# set before numpy loads (ecmgen.parallel says why).
for _name, _value in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_name, _value)

import numpy as np  # noqa: E402

from ._version import __version__  # noqa: E402
from .errors import InputError, describe, reading, user_file_of  # noqa: E402
from .files import json_text  # noqa: E402
from .outputs import check_output_file, check_output_folder, refuse_inputs, staged  # noqa: E402


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
    from .console import StderrProgress, quiet

    return StderrProgress() if enabled else quiet


def cmd_build(args) -> int:
    from .config import load_config
    from .console import build_summary, cycle_table, note_lines
    from .pipeline import build
    from .report import build_json, pulse_test_table, validation_rows

    cfg = load_config(args.config)
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
        from .fit.quality import quality_words

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
    from .outputs import kept_beside

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

    from .config import load_config
    from .pipeline import prepare

    cfg = load_config(args.config)
    if cfg.pulse_tests:     # [[data.pulse_tests]]: the one named, with its own settings
        from .pipeline import pulse_test_config

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
    from .data.dcir import DEFAULT_TIMES_S, extract_dcir, find_pulses
    from .data.measure import read_timeseries

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

    from .config import load_config
    from .pipeline import fit_all

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
    from .data.measure import read_timeseries
    from .model.model import load_model
    from .model.simulate import validate

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
        from .config import load_config
        from .pipeline import read_series

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
        from .files import write_atomic
        from .plots import validation_png

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

    from .config import EstimatorConfig, load_config, start_settings
    from .data.measure import read_timeseries
    from .estimate.run import estimate_csv_text, estimate_json, estimate_record
    from .files import write_atomic
    from .model.model import load_model
    from .model.simulate import opens_settled, start_estimate

    out = None
    if args.out:
        out = check_output_file(args.out, [args.model, args.cycle, args.config])
    _check_numbers(args)
    model = load_model(args.model)
    settings = EstimatorConfig()
    set_keys: set = set()               # the [estimator] keys the config sets
    if args.config:
        from .pipeline import read_series

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
    from .estimate.run import coulomb_count

    cut = series.window(*window_s)
    k0 = int(np.searchsorted(series.time_s, cut.time_s[0]))
    ref = coulomb_count(model, series.time_s[:k0 + 1], series.current_a[:k0 + 1], soc0)
    return cut, min(max(float(ref[-1]), 0.0), 1.0)


def _settings_from_validation(cfg, model, settings, cycle: Path):
    """[estimator] model_error / error_correlation_s not set in the config: measured on its
    validation cycles but the one being estimated (its own residual never tunes its
    filter). Returns (settings, the keys measured)."""
    from dataclasses import replace

    from .estimate.residual import settings_from_cycles
    from .pipeline import read_series

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
    from .c.verify import verify

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
    from .c.codegen import file_names, generate_c, prepare
    from .c.golden import vector_names, write_golden
    from .c.spec import check_options, coarsen_tables
    from .model.model import load_model

    _check_numbers(args)
    check_options(args.prefix, args.numeric, args.dt_s, None)     # the options' own words
    out = check_output_folder(args.out, [args.model])
    estimator = None
    if args.estimator != "none":
        from .config import EstimatorConfig

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
                from .c.estc import prepare_estimator
                from .c.estgolden import write_est_golden
                from .c.golden import drive_segment

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
    from .config import load_config
    from .pipeline import run_diagnose

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
    from .fleet import Options, run_fleet

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
    from .fleet.law import write_aged_model

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
    from .config_schema import reference

    sys.stdout.write(reference())
    return 0


class _Parser(argparse.ArgumentParser):
    """Bad arguments are bad input too: one line ``ecmgen: error: ...``, exit 2."""

    def error(self, message):
        where = self.prog.removeprefix("ecmgen").strip()
        if not where and "required: command" in message:     # `ecmgen` alone
            print(self.command_list(), file=sys.stderr)
            sys.exit(2)
        print(f"ecmgen: error: {where + ': ' if where else ''}{' '.join(message.split())}",
              file=sys.stderr)
        sys.exit(2)

    def command_list(self) -> str:
        """`ecmgen` alone: what it does and each command with its one-line help."""
        actions = self._subparsers._group_actions[0]
        helps = {a.dest: a.help for a in actions._choices_actions}
        width = max(len(n) for n in actions.choices)
        return "\n".join(["usage: ecmgen COMMAND [options]   (ecmgen COMMAND --help)", "",
                          "commands:"] + [f"  {n:<{width}}  {helps.get(n, '')}"
                                          for n in actions.choices])


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ecmgen", description=__doc__)
    p.add_argument("--version", action="version", version=f"ecmgen {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    b = sub.add_parser("build", help="run the whole chain from a config file")
    b.add_argument("config")
    b.add_argument("--out", help="output folder (default: ecmgen-out beside the config)")
    b.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    b.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing on success but warnings (on stderr)")
    b.add_argument("--no-plots", action="store_true")
    b.add_argument("--no-c", action="store_true", help="skip C generation")
    b.add_argument("--strict", action="store_true",
                   help="fail (exit 2, nothing written) when the best model's tables are not "
                        "smooth and positive")
    b.set_defaults(func=cmd_build)

    d = sub.add_parser("dcir", help="extract the DC-IR table of a pulse test")
    d.add_argument("pulses", nargs="?", help="the pulse test (default with --config: its "
                                             "data.pulses)")
    d.add_argument("--config", help="a build config: its column mapping, capacity, start "
                                    "SOC and [dcir] settings (the table build writes)")
    d.add_argument("--capacity-ah", type=float, help="cell capacity (needed without --config)")
    d.add_argument("--soc0", type=float, help="SOC at the start of the test (default 1.0, "
                                              "or as the build with --config)")
    d.add_argument("--times", type=float, nargs="+",
                   help="DC-IR times in s (default 0.1 1 3 6 10, or [dcir] times_s)")
    d.add_argument("--out", help="CSV path (default: stdout)")
    d.add_argument("-q", "--quiet", action="store_true", help="no notes on stderr")
    d.set_defaults(func=cmd_dcir)

    f = sub.add_parser("fit", help="fit a model.json from a config file")
    f.add_argument("config")
    f.add_argument("--method", choices=["ga", "lm", "curve"])
    f.add_argument("--out", default="model.json")
    f.add_argument("-q", "--quiet", action="store_true")
    f.set_defaults(func=cmd_fit)

    v = sub.add_parser("validate", help="simulate a model over a measured cycle")
    v.add_argument("model")
    v.add_argument("cycle")
    v.add_argument("--soc0", type=float, help="start SOC (default: from the OCV)")
    v.add_argument("--temperature-c", type=float, default=None,
                   help="cell temperature in degC for a file without a temperature column")
    v.add_argument("--equivalent-full-cycles", type=float, default=None, metavar="EFC",
                   help="the cell's age, for a model with an ageing law (default: fresh)")
    v.add_argument("--json", action="store_true")
    v.add_argument("--plot", help="write measured vs simulated PNG here")
    v.add_argument("--config", help="a build config whose [data.columns] maps the cycle's CSV")
    v.add_argument("--window-s", type=float, nargs=2, metavar=("T0", "T1"),
                   help="validate on the rows with T0 <= time <= T1 s (the file's own time)")
    v.add_argument("-q", "--quiet", action="store_true", help="(no progress is shown anyway)")
    v.set_defaults(func=cmd_validate)

    e = sub.add_parser("estimate", help="run the SOC filter over a measured cycle and "
                                        "compare it with coulomb counting")
    e.add_argument("model")
    e.add_argument("cycle")
    e.add_argument("--soc0-guess", type=float, help="start SOC the filter is told "
                   "(default: --soc0)")
    e.add_argument("--soc0", type=float, help="true start SOC, for the reference SOC by "
                   "coulomb counting the measured current (default: from the OCV)")
    e.add_argument("--current-offset-a", type=float, default=0.0,
                   help="offset added to the current the filter sees, A")
    e.add_argument("--current-gain", type=float, default=1.0,
                   help="gain applied to the current the filter sees")
    e.add_argument("--temperature-c", type=float, default=None,
                   help="cell temperature in degC for a file without a temperature column")
    e.add_argument("--filter", choices=["ekf", "ukf"],
                   help="override the config's estimator.filter (default ekf)")
    e.add_argument("--config", help="a build config: its [estimator] settings and the "
                   "[data.columns] of the cycle's CSV")
    e.add_argument("--window-s", type=float, nargs=2, metavar=("T0", "T1"),
                   help="start the filter at T0 (the file's own time) and run it to T1; "
                        "--soc0 stays the SOC at the file's start, --soc0-guess is the "
                        "guess at T0")
    e.add_argument("--start", choices=["rested", "anywhere"],
                   help="how the record starts: rested (its first voltage read as the OCV) "
                        "or anywhere (under load or mid-relaxation: the start-anywhere "
                        "settings where [estimator] sets none); default: the config's, "
                        "anywhere when the record (or --window-s) opens unsettled")
    e.add_argument("--out", help="write time_s,soc,soc_sigma,voltage_pred_v,soc_ref here")
    e.add_argument("--json", action="store_true")
    e.add_argument("--quiet", action="store_true", help="(no progress is shown anyway)")
    e.set_defaults(func=cmd_estimate)

    c = sub.add_parser("codegen", help="write the C of a model.json (e.g. an augmented one)")
    c.add_argument("model")
    c.add_argument("--out", required=True, help="folder for the .h/.c and runtime headers")
    c.add_argument("--prefix", default="ecm", help="C symbol prefix")
    c.add_argument("--numeric", choices=["float", "fixed"], default="float")
    c.add_argument("--dt-s", type=float, help="fixed step in s (default: variable dt)")
    c.add_argument("--estimator", choices=["none", "ekf"], default="none",
                   help="also generate the SOC filter <prefix>_est_f32.h/.c (float, "
                        "variable dt; the [estimator] defaults)")
    for what in ("ocv", "rc"):
        c.add_argument(f"--{what}-soc-step", type=int, default=1, metavar="N",
                       help=f"flash: the {what.upper()} table{'s' if what == 'rc' else ''} on "
                            "every N-th SOC breakpoint (and the last; [c] "
                            f"{what}_soc_step)")
    c.add_argument("-q", "--quiet", action="store_true", help="do not list the files written")
    c.set_defaults(func=cmd_codegen)

    v = sub.add_parser("verify", help="check your copy of the generated C against the build's "
                       "golden vectors (exit 0 pass, 1 fail, 2 bad input)")
    v.add_argument("golden", help="a build's c/float or c/fixed folder (or the build folder, "
                   "or one <prefix>_ecm_<s>_vectors.h)")
    v.add_argument("--c", dest="csrc", help="folder of your copy of the C (<prefix>_ecm_<s>.c "
                   "and its headers; default: the golden folder)")
    v.add_argument("--cc", help="C compiler command (default: cc)")
    v.add_argument("--cflags", help="compiler flags, one string (default: "
                   "'-std=c99 -O2 -ffp-contract=off')")
    v.add_argument("--run", help="command that runs the test program, e.g. an emulator "
                   "(default: run it directly)")
    v.set_defaults(func=cmd_verify)

    g = sub.add_parser("diagnose", help="find, add and check missing model effects")
    g.add_argument("config")
    g.add_argument("--out")
    g.add_argument("--json", action="store_true")
    g.add_argument("-q", "--quiet", action="store_true")
    g.add_argument("--no-plots", action="store_true")
    g.set_defaults(func=cmd_diagnose)

    fl = sub.add_parser("fleet", help="build every cell x check-up of a manifest on Dask and "
                        "tabulate their trends (exit 0 all built, 1 some rows failed, 2 bad "
                        "input)")
    fl.add_argument("manifest", help="CSV: cell,checkup,config[,cycles,throughput_ah,date]")
    fl.add_argument("--out", required=True, metavar="DIR", help="output folder: <cell>/<checkup>/ "
                    "per row, fleet.csv, fleet.parquet, ageing.csv, failures.csv, trend plots")
    fl.add_argument("--scheduler", metavar="ADDRESS", help="address of a running Dask scheduler (default: a "
                    "local cluster)")
    fl.add_argument("--workers", type=int, metavar="N", help="local worker processes (default: one per "
                    "core); with --scheduler, wait for this many workers")
    fl.add_argument("--soc", type=float, nargs="+", default=[0.2, 0.5, 0.8], metavar="S",
                    help="SOC points of the fleet table (default 0.2 0.5 0.8)")
    fl.add_argument("--temperature-c", type=float, nargs="+", default=[25.0], metavar="T",
                    help="temperature points of the fleet table, degC (default 25; a "
                         "one-temperature model gives its own table)")
    fl.add_argument("--build-plots", action="store_true", help="each row's build plots too "
                    "(none by default)")
    fl.add_argument("--no-plots", action="store_true", help="no trend plots")
    fl.add_argument("--no-c", action="store_true", help="no C for any row")
    fl.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    fl.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    fl.set_defaults(func=cmd_fleet)

    ag = sub.add_parser("age", help="fit the fleet's ageing law (resistance and capacity over "
                        "equivalent full cycles) into a model.json")
    ag.add_argument("fleet_dir", help="the --out folder of `ecmgen fleet` (its fleet.csv)")
    ag.add_argument("--out", required=True, metavar="MODEL.json", help="the aged model")
    ag.add_argument("--base", metavar="MODEL.json", help="the model the law is written into "
                    "(default: the first non-outlier cell's model at its first check-up)")
    ag.set_defaults(func=cmd_age)

    k = sub.add_parser("config", help="print the config reference (every section and key)")
    k.add_argument("--explain", action="store_true", help="every key: type, unit, range, "
                   "default, meaning (markdown; docs/config.md holds this text)")
    k.set_defaults(func=cmd_config)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        with _no_stray_warnings(), _sigterm_unwinds():
            code = int(args.func(args) or 0)
            sys.stdout.flush()          # a full or closed stdout fails here, not at exit
            return code
    except InputError as exc:
        return _error(str(exc))
    except OSError as exc:
        if exc.filename is not None or exc.errno not in _STDOUT_ERRNOS:
            return _boundary(exc)
        _silence_stdout()               # else Python's own flush at exit fails again
        if exc.errno == errno.EPIPE:    # `ecmgen ... | head`: the reader left, not an error
            return 141
        return _error(f"standard output: cannot be written ({describe(exc)})")
    except KeyboardInterrupt:
        return 130
    except Terminated:
        return 143
    except Exception as exc:
        return _boundary(exc)


# errors of a write to a full, broken or closed standard output (a file name is not set)
_STDOUT_ERRNOS = {errno.ENOSPC, errno.EPIPE, errno.EIO, errno.EDQUOT, errno.EBADF, errno.EFBIG}


def _silence_stdout() -> None:
    with contextlib.suppress(OSError, ValueError, AttributeError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _boundary(exc: BaseException) -> int:
    """The one boundary: an exception raised while reading a user's file (marked by
    ecmgen.errors.reading), or the system refusing a path (an output folder under /proc, a
    full disk), is bad input or a bad place: one line, exit 2. Anything else is a fault of
    ecmgen and keeps its traceback (exit 1)."""
    where = user_file_of(exc)
    if where is None and isinstance(exc, OSError) and exc.filename is not None:
        where = exc.filename
    if where is None:
        raise exc
    return _error(f"{where}: {describe(exc)}")


def _error(message: str) -> int:
    print(f"ecmgen: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


class Terminated(BaseException):
    """SIGTERM, raised where the program is, like KeyboardInterrupt for SIGINT (not an
    Exception: no ``except Exception`` on the way may swallow it)."""


@contextlib.contextmanager
def _sigterm_unwinds():
    """SIGTERM (a CI timeout, ``kill``) unwinds the stack as Ctrl-C does, so that the
    staging folder and temporary files are removed on the way out (exit 143)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _no_stray_warnings():
    """Safety net: no Python warning reaches the user of the command line. What the user
    must know is said as a note or an error; the warnings numpy/scipy/matplotlib raise
    about intermediate values are fixed at their cause where found (and tested with
    ``-W error``), and anything left is not the user's to act on. A developer who asks
    for warnings (``python -W ...`` or PYTHONWARNINGS) still sees them."""
    if sys.warnoptions:
        yield
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


if __name__ == "__main__":
    sys.exit(main())
