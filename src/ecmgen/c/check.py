"""The C stage of ``ecmgen build``: generate the C of the best model and check it.

:func:`build_c_outputs` writes ``c/<numeric>/`` with :mod:`ecmgen.c.codegen` and compiles
and compares it with :mod:`ecmgen.c.cbuild`; it sits above both so that the code
generator never imports the cffi build.
"""

from __future__ import annotations

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
    ``"skipped"`` with the reason."""
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
    eq: dict = {}
    est_eq: dict | None = None
    series = None
    if val is not None:
        progress(f"checking the C against Python on {Path(val.source).name or 'the cycle'}")
        series = TimeSeries(val.sim.time_s, val.sim.current_a, val.measured_v,
                            getattr(val, "temperature_c", None), source=val.source)
        try:
            eq = c_equivalence(model, series, val.soc0, dt_s=dt_s, prefix=prefix, numerics=numerics)
            if est is not None:
                detail_of(progress)("checking the C estimator against its references")
                est_eq = _estimator_block(model, specs["float"], est, series, val.soc0)
                est_eq["settings_from"] = est_from
        except CToolchainMissing as exc:
            eq = {n: {"skipped": str(exc).strip().splitlines()[0]} for n in numerics}
            est_eq = None if est is None else {"skipped": eq["float"]["skipped"]}
        except CBuildError as exc:
            # the C ecmgen generated does not compile or run: never a build that exits 0
            lines = [ln for ln in str(exc).splitlines() if "error" in ln] or str(exc).splitlines()
            raise InputError(getattr(cfg, "path", None),
                             f"the generated C failed its compile check ({lines[0][:300]}); "
                             "nothing was written") from None
        for r in eq.values():
            r["cycle"] = Path(val.source).name
    out_dir = Path(out_dir)
    block = {}
    for n in numerics:
        detail_of(progress)(f"writing {n} C ({file_names(prefix, n)['source']})")
        files = generate_c(model, out_dir / "c" / n, prefix=prefix, numeric=n, dt_s=dt_s,
                           equivalence={n: eq[n]} if n in eq else None,
                           estimator=est_cfg if n == "float" else None)
        files += write_golden(specs[n], out_dir / "c" / n, series if val is not None else None,
                              val.soc0 if val is not None else 1.0)
        if est is not None and n == "float":
            files += _est_golden(specs[n], est, out_dir / "c" / n, series,
                                 val.soc0 if val is not None else 1.0)
        entry = dict(eq.get(n, {"skipped": "no validation cycle to compare on"}))
        if est is not None and n == "float":
            entry["estimator"] = est_eq or {"skipped": "no validation cycle to compare on"}
        entry.update({"dir": f"c/{n}", "files": [p.relative_to(out_dir).as_posix() for p in files],
                      "table_bytes": describe(specs[n])["table_bytes"], **steps,
                      "temperature_rows": describe(specs[n])["points"]["temperatures"]})
        block[n] = entry
    return block


def _est_golden(spec, est, out_dir, series, soc0: float) -> list[Path]:
    """The estimator's golden vectors: the cycle's first steps with its measured voltage,
    or (no cycle) the drive of golden.drive_segment with the model's own voltage."""
    from .estgolden import write_est_golden
    from .golden import cycle_segment, drive_segment

    if series is None:
        return write_est_golden(spec, est, out_dir, drive_segment(spec))
    seg = cycle_segment(spec, series, soc0)
    return write_est_golden(spec, est, out_dir, seg, series.voltage_v[:seg.current_a.size])


def _estimator_block(model, spec, est, series, soc0: float) -> dict:
    """The estimator's figures of ``--json``: the C filter over the validation cycle from
    the true start SOC with the measured current, against its float32 reference (bit for
    bit) and the float64 Python filter (largest SOC difference)."""
    from .cbuild import compile_spec
    from .estcheck import estimator_equivalence

    cm = compile_spec(spec, estimator=est)
    out = estimator_equivalence(model, cm, series.time_s, series.current_a, series.voltage_v,
                                soc0, series.temperature_c)
    out.update({"kind": est.kind, "states": list(est.names), "soc0": float(soc0),
                "model_error": est.settings.model_error,
                "error_correlation_s": est.settings.error_correlation_s})
    return out


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
