"""model.temperature.assemble_over_temperature on known truth: one-temperature models made
from an Arrhenius law are joined into tables that reproduce the law between the
breakpoints, extrapolate it to the derived warm row, clamp outside and come out the same
whatever the order of the inputs."""

from __future__ import annotations

import numpy as np
import pytest

from ecmgen.model.model import EcmModel, OcvTable, RcTable, model_from_json_dict
from ecmgen.model.temperature import (KELVIN, arrhenius_interp, assemble_over_temperature,
                                      temperature_grid)

T_REF = 25.0
SOC = np.linspace(0.0, 1.0, 11)
# Ea/R in kelvin per parameter (a time constant may fall or rise with temperature)
EA = {"r0_ohm": 1800.0, "r_fast_ohm": 6000.0, "r_slow_ohm": 2500.0, "tau_fast_s": 300.0,
      "tau_slow_s": -200.0, "r_diff_ohm": 2300.0, "i0_a": -5200.0}
REF = {"r0_ohm": lambda s: 0.020 + 0.010 * (1 - s) ** 2,
       "r_fast_ohm": lambda s: np.full(np.shape(s), 0.005),
       "r_slow_ohm": lambda s: 0.012 + 0.004 * s, "tau_fast_s": lambda s: 1.0 + 0.2 * s,
       "tau_slow_s": lambda s: np.full(np.shape(s), 30.0), "r_diff_ohm": lambda s: 0.026,
       "i0_a": lambda s: 17.5}


def law(key, t_c, soc=SOC):
    x = 1.0 / (np.asarray(t_c, dtype=float) + KELVIN) - 1.0 / (T_REF + KELVIN)
    return REF[key](soc) * np.exp(EA[key] * x)


def ocv_at(t_c):
    return OcvTable(SOC, 3.0 + 1.2 * SOC + 0.0002 * t_c * SOC)


def one_temperature_model(t_c, branches=True, soc=SOC, ocv=None):
    def table():
        cols = {k: law(k, t_c, soc) for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm",
                                                 "tau_fast_s", "tau_slow_s")}
        extra = dict(r_diff_ohm=[float(law("r_diff_ohm", t_c))], tau_diff_s=[500.0],
                     i0_a=[float(law("i0_a", t_c))]) if branches else {}
        return RcTable(soc=soc, fit_error=np.zeros(soc.size), converged=np.ones(soc.size, bool),
                       **cols, **extra)

    return EcmModel(capacity_ah=2.9, ocv=ocv or ocv_at(t_c), charge=table(),
                    discharge=table(), method="curve", seed=0, notes=(f"fit at {t_c}",))


TEMPS = (25.8, 0.6, -9.9, -19.9)


@pytest.fixture(scope="module")
def assembled():
    return assemble_over_temperature([one_temperature_model(t) for t in TEMPS], TEMPS,
                                     labels=[f"t{t}" for t in TEMPS])


def test_grid_rows_are_the_arrhenius_law(assembled):
    table = assembled.discharge
    assert np.array_equal(table.temperature_c, np.arange(-20.0, 46.0, 5.0))
    assert np.array_equal(table.temperature_c, temperature_grid(-19.9, 45.0, 5.0))
    for k, t in enumerate(table.temperature_c):
        if not -19.9 <= t <= 25.8:
            continue
        for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm", "tau_fast_s", "tau_slow_s"):
            np.testing.assert_allclose(getattr(table, key)[k], law(key, t), rtol=1e-12)
        for key in ("r_diff_ohm", "i0_a"):
            np.testing.assert_allclose(getattr(table, key)[k], law(key, t), rtol=1e-12)
        assert table.tau_diff_s[k] == pytest.approx(500.0, rel=1e-14)


def test_between_grid_rows_the_law_is_followed_closely(assembled):
    for t in (-17.3, -4.2, 3.3, 12.9, 21.1):
        p = assembled.discharge.at(SOC, t)
        for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm", "tau_fast_s", "tau_slow_s",
                    "r_diff_ohm", "i0_a"):
            # linear between 5 K rows of exp(Ea/R / T): the steepest here (r_fast, 6000 K
            # at -17 degC, x1.6 per row) is 2.3 % off mid-row
            np.testing.assert_allclose(p[key], law(key, t), rtol=2.5e-2)


def test_the_derived_warm_row_extrapolates_one_activation_energy(assembled):
    table = assembled.discharge
    assert table.temperature_c[-1] == 45.0
    # one Ea per parameter, SOC-independent in the truth: the extrapolation is exact
    for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm", "r_diff_ohm", "i0_a"):
        np.testing.assert_allclose(np.atleast_1d(getattr(table, key)[-1]), law(key, 45.0),
                                   rtol=1e-9)
    # time constants stay those of the warmest test
    np.testing.assert_allclose(table.tau_fast_s[-1], law("tau_fast_s", 25.8), rtol=1e-12)
    np.testing.assert_allclose(table.tau_slow_s[-1], law("tau_slow_s", 25.8), rtol=1e-12)
    note = next(n for n in assembled.notes if n.startswith("derived warm row at 45 degC"))
    assert "r_fast_ohm 6000 K" in note and "i0_a 5200 K" in note


def test_clamped_outside_the_table(assembled):
    t = assembled.discharge
    cold = t.at(SOC, -40.0)
    warm = t.at(SOC, 80.0)
    for key in ("r0_ohm", "tau_slow_s"):
        np.testing.assert_array_equal(cold[key], getattr(t, key)[0])
        np.testing.assert_array_equal(warm[key], getattr(t, key)[-1])
    # the -20 degC grid row is the coldest measured row (-19.9), clamped
    np.testing.assert_allclose(t.r0_ohm[0], law("r0_ohm", -19.9), rtol=1e-12)


def test_ocv_one_row_per_test_linear_in_temperature(assembled):
    ocv = assembled.ocv
    assert np.array_equal(ocv.temperature_c, sorted(TEMPS))
    np.testing.assert_allclose(ocv.ocv_at(0.5, 10.0), 3.6 + 0.0001 * 10.0, rtol=1e-12)
    np.testing.assert_allclose(ocv.ocv_at(0.5, 60.0), 3.6 + 0.0001 * 25.8, rtol=1e-12)


def test_notes_name_the_measured_breakpoints_and_the_grid(assembled):
    notes = "\n".join(assembled.notes)
    assert "temperature breakpoints measured: -19.9 degC (t-19.9), -9.9 degC (t-9.9), " \
           "0.6 degC (t0.6), 25.8 degC (t25.8)" in notes
    assert "uniform 5 K grid -20..45 degC (14 rows)" in notes
    assert "[0.6 degC] fit at 0.6" in notes


def test_deterministic_and_independent_of_the_order():
    models = [one_temperature_model(t) for t in TEMPS]
    a = assemble_over_temperature(models, TEMPS, labels=list("abcd"))
    order = [2, 0, 3, 1]
    b = assemble_over_temperature([models[k] for k in order], [TEMPS[k] for k in order],
                                  labels=["abcd"[k] for k in order])
    assert a.to_json() == b.to_json()
    again = model_from_json_dict(__import__("json").loads(a.to_json()))
    assert again.to_json() == a.to_json()


def test_measured_breakpoints_kept_with_step_zero_and_no_warm_row():
    m = assemble_over_temperature([one_temperature_model(t) for t in TEMPS], TEMPS,
                                  step_c=0.0, warm_c=None)
    assert np.array_equal(m.discharge.temperature_c, sorted(TEMPS))
    np.testing.assert_allclose(m.discharge.r0_ohm[-1], law("r0_ohm", 25.8), rtol=1e-12)
    assert not any("derived warm row" in n for n in m.notes)
    # without a warm row the grid ends at the multiple of 5 above the warmest test, clamped
    g = assemble_over_temperature([one_temperature_model(t) for t in TEMPS], TEMPS,
                                  warm_c=None).discharge
    assert g.temperature_c[-1] == 30.0
    np.testing.assert_allclose(g.r0_ohm[-1], law("r0_ohm", 25.8), rtol=1e-12)


def test_one_model_keeps_its_row_and_gets_its_temperature():
    m = one_temperature_model(20.0)
    one = assemble_over_temperature([m], [20.0])
    assert one.discharge.n_temperatures == 1 and one.discharge.temperature_c[0] == 20.0
    assert one.ocv.temperature_c[0] == 20.0 and not one.needs_temperature
    np.testing.assert_array_equal(one.discharge.r0_ohm, m.discharge.r0_ohm)


def test_tests_on_different_soc_levels_and_activation_energy_never_negative():
    # the cold test was fitted on fewer SOC levels (a few close to the warm ones): the
    # common SOC grid merges levels closer than 0.01, and the nodes outside a table's span
    # (held flat there) do not count for the warm row's activation energy
    cold_soc = np.array([0.303, 0.498, 0.7, 0.904, 1.0])
    warm = one_temperature_model(25.0, branches=False)
    cold = one_temperature_model(0.0, branches=False, soc=cold_soc)
    m = assemble_over_temperature([warm, cold], [25.0, 0.0])
    merged = SOC.copy()
    merged[[3, 5, 9]] = (SOC[[3, 5, 9]] + cold_soc[[0, 1, 3]]) / 2
    np.testing.assert_allclose(m.discharge.soc, merged, rtol=0, atol=1e-15)
    r0_45 = m.discharge.at(merged, 45.0)["r0_ohm"]
    # the grid rows are each table interpolated onto the merged SOC levels; Ea/R from the
    # nodes 0.3..1 (both tables cover them) is close to the truth (1800 K)
    assert r0_45 == pytest.approx(law("r0_ohm", 45.0, merged), rel=3e-3)
    note = next(n for n in m.notes if "derived warm row" in n)
    assert "r0_ohm 1800 K" in note or "r0_ohm 1799 K" in note or "r0_ohm 1801 K" in note
    # a resistance that RISES with temperature gives Ea/R = 0: the warm row is the warmest
    flip = assemble_over_temperature([cold, warm], [25.0, 0.0])
    np.testing.assert_allclose(flip.discharge.r_fast_ohm[-1], law("r_fast_ohm", 0.0),
                               rtol=1e-12)


def test_shared_ocv_gives_one_row_and_bad_inputs_are_refused():
    ocv = ocv_at(25.0)
    ms = [one_temperature_model(t, ocv=ocv) for t in (25.0, 0.0)]
    assert assemble_over_temperature(ms, [25.0, 0.0]).ocv.n_temperatures == 1
    with pytest.raises(ValueError, match="both at about 25.0 degC"):
        assemble_over_temperature(ms, [25.0, 25.3], labels=["x", "y"])
    with pytest.raises(ValueError, match="one temperature per model"):
        assemble_over_temperature(ms, [25.0])
    from dataclasses import replace

    with pytest.raises(ValueError, match="method or capacity"):
        assemble_over_temperature([ms[0], replace(ms[1], method="ga")], [25.0, 0.0])


def test_arrhenius_interp_falls_back_to_linear_for_zero():
    rows = np.array([[0.0, 2.0], [1.0, 4.0]])
    mid = arrhenius_interp(np.array([0.0, 20.0]), rows, 10.0)
    x0, x1, x = 1 / KELVIN, 1 / (20 + KELVIN), 1 / (10 + KELVIN)
    w = (x - x0) / (x1 - x0)
    assert mid[0] == pytest.approx(w)
    assert mid[1] == pytest.approx(2.0 ** (1 - w) * 4.0 ** w)


def test_a_test_without_a_branch_gets_it_filled_in():
    """A test whose fit found no current dependence (no i0) or no diffusion pair joins the
    others: i0 from their Arrhenius line, r_diff = 0 with the nearest tau_diff."""
    from dataclasses import replace

    models = [one_temperature_model(t) for t in TEMPS]

    def strip(m, **kw):
        return replace(m, charge=replace(m.charge, **kw), discharge=replace(m.discharge, **kw))

    models[0] = strip(models[0], i0_a=None)                       # 25.8 degC: no i0
    models[2] = strip(models[2], r_diff_ohm=None, tau_diff_s=None)  # -9.9 degC: no diffusion
    m = assemble_over_temperature(models, TEMPS, step_c=0.0, warm_c=None)
    t = m.discharge
    np.testing.assert_allclose(t.i0_a[-1], law("i0_a", 25.8), rtol=1e-9)   # Arrhenius truth
    k = list(t.temperature_c).index(-9.9)
    assert t.r_diff_ohm[k] == 0.0 and t.tau_diff_s[k] == 500.0
    notes = "\n".join(m.notes)
    assert "i0_a at 25.8 degC" in notes and "r_diff_ohm = 0 there" in notes


def test_an_ocv_row_beyond_its_rests_takes_the_nearest_row_that_measured_there():
    """Rows measured over SOC 0.25-1 (-20 degC), 0.15-1 (0 degC) and 0.05-1 (25 degC),
    each an entropic offset from one shape: below its own span a row follows the nearest
    row that measured there, shifted to meet it, then the next; beyond every span, flat."""
    from ecmgen.model.model import OcvOverTemperature
    from ecmgen.model.temperature import fill_ocv_rows

    soc = np.round(np.linspace(0.0, 1.0, 101), 9)
    shape = 3.0 + 1.2 * soc - 0.3 * np.exp(-soc / 0.05)
    temps = np.array([-20.0, 0.0, 25.0])
    spans = [(0.25, 1.0), (0.15, 1.0), (0.05, 1.0)]
    rows = np.vstack([shape + d for d in (-0.02, -0.01, 0.0)])
    for row, (lo, _) in zip(rows, spans):          # held flat below the span, as measured
        row[soc < lo] = row[np.searchsorted(soc, lo)]
    got, notes = fill_ocv_rows(OcvOverTemperature(temps, soc, rows), spans)
    cold = got.ocv_v[0]
    inside = soc >= 0.05
    assert np.allclose(cold[inside], shape[inside] - 0.02, atol=1e-12)
    assert np.all(cold[soc < 0.05] == cold[np.searchsorted(soc, 0.05)])
    assert np.allclose(got.ocv_v[2], rows[2])        # the warm row measured all it has
    assert len(notes) == 2 and "from the 0.0 degC row" in notes[0] \
        and "from the 25.0 degC row" in notes[0]
