"""The firmware team's kit: float, fixed and estimator C in one image under one prefix,
golden vectors with their C test program, and ``ecmgen verify`` on a copy of the C."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ecmgen.c import target
from ecmgen.c.cbuild import STRICT_CFLAGS, host_cc
from ecmgen.c.codegen import generate_c, prepare
from ecmgen.c.estc import prepare_estimator
from ecmgen.c.estgolden import est_vector_names, write_est_golden
from ecmgen.c.golden import cycle_segment, vector_names, write_golden
from ecmgen.model.simulate import simulate
from ecmgen.config import EstimatorConfig
from ecmgen.data.measure import TimeSeries
from conftest import C_DIR
from test_codegen_helpers import temperature_model

ONE_IMAGE_MAIN = C_DIR / "one_image_main.c"



@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    """A model over temperature with branches, its float (+ estimator) and fixed C in one
    folder under one prefix, and golden vectors over a drive with rests."""
    d = tmp_path_factory.mktemp("kit")
    m = temperature_model(branches=True)
    t = np.cumsum(np.full(1500, 0.5))
    cur = np.where((t % 120) < 60, -6.0, np.where((t % 120) < 90, 3.0, 0.0))
    series = TimeSeries(t, cur, None, np.linspace(5.0, 35.0, t.size), source="drive")
    specs = {}
    for numeric in ("float", "fixed"):
        generate_c(m, d, prefix="pan", numeric=numeric,
                   estimator=EstimatorConfig() if numeric == "float" else None)
        specs[numeric] = prepare(m, numeric=numeric, prefix="pan")
        write_golden(specs[numeric], d, series, 0.9)
    est = prepare_estimator(m, specs["float"], EstimatorConfig())
    seg = cycle_segment(specs["float"], series, 0.9)
    v = simulate(m, t, cur, 0.9, series.temperature_c).voltage_v
    write_est_golden(specs["float"], est, d, seg, v)
    return d, specs


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def _formats(specs) -> list[str]:
    """-DQI, -DQV: the fixed point's formats, for tests/c/one_image_main.c."""
    q = specs["fixed"].q
    return [f"-DQI={q['Q_I']}", f"-DQV={q['Q_V']}"]


def test_float_fixed_and_estimator_link_into_one_program(kit, tmp_path):
    d, specs = kit
    exe = tmp_path / "all"
    srcs = [d / "pan_ecm_f32.c", d / "pan_est_f32.c", d / "pan_ecm_q.c", ONE_IMAGE_MAIN]
    proc = subprocess.run([*host_cc(), *STRICT_CFLAGS, *_formats(specs), "-O2", "-I", d, *srcs,
                           "-o", exe],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert subprocess.run([exe]).returncode == 0


def test_one_image_and_the_c_test_on_cortex_m4f(kit, tmp_path):
    reason = target.skip_reason(qemu=True)
    if reason:
        pytest.skip(reason)
    d, specs = kit
    flags = target.CPUS["m4f"]["flags"]
    (tmp_path / "startup.c").write_text(target.STARTUP)
    (tmp_path / "link.ld").write_text(target.LINKER_SCRIPT)
    start = tmp_path / "startup.o"
    subprocess.run([target.GCC, *flags, "-std=gnu99", "-O2", "-c", tmp_path / "startup.c", "-o",
                    start], check=True)
    progs = {"all": [d / "pan_ecm_f32.c", d / "pan_est_f32.c", d / "pan_ecm_q.c",
                     ONE_IMAGE_MAIN]}
    for numeric in ("float", "fixed"):
        stem = vector_names("pan", numeric)["test"][:-2]
        progs[stem] = [d / f"{stem}.c", d / f"{stem[:-5]}.c"]
    progs["pan_est_f32_test"] = [d / est_vector_names("pan")["test"], d / "pan_est_f32.c",
                                 d / "pan_ecm_f32.c"]
    for name, srcs in progs.items():
        elf = tmp_path / f"{name}.elf"
        proc = subprocess.run([target.GCC, *flags, *STRICT_CFLAGS, *_formats(specs), "-O2",
                               "-DECMV_HOSTED=0",
                               "-nostartfiles", "-T", tmp_path / "link.ld", "-I", d, *srcs, start,
                               "-lgcc", "-o", elf], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        run = subprocess.run([target.QEMU, "-M", target.CPUS["m4f"]["machine"], "-nographic",
                              "-monitor", "none", "-serial", "none", "-semihosting-config",
                              "enable=on,target=native", "-kernel", elf],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (name, run.returncode, run.stderr)   # main's return


def test_the_c_test_program_alone(kit, tmp_path):
    d, _ = kit
    for numeric in ("float", "fixed"):
        names = vector_names("pan", numeric)
        exe = tmp_path / numeric
        src = d / (names["test"][:-len("_test.c")] + ".c")
        proc = subprocess.run([*host_cc(), *STRICT_CFLAGS, "-O2", "-I", d, d / names["test"],
                               src, "-o", exe], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        run = subprocess.run([exe], capture_output=True, text=True)
        steps = re.search(r"_VEC_STEPS (\d+)u", (d / names["vectors"]).read_text()).group(1)
        assert run.returncode == 0 and f": PASS: {steps} steps, 0 differ" in run.stdout, \
            run.stdout


def _one_char(src: str, name: str) -> str:
    """``src`` with one digit of the middle value of the array ``name`` changed by 5: the
    last digit of an integer, the fourth decimal of a float (a float's last digits may
    round to the same float32)."""
    m = re.search(rf"static const \w+ {name}\[\d+\] = \{{(.*?)\}};", src, re.S)
    vals = list(re.finditer(r"-?\d[\d.e+-]*", m.group(1)))
    v = vals[len(vals) // 2]
    pos = v.group(0).index(".") + 4 if "." in v.group(0) else len(v.group(0)) - 1
    at = m.start(1) + v.start() + pos
    return src[:at] + str((int(src[at]) + 5) % 10) + src[at + 1:]


def test_verify_passes_and_names_the_first_differing_step(kit, tmp_path):
    """The C as generated passes; one character of a table value (the OCV's middle one) or
    of the estimator's settings changed: the check fails, naming the first step."""
    d, _ = kit
    res = _cli("verify", d)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.splitlines()[-1] == "ecmgen verify: 3 of 3 passed"
    for stem, where in (("pan_ecm_q", "ocv_v"), ("pan_ecm_f32", "ocv_v"),
                        ("pan_est_f32", None)):
        mine = tmp_path / stem
        shutil.copytree(d, mine)
        src = (mine / f"{stem}.c").read_text()
        if where is None:       # the estimator: the first digit of its voltage noise
            m = re.search(r"\.vn2 = (\d)", src)
            src = src[:m.start(1)] + str((int(m.group(1)) + 5) % 10) + src[m.end(1):]
        else:
            src = _one_char(src, where)
        (mine / f"{stem}.c").write_text(src)
        res = _cli("verify", d, "--c", mine, "--cflags", "-std=c99 -O1 -ffp-contract=off")
        assert res.returncode == 1, res.stdout + res.stderr
        line = next(ln for ln in res.stdout.splitlines() if ln.startswith(stem))
        assert ": FAIL: " in line and re.search(r"first at step \d+", line), line
        assert "failed: " + stem in res.stdout.splitlines()[-1]


def test_verify_bad_input_is_one_line_exit_2(kit, tmp_path):
    d, _ = kit
    for args in ([tmp_path / "nothing"], [tmp_path], [d, "--c", tmp_path / "nothing"],
                 [d, "--cc", "no-such-compiler-xyz"]):
        res = _cli("verify", *args)
        assert res.returncode == 2, (args, res.stdout, res.stderr)
        assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    empty = tmp_path / "mine"
    empty.mkdir()
    (empty / "x.c").write_text("")
    res = _cli("verify", d / "pan_ecm_q_vectors.h", "--c", empty)
    assert res.returncode == 2 and "pan_ecm_q.c" in res.stderr




def test_fixed_point_types_and_formats_break_the_build_when_they_change(kit, tmp_path):
    """The conversion macros are exact; code written for other formats does not compile."""
    d, specs = kit
    q = specs["fixed"].q
    qi, qv = q["Q_I"], q["Q_V"]

    def build(qi_, qv_):
        return subprocess.run([*host_cc(), *STRICT_CFLAGS, f"-DQI={qi_}", f"-DQV={qv_}", "-I", d,
                               C_DIR / "q_formats_main.c", d / "pan_ecm_q.c", "-o",
                               tmp_path / "f"], capture_output=True, text=True)

    ok = build(qi, qv)
    assert ok.returncode == 0, ok.stderr
    assert subprocess.run([tmp_path / "f"]).returncode == 0
    for other in ((qi, qv - 1), (qi + 1, qv)):          # a refit that moved a format
        assert build(*other).returncode != 0


def test_fast_math_is_refused(kit, tmp_path):
    d, _ = kit
    proc = subprocess.run([*host_cc(), "-std=c99", "-ffast-math", "-I", d, "-c",
                           d / "pan_ecm_f32.c", "-o", tmp_path / "x.o"], capture_output=True,
                          text=True)
    assert proc.returncode != 0 and "-ffast-math" in proc.stderr


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_codegen_writes_golden_vectors_that_verify_passes(tmp_path, numeric):
    """ecmgen codegen has no cycle: its vectors are a drive of pulses and rests and the
    edge-case set, and the C as written passes them."""
    model = temperature_model(branches=True).save(tmp_path / "model.json")
    out = tmp_path / "c"
    res = _cli("codegen", model, "--out", out, "--prefix", "cell", "--numeric", numeric, "-q")
    assert res.returncode == 0, res.stderr
    names = vector_names("cell", numeric)
    assert all((out / n).is_file() for n in names.values())
    res = _cli("verify", out)
    assert res.returncode == 0 and "1 of 1 passed" in res.stdout, res.stdout + res.stderr


def test_table_options_shrink_the_tables_and_keep_the_c_exact(tmp_path):
    """[c] ocv_soc_step / rc_soc_step (codegen --ocv-soc-step / --rc-soc-step): fewer table
    bytes, the ends kept, and the C still equal to its reference (verify passes)."""
    from ecmgen.c.codegen import describe
    from ecmgen.c.spec import coarsen_tables

    m = temperature_model(branches=True)
    coarse = coarsen_tables(m, 2, 3)
    assert coarse.ocv.soc[-1] == m.ocv.soc[-1] and coarse.charge.soc[0] == m.charge.soc[0]
    assert coarse.ocv.soc.size == (m.ocv.soc.size + 2) // 2
    for n in ("float", "fixed"):
        assert describe(prepare(coarse, n))["table_bytes"] < describe(prepare(m, n))["table_bytes"]
    model = m.save(tmp_path / "model.json")
    out = tmp_path / "c"
    res = _cli("codegen", model, "--out", out, "--numeric", "fixed", "--ocv-soc-step", "2",
               "--rc-soc-step", "3", "-q")
    assert res.returncode == 0, res.stderr
    assert f"{describe(prepare(coarse, 'fixed'))['table_bytes']} bytes" in \
        (out / "ecm_ecm_q.h").read_text()
    res = _cli("verify", out)
    assert res.returncode == 0, res.stdout + res.stderr
    res = _cli("codegen", model, "--out", tmp_path / "d", "--rc-soc-step", "0")
    assert res.returncode == 2 and "--rc-soc-step" in res.stderr
