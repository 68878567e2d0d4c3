"""The fleet table: one row per cell x check-up with the figures an ageing study follows.

Read from each row's outputs: model.json through the model package
(:func:`ecmgen.model.load_model`; the discharge table's R0, R_fast, R_slow, tau_fast,
tau_slow and the OCV at each SOC point and temperature point) and the row's record
(ecmgen.fleet.task: the capacity from the tests, the validation MAE, the table quality).
Columns, in this order:

- ``cell``, ``checkup``, ``cycles``, ``throughput_ah``, ``date`` (from the manifest);
- ``capacity_ah`` (from the tests, see ``capacity_from``), ``capacity_rel`` (over the
  cell's first check-up that has one), ``pulses_temperature_c`` (the pulse test's median
  cell temperature), ``temperature_rows`` (of the model's tables);
- ``<p>_soc<SS>_<T>c`` for each parameter p (``r0_ohm``, ``r_fast_ohm``, ``r_slow_ohm``,
  ``tau_fast_s``, ``tau_slow_s``, ``ocv_v``), SOC point SS (percent) and temperature point
  T (degC; ``m10c`` for -10 degC). A one-temperature model gives its one table at every
  temperature point: ``pulses_temperature_c`` is the temperature it was measured at;
- ``roughness``, ``quality_passes`` (ecmgen.fit.quality, the best method's),
  ``fit_rms_mv`` (the mean fit error of its discharge table), ``validation_mae_mv`` (the
  largest over the row's validation cycles; empty without one), ``notes``;
- ``outliers``: the columns in which the row is an outlier (see :func:`mark_outliers`),
  joined by ``;``.

The CSV writes floats in full (repr); ``fleet.parquet`` holds the same columns (needs
pyarrow).
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from ..files import write_atomic
from ..model import load_model
from .manifest import Row
from .task import read_record, row_folder

PARAMETERS = ("r0_ohm", "r_fast_ohm", "r_slow_ohm", "tau_fast_s", "tau_slow_s")
# the columns judged for outliers: the trends a study follows
TREND_PREFIXES = ("capacity_ah", "r0_ohm", "r_fast_ohm", "r_slow_ohm", "ocv_v")
OUTLIER_Z = 3.5           # robust z-score (median / 1.4826 MAD) above which a value is one
MIN_SPREAD = 0.01         # the MAD is taken at least this (relative), so alike cells pass


def temperature_tag(t: float) -> str:
    """25 -> '25c', -10 -> 'm10c', 2.5 -> '2.5c' (a column-name part)."""
    text = f"{abs(t):g}c"
    return ("m" if t < 0 else "") + text


def column(parameter: str, soc: float, temperature_c: float) -> str:
    unit = parameter.rsplit("_", 1)[1]
    name = parameter[: -len(unit) - 1]
    return f"{name}_{unit}_soc{round(100 * soc):02d}_{temperature_tag(temperature_c)}"


def table_rows(rows: list[Row], out: Path, soc_points, temperatures_c) -> list[dict]:
    """One dict per manifest row that has a record (in manifest order)."""
    table = []
    for row in rows:
        folder = row_folder(out, row)
        record = read_record(folder)
        if record is None or not (folder / "model.json").is_file():
            continue
        table.append(_row(row, record, load_model(folder / "model.json"), soc_points,
                          temperatures_c))
    _relative_capacity(table)
    mark_outliers(table)
    return table


def _row(row: Row, record: dict, model, soc_points, temperatures_c) -> dict:
    d = {"cell": row.cell, "checkup": row.checkup, "cycles": row.cycles,
         "throughput_ah": row.throughput_ah, "date": row.date,
         "capacity_ah": record.get("capacity_ah"), "capacity_rel": None,
         "capacity_from": record.get("capacity_from"),
         "pulses_temperature_c": record.get("pulses_temperature_c"),
         "temperature_rows": model.discharge.n_temperatures}
    over_t = model.discharge.n_temperatures > 1
    for t in temperatures_c:
        temp = float(t) if over_t else None
        for s in soc_points:
            p = model.discharge.at(float(s), temp)
            for name in PARAMETERS:
                d[column(name, s, t)] = float(p[name])
            d[column("ocv_v", s, t)] = float(model.ocv.ocv_at(float(s), temp))
    maes = [v for v in (record.get("validation_mae_v") or {}).values() if v is not None]
    fit_error = np.asarray(model.discharge.fit_error, dtype=np.float64)
    finite = fit_error[np.isfinite(fit_error)]
    d.update({"roughness": record.get("roughness"),
              "quality_passes": record.get("quality_passes"),
              "fit_rms_mv": float(np.mean(finite)) * 1e3 if finite.size else None,
              "validation_mae_mv": max(maes) * 1e3 if maes else None,
              "notes": record.get("notes"), "outliers": ""})
    return d


def _relative_capacity(table: list[dict]) -> None:
    first: dict[str, float] = {}
    for d in table:
        q = d["capacity_ah"]
        if q is None:
            continue
        q0 = first.setdefault(d["cell"], q)
        d["capacity_rel"] = q / q0


def trend_columns(table: list[dict]) -> list[str]:
    if not table:
        return []
    return [c for c in table[0] if c.startswith(TREND_PREFIXES)]


def mark_outliers(table: list[dict]) -> None:
    """Mark, per trend column and check-up, the cells whose change since their own first
    check-up lies far from the other cells' (robust z-score above OUTLIER_Z: the median
    and 1.4826 x the median absolute deviation over the cells at that check-up, the
    deviation at least MIN_SPREAD of the median); needs 4 cells or more at a check-up.
    Judging the change, not the value, keeps a cell that was fresh a little apart from
    being marked at every check-up. Sets each row's ``outliers``."""
    first: dict[tuple[str, str], float] = {}
    for d in table:
        for c in trend_columns(table):
            v = d.get(c)
            if v is not None and math.isfinite(v) and v != 0:
                first.setdefault((d["cell"], c), v)
    marks: dict[int, list[str]] = {}
    for c in trend_columns(table):
        by_checkup: dict[str, list[tuple[int, float]]] = {}
        for k, d in enumerate(table):
            v, v0 = d.get(c), first.get((d["cell"], c))
            if v is None or v0 is None or not math.isfinite(v):
                continue
            by_checkup.setdefault(d["checkup"], []).append((k, v / v0))
        for members in by_checkup.values():
            if len(members) < 4:
                continue
            x = np.array([m[1] for m in members])
            med = float(np.median(x))
            spread = max(1.4826 * float(np.median(np.abs(x - med))), MIN_SPREAD * abs(med))
            for (k, _), z in zip(members, np.abs(x - med) / spread):
                if z > OUTLIER_Z:
                    marks.setdefault(k, []).append(c)
    for k, cols in marks.items():
        table[k]["outliers"] = ";".join(cols)


def csv_text(table: list[dict]) -> str:
    buf = io.StringIO()
    if not table:
        return ""
    w = csv.writer(buf, lineterminator="\n")
    names = list(table[0])
    w.writerow(names)
    for d in table:
        w.writerow([_text(d[n]) for n in names])
    return buf.getvalue()


def _text(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def write_table(table: list[dict], out: Path, parquet: bool = True) -> list[Path]:
    """fleet.csv and (``parquet``) fleet.parquet in ``out``; returns the paths written."""
    written = [out / "fleet.csv"]
    write_atomic(written[0], csv_text(table))
    if parquet:
        written.append(write_parquet(table, out / "fleet.parquet"))
    return written


def write_parquet(table: list[dict], path: Path) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = list(table[0]) if table else ["cell", "checkup"]
    cols = {}
    for n in names:
        values = [d.get(n) for d in table]
        if all(v is None or isinstance(v, str) for v in values):
            cols[n] = pa.array(values, type=pa.string())
        elif all(v is None or isinstance(v, bool) for v in values):
            cols[n] = pa.array(values, type=pa.bool_())
        else:
            cols[n] = pa.array([None if v is None else float(v) for v in values],
                               type=pa.float64())
    buf = pa.BufferOutputStream()
    pq.write_table(pa.table(cols), buf)
    write_atomic(path, buf.getvalue().to_pybytes())
    return path
