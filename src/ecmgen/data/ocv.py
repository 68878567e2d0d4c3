"""OCV(SOC) from a ``soc,ocv_v`` table, a low-rate test, or the rests of a pulse test."""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np

from .errors import InputError
from .measure import TimeSeries
from .model import OcvTable, check_ocv

GRID = np.linspace(0.0, 1.0, 101)
# strictly increasing OCV is needed to invert it; flat LFP plateaus get this tiny slope
MIN_SLOPE_V_PER_SOC = 1e-4


def read_ocv_table(path: str | Path) -> OcvTable:
    """Read a CSV with columns ``soc,ocv_v`` (SOC in 0..1 or percent)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    if not rows:
        raise InputError(path, "empty file")
    header = [h.strip().lower() for h in rows[0]]
    for col in ("soc", "ocv_v"):
        if col not in header:
            raise InputError(path, f"missing column '{col}' (found: {', '.join(header)})")
    js, jv = header.index("soc"), header.index("ocv_v")
    soc, ocv = [], []
    for n, r in enumerate(rows[1:], start=2):
        try:
            soc.append(float(r[js]))
            ocv.append(float(r[jv]))
        except (ValueError, IndexError):
            raise InputError(path, f"row {n}: column soc/ocv_v is not a number") from None
    soc_a, ocv_a = np.array(soc), np.array(ocv)
    if not np.all(np.isfinite(soc_a)) or not np.all(np.isfinite(ocv_a)):
        k = int(np.flatnonzero(~(np.isfinite(soc_a) & np.isfinite(ocv_a)))[0])
        raise InputError(path, f"row {k + 2}: non-finite value in soc/ocv_v")
    if soc_a.size and soc_a.max() > 1.5:
        soc_a = soc_a / 100.0
    check_ocv(soc_a, ocv_a, path)
    return OcvTable(soc_a, ocv_a)


def looks_like_ocv_table(path: str | Path) -> bool:
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return False
    with open(path, newline="") as fh:
        first = fh.readline().strip().lower().replace(" ", "")
    cols = first.split(",")
    return "soc" in cols and "ocv_v" in cols


def _monotone(soc: np.ndarray, ocv: np.ndarray) -> OcvTable:
    """Resample onto GRID, make strictly increasing (isotonic, then a minimal slope)."""
    order = np.argsort(soc)
    soc, ocv = soc[order], ocv[order]
    v = np.interp(GRID, soc, ocv)
    v = _isotonic(v)
    v = v + MIN_SLOPE_V_PER_SOC * GRID  # strictly increasing without moving it by > 0.1 mV
    return OcvTable(GRID.copy(), v)


def _isotonic(y: np.ndarray) -> np.ndarray:
    """Pool-adjacent-violators: the closest non-decreasing sequence (least squares)."""
    vals, wts, lens = [], [], []
    for x in y:
        vals.append(float(x)); wts.append(1.0); lens.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            w = wts[-2] + wts[-1]
            vals[-2] = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / w
            wts[-2] = w
            lens[-2] += lens[-1]
            vals.pop(); wts.pop(); lens.pop()
    return np.repeat(vals, lens)


def ocv_from_low_rate(series: TimeSeries, capacity_ah: float, soc0: float | None = None,
                      branch: str = "both") -> tuple[OcvTable, list[str]]:
    """OCV from a slow (about C/20) charge and/or discharge.

    SOC by coulomb counting from ``soc0`` (default: 1.0 when the test starts with a
    discharge, 0.0 when it starts with a charge). Where both branches exist the OCV is
    their average (cancelling the I*R drop and most hysteresis); a single branch is
    used with a warning. ``branch`` = "charge" or "discharge" uses that branch only
    (e.g. when the other was logged at another temperature)."""
    notes: list[str] = []
    i = series.current_a
    thr = 0.002 * capacity_ah
    moving = np.abs(i) > thr
    if not moving.any():
        raise InputError(series.source, "low-rate OCV test has no current")
    c_rate = np.abs(i[moving]).max() / capacity_ah
    if c_rate > 0.2:
        raise InputError(series.source, f"current reaches {c_rate:.2f} C: not a low-rate OCV test "
                                        "(expected about C/20 or slower)")
    first = i[np.flatnonzero(moving)[0]]
    if soc0 is None:
        soc0 = 1.0 if first < 0 else 0.0
    soc = soc0 + series.coulomb_ah() / capacity_ah
    v = series.voltage_v
    branches = {}
    for name, mask in (("discharge", i < -thr), ("charge", i > thr)):
        if mask.sum() >= 10 and branch in ("both", name):
            branches[name] = (soc[mask], v[mask])
    if not branches:
        raise InputError(series.source, f"low-rate test has no {branch} branch")
    grids = {}
    for name, (s, vv) in branches.items():
        lo, hi = max(s.min(), 0.0), min(s.max(), 1.0)
        order = np.argsort(s)
        g = np.interp(GRID, s[order], vv[order])
        g[(GRID < lo) | (GRID > hi)] = np.nan
        grids[name] = g
    if len(grids) == 2:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # SOC covered by one branch only
            both = np.nanmean(np.vstack([grids["charge"], grids["discharge"]]), axis=0)
        notes.append("OCV: average of the charge and discharge branches of the low-rate test")
    else:
        (name, both), = grids.items()
        chosen = branch != "both"
        notes.append(f"OCV: the {name} branch of the low-rate test (as configured)" if chosen else
                     f"OCV: only the {name} branch of the low-rate test exists; its I*R drop "
                     "and hysteresis stay in the OCV (warning)")
    ok = np.isfinite(both)
    if ok.sum() < 10:
        raise InputError(series.source, "low-rate test covers too little SOC for an OCV table")
    table = _monotone(GRID[ok], both[ok])
    lo, hi = GRID[ok][0], GRID[ok][-1]
    if lo > 0.02 or hi < 0.98:
        notes.append(f"OCV: measured SOC span {lo:.2f}..{hi:.2f}; held flat beyond it")
    check_ocv(table.soc, table.ocv_v, series.source)
    return table, notes


def ocv_from_pulse_rests(series: TimeSeries, pulses, capacity_ah: float, soc0: float
                         ) -> tuple[OcvTable, list[str]]:
    """OCV from the rested voltage before each pulse of a pulse test (the SOC of each
    rest from the same coulomb count as the pulses)."""
    soc = np.array([p.soc for p in pulses])
    v = np.array([series.voltage_v[p.rest_index] for p in pulses])
    order = np.argsort(soc)
    soc, v = soc[order], v[order]
    keep = np.concatenate(([True], np.diff(soc) > 1e-4))
    if keep.sum() < 3:
        raise InputError(series.source, "fewer than 3 rested points for an OCV table")
    table = _monotone(np.clip(soc[keep], 0, 1), v[keep])
    return table, [f"OCV: from {int(keep.sum())} rested voltages of the pulse test, "
                   f"SOC {soc[0]:.2f}..{soc[-1]:.2f}, held flat beyond"]
