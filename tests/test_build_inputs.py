"""The build's inputs on cells it was not shaped around: OCV sources combined
and cross-checked, a flat OCV refused, a flat-OCV LFP cell with hysteresis built and
diagnosed without a start SOC, and what --json tells about them."""

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import PANASONIC, make_pulse_test, need, synthetic_nca_model
from ecmgen.cli import main
from ecmgen.data.measure import TimeSeries, write_timeseries_csv


def _low_rate(model, q=None, i_a=0.145, dt=60.0, drop_v=0.01):
    """C/20 discharge from full, 1 h rest, C/20 charge (branches +-drop_v about the OCV)."""
    q = model.capacity_ah if q is None else q
    n = int(round(q * 3600 / i_a / dt))
    s = np.concatenate([np.ones(5), 1 - np.arange(1, n + 1) / n, np.zeros(60),
                        np.arange(1, n + 1) / n, np.ones(60)])
    i = np.concatenate([np.zeros(5), np.full(n, -i_a), np.zeros(60), np.full(n, i_a),
                        np.zeros(60)])
    v = model.ocv.ocv_at(s) + np.sign(i) * drop_v
    return TimeSeries(dt * np.arange(s.size), i, v, source="c20.csv")


def _three_files(folder: Path, cycle_s: float, cycle_soc0: float):
    """pulses.csv (SOC 0.9, 0.6, 0.3), c20.csv and cycle.csv (a minute of rest, then 1C
    for the rest of ``cycle_s`` from ``cycle_soc0``) from a synthetic cell; its model."""
    from ecmgen.model.simulate import simulate

    truth = synthetic_nca_model()
    series, _ = make_pulse_test(truth, soc_levels=(0.9, 0.6, 0.3), c_rates=(1.0, 3.0),
                                rest_s=600.0)
    write_timeseries_csv(series, folder / "pulses.csv")
    write_timeseries_csv(_low_rate(truth), folder / "c20.csv")
    t = np.arange(0.0, cycle_s)
    i = np.where(t < 60, 0.0, -2.9)
    write_timeseries_csv(TimeSeries(t, i, simulate(truth, t, i, cycle_soc0).voltage_v),
                         folder / "cycle.csv")
    return truth


def test_lfp_cell_with_hysteresis_builds_and_diagnoses_without_pulses_soc0(tmp_path):
    """Its pulse test starts on the LFP plateau on the discharge branch: the old start
    SOC (the first rest through the OCV) was 0.26 low and the build stopped with an
    SOC-range error. (Mechanics: that build and diagnose run and what they write, not what
    is named, so a cell of ecmgen's own equations will do.)"""
    from ecmgen.diagnosis.synthcell import random_cell

    cell = random_cell(1, "hysteresis", chemistry="lfp", effect_options={"initial_state": -1.0})
    pulses = cell.pulse_test(levels=(0.45, 0.3, 0.15, 0.05), c_rates_discharge=(1.0, 2.0),
                             c_rates_charge=(1.0,), soc_start=0.55)
    write_timeseries_csv(pulses, tmp_path / "pulses.csv")
    write_timeseries_csv(cell.ocv_test(), tmp_path / "ocv.csv")
    write_timeseries_csv(cell.drive_cycle(soc_start=0.9, soc_end=0.3), tmp_path / "cycle.csv")
    cfg = tmp_path / "cell.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = {cell.capacity_ah}\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "ocv.csv"\ncycle = "cycle.csv"\n[fit]\nmethods = ["ga"]\n'
                   '[c]\nnumeric = []\n')
    out = tmp_path / "out"
    assert main(["build", str(cfg), "--out", str(out), "--quiet", "--no-plots", "--json"]) == 0
    doc = json.loads((out / "model.json").read_text())
    assert any("pulse test start SOC 0.55" in n for n in doc["notes"])
    assert main(["diagnose", str(cfg), "--out", str(tmp_path / "diag"), "--quiet",
                 "--no-plots"]) == 0
    assert (tmp_path / "diag" / "model.json").exists()
    # [diagnose] base: it starts from the model the build wrote, as it is (not the plain
    # 2RC it fits itself), and never writes over it
    cfg.write_text(cfg.read_text() + '[diagnose]\nbase = "out/model.json"\n')
    assert main(["diagnose", str(cfg), "--out", str(tmp_path / "given"), "--quiet",
                 "--no-plots"]) == 0
    base = json.loads((tmp_path / "given" / "model-base.json").read_text())
    assert base == doc == json.loads((out / "model.json").read_text())
    cfg.write_text(cfg.read_text().replace("out/model.json", "none.json"))
    assert main(["diagnose", str(cfg), "--out", str(tmp_path / "none"), "--quiet"]) == 2
    assert not (tmp_path / "none").exists()


@pytest.fixture(scope="module")
def panasonic_c20_inputs():
    from ecmgen.config import load_config
    from ecmgen.pipeline import prepare

    data = need(PANASONIC)
    path = Path(__file__).parent / "_pan_c20.toml"
    return data, path, load_config, prepare


def test_panasonic_c20_disagrees_with_the_pulse_rests_and_says_so(tmp_path, panasonic_c20_inputs):
    """Before: no normalisation and no word that the C/20 OCV sits 20-80 mV off the pulse
    test's rested voltages."""
    data, _, load_config, prepare = panasonic_c20_inputs
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "{data}/hppc.mat"\n'
                   f'pulses_soc0 = 1.0\nocv = "{data}/ocv-c20.mat"\n')
    inputs = prepare(load_config(cfg))
    check = inputs.ocv_report.check
    # data.ocv_branch auto: the discharge branch is the reading closest to the rests
    # (8 mV RMS); the average of both branches (25 mV) is warned about
    assert check.warning and check.better == "pulses"
    assert check.rms_v < 0.010
    note = next(n for n in inputs.notes if n.startswith("OCV check"))
    assert "warning: read as the average of its branches, it differs by 2" in note
    assert "the pulse test's rests are still the better source" in note
    assert any("data.ocv_branch auto: its discharge branch" in n for n in inputs.notes)
    # read as the average (data.ocv_branch = "both"): 25 mV RMS off the relaxed rests at the
    # test's own temperature, so the rests lead and the file fills the SOC beyond them ...
    cfg.write_text(cfg.read_text() + 'ocv_branch = "both"\n')
    led = prepare(load_config(cfg))
    assert led.ocv_report.sources[0] == "pulses"
    assert any("the pulse test's rests first" in n for n in led.notes)
    # ... and, the file kept as given (data.ocv_rests_first = "never"), the check warns
    cfg.write_text(cfg.read_text() + 'ocv_rests_first = "never"\n')
    both_ = prepare(load_config(cfg)).ocv_report.check
    assert both_.warning and 0.015 < both_.rms_v < 0.035
    # the rests themselves: 66 before the pulses, the record's first, one after a cut-off
    assert check.n == 68
    # combined: the rests over their span, the C/20 test below it; no warning
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "{data}/hppc.mat"\n'
                   f'pulses_soc0 = 1.0\nocv = ["pulses", "{data}/ocv-c20.mat"]\n')
    both = prepare(load_config(cfg))
    assert not both.ocv_report.check.warning
    assert both.ocv_report.check.rms_v < 0.003
    assert any("SOC 0.00..0.04 from ocv-c20.mat, shifted by" in n for n in both.notes)
    assert not any("held flat" in n for n in both.notes)


def test_pulse_rests_combined_with_a_low_rate_test_fix_the_end_of_discharge(tmp_path):
    """OCV from pulse rests between SOC 0.9 and 0.3 held flat below: at the end of
    discharge the model was hundreds of mV off. With the low-rate test after it, not."""
    truth = _three_files(tmp_path, 3300.0, 0.95)        # 1C from 0.95 to 0.04
    maxes = {}
    for name, ocv in (("rests", '"pulses"'), ("both", '["pulses", "c20.csv"]')):
        cfg = tmp_path / f"{name}.toml"
        cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                       f'pulses_soc0 = 1.0\nocv = {ocv}\ncycle = "cycle.csv"\nsoc0 = 0.95\n'
                       '[fit]\nmethods = ["ga"]\n[c]\nnumeric = []\n')
        out = tmp_path / name
        assert main(["build", str(cfg), "--out", str(out), "--quiet", "--no-plots"]) == 0
        from ecmgen.model import load_model
        from ecmgen.model.simulate import validate
        from ecmgen.data.measure import read_timeseries

        val = validate(load_model(out / "model.json"), read_timeseries(tmp_path / "cycle.csv"),
                       0.95)
        maxes[name] = val.overall.max_abs_v
    assert maxes["rests"] > 0.15 and maxes["both"] < 0.04, maxes


def test_a_flat_ocv_stops_the_build_with_one_line(tmp_path, capsys):
    truth = synthetic_nca_model()
    series, _ = make_pulse_test(truth, soc_levels=(0.9, 0.6), c_rates=(1.0,), rest_s=600.0)
    write_timeseries_csv(series, tmp_path / "pulses.csv")
    t = np.arange(0, 20 * 3600.0, 60.0)
    write_timeseries_csv(TimeSeries(t, np.full(t.size, -0.145), np.full(t.size, 3.9076)),
                         tmp_path / "c15.csv")
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "c15.csv"\n[fit]\nmethods = ["ga"]\n')
    out = tmp_path / "out"
    assert main(["build", str(cfg), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ecmgen: error: ") and "c15.csv: the OCV is flat" in err
    assert "\n" not in err and not out.exists()


@pytest.mark.parametrize("ocv,needle", [
    ('["pulses", "pulses"]', "names a source twice"),
    ('["pulses", "missing.csv"]', "data.ocv names a missing file: missing.csv"),
    ('[]', "non-empty list"),
    ('"pulses"\nocv_cycle = 0', "data.ocv_cycle must be a cycle number"),
])
def test_bad_ocv_settings(tmp_path, ocv, needle):
    from ecmgen.config import load_config
    from ecmgen.errors import InputError

    (tmp_path / "p.csv").write_text("time_s,current_a,voltage_v\n0,0,3.7\n1,0,3.7\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "p.csv"\nocv = {ocv}\n')
    with pytest.raises(InputError, match=needle):
        load_config(cfg)


def test_build_json_tells_what_was_not_measured(tmp_path):
    """--json: the OCV's sources, spans and check; the fit flags; each cycle's SOC range,
    start SOC and how it was found; an OCV plot in every build."""
    truth = _three_files(tmp_path, 2000.0, 0.9)
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "c20.csv"\ncycle = "cycle.csv"\n[fit]\nmethods = ["ga"]\n'
                   '[c]\nnumeric = []\n')
    out = tmp_path / "out"
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "build", str(cfg), "--out",
                          str(out), "--json", "--quiet"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""                               # no stray warnings
    doc = json.loads(res.stdout)
    ocv = doc["checks"]["ocv"]
    assert ocv["sources"] == ["c20.csv"] and ocv["capacity_ah"]["c20.csv"]["discharge"] > 2.8
    assert ocv["check"]["rms_v"] < 0.005 and ocv["check"]["warning"] is False
    assert isinstance(doc["checks"]["fit_flags"]["ga"], list)
    assert doc["checks"]["soc_spans"]["ga"]["discharge"][0] == pytest.approx(0.3, abs=0.01)
    cyc = doc["validation"]["ga"]["cycles"]["cycle.csv"]
    assert cyc["soc0"] == pytest.approx(0.9, abs=0.01) and "rest it opens with" in cyc["soc0_how"]
    assert cyc["soc_range"][0] == pytest.approx(0.9 - 1940 / 3600, abs=0.01) and cyc["warnings"] == []
    assert (out / "ocv.png").stat().st_size > 10_000
    # the pulse test's start SOC came from its rests against the C/20 OCV
    assert any(n.startswith("pulse test start SOC 1.0") for n in doc["notes"])
