"""Measurement readers: real files, canonical CSV round trip, column maps, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from conftest import CALCE, PANASONIC, REPO, need
from ecmgen.errors import InputError
from ecmgen.data.measure import (ColumnMap, TimeSeries, read_timeseries,
                                 write_timeseries_csv)

EXAMPLE = REPO / "examples" / "panasonic-25degC"
PANASONIC_FILES = ("hppc.mat", "ocv-c20.mat", "us06.mat", "hwfet-a.mat",
                   "hppc-soc-steps.mat")
FIELDS = ("time_s", "current_a", "voltage_v", "temperature_c", "charge_ah")


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def assert_one_line_error(exc: pytest.ExceptionInfo, path: Path, *words: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: ")
    for word in words:
        assert word in msg, f"{word!r} not in {msg!r}"
    return msg


GOOD_CSV = ("time_s,current_a,voltage_v\n"
            "0,0,3.9\n"
            "1,-1.5,3.8\n"
            "2,-1.5,3.79\n"
            "3,0,3.85\n")


# --------------------------------------------------------------------------- real data

@pytest.mark.parametrize("name", PANASONIC_FILES)
def test_reads_panasonic_mat(name):
    path = need(PANASONIC / name)
    ts = read_timeseries(path, capacity_ah=2.9)      # its speed: bench/bench_read.py
    assert ts.source == str(path)
    n = len(ts)
    for f in FIELDS:
        arr = getattr(ts, f)
        assert arr.dtype == np.float64 and arr.shape == (n,)
    assert np.all(np.diff(ts.time_s) >= 0)
    assert 2.4 < ts.voltage_v.min() and ts.voltage_v.max() < 4.3
    # Discharge negative in the file = charge-positive: the logged Ah moves with the current.
    d_ah = np.diff(ts.charge_ah)
    mid_i = 0.5 * (ts.current_a[1:] + ts.current_a[:-1])
    moving = (d_ah != 0) & (mid_i != 0)
    assert np.mean(np.sign(d_ah[moving]) == np.sign(mid_i[moving])) > 0.99


def test_panasonic_hppc_details():
    ts = read_timeseries(need(PANASONIC / "hppc.mat"))
    assert len(ts) == 102_800
    assert ts.current_a.min() == pytest.approx(-17.40298)  # 6 C discharge pulse
    assert ts.current_a.max() == 0.0                       # no charge pulses
    assert np.sum(np.diff(ts.time_s) == 0) > 0             # repeated stamps survive


def test_reads_calce_dynamic_csv():
    path = need(CALCE / "dynamics-dst-us06-fuds.csv")
    ts = read_timeseries(path, capacity_ah=1.1)
    assert len(ts) == 26_099
    assert ts.temperature_c is None and ts.charge_ah is None
    assert ts.time_s[0] == pytest.approx(3.006273302)  # Test_Time(s), not Step_Time(s)
    assert "Arbin" in ts.notes[0]
    # First step is the 1.1 A discharge: current negative while the voltage falls.
    assert ts.current_a[1] == pytest.approx(-1.099776387)
    assert ts.voltage_v[5] < ts.voltage_v[1]


def test_reads_calce_ocv_csv_with_index_column():
    path = need(CALCE / "ocv-charge-c22.csv")
    ts = read_timeseries(path, capacity_ah=1.1)
    assert len(ts) == 15_126
    assert ts.time_s[0] == pytest.approx(5.007542513978846)  # Step_Time(s)
    assert ts.temperature_c is not None and ts.temperature_c[0] == pytest.approx(21.5914116)
    # Low-rate CHARGE: current positive, voltage rising 2.59 -> 3.60 V.
    assert np.all(ts.current_a > 0.049)
    assert ts.voltage_v[-1] > ts.voltage_v[0] + 0.9


# --------------------------------------------------------------------------- example

BUNDLED = {EXAMPLE: (PANASONIC, ("hppc.mat", "hppc-soc-steps.mat", "ocv-c20.mat", "us06.mat",
                                 "hwfet-a.mat"))}
for _t in ("0degC", "n10degC", "n20degC"):
    BUNDLED[REPO / "examples" / "panasonic-temperature" / _t] = (
        PANASONIC.parent / f"panasonic-18650pf-{_t}",
        ("hppc.mat", "hppc-soc-steps.mat", "us06.mat", "hwfet.mat"))


def test_bundled_examples_match_shared_data():
    total = 0
    for folder, (shared, names) in BUNDLED.items():
        assert folder.is_dir(), "run python examples/make_panasonic_example.py"
        files = sorted(folder.glob("*.mat"))
        assert [f.name for f in files] == sorted(names)
        total += sum(f.stat().st_size for f in files)
        for f in files:
            small = _raw_fields(f)
            if (shared / f.name).exists():
                full = _raw_fields(shared / f.name)
                cell = (full["Voltage"] >= 0.5) & (full["Voltage"] <= 6.0)  # see SOURCE.md
                for k, v in small.items():
                    np.testing.assert_array_equal(v, full[k][cell])
            read_timeseries(f, capacity_ah=2.9)      # every bundled file reads
    assert total < 15e6                       # the budget for bundled data
    for source in (EXAMPLE / "SOURCE.md", REPO / "examples" / "panasonic-temperature" /
                   "SOURCE.md"):
        assert "10.17632/wykht8y7tg.1" in source.read_text()


def _raw_fields(path: Path) -> dict[str, np.ndarray]:
    """The fields ecmgen reads, as stored (read_timeseries refuses the last row of the
    shared -20 degC steps file, logged at 0 V)."""
    meas = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)["meas"]
    return {k: np.asarray(getattr(meas, k), dtype=np.float64)
            for k in ("Time", "Current", "Voltage", "Ah", "Battery_Temp_degC")}


# --------------------------------------------------------------------------- CSV round trip

def test_csv_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    n = 200
    ts = TimeSeries(time_s=np.cumsum(rng.uniform(0, 0.2, n)),
                    current_a=rng.normal(0, 3, n), voltage_v=rng.uniform(2.5, 4.2, n),
                    temperature_c=rng.uniform(20, 30, n), charge_ah=rng.normal(0, 1, n) / 7)
    out = write_timeseries_csv(ts, tmp_path / "sub" / "rt.csv")
    assert out.read_text().splitlines()[0] == ",".join(FIELDS)
    back = read_timeseries(out)
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(back, k), getattr(ts, k))
    assert [p.name for p in out.parent.iterdir()] == ["rt.csv"]  # no temp file left


def test_csv_round_trip_optional_columns_absent(tmp_path):
    ts = TimeSeries(np.array([0.0, 1.0]), np.array([0.1, -0.2]), np.array([3.7, 3.6]),
                    charge_ah=np.array([0.0, 1e-5]))
    back = read_timeseries(write_timeseries_csv(ts, tmp_path / "a.csv"))
    assert back.temperature_c is None
    np.testing.assert_array_equal(back.charge_ah, ts.charge_ah)


def test_real_mat_round_trips_through_csv(tmp_path):
    ts = read_timeseries(need(PANASONIC / "ocv-c20.mat"))
    back = read_timeseries(write_timeseries_csv(ts, tmp_path / "ocv.csv"))
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(back, k), getattr(ts, k))


# --------------------------------------------------------------------------- column maps

def test_column_map_units_and_discharge_positive(tmp_path):
    path = write(tmp_path / "cycler.csv",
                 "TestTime[h],I[mA],U[mV],T,Q[mAh]\n"
                 "0,0,3900,25,0\n"
                 "0.5,1500,3800,25.5,750\n"
                 "1,1500,3700,26,1500\n")
    cols = ColumnMap(time="TestTime[h]", current="I[mA]", voltage="U[mV]", temperature="T",
                     charge="Q[mAh]", time_unit="h", current_unit="mA", voltage_unit="mV",
                     charge_unit="mAh", current_sign="discharge_positive")
    ts = read_timeseries(path, cols, capacity_ah=3.0)
    np.testing.assert_allclose(ts.time_s, [0, 1800, 3600])
    np.testing.assert_allclose(ts.current_a, [0, -1.5, -1.5])  # discharge -> negative
    np.testing.assert_allclose(ts.voltage_v, [3.9, 3.8, 3.7])
    np.testing.assert_allclose(ts.temperature_c, [25, 25.5, 26])
    np.testing.assert_allclose(ts.charge_ah, [0, -0.75, -1.5])
    np.testing.assert_allclose(ts.coulomb_ah(), [0, -0.75, -1.5])


def test_column_map_minutes(tmp_path):
    path = write(tmp_path / "m.csv", "t,i,v\n0,1,3.7\n2,1,3.8\n")
    ts = read_timeseries(path, ColumnMap("t", "i", "v", time_unit="min"))
    np.testing.assert_allclose(ts.time_s, [0, 120])


def test_column_map_from_toml():
    table = {"time": "Test_Time(s)", "current": "Current(A)", "voltage": "Voltage(V)",
             "current_unit": "mA", "current_sign": "discharge_positive"}
    cols = ColumnMap.from_toml(table, "cell.toml")
    assert ColumnMap.from_table(table, "cell.toml") == cols
    assert cols == ColumnMap("Test_Time(s)", "Current(A)", "Voltage(V)", current_unit="mA",
                             current_sign="discharge_positive")


@pytest.mark.parametrize("table, words", [
    ({"time": "t", "current": "i", "voltage": "v", "volt_unit": "mV"}, ["unknown key", "volt_unit"]),
    ({"time": "t", "current": "i", "voltage": "v", "current_unit": "uA"}, ["current_unit", "'uA'", "'mA'"]),
    ({"time": "t", "current": "i", "voltage": "v", "current_sign": "negative"}, ["current_sign"]),
    ({"time": "t", "current": "i", "voltage": "v", "time_unit": "ms"}, ["time_unit"]),
    ({"time": "t", "current": "i"}, ["missing key", "voltage"]),
    ({"time": "t", "current": 0, "voltage": "v"}, ["current = 0", "counts from 1"]),
    ({"time": "t", "current": True, "voltage": "v"}, ["current", "column name"]),
    ({"time": "t", "current": "i", "voltage": "v", "header": False}, ["header = false", "position"]),
    ({"time": 1, "current": 2, "voltage": 3, "header": "no"}, ["header", "true or false"]),
    ("not a table", ["must be a table"]),
])
def test_column_map_from_toml_rejects(table, words):
    with pytest.raises(InputError) as exc:
        ColumnMap.from_toml(table, Path("cfg/cell.toml"))
    assert_one_line_error(exc, Path("cfg/cell.toml"), "[data.columns]", *words)


def test_mapping_for_mat_fields(tmp_path):
    path = tmp_path / "flat.mat"
    scipy.io.savemat(path, {"t_min": np.array([0.0, 1.0, 2.0]), "i_ma": np.array([500.0, 500, 0]),
                            "u": np.array([3.6, 3.7, 3.75])})
    ts = read_timeseries(path, ColumnMap("t_min", "i_ma", "u", time_unit="min",
                                         current_unit="mA"))
    np.testing.assert_allclose(ts.time_s, [0, 60, 120])
    np.testing.assert_allclose(ts.current_a, [0.5, 0.5, 0])


# --------------------------------------------------------------------------- auto layouts

def test_arbin_layout_recognised(tmp_path):
    path = write(tmp_path / "arbin.csv",
                 "Data_Point,Test_Time(s),Step_Time(s),Current(A),Voltage(V),"
                 "Charge_Capacity(Ah),Temperature (C)_1\n"
                 "1,0.0,0.0,0,3.30,0,22.0\n"
                 "2,1.0,1.0,-1.1,3.20,0,22.1\n"
                 "3,2.0,0.0,-1.1,3.19,0,22.2\n")
    ts = read_timeseries(path)
    np.testing.assert_allclose(ts.time_s, [0, 1, 2])       # Test_Time, not Step_Time
    np.testing.assert_allclose(ts.current_a, [0, -1.1, -1.1])  # already charge-positive
    np.testing.assert_allclose(ts.temperature_c, [22.0, 22.1, 22.2])
    assert ts.charge_ah is None  # Arbin capacity columns reset per cycle: not used


def test_leading_unnamed_index_and_semicolons_tolerated(tmp_path):
    path = write(tmp_path / "idx.csv", ";time_s;current_a;voltage_v\n7;0;0.1;3.6\n8;5;0.1;3.61\n")
    ts = read_timeseries(path)
    np.testing.assert_allclose(ts.time_s, [0, 5])


def test_unknown_layout_asks_for_mapping(tmp_path):
    path = write(tmp_path / "odd.csv", "Zeit,Strom,Spannung\n0,1,3.7\n1,1,3.8\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'Zeit'", "'Strom'", "'Spannung'", "[data.columns]")


def test_step_time_going_backwards_explains(tmp_path):
    path = write(tmp_path / "steps.csv",
                 "Step_Time(s),Current(A),Voltage(V)\n0,0,3.3\n5,1,3.4\n0.5,1,3.41\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'Step_Time(s)'", "row 3", "backwards", "Test_Time")


def test_mat_with_top_level_fields(tmp_path):
    path = tmp_path / "top.mat"
    scipy.io.savemat(path, {"Time": np.array([0.0, 0.1, 0.2]),
                            "Current": np.array([0.0, -2.0, -2.0]),
                            "Voltage": np.array([4.1, 4.0, 3.99])})
    ts = read_timeseries(path)
    np.testing.assert_allclose(ts.current_a, [0, -2, -2])
    assert ts.temperature_c is None and ts.charge_ah is None


def test_repeated_time_stamps_accepted(tmp_path):
    path = write(tmp_path / "edge.csv",
                 "time_s,current_a,voltage_v\n0,0,3.9\n1,0,3.9\n1,-3,3.7\n1,-3,3.69\n2,-3,3.68\n")
    ts = read_timeseries(path)
    np.testing.assert_array_equal(ts.time_s, [0, 1, 1, 1, 2])


# --------------------------------------------------------------------------- bad input

def test_missing_file(tmp_path):
    path = tmp_path / "nope.csv"
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "no such file")


def test_missing_column_canonical(tmp_path):
    path = write(tmp_path / "a.csv", "time_s,current_a,temperature_c\n0,1,25\n1,1,25\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "missing column 'voltage_v'", "'temperature_c'")


def test_missing_column_mapped(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV)
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap(temperature="Temp"))
    assert_one_line_error(exc, path, "missing column 'Temp'", "temperature", "'time_s'")


def test_missing_field_in_mat(tmp_path):
    path = tmp_path / "m.mat"
    scipy.io.savemat(path, {"meas": {"Time": np.arange(3.0), "Current": np.zeros(3)}})
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'Voltage'", "'Time'", "'Current'")


def test_time_backwards(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV.replace("2,-1.5,3.79", "0.5,-1.5,3.79"))
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'time_s'", "row 3 (line 4)", "backwards")


def test_nan(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV.replace("3.8\n", "nan\n"))
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'voltage_v'", "row 2 (line 3)", "NaN")


def test_inf_in_mat(tmp_path):
    path = tmp_path / "m.mat"
    scipy.io.savemat(path, {"meas": {"Time": np.arange(3.0), "Current": np.array([0, np.inf, 0]),
                                     "Voltage": np.full(3, 3.7)}})
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "field 'Current'", "row 2", "+inf")


def test_non_numeric_cell(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV.replace("1,-1.5,3.8", "1,abc,3.8"))
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'current_a'", "row 2 (line 3)", "'abc'", "not a number")


def test_decimal_comma_hint(tmp_path):
    path = write(tmp_path / "a.csv", "time_s;current_a;voltage_v\n0;0;3,9\n1;0;3,8\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'voltage_v'", "row 1", "decimal comma")


def test_ragged_row(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV + "4,0\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "line 6", "2 fields", "header has 3")


def test_ma_declared_as_a_with_capacity(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV.replace("-1.5", "-2900"))
    with pytest.raises(InputError) as exc:
        read_timeseries(path, capacity_ah=2.9)
    assert_one_line_error(exc, path, "'current_a'", "row 2",
                          "current reaches 2900 A = 1000 C for a 2.9 Ah cell",
                          "mA declared as A?")


def test_ma_declared_as_a_without_capacity(tmp_path):
    path = write(tmp_path / "a.csv", GOOD_CSV.replace("-1.5", "-2900"))
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'current_a'", "2900 A", "mA declared as A?")
    # Plausible without a capacity: 150 A (e.g. a large prismatic cell) is fine.
    read_timeseries(write(tmp_path / "b.csv", GOOD_CSV.replace("-1.5", "-150")))


def test_mv_declared_as_v(tmp_path):
    path = write(tmp_path / "a.csv", "time_s,current_a,voltage_v\n0,0,3900\n1,-1,3800\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'voltage_v'", "row 1", "3900 V", "mV declared as V?")


def test_v_declared_as_mv(tmp_path):
    path = write(tmp_path / "a.csv", "t,i,u\n0,0,3.9\n1,-1,3.8\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path, ColumnMap("t", "i", "u", voltage_unit="mV"))
    assert_one_line_error(exc, path, "'u'", "V declared as mV?")


def test_too_few_rows(tmp_path):
    path = write(tmp_path / "a.csv", "time_s,current_a,voltage_v\n0,0,3.9\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "only 1 data row", "at least 2")


def test_empty_file(tmp_path):
    path = write(tmp_path / "a.csv", "")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "empty")


def test_corrupt_mat(tmp_path):
    path = tmp_path / "bad.mat"
    path.write_bytes(b"MATLAB 5.0 MAT-file" + b"\0" * 20)
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, ".mat")


def test_charge_column_with_opposite_sign(tmp_path):
    # A discharge logged with an always-positive "discharged Ah" counter mapped as charge.
    n = 30
    t = np.arange(n, dtype=float)
    rows = "\n".join(f"{ti},-1.0,{3.9 - 0.01 * ti},{ti / 3600}" for ti in t)
    path = write(tmp_path / "a.csv", "time_s,current_a,voltage_v,charge_ah\n" + rows + "\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'charge_ah'", "opposite sign")


def test_header_only(tmp_path):
    path = write(tmp_path / "a.csv", "time_s,current_a,voltage_v\n\n")
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "only 0 data rows")


def test_mat_without_known_fields(tmp_path):
    path = tmp_path / "x.mat"
    scipy.io.savemat(path, {"x": np.arange(3.0)})
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'x'", "'meas'", "[data.columns]")


def test_mat_text_field(tmp_path):
    path = tmp_path / "t.mat"
    scipy.io.savemat(path, {"meas": {"Time": np.arange(3.0), "Current": "abc",
                                     "Voltage": np.full(3, 3.7)}})
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "field 'Current'", "text")


def test_mat_fields_of_unequal_length(tmp_path):
    path = tmp_path / "u.mat"
    scipy.io.savemat(path, {"meas": {"Time": np.arange(3.0), "Current": np.zeros(4),
                                     "Voltage": np.full(3, 3.7)}})
    with pytest.raises(InputError) as exc:
        read_timeseries(path)
    assert_one_line_error(exc, path, "'Current' has 4 rows", "'Time' has 3")


def test_column_map_direct_construction_is_checked():
    with pytest.raises(InputError, match="voltage_unit"):
        ColumnMap(voltage_unit="kV")


# --------------------------------------------------------------------------- voltage lag

def _lagged_record(lag: int, *, seed=0, name="lagged.csv") -> TimeSeries:
    """A drive-cycle-like record: a 1 Hz rest, then 10 Hz random current steps; the
    voltage (R0 plus one RC pair, 0.5 mV noise) answers the current ``lag`` samples late."""
    rng = np.random.default_rng(seed)
    levels = rng.uniform(-8.0, 4.0, 400)
    i_fast = np.repeat(levels, rng.integers(1, 30, levels.size))
    t = np.concatenate((np.arange(0.0, 60.0, 1.0), 60.0 + 0.1 * np.arange(i_fast.size)))
    i = np.concatenate((np.zeros(60), i_fast))
    seen = np.concatenate((np.zeros(lag), i[:i.size - lag]))   # what the voltage answers
    u = np.zeros_like(seen)
    for k in range(1, seen.size):
        a = np.exp(-(t[k] - t[k - 1]) / 20.0)
        u[k] = a * u[k - 1] + 0.015 * (1 - a) * seen[k]
    v = 3.7 + 0.02 * seen + u + 0.0005 * rng.standard_normal(t.size)
    return TimeSeries(t, i, v, source=f"/some/where/{name}")


@pytest.mark.parametrize("lag", [0, 1, 2])
def test_voltage_lag_recovers_a_known_shift(lag):
    from ecmgen.data.measure import LAG_MARGIN, voltage_lag

    found = voltage_lag(_lagged_record(lag))
    assert found is not None and found.samples == lag
    assert found.sample_s == pytest.approx(0.1)            # the 10 Hz part, not the 1 Hz rest
    assert len(found.correlation) == 3
    assert int(np.argmax(found.correlation)) == lag
    if lag:
        assert found.correlation[lag] > found.correlation[0] + LAG_MARGIN
        note = found.note("/some/where/lagged.csv")
        assert "\n" not in note and note.startswith("lagged.csv: the voltage lags the current by")
        assert f"by {lag} sample" in note and f"({lag * 0.1:.2g} s)" in note
        assert f"at lag {lag} vs" in note


def test_voltage_lag_needs_steps():
    from ecmgen.data.measure import voltage_lag

    t = np.arange(0.0, 100.0, 0.1)
    constant = TimeSeries(t, np.full(t.size, -1.0), 3.7 - 0.001 * t / 100, source="cc.csv")
    assert voltage_lag(constant) is None
    few = np.where((t % 20) < 10, -2.0, 0.0)                # 9 steps
    assert voltage_lag(TimeSeries(t, few, 3.7 + 0.02 * few, source="few.csv")) is None
    assert voltage_lag(TimeSeries(t[:2], few[:2], 3.7 + 0.02 * few[:2])) is None


def test_validation_reports_the_lag_and_does_not_shift(synthetic_model):
    from ecmgen.model.simulate import simulate, validate

    rec = _lagged_record(0, name="drive.csv")
    i = rec.current_a
    seen = np.concatenate(([0.0], i[:-1]))
    v = simulate(synthetic_model, rec.time_s, seen, 0.8).voltage_v   # one sample late
    val = validate(synthetic_model, TimeSeries(rec.time_s, i, v, source=rec.source), 0.8)
    assert val.voltage_lag_samples == 1
    assert any(w.startswith("drive.csv: the voltage lags the current by 1 sample")
               for w in val.warnings)
    np.testing.assert_array_equal(val.measured_v, v)
    on_time = validate(synthetic_model, TimeSeries(rec.time_s, seen, v, source="x.csv"), 0.8)
    assert on_time.voltage_lag_samples == 0 and not on_time.warnings


def test_shared_panasonic_voltage_lags_on_drive_cycles_only():
    """us06 (10 Hz): the voltage answers a current step one sample late (measured 0.81 at
    lag 1 vs 0.44 at lag 0); the pulse test's steps line up (0.97 at lag 0)."""
    from ecmgen.data.measure import voltage_lag

    us06 = voltage_lag(read_timeseries(need(PANASONIC / "us06.mat")))
    assert us06.samples == 1 and us06.sample_s == pytest.approx(0.1, abs=0.005)
    hppc = voltage_lag(read_timeseries(need(PANASONIC / "hppc.mat")))
    assert hppc.samples == 0 and hppc.correlation[0] > 0.9
