"""A model over temperature from real data: the bundled Panasonic 18650PF pulse tests at 25
and 0 degC (examples/), every method, validated on a 25 and two 0 degC drive cycles on
their measured cell temperature (the 0 degC cells warm to 14 degC in US06)."""

from __future__ import annotations

import json

import pytest

from conftest import REPO, built_once
from ecmgen.cli import main

EXAMPLE = REPO / "examples" / "panasonic-temperature"


@pytest.fixture(scope="module")
def build_25_and_0(tmp_path_factory):
    """The build's --json document and its MAE per (method, cycle) in mV."""
    import subprocess
    import sys

    def build(tmp_path):
        c25, c0 = REPO / "examples" / "panasonic-25degC", EXAMPLE / "0degC"
        cfg = tmp_path / "cell.toml"
        cfg.write_text(
            f'[cell]\ncapacity_ah = 2.9\n[data]\ncycle = "{c25 / "us06.mat"}"\n'
            f'extra_cycles = ["{c0 / "us06.mat"}", "{c0 / "hwfet.mat"}"]\nsoc0 = 1.0\n' +
            "".join(f'[[data.pulse_tests]]\nfile = "{d / "hppc.mat"}"\nsoc0 = 1.0\n'
                    f'steps = "{d / "hppc-soc-steps.mat"}"\n' for d in (c25, c0)))
        res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "build", str(cfg), "--out",
                              str(tmp_path / "out"), "--json", "--quiet", "--no-c",
                              "--no-plots"], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        (tmp_path / "build.json").write_text(res.stdout)

    folder = built_once(tmp_path_factory, "panasonic-25-and-0", build)
    doc = json.loads((folder / "build.json").read_text())
    mae = {(m, c): v["mae_v"] * 1e3 for m, val in doc["validation"].items()
           for c, v in val["cycles"].items()}
    return doc, mae


_25, _0U, _0H = "panasonic-25degC/us06.mat", "0degC/us06.mat", "0degC/hwfet.mat"
# The report's verdict: a model passes a cycle within [report] max_mae_mv (default 50 mV).
VERDICT_MV = 50.0
# The paper's five-point methods miss it on the 0 degC cycles that warm to 14 degC
# (82.9 / 75.7 mV when this test was written): known misses, strict.
KNOWN_MISSES = {(m, c) for m in ("ga", "lm") for c in (_0U, _0H)}


@pytest.mark.slow
def test_25_and_0_degC_tests_read_their_temperatures(build_25_and_0):
    doc, _ = build_25_and_0
    temps = [t["temperature_c"] for t in doc["temperature"]["pulse_tests"]]
    assert temps == [pytest.approx(25.8, abs=0.3), pytest.approx(0.6, abs=0.3)]
    assert doc["validation"]["curve"]["cycles"]["0degC/us06.mat"]["temperature_c"]["max"] > 13


@pytest.mark.slow
@pytest.mark.parametrize("key", [
    pytest.param((m, c), marks=pytest.mark.xfail(strict=True, reason="known miss"))
    if (m, c) in KNOWN_MISSES else (m, c)
    for m in ("curve", "ga", "lm") for c in (_25, _0U, _0H)])
def test_25_and_0_degC_build_passes_the_reports_verdict(build_25_and_0, key):
    _, mae = build_25_and_0
    assert mae[key] <= VERDICT_MV, (key, mae[key])


@pytest.mark.slow
@pytest.mark.parametrize("cycle", [_25, _0U, _0H])
def test_25_and_0_degC_whole_test_fit_beats_the_papers_methods(build_25_and_0, cycle):
    """The default fit against the paper's five-point GA / LM on the same data and cycle."""
    _, mae = build_25_and_0
    assert mae[("curve", cycle)] < min(mae[("ga", cycle)], mae[("lm", cycle)]), mae


@pytest.mark.slow
def test_a_test_between_two_others_takes_their_time_constants_where_they_predict_better(
        tmp_path):
    """The bundled 0.6, -9.9 and -19.9 degC tests: alone, the -9.9 degC one puts its
    diffusion pair at 283 s, below both neighbours (507 / 672 s); their time constants
    interpolated to its temperature predict its left-out levels better (measured 0.91 x
    the error) and are kept: tau_diff then rises monotonically towards the cold."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import fit_pulse_tests

    cfg_path = tmp_path / "cell.toml"
    cfg_path.write_text(
        '[cell]\ncapacity_ah = 2.9\n[fit]\nmethods = ["curve"]\n' +
        "".join(f'[[data.pulse_tests]]\nfile = "{EXAMPLE / d / "hppc.mat"}"\nsoc0 = 1.0\n'
                f'steps = "{EXAMPLE / d / "hppc-soc-steps.mat"}"\n'
                for d in ("0degC", "n10degC", "n20degC")))
    fits = fit_pulse_tests(load_config(cfg_path), workers=1)
    cold = [f.raw["curve_fit"] for f in fits]
    said = [n for n in fits[1].models["curve"].notes if "neighbouring tests" in n]
    assert len(said) == 1 and "predict a left-out level better" in said[0], said
    assert cold[0].tau_diff_s < cold[1].tau_diff_s < cold[2].tau_diff_s
    assert not any("neighbouring" in n for f in (fits[0], fits[2])
                   for n in f.models["curve"].notes)
