"""A low-rate OCV test split over files (Plett's four A123 scripts) joined into one cycle by
the tool, and a constant-voltage hold with dither that no longer breaks cycle detection."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SHARED_DATA, need
from ecmgen.data.lowrate import split_low_rate
from ecmgen.data.measure import TimeSeries

Q = 2.0


def _ocv(soc):
    return 3.0 + 0.9 * soc + 0.1 * np.sin(3 * soc)


def test_dither_in_a_cv_hold_does_not_break_the_cycle():
    """Discharge at C/20, a 2 h hold at the bottom whose current dithers about zero, then
    a C/20 charge. Before: the dither's tiny branches sat between the two complete ones
    and no cycle was found."""
    dt = 10.0
    n = int(20 * 3600 / dt)
    soc_d = 1 - np.arange(1, n + 1) / n
    i_d = np.full(n, -Q / 20)
    hold = np.where(np.arange(720) % 2 == 0, 0.004, -0.004) * Q
    i = np.concatenate([[0.0], i_d, hold, -i_d])
    v = np.concatenate([[_ocv(1.0)], _ocv(soc_d) - 0.01, np.full(720, _ocv(0.0)),
                        _ocv(1 - soc_d) + 0.01])
    t = np.arange(i.size) * dt
    test = split_low_rate(TimeSeries(t, i, v, source="dither.csv"), Q)
    assert len(test.cycles) == 1
    a, b = test.cycles[0]
    assert (test.branches[a].direction, test.branches[b].direction) == ("discharge", "charge")


def test_plett_ocv_scripts_are_joined_into_one_cycle(tmp_path):
    """The four A123 scripts as shared, listed in data.ocv. Before: each file a test of its
    own, none a discharge + charge cycle (S2 and S4 alone, their holds' dither)."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import prepare

    d = need(SHARED_DATA / "plett-a123-lfp" / "ocv_data")
    (tmp_path / "dcir.csv").write_text("soc,direction,t_s,r_ohm\n" + "".join(
        f"0.5,discharge,{t},{0.01 + 0.001 * k}\n" for k, t in enumerate((0.1, 1, 3, 6, 10))))
    files = ", ".join(f'"{d}/A123_OCV_P25_S{k}.csv"' for k in (1, 2, 3, 4))
    cfg = tmp_path / "a123.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.06\n[data]\ndcir = "dcir.csv"\nocv = [{files}]\n')
    inputs = prepare(load_config(cfg))
    assert any("parts of one low-rate test" in n and "S1.csv + A123_OCV_P25_S2.csv" in n
               for n in inputs.notes)
    assert any("cycle 1 of 1: the average of its discharge and charge branches" in n
               for n in inputs.notes)
    # read from the files themselves: at empty and full the rested voltages S2 and S4 open
    # with (the rests after S1's discharge and S3's charge), at half charge the mean of S1's
    # discharge and S3's charge at half their own charge; each to the derived table's
    # strictly-increasing tilt
    from ecmgen.data.measure import read_timeseries
    from ecmgen.data.ocv import MIN_SLOPE_V_PER_SOC

    part = {k: read_timeseries(d / f"A123_OCV_P25_S{k}.csv") for k in (1, 2, 3, 4)}

    def opening_rest(s):
        return s.voltage_v[:np.flatnonzero(s.current_a != 0)[0]]

    def at_half_charge(s, sign):
        moving = np.sign(s.current_a) == sign
        q = np.abs(s.coulomb_ah()[moving])
        q -= q[0]
        return float(np.interp(0.5 * q[-1], q, s.voltage_v[moving]))

    for soc, rest in ((0.0, opening_rest(part[2])), (1.0, opening_rest(part[4]))):
        assert rest.min() <= inputs.ocv.ocv_at(soc) <= rest.max() + MIN_SLOPE_V_PER_SOC, soc
    half = 0.5 * (at_half_charge(part[1], -1) + at_half_charge(part[3], 1))
    assert inputs.ocv.ocv_at(0.5) == pytest.approx(half, abs=MIN_SLOPE_V_PER_SOC)


def test_plett_dynamic_test_read_as_shared():
    """Plett's CSV (discharge POSITIVE, chgAh / disAh) read with no mapping: the current
    turned to ecmgen's sign, the charge from the two counters (before: 'columns not
    recognised')."""
    from ecmgen.data.measure import read_timeseries

    path = need(SHARED_DATA / "plett-a123-lfp" / "dyn_data" / "A123_DYN_50_P25_s1.csv")
    ts = read_timeseries(path)
    assert any("Plett" in n and "positive on discharge" in n for n in ts.notes)
    # the net charge is the file's own counters at its last row: chgAh - disAh
    last = path.read_text().strip().splitlines()[-1].split(",")
    assert ts.coulomb_ah()[-1] == pytest.approx(float(last[4]) - float(last[5]), abs=1e-9)
    # the current turned to ecmgen's sign moves with the counters (rounded to 0.1 mAh,
    # most 1 s steps move them by nothing), not against them
    dq = np.diff(ts.coulomb_ah())
    assert np.corrcoef(dq[1:], ts.current_a[1:-1])[0, 1] > 0
