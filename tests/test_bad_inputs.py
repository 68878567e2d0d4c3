"""Every bad input is one line ``ecmgen: error: <file>: <what>``, exit 2, no traceback:
the findings of an adversarial run (directories, line ends, binary and non-UTF-8 files,
model.json of the wrong types or out of range, values the fixed point cannot hold,
implausible measurements, non-finite options), and the boundary that makes it structural
rather than a list of special cases."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from ecmgen.cli import main
from test_outputs import one_line_error


@pytest.fixture
def folder(tmp_path, cell_files):
    for f in cell_files.iterdir():
        shutil.copy(f, tmp_path / f.name)
    return tmp_path


def edited_model(folder: Path, edit) -> Path:
    doc = json.loads((folder / "model.json").read_text())
    edit(doc)
    path = folder / "bad-model.json"
    path.write_text(json.dumps(doc))
    return path


def cycle_lines(folder: Path) -> list[str]:
    return (folder / "cycle.csv").read_text().splitlines()


def _set(*keys_value):
    *keys, value = keys_value

    def edit(doc):
        d = doc
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return edit


def _del(*keys):
    def edit(doc):
        d = doc
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]
    return edit


MODEL_CASES = {
    "notes: 5": (_set("notes", 5), "notes"),
    "inputs: [5]": (_set("inputs", [5]), "inputs[1]"),
    "an input without its name": (_set("inputs", [{"role": "pulses", "sha256": "0"}]),
                                  "inputs[1]"),
    "seed: [1]": (_set("seed", [1]), "seed"),
    "schema_version: true": (_set("schema_version", True), "schema_version"),
    "capacity as a string": (_set("capacity_ah", "2.9"), "capacity_ah"),
    "capacity as a boolean": (_set("capacity_ah", True), "capacity_ah"),
    "r0 as a string": (_set("rc", "discharge", "r0_ohm", [["0.05"] * 11]), "r0_ohm"),
    "r0 = 1e6 ohm": (_set("rc", "discharge", "r0_ohm", [[1e6] * 11]), "r0_ohm"),
    "capacity 1e300": (_set("capacity_ah", 1e300), "capacity_ah"),
    "dead band 1e300": (_set("direction_deadband_a", 1e300), "direction_deadband_a"),
    "a temperature of 300 degC": (_set("ocv", "temperature_c", [300.0]), "temperature_c"),
    "a misspelt key": (_set("methd", "lm"), "did you mean 'method'"),
    "no rc tables": (_del("rc"), "rc"),
    "converged as numbers": (_set("rc", "charge", "converged", [[1] * 11]), "converged"),
}


@pytest.mark.parametrize("case", list(MODEL_CASES))
def test_model_json_of_the_wrong_type_or_range_is_one_line(folder, capsys, case):
    """Before: tracebacks (TypeError, KeyError, ValueError, OverflowError) or silent
    acceptance (true read as 1, "0.05" and booleans taken as numbers, r0 = 1e6 ohm
    validated to an MAE of 2.7e9 mV); validate and codegen now refuse the same models."""
    edit, words = MODEL_CASES[case]
    bad = edited_model(folder, edit)
    assert main(["validate", str(bad), str(folder / "cycle.csv")]) == 2
    one_line_error(capsys, str(bad), words)
    for numeric in ("float", "fixed"):
        assert main(["codegen", str(bad), "--out", str(folder / "c"), "--numeric", numeric,
                     "-q"]) == 2
        one_line_error(capsys, str(bad), words)
    assert not (folder / "c").exists()


def test_model_json_nested_too_deeply_or_with_nan_is_one_line(folder, capsys):
    deep = folder / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    assert main(["validate", str(deep), str(folder / "cycle.csv")]) == 2
    one_line_error(capsys, "deep.json", "nested too deeply")
    text = (folder / "model.json").read_text().replace('"capacity_ah": 2.9', '"capacity_ah": NaN')
    (folder / "nan.json").write_text(text)
    assert main(["validate", str(folder / "nan.json"), str(folder / "cycle.csv")]) == 2
    one_line_error(capsys, "nan.json", "capacity_ah")


def test_a_folder_given_as_the_config_is_one_line(folder, capsys):
    """Before: IsADirectoryError traceback."""
    for command in ("build", "fit", "diagnose"):
        assert main([command, str(folder), "-q"]) == 2
        one_line_error(capsys, str(folder), "folder")


def test_a_config_that_is_not_utf8_is_one_line(folder, capsys):
    """Before: UnicodeDecodeError traceback."""
    cfg = folder / "latin.toml"
    cfg.write_bytes('[cell]\ncapacity_ah = 2.9   # 25 °C\n'.encode("latin-1"))
    assert main(["build", str(cfg), "-q"]) == 2
    one_line_error(capsys, "latin.toml", "UTF-8")


def test_a_csv_with_cr_only_line_ends_reads_as_any_other(folder, capsys):
    """Before: _csv.Error traceback ("new-line character seen in unquoted field")."""
    (folder / "mac.csv").write_text("\r".join(cycle_lines(folder)) + "\r", newline="")
    assert main(["validate", str(folder / "model.json"), str(folder / "mac.csv"), "--json"]) == 0
    mac = json.loads(capsys.readouterr().out)
    assert main(["validate", str(folder / "model.json"), str(folder / "cycle.csv"), "--json"]) == 0
    assert mac["mae_v"] == json.loads(capsys.readouterr().out)["mae_v"]


def test_a_binary_file_given_as_a_csv_is_one_line(folder, capsys):
    data = np.random.default_rng(3).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    (folder / "bin.csv").write_bytes(data)
    assert main(["validate", str(folder / "model.json"), str(folder / "bin.csv")]) == 2
    one_line_error(capsys, "bin.csv", "binary")


@pytest.mark.parametrize("change, words", [
    (lambda ls: ls[:5] + [ls[5].replace(".", "_", 1)] + ls[6:], "not a number"),  # "1_0"
    (lambda ls: [ls[0]] + ["5" + l[l.index(","):] for l in ls[1:40]], "does not advance"),
    (lambda ls: [ls[0] + ",temperature_c"] + [l + ",1e30" for l in ls[1:]], "temperature"),
    (lambda ls: [ls[0] + ",temperature_c"] + [l + ",-500" for l in ls[1:]], "temperature"),
    (lambda ls: [ls[0] + ",temperature_c"] + [l + ",298.15" for l in ls[1:]], "kelvin"),
])
def test_implausible_measurements_are_one_line(folder, capsys, change, words):
    """Before: "1_0" read as 10 A, all-equal time stamps and temperatures of 1e30 or
    -500 degC passed."""
    (folder / "odd.csv").write_text("\n".join(change(cycle_lines(folder))) + "\n")
    assert main(["validate", str(folder / "model.json"), str(folder / "odd.csv")]) == 2
    one_line_error(capsys, "odd.csv", words)


@pytest.mark.parametrize("option", [["--soc0", "nan"], ["--soc0", "inf"], ["--soc0", "1.5"],
                                    ["--temperature-c", "nan"], ["--temperature-c", "300"],
                                    ["--window-s", "0", "inf"]])
def test_numeric_options_are_range_checked(folder, capsys, option):
    """Before: `validate --soc0 nan` printed "MAE nan mV", exit 0."""
    assert main(["validate", str(folder / "model.json"), str(folder / "cycle.csv"),
                 *option]) == 2
    one_line_error(capsys, option[0])


def test_validate_json_is_valid_json_when_a_figure_has_no_value(folder, capsys):
    """Before: a cycle that never rises above 10 % SOC printed a bare NaN (invalid JSON)."""
    from ecmgen.data.measure import TimeSeries, write_timeseries_csv
    from ecmgen.model.model import load_model
    from ecmgen.model.simulate import simulate

    model = load_model(folder / "model.json")
    t = np.arange(0.0, 600.0)
    i = np.where(t < 60, 0.0, -0.5)
    write_timeseries_csv(TimeSeries(t, i, simulate(model, t, i, 0.08).voltage_v),
                         folder / "low.csv")
    assert main(["validate", str(folder / "model.json"), str(folder / "low.csv"), "--json",
                 "--soc0", "0.08"]) == 0
    out = capsys.readouterr().out
    doc = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert doc["soc_above_10"]["mae_v"] is None and math.isfinite(doc["mae_v"])


def test_plot_into_a_missing_folder_makes_it(folder, capsys):
    """Before: FileNotFoundError traceback after the validation."""
    plot = folder / "plots" / "deeper" / "v.png"
    assert main(["validate", str(folder / "model.json"), str(folder / "cycle.csv"),
                 "--plot", str(plot)]) == 0
    assert plot.read_bytes()[:4] == b"\x89PNG"


def test_fixed_point_codegen_of_tiny_resistances_is_not_a_traceback(folder, capsys):
    """Before: R = 1e-300 in both tables' r0 (or r_fast, r_slow) raised OverflowError
    choosing the fixed-point format (log2 of an infinite ratio); validate took the model.
    Such a column is zero in the fixed point now: validate and codegen both take it."""
    for field in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
        def tiny(doc, field=field):
            for d in ("charge", "discharge"):
                doc["rc"][d][field] = [[1e-300] * 11]

        bad = edited_model(folder, tiny)
        assert main(["codegen", str(bad), "--out", str(folder / field), "--numeric", "fixed",
                     "-q"]) == 0, capsys.readouterr().err
        assert main(["validate", str(bad), str(folder / "cycle.csv")]) == 0


def test_the_boundary_names_the_file_and_keeps_faults_of_ecmgen_apart(folder, capsys,
                                                                     monkeypatch):
    """An exception raised while a user's file is read becomes the one line naming the
    file (with the exception's kind, so that it can be traced); one raised anywhere else
    is a fault of ecmgen and keeps its traceback."""
    import ecmgen.data.measure as measure

    def broken(path, *a, **k):
        raise KeyError("an unforeseen problem")

    monkeypatch.setattr(measure, "_read_csv", broken)
    assert main(["validate", str(folder / "model.json"), str(folder / "cycle.csv")]) == 2
    one_line_error(capsys, "cycle.csv", "KeyError", "unforeseen")

    import ecmgen.model.simulate as simulate

    monkeypatch.undo()
    monkeypatch.setattr(simulate, "validate", lambda *a, **k: {}["a fault"])
    with pytest.raises(KeyError):
        main(["validate", str(folder / "model.json"), str(folder / "cycle.csv")])


def test_codegen_errors_name_the_model_file(folder, capsys):
    """Before: a model the C cannot represent was refused without naming the file."""
    def many_points(doc):
        t = doc["rc"]["charge"]
        n = 300
        t["soc"] = list(np.linspace(0.0, 1.0, n))
        for k in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s",
                  "fit_error"):
            t[k] = [[t[k][0][0]] * n]
        t["converged"] = [[True] * n]

    bad = edited_model(folder, many_points)
    assert main(["validate", str(bad), str(folder / "cycle.csv")]) == 0   # a model, still
    capsys.readouterr()
    assert main(["codegen", str(bad), "--out", str(folder / "c"), "-q"]) == 2
    one_line_error(capsys, str(bad), "at most 255")
    assert main(["codegen", str(folder / "model.json"), "--out", str(folder / "c"),
                 "--dt-s", "0", "-q"]) == 2
    one_line_error(capsys, "--dt-s")


def test_a_flipped_current_sign_is_named_as_the_cause(folder, capsys):
    """Before: the only notes blamed the start SOC and cell.capacity_ah (a SOC running to
    1.42) and reported a 2-sample "lag"."""
    lines = cycle_lines(folder)
    rows = [lines[0]] + [f"{t},{-float(i)!r},{v}" for t, i, v in (r.split(",") for r in lines[1:])]
    (folder / "flip.csv").write_text("\n".join(rows) + "\n")
    assert main(["validate", str(folder / "model.json"), str(folder / "flip.csv"), "--json"]) == 0
    warns = json.loads(capsys.readouterr().out)["warnings"]
    assert len(warns) == 1 and "sign looks flipped" in warns[0]
    assert "current_sign" in warns[0] and "capacity_ah" not in warns[0]
    assert main(["validate", str(folder / "model.json"), str(folder / "cycle.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == []


def test_a_record_of_another_cell_is_said_to_be_one(folder, capsys):
    """Before: a model of another cell validated with exit 0 and only an indirect SOC
    warning. Here the record is of a cell with half the capacity and an OCV 0.3 V lower."""
    from dataclasses import replace

    from ecmgen.data.measure import TimeSeries, write_timeseries_csv
    from ecmgen.model.model import OcvTable, load_model
    from ecmgen.model.simulate import simulate

    model = load_model(folder / "model.json")
    other = replace(model, capacity_ah=model.capacity_ah / 2,
                    ocv=OcvTable(model.ocv.soc, model.ocv.ocv_v[0] - 0.3))
    t = np.arange(0.0, 2400.0)
    i = np.where((t > 60) & (t % 120 < 90), -2.0, 0.0)
    write_timeseries_csv(TimeSeries(t, i, simulate(other, t, i, 0.95).voltage_v),
                         folder / "other.csv")
    assert main(["validate", str(folder / "model.json"), str(folder / "other.csv"),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["mae_v"] > 0.15
    assert any("another cell" in w for w in doc["warnings"]), doc["warnings"]


def test_diagnose_cycle_naming_a_missing_file_is_one_line(folder, capsys):
    """[diagnose] cycle (the record to diagnose on) must exist, like judge."""
    cfg = folder / "d.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "ocv.csv"\n[diagnose]\ncycle = "nope.csv"\n')
    assert main(["diagnose", str(cfg), "--out", str(folder / "out"), "-q"]) == 2
    one_line_error(capsys, "d.toml", "diagnose.cycle names a missing file: nope.csv")
    assert not (folder / "out").exists()
