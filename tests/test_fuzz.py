"""Property-based fuzzing of what a user hands ecmgen: configs, model.json files and
measurement CSVs, each a valid file mutated by hypothesis (values of every type and
size, keys removed, unknown keys, raw bytes, line ends, encodings).

Each case runs the command line in this process (``ecmgen.cli.main``) and must end in
success, or in exactly one line ``ecmgen: error: ...`` with exit 2: never a traceback,
never another exit code, never a file changed outside the command's ``--out``, and
``--json`` output is valid JSON. Seeded (the same cases every run); the case counts add
up to more than 2000 per run.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from ecmgen.cli import main
from ecmgen.config.schema import SECTIONS

def fuzz(cases: int) -> settings:
    return settings(FUZZ, max_examples=cases)


FUZZ = settings(deadline=None, database=None, derandomize=False, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow,
                                       HealthCheck.function_scoped_fixture,
                                       HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def files(tmp_path_factory, cell_files):
    """The synthetic cell's files and an 80-row cycle (fast to validate)."""
    folder = tmp_path_factory.mktemp("fuzz")
    for f in cell_files.iterdir():
        shutil.copy(f, folder / f.name)
    lines = (folder / "cycle.csv").read_text().splitlines()
    (folder / "short.csv").write_text("\n".join(lines[:81]) + "\n")
    return folder


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def check_outcome(argv, folder: Path, before: dict, out_dir: str | None = None) -> int:
    code, out, err = run(argv)
    assert code in (0, 2), (code, err)
    assert "Traceback" not in err
    if code == 2:
        assert err.startswith("ecmgen: error: ") and err.count("\n") == 1, err
    elif "--json" in argv:
        json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} in --json output"))
    after = snapshot(folder)
    if out_dir is not None:
        after = {k: v for k, v in after.items() if not k.startswith(out_dir + "/")}
    assert after == before, "a file outside --out changed"
    return code


# --------------------------------------------------------------------------- values

TEXTS = st.sampled_from(["", "pulses", "ocv.csv", "cycle.csv", "pulses.csv", "missing.csv",
                         "ecm", "ecmrt_f32", "ecm\n", "ekf", "ukf", "float", "fixed", "max",
                         "all", "curve", "lm", "mA", "V", "h", "discharge_positive", "../x",
                         "/proc/x", "°C", "\x00"]) | \
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)
NUMBERS = st.sampled_from([0, 1, -1, 2, 5, 0.5, 1e-300, 1e300, -1e300, 2**63, 1e6, 3600,
                           math.nan, math.inf, -math.inf]) | st.floats(-1e4, 1e4) | \
    st.integers(-10, 10)
SCALARS = NUMBERS | TEXTS | st.booleans()
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) |
                      st.dictionaries(st.sampled_from(["time", "x", "soc", "file", "a"]),
                                      inner, max_size=3), max_leaves=6)


# --------------------------------------------------------------------------- configs

def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(max(min(v, 2**63 - 1), -2**63))
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) \
            else repr(v)
    if isinstance(v, str):      # a TOML basic string; astral characters as they are (JSON
        return json.dumps(v, ensure_ascii=False)   # would escape them as surrogate pairs)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{toml_value(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


def toml_text(cfg: dict) -> str:
    lines = []
    for section, table in cfg.items():
        if isinstance(table, list):
            for entry in table:
                lines.append(f"[[{section}]]")
                lines += [f"{toml_value(k)} = {toml_value(v)}" for k, v in entry.items()]
        else:
            lines.append(f"[{section}]")
            lines += [f"{toml_value(k)} = {toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def key_values(section: str, name: str):
    """Values for one key: mostly near what it takes (its range, its choices), so that
    the fuzz reaches past the first check, and anything at all."""
    from ecmgen.config.schema import BY_NAME

    key = BY_NAME[section].key(name) if section in BY_NAME else None
    near = [VALUES]
    if key is not None and key.range is not None:
        lo, hi = key.range
        span = max(hi - lo, 1.0)
        near.append(st.floats(lo - 0.1 * span, min(hi + 0.1 * span, 1e300)))
        near.append(st.lists(st.floats(lo, min(hi, 1e6)), min_size=1, max_size=6))
    if key is not None and key.choices:
        near.append(st.sampled_from(key.choices))
        near.append(st.lists(st.sampled_from(key.choices), max_size=3))
    return st.one_of(near)


BASE_CONFIG = {"cell": {"capacity_ah": 2.9},
               "data": {"pulses": "pulses.csv", "ocv": "ocv.csv", "cycle": "cycle.csv"},
               "fit": {"methods": ["lm"]}, "c": {"numeric": ["float"]}}
SECTION_KEYS = [(s.name, k.name) for s in SECTIONS for k in s.keys if "." not in s.name] + \
    [("data.columns", k.name) for k in SECTIONS[3].keys] + \
    [("data.pulse_tests", k.name) for k in SECTIONS[2].keys] + \
    [("c", "typo"), ("fit", "methd"), ("nonsense", "x")]


@st.composite
def configs(draw) -> str:
    cfg = json.loads(json.dumps(BASE_CONFIG))
    for _ in range(draw(st.integers(1, 4))):
        section, key = draw(st.sampled_from(SECTION_KEYS))
        value = draw(key_values(section, key))
        if section == "data.pulse_tests":
            cfg["data"].pop("pulses", None)
            cfg.setdefault(section, [{"file": "pulses.csv"}])[0][key] = value
        elif draw(st.integers(0, 9)) == 0:
            cfg.get(section, {}).pop(key, None)
        else:
            cfg.setdefault(section, {})[key] = value
    text = toml_text(cfg)
    if draw(st.integers(0, 9)) == 0:             # raw damage: truncation, bytes, line ends
        cut = draw(st.integers(0, len(text)))
        text = text[:cut] + draw(st.sampled_from(["", "\r", "\x00", "\ufeff", "[", "=",
                                                  "\u00e9"])) + text[cut:]
    return text


@seed(16001)
@fuzz(700)
@given(text=configs(), as_bytes=st.sampled_from(["utf-8", "utf-8", "utf-8", "latin-1"]))
def test_fuzzed_configs(files, text, as_bytes):
    cfg = files / "fuzz.toml"
    cfg.write_bytes(text.encode(as_bytes, errors="replace"))
    before = snapshot(files)
    check_outcome(["validate", str(files / "model.json"), str(files / "short.csv"),
                   "--config", str(cfg), "--json"], files, before)


# --------------------------------------------------------------------------- model.json

def paths_of(doc, prefix=()) -> list[tuple]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += paths_of(v, prefix + (k,))
    elif isinstance(doc, list) and doc:
        out += paths_of(doc[0], prefix + (0,))
        if len(doc) > 1:
            out += paths_of(doc[-1], prefix + (len(doc) - 1,))
    return out


@st.composite
def model_texts(draw, base: dict) -> str:
    doc = json.loads(json.dumps(base))
    # hypothesis draws the first entries most often (its simplest choice): the table
    # numbers first, so that most cases get past the keys into the values
    paths = [p for p in paths_of(doc) if p]
    paths.sort(key=lambda p: (p[0] != "rc", p[0] != "ocv", len(p)))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(paths))
        holder = doc
        try:
            for k in path[:-1]:
                holder = holder[k]
            kind = draw(st.integers(0, 9))
            if kind == 0 and isinstance(holder, dict):
                del holder[path[-1]]
            elif kind == 1 and isinstance(holder, dict):
                holder[draw(st.sampled_from(["extra", "nme", "Method"]))] = draw(VALUES)
            elif kind == 2:
                holder[path[-1]] = [holder[path[-1]]] * draw(st.integers(0, 3))
            elif kind < 6 and isinstance(holder[path[-1]], (int, float)):
                holder[path[-1]] = draw(NUMBERS)      # a number where one belongs
            else:
                holder[path[-1]] = draw(VALUES)
        except (KeyError, IndexError, TypeError):
            continue                 # an earlier mutation removed or replaced the way
    text = json.dumps(doc, allow_nan=True)
    if draw(st.integers(0, 14)) == 0:
        cut = draw(st.integers(0, len(text)))
        text = text[:cut] + draw(st.sampled_from(["", "}", "\x00", "NaN", "[" * 50])) + \
            text[cut:]
    return text


@pytest.fixture(scope="module")
def model_doc(files):
    return json.loads((files / "model.json").read_text())


@seed(16002)
@fuzz(700)
@given(data=st.data())
def test_fuzzed_model_json(files, model_doc, data):
    text = data.draw(model_texts(model_doc))
    bad = files / "fuzz-model.json"
    bad.write_text(text)
    before = snapshot(files)
    check_outcome(["validate", str(bad), str(files / "short.csv"), "--json"], files, before)
    if data.draw(st.integers(0, 7)) == 0:        # codegen is slower: one case in eight
        numeric = data.draw(st.sampled_from(["float", "fixed"]))
        out = files / "c-out"
        code = check_outcome(["codegen", str(bad), "--out", str(out), "--numeric", numeric,
                              "-q"], files, before, out_dir="c-out")
        assert code == 0 or not out.exists(), "a refused model left C behind"
        shutil.rmtree(out, ignore_errors=True)


# --------------------------------------------------------------------------- CSV

CELLS = st.sampled_from(["", "nan", "inf", "-inf", "1e308", "-1e308", "abc", "1_0", "1,5",
                         "0x10", " 3.7 ", "1e-320", "3.7V", "-", "+", ".", "1e", "٣"]) | \
    st.floats(allow_nan=True, allow_infinity=True).map(repr) | \
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=6)
HEADERS = st.sampled_from(["time_s,current_a,voltage_v",
                           "time_s,current_a,voltage_v,temperature_c",
                           "Test_Time(s),Current(A),Voltage(V)",
                           "time_s,voltage_v,current_a", "t,i,v", "", "time_s;current_a;voltage_v",
                           "time_s,current_a,voltage_v,charge_ah"])


@st.composite
def csv_bytes(draw, lines: list[str]) -> bytes:
    drop = draw(st.integers(0, len(lines) - 1))       # 0, all rows, is drawn most often
    rows = [r.split(",") for r in lines[1:len(lines) - drop]]
    header = draw(HEADERS)
    width = max(1, len(header.replace(";", ",").split(",")))
    for r in rows:
        r[:] = (r + ["25.0", "0.1"])[:width]
    for _ in range(draw(st.integers(0, 4))):
        if not rows:
            break
        k = draw(st.integers(0, len(rows) - 1))
        kind = draw(st.integers(0, 5))
        if kind == 0:
            del rows[k]
        elif kind == 1:
            rows.insert(k, list(rows[k]))
        elif kind == 2:
            rows[k] = rows[k][:-1]
        else:
            j = draw(st.integers(0, len(rows[k]) - 1)) if rows[k] else 0
            if rows[k]:
                rows[k][j] = draw(CELLS)
    sep = ";" if ";" in header else ","
    end = draw(st.sampled_from(["\n", "\n", "\r\n", "\r"]))
    text = end.join([header] + [sep.join(r) for r in rows]) + draw(st.sampled_from([end, ""]))
    data = text.encode(draw(st.sampled_from(["utf-8", "utf-8", "latin-1", "utf-16"])),
                       errors="replace")
    if draw(st.integers(0, 9)) == 0:
        cut = draw(st.integers(0, len(data)))
        data = data[:cut] + draw(st.binary(max_size=8)) + data[cut:]
    return data


@seed(16003)
@fuzz(700)
@given(data=st.data())
def test_fuzzed_measurement_csv(files, data):
    lines = (files / "short.csv").read_text().splitlines()
    path = files / "fuzz.csv"
    path.write_bytes(data.draw(csv_bytes(lines)))
    before = snapshot(files)
    options = data.draw(st.sampled_from([[], ["--json"], ["--soc0", "0.8"],
                                         ["--temperature-c", "25"]]))
    check_outcome(["validate", str(files / "model.json"), str(path), *options], files, before)


# --------------------------------------------------------------------------- .mat

MAT_VALUES = st.sampled_from(["text", "", 0, 1e300, math.nan]) | \
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5) | \
    st.lists(st.lists(st.floats(-10, 10), min_size=2, max_size=2), max_size=3)


@st.composite
def mat_fields(draw, series) -> dict:
    import numpy as np

    fields = {"Time": series.time_s, "Current": series.current_a,
              "Voltage": series.voltage_v}
    if draw(st.booleans()):
        fields["Battery_Temp_degC"] = np.full(series.time_s.size, 25.0)
    for _ in range(draw(st.integers(0, 3))):
        name = draw(st.sampled_from(sorted(fields) + ["Ah", "Extra"]))
        kind = draw(st.integers(0, 4))
        if kind == 0:
            fields.pop(name, None)
        elif kind == 1 and name in fields:
            fields[name] = np.asarray(fields[name])[:draw(st.integers(0, 5))]
        elif kind == 2 and name in fields:
            fields[name] = np.asarray(fields[name]).reshape(-1, 1).repeat(2, axis=1)
        else:
            fields[name] = np.asarray(draw(MAT_VALUES), dtype=object) \
                if draw(st.booleans()) else draw(MAT_VALUES)
    return {"meas": fields} if draw(st.integers(0, 5)) else fields


@seed(16004)
@fuzz(300)
@given(data=st.data())
def test_fuzzed_measurement_mat(files, data):
    import scipy.io

    from ecmgen.data.measure import read_timeseries

    series = read_timeseries(files / "short.csv")
    path = files / "fuzz.mat"
    try:
        scipy.io.savemat(path, data.draw(mat_fields(series)))
    except Exception:            # a value scipy itself cannot write: not a case
        return
    before = snapshot(files)
    check_outcome(["validate", str(files / "model.json"), str(path), "--json"], files, before)
