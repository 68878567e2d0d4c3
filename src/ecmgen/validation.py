"""The validation and output stage of ``ecmgen build`` (:func:`ecmgen.pipeline.build`):
each model on each validation cycle, what the validation says about the models' use, and
the plots and the C check, given to the build's workers side by side once the cycles are
simulated (the C check of the best model beside the validation plots)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from .config import BuildConfig
from .console import detail_of
from .data.sources import read_series
from .errors import InputError
from .files import short_names
from .model.model import EcmModel
from .model.simulate import Validation, validate
from .parallel import Workers

Progress = Callable[[str], None]


def _quiet(_msg: str) -> None:
    pass


def validate_cycle(cfg: BuildConfig, path: Path, role: str, label: str,
                   models: dict[str, EcmModel], progress: Progress = _quiet
                   ) -> dict[str, Validation]:
    """Every model on one validation cycle (read once)."""
    progress(f"validating on {label}")
    series = read_series(cfg, path, role)
    if series.temperature_c is None and any(m.needs_temperature for m in models.values()):
        raise InputError(path, "no cell temperature column: the model has tables over "
                               "temperature and each validation cycle needs its cell "
                               "temperature (a temperature_c column, a mapped one in "
                               "[data.columns], or data.temperature_c)")
    return {m: validate(model, series, cfg.soc0) for m, model in models.items()}


def named(warning: str, source: str | None, name: str) -> str:
    """A validation warning that opens with the file's base name, named as the build's
    table names the cycle (0degC/us06.mat and n20degC/us06.mat are both us06.mat)."""
    base = Path(source).name if source else ""
    return name + warning[len(base):] if base and warning.startswith(base + ":") else warning


def cycles(cfg: BuildConfig) -> list[tuple[Path, str, str]]:
    """The config's validation cycles: (path, role, the name the build gives it)."""
    paths = ([cfg.cycle] if cfg.cycle else []) + list(cfg.extra_cycles)
    roles = (["cycle"] if cfg.cycle else []) + ["extra_cycles"] * len(cfg.extra_cycles)
    return list(zip(paths, roles, short_names(paths))) if paths else []


def validate_all(cfg: BuildConfig, models: dict[str, EcmModel], progress: Progress = _quiet,
                 *, workers: Workers | None = None,
                 meanwhile: Callable[[], None] | None = None
                 ) -> dict[str, dict[str, Validation]]:
    """Each model on the config's validation cycle(s); ``soc0`` applies to every cycle.
    A model over temperature runs on each cycle's own cell temperature column.
    Returns {method: {cycle name: Validation}}. The cycles run on ``workers`` if given;
    ``meanwhile`` is called once they are given, before their results are waited for
    (the build queues its parameter plots behind them there: the workers draw them while
    this process takes the validations in and plans the C)."""
    workers = workers or Workers(1)
    todo = cycles(cfg)
    tasks = [workers.submit(validate_cycle, cfg, path, role, label, models)
             for path, role, label in todo]
    if meanwhile is not None:
        meanwhile()
    out: dict[str, dict[str, Validation]] = {m: {} for m in models}
    if len(todo) > 1:
        progress(f"validating on {len(todo)} cycles")
    try:
        for (_, _, label), task in zip(todo, tasks):
            for m, v in task.result(detail_of(progress) if len(todo) > 1 else progress).items():
                out[m][label] = v
    except BaseException:
        workers.cancel(tasks)
        raise
    return out


def validation_plots(workers: Workers, validations: dict, best: str) -> dict:
    """The validation plot of each cycle (every model on it), submitted to ``workers``:
    {cycle name: task of its PNG bytes}."""
    from .plots.figures import validation_png

    labels = list(next(iter(validations.values()), {}))
    return {label: workers.submit(validation_png, {m: v[label] for m, v in validations.items()},
                                  label, best) for label in labels}


def submit_c(workers: Workers, cfg: BuildConfig, result, staging: Path):
    """The C of the best model (if the code generator is installed) and its checks, as
    tasks of ``workers``: the files with the check against Python, and the estimator's two
    checks beside it (:mod:`ecmgen.c.check`); they write into ``staging``. Returns what
    gives the ``"c"`` block (``.result(progress)``), or None."""
    try:
        from .c.check import ESTIMATOR_PARTS, c_files, c_plan, estimator_part
    except ImportError:
        return None
    best = result.best
    slim = SimpleNamespace(models={best: result.models[best]}, best=best,
                           validations={best: result.validations.get(best, {})})
    plan = c_plan(cfg, slim)
    parts = [workers.submit(estimator_part, plan, part) for part in ESTIMATOR_PARTS] \
        if plan.check_estimator else []
    return _CTasks(plan, workers.submit(c_files, cfg, plan, staging), parts)


class _CTasks:
    def __init__(self, plan, files, parts):
        self.plan, self.files, self.parts = plan, files, parts

    def result(self, progress: Progress = _quiet) -> dict:
        from .c.check import with_estimator

        block = self.files.result(progress)
        parts = [task.result(progress) for task in self.parts]
        if parts and "skipped" not in block.get("float", {}):
            detail_of(progress)("checking the C estimator against its references")
            with_estimator(block, self.plan, *parts)
        return block


def plot_files(raw: dict, inputs, tests, tasks: dict, progress: Progress) -> dict[str, bytes]:
    """Every plot of a build by file name: the fit plots and OCV of the pulse test (of
    each test, drawn where it was fitted), and the plot tasks' (file name -> task): the
    parameters per method, one validation per cycle."""
    from .plots.figures import fit_pngs, ocv_png, pulse_test_degrees

    at = pulse_test_degrees(inputs)
    pngs = dict(fit_pngs(raw, at=at), **{"ocv.png": ocv_png(inputs, at=at)}) if not tests else {}
    for t in tests:
        pngs.update(t.pngs)
    for name, task in tasks.items():
        pngs[name] = task.result(progress)
    return pngs


def validation_png_name(label: str) -> str:
    return f"validation-{label.replace('/', '-').rsplit('.', 1)[0]}.png"


def _row_spans(result, method: str) -> list | None:
    """Per pulse test (a temperature row of a model over temperature): the SOC its OCV
    and its RC tables were measured at; None with one test."""
    from .model.spans import table_spans

    rows = []
    for t in result.tests:
        if method not in t.models or not np.isfinite(t.temperature_c):
            return None
        spans = table_spans(t.models[method])
        report = t.inputs.ocv_report
        if report is not None and report.curves:
            spans["ocv"] = [min(c.span[0] for c in report.curves),
                            max(c.span[1] for c in report.curves)]
        rows.append((float(t.temperature_c), spans))
    return rows if len(rows) > 1 else None


def record_usage(result, test_c: float | None) -> None:
    """Fit flags, and the SOC each validation ran through against the measured spans
    (``test_c``: the temperature of a build's one pulse test, :func:`ecmgen.pipeline.
    one_test_c`)."""
    from .model.spans import temperature_note, usage, usage_notes

    report = result.inputs.ocv_report
    ocv_span = None
    if report is not None and report.curves:
        ocv_span = (min(c.span[0] for c in report.curves), max(c.span[1] for c in report.curves))
    for m, vals in result.validations.items():
        result.usage[m] = {}
        rows = _row_spans(result, m)
        for name, v in vals.items():
            use = usage(result.models[m], v, ocv_span, rows)
            result.usage[m][name] = use
            if m == result.best:
                result.notes.extend(named(w, v.source, name) for w in v.warnings)
                result.notes.extend(usage_notes(result.models[m], name, use, ocv_span))
                note = temperature_note(result.models[m], name, v, test_c)
                result.notes.extend([note] if note else [])
