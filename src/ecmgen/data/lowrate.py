"""A low-rate (pseudo-OCV) test split into its branches and cycles.

A low-rate record may hold several cycles (a top-up charge, then discharge, charge,
discharge, ...). It is cut into *branches*: maximal runs of current of one sign (short
interruptions of at most ``MERGE_GAP_S`` inside a run are bridged). A branch is
*complete* when it moves at least ``COMPLETE_FRACTION`` of the largest branch's charge
(a top-up charge or an aborted step is not). A *cycle* is a complete discharge branch
followed by a complete charge branch (or, in a record with no such pair, a complete
charge followed by a complete discharge); cycles are numbered from 1 in record order.

Each branch carries its own charge throughput, so its SOC can be normalised to it
(0..1 over its own Ah): a branch run months later on an aged cell, or one whose
charge ended early, still spans the whole SOC range. The rest that follows a complete
branch (the cell resting after the cut-off) gives a rested voltage at that branch's end
(SOC 0 after a discharge, 1 after a charge).

This module only reads the record; :mod:`ecmgen.data.ocv` makes the OCV from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .measure import TimeSeries
from .sign import check_sign

MERGE_GAP_S = 300.0          # a pause this short inside a branch does not end it
COMPLETE_FRACTION = 0.8      # of the largest branch's charge: a complete branch
MAX_C_RATE = 0.2             # faster than C/5 is not a low-rate (pseudo-OCV) test
MIN_END_REST_S = 600.0       # a rest after a cut-off this long gives a rested end point


@dataclass(frozen=True)
class Branch:
    """One run of low-rate current of one sign (indices into the record)."""

    direction: str           # "charge" | "discharge"
    start: int               # first sample with current on
    stop: int                # exclusive end
    charge_ah: float         # charge moved, > 0
    current_a: float         # median current (positive = charge)
    complete: bool
    rest_after_s: float      # length of the rest that follows (0 if none)
    rest_end: int            # last sample of that rest (or stop - 1)

    def normalised_soc(self, series: TimeSeries) -> np.ndarray:
        """SOC over the branch, 0..1 over its own charge (1 -> 0 on a discharge)."""
        q = series.coulomb_ah()
        ref = q[self.start - 1] if self.start > 0 else q[0]
        moved = np.clip(np.abs(q[self.start:self.stop] - ref) / self.charge_ah, 0.0, 1.0)
        return 1.0 - moved if self.direction == "discharge" else moved


@dataclass(frozen=True)
class LowRateTest:
    branches: tuple[Branch, ...]
    cycles: tuple[tuple[int, int], ...]   # pairs of branch indices, in record order
    c_rate: float


def split_low_rate(series: TimeSeries, capacity_ah: float) -> LowRateTest:
    """Branches and cycles of a low-rate test; InputError when it is not one."""
    i, t = series.current_a, series.time_s
    thr = 0.002 * capacity_ah
    sign = np.where(i > thr, 1, np.where(i < -thr, -1, 0))
    moving = np.flatnonzero(sign != 0)
    if moving.size == 0:
        peak = float(np.nanmax(np.abs(i))) if i.size else 0.0
        if peak > 0:            # a current, below C/500 of the capacity given
            raise InputError(series.source, f"low-rate OCV test: its largest current, "
                                            f"{peak:.4g} A, is below C/500 of cell.capacity_ah "
                                            f"= {capacity_ah:g} Ah: is the capacity in Ah?")
        raise InputError(series.source, "low-rate OCV test has no current")
    check_sign(series, "low-rate OCV test", slow=True)
    c_rate = float(np.abs(i[moving]).max()) / capacity_ah
    if c_rate > MAX_C_RATE:
        raise InputError(series.source, f"current reaches {c_rate:.2f} C: not a low-rate OCV "
                                        "test (expected about C/20 or slower)")
    # runs of one sign, bridging pauses shorter than MERGE_GAP_S
    runs: list[list[int]] = []          # [sign, start, stop)
    for k in moving:
        if runs and runs[-1][0] == sign[k] and (
                runs[-1][2] == k or t[k] - t[runs[-1][2] - 1] <= MERGE_GAP_S and
                not np.any(sign[runs[-1][2]:k] == -sign[k])):
            runs[-1][2] = int(k) + 1
        else:
            runs.append([int(sign[k]), int(k), int(k) + 1])
    q = series.coulomb_ah()
    moved = [abs(q[min(b, len(q) - 1)] - q[a - 1 if a > 0 else 0]) for _, a, b in runs]
    biggest = max(moved)
    branches = []
    for n, ((s, a, b), dq) in enumerate(zip(runs, moved)):
        nxt = runs[n + 1][1] if n + 1 < len(runs) else len(i)
        rest_end = nxt - 1 if nxt > b else b - 1
        branches.append(Branch(
            direction="charge" if s > 0 else "discharge", start=int(a), stop=int(b),
            charge_ah=float(dq), current_a=float(np.median(i[a:b])),
            complete=bool(dq >= COMPLETE_FRACTION * biggest and b - a >= 10),
            rest_after_s=float(t[rest_end] - t[b - 1]) if rest_end >= b else 0.0,
            rest_end=int(rest_end)))
    cycles = _pairs(branches, ("discharge", "charge")) or _pairs(branches, ("charge", "discharge"))
    return LowRateTest(tuple(branches), tuple(cycles), c_rate)


def _pairs(branches: list[Branch], order: tuple[str, str]) -> list[tuple[int, int]]:
    """Complete branches in ``order``, each with the next complete branch after it: the
    incomplete ones between (a top-up, a constant-voltage hold whose dither flips the
    current's sign, the low-current finish of Plett's scripts) do not break a cycle."""
    complete = [k for k, b in enumerate(branches) if b.complete]
    out = []
    n = 0
    while n + 1 < len(complete):
        a, b = complete[n], complete[n + 1]
        if (branches[a].direction, branches[b].direction) == order:
            out.append((a, b))
            n += 2
        else:
            n += 1
    return out


def join_records(parts: list[TimeSeries]) -> tuple[TimeSeries, str]:
    """One low-rate test logged in several files (Plett's four OCV scripts), joined end
    to end in the order given: each part's clock continues one sampling interval after
    the part before ends (the pause between the runs is not logged; at a low rate it
    moves no charge), its charge count continues from the part before's end. Returns the
    record and a note naming the parts."""
    t, i, v, temp, q = [], [], [], [], []
    t_end = q_end = 0.0
    for k, s in enumerate(parts):
        dt = float(np.median(np.diff(s.time_s)))
        t.append(s.time_s - s.time_s[0] + (t_end + dt if k else 0.0))
        qs = s.coulomb_ah()
        q.append(qs + q_end)
        t_end, q_end = float(t[-1][-1]), float(q[-1][-1])
        i.append(s.current_a)
        v.append(s.voltage_v)
        temp.append(s.temperature_c)
    temps = None if any(x is None for x in temp) else np.concatenate(temp)
    names = " + ".join(Path(s.source).name for s in parts)
    joined = TimeSeries(np.concatenate(t), np.concatenate(i), np.concatenate(v), temps,
                        np.concatenate(q), names,
                        tuple(n for s in parts for n in s.notes))
    return joined, (f"OCV: {names}: parts of one low-rate test, none a discharge + charge "
                    f"cycle alone, joined end to end in that order (each part's clock and "
                    f"charge count continued from the one before)")


def choose_branches(test: LowRateTest, source, cycle: int | None = None,
                    branch: str = "both") -> tuple[list[Branch], str]:
    """The branches the OCV is made of and a note saying which: cycle ``cycle`` (1-based;
    default the last complete one), both branches or only ``branch``. Without a complete
    cycle, the last complete branch of the wanted direction."""
    n = len(test.cycles)
    if cycle is not None and not 1 <= cycle <= n:
        raise InputError(source, f"data.ocv_cycle = {cycle}, but the low-rate test has "
                                 f"{n} complete discharge + charge cycle{'s' if n != 1 else ''}")
    if n:
        k = (cycle or n) - 1
        pair = [test.branches[j] for j in test.cycles[k]]
        chosen = [b for b in pair if branch in ("both", b.direction)]
        what = f"cycle {k + 1} of {n}"
        return chosen, what
    want = [b for b in test.branches if b.complete and branch in ("both", b.direction)]
    if not want:
        raise InputError(source, f"low-rate test has no complete {'' if branch == 'both' else branch + ' '}"
                                 "branch (none moves most of the charge)")
    if cycle is not None:
        raise InputError(source, f"data.ocv_cycle = {cycle}, but the low-rate test has no "
                                 "complete discharge + charge cycle")
    return [want[-1]], "one complete branch (no discharge + charge cycle)"
