"""An ageing law from a fleet (``ecmgen age FLEET_DIR --out MODEL.json``): the fleet's
resistance and capacity over equivalent full cycles, written into a base model as its
``ageing`` section (ecmgen.model.ageing), which the C then takes as a run-time input.

From ``fleet.csv`` (ecmgen.fleet.table), per row:

- its age: the manifest's ``cycles`` (taken as equivalent full cycles), else its
  ``throughput_ah`` over twice the base model's capacity (one full cycle moves the capacity
  out and back in);
- its resistance ratio: the median over the table's R0 columns (every SOC and temperature
  point) of each column's value over the cell's row at the fleet's first check-up (the
  check-up of the smallest median age; a cell without a row there - its first check-up
  failed - is left out, as it has no fresh reference; R0 must be positive). R0 because it is what a
  pulse test measures best (the voltage step at the current step): on the synthetic study
  (5 cells x 3 check-ups, tests/test_fleet_law.py) the law from R0 is within 0.007 of the
  truth, from R0 and R_fast within 0.02, and with R_slow (which 10 s pulses do not pin
  down: one cell's R_slow ratios run 0.5 to 3.4 while its R0 moves 8 %) 0.06 off, 0.12
  off when summed instead of the median. The scale is then applied to every resistance,
  as a growing film or contact resistance does;
- its capacity ratio: ``capacity_ah`` (the tests' capacity) over the cell's at the first
  check-up.

The law is pooled per check-up, not fitted per cell: a breakpoint at each check-up (its
median age over the cells), each scale the median over the cells of their ratios there.
The median keeps a minority of outlier cells (one cell of six ageing 3x faster) from moving
the law, and the per-check-up breakpoints keep a knee if the study has one, where a
straight line through each cell's rates (ageing.csv) would average it away. Both scales are
1 at the first check-up by construction; the base model should be a cell measured there.
"""

from __future__ import annotations

import csv
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import write_atomic
from ..model import load_model
from ..model.ageing import MAX_BREAKPOINTS, AgeingLaw
from .table import PARAMETERS

LAW_COLUMNS = PARAMETERS[0]         # r0_ohm (see the module)


def read_fleet_csv(path: Path) -> list[dict]:
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise InputError(path, "no such file (run `ecmgen fleet` into this folder first)") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"not a fleet table (a CSV text file): {exc}") from None
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    if not rows:
        raise InputError(path, "the fleet table has no rows")
    if not {"cell", "checkup"} <= set(rows[0]):
        raise InputError(path, "not a fleet table: no cell and checkup columns")
    return rows


def _number(row: dict, key: str) -> float | None:
    text = row.get(key) or ""
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def row_ages(rows: list[dict], capacity_ah: float, path: Path) -> list[float]:
    """Each row's equivalent full cycles (see the module)."""
    if all(_number(r, "cycles") is not None for r in rows):
        return [_number(r, "cycles") for r in rows]
    if all(_number(r, "throughput_ah") is not None for r in rows):
        return [_number(r, "throughput_ah") / (2.0 * capacity_ah) for r in rows]
    raise InputError(path, "an ageing law needs every row's age: give the manifest a cycles "
                           "or throughput_ah column")


def _resistance_ratio(row: dict, first: dict, columns: list[str]) -> float | None:
    """The median over ``columns`` of row / first (columns missing in either are left out)."""
    ratios = [v / f for c in columns
              if (v := _number(row, c)) is not None and (f := _number(first, c))]
    return float(np.median(ratios)) if ratios else None


def first_checkup(rows: list[dict], ages: list[float]) -> str:
    """The fleet's first check-up: the one of the smallest median age."""
    by: dict[str, list[float]] = {}
    for age, r in zip(ages, rows):
        by.setdefault(r["checkup"], []).append(age)
    return min(by, key=lambda k: (float(np.median(by[k])), k))


def _check_resistances(rows: list[dict], columns: list[str], path: Path) -> None:
    """A resistance that is not positive is a failed fit, not an ageing ratio."""
    bad = [f"{r['cell']} check-up {r['checkup']} {c} = {v:g}" for r in rows for c in columns
           if (v := _number(r, c)) is not None and v <= 0]
    if bad:
        raise InputError(path, f"R0 must be positive: {'; '.join(bad[:3])}"
                               + (f" (and {len(bad) - 3} more)" if len(bad) > 3 else ""))


def fit_ageing_law(rows: list[dict], capacity_ah: float, path: Path,
                   notes: list[str] | None = None) -> AgeingLaw:
    """The fleet's law pooled per check-up (see the module) from the rows of fleet.csv.
    Each cell's ratios are over its own row at the fleet's first check-up: a cell whose
    first check-up has no row (it failed) has no fresh reference and is left out (named
    in ``notes``), instead of counting a later check-up as its age 0."""
    columns = [c for c in rows[0] if c.startswith(f"{LAW_COLUMNS}_soc")]
    if not columns:
        raise InputError(path, "the fleet table has no R0 columns")
    _check_resistances(rows, columns, path)
    ages = row_ages(rows, capacity_ah, path)
    start = first_checkup(rows, ages)
    first = {r["cell"]: r for r in rows if r["checkup"] == start}
    left_out = sorted({r["cell"] for r in rows} - set(first))
    if left_out and notes is not None:
        notes.append(f"cells without a row at the first check-up ({start}): "
                     f"{', '.join(left_out)}; left out of the law (no fresh reference)")
    groups: dict[str, list[tuple[float, float, float]]] = {}
    for age, r in zip(ages, rows):
        ref = first.get(r["cell"])
        if ref is None:
            continue
        ratio = _resistance_ratio(r, ref, columns)
        q, q0 = _number(r, "capacity_ah"), _number(ref, "capacity_ah")
        q_rel = q / q0 if q is not None and q0 else None
        if ratio is None or q_rel is None:
            continue
        groups.setdefault(r["checkup"], []).append((age, ratio, q_rel))
    points = sorted((float(np.median([g[0] for g in v])), float(np.median([g[1] for g in v])),
                     float(np.median([g[2] for g in v])), k) for k, v in groups.items())
    if len(points) < 2:
        raise InputError(path, "an ageing law needs at least two check-ups with a resistance "
                               "and a capacity")
    if len(points) > MAX_BREAKPOINTS:
        raise InputError(path, f"{len(points)} check-ups; an ageing law holds at most "
                               f"{MAX_BREAKPOINTS}")
    x = np.array([p[0] for p in points])
    if np.any(np.diff(x) <= 0):
        raise InputError(path, "two check-ups have the same median age; the law's "
                               "breakpoints must increase")
    r = np.array([p[1] for p in points])
    q = np.array([p[2] for p in points])
    source = (f"ecmgen age: {len(first)} cells, check-ups "
              f"{', '.join(p[3] for p in points)}; per check-up the median over the cells of "
              "(the median of its R0 columns) and of the capacity, each over the cell's "
              "first check-up")
    try:
        return AgeingLaw(x - x[0] if x[0] < 0 else x, r / r[0], q / q[0], source)
    except ValueError as exc:
        raise InputError(path, f"the fleet's ageing law is not one ecmgen takes: {exc}") from None


def base_model_path(fleet_dir: Path, rows: list[dict]) -> Path:
    """The default base model: a cell's model at the fleet's first check-up (the first
    such row not marked an outlier; the fleet's own model of a fresh cell), never a later
    check-up of a cell whose first one failed."""
    ages = row_ages(rows, 1.0, fleet_dir / "fleet.csv") if _has_ages(rows) else \
        [float(n) for n in range(len(rows))]
    start = first_checkup(rows, ages)
    at_start = [r for r in rows if r["checkup"] == start]
    r = next((r for r in at_start if not r.get("outliers")), at_start[0])
    return fleet_dir / r["cell"] / r["checkup"] / "model.json"


def _has_ages(rows: list[dict]) -> bool:
    return any(all(_number(r, k) is not None for r in rows) for k in ("cycles", "throughput_ah"))


def write_aged_model(fleet_dir, out, base=None, notes: list[str] | None = None
                     ) -> tuple[Path, AgeingLaw, Path]:
    """``ecmgen age``: the law of the fleet in ``fleet_dir`` into the base model (``base``,
    or :func:`base_model_path`), written to ``out``; returns (out, law, base). ``out`` may
    be none of the files read (the fleet table, the base model) nor a row's model."""
    from ..outputs import check_output_file

    fleet_dir = Path(fleet_dir)
    table = fleet_dir / "fleet.csv"
    rows = read_fleet_csv(table)
    base = Path(base) if base is not None else base_model_path(fleet_dir, rows)
    models = [fleet_dir / r["cell"] / r["checkup"] / "model.json" for r in rows]
    out = check_output_file(out, [table, fleet_dir / "fleet.parquet", base, *models])
    model = load_model(base)
    law = fit_ageing_law(rows, model.capacity_ah, table, notes)
    write_atomic(out, replace(model, ageing=law).to_json())
    return out, law, base
