"""Inputs that gave a silent wrong result are refused, or named right: a model.json with a
key twice, a temperature log that covers a small part of its record (and one without a
time column, before any fit), pulse tests whose temperature_c contradicts their own
temperature column, and the parts of a split data.ocv recorded under their own names."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import ecmgen.pipeline
from conftest import SHARED_DATA, make_pulse_test, need, synthetic_nca_model
from ecmgen.cli import main
from ecmgen.config import load_config
from ecmgen.data.measure import write_timeseries_csv
from ecmgen.errors import InputError
from ecmgen.model import load_model
from test_codegen_helpers import realistic_model


def _one_line(capsys, *words):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ecmgen: error: "), err
    for w in words:
        assert w in err, (w, err)


def test_a_model_json_with_a_key_twice_is_refused(tmp_path, capsys):
    """Before: accepted, the last value winning."""
    path = realistic_model(n_rc=6).save(tmp_path / "model.json")
    text = path.read_text()
    assert text.count('"capacity_ah":') == 1
    path.write_text(text.replace('"capacity_ah":', '"capacity_ah": 99.0, "capacity_ah":', 1))
    with pytest.raises(InputError, match='"capacity_ah" appears twice'):
        load_model(path)
    assert main(["codegen", str(path), "--out", str(tmp_path / "c"), "-q"]) == 2
    _one_line(capsys, "model.json", "appears twice")


def _no_fit(monkeypatch):
    def no_fit(*a, **k):
        raise AssertionError("a fit ran before the inputs were checked")

    monkeypatch.setattr(ecmgen.pipeline, "fit_all", no_fit)


def test_a_temperature_log_without_time_is_refused_before_the_fit(cell_files, tmp_path,
                                                                   monkeypatch, capsys):
    """Before: refused only when the cycle was read for validation, after the fit (39 s
    on the issue's build)."""
    for f in cell_files.iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes())
    (tmp_path / "t.csv").write_text("Temperature_1\n25.1\n25.2\n")
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "ocv.csv"\ncycle = "cycle.csv"\n'
                   'temperature_c = {"cycle.csv" = "t.csv"}\n[fit]\nmethods = ["lm"]\n')
    _no_fit(monkeypatch)
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "-q"]) == 2
    _one_line(capsys, "t.csv", "no time column")


def _pulse_files(folder, temps):
    for t in temps:
        series, _ = make_pulse_test(synthetic_nca_model(), soc_levels=(0.9, 0.5),
                                    c_rates=(1.0, 3.0), rest_s=900.0)
        write_timeseries_csv(replace(series, temperature_c=np.full(series.time_s.size, t)),
                             folder / f"p{t:g}.csv")
    np.savetxt(folder / "ocv.csv", np.column_stack([np.linspace(0, 1, 11),
                                                    np.linspace(3.0, 4.2, 11)]),
               delimiter=",", header="soc,ocv_v", comments="")


def test_pulse_tests_labelled_against_their_own_temperature_are_refused(tmp_path, capsys):
    """Two tests with their temperature_c swapped. Before: built, exit 0, each table row
    at the other's temperature."""
    _pulse_files(tmp_path, (25.0, 0.0))
    tests = "".join(f'[[data.pulse_tests]]\nfile = "p{f:g}.csv"\nsoc0 = 1.0\n'
                    f'temperature_c = {label:g}\n' for f, label in ((25.0, 0.0), (0.0, 25.0)))
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\nocv = "ocv.csv"\n' + tests +
                   '[fit]\nmethods = ["lm"]\n')
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "-q"]) == 2
    _one_line(capsys, "temperature_c = 0 degC", "reads 25.0 degC", "swapped")


def test_the_parts_of_a_split_ocv_keep_their_own_names(tmp_path):
    """A model over temperature from Plett's four OCV scripts: before, all four were
    recorded as A123_OCV_P25_S1.csv (with S1..S4's hashes) in model.json and report.md."""
    from ecmgen.model.model import InputRecord
    from ecmgen.pipeline import pulse_test_records

    d = need(SHARED_DATA / "plett-a123-lfp" / "ocv_data")
    parts = [d / f"A123_OCV_P25_S{k}.csv" for k in range(1, 5)]
    cfg_path = tmp_path / "c.toml"
    cfg_path.write_text("[cell]\ncapacity_ah = 2.06\n[data]\nocv = [" +
                        ", ".join(f'"{p}"' for p in parts) + "]\n" +
                        "".join(f'[[data.pulse_tests]]\nfile = "{parts[k]}"\n'
                                f'temperature_c = {t}\ndynamic = true\n'
                                for k, t in ((0, 25), (2, 0))))
    cfg = load_config(cfg_path)
    records = tuple(InputRecord("ocv", p.name, f"sha{k}") for k, p in enumerate(parts))
    for test in cfg.pulse_tests:
        named = pulse_test_records(cfg, test, records)
        assert [r.sha256 for r in named] == [r.sha256 for r in records]
        assert len({r.name for r in named}) == 4, named
