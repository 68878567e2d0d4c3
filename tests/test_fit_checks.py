"""Honest fits: time constants longer than the data or on a search bound are
flagged for every method, levels left out are named, RC tables used beyond their
measured SOC span are noted, and the progress line tells the relaxation really used."""

import numpy as np
import pytest

from conftest import make_pulse_test, synthetic_nca_model
from ecmgen.data.dcir import extract_dcir, find_pulses, relaxation_s
from ecmgen.data.measure import TimeSeries, write_timeseries_csv
from ecmgen.fit.checks import curve_fit_flags, flag_notes, point_fit_flags
from ecmgen.fit.curve import CurveOptions, fit_pulse_curves


def _short_rest_test():
    """40 s rests after 10 s pulses on a cell whose slow pole is 200 s (A123-like)."""
    truth = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=200.0)
    series, soc0 = make_pulse_test(truth, soc_levels=(0.8, 0.5), c_rates=(2.0,),
                                   rest_s=40.0, noise_v=0.0003)
    return truth, series, soc0


def test_curve_tau_longer_than_the_relaxation_is_flagged():
    """Before: a slow time constant fitted on 40 s of rest went unremarked."""
    truth, series, soc0 = _short_rest_test()
    pulses = find_pulses(series, 2.9, soc0=soc0)
    relax = relaxation_s(series, pulses, 1800.0)
    assert np.all(relax <= 40.0)                  # not the 1800 s asked for
    fit = fit_pulse_curves(series, pulses, truth.ocv, 2.9,
                           CurveOptions(relax_s=1800.0, diffusion=False))
    flags = curve_fit_flags(fit, float(relax.max()))
    if fit.tau_slow_s > 40.0:
        assert any(f.kind == "tau_beyond_data" and f.param == "tau_slow_s" for f in flags)
        assert any("curve: tau_slow longer than the data" in n for n in flag_notes(flags))
    else:                                         # or it sits on its bound, and says so
        assert any("tau_slow" in n and "search bound" in n for n in fit.notes)


def test_ga_and_lm_tau_on_the_search_bound_is_flagged():
    """Five DC-IR points within 10 s of a 300 s pole: the slow time constant runs to the
    box's 5 x 10 s = 50 s limit. Before, nothing said so."""
    from ecmgen.fit.ga import fit_ga
    from ecmgen.fit.lm import fit_lm

    truth = synthetic_nca_model(tau_fast_s=1.0, tau_slow_s=300.0)
    series, soc0 = make_pulse_test(truth, soc_levels=(0.7,), c_rates=(2.0,))
    table = extract_dcir(series, find_pulses(series, 2.9, soc0=soc0))
    for name, fit in (("ga", fit_ga(table.t_s, table.r_ohm, seed=0)),
                      ("lm", fit_lm(table.t_s, table.r_ohm))):
        flags = point_fit_flags(name, fit, table)
        kinds = {(f.kind, f.param) for f in flags}
        assert ("tau_on_bound", "tau_slow_s") in kinds, (name, flags)
        assert ("tau_beyond_data", "tau_slow_s") in kinds
        notes = flag_notes(flags)
        assert any(n.startswith(f"{name}: tau_slow on its search bound (50 s)") for n in notes)


def test_rc_tables_held_flat_far_outside_their_span_are_noted():
    from ecmgen.model.simulate import simulate, validate
    from ecmgen.model.spans import model_span_notes, usage, usage_notes

    m = synthetic_nca_model()
    from dataclasses import replace

    def narrow(t):
        keep = (t.soc >= 0.09) & (t.soc <= 0.25)
        cols = {k: getattr(t, k)[:, keep] for k in ("r0_ohm", "r_fast_ohm", "tau_fast_s",
                                                    "r_slow_ohm", "tau_slow_s", "fit_error",
                                                    "converged")}
        return replace(t, soc=t.soc[keep], **cols)

    a123 = replace(m, charge=narrow(m.charge), discharge=narrow(m.discharge))
    notes = model_span_notes(a123)
    assert any("discharge RC table is measured at SOC 0.10..0.20 only" in n for n in notes)
    t = np.arange(0.0, 3000.0)
    i = np.full(t.size, -2.0)
    v = simulate(m, t, i, 0.95).voltage_v
    val = validate(a123, TimeSeries(t, i, v, source="dst.csv"), soc0=0.95)
    use = usage(a123, val, ocv_span=(0.0, 1.0))
    assert use["beyond_span"]["discharge"] == pytest.approx(1.0)
    assert use["beyond_span"]["ocv"] == 0.0
    text = usage_notes(a123, "dst.csv", use, (0.0, 1.0))[0]
    assert "the discharge RC table (measured at SOC 0.10..0.20) on 100% of the samples" in text


def test_progress_line_tells_the_relaxation_used(tmp_path):
    """Before: "with 1800 s of relaxation each" when the rests were 40 s long."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import fit_models, prepare

    truth, series, _ = _short_rest_test()
    write_timeseries_csv(series, tmp_path / "p.csv")
    np.savetxt(tmp_path / "ocv.csv", np.column_stack([truth.ocv.soc, truth.ocv.ocv_v[0]]),
               delimiter=",", header="soc,ocv_v", comments="")
    (tmp_path / "c.toml").write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "p.csv"\n'
                                     'pulses_soc0 = 1.0\nocv = "ocv.csv"\n'
                                     '[fit]\nmethods = ["curve"]\n')
    cfg = load_config(tmp_path / "c.toml")
    lines = []
    models, _ = fit_models(cfg, prepare(cfg), lines.append)
    line = next(x for x in lines if x.startswith("whole-test fit"))
    assert "1800 s of relaxation" not in line.split("(")[0]
    assert "40 s of relaxation each" in line, line
    assert "fit.relax_s = 1800 s" in line


def test_spans_are_judged_at_the_cycle_temperature_row():
    """A model over temperature whose -20 degC row's OCV was measured down to SOC 0.25 only
    (0.05 at 25 degC), on a -20 degC cycle down to SOC 0.10. Before: the union of the spans
    (0.05..1) -- no warning; now the -20 degC row's span, the share beyond it, a warning
    naming each row's span."""
    from ecmgen.model.simulate import simulate, validate
    from ecmgen.model.spans import usage, usage_notes

    m = synthetic_nca_model()
    t = np.arange(0.0, 3000.0)
    i = np.full(t.size, -3.0)                  # 0.95 -> 0.09
    v = simulate(m, t, i, 0.95).voltage_v
    val = validate(m, TimeSeries(t, i, v, np.full(t.size, -20.0), source="cold.csv"),
                   soc0=0.95)
    full = {"charge": [0.0, 1.0], "discharge": [0.0, 1.0]}
    rows = [(25.0, dict(full, ocv=[0.05, 1.0])), (-20.0, dict(full, ocv=[0.25, 1.0]))]
    union = usage(m, val, ocv_span=(0.05, 1.0))
    assert union["beyond_span"]["ocv"] < 0.01
    use = usage(m, val, ocv_span=(0.05, 1.0), rows=rows)
    share = float(np.mean(np.clip(val.sim.soc, 0, 1) < 0.25 - 0.02))
    assert use["beyond_span"]["ocv"] == pytest.approx(share) and share > 0.1
    text = usage_notes(m, "cold.csv", use, (0.05, 1.0))[0]
    assert "the OCV (measured at SOC 0.25..1.00 at -20 degC, 0.05..1.00 at 25 degC)" in text
    assert "(warning)" in text
