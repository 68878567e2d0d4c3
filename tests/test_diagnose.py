"""diagnose: the casadi model vs the simulator, the statistics, and its mechanics on small
synthetic runs.

The cells here are made by ecmgen's own equations (ecmgen.diagnosis.synthcell), the ones
diagnose fits: fine for where the parts come from, what is written and what is refused,
not for whether diagnose names the right effect. That is scored on cells of the
independent generator (bench/diagnose_cells.py): test_diagnose_synthetic.py for the
effects it has a candidate for, test_diagnose_unknown_effects.py for those it has not."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ecmgen.model import effects as fx
from ecmgen.diagnosis.output import write_diagnose_outputs
from ecmgen.diagnosis.problems import _Problem, _specs
from ecmgen.diagnosis.search import (DiagnoseResult, _context, block_bootstrap_low, decimate,
                                     diagnose, noise_std)
from ecmgen.data.measure import TimeSeries
from ecmgen.model import load_model
from ecmgen.model.simulate import simulate
from ecmgen.diagnosis.synthcell import random_cell


def _cycle(seed=3, n=2500):
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.where(rng.uniform(size=n) < 0.2, 0.5, 1.0))
    t -= t[0]
    i = np.repeat(rng.normal(-1.0, 3.0, n // 25), 25)[:n]
    i[600:800] = 0.0
    i[1200:1500] = 1.5
    temp = 25.0 + 5.0 * t / t[-1]
    return t, i, temp


def _check_jacobian(prob, z, jac):
    """The casadi Jacobian against central differences, column by column."""
    for col in range(z.size):
        h = 1e-6 * max(1.0, abs(z[col]))
        zp, zm = z.copy(), z.copy()
        zp[col] += h
        zm[col] -= h
        fd = (prob.simulate(zp)[0] - prob.simulate(zm)[0]) / (2 * h)
        scale = max(np.max(np.abs(fd)), 1e-9)
        assert np.max(np.abs(fd - jac[:, col])) < 1e-4 * scale + 1e-9, prob.free[col][1]


def test_casadi_model_equals_the_simulator_and_its_jacobian(synthetic_model):
    """The fit's casadi model (forward sensitivities) is the simulator, exactly."""
    t, i, temp = _cycle()
    effects = [
        fx.ExtraRc(r_ohm=0.01, tau_s=500.0),
        fx.Hysteresis(m_v=0.02, decay_ah=0.1, m0_v=0.003, ocv_table_state=0.2,
                      initial_state=0.4),
        fx.CurrentDependentResistance(scale_at_zero=1.2, i0_a=2.5),
        fx.CapacityError(capacity_scale=0.95),
        fx.TemperatureDependence(activation_k=3000.0, t_ref_c=25.0),
    ]
    series = TimeSeries(t, i, np.zeros_like(t), temp, None, "x")
    ctx = {"r_total_ohm": 0.04, "tau_min_s": 60.0, "tau_max_s": 5000.0}
    layout = []
    for e in effects:
        specs = _specs(e.name, synthetic_model, ctx)
        layout.append((e.name, e.params(), specs))
    prob = _Problem(synthetic_model, series, 0.8, layout)
    z = prob.z0()
    v, jac = prob.simulate(z)
    ref = simulate(synthetic_model.with_effects(effects), t, i, 0.8, temp).voltage_v
    assert np.max(np.abs(v - ref)) < 1e-10
    assert jac.shape == (t.size, len(prob.free))
    _check_jacobian(prob, z, jac)


def _over_temperature(model):
    """The synthetic model at 25 and 0 degC (x2.2 resistances), with a diffusion pair and a
    Butler-Volmer fast branch, joined over temperature."""
    from dataclasses import replace

    from ecmgen.model.temperature import assemble_over_temperature

    def at(scale, i0, r_diff):
        def t(tab):
            return replace(tab, r0_ohm=tab.r0_ohm * scale, r_fast_ohm=tab.r_fast_ohm * scale,
                           r_slow_ohm=tab.r_slow_ohm * scale, r_diff_ohm=[r_diff],
                           tau_diff_s=[700.0], i0_a=[i0])
        return replace(model, charge=t(model.charge), discharge=t(model.discharge))

    return assemble_over_temperature([at(1.0, 6.0, 0.02), at(2.2, 1.5, 0.05)], [25.0, 0.0])


def test_casadi_model_equals_the_simulator_over_temperature_with_branches(synthetic_model):
    """A base model over temperature with the diffusion pair and Butler-Volmer: the casadi
    model reads the tables at the cell temperature and has both branches, exactly."""
    t, i, temp = _cycle()
    temp = 2.0 + 20.0 * t / t[-1]
    base = _over_temperature(synthetic_model)
    assert base.needs_temperature and base.discharge.has_diffusion
    effects = [fx.ExtraRc(r_ohm=0.01, tau_s=500.0),
               fx.CurrentDependentResistance(scale_at_zero=1.2, i0_a=2.5),
               fx.CapacityError(capacity_scale=0.95)]
    series = TimeSeries(t, i, np.zeros_like(t), temp, None, "x")
    ctx = {"r_total_ohm": 0.04, "tau_min_s": 60.0, "tau_max_s": 5000.0}
    layout = [(e.name, e.params(), _specs(e.name, base, ctx)) for e in effects]
    prob = _Problem(base, series, 0.8, layout)
    z = prob.z0()
    v, jac = prob.simulate(z)
    ref = simulate(base.with_effects(effects), t, i, 0.8, temp)
    assert np.max(np.abs(ref.u_diff_v)) > 1e-3        # the branches matter here
    assert np.max(np.abs(v - ref.voltage_v)) < 1e-10
    _check_jacobian(prob, z, jac)
    # without the cell temperature a model over temperature cannot be diagnosed
    from ecmgen.errors import InputError

    with pytest.raises(InputError, match="no cell temperature column"):
        _Problem(base, TimeSeries(t, i, np.zeros_like(t), None, None, "x"), 0.8, layout)


def test_block_bootstrap_separates_a_real_gain_from_noise():
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 1e-3, 5000)
    assert block_bootstrap_low(noise, 100, 0.99) < 0
    assert block_bootstrap_low(noise + 5e-4, 100, 0.99) > 0


def test_decimate_keeps_the_charge():
    t, i, temp = _cycle(n=2000)
    s = TimeSeries(t, i, 3.7 + 0.01 * i, temp, None, "x")
    d = decimate(s, 4)
    assert len(d) == 500
    dt = np.diff(t, prepend=t[0])
    ddt = np.diff(d.time_s, prepend=0.0)
    ddt[0] = t[3] - t[0]
    assert np.sum(d.current_a * ddt) == pytest.approx(np.sum(i * dt), rel=1e-12)
    assert d.time_s[-1] == t[-1]


def test_noise_estimate():
    rng = np.random.default_rng(1)
    t = np.arange(4000.0)
    i = np.where((t // 500) % 2 == 0, 0.0, -2.0)
    v = 3.7 + rng.normal(0, 1e-3, t.size)
    s = TimeSeries(t, i, v, None, None, "x")
    # the injected 1 mV within four standard errors of a MAD estimate of a std from the
    # rested sample-to-sample changes (1.1664 sigma / sqrt(n) for normal data)
    n = int(np.sum((i[1:] == 0) & (i[:-1] == 0)))
    assert noise_std(s, 0.03) == pytest.approx(1e-3, rel=4 * 1.1664 / np.sqrt(n))
    # quantised to 2 mV: the MAD of the steps is 0, the estimate must not be; it is the
    # injected noise give or take the rounding's own noise (one LSB / sqrt(12))
    lsb = 0.002
    q = TimeSeries(t, i, np.round(v / lsb) * lsb, None, None, "x")
    assert abs(noise_std(q, 0.03) - 1e-3) < lsb / np.sqrt(12)


@pytest.fixture(scope="module")
def extra_rc_run():
    cell = random_cell(21, "extra_rc")
    return cell, diagnose(cell.base_model(), cell.drive_cycle(), candidates=("extra_rc",))


def test_a_slow_rc_of_its_own_equations_is_recovered_and_judged_as_simulated(extra_rc_run):
    """Mechanics: the fit, given the extra RC as the only candidate on a cell made by the
    equations it fits (so the truth is one it can represent), finds its time constant, and
    the held-out MAE it reports is what simulating the augmented model gives."""
    cell, r = extra_rc_run
    assert isinstance(r, DiagnoseResult)
    assert r.effects == ("extra_rc",)
    st = r.steps[0]
    assert st.mae_before_v == r.mae_before_v and st.mae_after_v < st.mae_before_v
    assert st.ci_low_v > 0
    hidden = cell.hidden.effects[0]
    found = r.model.effects[0]
    # the time constant within the resolution the search starts from: nearer the hidden
    # one than half a step of the signature's log grid (six nodes over its tau range)
    ctx = _context(cell.base_model(), r.fit_series, r.fit_stop)
    half_step = np.log(ctx["tau_max_s"] / ctx["tau_min_s"]) / 5 / 2
    assert abs(np.log(found.tau_s / hidden.tau_s)) < half_step, (found.tau_s, hidden.tau_s)
    # the held-out MAE is what validate-style simulation of the augmented model gives
    j = r.judge_series
    sim = simulate(r.model, j.time_s, j.current_a, r.judge_soc0, j.temperature_c)
    e = sim.voltage_v[r.judge_start:] - j.voltage_v[r.judge_start:]
    assert np.mean(np.abs(e)) == pytest.approx(r.mae_after_v, rel=1e-9)


def test_outputs(extra_rc_run, tmp_path):
    """Mechanics: what is written for a result with an effect added (any cell will do)."""
    _, r = extra_rc_run
    files = write_diagnose_outputs(r, tmp_path / "out")
    names = {f.name for f in files}
    assert {"model.json", "report.md", "diagnose.json", "diagnose-signatures.png",
            "diagnose-comparison.png"} <= names
    m = load_model(tmp_path / "out" / "model.json")
    assert [e.name for e in m.effects] == list(r.effects)
    d = json.loads((tmp_path / "out" / "diagnose.json").read_text())
    assert d["effects"][0]["name"] == "extra_rc"
    assert {"name", "mae_before_v", "mae_after_v"} <= set(d["effects"][0])
    assert d["mae_after_v"] < d["mae_before_v"]
    assert d["model"].endswith("model.json")
    text = (tmp_path / "out" / "report.md").read_text()
    assert "extra_rc" in text and "Held-out MAE" in text
    for png in ("diagnose-signatures.png", "diagnose-comparison.png"):
        assert (tmp_path / "out" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    json.dumps(r.to_json_dict("m.json"), allow_nan=False)


def test_second_cycle_as_judge_and_given_soc():
    """Mechanics: with a second cycle as the judge, the whole first cycle is fitted and the
    whole second judged, from the SOCs given (where the parts come from, not what is named:
    a cell of diagnose's own equations will do)."""
    cell = random_cell(8, "hysteresis")
    base = cell.base_model()
    fit = cell.drive_cycle(seed=1)
    judge = cell.drive_cycle(seed=2, soc_start=0.9)
    r = diagnose(base, fit, judge, soc0=0.95, judge_soc0=0.9)
    assert r.judge_start == 0 and r.fit_stop == len(fit)
    assert len(r.judge_series) == len(judge)
    assert r.soc0 == 0.95 and r.judge_soc0 == 0.9
    assert "all of" in r.split


def test_a_judge_that_never_rises_above_10_percent_soc_is_refused():
    """Below 10 % SOC the error measures where the cell ends, not a missing effect: a
    held-out part that never rises above it is refused, not judged. (Mechanics: a cell of
    diagnose's own equations will do.)"""
    from ecmgen.diagnosis.search import NothingToJudge

    cell = random_cell(8, "hysteresis")
    fit = cell.drive_cycle(seed=1)
    judge = cell.drive_cycle(seed=2, soc_start=0.9)
    with pytest.raises(NothingToJudge, match="above 10 % SOC in only 0 of"):
        diagnose(cell.base_model(), fit, judge, soc0=0.95, judge_soc0=0.08)


def test_a_fit_on_a_magnitude_bound_does_not_pass():
    """A hysteresis of 0.3 V (its search bound) or a capacity 0.7x is no explanation.
    (Mechanics: the cell only gives the bounds a base; any model will do.)"""
    from ecmgen.diagnosis.search import _on_bound

    model = random_cell(8, "hysteresis").base_model()
    h = _specs("hysteresis", model, {})
    assert _on_bound({"m_v": 0.2999, "ocv_table_state": 1.0, "initial_state": -1.0}, h)
    assert not _on_bound({"m_v": 0.0, "ocv_table_state": 1.0, "initial_state": -1.0}, h)
    c = _specs("capacity_error", model, {})
    assert _on_bound({"capacity_scale": 0.7}, c) and _on_bound({"capacity_scale": 1.4}, c)
    assert not _on_bound({"capacity_scale": 0.95}, c)


def test_candidates_can_be_restricted_and_bad_names_fail(synthetic_model):
    """Mechanics: only the candidates asked for are tried or named (what is named among
    them is scored on the independent generator's cells)."""
    cell = random_cell(9, "capacity_error")
    base = cell.base_model()
    cyc = cell.drive_cycle()
    r = diagnose(base, cyc, candidates=("extra_rc", "capacity_error"))
    assert {c.name for c in r.candidates} <= {"extra_rc", "capacity_error"}
    assert set(r.effects) <= {"extra_rc", "capacity_error"}
    with pytest.raises(ValueError, match="unknown effect"):
        diagnose(base, cyc, candidates=("bogus",))


def test_config_section_options():
    from ecmgen.diagnosis.search import diagnose_options
    from ecmgen.errors import InputError

    assert diagnose_options(None) == {"judge": None, "cycle": None, "base": None}
    o = diagnose_options({"judge": "hwfet-a.mat", "split": 0.5, "effects": ["extra_rc"],
                          "max_effects": 2, "confidence": 0.95, "judge_soc0": 1.0,
                          "min_rel_gain": 0.1, "cycle": "us06.mat", "cycle_soc0": 0.9,
                          "base": "out/model.json"}, "c.toml")
    assert o == {"judge": "hwfet-a.mat", "split": 0.5, "candidates": ("extra_rc",),
                 "max_effects": 2, "confidence": 0.95, "judge_soc0": 1.0, "min_rel_gain": 0.1,
                 "cycle": "us06.mat", "soc0": 0.9, "base": "out/model.json"}
    for bad, words in (({"splitt": 0.5}, "unknown key"), ({"split": 2.0}, "diagnose.split"),
                       ({"effects": ["x"]}, "diagnose.effects"),
                       ({"max_effects": 1.5}, "integer"), ({"judge": 3}, "file name"),
                       ({"cycle": ""}, "file name"), ({"base": 1}, "file name"),
                       ({"cycle_soc0": 2}, "cycle_soc0")):
        with pytest.raises(InputError, match=words) as err:
            diagnose_options(bad, "c.toml")
        assert str(err.value).startswith("c.toml: ")
