"""Start SOC from all the evidence: a pulse test's start SOC fitted on all its
rests with a hysteresis offset; a record's start SOC robust to a top-up charge and to
an LFP cell's flat OCV; a warning when the simulated SOC leaves [0, 1]."""

import numpy as np
import pytest

from conftest import synthetic_nca_model
from ecmgen.data.measure import TimeSeries
from ecmgen.data.ocv import curve_from_low_rate, merge_curves
from ecmgen.data.soc import find_rests, fit_start_soc, record_start_soc
from ecmgen.diagnosis.synthcell import random_cell
from ecmgen.model.simulate import simulate, validate

# The spec: the start SOC of a test within 1 % of its truth.
SPEC_SOC = 0.01


def _lfp_cell(seed=1):
    """A flat-OCV LFP cell whose hidden hysteresis starts on the discharge branch."""
    return random_cell(seed, "hysteresis", chemistry="lfp",
                       effect_options={"initial_state": -1.0})


def _mean_branch_ocv(cell):
    low = cell.ocv_test()
    return merge_curves([curve_from_low_rate(low, cell.capacity_ah, "ocv")])[0]


@pytest.mark.parametrize("seed", [1, 2])
def test_pulse_test_start_soc_on_a_flat_lfp_ocv_with_hysteresis(seed):
    """Inverting the first rest through the mean-branch OCV is off by 0.2-0.3 on the LFP
    plateau (the rest sits on the discharge branch); the fit over all rests is not."""
    cell = _lfp_cell(seed)
    q = cell.capacity_ah
    pulses = cell.pulse_test(levels=(0.45, 0.3, 0.15, 0.05), c_rates_discharge=(1.0, 2.0),
                             c_rates_charge=(1.0,), soc_start=0.55)
    ocv = _mean_branch_ocv(cell)
    first_rest = float(ocv.soc_at(pulses.voltage_v[0]))
    assert abs(first_rest - 0.55) > SPEC_SOC      # what the old start SOC did
    rests = find_rests(pulses, 0.02 * q, 300.0)
    fit = fit_start_soc(ocv, q, rests, "pulses.csv")
    assert fit.soc0 == pytest.approx(0.55, abs=SPEC_SOC)
    # the rests after a discharge sit below the mean-branch OCV by the hysteresis: the cell
    # stays on its discharge branch (h = -1; the 1C charge pulses barely move it), m_v
    # below, give or take its instantaneous m0_v and what the spec's 1 % of start SOC
    # moves the OCV over the rests' SOC range
    hys = cell.hidden.effects[0]
    slack = SPEC_SOC * float(ocv.ocv_at(0.55) - ocv.ocv_at(0.05)) / 0.5
    assert -hys.m_v - hys.m0_v - slack <= fit.offset_v["after discharge"] \
        <= -hys.m_v + hys.m0_v + slack, (fit.offset_v, hys)
    assert "hysteresis offset" in fit.note


def _lfp_drive_start():
    cell = _lfp_cell(1)
    ocv = _mean_branch_ocv(cell)
    cycle = cell.drive_cycle(soc_start=0.9, soc_end=0.3)
    soc0, how = record_start_soc(ocv, cell.capacity_ah, cycle, cell.capacity_ah / 100)
    return ocv, cycle, soc0, how


def test_drive_cycle_on_a_flat_lfp_ocv_fits_all_its_rests():
    ocv, cycle, soc0, how = _lfp_drive_start()
    assert "fit to its rests" in how
    # its first rest alone, on the plateau and on the discharge branch, says worse
    assert abs(float(ocv.soc_at(cycle.voltage_v[599])) - 0.9) > abs(soc0 - 0.9)


@pytest.mark.xfail(strict=True, reason="known miss: 0.879 against 0.9; the rests' true "
                   "offsets vary with how far the hysteresis had moved, one per direction "
                   "is fitted")
def test_drive_cycle_on_a_flat_lfp_ocv_start_within_the_spec():
    _, _, soc0, _ = _lfp_drive_start()
    assert soc0 == pytest.approx(0.9, abs=SPEC_SOC)


def _top_up_then_discharge(model):
    """A 1C/2C/3C-style file: it opens charging, a CC-CV top-up from SOC 0.87 (the
    voltage held, the current tapering to C/40), straight into a 1C discharge to 20 %
    SOC, then a 1 h rest."""
    q = model.capacity_ah
    t = np.arange(0.0, 20000.0, 1.0)
    i = np.zeros(t.size)
    cc = 400                                      # 0.5C for 400 s: +0.056
    i[:cc] = 0.5 * q
    cv = np.arange(cc, cc + 1800)
    i[cv] = 0.5 * q * np.exp(-(cv - cc) / 600.0)   # tapers to 0.025 C
    start_dis = cc + 1800
    n_dis = int(0.8 * 3600)
    i[start_dis:start_dis + n_dis] = -q
    stop = start_dis + n_dis + 3600
    t, i = t[:stop], i[:stop]
    charged = np.sum(i[1:start_dis]) / 3600.0 / q    # the record's own (rectangle) count
    soc0 = 1.0 - charged                          # full at the end of the CV phase
    v = simulate(model, t, i, soc0).voltage_v
    v[cc:start_dis] = v[cc]                       # the charger holds the voltage
    return TimeSeries(t, i, v, source="1c.csv"), soc0


def test_a_record_opening_with_a_top_up_charge_is_full_at_its_end():
    """Before: the first rested sample was the rest after the 1C discharge (still
    relaxing up from the cut-off), giving a start SOC 0.05-0.1 too high or low."""
    m = synthetic_nca_model()
    series, soc0 = _top_up_then_discharge(m)
    got, how = record_start_soc(m.ocv, m.capacity_ah, series, m.capacity_ah / 100)
    # to the count's resolution: one 1 s sample of the 0.5C charge
    assert got == pytest.approx(soc0, abs=0.5 * 1.0 / 3600.0)
    assert "constant-voltage" in how


def test_a_record_opening_rested_takes_the_most_relaxed_sample_of_that_rest():
    """The rest a record opens with still relaxes from a charge: its last sample is
    the one nearest the OCV."""
    m = synthetic_nca_model()
    t = np.arange(0.0, 1200.0, 1.0)
    i = np.where(t >= 600, -2.9, 0.0)
    v = simulate(m, t, i, 0.7).voltage_v
    v[:600] += 0.010 * np.exp(-t[:600] / 120.0)   # relaxing down from a charge
    got, how = record_start_soc(m.ocv, m.capacity_ah, TimeSeries(t, i, v, source="c.csv"),
                                0.029)
    # no further off than the relaxation the last sample still holds, through the OCV
    ocv = m.ocv.at_temperature(None)
    left = float(ocv.soc_at(ocv.ocv_at(0.7) + 0.010 * np.exp(-t[599] / 120.0))) - 0.7
    assert abs(got - 0.7) <= left + 1e-9, (got, left)
    assert "last sample of the rest it opens with" in how


def test_a_simulated_soc_outside_0_1_is_warned_about():
    m = synthetic_nca_model()
    t = np.arange(0.0, 4000.0, 1.0)
    i = np.full(t.size, -2.9)
    i[:10] = 0.0
    v = simulate(m, t, i, 1.0).voltage_v
    series = TimeSeries(t, i, v, source="long.csv")
    val = validate(m, series, soc0=1.0)
    assert val.soc0_how == "given"
    assert len(val.warnings) == 1 and "long.csv: simulated SOC runs" in val.warnings[0]
    assert "outside [0, 1]" in val.warnings[0]
    assert not validate(m, series.slice(0, 3000), soc0=1.0).warnings


@pytest.mark.parametrize("scale", [0.88, 1.0, 1.14])
def test_start_soc_and_capacity_from_the_rests_together(scale):
    """A pulse test run on a cell whose capacity is not the nominal one: the rests fix the
    start SOC and the capacity together; with the right capacity nothing moves."""
    from dataclasses import replace

    from conftest import make_pulse_test
    from ecmgen.data.soc import pulse_test_start_soc_and_capacity

    nominal = synthetic_nca_model()
    truth = replace(nominal, capacity_ah=scale * nominal.capacity_ah)
    series, soc0 = make_pulse_test(truth, soc_levels=(0.85, 0.7, 0.55, 0.4, 0.25),
                                   c_rates=(1.0, 2.0), noise_v=0.0005, seed=2, log_moves=True)
    rests = find_rests(series, 0.02 * nominal.capacity_ah, 300.0)
    fit, q = pulse_test_start_soc_and_capacity(nominal.ocv, nominal.capacity_ah, rests, "p.csv")
    # the spec: the start SOC and the SOC at the last level within 1 %
    assert fit.soc0 == pytest.approx(soc0, abs=SPEC_SOC)
    last = rests.charge_ah[-1]
    assert fit.soc0 + last / q == pytest.approx(soc0 + last / truth.capacity_ah, abs=SPEC_SOC)
    assert ("the capacity the rests imply" in fit.note) == (scale != 1.0)


# --------------------------------------------------------------------------- opening rests

def test_an_unrelaxed_opening_rest_is_taken_where_its_relaxation_heads():
    """A record that opens 20 s into a rest after a discharge, its voltage still
    recovering (one exponential, 30 s, 60 mV below the OCV at the first sample). Before:
    the OCV of its last sample, 3 % SOC low; now where the relaxation heads (Aitken's
    delta squared over the rest), exact for one exponential but for float rounding."""
    from ecmgen.data.soc import _relaxed_voltage

    m = synthetic_nca_model()
    ocv = m.ocv.at_temperature(None)
    soc_true = 0.6
    t = np.arange(0.0, 600.0, 1.0)
    i = np.where(t < 20, 0.0, -2.9)
    v_rest = float(ocv.ocv_at(soc_true)) - 0.060 * np.exp(-t[:20] / 30.0)
    q = np.concatenate(([0.0], np.cumsum(i[1:] * 1.0 / 3600)))
    v = np.concatenate([v_rest, ocv.ocv_at(soc_true + q[20:] / 2.9) - 0.03])
    rec = TimeSeries(t, i, v, source="unrelaxed")
    # float64 rounding, amplified by the second difference of samples that near the OCV
    rounding = 1e6 * np.finfo(float).eps
    assert _relaxed_voltage(rec, 19) == pytest.approx(float(ocv.ocv_at(soc_true)),
                                                      abs=rounding)
    soc0, how = record_start_soc(ocv, 2.9, rec, rest_a=0.029)
    assert abs(soc0 - soc_true) < rounding and "relaxation" in how, how
    old = float(ocv.soc_at(v[19]))
    assert soc_true - old > SPEC_SOC     # what the last sample alone gave


@pytest.mark.slow
def test_auto_start_soc_of_the_shared_cycles_within_half_a_millivolt_of_a_full_start():
    """The eight shared Panasonic drive cycles start full: each auto start gives the MAE of
    SOC 1.0 within the spec's 0.5 mV, or says it is uncertain with 1.0 within two of its sigma
    (the 95 % interval of the uncertainty it states, read as a normal one) (six
    open under load, read against the model over their first 2400 s; this older model
    errs 60 mV on the -20 degC US06, whose start it reads 0.99 +- 0.02)."""
    from ecmgen.model.simulate import start_estimate

    from conftest import REPO, SHARED_DATA, need
    from ecmgen.data.measure import read_timeseries
    from ecmgen.model.model import load_model

    model = load_model(REPO / "tests" / "data" / "panasonic-temperature-model.json")
    for folder, name in [("25degC", "us06"), ("25degC", "hwfet-a"), ("0degC", "us06"),
                         ("0degC", "hwfet"), ("n10degC", "us06"), ("n10degC", "hwfet"),
                         ("n20degC", "us06"), ("n20degC", "hwfet")]:
        series = read_timeseries(need(SHARED_DATA / f"panasonic-18650pf-{folder}" /
                                      f"{name}.mat"))
        auto, full = validate(model, series, None), validate(model, series, 1.0)
        got = start_estimate(model, series)
        assert abs(auto.overall.mae_v - full.overall.mae_v) < 0.5e-3 or \
            (got.uncertain and abs(got.soc0 - 1.0) <= 2 * got.sigma), (folder, name, got)


def test_a_start_soc_that_needs_an_offset_beyond_any_hysteresis_is_said_uncertain():
    """A cell whose OCV falls steeply towards empty, and an OCV table held flat below SOC
    0.12 (a test whose rests stop there): rests down to SOC 0.05 pull the fit to an offset
    far beyond a hysteresis (LFP: 10-30 mV) and its note says the start is uncertain; with
    the true OCV it says nothing."""
    from ecmgen.data.ocv import OcvTable
    from ecmgen.data.soc import Rests

    soc = np.linspace(0.0, 1.0, 101)
    true_v = 3.2 + 0.9 * soc - 0.5 * np.exp(-soc / 0.04)
    held_v = np.where(soc < 0.12, true_v[12], true_v)
    at = np.array([0.9, 0.6, 0.3, 0.05])
    rests = Rests(np.arange(4), np.full(4, 3600.0), np.array([0, -1, -1, -1]),
                  (at - at[0]) * 2.0, OcvTable(soc, true_v).ocv_at(at))
    held = fit_start_soc(OcvTable(soc, held_v), 2.0, rests, "cycle.csv")
    true = fit_start_soc(OcvTable(soc, true_v), 2.0, rests, "cycle.csv")
    assert "warning" in held.note and "uncertain" in held.note
    # noise-free rests on the true OCV: exact but for the solver's tolerance
    assert "warning" not in true.note and true.soc0 == pytest.approx(0.9, abs=1e-6)


def _drive(seconds: float, seed: int = 0):
    """A discharge-heavy drive profile (1 Hz, 20 s steps of -8 .. +2 A)."""
    t = np.arange(0.0, seconds, 1.0)
    rng = np.random.default_rng(seed)
    return t, np.repeat(rng.uniform(-8.0, 2.0, t.size // 20 + 1), 20)[:t.size]


@pytest.mark.parametrize("cut_s", [900.0, 1805.0])
def test_a_record_cut_under_load_is_read_against_the_model(cut_s):
    """The model's own cell (1 mV noise), driven from SOC 0.9 and cut in the drive: the
    opening is unsettled, the start SOC comes from the voltage over the first window
    against the model, within its 3 sigma of the truth (the estimator spec) and 3 sigma
    within the spec's 1 %, and it is sure of it;
    the opening rest logic read the first 20 s step's voltage as a rest before."""
    from ecmgen.model.simulate import start_estimate

    model = synthetic_nca_model()
    t, i = _drive(5400.0)
    sim = simulate(model, t, i, 0.9)
    v = sim.voltage_v + np.random.default_rng(1).normal(0.0, 0.001, t.size)
    k = int(np.searchsorted(t, cut_s))
    part = TimeSeries(t[k:] - t[k], i[k:], v[k:])
    got = start_estimate(model, part)
    assert not got.settled and "against the model" in got.how
    assert abs(got.soc0 - sim.soc[k - 1]) <= 3 * got.sigma, (got.soc0, got.sigma)
    assert 3 * got.sigma < SPEC_SOC and "uncertain" not in got.how


def test_an_unsure_start_is_said_uncertain_on_validate():
    """The same cut judged by a model 30 % off in its resistances: the start SOC moves and
    the residual grows, and validate warns that the start is uncertain."""
    from dataclasses import replace as dc_replace

    model = synthetic_nca_model()
    t, i = _drive(5400.0)
    v = simulate(model, t, i, 0.9).voltage_v
    k = int(np.searchsorted(t, 1805.0))
    part = TimeSeries(t[k:] - t[k], i[k:], v[k:], source="cut.csv")
    wrong = dc_replace(model, discharge=dc_replace(model.discharge,
                                                   r0_ohm=model.discharge.r0_ohm * 1.3,
                                                   r_slow_ohm=model.discharge.r_slow_ohm * 1.3))
    val = validate(wrong, part)
    assert any("start SOC" in w and "uncertain" in w for w in val.warnings)
