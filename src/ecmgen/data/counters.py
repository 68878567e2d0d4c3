"""Charge as the cycler counted it, and the current held over logging gaps.

A cycler's own Ah counter is the best record of the charge that flowed: it integrates at
the cycler's own rate, also between the samples it logs. Counters come in three forms:

* cumulative over the test (Digatron's ``Ah``);
* restarting at every step, or every cycle (Bitrode's ``Capacity(Ah)``, Arbin's
  ``Charge_/Discharge_Capacity(Ah)`` at a new cycle);
* split into a charge counter and a discharge counter, each counting up (Arbin's two
  columns, Plett's ``chgAh`` / ``disAh``).

:func:`join_counter` turns any of them into one cumulative charge (Ah, counting up on
charge). A restart is where the counter falls back towards zero by more than the current
explains while its new value is what the current gives since a step start: the charge
counted from 0 again. A counter that jumps away from zero with no logged current (a
record that leaves out its SOC moves, as the Panasonic HPPC files do) is not a restart.

Without a counter, :func:`integrate_current` integrates the logged current: the
trapezoid between samples, except over a logging gap -- an interval across which the
current changed and that is several times longer than the record's usual interval --
where the current logged at the gap's end is held over it. A cycler logs the end of every
step (the Bitrode's Ah counter shows the step's full charge on its last sample) and the
next step's first sample may come a whole logging interval after its start: the Leaf's
rests are logged every 60 s, and the ramp from -10 A to 0 A that a trapezoid draws over
the first minute of each rest adds 0.083 Ah that never flowed.
"""

from __future__ import annotations

import numpy as np

GAP_FACTOR = 4.0          # an interval this many times the median one is a logging gap ...
GAP_MIN_S = 2.0           # ... and at least this long
STEP_SHARE = 0.05         # ... across which the current changed by this share of |i|max


def _resolution(counter: np.ndarray) -> float:
    """The counter's logged resolution (its smallest step, e.g. 0.01 Ah), at least 1e-6."""
    d = np.abs(np.diff(counter))
    d = d[d > 1e-9]
    return max(float(d.min()) if d.size else 0.0, 1e-6)


def _distance(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.maximum(lo - x, 0.0) + np.maximum(x - hi, 0.0)


def counter_restarts(counter: np.ndarray, time_s: np.ndarray, flow_a: np.ndarray
                     ) -> np.ndarray:
    """Indices k where ``counter`` restarts between samples k and k + 1, given the flow
    it counts (A: the current for a signed counter, its charge or discharge part for a
    split one)."""
    dt_h = np.diff(time_s) / 3600.0
    a, b = flow_a[:-1] * dt_h, flow_a[1:] * dt_h          # held forward / backward
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    tol = 2.0 * _resolution(counter) + 0.02 * (hi - lo)
    lo, hi = lo - tol, hi + tol
    new = counter[1:]
    carried = _distance(new - counter[:-1], lo, hi)       # the count went on
    restarted = _distance(new, lo, hi)                    # it began again from 0
    return np.flatnonzero((np.abs(new) < np.abs(counter[:-1])) & (restarted == 0.0) &
                          (carried > 0.0))


def join_counter(counter: np.ndarray, time_s: np.ndarray, flow_a: np.ndarray
                 ) -> tuple[np.ndarray, int]:
    """The counter made cumulative across its restarts (from its first value), and how
    many restarts were joined."""
    inc = np.diff(counter)
    at = counter_restarts(counter, time_s, flow_a)
    inc[at] = counter[at + 1]
    return np.concatenate(([counter[0]], counter[0] + np.cumsum(inc))), int(at.size)


def cumulative_charge(time_s: np.ndarray, current_a: np.ndarray, charge: np.ndarray,
                      discharge: np.ndarray | None) -> tuple[np.ndarray, int]:
    """One cumulative charge (Ah, up on charge) from a signed counter ``charge``, or
    from a charge counter and a ``discharge`` counter that both count up; and the number
    of restarts joined."""
    if discharge is None:
        return join_counter(charge, time_s, current_a)
    up, n_up = join_counter(charge, time_s, np.maximum(current_a, 0.0))
    down, n_down = join_counter(discharge, time_s, np.maximum(-current_a, 0.0))
    return up - down, n_up + n_down


def logging_gaps(time_s: np.ndarray, current_a: np.ndarray) -> np.ndarray:
    """Indices k of the intervals [k, k + 1] that are logging gaps (module doc)."""
    if time_s.size < 3:
        return np.array([], dtype=int)
    dt = np.diff(time_s)
    usual = float(np.median(dt))
    big = float(np.max(np.abs(current_a)))
    changed = np.abs(np.diff(current_a)) > STEP_SHARE * big
    return np.flatnonzero(changed & (dt > max(GAP_FACTOR * usual, GAP_MIN_S)))


def integrate_current(time_s: np.ndarray, current_a: np.ndarray) -> np.ndarray:
    """Cumulative charge in Ah from 0 at the first sample: the trapezoid, with the
    current at a logging gap's end held over the gap."""
    dt = np.diff(time_s)
    mean = 0.5 * (current_a[1:] + current_a[:-1])
    gaps = logging_gaps(time_s, current_a)
    mean[gaps] = current_a[gaps + 1]
    return np.concatenate(([0.0], np.cumsum(mean * dt / 3600.0)))


def gap_note(time_s: np.ndarray, current_a: np.ndarray, counted: bool) -> str | None:
    """One line on the record's logging gaps, or None where it has none."""
    gaps = logging_gaps(time_s, current_a)
    if gaps.size == 0:
        return None
    dt = np.diff(time_s)[gaps]
    how = ("the cycler's Ah counter covers them" if counted else
           "the current logged at each gap's end is held over it, not ramped")
    return (f"{gaps.size} logging gap{'s' if gaps.size > 1 else ''} of {dt.min():.3g}.."
            f"{dt.max():.3g} s across which the current changed (the record's usual interval "
            f"is {float(np.median(np.diff(time_s))):.3g} s): {how}")
