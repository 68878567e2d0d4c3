"""OCV(SOC): the :class:`OcvTable` (and its check) and where it comes from.

Sources (``data.ocv``, one or a list):

* a ``soc,ocv_v`` table (CSV);
* a low-rate (pseudo-OCV) test: one cycle of it (:mod:`ecmgen.data.lowrate`), each
  branch normalised to its own charge (0..1 over its own Ah), the OCV the mean of the
  discharge and charge branches; where the cell rested after a cut-off, that rested
  voltage is the OCV at the branch's end (SOC 0 or 1);
* ``"pulses"``: the rested voltages of the pulse test (every rest of at least
  ``MIN_OCV_REST_S``, including the rests after a cut-off), at the SOC the coulomb
  count gives them.

Each source gives an :class:`OcvCurve` over the SOC span it measured. Several sources
are merged in the order given (:func:`merge_curves`): the first defines the OCV over
its span; each further one only extends the span beyond what is covered, shifted so
that it meets the OCV at the joint, the shift fading linearly to none at the far end
of what it adds (so its own end, e.g. a rest after the cut-off, is kept); beyond every
span the OCV is held flat (noted). A flat OCV (:func:`check_not_flat`) is an error, and :func:`cross_check`
compares the OCV with the pulse test's rested voltages.

The OCV stage produces the table that the fits and the model use, so it lives here,
below both; :mod:`ecmgen.model` re-exports it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputError, reading
from .measure import TimeSeries

GRID = np.linspace(0.0, 1.0, 101)
# derived tables get this tiny slope, so that they stay strictly increasing (a table
# given by the user may be flat in places: an LFP plateau rounded to 1 mV)
MIN_SLOPE_V_PER_SOC = 1e-4
MIN_OCV_REST_S = 300.0      # a rest this long gives a rested (OCV) voltage
# a source filling past the first one that meets it further off than this is warned about:
# measured at the joint with the Panasonic 25 degC C/20 file, 19 / 44 / 49 / 74 mV from the
# 25 / 0 / -10 / -20 degC tests' rests (the same cell; the cold ones at another
# temperature), 173 mV for the Leaf's cycling file against its 25 degC rests (a cycle at
# an unlabelled ambient)
JOINT_WARN_V = 0.05
FLAT_WINDOW_SOC = 0.5       # an OCV rising less than FLAT_RISE_V over half the SOC
FLAT_RISE_V = 0.005         # range carries no SOC information (LFP plateaus: >= 40 mV)
# The OCV cross-check warns above this RMS difference from the pulse test's rested
# voltages. Rested voltages of one cell scatter by 1-3 mV about a smooth OCV (logger
# noise, relaxation left after 20 min); the held-out drive cycles validate at 12-20 mV
# MAE. 10 mV is well above the scatter and half of the validation error: a difference
# that size is a different OCV (another branch, another temperature or age).
OCV_CHECK_RMS_V = 0.010


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
    non-decreasing (a flat run, e.g. an LFP plateau rounded to 1 mV, is allowed)."""

    soc: np.ndarray
    ocv_v: np.ndarray

    def __post_init__(self):
        check_ocv(self.soc, self.ocv_v, None)

    def ocv_at(self, soc) -> np.ndarray:
        """OCV in volts; SOC outside the table is clamped to its ends."""
        return np.interp(soc, self.soc, self.ocv_v)

    def soc_at(self, ocv_v) -> np.ndarray:
        """Inverse lookup (OCV -> SOC), clamped to the table ends. A voltage on a flat
        run of the table maps to the middle of the run."""
        v, first = np.unique(self.ocv_v, return_index=True)
        if v.size == self.ocv_v.size:
            return np.interp(ocv_v, self.ocv_v, self.soc)
        last = self.ocv_v.size - 1 - np.unique(self.ocv_v[::-1], return_index=True)[1]
        # a flat run spans [first, last]: approached from below it starts at its first
        # SOC, from above at its last; exactly on it, the middle
        xp = np.column_stack([v, v + 1e-9]).ravel()
        fp = np.column_stack([self.soc[first], self.soc[last]]).ravel()
        x = np.asarray(ocv_v, dtype=np.float64)
        out = np.interp(x, xp, fp)
        k = np.clip(np.searchsorted(v, x), 0, v.size - 1)
        on = v[k] == x
        return np.where(on, 0.5 * (self.soc[first][k] + self.soc[last][k]), out)


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
    if np.any(np.diff(ocv_v) < 0):
        k = int(np.flatnonzero(np.diff(ocv_v) < 0)[0])
        raise InputError(path, f"OCV is not monotonic in SOC: ocv_v falls from {ocv_v[k]:.6g} V "
                               f"to {ocv_v[k + 1]:.6g} V between soc {soc[k]:.6g} and {soc[k + 1]:.6g}")
    if ocv_v[0] < 0.5 or ocv_v[-1] > 6.0:
        raise InputError(path, f"OCV values {ocv_v[0]:.4g}..{ocv_v[-1]:.4g} V are not plausible "
                               "cell voltages (mV given as V?)")


def read_ocv_table(path: str | Path) -> OcvTable:
    """Read a CSV with columns ``soc,ocv_v`` (SOC in 0..1 or percent)."""
    with reading(path):
        return _read_ocv_table(path)


def _read_ocv_table(path: str | Path) -> OcvTable:
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
    with reading(path), open(path, newline="", errors="replace") as fh:
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


# --------------------------------------------------------------------------- sources

@dataclass(frozen=True)
class OcvCurve:
    """One source's OCV over the SOC span it measured (GRID points within the span).

    name       the source as configured ("pulses" or a file name)
    soc, ocv_v non-decreasing OCV at the GRID points in [span_lo, span_hi]
    notes      what was done (for the model's notes)
    capacity_ah  charge of each low-rate branch used ({"discharge": 2.99, ...}), if any
    raw        (label, soc, voltage) of what it was made from, for the OCV plot
    """

    name: str
    soc: np.ndarray
    ocv_v: np.ndarray
    notes: tuple[str, ...] = ()
    capacity_ah: dict = field(default_factory=dict)
    raw: tuple = ()
    branches: dict = field(default_factory=dict)   # low-rate: direction -> (soc, ocv_v)
    exact: bool = False      # a user's table: used as given when it is the only source
    temperature_c: float | None = None   # a low-rate test's median cell temperature

    @property
    def span(self) -> tuple[float, float]:
        return float(self.soc[0]), float(self.soc[-1])


def _on_grid(soc: np.ndarray, v: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Points -> a non-decreasing curve at the GRID points within [lo, hi]."""
    order = np.argsort(soc, kind="stable")
    soc, v = soc[order], v[order]
    g = GRID[(GRID >= lo - 0.005) & (GRID <= hi + 0.005)]   # to the nearest grid point
    if g.size < 2:
        g = np.array([lo, hi])
    return g, _isotonic(np.interp(g, soc, v))


def curve_from_table(table: OcvTable, name: str) -> OcvCurve:
    return OcvCurve(name, table.soc.copy(), table.ocv_v.copy(),
                    (f"OCV: {name}, a soc,ocv_v table (SOC {table.soc[0]:.2f}.."
                     f"{table.soc[-1]:.2f})",), raw=(("table", table.soc, table.ocv_v),),
                    exact=True)


def curve_from_rests(soc, v, name: str, source, what: str = "rested voltages of the pulse test"
                     ) -> OcvCurve:
    """OCV from rested voltages at known SOC (e.g. the rests of a pulse test)."""
    soc = np.asarray(soc, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    order = np.argsort(soc, kind="stable")
    soc, v = soc[order], v[order]
    keep = np.concatenate(([True], np.diff(soc) > 1e-4))
    if keep.sum() < 3:
        raise InputError(source, f"fewer than 3 rested points for an OCV table "
                                 f"(rests of at least {MIN_OCV_REST_S:g} s)")
    s, vv = np.clip(soc[keep], 0.0, 1.0), v[keep]
    g, c = _on_grid(s, vv, s[0], s[-1])
    return OcvCurve(name, g, c, (f"OCV: {name}, {int(keep.sum())} {what}, SOC "
                                 f"{s[0]:.2f}..{s[-1]:.2f}",),
                    raw=(("rests", s, vv),))


def curve_from_low_rate(series: TimeSeries, capacity_ah: float, name: str, *,
                        soc0: float | None = None, branch: str = "both",
                        cycle: int | None = None) -> OcvCurve:
    """OCV from one cycle of a low-rate test (see the module docstring).

    ``soc0`` None: each branch normalised to its own charge; a number: SOC counted with
    ``capacity_ah`` from ``soc0`` at the record's first sample (for a test that does
    not run from full to empty). ``branch``: "both" (their average), "discharge",
    "charge", or "auto" (the average until :func:`choose_reading` picks the reading
    that matches a pulse test's rests). Every reading of the cycle is kept in
    ``branches`` ({"both": (soc, ocv_v), "discharge": ..., "charge": ...})."""
    from .lowrate import choose_branches, split_low_rate

    test = split_low_rate(series, capacity_ah)
    chosen, what = choose_branches(test, series.source, cycle,
                                   "both" if branch == "auto" else branch)
    notes: list[str] = []
    curves, raw = _branch_curves(series, chosen, capacity_ah, soc0)
    caps = {b.direction: b.charge_ah for b, _, _ in curves}
    # the rest after a complete branch's cut-off: the OCV at that branch's end
    anchors = {} if soc0 is not None else _end_anchors(series, curves, notes, raw)
    readings = _readings(curves, anchors)
    if "both" in readings and branch in ("both", "auto"):
        key = "both"
        how = "the average of its discharge and charge branches" + (
            " (data.ocv_branch auto: the reading that matches the pulse test's rests is "
            "chosen below)" if branch == "auto" else "")
    else:
        key = branch if branch in readings else curves[-1][0].direction
        how = (f"its {key} branch (as configured)" if branch == key else
               f"only the {key} branch of a cycle exists; its I*R drop and hysteresis stay "
               "in the OCV (warning)")
    charge_text = ", ".join(f"{d} {q:.4g} Ah" for d, q in caps.items())
    norm = ("each branch normalised to its own charge" if soc0 is None else
            f"SOC counted from data.ocv_soc0 = {soc0:g} with {capacity_ah:g} Ah")
    notes.insert(0, f"OCV: {name}, {what}: {how}; measured charge {charge_text} "
                    f"(cell.capacity_ah {capacity_ah:g} Ah); {norm}")
    if len(caps) == 2:
        qd, qc = caps["discharge"], caps["charge"]
        if abs(qd - qc) > 0.05 * max(qd, qc):
            notes.insert(1, f"OCV: the low-rate branches of {name} moved different charge "
                            f"(discharge {qd:.4g} Ah, charge {qc:.4g} Ah, "
                            f"{abs(qd - qc) / max(qd, qc):.0%} apart): check the test (warning)")
    g, c = readings[key]
    temp = None if series.temperature_c is None else float(np.median(series.temperature_c))
    return OcvCurve(name, g, c, tuple(notes), caps, tuple(raw),
                    readings if len(readings) > 1 else {}, temperature_c=temp)


def _branch_curves(series: TimeSeries, chosen, capacity_ah: float, soc0: float | None):
    """Each chosen branch on the SOC grid: [(branch, grid, ocv_v)] and the raw readings
    [(label, soc, voltage)] for the plot."""
    curves, raw = [], []
    for b in chosen:
        if soc0 is None:
            s = b.normalised_soc(series)
        else:
            s = soc0 + series.coulomb_ah()[b.start:b.stop] / capacity_ah
        v = series.voltage_v[b.start:b.stop]
        lo, hi = max(float(s.min()), 0.0), min(float(s.max()), 1.0)
        if hi - lo < 0.1:
            raise InputError(series.source, f"the low-rate {b.direction} branch covers SOC "
                                            f"{lo:.2f}..{hi:.2f} only: too little for an OCV")
        g, c = _on_grid(s, v, lo, hi)
        curves.append((b, g, c.copy()))
        raw.append((f"{b.direction} branch", s, v))
    return curves, raw


def _end_anchors(series: TimeSeries, curves, notes: list[str], raw: list) -> dict:
    """SOC 0 (1) -> the rested voltage after a complete discharge (charge) branch's
    cut-off; each said in ``notes`` and kept in ``raw``."""
    anchors = {}
    for b, _, _ in curves:
        k = _end_rest(series, b)
        if k is None:
            continue
        end = 0.0 if b.direction == "discharge" else 1.0
        anchors[end] = float(series.voltage_v[k])
        notes.append(f"OCV: SOC {end:g} after the {b.direction} from the rested voltage "
                     f"{anchors[end]:.4f} V "
                     f"{series.time_s[k] - series.time_s[b.stop - 1]:.0f} s after the cut-off")
        raw.append((f"rest after the {b.direction}", np.array([end]), np.array([anchors[end]])))
    return anchors


def _readings(curves, anchors: dict) -> dict:
    """Every reading of the cycle (each branch, and "both": their average where they
    overlap by 0.1 SOC), its ends at the anchors, made monotonic."""
    readings = {b.direction: (g, c) for b, g, c in curves}
    lo = max(g[0] for _, g, _ in curves)
    hi = min(g[-1] for _, g, _ in curves)
    if len(curves) == 2 and hi - lo >= 0.1:
        g = GRID[(GRID >= lo - 1e-9) & (GRID <= hi + 1e-9)]
        readings["both"] = (g, 0.5 * sum(np.interp(g, gg, cc) for _, gg, cc in curves))
    for key, (g, c) in readings.items():
        c = c.copy()
        for end, value in anchors.items():
            at = 0 if end == 0.0 else -1
            if abs(g[at] - end) < 1e-9:
                c[at] = value
        readings[key] = (g, _isotonic(c))
    return readings


def choose_reading(curve: OcvCurve, rest_soc, rest_v) -> tuple[OcvCurve, dict, str]:
    """data.ocv_branch = "auto": of a low-rate cycle's readings (the average, the
    discharge branch, the charge branch), the one closest (RMS) to a pulse test's rested
    voltages, which are the cell's OCV under the pulse test's conditions (after its
    discharges the cell sits on the discharge side of its hysteresis). Returns the curve
    of that reading, the RMS of every reading and the name of the chosen one."""
    rest_soc, rest_v = np.asarray(rest_soc, float), np.asarray(rest_v, float)
    rms = {k: float(np.sqrt(np.mean((rest_v - np.interp(rest_soc, g, c)) ** 2)))
           for k, (g, c) in curve.branches.items()}
    best = min(rms, key=lambda k: (rms[k], k != "both"))
    g, c = curve.branches[best]
    text = ", ".join(f"{'the average' if k == 'both' else f'the {k} branch'} "
                     f"{v * 1e3:.1f} mV" for k, v in rms.items())
    what = "the average of both branches" if best == "both" else f"its {best} branch"
    note = (f"OCV: {curve.name}, data.ocv_branch auto: {what}, the reading closest to the "
            f"{rest_v.size} rested voltages of the pulse test (RMS: {text})")
    return replace(curve, soc=g, ocv_v=c, notes=curve.notes + (note,)), rms, best


def _end_rest(series: TimeSeries, b) -> int | None:
    """The sample of the rest after a complete branch's cut-off that stands for the OCV:
    at most one hour into the rest, and before the temperature leaves +-3 K of the
    branch's (a chamber changing set point)."""
    from .lowrate import MIN_END_REST_S

    if not b.complete or b.rest_after_s < MIN_END_REST_S:
        return None
    t = series.time_s
    stop = int(np.searchsorted(t, t[b.stop - 1] + 3600.0, side="right"))
    k = min(b.rest_end, stop - 1)
    if series.temperature_c is not None:
        tb = float(np.median(series.temperature_c[b.start:b.stop]))
        off = np.flatnonzero(np.abs(series.temperature_c[b.stop:k + 1] - tb) > 3.0)
        if off.size:
            k = b.stop + int(off[0]) - 1
    if t[k] - t[b.stop - 1] < MIN_END_REST_S:
        return None
    return k


def merge_curves(curves: list[OcvCurve]) -> tuple[OcvTable, list[str], np.ndarray]:
    """One OCV table from the sources in order (see the module docstring). Also returns,
    per GRID point, the index of the source it came from (-1: held flat)."""
    v = np.full(GRID.size, np.nan)
    origin = np.full(GRID.size, -1)
    notes: list[str] = []
    if len(curves) == 1 and curves[0].exact:       # a user's table alone: as given
        c = curves[0]
        origin[(GRID >= c.soc[0] - 1e-9) & (GRID <= c.soc[-1] + 1e-9)] = 0
        if c.soc[0] > 0.005 or c.soc[-1] < 0.995:
            notes.append(f"OCV: measured SOC span {c.soc[0]:.2f}..{c.soc[-1]:.2f}; held flat "
                         "beyond it")
        return OcvTable(c.soc.copy(), c.ocv_v.copy()), notes, origin
    for n, c in enumerate(curves):
        cv = np.full(GRID.size, np.nan)
        ix = np.round(c.soc * 100).astype(int)
        if np.allclose(GRID[ix], c.soc):
            cv[ix] = c.ocv_v
        else:
            inside = (GRID >= c.soc[0]) & (GRID <= c.soc[-1])
            cv[inside] = np.interp(GRID[inside], c.soc, c.ocv_v)
        if n == 0:
            v = cv
            origin[np.isfinite(cv)] = 0
            continue
        have = np.flatnonzero(np.isfinite(v))
        lo, hi = have[0], have[-1]
        for side, sel, joint in (("below", np.arange(GRID.size) < lo, lo),
                                 ("above", np.arange(GRID.size) > hi, hi)):
            take = sel & np.isfinite(cv)
            if not take.any():
                continue
            shift = float(v[joint] - cv[joint]) if np.isfinite(cv[joint]) else 0.0
            ix = np.flatnonzero(take)
            far = ix[0] if side == "below" else ix[-1]
            # the shift fades linearly from the joint to the far end of the added span
            fade = np.abs(ix - far) / max(abs(joint - far), 1)
            v[ix] = cv[ix] + shift * fade
            origin[take] = n
            span = GRID[take]
            notes.append(f"OCV: SOC {span[0]:.2f}..{span[-1]:.2f} from {c.name}"
                         + (f", shifted by {shift * 1e3:+.1f} mV at SOC {GRID[joint]:.2f} to "
                            f"meet {curves[0].name}, the shift fading to none at SOC "
                            f"{GRID[far]:.2f}" if abs(shift) >= 5e-5 else "")
                         + _joint_warning(shift, c.name, curves[0].name, side, GRID[joint]))
    ok = np.flatnonzero(np.isfinite(v))
    lo, hi = GRID[ok[0]], GRID[ok[-1]]
    table = _monotone(GRID[ok], v[ok])
    if lo > 0.005 or hi < 0.995:
        notes.append(f"OCV: measured SOC span {lo:.2f}..{hi:.2f}; held flat beyond it")
    return table, notes, origin


def _joint_warning(shift_v: float, name: str, first: str, side: str, soc: float) -> str:
    """The words of a warning when a source filling past the first one meets it
    ``shift_v`` away: more than JOINT_WARN_V, it is not the same cell state's OCV
    (another temperature, age or cycle) and its filled part is a guess."""
    if abs(shift_v) <= JOINT_WARN_V:
        return ""
    return (f"; warning: {name} is {abs(shift_v) * 1e3:.0f} mV from {first} where they meet "
            f"(more than {JOINT_WARN_V * 1e3:g} mV: another temperature, age or cycle?), so "
            f"the OCV {side} SOC {soc:.2f} is a guess: check data.ocv_cycle / "
            "data.ocv_branch, or leave the file out (the OCV is then held flat there)")


def check_not_flat(table: OcvTable, source, origin=None, sources=()) -> None:
    """InputError when the OCV rises less than FLAT_RISE_V over a FLAT_WINDOW_SOC window
    of SOC: such an OCV cannot tell SOC (a low-rate test read wrongly, a source that
    covers a small part of the range). The error names ``source``, or, given the
    ``origin`` of each GRID point (from :func:`merge_curves`) and the ``sources``, the
    source the flat stretch mostly came from."""
    g = GRID
    v = table.ocv_at(g)
    n = int(round(FLAT_WINDOW_SOC * (g.size - 1)))
    rise = v[n:] - v[:-n]
    k = int(np.argmin(rise))
    if rise[k] < FLAT_RISE_V:
        # the widest flat stretch around the window
        a, b = k, k + n
        while a > 0 and v[b] - v[a - 1] < FLAT_RISE_V:
            a -= 1
        while b < g.size - 1 and v[b + 1] - v[a] < FLAT_RISE_V:
            b += 1
        if origin is not None and len(sources):
            held = origin[a:b + 1]
            counts = np.bincount(held[held >= 0], minlength=len(sources))
            source = sources[int(np.argmax(counts))] if counts.sum() else sources[0]
        raise InputError(source, f"the OCV is flat: it rises {rise[k] * 1e3:.1f} mV over SOC "
                                 f"{g[a]:.2f}..{g[b]:.2f} (at {v[a]:.4f} V), so it cannot "
                                 "tell SOC; the OCV source does not cover that range or "
                                 "was not read right (data.ocv, data.ocv_cycle)")


@dataclass(frozen=True)
class OcvCheck:
    """The OCV against a pulse test's rested voltages."""

    rms_v: float
    mean_v: float            # mean of rested voltage - OCV
    max_abs_v: float
    n: int
    threshold_v: float
    warning: bool
    better: str              # the source judged better ("pulses" or the chosen OCV)
    note: str

    def as_dict(self) -> dict:
        return {"rms_v": self.rms_v, "mean_v": self.mean_v, "max_abs_v": self.max_abs_v,
                "n": self.n, "threshold_v": self.threshold_v, "warning": self.warning,
                "better": self.better}


def cross_check(table: OcvTable, soc, v, rest_s, chosen: str,
                threshold_v: float = OCV_CHECK_RMS_V, alternatives: dict | None = None,
                default_rms_v: float | None = None) -> OcvCheck:
    """RMS of (rested voltage - OCV(soc)) over a pulse test's rests; above the threshold
    the note is a warning naming the better source: the pulse test's rests when they
    are long enough to be relaxed (at least 10 min: the cell's own OCV at the pulse
    test's temperature and age), else the chosen OCV. ``alternatives`` ({"ocv_branch =
    \"discharge\"": (soc, ocv_v), ...}) are other readings of the chosen source whose
    RMS the warning reports too. ``default_rms_v``: the RMS of the source read the
    default way (the average of a low-rate test's branches) when data.ocv_branch = "auto"
    chose another reading; above the threshold it is a warning too (the file, read as
    usual, disagrees with the rests)."""
    soc, v = np.asarray(soc, dtype=np.float64), np.asarray(v, dtype=np.float64)
    d = v - table.ocv_at(soc)
    rms = float(np.sqrt(np.mean(d * d)))
    others = {k: float(np.sqrt(np.mean((v - np.interp(soc, g, c)) ** 2)))
              for k, (g, c) in (alternatives or {}).items()}
    warn = rms > threshold_v or (default_rms_v is not None and default_rms_v > threshold_v)
    rested = float(np.median(rest_s)) >= 600.0
    better = "pulses" if rested or not warn else chosen
    text = (f"OCV check: the OCV ({chosen}) differs from the {d.size} rested voltages of "
            f"the pulse test by {rms * 1e3:.1f} mV RMS (mean {np.mean(d) * 1e3:+.1f} mV, "
            f"threshold {threshold_v * 1e3:g} mV)")
    if default_rms_v is not None and default_rms_v > threshold_v:
        text += (f"; warning: read as the average of its branches, it differs by "
                 f"{default_rms_v * 1e3:.1f} mV RMS (its branches do not agree: another "
                 "temperature, age or charge end?)")
        if rms <= threshold_v:
            text += ("; data.ocv_branch auto took the closer branch; the pulse test's rests "
                     "are still the better source: ocv = \"pulses\" or [\"pulses\", ...]")
    if warn and rms > threshold_v and better == "pulses":
        text += ("; warning: the pulse test's rests are the better source (the cell's OCV "
                 "at the pulse test's own temperature and age): ocv = \"pulses\", or "
                 "[\"pulses\", ...] to fill the SOC they do not cover")
    elif warn and rms > threshold_v:
        text += ("; warning: the rests of the pulse test are short (median "
                 f"{np.median(rest_s):.0f} s), not relaxed: {chosen} is the better source")
    if warn and others:
        text += "; " + ", ".join(f"{k}: {r * 1e3:.1f} mV RMS" for k, r in others.items())
    return OcvCheck(rms, float(np.mean(d)), float(np.max(np.abs(d))), int(d.size),
                    threshold_v, bool(warn), better, text)


# a file of the OCV and a pulse test within this of each other are at one temperature (the
# pulse-test label check's tolerance, ecmgen.data.sources.PULSE_LABEL_TOL_K)
SAME_TEMPERATURE_K = 5.0


def rests_should_lead(check: OcvCheck, curves, sources, series: TimeSeries | None
                      ) -> str | None:
    """Why the pulse test's rests should lead the OCV files given alone (None: they should
    not): the files fail the check against rests relaxed enough to be the cell's own OCV
    (``check.better``), and each was measured at the pulse test's own temperature, so an
    entropic shift cannot explain the difference (a file at another temperature is kept
    as given: that the test's rests differ from it is expected, and which of the two the
    cell's cycles follow, the rests say nothing of)."""
    if "pulses" in sources or not (check.warning and check.rms_v > check.threshold_v
                                   and check.better == "pulses"):
        return None
    if series is None or series.temperature_c is None:
        return None
    test_c = float(np.median(series.temperature_c))
    temps = [c.temperature_c for c in curves]
    if any(t is None or abs(t - test_c) > SAME_TEMPERATURE_K for t in temps):
        return None
    files = " + ".join(c.name for c in curves)
    return (f"the pulse test's rests first, {files} filling the SOC they do not cover: "
            f"{files} alone differs from the test's {check.n} rested voltages by "
            f"{check.rms_v * 1e3:.1f} mV RMS (mean {check.mean_v * 1e3:+.1f} mV, the check "
            f"allows {check.threshold_v * 1e3:g} mV) at the test's own temperature "
            f"({test_c:.1f} degC, the file {', '.join(f'{t:.1f}' for t in temps)} degC); "
            "the rests are the cell's OCV at the test's age and state "
            "(data.ocv_rests_first = \"never\" keeps the files alone)")


# --------------------------------------------------------------------------- beyond the rests
# OCV where a pulse test's rests do not reach, from the test's own low-rate branches.
#
# A pulse test that opens with a charge from near empty, or closes with a discharge to the
# cut-off, runs past its lowest (highest) rest under a steady current. There the rests
# say nothing and the OCV used to be held flat. A charge and a discharge branch over the
# same SOC bracket the OCV: with a linear resistance R, v_ch = OCV + R i_ch and
# v_dis = OCV - R i_dis, so OCV = (i_dis v_ch + i_ch v_dis) / (i_ch + i_dis), whatever R is.
# Beyond the SOC both branches cover, the one branch that goes on is taken with the
# overpotential measured where they last overlapped (its resistance grows towards empty,
# so this errs on the side of a too-low OCV below empty-side overlaps, where a flat hold
# errs by far more the other way: 0.38 V on the shared Leaf 25 degC test).
#
# Only a steady part of a branch counts: a segment of constant current (within
# ``STEADY_REL``) no faster than ``MAX_RATE_C``, from ``SETTLE_S`` after the current
# started, so that the fast RC pairs have settled.

MAX_RATE_C = 0.5        # a branch: at most C/2 (a low-rate branch, not a pulse)
MIN_SEGMENT_S = 120.0   # ... lasting at least this long
SETTLE_S = 60.0         # ... its first minute left out (the fast pairs settling)
STEADY_REL = 0.02       # constant current: within 2 % of the segment's median


def _steady_segments(series: TimeSeries, capacity_ah: float):
    """(start, stop, current) of every steady low-rate segment, the settling left out."""
    t, i = series.time_s, series.current_a
    on = np.abs(i) > 0.01 * capacity_ah
    sign = np.where(on, np.sign(i), 0.0)
    edges = np.flatnonzero(np.diff(sign)) + 1
    out = []
    for a, b in zip(np.r_[0, edges], np.r_[edges, t.size]):
        if sign[a] == 0 or t[b - 1] - t[a] < MIN_SEGMENT_S:
            continue
        med = float(np.median(i[a:b]))
        if abs(med) > MAX_RATE_C * capacity_ah:
            continue
        steady = np.abs(i[a:b] - med) <= STEADY_REL * abs(med)
        keep = np.flatnonzero(steady & (t[a:b] >= t[a] + SETTLE_S)) + a
        if keep.size >= 2 and np.all(np.diff(keep) == 1):
            out.append((int(keep[0]), int(keep[-1]) + 1, med))
    return out


def _branch(series, soc, seg, lo, hi):
    """One segment's (grid SOC, voltage) within [lo, hi] (interpolated in SOC)."""
    a, b, _ = seg
    s, v = soc[a:b], series.voltage_v[a:b]
    order = np.argsort(s, kind="stable")
    s, v = s[order], v[order]
    g = GRID[(GRID >= max(lo, s[0])) & (GRID <= min(hi, s[-1]))]
    return g, np.interp(g, s, v)


def curve_from_branches(series: TimeSeries, soc0: float, capacity_ah: float,
                        span: tuple[float, float]) -> OcvCurve | None:
    """The OCV below ``span[0]`` and above ``span[1]`` (the rests' span) from the test's
    own charge and discharge branches there (module docstring), or None when the test
    has no pair of branches beyond its rests."""
    soc = soc0 + series.coulomb_ah() / capacity_ah
    segments = _steady_segments(series, capacity_ah)
    points: dict[float, float] = {}
    notes = []
    for lo, hi, side in ((0.0, span[0], "below"), (span[1], 1.0, "above")):
        ch = [_branch(series, soc, s, lo, hi) + (s[2],) for s in segments if s[2] > 0]
        dis = [_branch(series, soc, s, lo, hi) + (-s[2],) for s in segments if s[2] < 0]
        ch, dis = [c for c in ch if c[0].size], [d for d in dis if d[0].size]
        if not ch or not dis:
            continue
        (gc, vc, ic), (gd, vd, id_) = ch[0] if side == "below" else ch[-1], \
            dis[-1] if side == "below" else dis[0]
        both = np.intersect1d(gc, gd)
        if both.size == 0:
            continue
        v_ch, v_dis = np.interp(both, gc, vc), np.interp(both, gd, vd)
        ocv = (id_ * v_ch + ic * v_dis) / (ic + id_)
        points.update(zip(both.tolist(), ocv.tolist()))
        # past the overlap: the branch that goes on, with the overpotential at its edge
        edge = both[0] if side == "below" else both[-1]
        g, v, eta = (gd, vd, ocv[0] - v_dis[0]) if side == "below" else \
            (gc, vc, ocv[-1] - v_ch[-1])
        past = (g < edge) if side == "below" else (g > edge)
        points.update(zip(g[past].tolist(), (v[past] + eta).tolist()))
        far = g[past][0 if side == "below" else -1] if past.any() else edge
        goes_on = "discharge" if side == "below" else "charge"
        past_words = (f"; past it the {goes_on} branch {abs(eta) * 1e3:.0f} mV from its OCV "
                      "there" if past.any() else "")
        notes.append(f"OCV: SOC {min(far, both[0]):.2f}..{max(far, both[-1]):.2f} ({side} the "
                     f"rests) from the pulse test's own {ic:.3g} A charge and {id_:.3g} A "
                     f"discharge branches (their current-weighted mean over SOC "
                     f"{both[0]:.2f}..{both[-1]:.2f}{past_words})")
    if not points:
        return None
    g = np.array(sorted(points))
    v = _isotonic(np.array([points[x] for x in g]))
    return OcvCurve("the pulse test's branches", g, v, tuple(notes),
                    raw=(("branches", g, v),))


# --------------------------------------------------------------------------- one call

def ocv_from_low_rate(series: TimeSeries, capacity_ah: float, soc0: float | None = None,
                      branch: str = "both", cycle: int | None = None
                      ) -> tuple[OcvTable, list[str]]:
    """OCV table from one cycle of a low-rate test (see :func:`curve_from_low_rate`)."""
    name = Path(series.source).name or "low-rate test"
    curve = curve_from_low_rate(series, capacity_ah, name, soc0=soc0, branch=branch,
                                cycle=cycle)
    table, notes, _ = merge_curves([curve])
    check_not_flat(table, series.source)
    return table, list(curve.notes) + notes


def ocv_from_pulse_rests(series: TimeSeries, pulses, capacity_ah: float, soc0: float
                         ) -> tuple[OcvTable, list[str]]:
    """OCV from the rested voltage before each pulse of a pulse test (the SOC of each
    rest from the same coulomb count as the pulses)."""
    soc = np.array([p.soc for p in pulses])
    v = np.array([series.voltage_v[p.rest_index] for p in pulses])
    curve = curve_from_rests(soc, v, "pulses", series.source)
    table, notes, _ = merge_curves([curve])
    return table, list(curve.notes) + notes


# --------------------------------------------------------------------------- assembly

@dataclass(frozen=True)
class OcvReport:
    """How the OCV was made, for --json and the OCV plot."""

    sources: tuple[str, ...]
    curves: tuple                      # the OcvCurve of each source, in merge order
    check: OcvCheck | None             # against the pulse test's rests
    rests_soc: np.ndarray | None       # the pulse test's rested points
    rests_v: np.ndarray | None

    @property
    def span(self) -> tuple[float, float]:
        """The SOC span its sources measured together."""
        return (min(c.span[0] for c in self.curves), max(c.span[1] for c in self.curves))

    def as_dict(self) -> dict:
        return {"sources": list(self.sources),
                "spans": {c.name: list(c.span) for c in self.curves},
                "capacity_ah": {c.name: dict(c.capacity_ah) for c in self.curves
                                if c.capacity_ah},
                "check": self.check.as_dict() if self.check is not None else None}


def assemble(sources, file_curves: dict, paths: dict, rests, soc0, capacity_ah: float, *,
             auto: bool = True, series: TimeSeries | None = None, rests_first: bool = True
             ) -> tuple[OcvTable, list[str], OcvReport]:
    """The OCV of one pulse test (or of a DC-IR table's build, ``rests`` None): the
    sources in order ("pulses" or a key of ``file_curves``; ``paths`` names each one's
    file for errors), a low-rate cycle read the way that matches the rests (``auto``,
    :func:`choose_reading`), the pulse rests' curve at SOC ``soc0`` + their charge,
    merged (:func:`merge_curves`), checked for flatness (an InputError naming the
    source) and against the rests (:func:`cross_check`). Returns the table, the notes
    and the report. ``series``: the pulse test, whose own low-rate branches fill the SOC
    that no source covers (:func:`curve_from_branches`) when its rests are a source.
    ``rests_first``: where the files alone fail the check against relaxed rests at the
    pulse test's own temperature (:func:`rests_should_lead`), the rests lead and the
    files fill the SOC they do not cover.
    """
    notes: list[str] = []
    has_rests = rests is not None and len(rests) > 0
    rest_soc = soc0 + rests.charge_ah / capacity_ah if has_rests else None
    rest_v = rests.voltage_v if has_rests else None
    given, file_curves = file_curves, dict(file_curves)
    default_rms = None
    if auto and has_rests:
        for src, c in file_curves.items():
            if c.branches:
                file_curves[src], rms, best = choose_reading(c, rest_soc, rest_v)
                if best != "both" and sources[0] == src:
                    default_rms = rms["both"]
    curves = [curve_from_rests(rest_soc, rest_v, "pulses", paths["pulses"])
              if src == "pulses" else file_curves[src] for src in sources]
    if series is not None and "pulses" in sources:
        lo, hi = min(c.span[0] for c in curves), max(c.span[1] for c in curves)
        if lo > 0.005 or hi < 0.995:
            more = curve_from_branches(series, soc0, capacity_ah, (lo, hi))
            curves += [more] if more is not None else []
    table, n, origin = merge_curves(curves)
    for c in curves:
        notes.extend(c.notes)
    notes.extend(n)
    check_not_flat(table, paths[sources[0]], origin, [paths[s] for s in sources])
    check = None
    if has_rests and tuple(sources) != ("pulses",):
        chosen = " + ".join(c.name for c in curves)
        alt = {}
        if len(curves) == 1:
            alt = {(f"its {d} branch alone (data.ocv_branch = \"{d}\")" if d != "both" else
                    "the average of its branches (data.ocv_branch = \"both\")"): b
                   for d, b in curves[0].branches.items()
                   if not np.array_equal(b[1], curves[0].ocv_v)}
        check = cross_check(table, rest_soc, rest_v, rests.duration_s, chosen,
                            alternatives=alt, default_rms_v=default_rms)
        lead = rests_should_lead(check, curves, sources, series) if rests_first else None
        if lead is not None:
            table, more, report = assemble(("pulses", *sources), given,
                                           {"pulses": series.source, **paths}, rests,
                                           soc0, capacity_ah, auto=auto, series=series,
                                           rests_first=False)
            return table, [f"OCV: {lead}"] + more, report
        notes.append(check.note)
    return table, notes, OcvReport(tuple(c.name for c in curves), tuple(curves), check,
                                   rest_soc, rest_v)
