"""The C stage of ``ecmgen build``: generate the C of the best model and check it.

:func:`build_c_outputs` writes ``c/<numeric>/`` with :mod:`ecmgen.c.codegen` and compiles
and compares it with :mod:`ecmgen.c.cbuild`; it sits above both so that the code
generator never imports the cffi build.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..console import detail_of
from ..data.measure import TimeSeries
from ..errors import InputError
from .cbuild import CBuildError, CToolchainMissing, c_equivalence
from .codegen import describe, file_names, generate_c, prepare
from .spec import coarsen_tables
from .golden import write_golden


def build_c_outputs(cfg, result, out_dir, progress=lambda msg: None) -> dict:
    """The C stage of ``ecmgen build`` (called by pipeline._write_c).

    For each numeric of ``cfg.c_numeric`` (prefix ``cfg.c_prefix``, ``cfg.c_dt_s``: None =
    variable dt; the tables on every ``cfg.c_ocv_soc_step``-th / ``c_rc_soc_step``-th SOC
    breakpoint) the files go to ``out_dir/c/<numeric>/``; the C is compiled on the host and
    compared (cbuild.c_equivalence) over the first validation cycle of the best model, at its
    cell temperature (the one the validation simulated on). Returns
    the ``"c"`` block of ``--json``: ``{numeric: {"mae_v", "max_abs_diff_vs_python_v", ...,
    "dir", "files"}}``. Without a host compiler the C is still written and each block says
    ``"skipped"`` with the reason. One piece after the other: :func:`c_plan`, then
    :func:`c_files` and the estimator's two checks (:func:`estimator_part`), which a build
    runs side by side."""
    plan = c_plan(cfg, result)
    block = c_files(cfg, plan, out_dir, progress)
    if plan.check_estimator and "skipped" not in block.get("float", {}):
        detail_of(progress)("checking the C estimator against its references")
        with_estimator(block, plan, *(estimator_part(plan, p) for p in ESTIMATOR_PARTS))
    return block


@dataclass
class CPlan:
    """What the C stage of a build works from (:func:`c_plan`)."""

    model: object                 # the best model, its tables coarsened as configured
    numerics: tuple
    dt_s: float | None
    prefix: str
    steps: dict                   # {"ocv_soc_step", "rc_soc_step"}
    specs: dict                   # numeric -> CSpec
    est_cfg: object | None        # the [estimator] settings baked into the C (None: none)
    est_from: str | None
    est: object | None            # the estimator's EstSpec (float C only)
    series: TimeSeries | None     # the first validation cycle of the best model
    soc0: float | None
    cycle: str                    # its file name
    path: Path | None             # the config (an error's file)

    @property
    def check_estimator(self) -> bool:
        return self.est is not None and self.series is not None


def c_plan(cfg, result) -> CPlan:
    """The best model's specs (checked first), the estimator's settings and the cycle the
    C is compared on (the best model's first validation cycle)."""
    steps = {"ocv_soc_step": getattr(cfg, "c_ocv_soc_step", 1),
             "rc_soc_step": getattr(cfg, "c_rc_soc_step", 1)}
    model = coarsen_tables(result.models[result.best], **steps)     # the flash options
    numerics = tuple(cfg.c_numeric)
    dt_s, prefix = cfg.c_dt_s, cfg.c_prefix
    specs = {n: prepare(model, numeric=n, dt_s=dt_s, prefix=prefix) for n in numerics}  # checks first
    vals = (getattr(result, "validations", None) or {}).get(result.best) or {}
    val = next(iter(vals.values()), None)
    est_cfg = cfg.estimator if getattr(cfg, "c_estimator", None) else None
    est_from = None
    if est_cfg is not None:
        est_cfg, est_from = _estimator_settings(cfg, est_cfg, vals)
    est = None
    if est_cfg is not None and "float" in specs:
        from .estc import prepare_estimator

        est = prepare_estimator(model, specs["float"], est_cfg)           # checks first
    series = None if val is None else TimeSeries(
        val.sim.time_s, val.sim.current_a, val.measured_v, getattr(val, "temperature_c", None),
        source=val.source)
    return CPlan(model, numerics, dt_s, prefix, steps, specs, est_cfg, est_from, est, series,
                 None if val is None else val.soc0,
                 "" if val is None else (Path(val.source).name or "the cycle"),
                 getattr(cfg, "path", None))


def c_files(cfg, plan: CPlan, out_dir, progress=lambda msg: None) -> dict:
    """The C of every numeric and its check against Python (the ``"c"`` block; the
    estimator's figures left to :func:`with_estimator`)."""
    numerics, dt_s, prefix, specs, est = (plan.numerics, plan.dt_s, plan.prefix, plan.specs,
                                          plan.est)
    series, soc0 = plan.series, plan.soc0
    eq: dict = {}
    if series is not None:
        progress(f"checking the C against Python on {plan.cycle}")
        try:
            eq = c_equivalence(plan.model, series, soc0, dt_s=dt_s, prefix=prefix,
                               numerics=numerics)
        except CToolchainMissing as exc:
            eq = {n: {"skipped": str(exc).strip().splitlines()[0]} for n in numerics}
        except CBuildError as exc:
            raise _compile_failed(plan.path, exc) from None
        for r in eq.values():
            r["cycle"] = Path(series.source).name
    out_dir = Path(out_dir)
    block = {}
    for n in numerics:
        detail_of(progress)(f"writing {n} C ({file_names(prefix, n)['source']})")
        files = generate_c(plan.model, out_dir / "c" / n, prefix=prefix, numeric=n, dt_s=dt_s,
                           equivalence={n: eq[n]} if n in eq else None,
                           estimator=plan.est_cfg if n == "float" else None)
        files += write_golden(specs[n], out_dir / "c" / n, series,
                              soc0 if series is not None else 1.0)
        if est is not None and n == "float":
            files += _est_golden(specs[n], est, out_dir / "c" / n, series,
                                 soc0 if series is not None else 1.0)
        entry = dict(eq.get(n, {"skipped": "no validation cycle to compare on"}))
        if est is not None and n == "float":
            entry["estimator"] = ({"skipped": entry["skipped"]} if "skipped" in entry
                                  else {"skipped": "no validation cycle to compare on"})
        entry.update({"dir": f"c/{n}", "files": [p.relative_to(out_dir).as_posix() for p in files],
                      "table_bytes": describe(specs[n])["table_bytes"], **plan.steps,
                      "temperature_rows": describe(specs[n])["points"]["temperatures"]})
        block[n] = entry
    return block


ESTIMATOR_PARTS = ("reference", "python")


def estimator_part(plan: CPlan, part: str, progress=lambda msg: None) -> dict:
    """One of the estimator's checks over the cycle: ``"reference"`` the C filter against
    its float32 reference (bit for bit), with its SOC; ``"python"`` the float64 Python
    filter's SOC (:func:`ecmgen.c.estcheck.estimator_equivalence` is both)."""
    from .estcheck import python_filter_soc, reference_check

    s = plan.series
    if part == "python":
        return {"soc": python_filter_soc(plan.model, s.time_s, s.current_a, s.voltage_v,
                                         plan.soc0, plan.est.settings, s.temperature_c)}
    from .cbuild import compile_spec

    try:
        cm = compile_spec(plan.specs["float"], estimator=plan.est)
    except CToolchainMissing as exc:
        return {"skipped": str(exc).strip().splitlines()[0]}
    except CBuildError as exc:
        raise _compile_failed(plan.path, exc) from None
    return reference_check(cm, s.time_s, s.current_a, s.voltage_v, plan.soc0, s.temperature_c)


def with_estimator(block: dict, plan: CPlan, reference: dict, python: dict) -> dict:
    """The estimator's figures (``--json``) from its two checks, into ``block["float"]``
    unless the C could not be checked."""
    entry = block.get("float")
    if entry is None or "skipped" in entry or "skipped" in reference:
        return block
    from .estcheck import equivalence_figures

    est = plan.est
    out = equivalence_figures(reference, python["soc"])
    out.update({"kind": est.kind, "states": list(est.names), "soc0": float(plan.soc0),
                "model_error": est.settings.model_error,
                "error_correlation_s": est.settings.error_correlation_s})
    out["settings_from"] = plan.est_from
    entry["estimator"] = out
    return block


def _compile_failed(path, exc) -> InputError:
    """The C ecmgen generated does not compile or run: never a build that exits 0."""
    lines = [ln for ln in str(exc).splitlines() if "error" in ln] or str(exc).splitlines()
    return InputError(path,
                      f"the generated C failed its compile check ({lines[0][:300]}); "
                      "nothing was written")


def _est_golden(spec, est, out_dir, series, soc0: float) -> list[Path]:
    """The estimator's golden vectors: the cycle's first steps with its measured voltage,
    or (no cycle) the drive of golden.drive_segment with the model's own voltage."""
    from .estgolden import write_est_golden
    from .golden import cycle_segment, drive_segment

    if series is None:
        return write_est_golden(spec, est, out_dir, drive_segment(spec))
    seg = cycle_segment(spec, series, soc0)
    return write_est_golden(spec, est, out_dir, seg, series.voltage_v[:seg.current_a.size])


def _estimator_settings(cfg, est_cfg, vals: dict):
    """The [estimator] settings baked into the C: model_error and error_correlation_s as
    the config gives them, else measured on the best model's validation cycles (as
    ``ecmgen estimate --config`` does); returns (settings, where the two came from)."""
    from dataclasses import replace

    from ..estimate.residual import pooled, residual_figures

    given = (getattr(cfg, "raw", None) or {}).get("estimator", {})
    if ("model_error" in given and "error_correlation_s" in given) or not vals:
        return est_cfg, "config" if "model_error" in given else "defaults"
    figs = pooled([residual_figures(v, est_cfg.voltage_noise_v) for v in vals.values()])
    return replace(est_cfg, **{k: v for k, v in figs.as_dict().items() if k not in given}), \
        "validation cycles"
