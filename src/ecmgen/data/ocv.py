"""OCV(SOC): the :class:`OcvTable` (and its check) and where it comes from: a
``soc,ocv_v`` table, a low-rate test, or the rests of a pulse test.

The OCV stage produces the table that the fits and the model use, so it lives here,
below both; :mod:`ecmgen.model` re-exports it.
"""

from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .measure import TimeSeries

GRID = np.linspace(0.0, 1.0, 101)
# strictly increasing OCV is needed to invert it; flat LFP plateaus get this tiny slope
MIN_SLOPE_V_PER_SOC = 1e-4


def _f64(values, name: str, path) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{name} is not a list of numbers") from None
    if arr.ndim != 1 or arr.size == 0:
        raise InputError(path, f"{name} must be a non-empty 1-D list")
    if not np.all(np.isfinite(arr)):
        raise InputError(path, f"{name} has non-finite values (NaN or inf)")
    return arr


@dataclass(frozen=True)
class OcvTable:
    """Open-circuit voltage over SOC. soc strictly increasing in [0, 1]; ocv_v in volts,
    non-decreasing (strictly increasing where the OCV has to be inverted)."""

    soc: np.ndarray
    ocv_v: np.ndarray

    def __post_init__(self):
        check_ocv(self.soc, self.ocv_v, None)

    def ocv_at(self, soc) -> np.ndarray:
        """OCV in volts; SOC outside the table is clamped to its ends."""
        return np.interp(soc, self.soc, self.ocv_v)

    def soc_at(self, ocv_v) -> np.ndarray:
        """Inverse lookup (OCV -> SOC), clamped to the table ends."""
        return np.interp(ocv_v, self.ocv_v, self.soc)


def check_ocv(soc, ocv_v, path) -> None:
    """Raise InputError unless (soc, ocv_v) is a usable OCV table."""
    soc = _f64(soc, "ocv soc", path)
    ocv_v = _f64(ocv_v, "ocv_v", path)
    if soc.shape != ocv_v.shape:
        raise InputError(path, f"OCV table has {soc.size} SOC points but {ocv_v.size} voltages")
    if soc.size < 2:
        raise InputError(path, "OCV table needs at least 2 points")
    if np.any(np.diff(soc) <= 0):
        k = int(np.flatnonzero(np.diff(soc) <= 0)[0])
        raise InputError(path, f"OCV table SOC is not strictly increasing at row {k + 1} "
                               f"(soc {soc[k]:.6g} then {soc[k + 1]:.6g})")
    if soc[0] < -1e-9 or soc[-1] > 1 + 1e-9:
        raise InputError(path, f"OCV table SOC must lie in [0, 1], got {soc[0]:.6g}..{soc[-1]:.6g}")
    if np.any(np.diff(ocv_v) <= 0):
        k = int(np.flatnonzero(np.diff(ocv_v) <= 0)[0])
        raise InputError(path, f"OCV is not monotonic in SOC: ocv_v falls from {ocv_v[k]:.6g} V "
                               f"to {ocv_v[k + 1]:.6g} V between soc {soc[k]:.6g} and {soc[k + 1]:.6g}")
    if ocv_v[0] < 0.5 or ocv_v[-1] > 6.0:
        raise InputError(path, f"OCV values {ocv_v[0]:.4g}..{ocv_v[-1]:.4g} V are not plausible "
                               "cell voltages (mV given as V?)")


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
