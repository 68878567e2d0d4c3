"""A user's own files: headerless CSVs read by column position, a
per-role column mapping that extends the global one (and covers extra_cycles and judge),
``ecmgen dcir --config``, both names of both current-sign conventions, layouts named by
what they match, a time window for validation files, ``-q`` everywhere, and no Python
warning reaching the user."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import CALCE, REPO, make_pulse_test, need, synthetic_nca_model
from ecmgen.cli import main
from ecmgen.config import load_config
from ecmgen.data.measure import ColumnMap, TimeSeries, read_timeseries, write_timeseries_csv
from ecmgen.errors import InputError
from ecmgen.pipeline import read_series
from test_measure import assert_one_line_error


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO)


def write_bitrode_like(series: TimeSeries, path: Path, *, discharge_positive=True,
                       header: str | None = None) -> Path:
    """A cycler export in the Leaf/Bitrode shape: ten columns, time in the 2nd, current in
    the 9th (discharge positive unless told), voltage in the 10th; no header line unless
    ``header`` is given."""
    n = len(series)
    sign = -1.0 if discharge_positive else 1.0
    ah = series.coulomb_ah()
    cols = [np.arange(1, n + 1), series.time_s, np.ones(n), np.ones(n), series.time_s,
            sign * ah, sign * ah * 3.7, np.full(n, 25.0), sign * series.current_a,
            series.voltage_v]
    lines = [] if header is None else [header]
    lines += [",".join(f"{c[k]:.10g}" for c in cols) for k in range(n)]
    path.write_text("\n".join(lines) + "\n")
    return path


LEAF_MAP = dict(time=2, current=9, voltage=10, header=False,
                current_sign="discharge_positive")


@pytest.fixture(scope="module")
def cell():
    truth = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=60.0)
    series, _ = make_pulse_test(truth, soc_levels=(0.9, 0.5), c_rates=(1.0, 3.0),
                                rest_s=600.0)
    t = np.arange(0, 1200.0, 1.0)
    rng = np.random.default_rng(1)
    i = np.repeat(rng.uniform(-8, 2, t.size // 20), 20)
    i[:60] = 0.0
    from ecmgen.model.simulate import simulate

    cycle = TimeSeries(t, i, simulate(truth, t, i, 0.9).voltage_v, source="cycle")
    return truth, series, cycle


def _small(series: TimeSeries, n=50) -> TimeSeries:
    return series.slice(0, n)


# --------------------------------------------------------------------------- headerless CSV

def test_headerless_csv_read_by_position(tmp_path, cell):
    _, series, _ = cell
    path = write_bitrode_like(series, tmp_path / "leaf-hppc.csv")
    ts = read_timeseries(path, ColumnMap(**LEAF_MAP), capacity_ah=2.9)
    assert len(ts) == len(series)
    np.testing.assert_allclose(ts.time_s, series.time_s, rtol=1e-9)
    np.testing.assert_allclose(ts.current_a, series.current_a, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ts.voltage_v, series.voltage_v, rtol=1e-9)
    assert any("negated" in n for n in ts.notes)


def test_positions_also_work_under_a_header(tmp_path, cell):
    path = write_bitrode_like(_small(cell[1]), tmp_path / "h.csv",
                              header="Rec,Total Time,Cycle,Loop,Step Time,Ah,Wh,Temp,Amps,Volts")
    ts = read_timeseries(path, ColumnMap(time=2, current="Amps", voltage=10,
                                         current_sign="charge_negative"))
    np.testing.assert_allclose(ts.current_a, _small(cell[1]).current_a, atol=1e-12)


def test_headerless_csv_without_mapping_says_so(tmp_path, cell):
    """Before: 'columns not recognised (found: '1', '0', '1', ...)' -- data values listed
    as if they were column names."""
    path = write_bitrode_like(_small(cell[1]), tmp_path / "leaf.csv")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    msg = assert_one_line_error(exc, path, "no header line", "header = false", "time = 1")
    assert "found" not in msg


def test_headerless_csv_with_named_mapping_says_so(tmp_path, cell):
    path = write_bitrode_like(_small(cell[1]), tmp_path / "leaf.csv")
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap("Total Time", "Amps", "Volts"))
    msg = assert_one_line_error(exc, path, "no header line", "line 1", "header = false")
    assert "found:" not in msg


@pytest.mark.parametrize("mapping, words", [
    (dict(LEAF_MAP, voltage=12), ["voltage = 12", "has 10 columns"]),
    (dict(time=1, current=2, voltage=3, header=False), ["line 1", "holds names"]),
])
def test_positional_mapping_errors(tmp_path, cell, mapping, words):
    header = None if mapping.get("voltage") == 12 else "t,i,v,a,b,c,d,e,f,g"
    path = write_bitrode_like(_small(cell[1]), tmp_path / "x.csv", header=header)
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap(**mapping))
    assert_one_line_error(exc, path, *words)


def test_positional_cell_errors_name_the_position(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("0,0,3.7\n1,abc,3.7\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap(time=1, current=2, voltage=3, header=False))
    assert_one_line_error(exc, path, "column 2, row 2 (line 2)", "'abc'")


def test_positions_refused_for_mat_fields(tmp_path):
    import scipy.io

    path = tmp_path / "m.mat"
    scipy.io.savemat(path, {"meas": {"Time": np.arange(3.0), "Current": np.zeros(3),
                                     "Voltage": np.full(3, 3.7)}})
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap(time=1, current=2, voltage=3))
    assert_one_line_error(exc, path, "positions apply to CSV")


# --------------------------------------------------------------------------- current sign

@pytest.mark.parametrize("name, sign", [("charge_positive", 1), ("discharge_negative", 1),
                                        ("discharge_positive", -1), ("charge_negative", -1)])
def test_current_sign_accepts_both_names_of_both_conventions(tmp_path, name, sign):
    """Before: 'discharge_negative' and 'charge_negative' were refused."""
    path = tmp_path / "s.csv"
    path.write_text("t,i,v\n0,0,3.7\n1,-2,3.6\n2,-2,3.59\n")
    cols = ColumnMap.from_toml({"time": "t", "current": "i", "voltage": "v",
                                "current_sign": name}, "c.toml")
    ts = read_timeseries(path, cols)
    np.testing.assert_allclose(ts.current_a, [0, -2 * sign, -2 * sign])
    assert cols.current_sign in ("charge_positive", "discharge_positive")


# --------------------------------------------------------------------------- layout names

ARBIN_NAMES = "Test_Time(s),Current(A),Voltage(V)\n0,0,3.6\n1,-20,3.5\n2,-20,3.49\n"


def test_layout_named_by_what_it_matches(tmp_path):
    """A Bitrode (or any) export with Arbin-style names is not called 'Arbin layout'."""
    path = tmp_path / "bitrode-export.csv"
    path.write_text(ARBIN_NAMES)
    ts = read_timeseries(path)
    note = ts.notes[0]
    assert "Arbin/CALCE-style columns (Test_Time(s), Current(A), Voltage(V))" in note
    assert "positive on charge" in note
    assert "Arbin layout" not in note


def test_nearly_matching_layout_names_what_is_missing(tmp_path):
    path = tmp_path / "b.csv"
    path.write_text("Test_Time(s),Current(A),Volts\n0,0,3.6\n1,-2,3.5\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    msg = assert_one_line_error(exc, path, "missing column 'Voltage(V)'", "Arbin/CALCE-style",
                         "[data.columns]")
    assert "Arbin layout" not in msg


# --------------------------------------------------------------------------- per-role mapping

def _project(tmp_path: Path, cell, columns: str, *, extra: str = "") -> Path:
    """A config over Leaf-like headerless files: pulses, a cycle and an extra cycle, and
    the cell's OCV table (the headerless pulse file has no Ah column, so its rests, with
    the SOC moves left out of the record, cannot give an OCV)."""
    truth, series, cycle = cell
    write_bitrode_like(series, tmp_path / "hppc.csv")
    write_bitrode_like(cycle, tmp_path / "cycle1.csv")
    write_bitrode_like(cycle, tmp_path / "cycle2.csv")
    np.savetxt(tmp_path / "ocv.csv", np.column_stack([truth.ocv.soc, truth.ocv.ocv_v[0]]),
               delimiter=",", header="soc,ocv_v", comments="")
    cfg = tmp_path / "leaf.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "hppc.csv"\n'
                   'pulses_soc0 = 1.0\nocv = "ocv.csv"\ncycle = "cycle1.csv"\n'
                   'extra_cycles = ["cycle2.csv"]\n' + extra + columns)
    return cfg


GLOBAL_LEAF = ('[data.columns]\nheader = false\ntime = 2\ncurrent = 9\nvoltage = 10\n'
               'current_sign = "discharge_positive"\n')


def test_per_role_mapping_extends_the_global_one(tmp_path, cell):
    """Before: any [data.columns.<role>] table made the global keys silently ignored, so
    this config read the cycle with the default names (and failed on the pulses)."""
    cfg = load_config(_project(tmp_path, cell, GLOBAL_LEAF +
                               '[data.columns.cycle]\ncurrent_sign = "charge_positive"\n'))
    pulses = read_series(cfg, cfg.pulses, "pulses")
    np.testing.assert_allclose(pulses.current_a, cell[1].current_a, atol=1e-12)
    cyc = read_series(cfg, cfg.cycle, "cycle")           # global names, its own sign
    np.testing.assert_allclose(cyc.current_a, -cell[2].current_a, atol=1e-12)


def test_cycle_mapping_covers_extra_cycles_and_judge(tmp_path, cell):
    """Before: extra_cycles ignored [data.columns.cycle] (read with the default names)."""
    cfg = load_config(_project(tmp_path, cell, '[data.columns.cycle]\n' +
                               GLOBAL_LEAF.split("\n", 1)[1] + '[data.columns.pulses]\n' +
                               GLOBAL_LEAF.split("\n", 1)[1]))
    for role in ("extra_cycles", "judge"):
        s = read_series(cfg, cfg.extra_cycles[0], role)
        np.testing.assert_allclose(s.current_a, cell[2].current_a, atol=1e-12)


def test_extra_cycles_mapping_of_its_own_wins(tmp_path, cell):
    _, _, cycle = cell
    cfg_path = _project(tmp_path, cell, GLOBAL_LEAF +
                        '[data.columns.extra_cycles]\ntime = "t"\ncurrent = "i"\n'
                        'voltage = "v"\nheader = true\ncurrent_sign = "charge_positive"\n')
    (tmp_path / "cycle2.csv").write_text(
        "t,i,v\n" + "\n".join(f"{a!r},{b!r},{c!r}" for a, b, c in
                              zip(cycle.time_s.tolist(), cycle.current_a.tolist(),
                                  cycle.voltage_v.tolist())) + "\n")
    cfg = load_config(cfg_path)
    s = read_series(cfg, cfg.extra_cycles[0], "extra_cycles")
    np.testing.assert_array_equal(s.current_a, cycle.current_a)


def test_global_mapping_skips_mat_files_but_a_role_table_applies(tmp_path):
    import scipy.io

    mat = tmp_path / "p.mat"
    scipy.io.savemat(mat, {"meas": {"Time": np.arange(3.0), "Current": np.array([0, -1, -1.0]),
                                    "Voltage": np.full(3, 3.7), "I_ma": np.array([0, 1e3, 1e3])}})
    glob = {"time": 1, "current": 2, "voltage": 3, "header": False}
    assert ColumnMap.for_file(glob, ("pulses",), "c.toml", mat) is None
    cols = ColumnMap.for_file({"pulses": {"time": "Time", "current": "I_ma", "voltage": "Voltage",
                                          "current_unit": "mA",
                                          "current_sign": "discharge_positive"}},
                              ("pulses",), "c.toml", mat)
    np.testing.assert_allclose(read_timeseries(mat, cols).current_a, [0, -1, -1])


def test_merged_mapping_errors_name_both_tables(tmp_path):
    with pytest.raises(InputError) as exc:
        ColumnMap.for_file({"current": "i", "cycle": {"voltage": "v"}}, ("cycle",),
                           Path("c.toml"), tmp_path / "x.csv")
    assert_one_line_error(exc, "c.toml", "[data.columns.cycle] with [data.columns]", "'time'")


# --------------------------------------------------------------------------- ecmgen dcir --config

def test_dcir_with_config_reads_the_mapped_file(tmp_path, cell, capsys):
    """Before: `ecmgen dcir` had no --config, so a headerless or renamed file could not be
    read at all, and the capacity had to be repeated."""
    from ecmgen.pipeline import prepare

    cfg_path = _project(tmp_path, cell, GLOBAL_LEAF)
    assert main(["dcir", "--config", str(cfg_path), "-q"]) == 0
    out = capsys.readouterr()
    assert out.err == ""
    assert out.out == prepare(load_config(cfg_path)).dcir.to_csv_text()
    rows = out.out.strip().split("\n")
    assert rows[0] == "soc,direction,c_rate,t_s,r_ohm" and len(rows) == 1 + 4 * 5
    # the file may also be given, the options override the config
    out_csv = tmp_path / "d.csv"
    assert main(["dcir", str(tmp_path / "hppc.csv"), "--config", str(cfg_path),
                 "--times", "1", "2", "5", "10", "--out", str(out_csv), "-q"]) == 0
    assert out_csv.read_text().count("\n") == 1 + 4 * 4


def test_dcir_without_config_or_capacity_is_one_line(tmp_path, cell, capsys):
    path = write_timeseries_csv(cell[1], tmp_path / "p.csv")
    assert main(["dcir", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"ecmgen: error: {path}: ")
    assert "--capacity-ah" in err and "--config" in err


def test_dcir_config_with_a_dcir_table_only(tmp_path, capsys):
    (tmp_path / "d.csv").write_text("soc,direction,t_s,r_ohm\n0.5,discharge,1,0.02\n")
    (tmp_path / "o.csv").write_text("soc,ocv_v\n0,3.0\n1,4.2\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\ndcir = "d.csv"\nocv = "o.csv"\n')
    assert main(["dcir", "--config", str(cfg)]) == 2
    assert "no data.pulses" in capsys.readouterr().err


# --------------------------------------------------------------------------- time windows

def test_window_cuts_a_record():
    t = np.arange(0.0, 100.0)
    s = TimeSeries(t, np.zeros(100), np.full(100, 3.7), source="f.csv")
    w = s.window(10.0, 19.5)
    np.testing.assert_array_equal(w.time_s, np.arange(10.0, 20.0))
    assert "time window 10 .. 19.5 s" in w.notes[-1]
    for t0, t1, words in ((20, 10, ["start must come before"]), (200, 300, ["outside"]),
                          (10.2, 10.7, ["holds 0 samples"])):
        with pytest.raises(InputError) as exc:
            s.window(t0, t1)
        assert_one_line_error(exc, "f.csv", "time window", *words)


def test_cycle_window_in_config_applies_to_cycle_and_extra_cycles(tmp_path, cell):
    """Before: a validation file could not be cut to a window."""
    cfg = load_config(_project(tmp_path, cell, GLOBAL_LEAF, extra="cycle_window_s = [100, 500]\n"))
    assert cfg.window_for(cfg.cycle) == (100.0, 500.0)
    for path, role in ((cfg.cycle, "cycle"), (cfg.extra_cycles[0], "extra_cycles")):
        s = read_series(cfg, path, role)
        assert s.time_s[0] == 100.0 and s.time_s[-1] == 500.0
    assert len(read_series(cfg, cfg.pulses, "pulses")) == len(cell[1])   # not the pulses
    cfg = load_config(_project(tmp_path, cell, GLOBAL_LEAF,
                               extra='cycle_window_s = {"cycle2.csv" = [0, 300]}\n'))
    assert len(read_series(cfg, cfg.cycle, "cycle")) == len(cell[2])
    assert read_series(cfg, cfg.extra_cycles[0], "extra_cycles").time_s[-1] == 300.0


@pytest.mark.parametrize("window, words", [
    ("[500, 100]", ["data.cycle_window_s = [500, 100]", "start must come before"]),
    ("[1, 2, 3]", ["data.cycle_window_s must be [t0, t1]"]),
    ('{"nope.csv" = [0, 1]}', ["missing file: nope.csv"]),
])
def test_bad_cycle_window_in_config(tmp_path, cell, window, words):
    cfg = _project(tmp_path, cell, GLOBAL_LEAF, extra=f"cycle_window_s = {window}\n")
    with pytest.raises(InputError) as exc:
        load_config(cfg)
    assert_one_line_error(exc, cfg, *words)


def test_cycle_window_outside_the_file_stops_the_build(tmp_path, cell, capsys):
    cfg = _project(tmp_path, cell, GLOBAL_LEAF, extra="cycle_window_s = [5000, 6000]\n")
    out = tmp_path / "out"
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots", "--no-c"]) == 2
    err = capsys.readouterr().err
    assert err == (f"ecmgen: error: {tmp_path / 'cycle1.csv'}: time window [5000, 6000] s "
                   f"lies outside the record (the record runs from 0 to 1199 s)\n")
    assert not out.exists()


def test_validate_window_option(tmp_path, cell, synthetic_model, capsys):
    from ecmgen.model.simulate import validate

    truth, _, cycle = cell
    truth.save(tmp_path / "model.json")
    path = write_timeseries_csv(cycle, tmp_path / "cycle.csv")
    assert main(["validate", str(tmp_path / "model.json"), str(path), "--window-s", "300",
                 "900", "--soc0", "0.85", "--json", "-q"]) == 0
    got = json.loads(capsys.readouterr().out)
    want = validate(truth, read_timeseries(path).window(300, 900), 0.85)
    assert got["mae_v"] == pytest.approx(want.overall.mae_v, rel=1e-12)
    assert main(["validate", str(tmp_path / "model.json"), str(path), "--window-s", "9",
                 "3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "start must come before the end" in err


# --------------------------------------------------------------------------- quiet, warnings

@pytest.mark.parametrize("command", ["build", "dcir", "fit", "validate", "codegen",
                                     "diagnose"])
def test_every_command_takes_dash_q(command):
    """Before: `-q` was an unknown argument."""
    from ecmgen.cli import parser

    sub = parser()._subparsers._group_actions[0].choices[command]
    assert "-q" in sub._option_string_actions


def test_point_rows_with_an_unreached_time_does_not_warn():
    """Before: 'RuntimeWarning: Mean of empty slice' for every DC-IR time that no pulse of
    a SOC level reached (a slow logger, short pulses: the A123 builds)."""
    from ecmgen.data.dcir import DcirTable
    from ecmgen.fit.points import five_point_rows

    r = np.array([[0.020, np.nan, 0.024], [0.021, np.nan, np.nan], [0.030, 0.031, 0.032]])
    table = DcirTable(np.array([0.5, 0.5, 0.2]), np.array(["discharge"] * 3),
                      np.array([1.0, 1.0, 1.0]), np.array([1.0, 3.0, 10.0]), r)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rows, _ = five_point_rows(table, "all")
        best, notes = five_point_rows(table, "max")
    np.testing.assert_allclose(rows.soc, [0.5, 0.2])      # levels from the top
    np.testing.assert_allclose(rows.r_ohm[0], [0.0205, np.nan, 0.024])
    np.testing.assert_allclose(rows.r_ohm[1], [0.030, 0.031, 0.032])
    # "max" takes complete rows only: the 0.5 level has none and is named
    np.testing.assert_allclose(best.soc, [0.2])
    assert any("no complete pulse at SOC 0.500" in n for n in notes)


def test_cli_keeps_remaining_warnings_off_stderr(monkeypatch, capsys, tmp_path):
    import ecmgen.cli as cli
    import ecmgen.cli.commands as commands

    def noisy(args):
        warnings.warn("something numerical", RuntimeWarning)
        return 0

    monkeypatch.setattr(commands, "cmd_codegen", noisy)     # parser() binds it per call
    monkeypatch.setattr(sys, "warnoptions", [])
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert cli.main(["codegen", "m.json", "--out", str(tmp_path)]) == 0
    assert seen == [] and capsys.readouterr().err == ""
    monkeypatch.setattr(sys, "warnoptions", ["default"])   # a developer asked to see them
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        cli.main(["codegen", "m.json", "--out", str(tmp_path)])
    assert [str(w.message) for w in seen] == ["something numerical"]


A123_CONFIG = """[cell]
capacity_ah = 1.1
[data]
pulses = "{d}/dynamics-dst-us06-fuds.csv"   # its 1.1 A discharge (1 C, 1370 s) from rest
ocv = "{d}/ocv-charge-c22.csv"              # the C/22 charge branch (another cell)
cycle = "{d}/dynamics-dst-us06-fuds.csv"
[dcir]
min_rest_s = 4
max_pulse_s = 1500
"""


@pytest.mark.slow
def test_a123_build_quiet_json_has_empty_stderr(tmp_path):
    """The CALCE A123 cell: with the 5 s logger's DC-IR times the build succeeds with
    nothing at all on stderr; so it does with the default times, the times before the
    first 5 s sample taking its R and the one left without a value said in notes (first:
    numpy's 'Mean of empty slice' warning, then an error naming no file; then one line,
    'no SOC level has an R(t) value at every [dcir] times_s')."""
    d = need(CALCE)
    cfg = tmp_path / "a123.toml"
    cfg.write_text(A123_CONFIG.format(d=d) + "times_s = [5, 20, 60, 200, 600]\n")
    r = run_cli("build", cfg, "--out", tmp_path / "out", "-q", "--json")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert json.loads(r.stdout)["c"]["float"]["bit_exact_vs_reference"] is True

    cfg.write_text(A123_CONFIG.format(d=d))
    r = run_cli("build", cfg, "--out", tmp_path / "out2", "-q", "--json")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    r = run_cli("build", cfg, "--out", tmp_path / "out3")
    assert r.returncode == 0 and "more notes: see" in r.stderr     # counted on the terminal
    report = (tmp_path / "out3" / "report.md").read_text()           # listed in the report
    assert "- DC-IR time 3 s comes before the first sample after the edge (5 s" in report
    assert "- DC-IR time 6 s: no pulse has a value there; the fits use the other 4" in report
