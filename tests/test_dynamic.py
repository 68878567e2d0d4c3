"""A model from a dynamic test (data.dynamic): a drive profile in blocks with rests between
them, no pulse test. Before: the only path was to force the file in as a pulse test
(data.pulses with [dcir] max_pulse_s = 2000), whose 'levels' were stray regen pulses inside
the drive blocks (one discharge level at SOC 1, six charge levels; held-out MAE 434 mV)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, SHARED_DATA, a123_example, need
from ecmgen.data.dynamic import find_blocks
from ecmgen.data.measure import TimeSeries

A123 = SHARED_DATA / "plett-a123-lfp"
EXAMPLE = REPO / "examples" / "a123-dynamic" / "config.toml"


def _drive(n: int, rng) -> np.ndarray:
    """A drive-like profile: discharge and regen steps with short stops (<= 20 s)."""
    out = []
    while len(out) < n:
        out += [float(rng.uniform(-3.0, -0.5))] * int(rng.integers(5, 40))
        out += [0.0] * int(rng.integers(1, 20))
        out += [float(rng.uniform(0.3, 1.5))] * int(rng.integers(2, 10))
    return np.array(out[:n])


def _dynamic_series(cut_last: bool = True) -> TimeSeries:
    """400 s rest, a 720 s constant discharge, then four 1400 s drive blocks, 600 s of rest
    after each block; the last block stopped at 2.0 V after 900 s (``cut_last``)."""
    rng = np.random.default_rng(0)
    parts = [np.zeros(400), np.full(720, -1.0), np.zeros(600)]
    for k in range(4):
        parts += [_drive(900 if (cut_last and k == 3) else 1400, rng), np.zeros(600)]
    i = np.concatenate(parts)
    t = np.arange(i.size, dtype=float)
    v = 3.3 + 0.05 * i
    if cut_last:
        v[-1500:-600] = np.linspace(3.2, 2.0, 900)    # the last block runs to the limit
    return TimeSeries(t, i, v, source="dyn.csv")


def test_blocks_are_the_stretches_between_long_rests():
    """The short stops inside a drive profile stay in their block; the shorter opening
    block (another kind of current) is a level like the others; the last block, stopped
    early at the record's lowest voltage, is cut short (its rows stay, it is no level)."""
    series = _dynamic_series()
    blocks = find_blocks(series, 2.0, soc0=1.0)
    assert len(blocks) == 5
    assert [b.cut_short for b in blocks] == [False, False, False, False, True]
    assert blocks[0].duration_s == pytest.approx(719, abs=2) and blocks[1].duration_s > 1300
    assert all(b.direction == "discharge" for b in blocks)
    socs = [b.soc for b in blocks]
    assert socs[0] == 1.0 and all(np.diff(socs) < 0)
    # the opening block's mean current is its -1 A: its level's mid SOC is half its charge
    assert blocks[0].current_a == pytest.approx(-1.0, rel=0.01)


def test_a_block_not_at_the_limit_is_a_level():
    blocks = find_blocks(_dynamic_series(cut_last=False), 2.0, soc0=1.0)
    assert not any(b.cut_short for b in blocks)


def test_a_record_without_current_is_refused():
    series = TimeSeries(np.arange(1000.0), np.zeros(1000), np.full(1000, 3.3),
                        source="rest.csv")
    with pytest.raises(Exception) as exc:
        find_blocks(series, 2.0, soc0=1.0)
    assert "rest.csv" in str(exc.value) and "not a dynamic test" in str(exc.value)


def _config(tmp_path, extra: str) -> str:
    (tmp_path / "dyn.csv").write_text("time_s,current_a,voltage_v\n0,0,3.3\n1,-1,3.2\n")
    (tmp_path / "ocv.csv").write_text("soc,ocv_v\n0,3.0\n1,4.0\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2\n[data]\ndynamic = "dyn.csv"\nocv = "ocv.csv"\n'
                   f'{extra}')
    return str(cfg)


@pytest.mark.parametrize("extra, words", [
    ('[fit]\nmethods = ["ga", "curve"]\n', "curve method only"),
    ('pulses = "dyn.csv"\n', "exactly one of"),
])
def test_dynamic_config_errors_are_one_line(tmp_path, extra, words):
    r = subprocess.run([sys.executable, "-m", "ecmgen.cli", "build", _config(tmp_path, extra),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "c.toml" in r.stderr and words in r.stderr
    assert "Traceback" not in r.stderr


def test_dynamic_config_defaults_to_the_curve_method(tmp_path):
    from ecmgen.config import load_config

    cfg = load_config(_config(tmp_path, ""))
    assert cfg.dynamic and cfg.methods == ("curve",) and cfg.pulses.name == "dyn.csv"


@pytest.mark.slow
def test_a123_model_from_the_ocv_scripts_and_the_dynamic_test(tmp_path_factory):
    """examples/a123-dynamic: the four OCV scripts as shared and the s1 dynamic test, no
    conversion; its tables pass the quality checks; validated on the held-out s3 run (a CC
    charge, then a dithered 3.6 V hold) and on s1 itself. Figures at the time of writing:
    MAE above 10 % SOC s1 9.7 mV, s3 55.9 mV (of which the 3.6 V hold, where the rested OCV
    tops out at 3.52 V, is most)."""
    from ecmgen.config import load_config
    from ecmgen.model.model import load_model
    from ecmgen.model.simulate import validate
    from ecmgen.pipeline import read_series

    need(A123)
    built = a123_example(tmp_path_factory)     # `build --json -q`, shared with other tests
    out = built / "out"
    got = json.loads((built / "build.json").read_text())
    quality = got["quality"]["curve"]
    assert quality["passes"] and quality["non_positive"] == 0
    notes = "\n".join(got["notes"])
    assert "dynamic test: 18 blocks" in notes and "1 cut short" in notes
    assert "joined end to end" in notes          # the four OCV scripts, one test
    assert "blocks run both ways" in notes       # the regen: charge tables of their own
    cfg = load_config(EXAMPLE)
    model = load_model(out / "model.json")
    mae = {}
    for run, soc0 in (("s1", 1.0), ("s3", None)):
        series = read_series(cfg, A123 / "dyn_data" / f"A123_DYN_50_P25_{run}.csv", "cycle")
        mae[run] = validate(model, series, soc0=soc0).soc_above_10.mae_v
    # the run it was fitted on passes the report's verdict ([report] max_mae_mv, 50 mV) and
    # fits better than the held-out s3; s3's own figure is gated by the accuracy matrix
    # (bench/baseline/accuracy_matrix.json, a123/s3; tests/test_accuracy_gate.py)
    assert mae["s1"] <= 0.050 and mae["s1"] < mae["s3"], mae


def test_a_pulse_test_entry_may_be_a_dynamic_test(tmp_path):
    """Dynamic tests at several temperatures: one [[data.pulse_tests]] entry each, with
    dynamic = true; their one-test configs read them as data.dynamic does."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import pulse_test_config

    for name in ("a.csv", "b.csv"):
        (tmp_path / name).write_text("time_s,current_a,voltage_v\n0,0,3.3\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2\n'
                   '[[data.pulse_tests]]\nfile = "a.csv"\ntemperature_c = 25\ndynamic = true\n'
                   '[[data.pulse_tests]]\nfile = "b.csv"\ntemperature_c = 0\ndynamic = true\n')
    got = load_config(cfg)
    assert got.methods == ("curve",) and all(t.dynamic for t in got.pulse_tests)
    assert pulse_test_config(got, got.pulse_tests[1]).dynamic
    cfg.write_text(cfg.read_text() + '[fit]\nmethods = ["lm"]\n')
    with pytest.raises(Exception) as exc:
        load_config(cfg)
    assert "curve method only" in str(exc.value)
