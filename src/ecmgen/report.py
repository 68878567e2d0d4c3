"""Text outputs of a build: the validation table (terminal and report.md) and --json."""

from __future__ import annotations

from pathlib import Path

from .files import write_atomic


def validation_rows(result) -> list[tuple[str, str, float, float, float, float]]:
    """(method, cycle, mae_mv, rmse_mv, max_mv, mae_soc_gt_10_mv) for every pair."""
    rows = []
    for method, vals in result.validations.items():
        for cycle, v in vals.items():
            rows.append((method, cycle, v.overall.mae_v * 1e3, v.overall.rmse_v * 1e3,
                         v.overall.max_abs_v * 1e3, v.soc_above_10.mae_v * 1e3))
    return rows


def validation_table(result) -> str:
    head = f"{'method':<7} {'cycle':<16} {'MAE mV':>8} {'RMSE mV':>8} {'max mV':>8} {'MAE SOC>10% mV':>15}"
    lines = [head, "-" * len(head)]
    for m, c, mae, rmse, mx, mae10 in validation_rows(result):
        star = " *" if m == result.best else ""
        lines.append(f"{m:<7} {c:<16} {mae:8.2f} {rmse:8.2f} {mx:8.1f} {mae10:15.2f}{star}")
    lines.append(f"(* = model.json, method '{result.best}')")
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
        entry["cycles"] = {name: dict(v.overall.as_dict(), soc0=v.soc0)
                           for name, v in vals.items()}
        validation[method] = entry
    doc = {
        "model": str(out_dir / "model.json") if out_dir else None,
        "best": result.best,
        "models": {m: str(out_dir / f"model-{m}.json") for m in result.models} if out_dir else {},
        "validation": validation,
        "notes": list(result.models[result.best].notes),
    }
    if result.c_report is not None:
        doc["c"] = result.c_report
    return doc


def write_build_report(cfg, result, out_dir: Path) -> Path:
    best = result.models[result.best]
    lines = [
        "# ecmgen build report", "",
        f"config: `{cfg.path.name}`  capacity: {cfg.capacity_ah:g} Ah  methods: "
        f"{', '.join(cfg.methods)}  seed: {cfg.seed}", "",
        "## Validation (simulated - measured voltage)", "", "```", validation_table(result),
        "```", "", "## Notes", "",
    ]
    lines += [f"- {n}" for n in best.notes] or ["- none"]
    lines += ["", "## Inputs", ""]
    lines += [f"- {r.role}: `{r.name}` sha256 {r.sha256[:16]}…" for r in best.inputs]
    lines += ["", f"model.json sha256: {best.sha256()}", ""]
    path = out_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path
