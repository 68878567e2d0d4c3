"""`ecmgen build` over temperature end to end on a synthetic cell: three pulse tests at
their temperatures ([[data.pulse_tests]]), fitted in parallel and joined into one model,
validated on cycles whose cell temperature moves; the same bytes whatever the number of
processes; no warning escapes; per-temperature reporting."""

from __future__ import annotations

import json
from pathlib import Path
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from conftest import REPO, make_pulse_test, synthetic_nca_model
from ecmgen.config import load_config
from ecmgen.data.measure import TimeSeries, write_timeseries_csv
from ecmgen.model.temperature import KELVIN, assemble_over_temperature

TEMPS = (25.0, 5.0, -10.0)


def _truth_at(t_c):
    """The synthetic NCA cell at t_c: resistances Arrhenius (Ea/R 2500 K), taus fixed."""
    m = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=60.0)
    f = float(np.exp(2500.0 * (1.0 / (t_c + KELVIN) - 1.0 / (25.0 + KELVIN))))

    def scale(t):
        return replace(t, r0_ohm=t.r0_ohm * f, r_fast_ohm=t.r_fast_ohm * f,
                       r_slow_ohm=t.r_slow_ohm * f)

    return replace(m, charge=scale(m.charge), discharge=scale(m.discharge))


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    folder = tmp_path_factory.mktemp("multi")
    truths = [_truth_at(t) for t in TEMPS]
    for t, truth in zip(TEMPS, truths):
        series, _ = make_pulse_test(truth, soc_levels=(0.9, 0.6, 0.3), c_rates=(1.0, 3.0),
                                    noise_v=0.0003, rest_s=900.0, seed=int(t) + 20)
        temp = np.full(series.time_s.size, t)
        write_timeseries_csv(replace(series, temperature_c=temp), folder / f"pulses{t:g}.csv")
    np.savetxt(folder / "ocv.csv", np.column_stack([truths[0].ocv.soc, truths[0].ocv.ocv_v[0]]),
               delimiter=",", header="soc,ocv_v", comments="")
    # the truth over temperature, interpolated as the fitted model will be
    truth = assemble_over_temperature(truths, TEMPS)
    from ecmgen.model.simulate import simulate

    t = np.arange(0, 1800.0, 1.0)
    rng = np.random.default_rng(1)
    i = np.repeat(rng.uniform(-8, 0, t.size // 20), 20)
    i[:60] = 0.0
    for name, temp in (("warming", np.linspace(-10.0, 24.0, t.size)),
                       ("cold", np.full(t.size, -4.0))):
        v = simulate(truth, t, i, 0.8, temp).voltage_v
        write_timeseries_csv(TimeSeries(t, i, v, temp), folder / f"{name}.csv")
    tests = "".join(f'[[data.pulse_tests]]\nfile = "pulses{t:g}.csv"\nsoc0 = 1.0\n'
                    for t in TEMPS)
    cfg = folder / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\nocv = "ocv.csv"\ncycle = "warming.csv"\n'
                   'extra_cycles = ["cold.csv"]\nsoc0 = 0.8\n' + tests +
                   '[fit]\nrelax_s = 900\nmethods = ["lm", "curve"]\n[c]\nnumeric = []\n')
    return folder, cfg, truth


def test_build_over_temperature_from_the_command_line(project):
    folder, cfg, truth = project
    out = folder / "out"
    # -W error: a warning anywhere, also in a worker process, would fail the build
    res = subprocess.run([sys.executable, "-W", "error", "-m", "ecmgen.cli", "build", str(cfg),
                          "--out", str(out), "--json"], capture_output=True, text=True, cwd=REPO)
    assert res.returncode == 0, res.stderr
    assert "Warning" not in res.stderr
    doc = json.loads(res.stdout)
    temps = doc["temperature"]
    assert [t["temperature_c"] for t in temps["pulse_tests"]] == list(TEMPS)
    assert {t["temperature_from"] for t in temps["pulse_tests"]} == \
        {"median cell temperature in its pulses"}
    assert temps["table_temperatures_c"] == list(np.arange(-10.0, 46.0, 5.0))
    assert temps["ocv_temperatures_c"] == [None]        # one OCV file for all tests
    cycles = doc["validation"]["curve"]["cycles"]
    # over the drive: the rest at -10 degC before its first current left out
    drive = cycles["warming.csv"]["temperature_c"]
    assert -10.0 < drive["min"] < -8.5 and drive["max"] == 24.0
    assert cycles["cold.csv"]["temperature_c"] == {"min": -4.0, "max": -4.0}
    # the whole-curve fit recovers each temperature's cell (on its three SOC levels; the
    # cycles run down to SOC 0.1); between them the tables follow the same Arrhenius law
    # as the truth: on both cycles it validates better than the paper's five points (LM)
    lm = doc["validation"]["lm"]["cycles"]
    for name in ("warming.csv", "cold.csv"):
        assert cycles[name]["mae_v"] < lm[name]["mae_v"], (name, cycles[name], lm[name])
    # the warm row's Ea/R is the two warmest tests' r0 slope: with each r0 within the
    # spec's 5 % of its truth, within ln(1.05 / 0.95) / (1/T(5 degC) - 1/T(25 degC)) of the
    # truth's 2500 K
    warm = [n for n in doc["notes"] if "derived warm row" in n]
    ea = re.search(r"r0_ohm (\d+) K", warm[0]) if warm else None
    within_k = np.log(1.05 / 0.95) / (1 / (5.0 + KELVIN) - 1 / (25.0 + KELVIN))
    assert ea and abs(int(ea.group(1)) - 2500.0) < within_k, warm
    for label in ("25.0degC", "5.0degC", "n10.0degC"):
        assert (out / f"dcir-{label}.csv").is_file()
    assert (out / "parameters-curve.png").stat().st_size > 10_000
    assert (out / "validation-warming.png").is_file()
    report = (out / "report.md").read_text()
    assert "## Pulse tests (temperature breakpoints)" in report and "-8.9..24.0" in report
    model = json.loads((out / "model.json").read_text())
    assert model["rc"]["discharge"]["temperature_c"] == temps["table_temperatures_c"]
    assert any(n.startswith("temperature breakpoints measured: -10.0 degC (pulses-10.csv)")
               for n in model["notes"])
    assert {r["name"] for r in model["inputs"]} >= {"pulses25.csv", "pulses5.csv", "ocv.csv"}


def test_same_model_on_one_or_two_processes(project, tmp_path):
    from ecmgen.pipeline import build

    folder, cfg_path, _ = project
    cfg = replace(load_config(cfg_path), methods=("lm",), best="lm")
    a = build(cfg, tmp_path / "a", plots=False, c_code=False, workers=2)
    b = build(cfg, tmp_path / "b", plots=False, c_code=False, workers=1)
    assert len(a.tests) == 3 and [t.temperature_c for t in a.tests] == list(TEMPS)
    for name in ("model.json", "dcir-5.0degC.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_a_bad_pulse_test_names_its_file_and_writes_nothing(project, tmp_path, capsys):
    from ecmgen.cli import main

    folder, cfg_path, _ = project
    flat = tmp_path / "flat.csv"
    t = np.arange(0, 4000.0)
    write_timeseries_csv(TimeSeries(t, np.zeros(t.size), np.full(t.size, 3.7),
                                    np.full(t.size, 0.0)), flat)
    cfg = tmp_path / "cell.toml"
    cfg.write_text(cfg_path.read_text().replace('"pulses5.csv"', f'"{flat}"')
                   .replace('"ocv.csv"', f'"{folder / "ocv.csv"}"')
                   .replace('"warming.csv"', f'"{folder / "warming.csv"}"')
                   .replace('"cold.csv"', f'"{folder / "cold.csv"}"')
                   .replace('"pulses25.csv"', f'"{folder / "pulses25.csv"}"')
                   .replace('"pulses-10.csv"', f'"{folder / "pulses-10.csv"}"'))
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"ecmgen: error: {flat}: no pulses found"), err
    assert not (tmp_path / "out").exists()


def test_a_cycle_without_temperature_is_refused_for_a_model_over_temperature(project,
                                                                            tmp_path, capsys):
    from ecmgen.cli import main

    folder, cfg_path, _ = project
    series_t = np.arange(0, 100.0)
    plain = tmp_path / "plain.csv"
    write_timeseries_csv(TimeSeries(series_t, np.zeros(100), np.full(100, 3.9)), plain)
    text = cfg_path.read_text().replace('extra_cycles = ["cold.csv"]',
                                        f'extra_cycles = ["{plain}"]')
    for name in ("ocv.csv", "warming.csv", "pulses25.csv", "pulses5.csv", "pulses-10.csv"):
        text = text.replace(f'"{name}"', f'"{folder / name}"')
    cfg = tmp_path / "cell.toml"
    cfg.write_text(text.replace('methods = ["lm", "curve"]', 'methods = ["lm"]'))
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ecmgen: error: {plain}: no cell temperature column"), err


def test_diagnose_on_a_model_over_temperature(project, tmp_path):
    """diagnose fits the base model from all pulse tests (over temperature) and runs it on
    the cycle's cell temperature; the truth has no missing effect to find."""
    from ecmgen.cli import main

    folder, cfg_path, _ = project
    cfg = folder / "diag.toml"
    cfg.write_text(cfg_path.read_text().replace('methods = ["lm", "curve"]',
                                                'methods = ["curve"]'))
    out = tmp_path / "diag"
    assert main(["diagnose", str(cfg), "--out", str(out), "--quiet", "--no-plots"]) == 0
    base = json.loads((out / "model-base.json").read_text())
    assert len(base["rc"]["discharge"]["temperature_c"]) > 1
    assert base["method"] == "curve"


def _one_test_config(folder, tmp_path, extra: str = "", pulses: str = "pulses5.csv") -> Path:
    cfg = tmp_path / "one.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "{folder / pulses}"\n'
                   f'pulses_soc0 = 1.0\nocv = "{folder / "ocv.csv"}"\n'
                   f'cycle = "{folder / "warming.csv"}"\nsoc0 = 0.8\n'
                   '[fit]\nrelax_s = 900\nmethods = ["curve"]\n[c]\nnumeric = ["float"]\n'
                   + extra)
    return cfg


def test_a_one_test_model_follows_the_cell_temperature_with_activation_k(project, tmp_path):
    """One pulse test (5 degC) validated on a cycle warming from -10 to 24 degC: without
    [model] activation_k the resistances stay the test's and the build says so; with the
    truth's Ea/R the model becomes one over temperature (rows derived about the pulses' own
    median cell temperature) that follows the cell, and its C stays bit-exact."""
    from ecmgen.pipeline import build, one_test_c
    from ecmgen.plots.figures import derived_rows

    folder, _, _ = project
    plain = build(load_config(_one_test_config(folder, tmp_path)), tmp_path / "plain",
                  plots=False, c_code=False)
    note = [n for n in plain.notes if "warming.csv: the cell runs at" in n]
    assert len(note) == 1 and "its pulse test's at 5.0 degC" in note[0], plain.notes
    cfg = load_config(_one_test_config(folder, tmp_path, "[model]\nactivation_k = 2500\n"))
    assert cfg.activation_k == 2500.0
    followed = build(cfg, tmp_path / "arr", plots=False, c_code=True)
    model = json.loads((tmp_path / "arr" / "model.json").read_text())
    assert model["rc"]["discharge"]["temperature_c"] == list(np.arange(-30.0, 46.0, 5.0))
    assert model["effects"] == []
    r0 = np.array(model["rc"]["discharge"]["r0_ohm"])
    ratio = np.median(r0[0] / r0[7])                     # -30 vs 5 degC: the Arrhenius factor
    assert abs(ratio / np.exp(2500.0 * (1 / 243.15 - 1 / 278.15)) - 1.0) < 1e-6, ratio
    assert any("derived from one pulse test at 5.0 degC" in n for n in model["notes"])
    # the parameters plot: the test's row solid, the two derived rows dashed
    test_c = one_test_c(followed.tests, followed.inputs)
    assert abs(test_c - 5.0) < 0.5, test_c
    assert derived_rows(followed.models["curve"], [test_c]) == (-30.0, 45.0)
    assert not [n for n in followed.notes if "the cell runs at" in n]
    mae = {k: r.validations["curve"]["warming.csv"].overall.mae_v
           for k, r in (("plain", plain), ("followed", followed))}
    # following the cell with the truth's Ea/R beats the test's resistances throughout
    # (the warming cycle spans -10 .. 24 degC; the accuracy of the law itself is checked
    # above, on the Arrhenius factor)
    assert mae["followed"] < mae["plain"], mae
    assert followed.c_report["float"]["bit_exact_vs_reference"] is True, followed.c_report


@pytest.mark.parametrize("extra, words", [
    ("[model]\nactivation_k = -1\n", "model.activation_k must lie in 0..50000 K"),
    ("[model]\nactivation_k = 2500\n", "needs the pulse test's cell temperature"),
])
def test_bad_activation_k_is_one_line(project, tmp_path, capsys, extra, words):
    from ecmgen.cli import main

    folder, _, _ = project
    plain = tmp_path / "no_temperature.csv"
    with_t = np.genfromtxt(folder / "pulses5.csv", delimiter=",", names=True)
    write_timeseries_csv(TimeSeries(with_t["time_s"], with_t["current_a"],
                                    with_t["voltage_v"]), plain)
    cfg = _one_test_config(folder, tmp_path, extra, pulses=str(plain))
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and words in err, err
    assert not (tmp_path / "out").exists()


def test_activation_k_is_refused_over_temperature(project, tmp_path, capsys):
    from ecmgen.cli import main

    folder, cfg_path, _ = project
    cfg = folder / "arr.toml"
    cfg.write_text(cfg_path.read_text() + "[model]\nactivation_k = 2500\n")
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "model.activation_k is for a model from one pulse test" in err, err
