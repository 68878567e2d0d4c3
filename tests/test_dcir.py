"""Pulse finding and DC-IR extraction: synthetic known truth and the real Panasonic HPPC."""

import numpy as np
import pytest

from conftest import PANASONIC, REPO, flat, make_pulse_test, need, synthetic_nca_model
from ecmgen.data.dcir import extract_dcir, find_pulses, read_dcir_csv
from ecmgen.errors import InputError
from ecmgen.data.measure import TimeSeries, read_timeseries


def test_synthetic_pulses_give_the_analytic_resistance():
    m = flat(synthetic_nca_model())
    series, soc0 = make_pulse_test(m, soc_levels=(0.8, 0.4), c_rates=(1.0, 4.0))
    pulses = find_pulses(series, m.capacity_ah, soc0=soc0)
    assert len(pulses) == 4
    assert not any(p.cut_short for p in pulses)
    assert [p.c_rate for p in pulses] == [1.0, 4.0, 1.0, 4.0]
    assert pulses[0].soc == pytest.approx(0.8, abs=1e-9)
    table = extract_dcir(series, pulses)
    for k, p in enumerate(pulses):
        # R(t) of the 2RC plus the OCV's fall with the charge drawn
        par = m.discharge.at(p.soc)
        t = table.t_s
        expected = (par["r0_ohm"] + par["r_fast_ohm"] * (1 - np.exp(-t / par["tau_fast_s"]))
                    + par["r_slow_ohm"] * (1 - np.exp(-t / par["tau_slow_s"])))
        ocv_drift = (m.ocv.ocv_at(p.soc) - m.ocv.ocv_at(p.soc - p.c_rate * t / 3600)) / (p.c_rate * 2.9)
        assert np.allclose(table.r_ohm[k], expected + ocv_drift, rtol=0, atol=1e-9)


def test_cut_short_pulse_is_flagged_and_left_out():
    m = synthetic_nca_model()
    series, soc0 = make_pulse_test(m, soc_levels=(0.8, 0.5), c_rates=(1.0,))
    # a voltage limit ends the second pulse after 2 s: current drops to zero early
    on = np.flatnonzero(series.current_a < 0)
    second = on[on > on[0] + 200]
    i = series.current_a.copy()
    i[second[20:]] = 0.0
    cut = TimeSeries(series.time_s, i, series.voltage_v, None, series.charge_ah, "cut.csv")
    pulses = find_pulses(cut, 2.9, soc0=soc0)
    assert [p.cut_short for p in pulses] == [False, True]
    table = extract_dcir(cut, pulses)
    assert len(table) == 1
    assert any("cut short" in n for n in table.notes)


def test_a_record_without_pulses_is_refused():
    t = np.arange(0, 3600.0)
    series = TimeSeries(t, np.full(t.size, -1.0), 3.7 - 1e-5 * t, source="cc.csv")
    with pytest.raises(InputError, match="cc.csv: no pulses found"):
        find_pulses(series, 2.9, soc0=1.0)


def test_panasonic_hppc_table():
    series = read_timeseries(need(PANASONIC / "hppc.mat"), capacity_ah=2.9)
    pulses = find_pulses(series, 2.9, soc0=1.0)
    assert len(pulses) == 67
    assert sorted({p.c_rate for p in pulses}) == [0.5, 1.0, 2.0, 4.0, 6.0]
    assert all(p.direction == "discharge" for p in pulses)
    # the voltage limit ends three pulses near empty, a fourth (6C at SOC 0.18) ends
    # within 20 mV of it
    assert sum(p.cut_short for p in pulses) == 4
    # SOC from the Ah column: the pulse sets sit at 100, 95, 90, 80 ... %
    first_of_set = [p.soc for p in pulses if p.c_rate == 0.5]
    assert first_of_set[:4] == pytest.approx([1.0, 0.95, 0.90, 0.80], abs=0.002)
    table = extract_dcir(series, pulses)
    assert len(table) == 63
    r01 = table.r_ohm[:, 0]
    assert np.all((r01 > 0.015) & (r01 < 0.045))
    # R(t) grows with time into every pulse
    assert np.all(np.diff(table.r_ohm, axis=1) > 0)


def test_dcir_csv_round_trip(tmp_path):
    table = read_dcir_csv(REPO / "tests" / "data" / "paper-table1.csv")
    assert table.t_s.tolist() == [0.1, 1, 3, 6, 10]
    assert table.r_ohm[0].tolist() == [0.0002, 0.0012, 0.0021, 0.0023, 0.0025]
    p = table.write_csv(tmp_path / "t.csv")
    again = read_dcir_csv(p)
    assert np.array_equal(again.r_ohm, table.r_ohm)


def test_dcir_csv_errors(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("soc,direction,t_s\n0.5,charge,1\n")
    with pytest.raises(InputError, match="bad.csv: missing column 'r_ohm'"):
        read_dcir_csv(p)
    p.write_text("soc,direction,t_s,r_ohm\n0.5,sideways,1,0.01\n")
    with pytest.raises(InputError, match="direction"):
        read_dcir_csv(p)


def test_a_slow_logger_does_not_reuse_the_first_sample():
    """At 1 s logging the first on-sample is R0's; R(1 s) cannot come from it too."""
    m = flat(synthetic_nca_model())
    series, soc0 = make_pulse_test(m, soc_levels=(0.6,), c_rates=(2.0,))
    on = series.current_a != 0
    keep = ~on | (np.round(series.time_s, 6) % 1.0 == 0)   # 1 Hz during the pulse
    slow = TimeSeries(series.time_s[keep], series.current_a[keep], series.voltage_v[keep],
                      None, series.charge_ah[keep], "slow.csv")
    pulses = find_pulses(slow, 2.9, soc0=soc0)
    table = extract_dcir(slow, pulses)
    assert np.isnan(table.r_ohm[0, 1])          # 1 s: only the first sample is there
    assert np.isfinite(table.r_ohm[0, [0, 2, 3, 4]]).all()
    assert any("logger is too slow" in n for n in table.notes)


def test_soc_outside_0_1_names_the_start_soc_and_capacity():
    m = synthetic_nca_model()
    series, _ = make_pulse_test(m, soc_levels=(0.5, 0.1), c_rates=(1.0,))
    with pytest.raises(InputError, match="pulses_soc0.*capacity_ah"):
        find_pulses(series, 2.9, soc0=0.5)   # the test really started full


def test_a_dynamic_profile_is_not_a_pulse_test():
    t = np.arange(0, 2000.0)
    i = np.where((t // 5) % 2 == 0, -2.0, 0.0)   # 5 s on, 5 s off: never a real rest
    series = TimeSeries(t, i, 3.7 + 0.02 * i, source="dst.csv")
    with pytest.raises(InputError, match="dst.csv: no pulses found.*not a pulse test"):
        find_pulses(series, 2.9, soc0=1.0)


def test_usabc_hppc_discharge_then_regen_after_40_s():
    """A 10 s discharge pulse, 40 s rest, a 10 s regen pulse: both are pulses."""
    m = flat(synthetic_nca_model())
    from ecmgen.model.simulate import simulate

    t = np.arange(0, 700.0, 0.1)
    i = np.zeros_like(t)
    i[(t > 300) & (t <= 310)] = -14.5
    i[(t > 350) & (t <= 360)] = 10.9
    sim = simulate(m, t, i, 0.5)
    series = TimeSeries(t, i, sim.voltage_v, source="hppc.csv")
    pulses = find_pulses(series, 2.9, soc0=0.5)
    assert [p.direction for p in pulses] == ["discharge", "charge"]
    table = extract_dcir(series, pulses)
    for k, tab in enumerate((m.discharge, m.charge)):
        p = tab.at(0.5)
        # R(0.1 s): R0, what both RC pairs reach in 0.1 s and the OCV's move with the
        # charge passed; the regen pulse starts while the slow pair still relaxes from
        # the discharge (a few micro-ohm)
        docv_dq = (m.ocv.ocv_at(0.51) - m.ocv.ocv_at(0.49)) / 0.02 / (3600 * 2.9)
        r01 = (p["r0_ohm"] + p["r_fast_ohm"] * -np.expm1(-0.1 / p["tau_fast_s"])
               + p["r_slow_ohm"] * -np.expm1(-0.1 / p["tau_slow_s"]) + docv_dq * 0.1)
        assert table.r_ohm[k, 0] == pytest.approx(float(r01), abs=5e-6)


def test_cut_short_is_judged_against_every_pulse_of_the_file():
    """At -10 degC the voltage limit cuts every 6C pulse (0.2 .. 1.9 s of 10 s): a median
    over the 6C pulses alone is itself short and let half of them through."""
    from conftest import SHARED_DATA

    series = read_timeseries(need(SHARED_DATA / "panasonic-18650pf-n10degC" / "hppc.mat"),
                             capacity_ah=2.9)
    pulses = find_pulses(series, 2.9, soc0=1.0)
    six = [p for p in pulses if p.c_rate == 6.0]
    assert len(six) == 6 and all(p.cut_short for p in six)
    assert sum(p.cut_short for p in pulses) == 11
    assert all(p.duration_s > 9.5 for p in pulses if not p.cut_short)


def test_a_clean_test_has_no_voltage_limit():
    """The deepest pulse of a test that never hit a limit is not cut for being deepest."""
    m = synthetic_nca_model()
    series, soc0 = make_pulse_test(m, soc_levels=(0.5, 0.1), c_rates=(1.0, 6.0))
    assert not any(p.cut_short for p in find_pulses(series, 2.9, soc0=soc0))


def test_usabc_leaf_hppc_regen_pulse_straight_into_the_soc_move():
    """A 30 s discharge pulse, 40 s rest, a 10 s regen pulse that runs straight into the
    C/3 SOC move (the Leaf's Bitrode HPPC). Before, the regen pulse and the move were one
    step (too long for a pulse): every charge pulse was missed."""
    from conftest import make_usabc_hppc

    truth = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=30.0)
    series = make_usabc_hppc(truth)
    pulses = find_pulses(series, 2.9, soc0=1.0)
    assert [p.direction for p in pulses] == ["discharge", "charge"] * 4
    assert [round(p.duration_s, 1) for p in pulses] == [30.0, 10.0] * 4
    assert not any(p.cut_short for p in pulses)
    charge = [p for p in pulses if p.direction == "charge"]
    # the regen pulse ends at the step into the SOC move: no relaxation after it, except
    # the last one, which rests
    assert all(p.next_start == p.stop for p in charge[:-1]) and charge[-1].next_start > charge[-1].stop
    assert all(series.current_a[p.stop] < 0 for p in charge[:-1])
    table = extract_dcir(series, pulses, (0.1, 1.0, 3.0, 10.0, 30.0))
    for k, p in enumerate(pulses):
        par = (truth.charge if p.direction == "charge" else truth.discharge).at(p.soc)
        t = table.t_s
        # the 2RC's R(t) plus the OCV's move with the charge passed
        dq = p.current_a * t / 3600.0 / 2.9
        ocv_move = (truth.ocv.ocv_at(p.soc + dq) - truth.ocv.ocv_at(p.soc)) / (p.current_a)
        expected = (par["r0_ohm"] + par["r_fast_ohm"] * -np.expm1(-t / par["tau_fast_s"])
                    + par["r_slow_ohm"] * -np.expm1(-t / par["tau_slow_s"]) + ocv_move)
        got = table.r_ohm[k]
        ok = np.isfinite(got)
        assert ok.sum() == (5 if p.direction == "discharge" else 4)     # 30 s: discharge only
        # within 5 %: the regen pulse's rest still relaxes from the discharge pulse (2-3 %)
        assert np.all(np.abs(got[ok] / expected[ok] - 1) < 0.05), (p.direction, p.soc)


def test_a_pulse_is_a_plateau_whatever_follows_it():
    """A discharge pulse that steps straight to another current (no rest in between)
    still ends at the step; a steady current after a rest is a pulse up to max_pulse_s."""
    m = flat(synthetic_nca_model())
    from ecmgen.model.simulate import simulate

    t = np.arange(0, 900.0, 0.1)
    i = np.zeros_like(t)
    i[(t > 300) & (t <= 310)] = -14.5          # 10 s at 5C ...
    i[(t > 310) & (t <= 700)] = -1.0           # ... straight into a 390 s C/3 discharge
    v = simulate(m, t, i, 0.8).voltage_v
    pulses = find_pulses(TimeSeries(t, i, v, source="x.csv"), 2.9, soc0=0.8)
    assert len(pulses) == 1
    p = pulses[0]
    assert p.duration_s == pytest.approx(10.0, abs=0.15) and p.current_a == pytest.approx(-14.5)
    assert p.next_start == p.stop and i[p.stop] == -1.0


def test_a_plateau_stepping_on_into_a_drive_profile_is_not_a_pulse():
    """After a long rest, a dynamic profile's first few seconds are a plateau too; what
    follows it keeps changing, so it is not a pulse (the A123 DST blocks)."""
    t = np.arange(0, 1000.0)
    rng = np.random.default_rng(1)
    i = np.repeat(rng.uniform(-3.0, 1.0, 100), 10)
    i[:300] = 0.0
    series = TimeSeries(t, i, 3.7 + 0.02 * i, source="dst.csv")
    with pytest.raises(InputError, match="dst.csv: no pulses found"):
        find_pulses(series, 2.9, soc0=0.8)


def _logged_every(series, dt_s):
    """The pulse test as a logger with a ``dt_s`` interval inside the pulses keeps it."""
    on = series.current_a != 0
    keep = ~on | (np.round(series.time_s, 6) % dt_s == 0)
    return TimeSeries(series.time_s[keep], series.current_a[keep], series.voltage_v[keep],
                      None, series.charge_ah[keep], f"every-{dt_s:g}s.csv")


def test_times_before_the_first_sample_take_its_value_said_in_a_note():
    """At 2 s logging the 1 s time comes before the first sample after the edge. Before:
    no value there and no word of it; now the first sample's R, said in a note."""
    m = flat(synthetic_nca_model())
    series, soc0 = make_pulse_test(m, soc_levels=(0.6,), c_rates=(2.0,))
    slow = _logged_every(series, 2.0)
    table = extract_dcir(slow, find_pulses(slow, 2.9, soc0=soc0))
    assert table.r_ohm[0, 1] == table.r_ohm[0, 0]
    assert any("DC-IR time 1 s comes before the first sample" in n and "1 of 1 pulses" in n
               for n in table.notes)
    assert np.isfinite(table.r_ohm[0, [2, 3, 4]]).all() or \
        any("DC-IR time 3 s: no value" in n for n in table.notes)


def test_a_time_without_a_value_is_said_and_dropped_before_the_fits(tmp_path, capsys):
    """At 1 s logging the 1 s time's sample is R0's: the table has no value there. Before:
    not a word, `dcir` said '1 pulses x 5 times' for 4 rows, and a build failed with 'no
    SOC level has an R(t) value at every [dcir] times_s'."""
    from ecmgen.cli import main
    from ecmgen.data.measure import write_timeseries_csv
    from ecmgen.fit.points import five_point_rows
    from ecmgen.config import load_config
    from ecmgen.pipeline import prepare

    m = flat(synthetic_nca_model())
    series, soc0 = make_pulse_test(m, soc_levels=(0.8, 0.6), c_rates=(2.0,))
    slow = _logged_every(series, 1.0)
    table = extract_dcir(slow, find_pulses(slow, 2.9, soc0=soc0))
    assert any("DC-IR time 1 s: no value in 2 of 2 pulses" in n for n in table.notes)
    path = write_timeseries_csv(slow, tmp_path / "hppc.csv")
    out = tmp_path / "dcir.csv"
    assert main(["dcir", str(path), "--capacity-ah", "2.9", "--soc0", f"{soc0}",
                 "--out", str(out)]) == 0
    said = capsys.readouterr().err
    written = out.read_text().count("\n") - 1
    assert written == 8 and f"wrote {written} R(t) values (2 pulses; 0.1 s: 2, 1 s: 0" in said
    cfg = tmp_path / "cell.toml"
    (tmp_path / "ocv.csv").write_text("soc,ocv_v\n" + "".join(
        f"{s!r},{v!r}\n" for s, v in zip(m.ocv.soc.tolist(), m.ocv.ocv_v[0].tolist())))
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "hppc.csv"\n'
                   f'pulses_soc0 = {soc0}\nocv = "ocv.csv"\n')
    dcir = prepare(load_config(cfg)).dcir
    assert dcir.t_s.tolist() == [0.1, 3.0, 6.0, 10.0]
    rows, _ = five_point_rows(dcir)
    assert len(rows) == 2 and np.isfinite(rows.r_ohm).all()


def test_the_first_time_asked_is_read_at_that_time_not_at_the_first_sample():
    """`--times 1 3 6 10` (also `[dcir] times_s`): before, R(1 s) was the first sample's
    (0.1 s) value, as if the first time were always R0; the analytic R(t) of the model is
    the truth at each time."""
    m = flat(synthetic_nca_model())
    series, soc0 = make_pulse_test(m, soc_levels=(0.6,), c_rates=(2.0,))
    pulses = find_pulses(series, m.capacity_ah, soc0=soc0)
    full = extract_dcir(series, pulses, (0.1, 1.0, 3.0, 6.0, 10.0))
    late = extract_dcir(series, pulses, (1.0, 3.0, 6.0, 10.0))
    assert np.array_equal(late.r_ohm, full.r_ohm[:, 1:])
    assert late.r_ohm[0, 0] > full.r_ohm[0, 0] * 1.05       # R(1 s) above R(0.1 s)
