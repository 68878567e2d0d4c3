"""C generation: files, determinism, literals, strict compilation, symbols, refusal of bad
models. (Equivalence with Python: test_codegen_equiv.py; robustness: test_codegen_robust.py;
property tests: test_codegen_props.py; Cortex-M: test_target.py.)"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess

import numpy as np
import pytest

from ecmgen import __version__
from ecmgen.c import cref
from ecmgen.c.cbuild import STRICT_CFLAGS, host_cc
from ecmgen.c.codegen import (c_float, describe, file_names, generate_c, prepare, render,
                              runtime_dir)
from ecmgen.c.names import c_names
from ecmgen.errors import InputError
from conftest import C_DIR
from test_codegen_helpers import realistic_model

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]
VARIANT_IDS = ["float-vdt", "float-dt0.1", "fixed-vdt", "fixed-dt0.1"]


def _cc(args, cwd=None):
    proc = subprocess.run([*host_cc(), *map(str, args)], capture_output=True, text=True, cwd=cwd)
    assert proc.returncode == 0, proc.stderr
    return proc


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_files_banner_and_byte_identical(tmp_path, synthetic_model, numeric, dt_s):
    a = generate_c(synthetic_model, tmp_path / "a", prefix="cell", numeric=numeric, dt_s=dt_s)
    b = generate_c(synthetic_model, tmp_path / "b", prefix="cell", numeric=numeric, dt_s=dt_s)
    names = sorted(p.name for p in a)
    rt = ["ecmrt_f32_step.h", "ecmrt_f32.h"] if numeric == "float" else ["ecmrt_q_exp.h", "ecmrt_q_step.h", "ecmrt_q.h"]
    nm = file_names("cell", numeric)
    assert names == sorted([nm["header"], nm["source"], nm["config"], "ecmrt.h", *rt,
                            nm["filelist"], nm["report"]])
    for pa, pb in zip(a, b):
        assert pa.read_bytes() == pb.read_bytes(), pa.name
    # regenerating into the same folder leaves the files alone
    before = {p: p.stat().st_mtime_ns for p in a}
    generate_c(synthetic_model, tmp_path / "a", prefix="cell", numeric=numeric, dt_s=dt_s)
    assert {p: p.stat().st_mtime_ns for p in a} == before
    header = (tmp_path / "a" / nm["header"]).read_text()
    if dt_s is None:
        s = "f32" if numeric == "float" else "q"
        assert "Time step: variable" in header and f"cell_step_{s}(cell_state_{s}_t *s, " in header
    else:
        assert f"Time step: fixed, dt = {dt_s} s - D = 1/(1 - exp(-dt/tau))" in header
    sha = synthetic_model.sha256()
    for name in (nm["header"], nm["source"], nm["config"]):
        text = (tmp_path / "a" / name).read_text()
        assert f"ecmgen {__version__}" in text and sha in text
        assert text.isascii()
    # the runtime is copied verbatim
    for r in rt:
        assert (tmp_path / "a" / r).read_text() == (runtime_dir() / r).read_text()


def test_different_model_different_bytes(tmp_path, synthetic_model):
    from dataclasses import replace

    a = render(prepare(synthetic_model))["ecm_ecm_f32.c"]
    b = render(prepare(replace(synthetic_model, capacity_ah=3.0)))["ecm_ecm_f32.c"]
    assert a != b


def test_float_literals_round_trip(synthetic_model):
    for x in [0.0, 1.0, 3.0, 0.1, 1e-5, 123456789.0, 3.4e38, 1.17549435e-38, 2.0**-140, 0.3]:
        s = c_float(x)
        assert s.endswith("f") and ("." in s or "e" in s)
        assert np.float32(float(s[:-1])) == np.float32(x)
        assert len(re.sub(r"[^0-9]", "", s.split("e")[0]).strip("0")) <= 9
    rng = np.random.default_rng(3)
    bits = rng.integers(0, 0x7F800000, 2000, dtype=np.uint32)
    for f in bits.view(np.float32):
        assert np.float32(float(c_float(f)[:-1])).view(np.uint32) == f.view(np.uint32)
    # every literal of a generated file reads back to the spec's float32 values
    spec = prepare(synthetic_model, numeric="float", dt_s=0.1)
    text = render(spec)["ecm_ecm_f32.c"]
    lits = re.findall(r"(?<![\w.])(-?\d+\.\d*(?:e[-+]?\d+)?|-?\d+e[-+]?\d+)f\b", text)
    values = {np.float32(float(s)).view(np.uint32).item() for s in lits}
    d = spec.dirs[0]
    assert spec.tau_t and spec.rc_uniform     # the synthetic model: taus constant, uniform grid
    for arr in (spec.ocv, d.r0, d.k_fast, d.k_slow, [d.grid.x0, d.grid.inv_h, d.grid.n - 1]):
        assert set(np.asarray(arr, np.float32).ravel().view(np.uint32).tolist()) <= values
    # and a model with searched grids and time constants over SOC
    spec = prepare(realistic_model(), numeric="float")
    text = render(spec)["ecm_ecm_f32.c"]
    lits = re.findall(r"(?<![\w.])(-?\d+\.\d*(?:e[-+]?\d+)?|-?\d+e[-+]?\d+)f\b", text)
    values = {np.float32(float(s)).view(np.uint32).item() for s in lits}
    d = spec.dirs[0]
    assert not spec.tau_t and not spec.rc_uniform
    for arr in (spec.ocv, d.grid.x, d.grid.inv_dx, d.r0, d.k_fast, d.k_slow):
        assert set(np.asarray(arr, np.float32).ravel().view(np.uint32).tolist()) <= values


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
@pytest.mark.parametrize("opt", ["-O0", "-O2", "-Os"])
def test_strict_flags_compile_without_warnings(tmp_path, synthetic_model, numeric, dt_s, opt):
    generate_c(synthetic_model, tmp_path, prefix="ecm", numeric=numeric, dt_s=dt_s)
    proc = _cc([*STRICT_CFLAGS, opt, "-I", tmp_path, "-c",
                tmp_path / file_names("ecm", numeric)["source"],
                "-o", tmp_path / "ecm.o"])
    assert proc.stderr == ""


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_symbols_prefixed_and_no_mutable_globals(tmp_path, synthetic_model, numeric, dt_s):
    generate_c(synthetic_model, tmp_path, prefix="pk1", numeric=numeric, dt_s=dt_s)
    obj = tmp_path / "m.o"
    nm = c_names("pk1", numeric)
    _cc([*STRICT_CFLAGS, "-O2", "-fno-pic", "-I", tmp_path, "-c", tmp_path / nm["source"], "-o", obj])
    out = subprocess.run(["nm", obj], capture_output=True, text=True, check=True).stdout
    syms = [line.split() for line in out.splitlines() if line.strip()]
    defined_global = [s[-1] for s in syms if len(s) == 3 and s[1].isupper()]
    # the API and the tables (const, read by the estimator's .c)
    assert sorted(defined_global) == sorted([nm["init"], nm["run"], nm["step"], nm["tables"]])
    undefined = [s[-1] for s in syms if s[0] == "U"]
    assert undefined == []                          # no libc, no libm, no malloc
    writable = [s for s in syms if len(s) == 3 and s[1] in "bBdDcC"]
    assert writable == [], "mutable globals found"




def test_two_models_link_into_one_program(tmp_path, synthetic_model):
    generate_c(synthetic_model, tmp_path, prefix="cellA", numeric="float")
    generate_c(synthetic_model, tmp_path, prefix="cellB", numeric="fixed", dt_s=0.1)
    exe = tmp_path / "two"
    _cc([*STRICT_CFLAGS, "-O2", "-I", tmp_path, tmp_path / "cellA_ecm_f32.c", tmp_path / "cellB_ecm_q.c",
         C_DIR / "two_models_main.c", "-o", exe])
    out = subprocess.run([exe], capture_output=True, text=True, check=True).stdout.split()
    va, vb = float(out[0]), float(out[1])
    assert 3.0 < va < 4.3 and 3.0 < vb < 4.3 and abs(va - vb) < 0.01


def test_two_models_tables_meet_in_one_file(tmp_path, synthetic_model):
    """Each model's table types carry its prefix (<prefix>_model_<s>_t): a file that holds
    two models' tables, as an application reading both cells' parameters would, compiles
    (one shared type name would be a redefinition, an error in C99)."""
    generate_c(synthetic_model, tmp_path, prefix="cellA", numeric="float")
    generate_c(synthetic_model, tmp_path, prefix="cellB", numeric="float")
    both = tmp_path / "both.c"
    both.write_text('#include "cellA_ecm_f32_config.h"\n#include "cellB_ecm_f32_config.h"\n'
                    "float r0_ohm(void) { return cellA_model_f32.dir[0].rows[0] "
                    "+ cellB_model_f32.dir[0].rows[0]; }\n")
    _cc([*STRICT_CFLAGS, "-O2", "-I", tmp_path, "-c", both, "-o", tmp_path / "both.o"])

def _strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r'"[^"\n]*"', '""', text)            # string literals (version, hash)
    return re.sub(r"//[^\n]*", " ", text)


@pytest.mark.parametrize("dt_s", [None, 0.1], ids=["vdt", "dt0.1"])
def test_fixed_point_has_no_float(tmp_path, synthetic_model, dt_s):
    files = generate_c(synthetic_model, tmp_path, prefix="ecm", numeric="fixed", dt_s=dt_s)
    for p in files:
        if p.name.startswith("ecm_ecm_q.") and p.suffix in (".c", ".h"):
            code = _strip_comments(p.read_text())
            assert not re.search(r"\b(float|double)\b", code), p.name
            assert not re.search(r"\d\.\d*[fF]?\b|\d[eE][-+]?\d", code), p.name  # no FP literal
    # the whole translation unit after preprocessing, our files only (not libc headers)
    pre = _cc(["-std=c99", "-E", "-I", tmp_path, tmp_path / "ecm_ecm_q.c"]).stdout
    ours, keep = [], True
    for line in pre.splitlines():
        if line.startswith("# "):
            keep = str(tmp_path) in line
        elif keep:
            ours.append(line)
    tu = _strip_comments("\n".join(ours))
    assert "ecm_step_q" in tu and "ecmrt_q_count" in tu
    assert not re.search(r"\b(float|double)\b", tu)
    # the compiler agrees: x86-64 without SSE/x87 registers accepts it
    proc = subprocess.run([*host_cc(), "-mgeneral-regs-only", "-x", "c", "-c", "-o", "/dev/null", "-"],
                          input="int f(int a){return a;}\n", capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip("compiler lacks -mgeneral-regs-only (not x86-64 gcc/clang)")
    _cc([*STRICT_CFLAGS, "-O2", "-mgeneral-regs-only", "-I", tmp_path, "-c", tmp_path / "ecm_ecm_q.c",
         "-o", tmp_path / "m.o"])


def test_fixed_header_documents_q_formats(synthetic_model):
    for dt_s in (None, 0.1):
        spec = prepare(synthetic_model, numeric="fixed", dt_s=dt_s)
        h = render(spec)["ecm_ecm_q.h"]
        for key, val in spec.q.items():
            if key in ("Q_K", "Q_RATE"):
                continue
            assert f"#define ECM_ECM_Q_{key.removeprefix('Q_')} {val}" in h, key
        assert "Saturation:" in h and "Rounding:" in h and f"Q{spec.q['Q_I']}" in h
        tables = [getattr(d, f) for d in spec.dirs for f in cref.PARAMS]
        for arr in (spec.ocv, spec.ocv_grid.x, spec.ocv_grid.inv_dx, *tables):
            assert arr.dtype == np.int64 and arr.min() >= 0 and arr.max() <= 2**31 - 1
        # the formats use the range: each table's largest value has >= 30 significant bits
        d = spec.dirs[0]
        for f in ("r0", "r_fast", "r_slow"):
            assert max(getattr(x, f).max() for x in spec.dirs) >= 2**30
        assert d.grid.inv_dx.max() >= 2**30
        rep = describe(spec)
        assert rep["numeric"] == "fixed" and rep["q"] == spec.q


def test_runtime_constants_match_python_reference():
    q = (runtime_dir() / "ecmrt_q_exp.h").read_text() + (runtime_dir() / "ecmrt_q.h").read_text()
    tab = re.search(r"exp2_tab\[8\] = \{([^}]*)\}", q).group(1)
    assert tuple(int(v) for v in tab.replace("\n", " ").split(",")) == cref.Q_EXP2_TAB
    poly = re.search(r"poly\[7\] = \{([^}]*)\}", q).group(1)
    assert tuple(int(v) for v in poly.replace("\n", " ").split(",")) == cref.Q_POLY
    assert cref.Q_EXP2_TAB == tuple(round(2**30 * 2 ** (-j / 8)) for j in range(8))
    assert cref.Q_POLY == tuple(round((-1) ** k / math.factorial(k) * 2**30) for k in range(7))
    assert f"((int64_t){cref.Q_LOG2E})" in q and f"((int64_t){cref.Q_LN2})" in q
    assert f"((int64_t){cref.Q_XMAX26})" in q
    f = _strip_comments((runtime_dir() / "ecmrt_f32.h").read_text())
    lits = {np.float32(float(x)) for x in re.findall(r"(\d+\.\d*(?:e[-+]?\d+)?)f\b", f)}
    for c in (cref.F_INVLN2, cref.F_LN2_HI, cref.F_LN2_LO, cref.F_HALF_LN2, cref.F_XMAX,
              *cref.F_TAYLOR, *cref.F_SMALL):
        assert c in lits, c
    assert "(x - fn * 0.693145752f) - fn * 1.42860677e-06f" in f
    assert int(cref.F_SERIES_X.view(np.uint32)) == 0x3E800000 and "bits.u < 0x3E800000u" in f
    # the fixed-point polynomial below x = 1/4: the float one's coefficients in Q30
    small = re.search(r"one_minus_exp_neg_small\(int64_t x30\)\n\{(.*?)\n\}", q, re.S).group(1)
    size, fast = small.split("#else")       # -Os: Horner on a table; else unrolled, the same
    assert [int(v) for v in re.findall(r"(-?\d{6,})", fast)] == list(cref.Q_SMALL)
    assert [int(v) for v in re.findall(r"(-?\d{6,})", size)] == list(cref.Q_SMALL[::-1])
    assert "{0, ECMRT_ONE30, -" in size
    b = [float(v) for v in cref.F_SMALL]
    assert [abs(v) / 2**30 for v in cref.Q_SMALL] == pytest.approx(b, rel=1e-6)
    assert f"ECMRT_XSMALL_Q30 ((int64_t)1 << 28)" in q and cref.Q_XSMALL30 == 2**28


def test_make_file_list(tmp_path, synthetic_model):
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    generate_c(synthetic_model, tmp_path / "gen", prefix="bms", numeric="fixed")
    (tmp_path / "Makefile").write_text(
        "include gen/bms_ecm_q_files.mk\n"
        "show:\n\t@echo $(BMS_ECM_Q_SRCS)\n\t@echo $(BMS_ECM_Q_HDRS)\n\t@echo $(BMS_ECM_Q_INC)\n")
    out = subprocess.run(["make", "-s", "show"], cwd=tmp_path, capture_output=True, text=True,
                         check=True).stdout.split("\n")
    assert out[0] == "gen/bms_ecm_q.c"
    assert out[1].split() == ["gen/bms_ecm_q.h", "gen/bms_ecm_q_config.h", "gen/ecmrt.h",
                              "gen/ecmrt_q_exp.h", "gen/ecmrt_q_step.h", "gen/ecmrt_q.h"]
    assert out[2] == "gen"
    for p in [*out[0].split(), *out[1].split()]:
        assert (tmp_path / p).exists()


def test_report(tmp_path, synthetic_model):
    files = generate_c(synthetic_model, tmp_path, prefix="ecm", numeric="fixed", dt_s=0.1)
    rep = next(p for p in files if p.name.endswith("_report.md")).read_text()
    assert synthetic_model.sha256() in rep and "| current i |" in rep and "dt = 0.1 s" in rep


def test_generate_from_path(tmp_path, synthetic_model):
    path = synthetic_model.save(tmp_path / "model.json")
    files = generate_c(path, tmp_path / "out", numeric="float")
    assert (tmp_path / "out" / "ecm_ecm_f32.c").exists() and len(files) == 8


# --- refusal ----------------------------------------------------------------------------

def _broken(tmp_path, synthetic_model, how: str):
    raw = synthetic_model.to_json_dict()
    if how == "schema_version":
        raw["schema_version"] = 99
    elif how == "schema":
        raw["schema"] = "something.else"
    elif how == "missing_charge":
        del raw["rc"]["charge"]
    elif how == "missing_ocv":
        del raw["ocv"]
    elif how == "missing_r0":
        del raw["rc"]["discharge"]["r0_ohm"]
    elif how == "nan":
        raw["rc"]["charge"]["r0_ohm"][0][3] = float("nan")
    elif how == "inf":
        raw["ocv"]["ocv_v"][0][2] = float("inf")
    elif how == "short":
        raw["rc"]["discharge"]["tau_slow_s"][0] = raw["rc"]["discharge"]["tau_slow_s"][0][:-1]
    path = tmp_path / f"{how}.json"
    path.write_text(json.dumps(raw))          # json writes NaN/Infinity tokens
    return path


@pytest.mark.parametrize("how,words", [
    ("schema_version", "schema_version 99 is not supported"),
    ("schema", "not an ecmgen model"),
    ("missing_charge", "missing rc.charge"),
    ("missing_ocv", "missing ocv"),
    ("missing_r0", "missing rc.discharge.r0_ohm"),
    ("nan", "non-finite"),
    ("inf", "non-finite"),
    ("short", "must have 11 values per row"),
])
def test_bad_model_json_refused_before_any_file(tmp_path, synthetic_model, how, words):
    path = _broken(tmp_path, synthetic_model, how)
    out = tmp_path / "out"
    with pytest.raises(InputError) as exc:
        generate_c(path, out, numeric="fixed")
    assert words in str(exc.value) and path.name in str(exc.value)
    assert not out.exists()


def test_bad_in_memory_model_refused(tmp_path, synthetic_model):
    from dataclasses import replace

    bad = replace(synthetic_model, charge=replace(synthetic_model.charge,
                                                  r_slow_ohm=np.full(11, np.nan)))
    with pytest.raises(InputError, match="rc.charge.r_slow_ohm has non-finite"):
        generate_c(bad, tmp_path / "out")
    bad = replace(synthetic_model, capacity_ah=float("inf"))
    with pytest.raises(InputError, match="capacity_ah"):
        generate_c(bad, tmp_path / "out")
    bad = replace(synthetic_model, discharge=replace(synthetic_model.discharge,
                                                     tau_fast_s=np.zeros(11)))
    with pytest.raises(InputError, match="tau_fast_s"):
        generate_c(bad, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_fixed_point_smallest_time_constant(tmp_path, synthetic_model):
    """Variable-dt fixed point takes time constants down to 2^-16 s (ecmrt_q_c_dt_tau's shift
    stays >= 1 without a check in the step; the tables' taus are >= 1 ms, an extra_rc's
    may be smaller) and refuses smaller ones in one line."""
    from ecmgen.model import effects as fx

    def with_tau(tau):
        return synthetic_model.with_effects([fx.make_effect("extra_rc", r_ohm=0.01, tau_s=tau)])

    spec = prepare(with_tau(2.0**-16), numeric="fixed")
    assert spec.fx["x_k"] == 2 ** (spec.q["Q_T"] - 16)
    with pytest.raises(InputError, match="time constants too small for the fixed-point format"):
        generate_c(with_tau(0.9 * 2.0**-16), tmp_path / "out", numeric="fixed")
    assert not (tmp_path / "out").exists()
    prepare(with_tau(0.9 * 2.0**-16), numeric="float")


@pytest.mark.parametrize("kw,words", [
    ({"prefix": "1cell"}, "prefix"), ({"prefix": "a-b"}, "prefix"), ({"prefix": ""}, "prefix"),
    ({"numeric": "double"}, "numeric"), ({"dt_s": 0.0}, "dt_s"), ({"dt_s": -0.1}, "dt_s"),
    ({"dt_s": float("nan")}, "dt_s"), ({"i_max_a": -1.0}, "i_max_a"),
])
def test_bad_options_refused(tmp_path, synthetic_model, kw, words):
    with pytest.raises(InputError, match=words):
        generate_c(synthetic_model, tmp_path / "out", **kw)
    assert not (tmp_path / "out").exists()


def test_single_point_tables_and_effects_note(synthetic_model):
    from dataclasses import replace

    from ecmgen.model import RcTable

    one = RcTable(soc=np.array([0.5]), r0_ohm=np.array([0.02]), r_fast_ohm=np.array([0.01]),
                  tau_fast_s=np.array([2.0]), r_slow_ohm=np.array([0.01]),
                  tau_slow_s=np.array([50.0]), fit_error=np.zeros(1), converged=np.ones(1, bool))
    m = replace(synthetic_model, charge=one)
    spec = prepare(m, numeric="float")
    assert spec.dirs[1].grid.n == 2 and np.all(spec.dirs[1].r0 == np.float32(0.02))


def test_build_c_outputs_for_the_pipeline(tmp_path, synthetic_model):
    """What pipeline._write_c calls: C per numeric under c/<numeric>/, and the "c" block."""
    from types import SimpleNamespace

    from ecmgen.c.check import build_c_outputs
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate, validate

    t = np.arange(4000) * 0.1
    cur = np.where((t % 60) < 30, -3.0, 1.0)
    v = simulate(synthetic_model, t, cur, 0.9).voltage_v + 0.002
    val = validate(synthetic_model, TimeSeries(t, cur, v, source="cycle.csv"), soc0=0.9)
    result = SimpleNamespace(models={"curve": synthetic_model}, best="curve",
                             validations={"curve": {"cycle.csv": val}})
    for dt_s in (None, 0.1):
        cfg = SimpleNamespace(c_prefix="pk", c_numeric=("float", "fixed"), c_dt_s=dt_s)
        out = tmp_path / f"out{dt_s}"
        block = build_c_outputs(cfg, result, out)
        assert set(block) == {"float", "fixed"}
        for n, r in block.items():
            assert r["bit_exact_vs_reference"] and r["cycle"] == "cycle.csv"
            # the C against the Python model within the spec's tolerances (|dMAE|, max |dv|:
            # float 0.05 / 0.5 mV, fixed 0.5 / 2 mV); on the record's own time stamps the
            # Python model's MAE is the 2 mV offset (at a fixed 0.1 s step it is not)
            d_mae, d_max = {"float": (0.05e-3, 0.5e-3), "fixed": (0.5e-3, 2e-3)}[n]
            assert abs(r["mae_v"] - r["python_mae_v"]) <= d_mae, r
            assert r["max_abs_diff_vs_python_v"] <= d_max, r
            if dt_s is None:
                assert r["python_mae_v"] == pytest.approx(0.002, abs=1e-12), r
            nm = file_names("pk", n)
            assert r["dir"] == f"c/{n}" and f"c/{n}/{nm['source']}" in r["files"]
            rep = (out / "c" / n / nm["report"]).read_text()
            assert "| yes |" in rep
        json.dumps(block)
