"""Each cell's ageing rates from the fleet table: ``ageing.csv``.

Per cell and trend column (the capacity, R0, R_fast, R_slow and the OCV at each SOC and
temperature point) a straight line through the cell's check-ups against the check-up
axis (ecmgen.fleet.plots.checkup_axis: the cycles, else the throughput, else the days,
else the check-up), least squares:

    cell, quantity, axis, checkups, first, slope, relative_slope, fleet_median, outlier

``first`` is the line's value at the cell's first check-up, ``slope`` its change per unit
of the axis (per cycle, Ah, day or check-up), ``relative_slope`` that over ``first`` (e.g.
-0.0002 per cycle: 2 % of the capacity lost every 100 cycles), ``fleet_median`` the median
relative slope of the cells, ``outlier`` whether the row's cell is marked an outlier in
that column at any check-up (ecmgen.fleet.table.mark_outliers). A cell with fewer than
two check-ups gets no row.
"""

from __future__ import annotations

import math

import numpy as np

from .plots import checkup_axis
from .table import trend_columns

COLUMNS = ("cell", "quantity", "axis", "checkups", "first", "slope", "relative_slope",
           "fleet_median", "outlier")


def ageing_rows(table: list[dict]) -> list[dict]:
    """The rows of ageing.csv (cells in table order, then the trend columns' order)."""
    if not table:
        return []
    x_all, axis = checkup_axis(table)
    rows = []
    for col in trend_columns(table):
        per_cell: dict[str, list[tuple[float, float, bool]]] = {}
        for x, d in zip(x_all, table):
            v = d.get(col)
            if v is not None and math.isfinite(v):
                marked = col in d["outliers"].split(";")
                per_cell.setdefault(d["cell"], []).append((x, float(v), marked))
        fitted = []
        for cell, pts in per_cell.items():
            xs = np.array([p[0] for p in pts])
            if len(pts) < 2 or np.ptp(xs) == 0:
                continue
            ys = np.array([p[1] for p in pts])
            slope, intercept = np.polyfit(xs, ys, 1)
            first = float(intercept + slope * xs.min())
            rel = float(slope / first) if first != 0 else math.nan
            fitted.append({"cell": cell, "quantity": col, "axis": axis, "checkups": len(pts),
                           "first": first, "slope": float(slope), "relative_slope": rel,
                           "fleet_median": None, "outlier": any(p[2] for p in pts)})
        finite = [f["relative_slope"] for f in fitted if math.isfinite(f["relative_slope"])]
        median = float(np.median(finite)) if finite else None
        for f in fitted:
            f["fleet_median"] = median
        rows += fitted
    order = {c: k for k, c in enumerate(dict.fromkeys(d["cell"] for d in table))}
    return sorted(rows, key=lambda r: order[r["cell"]])
