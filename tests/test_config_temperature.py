"""[[data.pulse_tests]] and [model] in the build config: what they parse to, and every bad
input as one line naming the config, exit code 2 and no output."""

from __future__ import annotations

import pytest

from ecmgen.cli import main
from ecmgen.config import load_config
from ecmgen.errors import InputError

HEAD = '[cell]\ncapacity_ah = 2.9\n[data]\ncycle = "cycle.csv"\n'


def _test(file="a.csv", **kw):
    lines = ["[[data.pulse_tests]]", f'file = "{file}"']
    lines += [f"{k} = {v}" for k, v in kw.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture
def folder(tmp_path):
    for name in ("a.csv", "b.csv", "c.csv", "steps.csv", "ocv.csv", "cycle.csv"):
        (tmp_path / name).write_text("time_s,current_a,voltage_v\n0,0,3.7\n")
    return tmp_path


def _write(folder, text):
    path = folder / "cell.toml"
    path.write_text(text)
    return path


def test_pulse_tests_parse_with_their_defaults(folder):
    cfg = load_config(_write(folder, HEAD + _test("a.csv", soc0=1.0) +
                             _test("b.csv", temperature_c=-10, steps='"steps.csv"',
                                   ocv='"ocv.csv"') + _test("c.csv", ocv='"pulses"')))
    assert cfg.over_temperature and cfg.pulses is None and cfg.dcir is None
    a, b, c = cfg.pulse_tests
    assert a.file == folder / "a.csv" and a.soc0 == 1.0 and a.temperature_c is None
    assert a.steps is None and a.ocv is None          # data.ocv defaults to "pulses" here
    assert b.temperature_c == -10.0 and b.steps == folder / "steps.csv"
    assert b.ocv == folder / "ocv.csv" and b.soc0 is None
    assert c.ocv is None
    assert cfg.methods == ("ga", "lm", "curve") and cfg.best == "curve"
    assert cfg.temperature_step_c == 5.0 and cfg.warm_row_c == 45.0
    assert cfg.curve_branches          # on over temperature, off for data.pulses


def test_a_global_ocv_file_applies_to_every_test_unless_one_says_otherwise(folder):
    cfg = load_config(_write(folder, HEAD + 'ocv = "ocv.csv"\n' + _test("a.csv") +
                             _test("b.csv", ocv='"pulses"')))
    assert cfg.pulse_tests[0].ocv == folder / "ocv.csv" and cfg.pulse_tests[1].ocv is None


def test_model_section(folder):
    cfg = load_config(_write(folder, HEAD + _test() + "[model]\ntemperature_step_c = 0\n"
                                                      "warm_row_c = false\n"))
    assert cfg.temperature_step_c == 0.0 and cfg.warm_row_c is None
    cfg = load_config(_write(folder, HEAD + _test() + "[model]\nwarm_row_c = 40\n"))
    assert cfg.warm_row_c == 40.0


def test_the_single_pulses_form_is_unchanged(folder):
    cfg = load_config(_write(folder, HEAD + 'pulses = "a.csv"\nocv = "pulses"\n'))
    assert cfg.pulse_tests == () and not cfg.over_temperature
    # the curve fit's branches default on however many pulse tests (set false to leave out)
    assert cfg.pulses == folder / "a.csv" and cfg.curve_branches
    cfg = load_config(_write(folder, HEAD + 'pulses = "a.csv"\nocv = "pulses"\n'
                                            '[fit]\ncurve_branches = false\n'))
    assert not cfg.curve_branches


BAD = [
    ('pulse_tests = "a.csv"\n', "data.pulse_tests must be"),
    ("pulse_tests = []\n", "data.pulse_tests must be"),
    ("[[data.pulse_tests]]\nsoc0 = 1.0\n", "data.pulse_tests[1]: missing file"),
    (_test("nope.csv"), "data.pulse_tests[1].file names a missing file: nope.csv"),
    (_test() + _test("b.csv", tempC=3), "data.pulse_tests[2]: unknown key(s) ['tempC']"),
    (_test(temperature_c='"cold"'), "data.pulse_tests[1].temperature_c must be a number"),
    (_test(temperature_c=-80), "temperature_c must lie in -60..100 degC"),
    (_test(temperature_c="nan"), "temperature_c must be a number"),
    (_test(temperature_c=0) + _test("b.csv", temperature_c=0.3), "within 0.5 K"),
    (_test() + _test("a.csv"), "data.pulse_tests[2] names the same file as"),
    (_test(soc0=1.5), "data.pulse_tests[1].soc0 is a SOC"),
    (_test(steps='"nope.csv"'), "data.pulse_tests[1].steps names a missing file"),
    (_test(ocv='"nope.csv"'), "data.pulse_tests[1].ocv names a missing file"),
    (_test(file="a.csv", steps=3), "data.pulse_tests[1].steps must be a file name"),
    ('pulses = "a.csv"\nocv = "pulses"\n' + _test(), "give exactly one of data.pulses"),
    ('dcir = "a.csv"\n' + _test(), "give exactly one of data.pulses"),
    ("pulses_soc0 = 1.0\n" + _test(), "give soc0 in each [[data.pulse_tests]]"),
    (_test() + "[model]\ntemperature_step_c = -5\n", "model.temperature_step_c must lie"),
    (_test() + "[model]\ntemperature_step_c = \"5K\"\n", "model.temperature_step_c must be"),
    (_test() + "[model]\nwarm_row_c = true\n", "model.warm_row_c must be a number"),
    (_test() + "[model]\nwarm_row_c = 200\n", "model.warm_row_c must lie"),
    (_test() + "[model]\ngrid = 5\n", "[model]: unknown key(s) ['grid']"),
    (_test() + "[fit]\ncurve_branches = 1\n", "fit.curve_branches must be true or false"),
]


@pytest.mark.parametrize("body,needle", BAD, ids=[b[1][:40] for b in BAD])
def test_bad_pulse_tests_and_model_section(folder, capsys, body, needle):
    text = HEAD + body
    cfg = _write(folder, text)
    with pytest.raises(InputError) as exc:
        load_config(cfg)
    assert needle in str(exc.value)
    # the command line: one line naming the config, exit code 2, nothing written
    out = folder / "out"
    assert main(["build", str(cfg), "--out", str(out), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip()
    assert err.count("\n") == 0 and err.startswith(f"ecmgen: error: {cfg}: "), err
    assert needle in err
    assert not out.exists()


def test_model_must_be_a_table(folder):
    with pytest.raises(InputError, match=r"\[model\] must be a table"):
        load_config(_write(folder, "model = 5\n" + HEAD + _test()))


def test_dcir_with_a_config_over_temperature_names_one_test(folder, capsys):
    from conftest import make_pulse_test, synthetic_nca_model
    from ecmgen.data.measure import write_timeseries_csv

    series, _ = make_pulse_test(synthetic_nca_model(), soc_levels=(0.9, 0.6, 0.3),
                                c_rates=(1.0,), rest_s=300.0)
    write_timeseries_csv(series, folder / "a.csv")
    cfg = _write(folder, HEAD + _test("a.csv", soc0=1.0) + _test("b.csv"))
    assert main(["dcir", "--config", str(cfg), "--quiet"]) == 2
    assert "name one, ecmgen dcir PULSES" in capsys.readouterr().err
    assert main(["dcir", str(folder / "a.csv"), "--config", str(cfg), "--quiet"]) == 0
    assert capsys.readouterr().out.startswith("soc,direction,c_rate,t_s,r_ohm\n")


# --------------------------------------------------------------------------- temperature_c

def _two_rows(path):
    path.write_text("time_s,current_a,voltage_v\n0,0,3.7\n1,0,3.7\n")
    return path


def test_data_temperature_c_gives_files_without_a_column_their_temperature(folder):
    """Before: no config key for a file's ambient temperature; a validation file without
    a temperature column was refused against a model over temperature."""
    from ecmgen.pipeline import read_series

    sub = folder / "runs"
    sub.mkdir()
    _two_rows(sub / "us06.csv")
    _two_rows(folder / "cycle.csv")
    cfg = load_config(_write(folder, HEAD.replace('cycle = "cycle.csv"',
                                                  'cycle = "cycle.csv"\n'
                                                  'extra_cycles = ["runs/us06.csv"]\n'
                                                  'temperature_c = {"us06.csv" = 40}') +
                             _test("a.csv", temperature_c=10)))
    # a key naming one file of the config by its base name; a pulse test's own value
    assert cfg.temperature_for(sub / "us06.csv") == 40.0
    assert cfg.temperature_for(folder / "a.csv") == 10.0
    assert cfg.temperature_for(folder / "cycle.csv") is None
    series = read_series(cfg, sub / "us06.csv", "extra_cycles")
    assert series.temperature_c.tolist() == [40.0, 40.0]
    assert any("40 degC" in n for n in series.notes)
    one = load_config(_write(folder, HEAD + "temperature_c = 25\n" + _test("a.csv")))
    assert read_series(one, _two_rows(folder / "cycle.csv"), "cycle").temperature_c[0] == 25


@pytest.mark.parametrize("value, words", [
    ('{"nope.csv" = 25}', ["data.temperature_c names a missing file", "nope.csv"]),
    ('{"cycle.csv" = 400}', ["data.temperature_c.'cycle.csv'", "-60..100"]),
    ('"warm"', ["data.temperature_c", "a number or a table"]),
])
def test_bad_data_temperature_c(folder, value, words):
    with pytest.raises(InputError) as exc:
        load_config(_write(folder, HEAD + f"temperature_c = {value}\n" + _test("a.csv")))
    assert all(w in str(exc.value) for w in words), str(exc.value)
    assert "\n" not in str(exc.value)


def test_cycle_window_key_may_name_a_file_by_its_base_name(folder):
    """Before: the key had to repeat the path exactly as data.extra_cycles wrote it."""
    sub = folder / "runs"
    sub.mkdir()
    _two_rows(sub / "us06.csv")
    cfg = load_config(_write(folder, HEAD.replace('cycle = "cycle.csv"',
                                                  'extra_cycles = ["runs/us06.csv"]\n'
                                                  'cycle_window_s = {"us06.csv" = [0, 1]}') +
                             _test("a.csv")))
    assert cfg.window_for(sub / "us06.csv") == (0.0, 1.0)


# ------------------------------------------------------------ a separate temperature log

def _record(path, n=5):
    rows = "".join(f"{10 + k},0,3.7\n" for k in range(n))
    path.write_text("time_s,current_a,voltage_v\n" + rows)
    return path


def test_temperature_from_a_time_stamped_log(folder):
    """A thermocouple logged apart from the cycler, with its own time stamps on the same
    clock: interpolated onto the record; where the record runs past the log, its end
    value is held and said. A pulse test's temperature is then the median in its pulses."""
    from ecmgen.pipeline import read_series

    _record(folder / "cycle.csv")
    (folder / "cycle-temp.csv").write_text("Time (s),Temp (degC)\n10,20\n12,22\n13,23\n")
    cfg = load_config(_write(folder, HEAD + 'temperature_c = {"cycle.csv" = '
                                            '"cycle-temp.csv"}\n' + _test("a.csv")))
    assert cfg.temperature_for(folder / "cycle.csv") == folder / "cycle-temp.csv"
    assert folder / "cycle-temp.csv" in cfg.input_files()
    series = read_series(cfg, folder / "cycle.csv", "cycle")
    assert series.temperature_c.tolist() == [20.0, 21.0, 22.0, 23.0, 23.0]
    assert any("cycle-temp.csv" in n and "20.0 % of the record lies beyond" in n
               for n in series.notes)


@pytest.mark.parametrize("log, words", [
    # the Leaf's thermocouple files: values with no time column
    ("Temperature_1,Temperature_2\n25.1,25.3\n25.2,25.4\n",
     ["no time column", "cannot be placed on the record's clock"]),
    ("time_s,voltage_v\n10,3.7\n11,3.7\n", ["no temperature column"]),
    ("time_s,temperature_c\n1e9,25\n1.1e9,26\n", ["do not overlap", "same clock"]),
    ("time_s,temperature_c\n10,warm\n", ["line 2: not a number"]),
    # 1 s of a 4 s record: before, its two values were stretched over the whole record
    ("time_s,temperature_c\n12,25\n13,26\n", ["cover 25.0 %", "the log of another test"]),
])
def test_bad_temperature_logs_are_one_line(folder, log, words, capsys):
    _record(folder / "cycle.csv")
    (folder / "t.csv").write_text(log)
    cfg = _write(folder, '[cell]\ncapacity_ah = 2.9\n[data]\ndcir = "dcir.csv"\n'
                         'ocv = "ocv.csv"\ncycle = "cycle.csv"\n'
                         'temperature_c = {"cycle.csv" = "t.csv"}\n')
    (folder / "dcir.csv").write_text("soc,direction,t_s,r_ohm\n0.5,discharge,1,0.02\n")
    from ecmgen.pipeline import read_series

    with pytest.raises(InputError) as exc:
        read_series(load_config(cfg), folder / "cycle.csv", "cycle")
    msg = str(exc.value)
    assert "t.csv" in msg and "\n" not in msg and all(w in msg for w in words), msg
