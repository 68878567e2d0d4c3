"""The pieces of the whole-test fit that make it well posed (ecmgen.fit.curve_levels and
the curve fit's own helpers): level nodes, time-constant ranges from the record, the
second difference on uneven nodes, the after-charge state and the rows' SOC span."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import make_pulse_test, synthetic_nca_model
from ecmgen.data.dcir import find_pulses
from ecmgen.fit.curve import CurveOptions, fit_pulse_curves, second_difference
from ecmgen.fit.curve_record import after_charge
from ecmgen.fit.curve_levels import data_tau_ranges, level_nodes, level_windows


def test_second_difference_is_1_2_1_on_an_even_grid_and_zero_on_a_line():
    d = second_difference(np.linspace(0.1, 0.9, 5))
    assert np.allclose(d[0, :3], [1.0, -2.0, 1.0])
    uneven = np.array([0.05, 0.1, 0.2, 0.5, 0.9])
    assert np.allclose(second_difference(uneven) @ (3.0 * uneven + 1.0), 0.0)
    assert second_difference(np.array([0.2, 0.4])).shape == (0, 2)


def test_the_after_charge_state_follows_the_last_current():
    i = np.array([0, 0, -1, -1, 0, 0, 2, 2, -1, -1, 0, 3, 0, 0.0])
    assert after_charge(i).astype(int).tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 0, 0, 0, 1, 1, 1]


def test_time_constant_ranges_follow_the_sampling_and_the_relaxation():
    ranges = {"fast": (0.1, 10.0), "slow": (5.0, 500.0), "diff": (150.0, 3000.0)}
    got, notes = data_tau_ranges(ranges, sampling_s=1.0, relaxation_s=1200.0)
    assert got == {"fast": (1.0, 10.0), "slow": (5.0, 500.0), "diff": (150.0, 1200.0)}
    assert len(notes) == 2 and "sampling" in notes[0] and "longest relaxation" in notes[1]
    same, notes = data_tau_ranges(ranges, sampling_s=0.1, relaxation_s=5000.0)
    assert same == ranges and notes == []
    # nothing left to search: the configured range stays
    kept, _ = data_tau_ranges({"diff": (150.0, 3000.0)}, 0.1, 200.0)
    assert kept == {"diff": (150.0, 3000.0)}


@pytest.fixture(scope="module")
def pulse_test():
    truth = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=60.0)
    series, soc0 = make_pulse_test(truth, soc_levels=(0.8, 0.5, 0.2), c_rates=(1.0, 3.0),
                                   noise_v=0.0005, seed=4, log_moves=True)
    return truth, series, find_pulses(series, truth.capacity_ah, soc0=soc0)


def test_level_nodes_are_the_mid_pulse_socs_of_each_direction(pulse_test):
    truth, series, pulses = pulse_test
    nodes = level_nodes(pulses, "discharge", truth.capacity_ah)
    # the profile's own arithmetic: at each level a 1C then a 3C pulse of 10 s, the first
    # from the level (mid-pulse 5 s of 1C below it), the second after the first's 10 s (10 s
    # of 1C and 5 s of 3C below); the node is their mean (the SOC from the Ah column: to
    # float rounding)
    MID_SHIFT = ((5.0 * 1.0) + (10.0 * 1.0 + 5.0 * 3.0)) / 2 / 3600.0
    assert nodes == pytest.approx(np.array([0.2, 0.5, 0.8]) - MID_SHIFT, abs=1e-9)
    assert level_nodes(pulses, "charge", truth.capacity_ah).size == 0
    ocv_nodes, level = level_windows(pulses, series.time_s, series.time_s)
    assert ocv_nodes.size == 3 and set(np.unique(level)) == {-1, 0, 1, 2}


def test_rows_beyond_the_pulses_soc_do_not_count(pulse_test, monkeypatch):
    """A discharge to empty after the last level (held-flat tables, extrapolated OCV)
    leaves the fit as it is."""
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate

    truth, series, pulses = pulse_test
    t_end = series.time_s[-1]
    t = np.arange(1.0, 3000.0, 1.0) + t_end
    i = np.full(t.size, -2.9)
    # the same cell past its last level, but with an OCV 50 mV off below SOC 0.15
    sim = simulate(truth, np.concatenate((series.time_s, t)),
                   np.concatenate((series.current_a, i)), 1.0)
    v = sim.voltage_v[series.time_s.size:] - 0.05
    longer = TimeSeries(np.concatenate((series.time_s, t)), np.concatenate((series.current_a, i)),
                        np.concatenate((series.voltage_v, v)), None, None, "p.csv")
    kw = dict(diffusion=False)
    a = fit_pulse_curves(series, pulses, truth.ocv, truth.capacity_ah, CurveOptions(**kw))
    b = fit_pulse_curves(longer, pulses, truth.ocv, truth.capacity_ah, CurveOptions(**kw))
    # only the first SPAN_MARGIN of SOC past the last level counts: 36 s at 1C
    assert a.n_rows < b.n_rows <= a.n_rows + 36
    # the rows past it change nothing: the fit is the one of the record cut where the
    # counted rows end (1 Hz, one row a sample)
    n = series.time_s.size + b.n_rows - a.n_rows
    cut = TimeSeries(longer.time_s[:n], longer.current_a[:n], longer.voltage_v[:n],
                     None, None, "p.csv")
    d = fit_pulse_curves(cut, pulses, truth.ocv, truth.capacity_ah, CurveOptions(**kw))
    for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
        assert np.array_equal(getattr(d.discharge, k), getattr(b.discharge, k)), k
    assert (d.tau_fast_s, d.tau_slow_s) == (b.tau_fast_s, b.tau_slow_s)
    from ecmgen.fit import curve

    monkeypatch.setattr(curve, "SPAN_MARGIN", 1.0)           # every row counts
    c = fit_pulse_curves(longer, pulses, truth.ocv, truth.capacity_ah, CurveOptions(**kw))

    def moved(f):
        return max(float(np.max(np.abs(getattr(f.discharge, k) / getattr(a.discharge, k) - 1)))
                   for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"))
    # every row counting, the 50 mV-off discharge moves the tables further than the rows
    # within the margin do
    assert moved(c) > moved(b)


def test_the_log_penalty_is_the_second_difference_of_ln_r_near_its_references():
    from ecmgen.fit.curve_levels import log_penalty

    nodes = np.array([0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9])
    dd = second_difference(nodes)
    ref = 0.002 * np.exp(np.array([2.1, 1.4, 0.3, 0.2, 0.0, 0.1, 0.15]))
    ww, wb, bb = log_penalty(dd, ref)
    s = float(np.mean(ref))

    def quadratic(r):
        return float(r @ ww @ r - 2.0 * wb @ r + bb)

    def exact(r):
        return float(np.sum((s * (dd @ np.log(r))) ** 2))

    assert quadratic(ref) == pytest.approx(exact(ref), rel=1e-12)
    step = np.random.default_rng(0).normal(size=ref.size)
    # first-order accurate: the mismatch falls with the square of the step
    e1, e2 = (abs(quadratic(ref * np.exp(h * step)) - exact(ref * np.exp(h * step)))
              for h in (1e-2, 1e-3))
    assert e2 < 2e-2 * e1
