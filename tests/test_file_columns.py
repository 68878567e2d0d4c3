"""A file's own column map: a [[data.pulse_tests]] entry's ``columns`` (its file and
steps) and ``[data.columns.files."NAME"]`` (any file of the config), over [data.columns]
and the role's table key by key, so that a headerless export and headered ones build
together without a converted file; and every file's map checked on its first lines
before any fitting (a wrong map used to be said 15 s into a Leaf build, after the fits).
"""

from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, need
from ecmgen.cli import main
from ecmgen.config import load_config
from ecmgen.data.measure import read_timeseries
from ecmgen.data.sources import check_column_maps, read_series
from ecmgen.errors import InputError
from test_outputs import one_line_error

LEAF = SHARED_DATA / "nissan-leaf"
LEAF_40 = "NissanLeaf-cell-Low-Current-HPPC-40C-1.csv"
LEAF_25 = "NissanLeaf-cell-Low-Current-HPPC-25C-2.csv"
# the Bitrode export's columns by position (its SOURCE.md): Time(s) 2, Current(A) 9,
# Voltage(V) 10, Capacity(Ah) 12; text in 1 and 14
BITRODE = "{header = false, time = 2, current = 9, voltage = 10, charge = 12}"
FIELDS = ("time_s", "current_a", "voltage_v", "temperature_c", "charge_ah")


def headerless(src: Path, dst: Path) -> Path:
    dst.write_text("".join(src.read_text().splitlines(keepends=True)[1:]))
    return dst


def leaf_config(tmp_path: Path, columns: str = BITRODE, extra: str = "", tables: str = ""
                ) -> Path:
    """Both Leaf HPPC tests, the 40 degC one as a headerless copy with ``columns``;
    ``extra``: more [data] keys, ``tables``: more tables at the end."""
    copy = headerless(need(LEAF / LEAF_40), tmp_path / "hppc-40-noheader.csv")
    cfg = tmp_path / "leaf.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 32.5\n[data]\nocv = "pulses"\n{extra}'
                   f'[[data.pulse_tests]]\nfile = "{LEAF / LEAF_25}"\ntemperature_c = 25\n'
                   f'[[data.pulse_tests]]\nfile = "{copy.name}"\ntemperature_c = 40\n'
                   f'columns = {columns}\n{tables}')
    return cfg


def same_series(a, b) -> bool:
    return all((getattr(a, f) is None and getattr(b, f) is None) or
               np.array_equal(getattr(a, f), getattr(b, f)) for f in FIELDS)


def test_a_headerless_leaf_test_beside_a_headered_one_reads_as_the_original(tmp_path):
    cfg = load_config(leaf_config(tmp_path))
    check_column_maps(cfg)
    headered, copy = (read_series(cfg, t.file, "pulses") for t in cfg.pulse_tests)
    original = read_timeseries(LEAF / LEAF_40)
    assert same_series(copy, replace(original, temperature_c=np.full(len(original), 40.0)))
    assert any("Bitrode" in n for n in headered.notes)      # recognised by its names


def test_a_headerless_and_a_headered_pulse_test_build_together(cell_files, tmp_path):
    """Two pulse tests of one synthetic cell, the second as a headerless export with its
    own columns: the model is the one from two headered files (bytes, but for the file
    names it records)."""
    pulses = (cell_files / "pulses.csv").read_text()
    (tmp_path / "a.csv").write_text(pulses)
    (tmp_path / "b.csv").write_text(pulses)
    headerless(tmp_path / "a.csv", tmp_path / "b-noheader.csv")
    head = (f'[cell]\ncapacity_ah = 2.9\n[data]\nocv = "{cell_files / "ocv.csv"}"\n'
            '[[data.pulse_tests]]\nfile = "a.csv"\ntemperature_c = 25\nsoc0 = 0.9\n'
            '[[data.pulse_tests]]\ntemperature_c = 35\nsoc0 = 0.9\n')
    tail = '[fit]\nmethods = ["lm"]\n[model]\nwarm_row_c = false\n'
    (tmp_path / "plain.toml").write_text(head + 'file = "b.csv"\n' + tail)
    (tmp_path / "mixed.toml").write_text(
        head + 'file = "b-noheader.csv"\ncolumns = {header = false, time = 1, current = 2, '
        'voltage = 3, charge = 4}\n' + tail)
    for name in ("plain", "mixed"):
        assert main(["fit", str(tmp_path / f"{name}.toml"), "--out",
                     str(tmp_path / f"{name}.json"), "-q"]) == 0
    plain, mixed = ((tmp_path / f"{n}.json").read_text() for n in ("plain", "mixed"))
    sha = {n: hashlib.sha256((tmp_path / n).read_bytes()).hexdigest()
           for n in ("b.csv", "b-noheader.csv")}
    assert mixed.replace("b-noheader.csv", "b.csv").replace(
        sha["b-noheader.csv"], sha["b.csv"]) == plain


def test_a_files_table_maps_one_validation_file(cell_files, tmp_path):
    cycle = cell_files / "cycle.csv"
    headerless(cycle, tmp_path / "cycle-noheader.csv")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "{cell_files / "pulses.csv"}"\n'
                   f'ocv = "{cell_files / "ocv.csv"}"\ncycle = "{cycle}"\n'
                   'extra_cycles = ["cycle-noheader.csv"]\n'
                   '[data.columns.files."cycle-noheader.csv"]\n'
                   'header = false\ntime = 1\ncurrent = 2\nvoltage = 3\n')
    config = load_config(cfg)
    check_column_maps(config)
    assert same_series(read_series(config, tmp_path / "cycle-noheader.csv", "extra_cycles"),
                       read_series(config, cycle, "cycle"))


# --------------------------------------------------------------------------- refused early

@pytest.fixture
def no_fitting(monkeypatch):
    """Any fit started fails the test: the map must be refused before."""
    import ecmgen.pipeline as pipeline

    def fit(*args, **kwargs):
        raise AssertionError("a fit started before the column maps were checked")

    monkeypatch.setattr(pipeline, "fit_pulse_tests", fit)
    monkeypatch.setattr(pipeline, "prepare", fit)


@pytest.mark.parametrize("columns, extra, words", [
    # a position on the Power column: its 0 W rows are no voltage
    (BITRODE.replace("voltage = 10", "voltage = 11"), "", ["column 11", "voltage 0 V"]),
    # the Mode column's text mapped as the temperature
    (BITRODE.replace("charge = 12", "charge = 12, temperature = 14"), "",
     ["temperature = 14", "'REST'"]),
    (BITRODE.replace("voltage = 10", "voltage = 40"), "", ["voltage = 40", "has 16 columns"]),
    (BITRODE.replace("header = false, ", ""), "", ["no header line", "header = false"]),
    (BITRODE.replace("voltage = 10", 'voltage = 10, voltage_unit = "mV"'), "",
     ["V declared as mV"]),
    # a wrong name for a validation file that is read only after the fits
    (BITRODE, f'cycle = "{LEAF / "NissanLeaf-cell-Cycling-10C-24C-40C.csv"}"\n',
     ["missing column 'Current (A)'"]),
])
def test_a_wrong_map_is_one_line_before_any_fitting(tmp_path, capsys, no_fitting, columns,
                                                    extra, words):
    cfg = leaf_config(tmp_path, columns, extra, '[data.columns.cycle]\ntime = "Time(s)"\n'
                      'current = "Current (A)"\nvoltage = "Voltage(V)"\n')
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "-q"]) == 2
    one_line_error(capsys, *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("columns, words", [
    ("{header = false, time = 2, curent = 9, voltage = 10}", ["curent", "did you mean"]),
    ("{header = false, time = 2, current = 9}", ["missing key 'voltage'"]),
    ('"hppc.csv"', ["columns must be a table"]),
])
def test_a_bad_columns_table_is_one_line(tmp_path, capsys, columns, words):
    cfg = leaf_config(tmp_path, columns)
    assert main(["build", str(cfg), "--out", str(tmp_path / "out"), "-q"]) == 2
    one_line_error(capsys, str(cfg), *words)


def test_a_files_table_naming_no_file_of_the_config_is_refused(tmp_path, capsys):
    cfg = leaf_config(tmp_path, tables='[data.columns.files."nope.csv"]\ntime = 1\n')
    with pytest.raises(InputError, match="names a missing file: nope.csv"):
        load_config(cfg)
