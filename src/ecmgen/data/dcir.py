"""Pulse test -> pulses -> DC-IR table ``R(t) = dV/dI``.

A pulse is a current plateau that starts from rest and ends at the next step of the
current, whatever comes after it: a rest, another plateau of current (a charge pulse
running straight into the constant-current SOC move of a USABC-style HPPC), or the end
of the record; a plateau that steps on into a changing current (the first second of a
drive cycle) is not a pulse. It must follow at least ``min_rest_s`` of rest and last at most
``max_pulse_s``. ``R(t)`` is taken against the last rested sample before the edge;
time is counted from that sample, so the first on-sample is the paper's "0.1 s" point
on a 10 Hz logger.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InputError, reading
from ..files import write_atomic
from .measure import TimeSeries
from .sign import check_sign

DEFAULT_TIMES_S = (0.1, 1.0, 3.0, 6.0, 10.0)


@dataclass(frozen=True)
class Pulse:
    """One current pulse of a pulse test (indices into the TimeSeries)."""

    rest_index: int          # last rested sample before the edge (the reference)
    start: int               # first sample with current on
    stop: int                # first sample after the plateau (exclusive end)
    next_start: int          # end of the relaxation after it: the next current (== stop
                             # when the pulse runs straight into another current)
    current_a: float         # median current in the pulse (positive = charge)
    direction: str           # "charge" | "discharge"
    c_rate: float            # |current| / capacity, rounded to 0.01
    soc: float               # SOC at the rest sample before the edge
    duration_s: float
    cut_short: bool          # stopped by a voltage limit (see flag_cut_short)


@dataclass(frozen=True)
class DcirTable:
    """DC-IR values: one row per pulse (or given row), one column per time.

    soc (n,), direction (n,) str, c_rate (n,), t_s (m,), r_ohm (n, m) with NaN where
    a time was not reached."""

    soc: np.ndarray
    direction: np.ndarray
    c_rate: np.ndarray
    t_s: np.ndarray
    r_ohm: np.ndarray
    notes: tuple[str, ...] = field(default=())

    def __len__(self) -> int:
        return int(self.soc.shape[0])

    def select(self, mask) -> "DcirTable":
        mask = np.asarray(mask)
        return DcirTable(self.soc[mask], self.direction[mask], self.c_rate[mask], self.t_s,
                         self.r_ohm[mask], self.notes)

    def n_values(self) -> int:
        """How many R(t) values the table holds (what its CSV writes: one row each)."""
        return int(np.count_nonzero(np.isfinite(self.r_ohm)))

    def counts(self) -> str:
        """What the table holds, in the words a command prints after writing it."""
        per = np.count_nonzero(np.isfinite(self.r_ohm), axis=0)
        full = all(int(c) == len(self) for c in per)
        how = f"{self.t_s.size} times each" if full else ", ".join(
            f"{t:g} s: {int(c)}" for t, c in zip(self.t_s, per))
        return f"{self.n_values()} R(t) values ({len(self)} pulses; {how})"

    def measured_times(self) -> "DcirTable":
        """The table without the times at which no pulse has a value (a logger too slow
        for them), said in a note; the fits need a value at every time of a row."""
        keep = np.isfinite(self.r_ohm).any(axis=0) if len(self) else \
            np.ones(self.t_s.size, bool)
        if keep.all() or keep.sum() < 2:
            return self
        gone = ", ".join(f"{t:g}" for t in self.t_s[~keep])
        note = (f"DC-IR time{'s' if (~keep).sum() > 1 else ''} {gone} s: no pulse has a "
                f"value there; the fits use the other {int(keep.sum())} times")
        return DcirTable(self.soc, self.direction, self.c_rate, self.t_s[keep],
                         self.r_ohm[:, keep], self.notes + (note,))

    def to_csv_text(self) -> str:
        out = io.StringIO()
        w = csv.writer(out, lineterminator="\n")
        w.writerow(["soc", "direction", "c_rate", "t_s", "r_ohm"])
        for k in range(len(self)):
            for j, t in enumerate(self.t_s):
                if np.isfinite(self.r_ohm[k, j]):
                    w.writerow([repr(float(self.soc[k])), self.direction[k],
                                repr(float(self.c_rate[k])), repr(float(t)),
                                repr(float(self.r_ohm[k, j]))])
        return out.getvalue()

    def write_csv(self, path: str | Path) -> Path:
        path = Path(path)
        write_atomic(path, self.to_csv_text())
        return path


def read_dcir_csv(path: str | Path) -> DcirTable:
    """Read a ``soc,direction,c_rate,t_s,r_ohm`` table (c_rate optional). SOC may be given
    in percent (values above 1.5 are divided by 100)."""
    with reading(path):
        return _read_dcir_csv(path)


def _read_dcir_csv(path: str | Path) -> DcirTable:
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such file")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise InputError(path, "empty file")
    header = [h.strip().lower() for h in rows[0]]
    for col in ("soc", "direction", "t_s", "r_ohm"):
        if col not in header:
            raise InputError(path, f"missing column '{col}' (found: {', '.join(header)})")
    ix = {h: header.index(h) for h in header}
    groups: dict[tuple, dict[float, float]] = {}
    for n, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            soc = float(row[ix["soc"]])
            t = float(row[ix["t_s"]])
            r = float(row[ix["r_ohm"]])
            c = float(row[ix["c_rate"]]) if "c_rate" in ix else 0.0
        except (ValueError, IndexError):
            raise InputError(path, f"row {n}: not a number in soc/c_rate/t_s/r_ohm") from None
        d = row[ix["direction"]].strip().lower()
        if d not in ("charge", "discharge"):
            raise InputError(path, f"row {n}: direction must be 'charge' or 'discharge', got '{d}'")
        if not all(np.isfinite([soc, t, r, c])):
            raise InputError(path, f"row {n}: non-finite value")
        if r <= 0 or r > 10:
            raise InputError(path, f"row {n}: r_ohm {r} is not a plausible cell resistance "
                                   "(mOhm given as Ohm?)")
        groups.setdefault((soc, d, c), {})[t] = r
    if not groups:
        raise InputError(path, "no data rows")
    times = np.array(sorted({t for g in groups.values() for t in g}))
    keys = sorted(groups)
    soc = np.array([k[0] for k in keys])
    if soc.max() > 1.5:
        soc = soc / 100.0
    r = np.array([[groups[k].get(t, np.nan) for t in times] for k in keys])
    return DcirTable(soc, np.array([k[1] for k in keys]), np.array([k[2] for k in keys]),
                     times, r)


STEP_TOLERANCE = 0.1    # a plateau's current stays within 10 % (+ the rest threshold)


def _plateau_end(i: np.ndarray, a: int, r: int, thr: float) -> int:
    """End (exclusive) of the current plateau that starts at sample ``a`` within the run
    [a, r) of on-samples: the first sample from which the current stays (two samples)
    more than STEP_TOLERANCE away from the plateau's level. The first sample may catch
    the current while it ramps; the level is the median of the next three."""
    if r - a <= 2:
        return r
    level = float(np.median(i[a + 1:min(r, a + 4)]))
    off = np.abs(i[a + 1:r] - level) > STEP_TOLERANCE * abs(level) + thr
    both = off[:-1] & off[1:]
    hits = np.flatnonzero(np.append(both, off[-1]))
    return r if hits.size == 0 else a + 1 + int(hits[0])


def _steady(seg: np.ndarray, thr: float) -> bool:
    """True when a run of current is one plateau (what may follow a pulse without a rest:
    the SOC move, a regen pulse): 90 % of it within STEP_TOLERANCE of its median (the
    first and last sample may ramp)."""
    med = float(np.median(seg))
    return bool(np.mean(np.abs(seg - med) <= STEP_TOLERANCE * abs(med) + thr) >= 0.9 or
                seg.size <= 2)


def find_pulses(series: TimeSeries, capacity_ah: float, *, soc0: float,
                rest_current_a: float | None = None, max_pulse_s: float = 120.0,
                min_rest_s: float = 30.0) -> list[Pulse]:
    """Find the current plateaus from rest in a pulse test (see the module doc).

    A pulse must follow at least ``min_rest_s`` of rest (else the voltage it starts
    from is not a rested one; 30 s admits the 40 s rest between the discharge and the
    regen pulse of a USABC-style HPPC) and last at most ``max_pulse_s`` (a longer
    plateau is a constant-current segment: an SOC move, a charge).

    SOC at each pulse comes from ``soc0`` plus the record's cumulative charge (its Ah
    column where it has one, which is right even when the file leaves out the
    discharges between pulse sets)."""
    i = series.current_a
    t = series.time_s
    thr = rest_current_a if rest_current_a is not None else max(0.02 * capacity_ah, 1e-3)
    on = np.abs(i) > thr
    starts = np.flatnonzero(on[1:] & ~on[:-1]) + 1
    stops = np.flatnonzero(~on[1:] & on[:-1]) + 1
    if on[-1]:
        stops = np.append(stops, len(i))
    stops = stops[stops > (starts[0] if starts.size else len(i))]
    first_rest = 0 if not on[0] else int(np.argmax(~on))  # where the record's first rest begins
    q_ah = series.coulomb_ah()
    pulses: list[Pulse] = []
    for n, (a, r) in enumerate(zip(starts, stops)):
        # a record is taken to start rested: a rest from its first sample always counts
        rest_start = stops[n - 1] if n > 0 else first_rest
        if rest_start > 0 and t[a - 1] - t[rest_start] < min_rest_s:
            continue
        b = _plateau_end(i, int(a), int(r), thr)
        dur = t[b - 1] - t[a - 1]
        if dur > max_pulse_s:
            continue  # a CC segment (SOC move, charge), not a pulse
        if b < r and not _steady(i[b:r], thr):
            continue  # steps on into a dynamic profile (a drive cycle), not a pulse test
        med = float(np.median(i[a:b]))
        nxt = b if b < r else (starts[n + 1] if n + 1 < starts.size else len(i))
        pulses.append(Pulse(
            rest_index=int(a - 1), start=int(a), stop=int(b), next_start=int(nxt),
            current_a=med, direction="charge" if med > 0 else "discharge",
            c_rate=round(abs(med) / capacity_ah, 2),
            soc=float(soc0 + q_ah[a - 1] / capacity_ah), duration_s=float(dur),
            cut_short=False))
    if not pulses:
        raise InputError(series.source, f"no pulses found (current steps above {thr:.3g} A "
                                        f"after at least {min_rest_s:g} s of rest, lasting at "
                                        f"most {max_pulse_s:g} s): not a pulse test?")
    check_sign(series, "pulse test")         # before the SOC span it would throw off
    check_soc_span(series, pulses, "pulse", soc0, capacity_ah)
    return flag_cut_short(series, pulses)


def check_soc_span(series: TimeSeries, pulses: list[Pulse], what: str, soc0: float,
                   capacity_ah: float) -> None:
    """InputError when coulomb counting puts a pulse (or block) far outside SOC 0..1: the
    start SOC or the capacity is wrong."""
    socs = np.array([p.soc for p in pulses])
    if socs.min() < -0.05 or socs.max() > 1.05:
        raise InputError(series.source, f"{what} SOC runs from {socs.min():.3f} to "
                                        f"{socs.max():.3f} by coulomb counting from soc0 = "
                                        f"{soc0:g} with {capacity_ah:g} Ah: check the start "
                                        "SOC (data.pulses_soc0) and cell.capacity_ah")


def flag_cut_short(series: TimeSeries, pulses: list[Pulse], *, rel_duration: float = 0.95,
                   limit_margin_v: float = 0.02) -> list[Pulse]:
    """Mark the pulses a voltage limit stopped (``cut_short``).

    A pulse is cut short when it lasts less than ``rel_duration`` x the median duration
    over ALL pulses of its direction in the file (the nominal pulse length; a median over
    the pulses of one C-rate fails when most of them are cut, as the 6C pulses of a cold
    test; one over both directions when they differ, as the 30 s discharge and 10 s regen
    pulses of a USABC/Leaf HPPC), or when the
    file shows a voltage limit and the pulse came within ``limit_margin_v`` of it. The
    file shows a limit when a pulse cut by the duration rule ended within the margin of the
    file's lowest (discharge) or highest (charge) voltage; a test that never hit a limit
    has none, and its deepest pulse is not flagged for being the deepest."""
    if not pulses:
        return []
    v = series.voltage_v
    nominal = {d: float(np.median([p.duration_s for p in pulses if p.direction == d]))
               for d in {p.direction for p in pulses}}
    short = [p.duration_s < rel_duration * nominal[p.direction] for p in pulses]
    v_lo, v_hi = float(np.min(v)), float(np.max(v))
    lo = [float(np.min(v[p.start:p.stop])) <= v_lo + limit_margin_v for p in pulses]
    hi = [float(np.max(v[p.start:p.stop])) >= v_hi - limit_margin_v for p in pulses]
    limit_lo = any(s and a and p.direction == "discharge" for s, a, p in zip(short, lo, pulses))
    limit_hi = any(s and b and p.direction == "charge" for s, b, p in zip(short, hi, pulses))
    out = []
    for p, s, a, b in zip(pulses, short, lo, hi):
        at_limit = (a and limit_lo and p.direction == "discharge") or \
            (b and limit_hi and p.direction == "charge")
        out.append(replace(p, cut_short=bool(s or at_limit)))
    return out


def relaxation_s(series: TimeSeries, pulses, relax_s: float = np.inf) -> np.ndarray:
    """The rest each pulse is followed by before the next current or a stretch the file
    leaves out (0 for a pulse running straight into another current), at most
    ``relax_s``: the relaxation a test really has to fit slow time constants on."""
    from .steps import pulse_test_gaps

    t = series.time_s
    gaps = pulse_test_gaps(series)             # unlogged stretches end a rest too
    out = []
    for p in pulses:
        end = p.next_start - 1
        g = gaps[(gaps >= p.stop - 1) & (gaps < end)]
        end = int(g[0]) if g.size else end
        out.append(min(float(t[end] - t[p.stop - 1]), relax_s))
    return np.array(out)


def relaxation_words(relax: np.ndarray, relax_s: float) -> str:
    """The relaxation the whole-curve fit actually uses, for the progress line."""
    if relax.size == 0:
        return "no relaxation"
    lo, med, hi = float(relax.min()), float(np.median(relax)), float(relax.max())
    return (f"{lo:.0f}..{hi:.0f} s of relaxation each (median {med:.0f} s; "
            f"fit.relax_s = {relax_s:g} s)" if hi - lo > 1 else
            f"{med:.0f} s of relaxation each (fit.relax_s = {relax_s:g} s)")


def extract_dcir(series: TimeSeries, pulses: list[Pulse],
                 times_s=DEFAULT_TIMES_S) -> DcirTable:
    """R(t) = (v(t) - v_rest) / (i(t) - i_rest) at each requested time into each pulse.

    A time at or before the first on-sample (the step's instant response on the logger's
    grid) takes that sample (on a logger slower than the times); the others, the first
    time among them (``--times 1 3 6 10``: R(1 s), not the first sample's), take the
    on-sample nearest in time, if within half a sampling interval and not one an earlier
    time took (else NaN). Every time that is
    replaced, or left without a value, in any pulse is said in a note. Pulses flagged
    ``cut_short`` are left out and noted."""
    times = np.asarray(times_s, dtype=np.float64)
    t, i, v = series.time_s, series.current_a, series.voltage_v
    rows, notes = [], []
    first_dt = []
    replaced = np.zeros(times.size, int)      # per time: pulses given the first sample's R
    missed = np.zeros(times.size, int)        # per time: pulses without a value there
    for p in pulses:
        if p.cut_short:
            notes.append(f"pulse at t={t[p.start]:.1f} s ({p.direction} {p.c_rate:g}C, "
                         f"soc {p.soc:.3f}) cut short after {p.duration_s:.2f} s: left out")
            continue
        t_on = t[p.start:p.stop] - t[p.rest_index]
        r = np.full(times.size, np.nan)
        dv = v[p.start:p.stop] - v[p.rest_index]
        di = i[p.start:p.stop] - i[p.rest_index]
        first_dt.append(t_on[0])
        dt_local = np.median(np.diff(t_on)) if t_on.size > 1 else np.inf
        used: set[int] = set()  # a sample gives one time: a slow logger's first is not R(1 s) too
        for j in range(times.size):
            k = int(np.argmin(np.abs(t_on - times[j])))
            tol = min(0.5 * dt_local, 0.25 * times[j]) + 1e-6
            if times[j] < t_on[0] - tol or (j == 0 and k == 0):
                r[j] = dv[0] / di[0]    # at or before the first sample: that sample's R
                replaced[j] += j > 0    # (the first time: the slow-logger note below)
                used.add(0)
            elif k not in used and abs(t_on[k] - times[j]) <= tol:
                r[j] = dv[k] / di[k]    # the first time too: R(1 s) is not the 0.1 s sample's
                used.add(k)
            else:
                missed[j] += 1
        rows.append((p.soc, p.direction, p.c_rate, r))
    if first_dt and np.median(first_dt) > 2.0 * times[0]:
        notes.append(f"the first sample after a pulse edge comes {np.median(first_dt):.2g} s "
                     f"after it (not {times[0]:g} s): R0 is taken there; the logger is too "
                     "slow for the early DC-IR times")
    notes += _time_notes(times, replaced, missed, len(rows), first_dt)
    if not rows:
        raise InputError(series.source, "every pulse was cut short; no DC-IR values")
    return DcirTable(np.array([x[0] for x in rows]), np.array([x[1] for x in rows]),
                     np.array([x[2] for x in rows]), times, np.array([x[3] for x in rows]),
                     tuple(notes))


def _time_notes(times, replaced, missed, n, first_dt) -> list[str]:
    """The DC-IR times some pulses could not give as asked, one note each."""
    notes = []
    first = float(np.median(first_dt)) if first_dt else 0.0
    for j in np.flatnonzero(replaced):
        notes.append(f"DC-IR time {times[j]:g} s comes before the first sample after the "
                     f"edge ({first:.2g} s after it) in {replaced[j]} of {n} pulses: the "
                     f"first sample's R is taken for it")
    for j in np.flatnonzero(missed):
        notes.append(f"DC-IR time {times[j]:g} s: no value in {missed[j]} of {n} pulses (no "
                     f"sample within half an interval of it other than the first, R0's, or "
                     f"the pulse ended before it)")
    return notes
