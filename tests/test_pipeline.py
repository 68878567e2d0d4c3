"""The `ecmgen` CLI end to end: the bundled example, --json, and bad inputs (one-line
error, non-zero exit, no partial output)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, synthetic_nca_model, write_synthetic_cell
from ecmgen.cli import main
from ecmgen.data.measure import TimeSeries, write_timeseries_csv

EXAMPLE = REPO / "examples" / "panasonic-25degC" / "config.toml"


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO)


@pytest.fixture
def synthetic_project(tmp_path):
    """A small synthetic cell: pulse test CSV, OCV table, a drive cycle and a config."""
    truth = write_synthetic_cell(tmp_path, 1800.0)
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "ocv.csv"\ncycle = "cycle.csv"\n[fit]\nrelax_s = 900\n[c]\nnumeric = []\n')
    return tmp_path, cfg, truth


def test_build_json_on_a_synthetic_cell(synthetic_project):
    folder, cfg, truth = synthetic_project
    out = folder / "out"
    res = run_cli("build", cfg, "--out", out, "--json", "--no-plots")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert Path(doc["model"]) == out / "model.json"
    assert set(doc["validation"]) == {"ga", "lm", "curve"}
    for m in doc["validation"].values():
        assert set(m) >= {"mae_v", "rmse_v", "max_abs_v"}
    # the whole-curve fit sees the 60 s pole that the paper's five points within 10 s
    # cannot: it validates better than both of them on the cycle the truth generated
    mae = {m: v["mae_v"] for m, v in doc["validation"].items()}
    assert mae["curve"] < min(mae["ga"], mae["lm"]), mae
    # soc0 was found from the first rested voltage of the cycle (the spec's start-SOC
    # target: within 1 %)
    assert doc["validation"]["curve"]["soc0"] == pytest.approx(0.8, abs=0.01)
    assert (out / "dcir.csv").exists() and (out / "model-ga.json").exists()
    # validate agrees with build
    res2 = run_cli("validate", out / "model.json", folder / "cycle.csv", "--json")
    assert res2.returncode == 0, res2.stderr
    assert json.loads(res2.stdout)["mae_v"] == pytest.approx(doc["validation"]["curve"]["mae_v"])
    # ... also above 10 % SOC, per cycle, as report.md and validate --json give it
    assert doc["validation"]["curve"]["cycles"]["cycle.csv"]["soc_above_10"] == pytest.approx(
        json.loads(res2.stdout)["soc_above_10"])
    # the simulated cycle's voltage answers its current on time
    assert json.loads(res2.stdout)["voltage_lag_samples"] == 0
    assert doc["validation"]["curve"]["cycles"]["cycle.csv"]["voltage_lag_samples"] == 0


def test_same_inputs_give_byte_identical_model(synthetic_project):
    folder, cfg, _ = synthetic_project
    for name in ("a", "b"):
        assert main(["build", str(cfg), "--out", str(folder / name), "--quiet", "--no-plots"]) == 0
    for f in ("model.json", "model-ga.json", "model-lm.json", "dcir.csv"):
        assert (folder / "a" / f).read_bytes() == (folder / "b" / f).read_bytes()


@pytest.mark.slow
def test_bundled_example_meets_the_accuracy_target(tmp_path):
    res = run_cli("build", EXAMPLE, "--out", tmp_path / "demo", "--json", "--no-c")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    val = doc["validation"]
    # every method within the report's verdict ([report] max_mae_mv, 50 mV), and the
    # whole-test fit ahead of the paper's five-point GA / LM on each cycle
    for cycle in ("us06.mat", "hwfet-a.mat"):
        got = {m: val[m]["cycles"][cycle]["mae_v"] for m in ("curve", "ga", "lm")}
        assert max(got.values()) <= 0.050, (cycle, got)
        assert got["curve"] < min(got["ga"], got["lm"]), (cycle, got)
    assert any("discharge pulses only" in n for n in doc["notes"])
    for png in ("dcir-fit.png", "curve-fit.png", "validation-us06.png"):
        assert (tmp_path / "demo" / png).stat().st_size > 10_000


def _fails(args, *needles):
    res = run_cli(*args, "--quiet")  # stderr then holds the error line alone
    assert res.returncode != 0
    err = res.stderr.strip()
    assert err.count("\n") == 0, err  # one line
    for n in needles:
        assert n in err, err
    return err


def test_config_naming_a_missing_file(synthetic_project):
    folder, cfg, _ = synthetic_project
    cfg.write_text(cfg.read_text().replace('cycle = "cycle.csv"', 'cycle = "nope.csv"'))
    _fails(["build", cfg, "--out", folder / "out"], "cell.toml", "nope.csv", "missing file")
    assert not (folder / "out").exists()


def test_ocv_table_not_monotonic(synthetic_project):
    folder, cfg, _ = synthetic_project
    (folder / "ocv.csv").write_text("soc,ocv_v\n0,3.0\n0.5,3.8\n1,3.7\n")
    _fails(["build", cfg, "--out", folder / "out"], "ocv.csv", "not monotonic")
    assert not (folder / "out").exists()


def test_pulse_test_without_pulses(synthetic_project):
    folder, cfg, _ = synthetic_project
    t = np.arange(0, 4000.0)
    write_timeseries_csv(TimeSeries(t, np.full(t.size, -1.0), 4.0 - 1e-4 * t),
                         folder / "pulses.csv")
    _fails(["build", cfg, "--out", folder / "out"], "pulses.csv", "no pulses found")
    assert not (folder / "out").exists()


def test_time_going_backwards_and_nan_and_missing_column(synthetic_project):
    folder, cfg, _ = synthetic_project
    lines = (folder / "cycle.csv").read_text().splitlines()
    bad = lines[:50] + [lines[40]] + lines[50:]
    (folder / "cycle.csv").write_text("\n".join(bad) + "\n")
    _fails(["build", cfg, "--out", folder / "out"], "cycle.csv", "time goes backwards")
    lines[30] = lines[30].rsplit(",", 1)[0] + ",nan"
    (folder / "cycle.csv").write_text("\n".join(lines) + "\n")
    _fails(["build", cfg, "--out", folder / "out"], "cycle.csv", "NaN")
    (folder / "cycle.csv").write_text("time_s,current_a\n0,0\n1,0\n")
    _fails(["build", cfg, "--out", folder / "out"], "cycle.csv", "voltage_v")
    assert not (folder / "out").exists()


def test_current_in_ma_declared_as_a(synthetic_project):
    folder, cfg, _ = synthetic_project
    lines = (folder / "cycle.csv").read_text().splitlines()
    rows = [lines[0]]
    for ln in lines[1:]:
        t, i, v = ln.split(",")[:3]
        rows.append(f"{t},{float(i) * 1000!r},{v}")
    (folder / "cycle.csv").write_text("\n".join(rows) + "\n")
    _fails(["build", cfg, "--out", folder / "out"], "cycle.csv", "mA declared as A")


def test_output_never_overwrites_an_input(synthetic_project):
    folder, cfg, _ = synthetic_project
    shutil.copy(folder / "ocv.csv", folder / "dcir.csv")
    cfg.write_text(cfg.read_text().replace('pulses = "pulses.csv"', 'pulses = "pulses.csv"\n'
                                           'extra_cycles = ["dcir.csv"]'))
    before = (folder / "dcir.csv").read_bytes()
    res = run_cli("build", cfg, "--out", folder, "--no-plots")
    assert res.returncode != 0
    assert (folder / "dcir.csv").read_bytes() == before
    assert not (folder / "model.json").exists()


def test_another_cyclers_csv_with_ma_and_discharge_positive(synthetic_project):
    """A pulse test exported by another cycler: its own column names, mA, current
    positive on discharge, time in minutes; mapped per file role in the config."""
    folder, cfg, truth = synthetic_project
    from ecmgen.data.measure import read_timeseries

    s = read_timeseries(folder / "pulses.csv")
    rows = ["Zeit_min;Strom_mA;Spannung_V;Ladung_mAh"] + [
        f"{float(t) / 60!r};{float(-i) * 1000!r};{float(v)!r};{float(-q) * 1000!r}"
        for t, i, v, q in zip(s.time_s, s.current_a, s.voltage_v, s.charge_ah)]
    (folder / "pulses-other.csv").write_text("\n".join(rows) + "\n")
    text = cfg.read_text().replace('pulses = "pulses.csv"', 'pulses = "pulses-other.csv"\n'
                                   'pulses_soc0 = 1.0')
    text += ('[data.columns.pulses]\ntime = "Zeit_min"\ntime_unit = "min"\ncurrent = "Strom_mA"\n'
             'current_unit = "mA"\ncurrent_sign = "discharge_positive"\nvoltage = "Spannung_V"\n'
             'charge = "Ladung_mAh"\ncharge_unit = "mAh"\n')
    cfg.write_text(text)
    res = run_cli("build", cfg, "--out", folder / "out2", "--json", "--no-plots", "--quiet")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    # same cell, same answer as from the canonical file (the same ordering of the methods)
    mae = {m: v["mae_v"] for m, v in doc["validation"].items()}
    assert mae["curve"] < min(mae["ga"], mae["lm"]), mae
    assert "pulses-other.csv" in (folder / "out2" / "model.json").read_text()


@pytest.mark.slow
def test_diagnose_cli_on_the_bundled_example(tmp_path):
    """US06 diagnosed, HWFET-a judged ([diagnose] judge in the example config)."""
    res = run_cli("diagnose", EXAMPLE, "--out", tmp_path / "diag", "--json", "--quiet",
                  "--no-plots")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert set(doc) >= {"effects", "mae_before_v", "mae_after_v", "model"}
    assert doc["effects"], "nothing found"
    for step in doc["effects"]:
        assert set(step) >= {"name", "mae_before_v", "mae_after_v"}
        assert step["mae_after_v"] < step["mae_before_v"]
    # the spec's target for the augmented model on HWFET-a: 15 mV
    assert doc["mae_after_v"] <= 0.015
    # the augmented model validates on the judge cycle with about that figure above 10 %
    # SOC (diagnose leaves out where the base model is below 10 %, validate where the
    # augmented one is: with a capacity error added they end at different samples)
    res2 = run_cli("validate", doc["model"], REPO / "examples" / "panasonic-25degC" / "hwfet-a.mat",
                   "--soc0", "1.0", "--json")
    assert json.loads(res2.stdout)["soc_above_10"]["mae_v"] == pytest.approx(
        doc["mae_after_v"], rel=0.15)


def test_codegen_cli_writes_c_for_a_model_and_refuses_bad_ones(tmp_path):
    from ecmgen.model.effects import make_effect

    model = synthetic_nca_model().with_effects([make_effect("extra_rc", r_ohm=0.01, tau_s=600.0)])
    path = model.save(tmp_path / "model.json")
    res = run_cli("codegen", path, "--out", tmp_path / "c", "--prefix", "cell1")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "c" / "cell1_ecm_f32.h").exists() and (tmp_path / "c" / "cell1_ecm_f32.c").exists()
    assert "extra_rc" in (tmp_path / "c" / "cell1_ecm_f32.h").read_text()
    bad = tmp_path / "bad.json"
    bad.write_text(path.read_text().replace('"schema_version": 2', '"schema_version": 99'))
    err = _fails(["codegen", bad, "--out", tmp_path / "c2"], "bad.json", "schema_version")
    assert "99" in err
    assert not (tmp_path / "c2").exists()


def test_validate_reads_another_cyclers_csv_through_the_config(synthetic_project):
    folder, cfg, _ = synthetic_project
    assert main(["build", str(cfg), "--out", str(folder / "out"), "--quiet", "--no-plots"]) == 0
    from ecmgen.data.measure import read_timeseries

    s = read_timeseries(folder / "cycle.csv")
    rows = ["t [h],I [mA],U [V]"] + [f"{float(t) / 3600!r},{float(-i) * 1000!r},{float(v)!r}"
                                    for t, i, v in zip(s.time_s, s.current_a, s.voltage_v)]
    (folder / "cycle-other.csv").write_text("\n".join(rows) + "\n")
    cfg.write_text(cfg.read_text() + '[data.columns.cycle]\ntime = "t [h]"\ntime_unit = "h"\n'
                   'current = "I [mA]"\ncurrent_unit = "mA"\ncurrent_sign = "discharge_positive"\n'
                   'voltage = "U [V]"\n')
    a = run_cli("validate", folder / "out" / "model.json", folder / "cycle.csv", "--json")
    b = run_cli("validate", folder / "out" / "model.json", folder / "cycle-other.csv",
                "--config", cfg, "--json")
    assert b.returncode == 0, b.stderr
    assert json.loads(b.stdout)["mae_v"] == pytest.approx(json.loads(a.stdout)["mae_v"], rel=1e-6)
    _fails(["validate", folder / "out" / "model.json", folder / "cycle-other.csv"],
           "cycle-other.csv", "columns not recognised")


def test_build_notes_name_validation_cycles_as_the_table_does():
    """Two cycles called us06.mat (0degC/, n20degC/): a validation warning that opens with
    the base name is told apart by the build's cycle name."""
    from ecmgen.validation import named as _named

    w = "us06.mat: the voltage lags the current by 1 sample (0.1 s)"
    assert _named(w, "/data/n20degC/us06.mat", "n20degC/us06.mat").startswith("n20degC/us06.mat: ")
    assert _named(w, "/data/us06.mat", "us06.mat") == w
    assert _named("simulated SOC left [0, 1]", "/d/us06.mat", "x/us06.mat") == \
        "simulated SOC left [0, 1]"
    assert _named(w, None, "us06.mat") == w


def test_build_reports_table_quality_and_strict_refuses_a_failing_model(synthetic_project,
                                                                         monkeypatch):
    from ecmgen.config import load_config
    from ecmgen.errors import InputError
    from ecmgen.fit import quality
    from ecmgen.pipeline import build
    from ecmgen.report import build_json

    folder, cfg, _ = synthetic_project
    result = build(load_config(cfg), folder / "out", plots=False, c_code=False, strict=True)
    doc = build_json(result)
    assert doc["quality"]["curve"]["passes"] and doc["quality"]["curve"]["non_positive"] == 0
    assert doc["quality"]["curve"]["roughness"] < 0.35
    assert "## Table quality" in (folder / "out" / "report.md").read_text()
    # the same model judged against an impossible limit: --strict refuses, nothing written
    monkeypatch.setattr(quality, "ROUGHNESS_LIMIT", -1.0)
    with pytest.raises(InputError, match="build --strict: model 'curve' fails the table checks"):
        build(load_config(cfg), folder / "strict", plots=False, c_code=False, strict=True)
    assert not (folder / "strict").exists()
