"""Cyclers' own files (ecmgen.data.native): Neware .nda / .ndax through NewareNDA,
BioLogic .mpr and Arbin .res through galvani, chosen by extension wherever a measurement
is read.

The three real Neware records in ../shared/data/cycler-samples/neware/ (NewareNDA's own
test files) are checked against what NewareNDA documents and its tests hold: voltage in
V and current in mA (its test compares them with the BTSDA export's mV / 1000 and
uA / 1000, BTSDA's own sign: discharge negative), ``Time`` the step's clock, the Ah
counters split into charge and discharge, in mAh. The independent checks here: the
current's sign against the cycler's step types (CC_DChg steps negative, the voltage
falling), the joined counters against the integral of the current, the joined step
clock against the wall-clock stamps. A record made here with its exact content known,
given to ecmgen as a Neware file, reads back the same as its CSV and validates alike.
"""

from __future__ import annotations

import json
import shutil
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, need
from ecmgen.cli import main
from ecmgen.data.measure import ColumnMap, read_timeseries
from ecmgen.data.native import INSTALL, read_native, step_time_joined
from ecmgen.errors import InputError
from test_measure import assert_one_line_error
from test_outputs import one_line_error

NEWARE = SHARED_DATA / "cycler-samples" / "neware"


def neware_file(name: str) -> Path:
    pytest.importorskip("NewareNDA", reason="the cyclers extra is not installed")
    return need(NEWARE / name)


def _reader_table(path: Path):
    """The table NewareNDA itself gives for ``path`` (its pandas deprecation warnings
    are not what these tests are about)."""
    import NewareNDA

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return NewareNDA.read(str(path))


def _status(path: Path) -> np.ndarray:
    """The cycler's step type per row."""
    return np.asarray(_reader_table(path)["Status"]).astype(str)


# --------------------------------------------------------------------------- real files

def test_neware_nda_cycling_record_reads_with_signs_and_units():
    path = neware_file("TestFile.nda")
    s = read_timeseries(path)
    table = _reader_table(path)
    status = _status(path)
    assert len(s) == status.size == 6670
    # this file's Time runs on over the test (nothing to join): the test clock as the file
    # holds it, which stands still in the two pauses where the wall clock jumps (by more
    # than a minute while Time moves by under a second: the note's "paused 2 times")
    time = np.asarray(table["Time"], dtype=float)
    assert np.array_equal(s.time_s, time) and np.all(np.diff(s.time_s) >= 0)
    wall = _wall_clock(path)
    assert np.sum((np.diff(wall) > 60.0) & (np.diff(time) < 1.0)) == 2
    # current in A, charge positive: the reader's mA / 1000 (its float32, to one rounding),
    # negative on the cycler's discharge steps (-3 A), positive on its CC charge (+1.2 A),
    # 0 at its rests
    f32 = float(np.finfo(np.float32).eps)
    ma = np.asarray(table["Current(mA)"], dtype=float)
    assert np.allclose(s.current_a, ma / 1000, rtol=f32, atol=0)
    dchg, chg = status == "CC_DChg", status == "CC_Chg"
    assert np.all(s.current_a[dchg] < 0) and np.all(s.current_a[chg] > 0)
    assert np.all(s.current_a[status == "Rest"] == 0.0)
    # voltage in V (the reader's field as it is), falling over every discharge step and
    # rising over every CC charge step
    assert np.array_equal(s.voltage_v, np.asarray(table["Voltage"], dtype=float))
    step = np.asarray(table["Step_Index"])
    for rows, sign in ((dchg, -1), (chg, 1)):
        for k in np.unique(step[rows]):
            v = s.voltage_v[rows & (step == k)]
            assert np.sign(v[-1] - v[0]) == sign, k
    # the counters (per step, charge and discharge apart) joined into one charge that
    # moves with the current: at every row within what the logged current leaves open
    # (half a sample's charge at every change of current, the rule between samples
    # unknown) and the float32 counters' rounding
    q = s.coulomb_ah()
    from ecmgen.data.counters import integrate_current
    i, t = s.current_a, s.time_s
    open_ah = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(i)) * np.diff(t) / 2 / 3600)))
    rounding = f32 * float(table["Discharge_Capacity(mAh)"].max()) / 1000
    assert np.all(np.abs(q - integrate_current(t, i)) <= open_ah + rounding)
    # the first discharge's end: the reader's Discharge_Capacity there (mAh)
    k = int(np.argmin(q))
    assert q[k] == pytest.approx(-table["Discharge_Capacity(mAh)"].iloc[k] / 1000, rel=f32)
    assert np.array_equal(s.temperature_c, np.asarray(table["T1"], dtype=float))  # degC
    notes = " ".join(s.notes)
    assert "Neware .nda" in notes and "paused 2 times" in notes and "restarts" in notes


def test_newer_nda_step_clock_is_joined_and_an_empty_channel_refused():
    """new_nda_file.nda is a channel with no cell (-0.09 V, +-0.05 mA): its reader's
    fields hold the sign and units, and ecmgen refuses the record in one line."""
    path = neware_file("new_nda_file.nda")
    record = read_native(path)
    stamps = _wall_clock(path)
    # Time restarts at every step (0 .. 5, 0 .. 25, ...): joined, it spans what the wall
    # clock spans (722 s, stamps to the second)
    assert record.fields["Time"][-1] == pytest.approx(stamps[-1], abs=1.0)
    assert np.all(np.diff(record.fields["Time"]) >= 0)
    status = _status(path)
    current = record.fields["Current(mA)"]
    assert np.all(current[status == "CC_Chg"] >= 0) and current.max() == pytest.approx(0.0505)
    assert np.all(current[status == "CC_DChg"] <= 0)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "field 'Voltage'", "-0.0911 V")


def _wall_clock(path: Path) -> np.ndarray:
    stamps = _reader_table(path)["Timestamp"]
    return (stamps - stamps.iloc[0]).dt.total_seconds().to_numpy()


def test_neware_ndax_rest_with_two_temperature_channels(tmp_path):
    path = neware_file("Unit27_Example_Data_File.ndax")
    s = read_timeseries(path)
    assert len(s) == 301 and s.time_s[0] == 0 and s.time_s[-1] == 300
    table = read_native(path).fields
    assert np.all(s.current_a == 0)
    assert np.array_equal(s.voltage_v, np.asarray(table["Voltage"], dtype=float))  # in V
    assert any("T1 (also logged: T2" in n for n in s.notes)
    # a column map names another channel, over the reader's names
    t2 = read_timeseries(path, ColumnMap(**read_native(path).columns | {"temperature": "T2"}))
    assert not np.array_equal(t2.temperature_c, s.temperature_c)
    assert np.array_equal(t2.temperature_c, np.asarray(table["T2"], dtype=float))


def test_a_config_maps_a_native_file_over_its_reader_names(cell_files, tmp_path):
    from ecmgen.config import load_config
    from ecmgen.data.sources import check_column_maps, read_series

    path = neware_file("Unit27_Example_Data_File.ndax")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[cell]\ncapacity_ah = 2.9\n[data]\npulses = "{cell_files / "pulses.csv"}"\n'
                   f'ocv = "{cell_files / "ocv.csv"}"\ncycle = "{path}"\n'
                   f'[data.columns.files."{path.name}"]\ntemperature = "T2"\n')
    config = load_config(cfg)
    check_column_maps(config)
    t2 = read_series(config, path, "cycle")
    assert np.array_equal(t2.temperature_c, read_native(path).fields["T2"])


def test_validate_runs_from_a_native_file(cell_files, capsys):
    path = neware_file("TestFile.nda")
    assert main(["validate", str(cell_files / "model.json"), str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.isfinite(out["mae_v"])


# --------------------------------------------------------------------------- known truth

def neware_frame(steps, dt_s=1.0):
    """A record as NewareNDA returns a Neware file of it: per step (current A, duration
    s) rows from the step's clock 0 to its end every ``dt_s`` (the step's first row at the
    instant the step before ended), Time the step's clock, current in mA, the charge and
    discharge counters in mAh from 0 in each step, float32 as NewareNDA stores them.
    Returns the frame and the truth: time s, current A, charge Ah."""
    pd = pytest.importorskip("pandas")
    rows, truth = logged_steps(steps, dt_s)
    frame = pd.DataFrame(rows, columns=["Step", "Status", "Time", "Current(mA)",
                                        "Charge_Capacity(mAh)", "Discharge_Capacity(mAh)"])
    frame = frame.astype({c: "float32" for c in frame.columns[2:]})
    return frame, truth


def logged_steps(steps, dt_s=1.0):
    """The rows of neware_frame (step, type, step clock, mA, the two counters in mAh) and
    the truth (time s, current A, charge Ah)."""
    rows, truth = [], []
    t0, q0 = 0.0, 0.0
    for n, (amps, dur) in enumerate(steps, 1):
        for k in np.arange(0.0, dur + dt_s / 2, dt_s):
            q = amps * k / 3600.0
            rows.append((n, "CC_Chg" if amps > 0 else "CC_DChg" if amps < 0 else "Rest", k,
                         amps * 1e3, max(q, 0.0) * 1e3, max(-q, 0.0) * 1e3))
            truth.append((t0 + k, amps, q0 + q))
        t0, q0 = t0 + dur, q0 + amps * dur / 3600.0
    return rows, np.array(truth)


def fake_neware(monkeypatch, frame, voltage_v):
    frame = frame.assign(Voltage=np.float32(voltage_v))
    module = types.SimpleNamespace(read=lambda path: frame.copy(), __version__="test")
    monkeypatch.setitem(sys.modules, "NewareNDA", module)


STEPS = [(0.0, 60.0), (-5.0, 40.0), (0.0, 30.0), (2.5, 20.0), (-8.0, 100.0), (0.0, 120.0),
         (-3.0, 300.0), (1.0, 50.0), (0.0, 200.0)]


def test_a_neware_record_reads_as_its_csv_and_validates_alike(cell_files, tmp_path, capsys,
                                                            monkeypatch):
    from ecmgen.data.measure import TimeSeries, write_timeseries_csv
    from ecmgen.model import load_model
    from ecmgen.model.simulate import simulate

    frame, truth = neware_frame(STEPS)
    time_s, current_a, charge_ah = truth.T
    model = load_model(cell_files / "model.json")
    voltage_v = simulate(model, time_s, current_a, 0.8).voltage_v
    write_timeseries_csv(TimeSeries(time_s, current_a, voltage_v.astype(np.float32)
                                    .astype(np.float64)), tmp_path / "record.csv")
    (tmp_path / "record.nda").write_bytes(b"NEWARE")
    fake_neware(monkeypatch, frame, voltage_v)

    s = read_timeseries(tmp_path / "record.nda")
    assert np.allclose(s.time_s, time_s, atol=1e-4) and np.allclose(s.current_a, current_a)
    assert np.allclose(s.coulomb_ah(), charge_ah, atol=1e-6)
    assert any("restarts at every step" in n for n in s.notes)
    results = []
    for name in ("record.csv", "record.nda"):
        assert main(["validate", str(cell_files / "model.json"), str(tmp_path / name),
                     "--soc0", "0.8", "--json"]) == 0
        results.append(json.loads(capsys.readouterr().out)["mae_v"])
    # the CSV holds the voltages as float32: the MAE moves by at most that rounding
    assert results[1] == pytest.approx(results[0],
                                       abs=float(np.finfo(np.float32).eps) * 4.5)


def test_step_clock_join():
    t, joined = step_time_joined(np.array([0, 1, 2, 0, 3, 0, 5.0]), np.array([1, 1, 1, 2, 2, 3, 3]))
    assert joined == 2 and t.tolist() == [0, 1, 2, 2, 5, 5, 10]
    running = np.array([0, 1, 2, 2.5, 3.0])
    assert step_time_joined(running, np.array([1, 1, 2, 2, 3]))[0] is running


# --------------------------------------------------------------------------- refused

@pytest.mark.parametrize("suffix, package", [(".nda", "NewareNDA"), (".ndax", "NewareNDA"),
                                             (".mpr", "galvani"), (".res", "galvani")])
def test_without_the_extra_a_native_file_is_refused_with_the_install_line(
        tmp_path, monkeypatch, capsys, cell_files, suffix, package):
    path = tmp_path / f"record{suffix}"
    path.write_bytes(b"\x00" * 64)
    for name in ("NewareNDA", "galvani", "galvani.BioLogic", "galvani.res2sqlite"):
        monkeypatch.setitem(sys.modules, name, None)       # import fails: not installed
    if suffix == ".res":
        monkeypatch.setattr(shutil, "which", lambda name: "/usr/bin/" + name)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, package, INSTALL)
    assert main(["validate", str(cell_files / "model.json"), str(path)]) == 2
    one_line_error(capsys, str(path), INSTALL)


@pytest.mark.parametrize("suffix, package", [(".nda", "NewareNDA"), (".ndax", "NewareNDA"),
                                             (".mpr", "galvani")])
def test_what_a_reader_cannot_read_is_one_line(tmp_path, suffix, package):
    pytest.importorskip(package, reason="the cyclers extra is not installed")
    path = tmp_path / f"notes{suffix}"
    path.write_text("not a cycler file\n" * 20)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, f"{package} cannot read it")


def test_arbin_res_needs_mdbtools(tmp_path, monkeypatch):
    pytest.importorskip("galvani", reason="the cyclers extra is not installed")
    path = tmp_path / "test.res"
    path.write_bytes(b"\x00" * 64)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "mdbtools", "export the file as CSV")


# --------------------------------------------------------------------------- other formats
# No real BioLogic or Arbin file is at hand: the readers are given a known record in the
# form each returns (galvani's MPRfile.data, its Arbin database's Channel_Normal_Table),
# which checks ecmgen's side, the names, units, sign and counters taken from them.

def _known_record():
    _, truth = logged_steps(STEPS)
    return truth.T, 3.6 + 0.01 * truth[:, 1]


def test_a_biologic_record_reads_as_known(tmp_path, monkeypatch):
    (time_s, current_a, charge_ah), voltage_v = _known_record()
    data = np.zeros(time_s.size, dtype=[("time/s", "<f8"), ("Ewe/V", "<f4"),
                                        ("<I>/mA", "<f8"), ("(Q-Qo)/mA.h", "<f8"),
                                        ("Ns", "<u2")])
    data["time/s"], data["Ewe/V"] = time_s, voltage_v
    data["<I>/mA"], data["(Q-Qo)/mA.h"] = current_a * 1e3, charge_ah * 1e3 + 12.0
    biologic = types.SimpleNamespace(MPRfile=lambda path: types.SimpleNamespace(data=data))
    monkeypatch.setitem(sys.modules, "galvani", types.SimpleNamespace(BioLogic=biologic))
    path = tmp_path / "gcpl.mpr"
    path.write_bytes(b"BIO-LOGIC")
    s = read_timeseries(path)
    assert np.allclose(s.time_s, time_s) and np.allclose(s.current_a, current_a)
    assert np.allclose(s.voltage_v, voltage_v, atol=1e-6)
    assert np.allclose(s.coulomb_ah(), charge_ah, atol=1e-9)
    assert any("BioLogic .mpr" in n for n in s.notes)


def test_an_arbin_record_reads_as_known(tmp_path, monkeypatch):
    import sqlite3

    (time_s, current_a, charge_ah), voltage_v = _known_record()
    # Arbin's counters count up apart (and restart every cycle: here one cycle)
    moved = np.diff(charge_ah, prepend=charge_ah[0])
    up, down = np.cumsum(np.maximum(moved, 0.0)), np.cumsum(np.maximum(-moved, 0.0))

    def convert(res, db):
        con = sqlite3.connect(db)
        con.execute('CREATE TABLE Channel_Normal_Table (Data_Point INTEGER, Test_Time REAL, '
                    'Current REAL, Voltage REAL, Charge_Capacity REAL, '
                    'Discharge_Capacity REAL, Step_Index INTEGER)')
        con.executemany('INSERT INTO Channel_Normal_Table VALUES (?, ?, ?, ?, ?, ?, 1)',
                        [(k, *row) for k, row in enumerate(zip(
                            time_s, current_a, voltage_v, up, down), 1)][::-1])
        con.commit()
        con.close()

    res2sqlite = types.SimpleNamespace(convert_arbin_to_sqlite=convert)
    monkeypatch.setitem(sys.modules, "galvani", types.SimpleNamespace(res2sqlite=res2sqlite))
    monkeypatch.setattr(shutil, "which", lambda name: "/usr/bin/" + name)
    path = tmp_path / "test.res"
    path.write_bytes(b"\x00\x01")
    s = read_timeseries(path)
    assert np.allclose(s.time_s, time_s) and np.allclose(s.current_a, current_a)
    assert np.allclose(s.coulomb_ah(), charge_ah, atol=1e-9)
