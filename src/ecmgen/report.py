"""Text outputs of a build: the validation table (terminal and report.md) and --json.

A build over temperature reports per cycle and method, each cycle with the range of its
cell temperature, and lists its pulse tests (temperature breakpoints)."""

from __future__ import annotations

import math

import numpy as np
from pathlib import Path

from .files import write_atomic


def _t_range(v) -> tuple[float, float] | None:
    r = v.temperature_range_c
    return None if r is None else (float(r[0]), float(r[1]))


def _temps(values) -> list[float | None]:
    return [float(x) if math.isfinite(x) else None for x in values]


def validation_rows(result) -> list[tuple]:
    """(method, cycle, mae_mv, rmse_mv, max_mv, mae_soc_gt_10_mv, (t_min, t_max) | None)
    for every pair, cycle by cycle (the order of the config), methods in config order."""
    rows = []
    cycles = list(dict.fromkeys(c for vals in result.validations.values() for c in vals))
    for cycle in cycles:
        for method, vals in result.validations.items():
            if cycle not in vals:
                continue
            v = vals[cycle]
            rows.append((method, cycle, v.overall.mae_v * 1e3, v.overall.rmse_v * 1e3,
                         v.overall.max_abs_v * 1e3, v.soc_above_10.mae_v * 1e3, _t_range(v)))
    return rows


def figure(value: float, spec: str, none: str = "-") -> str:
    """``value`` formatted by ``spec``, or ``none`` where it has no value (NaN: e.g. the
    MAE above 10 % SOC of a cycle that never gets there), never "nan"."""
    return format(value, spec) if math.isfinite(value) else format(none, f">{spec.split('.')[0]}")


def validation_table(result) -> str:
    rows = validation_rows(result)
    width = max([16] + [len(r[1]) for r in rows])
    with_t = any(r[6] is not None for r in rows)
    head = (f"{'method':<7} {'cycle':<{width}} {'MAE mV':>8} {'RMSE mV':>8} {'max mV':>8} "
            f"{'MAE SOC>10% mV':>15}" + (f" {'cell degC':>13}" if with_t else ""))
    lines = [head, "-" * len(head)]
    for m, c, mae, rmse, mx, mae10, tr in rows:
        star = " *" if m == result.best else ""
        t = ""
        if with_t:
            t = " " + (f"{f'{tr[0]:.1f}..{tr[1]:.1f}':>13}" if tr else f"{'-':>13}")
        lines.append(f"{m:<7} {c:<{width}} {mae:8.2f} {rmse:8.2f} {mx:8.1f} "
                     f"{figure(mae10, '15.2f')}{t}{star}")
    lines.append(f"(* = model.json, method '{result.best}')")
    return "\n".join(lines)


def pulse_test_table(result) -> str:
    """The pulse tests of a build over temperature: one line per temperature breakpoint."""
    head = f"{'temperature':>12}  {'from':<8} {'pulses':>6} {'DC-IR rows':>10} {'fit s':>6}  file"
    lines = [head, "-" * len(head)]
    for t in sorted(result.tests, key=lambda t: -t.temperature_c):
        src = "config" if t.temperature_from == "configured" else "pulses"
        lines.append(f"{t.temperature_c:9.1f} degC  {src:<8} {len(t.inputs.pulses):6d} "
                     f"{len(t.inputs.dcir):10d} {t.seconds:6.1f}  {t.test.file.name} "
                     f"({t.test.file.parent.name})")
    return "\n".join(lines)


def build_json(result) -> dict:
    out_dir = result.out_dir
    validation = {}
    for method, vals in result.validations.items():
        if not vals:
            continue
        first = next(iter(vals.values()))
        entry = first.overall.as_dict()
        entry["soc_above_10"] = first.soc_above_10.as_dict()
        entry["soc0"] = first.soc0
        entry["cycles"] = {}
        usage = getattr(result, "usage", {}).get(method, {})
        for name, v in vals.items():
            tr = _t_range(v)
            entry["cycles"][name] = dict(
                v.overall.as_dict(), soc0=v.soc0, soc0_how=v.soc0_how,
                soc_above_10=v.soc_above_10.as_dict(),
                warnings=list(v.warnings), voltage_lag_samples=v.voltage_lag_samples,
                **usage.get(name, {}),
                temperature_c=None if tr is None else {"min": tr[0], "max": tr[1]})
        validation[method] = entry
    doc = {
        "model": str(out_dir / "model.json") if out_dir else None,
        "best": result.best,
        "models": {m: str(out_dir / f"model-{m}.json") for m in result.models} if out_dir else {},
        "validation": validation,
        "notes": list(result.models[result.best].notes) + list(getattr(result, "notes", [])),
        "checks": checks_json(result),
        "quality": {m: q.as_dict() for m, q in getattr(result, "quality", {}).items()},
    }
    if result.tests:
        best = result.models[result.best]
        doc["temperature"] = {
            "pulse_tests": [{"file": str(t.test.file), "temperature_c": t.temperature_c,
                             "temperature_from": t.temperature_from, "fit_s": t.seconds}
                            for t in result.tests],
            "table_temperatures_c": _temps(best.discharge.temperature_c),
            "ocv_temperatures_c": _temps(best.ocv.temperature_c),   # null: any temperature
        }
    if result.c_report is not None:
        doc["c"] = result.c_report
    return doc


def checks_json(result) -> dict:
    """What the build could not measure or found suspect: the OCV's sources, spans and
    cross-check, the fit flags (time constants on a bound or beyond the data, levels
    left out) and the SOC span of each model's RC tables."""
    from .model.spans import table_spans

    report = result.inputs.ocv_report
    doc = {
        "ocv": report.as_dict() if report is not None else None,
        "fit_flags": {m: [f.as_dict() for f in flags]
                      for m, flags in getattr(result, "fit_flags", {}).items()},
        "soc_spans": {m: table_spans(model) for m, model in result.models.items()},
    }
    if getattr(result, "tests", None):        # [[data.pulse_tests]]: each test's OCV
        doc["ocv_per_test"] = {t.label: t.inputs.ocv_report.as_dict()
                               for t in result.tests if t.inputs.ocv_report is not None}
    return doc


def quality_lines(result) -> list[str]:
    """report.md's table-quality section: per method the worst roughness, the non-positive
    values and the time constants on a bound; per table row of the best model the
    roughness and where."""
    from .fit.quality import ROUGHNESS_LIMIT

    quality = getattr(result, "quality", {})
    if not quality:
        return []
    lines = ["## Table quality", "",
             "Roughness: the largest |ln p_k - interpolation of ln p at the neighbours| over "
             f"the SOC nodes of any RC table (smooth: below {ROUGHNESS_LIMIT:g}); non-positive: "
             "resistances and time constants <= 0.", "",
             "| method | roughness | non-positive | time constants on a bound | checks |",
             "|---|---|---|---|---|"]
    for m, q in quality.items():
        lines.append(f"| {m} | {q.roughness:.2f} | {q.non_positive} | "
                     f"{', '.join(q.on_bound) or '-'} | {'pass' if q.passes else 'FAIL'} |")
    q = quality.get(result.best)
    if q is not None and q.tables:
        lines += ["", f"Per table of `{result.best}` (the three roughest rows):", "",
                  "| direction | table | degC | roughness | at SOC | <= 0 at SOC |", "|---|---|---|---|---|---|"]
        for t in sorted(q.tables, key=lambda t: -t.roughness)[:3]:
            temp = "-" if not np.isfinite(t.temperature_c) else f"{t.temperature_c:g}"
            at = "-" if not np.isfinite(t.roughest_soc) else f"{t.roughest_soc:g}"
            bad = ", ".join(f"{s:g}" for s in t.non_positive_soc) or "-"
            lines.append(f"| {t.direction} | {t.name} | {temp} | {t.roughness:.2f} | {at} | {bad} |")
    return lines + [""]


def _verdict(ok: bool) -> str:
    return "pass" if ok else "**FAIL**"


def verdict_lines(cfg, result) -> list[str]:
    """report.md's first section: one row per check with what was measured, the
    threshold and pass / FAIL (fit quality, validation, the C, its estimator)."""
    from .fit.quality import ROUGHNESS_LIMIT

    lines = ["## Verdict", "", "| check | measured | passes when | verdict |", "|---|---|---|---|"]
    q = getattr(result, "quality", {}).get(result.best)
    if q is not None:
        lines.append(f"| table quality (`{result.best}`, model.json) | roughness {q.roughness:.2f}, "
                     f"{q.non_positive} values <= 0, {len(q.on_bound)} time constants on a bound "
                     f"| roughness < {ROUGHNESS_LIMIT:g}, no value <= 0 | {_verdict(q.passes)} |")
    vals = result.validations.get(result.best, {})
    if vals:
        limit = getattr(cfg, "max_mae_mv", 50.0)
        worst = max(vals, key=lambda c: vals[c].overall.mae_v)
        over = [c for c, v in vals.items() if v.overall.mae_v * 1e3 > limit]
        lines.append(f"| validation (`{result.best}`, {len(vals)} cycle{'s' if len(vals) > 1 else ''}) "
                     f"| worst MAE {vals[worst].overall.mae_v * 1e3:.1f} mV (`{worst}`)"
                     + (f"; above the limit: {', '.join(f'`{c}`' for c in over)}" if over else "")
                     + f" | MAE <= {limit:g} mV on every cycle (`[report] max_mae_mv`) "
                     f"| {_verdict(not over)} |")
    for numeric, c in (getattr(result, "c_report", None) or {}).items():
        lines.append(_c_verdict(f"C, {numeric}", c))
        if isinstance(c.get("estimator"), dict):
            lines.append(_c_verdict("C SOC estimator", dict(c["estimator"], cycle=c.get("cycle")),
                                    soc=True))
    return lines + [""]


def _c_verdict(what: str, c: dict, soc: bool = False) -> str:
    """A verdict row of the C: bit-identical to its Python reference over the cycle."""
    if "skipped" in c:
        return f"| {what} | not checked: {c['skipped']} | bit-identical to its reference | - |"
    exact = bool(c.get("bit_exact_vs_reference"))
    if soc:
        diff = c.get("max_abs_soc_diff_vs_python")
        far = "" if diff is None else f"; max abs SOC difference from the float64 filter {diff:.2g}"
    else:
        diff = c.get("max_abs_diff_vs_python_v")
        far = "" if diff is None else f"; max abs dv from the float64 model {diff * 1e3:.3g} mV"
    return (f"| {what} | {'bit-identical to' if exact else 'differs from'} its reference over "
            f"`{c.get('cycle') or 'the cycle'}`{far} | bit-identical to its reference | "
            f"{_verdict(exact)} |")


def picture_lines(out_dir: Path) -> list[str]:
    """The build's plots: the validations and parameters shown, the per-test fit plots
    linked."""
    pngs = sorted(p.name for p in Path(out_dir).glob("*.png"))
    shown = [n for n in pngs if n.startswith(("validation-", "parameters-"))]
    linked = [n for n in pngs if n not in shown]
    if not pngs:
        return []
    lines = ["## Plots", ""]
    lines += [f"![{n[:-4]}]({n})" for n in shown]
    if linked:
        lines += ["", "Fits per pulse test: " + ", ".join(f"[{n[:-4]}]({n})" for n in linked)]
    return lines + [""]


def write_build_report(cfg, result, out_dir: Path) -> Path:
    best = result.models[result.best]
    lines = [
        "# ecmgen build report", "",
        f"config: `{cfg.path.name}`  capacity: {cfg.capacity_ah:g} Ah  methods: "
        f"{', '.join(cfg.methods)}  seed: {cfg.seed}", "",
    ]
    lines += verdict_lines(cfg, result)
    if result.tests:
        grid = best.discharge.temperature_c
        c_rows = sorted({c["temperature_rows"] for c in (result.c_report or {}).values()
                         if "temperature_rows" in c})
        in_c = (f"; the C holds both on one grid of {c_rows[0]} rows (the RC rows and the "
                "OCV's joined)" if len(c_rows) == 1 and c_rows[0] != grid.size else "")
        lines += ["## Pulse tests (temperature breakpoints)", "", "```", pulse_test_table(result),
                  "```", "", f"RC tables over {grid.size} temperature rows "
                  f"({grid[0]:g}..{grid[-1]:g} degC), OCV over "
                  f"{best.ocv.n_temperatures} rows{in_c}; see the notes.", ""]
    q = getattr(result, "quality", {}).get(result.best)
    if q is not None and not q.passes:
        from .fit.quality import quality_words

        lines += [f"**Warning: {quality_words(result.best, q)}** (see Table quality).", ""]
    if best.surface_soc_gain:
        lines += [f"Surface SOC (`[model] surface_soc_gain` = {best.surface_soc_gain:g}): r0, "
                  "r_fast, r_slow and their time constants are read at clamp(soc + "
                  "gain u_diff / max(dOCV/dSOC, 0.3 V), 0, 1), u_diff of the previous sample.",
                  ""]
    lines += ["## Validation (simulated - measured voltage)", ""]
    if result.tests:
        lines += ["Each cycle is simulated on its own measured cell temperature; "
                  "`cell degC` is its range over the drive (a soak before it left out).", ""]
    lines += ["```", validation_table(result), "```", ""]
    lagging = {c: v.voltage_lag_samples for c, v in result.validations.get(result.best, {}).items()
               if v.voltage_lag_samples > 0}
    if lagging:
        which = ", ".join(f"`{c}` by {n} sample{'s' if n > 1 else ''}" for c, n in lagging.items())
        lines += [f"The measured voltage lags the current in {which} (see the notes): the "
                  "errors above include it, the data are not shifted.", ""]
    lines += picture_lines(out_dir)
    lines += quality_lines(result)
    lines += ["## Notes", ""]
    notes = list(best.notes) + list(getattr(result, "notes", []))
    lines += [f"- {n}" for n in notes] or ["- none"]
    lines += ["", "## Inputs", ""]
    lines += [f"- {r.role}: `{r.name}` sha256 {r.sha256[:16]}…" for r in best.inputs]
    lines += ["", f"model.json sha256: {best.sha256()}", ""]
    path = out_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path
