"""OCV from a table, a low-rate test (real Panasonic C/20, real CALCE charge branch) and
pulse-test rests."""

import numpy as np
import pytest

from conftest import CALCE, PANASONIC, need
from ecmgen.errors import InputError
from ecmgen.data.measure import TimeSeries, read_timeseries
from ecmgen.data.ocv import MIN_SLOPE_V_PER_SOC, ocv_from_low_rate, read_ocv_table


def derived_table_error_v(soc_step, curvature_v):
    """How far a table derived from a noise-free branch may sit from its truth: the tilt
    that keeps derived tables strictly increasing (MIN_SLOPE_V_PER_SOC x SOC, at most 0.1
    mV) and the linear interpolation of a curve sampled every ``soc_step`` (h^2 / 8 x its
    largest |second derivative|)."""
    return MIN_SLOPE_V_PER_SOC + soc_step ** 2 / 8 * curvature_v + 1e-12


def test_table_in_percent_and_fraction(tmp_path):
    p = tmp_path / "ocv.csv"
    p.write_text("soc,ocv_v\n0,3.0\n50,3.6\n100,4.2\n")
    t = read_ocv_table(p)
    assert t.soc.tolist() == [0.0, 0.5, 1.0]
    assert float(t.ocv_at(0.25)) == pytest.approx(3.3)
    assert float(t.soc_at(3.9)) == pytest.approx(0.75)


@pytest.mark.parametrize("body,needle", [
    ("soc,ocv_v\n0,3.0\n0.5,3.9\n1,3.8\n", "not monotonic"),
    ("soc,ocv_v\n0,3.0\n0.5,3.9\n0.5,4.0\n", "not strictly increasing"),
    ("soc,volts\n0,3.0\n1,4.0\n", "missing column 'ocv_v'"),
    ("soc,ocv_v\n0,3000\n1,4200\n", "mV given as V"),
    ("soc,ocv_v\n0,3.0\n1,abc\n", "not a number"),
])
def test_bad_tables(tmp_path, body, needle):
    p = tmp_path / "ocv.csv"
    p.write_text(body)
    with pytest.raises(InputError) as exc:
        read_ocv_table(p)
    assert str(exc.value).startswith(str(p)) and needle in str(exc.value)
    assert "\n" not in str(exc.value)


def test_synthetic_low_rate_branches_average_to_the_true_ocv():
    ocv = lambda s: 3.0 + 1.1 * s + 0.1 * np.sin(6 * s)  # noqa: E731
    q, i_ = 2.0, 0.1
    hours = q / i_
    t = np.linspace(0, hours * 3600, 400)
    soc_d = 1 - t / 3600 * i_ / q
    soc_c = t / 3600 * i_ / q
    # branches sit +-20 mV (I*R + hysteresis) around the OCV
    series = TimeSeries(np.concatenate([t, t + t[-1] + 60]),
                        np.concatenate([np.full(400, -i_), np.full(400, i_)]),
                        np.concatenate([ocv(soc_d) - 0.02, ocv(soc_c) + 0.02]), source="lr")
    table, notes = ocv_from_low_rate(series, q)
    assert "average" in notes[0]
    # the symmetric +-20 mV cancel in the average: what is left is the table's own making
    # (|d2 ocv / d soc2| <= 0.1 x 36, sampled every 1/399 of SOC)
    assert np.max(np.abs(table.ocv_v - ocv(table.soc))) < derived_table_error_v(1 / 399, 3.6)


def test_panasonic_c20_has_both_branches():
    s = read_timeseries(need(PANASONIC / "ocv-c20.mat"), capacity_ah=2.9)
    table, notes = ocv_from_low_rate(s, 2.9)
    assert "average" in notes[0]
    # within the cycler's voltage limits, as the file reaches them (2.5 V cut-off, 4.2 V
    # charge); the ends are checked to the file's rested voltages below
    assert s.voltage_v.min() < table.ocv_v[0] and table.ocv_v[-1] < s.voltage_v.max()
    assert np.all(np.diff(table.ocv_v) > 0)


def test_calce_single_charge_branch_is_used_with_a_warning():
    s = read_timeseries(need(CALCE / "ocv-charge-c22.csv"), capacity_ah=1.1)
    table, notes = ocv_from_low_rate(s, 1.1)
    assert "only the charge branch" in notes[0]
    # the OCV at half charge is the branch's voltage at half its own charge, read from the
    # file (an LFP plateau near 3.3 V), tilted to be strictly increasing
    from ecmgen.data.lowrate import split_low_rate

    (branch,) = split_low_rate(s, 1.1).branches
    q = s.coulomb_ah()
    part = slice(branch.start, branch.stop)
    half = np.interp(0.5, (q[part] - q[branch.start]) / branch.charge_ah, s.voltage_v[part])
    assert float(table.ocv_at(0.5)) == pytest.approx(half, abs=MIN_SLOPE_V_PER_SOC)
    assert np.all(np.diff(table.ocv_v) > 0)


def test_fast_test_is_not_an_ocv_test():
    t = np.arange(0, 3600.0, 10)
    s = TimeSeries(t, np.full(t.size, -2.9), 4.0 - 1e-4 * t, source="fast.csv")
    with pytest.raises(InputError, match="fast.csv.*not a low-rate OCV test"):
        ocv_from_low_rate(s, 2.9)


# --------------------------------------------------------------------------- OCV sources

def _lfp_like(s):
    from ecmgen.diagnosis.synthcell import lfp_like_ocv

    return lfp_like_ocv(np.asarray(s))


def _low_rate_cycles(ocv, capacities, *, i_a=0.1, dt=60.0, start_soc=0.6, top_up=True,
                     drop_v=0.02):
    """A low-rate record: (a top-up charge from start_soc), then per capacity in
    ``capacities`` a 1 h rest, a discharge to empty, a 1 h rest, a charge to full (the cell
    ages from cycle to cycle: each cycle's branches move its own capacity). Branches sit
    ``drop_v`` below/above the OCV; rests are relaxed."""
    t, i, v = [0.0], [0.0], [float(ocv(start_soc))]

    def seg(n, amps, volts):
        for k in range(n):
            t.append(t[-1] + dt)
            i.append(amps)
            v.append(float(volts(k)))

    q0 = capacities[0]
    if top_up:
        n = int(round((1 - start_soc) * q0 * 3600 / i_a / dt))
        seg(n, i_a, lambda k: ocv(start_soc + (k + 1) * i_a * dt / 3600 / q0) + drop_v)
    for q in capacities:
        seg(60, 0.0, lambda k: ocv(1.0))
        n = int(round(q * 3600 / i_a / dt))
        seg(n, -i_a, lambda k: ocv(1 - (k + 1) / n) - drop_v)
        seg(60, 0.0, lambda k: ocv(0.0))
        seg(n, i_a, lambda k: ocv((k + 1) / n) + drop_v)
    seg(60, 0.0, lambda k: ocv(1.0))
    return TimeSeries(np.array(t), np.array(i), np.array(v), source="c15-cycles.csv")


def test_several_cycles_the_last_complete_one_each_branch_over_its_own_charge():
    """A C/15-style file with a top-up charge and two cycles (the second on an aged cell):
    before, SOC was counted from 0 across the whole file and the OCV came out flat."""
    ocv = lambda s: 3.0 + 1.1 * np.asarray(s) + 0.1 * np.sin(6 * np.asarray(s))  # noqa: E731
    series = _low_rate_cycles(ocv, [2.0, 1.8])
    table, notes = ocv_from_low_rate(series, 2.0)
    text = " ".join(notes)
    assert "cycle 2 of 2" in text and "1.8 Ah" in text
    # 0.1 A samples every 60 s: 1/1200 of SOC on the 2 Ah cycle, less on the aged one
    bound = derived_table_error_v(1 / 1080, 3.6)
    assert np.max(np.abs(table.ocv_v - ocv(table.soc))) < bound
    table1, notes1 = ocv_from_low_rate(series, 2.0, cycle=1)
    assert "cycle 1 of 2" in " ".join(notes1)
    assert np.max(np.abs(table1.ocv_v - ocv(table1.soc))) < bound
    with pytest.raises(InputError, match="c15-cycles.csv: data.ocv_cycle = 3, but the "
                                         "low-rate test has 2"):
        ocv_from_low_rate(series, 2.0, cycle=3)


def test_branches_of_a_cycle_and_the_charge_they_moved():
    from ecmgen.data.lowrate import split_low_rate

    ocv = lambda s: 3.0 + 1.1 * np.asarray(s)  # noqa: E731
    test = split_low_rate(_low_rate_cycles(ocv, [2.0, 1.8]), 2.0)
    assert [b.direction for b in test.branches] == ["charge", "discharge", "charge",
                                                    "discharge", "charge"]
    assert [b.complete for b in test.branches] == [False, True, True, True, True]
    assert test.cycles == ((1, 2), (3, 4))
    # to one sample's charge (0.1 A for 60 s)
    assert test.branches[3].charge_ah == pytest.approx(1.8, abs=0.1 * 60 / 3600)


def test_a_flat_ocv_is_an_error_naming_the_file():
    """The Leaf's C/15 file read as one branch gave 3.9076 V at every SOC: now an error."""
    t = np.arange(0, 20 * 3600.0, 60.0)
    i = np.full(t.size, -0.1)
    v = 3.9076 + 0.0005 * np.sin(t / 5000.0)
    series = TimeSeries(t, i, v, source="flat.csv")
    with pytest.raises(InputError) as exc:
        ocv_from_low_rate(series, 2.0)
    msg = str(exc.value)
    assert msg.startswith("flat.csv: the OCV is flat") and "\n" not in msg


def test_an_lfp_plateau_is_not_flat():
    s = np.linspace(0, 1, 101)
    from ecmgen.data.ocv import OcvTable, check_not_flat

    check_not_flat(OcvTable(s, _lfp_like(s)), "lfp.csv")      # no error
    s = read_timeseries(need(CALCE / "ocv-charge-c22.csv"), capacity_ah=1.1)
    ocv_from_low_rate(s, 1.1)                                  # the real A123 plateau


def test_a_table_with_equal_neighbours_loads_and_inverts(tmp_path):
    """An LFP plateau rounded to 1 mV: equal neighbours are fine, only falls are not."""
    p = tmp_path / "ocv.csv"
    p.write_text("soc,ocv_v\n0,2.9\n0.2,3.300\n0.4,3.300\n0.6,3.300\n1,3.5\n")
    t = read_ocv_table(p)
    assert float(t.soc_at(3.3)) == pytest.approx(0.4)          # the middle of the plateau
    assert float(t.soc_at(3.4)) == pytest.approx(0.8)
    assert float(t.ocv_at(0.3)) == pytest.approx(3.3)


def test_panasonic_c20_branches_normalised_to_their_own_charge():
    """Read as it was, the C/20 file's charge branch ended at SOC 0.9 of 2.9 Ah and the
    average sat 35-80 mV above the pulse test's rested voltages; each branch over its own
    charge it is nearer them, and the charge each branch moved is reported."""
    s = read_timeseries(need(PANASONIC / "ocv-c20.mat"), capacity_ah=2.9)
    table, notes = ocv_from_low_rate(s, 2.9)
    text = " ".join(notes)
    assert "discharge 2.997 Ah, charge 2.616 Ah" in text and "normalised" in text
    assert "13% apart" in text
    from ecmgen.data.dcir import find_pulses
    from ecmgen.data.ocv import ocv_from_pulse_rests

    hppc = read_timeseries(PANASONIC / "hppc.mat", capacity_ah=2.9)
    rests, _ = ocv_from_pulse_rests(hppc, find_pulses(hppc, 2.9, soc0=1.0), 2.9, 1.0)
    g = np.linspace(0.1, 0.95, 18)
    # as it was: each branch over the cell's 2.9 Ah, the charge one counted up from empty
    from ecmgen.data.lowrate import split_low_rate

    dis, chg = split_low_rate(s, 2.9).branches
    q = s.coulomb_ah()
    d, c = slice(dis.start, dis.stop), slice(chg.start, chg.stop)
    old = 0.5 * (np.interp(g, (1.0 + (q[d] - q[dis.start]) / 2.9)[::-1], s.voltage_v[d][::-1])
                 + np.interp(g, (q[c] - q[chg.start]) / 2.9, s.voltage_v[c]))

    def rms(v):
        return float(np.sqrt(np.mean((v - rests.ocv_at(g)) ** 2)))
    assert rms(table.ocv_at(g)) < rms(old), (rms(table.ocv_at(g)), rms(old))
    # the rest after the discharge cut-off gives the OCV at SOC 0 (not 2.5 V under load):
    # the file's rested voltage at the end of that hour-long rest (its last minute of
    # samples: the last two share a time stamp)
    last = s.voltage_v[dis.stop:dis.rest_end][-3:]
    assert last.min() <= table.ocv_v[0] <= last.max(), (table.ocv_v[0], last)


def test_merge_first_source_over_its_span_the_next_beyond_it_shifted():
    from ecmgen.data.ocv import GRID, OcvCurve, merge_curves

    f = lambda s: 3.0 + 1.2 * s  # noqa: E731
    inner = GRID[15:91]
    a = OcvCurve("pulses", inner, f(inner) + 0.005)
    b = OcvCurve("c20.mat", GRID.copy(), f(GRID))
    table, notes, origin = merge_curves([a, b])
    inside = (GRID >= 0.15) & (GRID <= 0.9)
    # a linear truth on the grid: exact but for the strictly-increasing tilt
    tilt = derived_table_error_v(0.0, 0.0)
    assert np.allclose(table.ocv_v[inside], f(GRID[inside]) + 0.005, rtol=0, atol=tilt)
    # beyond: b's own values at its ends, shifted to meet a at the joints in between
    assert table.ocv_v[0] == pytest.approx(f(0.0), abs=tilt)
    assert table.ocv_v[100] == pytest.approx(f(1.0), abs=tilt)
    assert table.ocv_v[8] == pytest.approx(f(0.08) + 0.005 * 8 / 15, abs=tilt)
    assert origin[0] == 1 and origin[50] == 0 and origin[100] == 1
    assert any("SOC 0.00..0.14 from c20.mat, shifted by +5.0 mV at SOC 0.15" in n
               for n in notes)
    assert not any("held flat" in n for n in notes)
    only, notes1, _ = merge_curves([a])
    assert any("measured SOC span 0.15..0.90; held flat beyond it" in n for n in notes1)


@pytest.mark.parametrize("offset_v, warned", [(0.005, False), (0.045, False), (0.17, True)])
def test_a_filling_source_far_from_the_first_where_they_meet_is_warned(offset_v, warned):
    """Before: a low-rate file 170-250 mV from the rests where they meet (the Leaf's
    cycling file against its 25 degC rests) filled the SOC below them without a warning.
    Measured at the joint (data.ocv.JOINT_WARN_V): Panasonic 25 degC C/20 against the 25 /
    0 / -10 / -20 degC rests 19 / 44 / 49 / 74 mV, the Leaf 173 mV."""
    from ecmgen.data.ocv import GRID, OcvCurve, merge_curves

    f = lambda s: 3.0 + 1.2 * s  # noqa: E731
    inner = GRID[12:]
    a = OcvCurve("pulses", inner, f(inner) + offset_v)
    b = OcvCurve("cycling.csv", GRID.copy(), f(GRID))
    _, notes, _ = merge_curves([a, b])
    fill = next(n for n in notes if "from cycling.csv" in n)
    assert ("warning" in fill) == warned, fill
    if warned:
        assert f"{offset_v * 1e3:.0f} mV from pulses" in fill and "below SOC 0.12" in fill
