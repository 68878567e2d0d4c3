"""Files as cyclers write them: a headerless export with text columns read by position,
no line of data taken for a header, a logger-off row at a record's end dropped with a
note, the cycler's own Ah counters (restarting per step, or split into charge and
discharge) joined into one, and the current held over a logging gap. Each record is
written here with its exact charge known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, need
from ecmgen.data.counters import integrate_current
from ecmgen.data.measure import ColumnMap, read_timeseries
from ecmgen.errors import InputError
from test_measure import assert_one_line_error

# (mode, current A, duration s, logging interval s, the step's counter restarts)
LEAF_LEVEL = [("DCHG", -30.0, 30.0, 0.5, True), ("REST", 0.0, 40.0, 1.0, True),
              ("CHRG", 22.5, 10.0, 0.1, True), ("DCHG", -10.0, 1080.0, 1.0, True),
              ("REST", 0.0, 3600.0, 60.0, False)]   # the rest keeps the move's count


def bitrode_rows(steps, t0=0.0):
    """Rows as a Bitrode logs them: a step's first sample one logging interval after its
    start, its last exactly at its end; ``Capacity(Ah)`` the step's own charge rounded to
    0.01 Ah (or carried on from the step before). Returns the rows and the exact charge
    at each row (Ah, from 0 at the start)."""
    rows, exact = [], []
    t, q, counter_base = t0, 0.0, 0.0
    for n, (mode, amps, dur, dt, restarts) in enumerate(steps, 1):
        if restarts:
            counter_base = 0.0
        k = np.arange(1, int(round(dur / dt)) + 1) * dt
        for s in k:
            q_now = q + amps * s / 3600.0
            rows.append((t + s, n, s, amps, 3.7 + 0.002 * amps,
                         round(counter_base + amps * s / 3600.0, 2), mode))
            exact.append(q_now)
        counter_base += amps * dur / 3600.0
        q += amps * dur / 3600.0
        t += dur
    return rows, np.array(exact)


def write_bitrode(path: Path, rows, header: bool) -> Path:
    lines = ["Exclude,Time(s),Cycle,Loop,Loop,Loop,Step,StepTime(s),Current(A),Voltage(V),"
             "Power(W),Capacity(Ah),Energy(Wh),Mode,Data,"] if header else []
    for t, step, st, i, v, cap, mode in rows:
        lines.append(f"No,{t:.1f},1,1,1,1,{step},{st:.1f},{i:.2f},{v:.3f},{i * v:.1f},"
                     f"{cap:.2f},0.00,{mode}, ,")
    path.write_text("\n".join(lines) + "\n")
    return path


BITRODE_BY_POSITION = dict(time=2, current=9, voltage=10, charge=12)


def counter_rounding_ah(rows):
    """How far the joined per-step counters, counted from the first row, may be from the
    exact charge at each row: half the 0.01 Ah the file rounds each step's count to, for
    every step joined so far and for the first row's count."""
    return 0.005 * (np.array([r[1] for r in rows]) + 1) + 1e-12


def open_at_edges_ah(t, i):
    """What a record's short steps leave open at their changes of current: half a sample's
    charge at each (the rule between samples unknown), the 60 s logging gaps left out."""
    dt, di = np.diff(t), np.abs(np.diff(i))
    return float(np.sum((di * dt / 2 / 3600)[dt < 60.0]))


@pytest.fixture
def level(tmp_path):
    rows, exact = bitrode_rows([("CHRG", 10.0, 600.0, 1.0, True),
                                ("REST", 0.0, 600.0, 60.0, True)] + LEAF_LEVEL * 2)
    return rows, exact


def test_headerless_export_with_text_columns_is_read_by_position(tmp_path, level):
    """Before: 'header = false in [data.columns], but line 1 holds names (No, 1.0, ...)'."""
    rows, exact = level
    path = write_bitrode(tmp_path / "leaf.csv", rows, header=False)
    ts = read_timeseries(path, ColumnMap(**BITRODE_BY_POSITION, header=False))
    assert len(ts) == len(rows)
    # the file writes the time to 0.1 s
    np.testing.assert_allclose(ts.time_s, [r[0] for r in rows], rtol=0, atol=0.05 + 1e-9)
    np.testing.assert_allclose(ts.current_a, [r[3] for r in rows])
    # the per-step counter joined: within the 0.01 Ah rounding of the steps' counts
    assert np.all(np.abs(ts.coulomb_ah() - (exact - exact[0])) <= counter_rounding_ah(rows))


def test_a_line_of_data_is_never_taken_for_a_header(tmp_path, level):
    """Before: a positional map over a headerless export, header left out, read the file
    and dropped its first row without a word."""
    path = write_bitrode(tmp_path / "leaf.csv", level[0], header=False)
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap(**BITRODE_BY_POSITION))
    assert_one_line_error(exc, path, "no header line", "line 1", "header = false")


def test_bitrode_export_recognised_by_its_names_with_its_counter(tmp_path, level):
    """Before: 'columns not recognised'; with a [data.columns] map of Capacity(Ah) the
    counter's restarts made the charge jump back at every step."""
    rows, exact = level
    path = write_bitrode(tmp_path / "leaf.csv", rows, header=True)
    ts = read_timeseries(path)
    assert any("Bitrode" in n for n in ts.notes)
    assert any("restarts of its counter" in n for n in ts.notes)
    assert np.all(np.abs(ts.coulomb_ah() - (exact - exact[0])) <= counter_rounding_ah(rows))


def test_current_held_over_a_logging_gap(level):
    """Without a counter, the trapezoid ramps -10 A down to 0 A over the first logged
    minute of each rest: 0.083 Ah that never flowed, per level (the Leaf's HPPC; here
    +0.083 after the charge, -2 x 0.083 after the moves). Held, the count is within the
    trapezoid's error at the short steps' edges."""
    rows, exact = level
    t = np.array([r[0] for r in rows])
    i = np.array([r[3] for r in rows])
    truth = exact - exact[0]
    trapezoid = np.concatenate(([0.0], np.cumsum(0.5 * (i[1:] + i[:-1]) * np.diff(t)))) / 3600
    held = integrate_current(t, i)
    # the short steps' edges leave half a sample's charge open at each change of current,
    # whatever the rule; the 60 s gaps' ramps take the trapezoid beyond that, held not
    edges = open_at_edges_ah(t, i)
    assert abs(trapezoid[-1] - truth[-1]) > edges
    assert abs(held[-1] - truth[-1]) <= edges


def test_logging_gaps_are_said(tmp_path, level):
    rows = level[0]
    path = tmp_path / "plain.csv"
    path.write_text("time_s,current_a,voltage_v\n" +
                    "".join(f"{r[0]:.1f},{r[3]},{r[4]}\n" for r in rows))
    ts = read_timeseries(path)
    note = next(n for n in ts.notes if "logging gap" in n)
    assert "held over it" in note and "60 s" in note


def test_split_counters_restarting_per_cycle_are_joined(tmp_path):
    """Arbin's Charge_Capacity / Discharge_Capacity count up and restart every cycle."""
    t = np.arange(0.0, 4 * 3600.0, 10.0)
    i = np.where((t // 3600) % 2 == 0, -1.0, 1.0)           # 1 h discharge, 1 h charge
    i[0] = 0.0
    cycle = (t // 7200).astype(int)
    dq = np.concatenate(([0.0], i[1:] * np.diff(t) / 3600))
    chg = np.zeros_like(t)
    dis = np.zeros_like(t)
    for c in np.unique(cycle):
        m = cycle == c
        chg[m] = np.cumsum(np.maximum(dq[m], 0))
        dis[m] = np.cumsum(np.maximum(-dq[m], 0))
    path = tmp_path / "arbin.csv"
    path.write_text("Test_Time(s),Current(A),Voltage(V),Charge_Capacity(Ah),"
                    "Discharge_Capacity(Ah)\n" +
                    "".join(f"{a},{b},3.3,{c},{d}\n" for a, b, c, d in zip(t, i, chg, dis)))
    ts = read_timeseries(path)
    np.testing.assert_allclose(ts.coulomb_ah(), np.cumsum(dq), atol=1e-9)
    assert any("restart" in n for n in ts.notes)


def test_logger_off_row_at_the_end_is_dropped_with_a_note(tmp_path):
    path = tmp_path / "steps.csv"
    body = "".join(f"{k},{-1.0 if k < 150 else 0.0},{3.9 - 0.001 * k}\n" for k in range(300))
    path.write_text("time_s,current_a,voltage_v\n" + body + "300,0,-0.00064\n")
    ts = read_timeseries(path)
    assert len(ts) == 300
    assert any("row 301 (line 302) dropped" in n and "-0.00064 V" in n for n in ts.notes)


def test_an_implausible_row_inside_a_record_is_still_refused(tmp_path):
    path = tmp_path / "steps.csv"
    body = "".join(f"{k},0,{0.0 if k == 150 else 3.9}\n" for k in range(300))
    path.write_text("time_s,current_a,voltage_v\n" + body)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "row 151", "0 V")


def test_shared_minus_20_steps_file_read_as_shared():
    """Before: refused as a whole for its last row (0 V, the logger off)."""
    path = need(SHARED_DATA / "panasonic-18650pf-n20degC" / "hppc-soc-steps.mat")
    ts = read_timeseries(path)
    assert len(ts) == 1989
    assert any("row 1990 dropped" in n for n in ts.notes)
