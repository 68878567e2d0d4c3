"""A pulse test's unlogged SOC moves, from a second file: the merge of an SOC-step record.

Some cyclers log the discharges that move the SOC between pulse sets in a file of their
own (the Panasonic ``hppc-soc-steps.mat``: C/3.3 steps sampled at 60 s, their rests at
300 s). The pulse test then has gaps -- long time steps across which its Ah counter jumps
-- and a model fitted on the pulse test alone sees rests where the cell was discharged.
:func:`merge_soc_steps` puts the step record's samples into those gaps.

The step record keeps its own clock (it starts at 0 s). Its offset to the pulse test's
clock is found from the charge counters, which the two files share: a step that fills a
gap starts at the gap's first instant (the pulse test stops logging when the step starts)
at the gap's start charge ``q_a``, so each on-sample k of the step record, at charge q_k
and current i_k, dates that start to ``t_k - (q_a - q_k) / |i_k|``. Over every (gap,
on-sample) pair the true offset is the one most pairs agree on (within 5 s); samples of
the step record that then fall inside a gap, with their charge between the gap's end
values, are merged. Samples of other tests in the same file fall outside every gap.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .measure import TimeSeries

GAP_S = 100.0          # a time step longer than this, across which charge moved, is a gap
AGREE_S = 5.0          # offsets within this of the most common one are the same offset


def pulse_test_gaps(series: TimeSeries, min_gap_s: float = GAP_S, min_charge_ah: float = 1e-3
                    ) -> np.ndarray:
    """Indices g with an unlogged stretch between samples g and g + 1: a time step longer
    than ``min_gap_s`` across which the logged charge moved by more than the current
    explains (needs the Ah column; none without it)."""
    if series.charge_ah is None or len(series) < 2:
        return np.array([], dtype=int)
    dt = np.diff(series.time_s)
    logged = np.diff(series.charge_ah)
    expected = series.current_a[1:] * dt / 3600.0
    return np.flatnonzero((dt > min_gap_s) & (np.abs(logged - expected) > min_charge_ah))


def merge_soc_steps(pulse_test: TimeSeries, steps: TimeSeries, *, on_a: float | None = None
                    ) -> tuple[TimeSeries, tuple[str, ...]]:
    """The pulse test with the SOC-step record's samples inserted into its gaps.

    Returns the merged record (time-sorted; charge_ah continuous where the steps file
    covers a gap) and notes (how many gaps were filled, which were not). ``on_a``: the
    current above which a step sample counts as "on" (default: 1 % of the largest step
    current). Raises InputError (naming the step file) when either record lacks the Ah
    column or no offset between the two clocks makes the steps fit the gaps."""
    for s in (pulse_test, steps):
        if s.charge_ah is None:
            raise InputError(s.source, "merging SOC steps into a pulse test needs the Ah "
                                       "(charge) column in both files")
    gaps = pulse_test_gaps(pulse_test)
    if gaps.size == 0:
        return pulse_test, (f"{_name(steps)}: the pulse test has no unlogged gaps; the "
                            "SOC-step file is not needed",)
    t, q = pulse_test.time_s, pulse_test.charge_ah
    i_s = steps.current_a
    if on_a is None:
        on_a = 0.01 * float(np.max(np.abs(i_s))) if i_s.size else 0.0
    on = np.flatnonzero(np.abs(i_s) > max(on_a, 1e-9))
    if on.size == 0:
        raise InputError(steps.source, "the SOC-step file has no current flow")
    offset = _clock_offset(t[gaps], q[gaps], steps, on)
    if offset is None:
        raise InputError(steps.source, "no clock offset places the SOC steps into the pulse "
                                       "test's gaps (is it the step file of this test?)")
    t_s = steps.time_s + offset
    pieces, missed = [], []
    for g in gaps:
        qa, qb = sorted((q[g], q[g + 1]))
        sel = np.flatnonzero((t_s > t[g] + 0.5) & (t_s < t[g + 1] - 0.5) &
                             (steps.charge_ah >= qa - 0.01 * (qb - qa) - 1e-3) &
                             (steps.charge_ah <= qb + 0.01 * (qb - qa) + 1e-3))
        if sel.size:
            pieces.append(sel)
        else:
            missed.append(f"{t[g]:.0f} s")
    if not pieces:
        raise InputError(steps.source, "no sample of the SOC-step file falls into the pulse "
                                       "test's gaps")
    sel = np.concatenate(pieces)

    def cat(a, b):
        return None if a is None or b is None else np.concatenate((a, b[sel]))

    time = np.concatenate((t, t_s[sel]))
    order = np.argsort(time, kind="stable")
    temp = cat(pulse_test.temperature_c, steps.temperature_c)
    merged = TimeSeries(time[order], cat(pulse_test.current_a, steps.current_a)[order],
                        cat(pulse_test.voltage_v, steps.voltage_v)[order],
                        None if temp is None else temp[order],
                        cat(pulse_test.charge_ah, steps.charge_ah)[order],
                        f"{pulse_test.source}+{_name(steps)}", pulse_test.notes)
    notes = [f"{_name(steps)}: {sel.size} samples merged into {len(pieces)} of the pulse "
             f"test's {gaps.size} unlogged gaps (clock offset {offset:.0f} s)"]
    if missed:
        notes.append(f"{_name(steps)}: gaps at {', '.join(missed)} not covered; the fit "
                     "sees rests there")
    return merged, tuple(notes)


def _clock_offset(t_gap, q_gap, steps: TimeSeries, on: np.ndarray) -> float | None:
    """The offset (s) to add to the step record's time, agreed by most (gap, on-sample)
    pairs (see the module docstring); None when no two pairs agree."""
    t_k = steps.time_s[on][None, :]
    q_k = steps.charge_ah[on][None, :]
    i_k = np.abs(steps.current_a[on])[None, :]
    start = t_k - np.abs(q_gap[:, None] - q_k) / i_k * 3600.0
    d = (t_gap[:, None] - start).ravel()
    if d.size < 2:
        return None
    d = np.sort(d)
    # the densest window of width 2 * AGREE_S
    hi = np.searchsorted(d, d + 2 * AGREE_S, side="right")
    count = hi - np.arange(d.size)
    k = int(np.argmax(count))
    if count[k] < 2:
        return None
    return float(np.median(d[k:hi[k]]))


def _name(series: TimeSeries) -> str:
    return str(series.source).replace("\\", "/").rsplit("/", 1)[-1] or "steps"

