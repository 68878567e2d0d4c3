"""`ecmgen verify` checks every table entry, not the band a drive cycle reaches: golden
probes at every SOC x temperature segment of every table, the tables' fingerprint, and no
pass without the test program's own result line.

The model is the test model over temperature with diffusion and Butler-Volmer branches
(tests/test_codegen_helpers.temperature_model); its cycle stays near SOC 0.9 at 5..35 degC,
so a wrong entry at SOC 0.1 or 0.3 is reached by the probes alone. The figures over random
entries of the demo's C are bench/verify_coverage.py's.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ecmgen.c.codegen import c_float, generate_c, prepare
from ecmgen.c.golden import write_golden
from ecmgen.c.verify import verify
from ecmgen.data.measure import TimeSeries
from test_codegen_helpers import temperature_model

ARRAY = re.compile(r"static const (?:float|int32_t) (\w+)\[(\d+)\] = \{(.*?)\};", re.S)
STEM = {"float": "cov_ecm_f32", "fixed": "cov_ecm_q"}


@pytest.fixture(scope="module")
def golden(tmp_path_factory):
    """numeric -> (folder of the C and its vectors, CSpec)."""
    m = temperature_model(branches=True)
    t = np.cumsum(np.full(600, 1.0))
    cur = np.where((t % 120) < 60, -3.0, 0.0)           # ~0.1 of SOC from full
    series = TimeSeries(t, cur, None, np.full(t.size, 25.0), source="drive")
    out = {}
    for numeric in ("float", "fixed"):
        d = tmp_path_factory.mktemp(numeric)
        generate_c(m, d, prefix="cov", numeric=numeric)
        spec = prepare(m, numeric=numeric, prefix="cov")
        write_golden(spec, d, series, 1.0)
        out[numeric] = (d, spec)
    return out


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def _edit(src: str, name: str, index: int, new) -> str:
    """``src`` with element ``index`` of the array ``name`` replaced by ``new(old text)``."""
    m = next(a for a in ARRAY.finditer(src) if a.group(1) == name)
    tok = list(re.finditer(r"[^,\s]+", m.group(3)))[index]
    at = m.start(3) + tok.start()
    return src[:at] + new(tok.group(0)) + src[at + len(tok.group(0)):]


def _copy_with(golden_dir, tmp_path, stem, edit):
    mine = tmp_path / "mine"
    shutil.copytree(golden_dir, mine)
    c = mine / f"{stem}.c"
    c.write_text(edit(c.read_text()))
    return mine


def _row_near_25(spec) -> int:
    """The temperature row nearest 25 degC the step reads: a float table's last row is
    never read (the row before holds its values as differences)."""
    t = np.asarray(spec.temp_grid.x, dtype=np.float64) / (256.0 if spec.fixed else 1.0)
    row = int(np.argmin(np.abs(t - 25.0)))
    return row if spec.fixed else min(row, t.size - 2)


def _scaled(spec, factor=None, add_v=None):
    def new(tok):
        if spec.fixed:
            v = int(tok)
            return str(v + int(add_v * 2 ** spec.q["Q_V"]) if add_v else int(round(v * factor)))
        v = np.float32(float(tok.rstrip("f")))
        return c_float(v + np.float32(add_v) if add_v else v * np.float32(factor))
    return new


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_a_wrong_entry_far_from_the_cycle_fails_on_the_vectors(golden, tmp_path, numeric):
    """The issue's two cases, which passed with "0 differ": the OCV at SOC 0.10 + 0.5 V
    and R0 at SOC 0.30 x 10 (row nearest 25 degC). The vectors themselves catch them (a
    step differs), not only the fingerprint."""
    d, spec = golden[numeric]
    width = 1 if spec.fixed else 2                  # float tables hold (value, difference)
    row = _row_near_25(spec)
    soc = lambda g: np.asarray(g.x, float) / (2.0 ** 30 if spec.fixed else 1.0)  # noqa: E731
    k_ocv = int(np.argmin(np.abs(soc(spec.ocv_grid) - 0.10)))
    g = spec.dirs[0].grid
    k_r0 = int(np.argmin(np.abs(soc(g) - 0.30)))
    npar = 3 if spec.tau_t else 5
    cases = {"ocv": ("ocv_v", (row * spec.ocv_grid.n + k_ocv) * width, _scaled(spec, add_v=0.5)),
             "r0": ("dis_rows", (row * g.n + k_r0) * npar * width, _scaled(spec, factor=10.0))}
    for what, (name, index, new) in cases.items():
        mine = _copy_with(d, tmp_path / what, STEM[numeric],
                          lambda src: _edit(src, name, index, new))
        (v,) = verify(d, mine)
        assert not v.passed, (what, v.line)
        assert re.search(r"[1-9]\d* differ \(first at step \d+", v.line), (what, v.line)


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_random_table_values_raised_5_percent_fail_on_the_vectors(golden, tmp_path, numeric):
    """Values drawn at random (seeded) from every table of every direction, raised by 5 %:
    each copy fails on a differing step (float: beyond the tolerance). Float tables hold
    each value with its difference to the next temperature row; the values are drawn (the
    differences: bench/verify_coverage.py), not from the last row, which the interpolation
    never reads (its values are the row before plus the differences)."""
    d, spec = golden[numeric]
    src = (d / f"{STEM[numeric]}.c").read_text()
    n_t = spec.ocv.shape[0]
    pool = []
    for m in ARRAY.finditer(src):
        name, n = m.group(1), int(m.group(2))
        if not re.match(r"ocv_v|(dis|chg)_(rows|branch|tau)", name):
            continue
        per_row = n // n_t
        for k in range(n):
            if spec.fixed or (k % 2 == 0 and k < n - per_row):
                pool.append((name, k))
    rng = np.random.default_rng(7)
    for j in rng.choice(len(pool), size=6, replace=False):
        name, k = pool[j]
        mine = _copy_with(d, tmp_path / f"{name}{k}", STEM[numeric],
                          lambda s: _edit(s, name, k, _scaled(spec, factor=1.05)))
        (v,) = verify(d, mine)
        assert not v.passed, (name, k, v.line)
        if spec.fixed:
            assert re.search(r"[1-9]\d* differ", v.line), (name, k, v.line)
        else:
            assert re.search(r"[1-9]\d* beyond the tolerance", v.line), (name, k, v.line)


def test_the_fingerprint_catches_an_entry_no_step_reads(golden, tmp_path):
    """The float OCV's last temperature row is never read (its values are the row before
    plus the stored differences): changing it moves no step, and the tables' fingerprint
    fails the check."""
    d, spec = golden["float"]
    n = spec.ocv.size * 2
    mine = _copy_with(d, tmp_path, STEM["float"],
                      lambda s: _edit(s, "ocv_v", n - 2, _scaled(spec, add_v=0.5)))
    (v,) = verify(d, mine)
    assert not v.passed and ", 0 differ" in v.line and "not the generated" in v.line, v.line


def test_a_run_that_never_ran_or_stopped_early_fails(golden, tmp_path):
    """`--run true`, `--run echo` and a copy whose init calls exit(0) exit 0 without the
    program's result line: each is a failure (exit 1), whatever the exit status."""
    d, _ = golden["fixed"]
    for run in ("true", "echo"):
        res = _cli("verify", d, "--run", run)
        assert res.returncode == 1, (run, res.stdout, res.stderr)
        assert "no result line" in res.stdout, res.stdout

    def exit_in_init(src):
        src = src.replace('#include "cov_ecm_q_config.h"',
                          '#include "cov_ecm_q_config.h"\n#include <stdlib.h>', 1)
        return re.sub(r"(void cov_init_q\([^)]*\)\n\{\n)", r"\1    exit(0);\n", src)

    mine = _copy_with(d, tmp_path, STEM["fixed"], exit_in_init)
    assert "exit(0);" in (mine / "cov_ecm_q.c").read_text()
    res = _cli("verify", d, "--c", mine)
    assert res.returncode == 1 and "no result line" in res.stdout, res.stdout + res.stderr


@pytest.mark.parametrize("option, value", [("--cflags", '"-O2'), ("--cc", "'gcc"),
                                           ("--run", 'qemu "x')])
def test_unbalanced_quotes_are_one_line_exit_2(golden, option, value):
    d, _ = golden["fixed"]
    res = _cli("verify", d, option, value)
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr and option in res.stderr


def test_a_contracted_float_build_still_passes(golden, tmp_path):
    """The probes drive large currents; a compiler that fuses a*b+c (x86-64 FMA) changes
    the float results by rounding only, which stays inside the float tolerance (the C
    API docs' contract), on the probes too."""
    from ecmgen.c.cbuild import host_cc

    probe = subprocess.run([*host_cc(), "-mfma", "-x", "c", "-", "-o", tmp_path / "p"],
                           input="int main(void){return 0;}", capture_output=True, text=True)
    if probe.returncode != 0 or "fma" not in open("/proc/cpuinfo").read():
        pytest.skip("no FMA on this host")
    d, _ = golden["float"]
    (v,) = verify(d, cflags="-std=c99 -O2 -ffp-contract=fast -mfma")
    assert v.passed, v.line
