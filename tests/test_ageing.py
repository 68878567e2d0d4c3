"""A model that knows its age: the ageing section of model.json, the simulation at an age,
and the C's set_age input, bit-exact to its references (host, sanitizers, Cortex-M4F under
QEMU) in both numerics; the fleet's law is checked in test_fleet.py."""

from __future__ import annotations

import functools
import json
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from ecmgen.c import cbuild, target
from ecmgen.c.cbuild import STRICT_CFLAGS, host_cc
from ecmgen.c.codegen import file_names, generate_c, prepare
from ecmgen.c.golden import vector_names, write_golden
from ecmgen.errors import InputError
from ecmgen.model.ageing import AgeingLaw
from ecmgen.model.model import model_from_json_dict
from ecmgen.model.simulate import simulate
from test_codegen_helpers import temperature_model

LAW = AgeingLaw([0.0, 200.0, 400.0, 700.0], [1.0, 1.08, 1.19, 1.45],
                [1.0, 0.962, 0.925, 0.86], "a test law")
VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]
VARIANT_IDS = ["float-vdt", "float-dt0.1", "fixed-vdt", "fixed-dt0.1"]


@functools.lru_cache(maxsize=None)
def _model():
    """Over temperature, with the diffusion pair and the Butler-Volmer branch, and a law."""
    return replace(temperature_model(branches=True), ageing=LAW)


def _drive(n=1500, seed=5):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 2.0, n))
    i = np.where((t % 300) < 150, -6.0, np.where((t % 300) < 220, 3.0, 0.0)) * rng.random(n)
    return t - t[0], i, np.linspace(-15.0, 40.0, n)


def test_the_section_round_trips_and_a_model_without_it_is_unchanged():
    m = _model()
    text = m.to_json()
    raw = json.loads(text)
    assert raw["ageing"]["version"] == 1 and raw["ageing"]["axis"] == "equivalent_full_cycles"
    assert model_from_json_dict(raw).to_json() == text
    plain = replace(m, ageing=None)
    assert "ageing" not in json.loads(plain.to_json())
    assert model_from_json_dict(json.loads(plain.to_json())).ageing is None


@pytest.mark.parametrize("change, words", [
    ({"version": 2}, "ageing.version 2 is not supported"),
    ({"axis": "throughput_ah"}, "ageing.axis must be"),
    ({"resistance_scale": [1.1, 1.2, 1.3, 1.4]}, "must be 1 at the first breakpoint"),
    ({"capacity_scale": [1.0, 0.9]}, "one value per breakpoint"),
    ({"equivalent_full_cycles": [0, 300, 200, 700]}, "strictly increasing"),
    ({"capacity_scale": [1.0, 0.9, "0.8", 0.7]}, "must be a list of numbers"),
    ({"knee": 3}, "unknown key ageing.'knee'"),
])
def test_a_bad_section_is_one_line_naming_the_file(change, words):
    raw = json.loads(_model().to_json())
    raw["ageing"].update(change)
    with pytest.raises(InputError) as exc:
        model_from_json_dict(raw, "aged.json")
    assert words in str(exc.value) and "aged.json" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_simulate_at_an_age_is_the_scaled_model():
    m = _model()
    t, i, temps = _drive()
    fresh = simulate(replace(m, ageing=None), t, i, 0.9, temps).voltage_v
    assert np.array_equal(simulate(m, t, i, 0.9, temps).voltage_v, fresh)
    assert np.array_equal(simulate(m, t, i, 0.9, temps, equivalent_full_cycles=0.0).voltage_v,
                          fresh)
    k_r, k_q = 1.08 + 0.5 * (1.19 - 1.08), 0.962 + 0.5 * (0.925 - 0.962)   # at 300 cycles

    def scaled(tb):
        return replace(tb, r0_ohm=k_r * tb.r0_ohm, r_fast_ohm=k_r * tb.r_fast_ohm,
                       r_slow_ohm=k_r * tb.r_slow_ohm, r_diff_ohm=k_r * tb.r_diff_ohm)

    by_hand = replace(m, ageing=None, capacity_ah=k_q * m.capacity_ah,
                      charge=scaled(m.charge), discharge=scaled(m.discharge))
    aged = simulate(m, t, i, 0.9, temps, equivalent_full_cycles=300.0)
    np.testing.assert_allclose(aged.voltage_v, simulate(by_hand, t, i, 0.9, temps).voltage_v,
                               atol=1e-12)
    assert np.max(np.abs(aged.voltage_v - fresh)) > 5e-3       # the age shows
    # clamped past the law's last breakpoint
    assert np.array_equal(simulate(m, t, i, 0.9, temps, equivalent_full_cycles=700.0).voltage_v,
                          simulate(m, t, i, 0.9, temps, equivalent_full_cycles=5000.0).voltage_v)


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_c_set_age_bit_exact_to_its_reference(numeric, dt_s):
    m = _model()
    t, i, temps = _drive()
    if dt_s is not None:
        t = dt_s * np.arange(t.size)
    cm = cbuild.build(m, numeric=numeric, dt_s=dt_s, prefix="ag")
    plain = cbuild.build(replace(m, ageing=None), numeric=numeric, dt_s=dt_s, prefix="ag0")
    fresh = cbuild.compare(replace(m, ageing=None), plain, t, i, 0.9, None, temps)
    for efc in (None, 0.0, 137.25, 300.0, 690.0, 5000.0, -3.0):
        res = cbuild.compare(m, cm, t, i, 0.9, None, temps, efc)
        assert res["bit_exact_vs_reference"], (efc, res)
        # to the float64 model as close as the fresh C is, plus the 1/capacity scale the C
        # interpolates between breakpoints (< 1e-4 relative on this law)
        assert res["max_abs_diff_vs_python_v"] < fresh["max_abs_diff_vs_python_v"] + 2e-4, efc
    # init is fresh: float, the same bits as the C of the model without the law; fixed
    # point, within the rounding of the wider formats the law's largest scales need
    dt = cbuild.cref.dt_from_time(t)
    v, v0 = cm.simulate(i, dt, 0.9, temps), plain.simulate(i, dt, 0.9, temps)
    if numeric == "float":
        assert np.array_equal(v, v0)
    else:
        assert np.max(np.abs(v - v0)) < 1e-5


def test_the_fixed_formats_make_room_for_the_law():
    plain = prepare(replace(_model(), ageing=None), numeric="fixed")
    aged = prepare(_model(), numeric="fixed")
    assert aged.q["Q_AR"] == 30 and aged.q["Q_AQ"] == 30 and aged.age["r"][0] == 1 << 30
    assert aged.q["Q_V"] <= plain.q["Q_V"] and aged.q["Q_K"] <= plain.q["Q_K"]
    assert aged.switches["AGE"] == 1 and plain.switches["AGE"] == 0


def test_golden_vectors_run_aged_and_pass_on_the_host(tmp_path):
    """codegen of an aged model: fresh drive, the drive aged, the edge cases past the law;
    the C test program passes them (ecmgen verify)."""
    path = _model().save(tmp_path / "model.json")
    for numeric in ("float", "fixed"):
        out = tmp_path / numeric
        res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "codegen", path, "--out", out,
                              "--prefix", "cell", "--numeric", numeric, "-q"],
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        text = (out / vector_names("cell", numeric)["vectors"]).read_text()
        n_seg = int(re.search(r"_VEC_SEGMENTS (\d+)u", text).group(1))
        # the drive fresh and aged, the edge cases past the law, then the probes (one per
        # segment of the law among them)
        assert n_seg > 3 and f"_age[{n_seg}]" in text
        res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "verify", out],
                             capture_output=True, text=True)
        assert res.returncode == 0 and ", 0 differ" in res.stdout, res.stdout + res.stderr


def test_golden_vectors_bit_exact_on_cortex_m4f(tmp_path):
    reason = target.skip_reason(qemu=True)
    if reason:
        pytest.skip(reason)
    flags = target.CPUS["m4f"]["flags"]
    (tmp_path / "startup.c").write_text(target.STARTUP)
    (tmp_path / "link.ld").write_text(target.LINKER_SCRIPT)
    start = tmp_path / "startup.o"
    subprocess.run([target.GCC, *flags, "-std=gnu99", "-O2", "-c", tmp_path / "startup.c",
                    "-o", start], check=True)
    for numeric, dt_s in VARIANTS:
        d = tmp_path / f"{numeric}-{dt_s}"
        generate_c(_model(), d, prefix="cell", numeric=numeric, dt_s=dt_s)
        write_golden(prepare(_model(), numeric=numeric, dt_s=dt_s, prefix="cell"), d)
        names = vector_names("cell", numeric)
        elf = d / "t.elf"
        proc = subprocess.run([target.GCC, *flags, *STRICT_CFLAGS, "-O2", "-DECMV_HOSTED=0",
                               "-nostartfiles", "-T", tmp_path / "link.ld", "-I", d,
                               d / names["test"], d / file_names("cell", numeric)["source"],
                               start, "-lgcc", "-o", elf], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        run = subprocess.run([target.QEMU, "-M", target.CPUS["m4f"]["machine"], "-nographic",
                              "-monitor", "none", "-serial", "none", "-semihosting-config",
                              "enable=on,target=native", "-kernel", elf],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (numeric, dt_s, run.returncode, run.stderr)


SAN_MAIN = r"""
#include <stdio.h>
#include <stdint.h>
#include "fv_ecm_f32.h"
#include "fd_ecm_f32.h"
#include "qv_ecm_q.h"
#include "qd_ecm_q.h"
static uint32_t rnd(uint32_t *x) { *x ^= *x << 13; *x ^= *x >> 17; *x ^= *x << 5; return *x; }
int main(int argc, char **argv)
{
    const float nan = 0.0f / (argc > 99 ? 1.0f : 0.0f);
    const float ages[] = {0.0f, -1e30f, 1e30f, 350.5f, 700.0f, 1e-45f, 0.0f};
    const int32_t qages[] = {INT32_MIN, -1, 0, 89728, 179200, INT32_MAX};
    fv_state_f32_t a; fd_state_f32_t b; qv_state_q_t c; qd_state_q_t d;
    uint32_t x = 2463534242u;
    long k, bad = 0;
    (void)argv;
    fv_init_f32(&a, 0.5f); fd_init_f32(&b, 0.5f); qv_init_q(&c, 1 << 29); qd_init_q(&d, 1 << 29);
    for (k = 0; k < 200000; k++) {
        const uint32_t r1 = rnd(&x), r2 = rnd(&x);
        const float fi = (float)(int32_t)r1 * (1.0f / 8388608.0f);
        const float ft = (float)(r2 >> 25) - 40.0f;
        if ((k & 255) == 0) {
            const float age = (k & 4096) ? nan : ages[(unsigned)(k >> 8) % 7u];
            fv_set_age_f32(&a, age); fd_set_age_f32(&b, age);
            qv_set_age_q(&c, qages[(unsigned)(k >> 8) % 6u]);
            qd_set_age_q(&d, qages[(unsigned)(k >> 9) % 6u]);
        }
        bad += !(fv_step_f32(&a, fi, ft, 0.5f) < 1e6f) + !(fd_step_f32(&b, fi, ft) < 1e6f);
        (void)qv_step_q(&c, (int32_t)r1 >> (r2 % 24u), (int32_t)(r2 >> 18), (int32_t)(r2 >> 13));
        (void)qd_step_q(&d, (int32_t)r1 >> (r2 % 24u), (int32_t)(r2 >> 18));
        bad += !(a.age_r >= 1.0f && a.age_r <= 1.46f) + (c.age_r < (1 << 30));
    }
    printf("bad %ld\n", bad);
    return bad != 0;
}
"""


def test_sanitized_set_age_and_step(tmp_path):
    cc = host_cc()
    probe = subprocess.run([*cc, *cbuild.SANITIZE_FLAGS, "-x", "c", "-", "-o", tmp_path / "p"],
                           input="int main(void){return 0;}\n", capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"compiler cannot build with sanitizers: {probe.stderr.strip()[:200]}")
    srcs = []
    for prefix, (numeric, dt_s) in zip(("fv", "fd", "qv", "qd"), VARIANTS):
        generate_c(_model(), tmp_path, prefix=prefix, numeric=numeric, dt_s=dt_s)
        srcs.append(tmp_path / file_names(prefix, numeric)["source"])
    (tmp_path / "main.c").write_text(SAN_MAIN)
    flags = [f for f in STRICT_CFLAGS if f != "-Werror"]
    proc = subprocess.run([*cc, *flags, *cbuild.SANITIZE_FLAGS, "-O1", "-I", tmp_path,
                           *srcs, tmp_path / "main.c", "-o", tmp_path / "san"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    run = subprocess.run([tmp_path / "san"], capture_output=True, text=True, timeout=300)
    assert "runtime error" not in run.stderr and "AddressSanitizer" not in run.stderr, run.stderr
    assert run.returncode == 0 and "bad 0" in run.stdout, run.stdout + run.stderr


def test_an_age_for_a_model_without_a_law_is_refused(tmp_path):
    plain = replace(_model(), ageing=None)
    t, i, temps = _drive(50)
    with pytest.raises(ValueError, match="no ageing law"):
        simulate(plain, t, i, 0.9, temps, equivalent_full_cycles=100.0)
    path = plain.save(tmp_path / "plain.json")
    cycle = tmp_path / "cycle.csv"
    cycle.write_text("time_s,current_a,voltage_v,temperature_c\n" + "".join(
        f"{a:.3f},{b:.3f},3.9,{c:.1f}\n" for a, b, c in zip(t, i, temps)))
    res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "validate", path, cycle,
                          "--soc0", "0.9", "--equivalent-full-cycles", "100"],
                         capture_output=True, text=True)
    assert res.returncode == 2 and "no ageing law" in res.stderr and "plain.json" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    aged = _model().save(tmp_path / "aged.json")
    res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "validate", aged, cycle,
                          "--soc0", "0.9", "--equivalent-full-cycles", "100", "--json"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("cpu", ["m4f", "m0"])
def test_fixed_point_set_age_and_step_have_no_division_nor_float(tmp_path, cpu):
    if target.skip_reason(qemu=False):
        pytest.skip(target.skip_reason(qemu=False))
    from test_target import DIV64, FIXED_HELPERS

    for dt_s in (None, 0.1):
        obj = target.cross_compile(prepare(_model(), numeric="fixed", dt_s=dt_s), tmp_path /
                                   str(dt_s), cpu=cpu, opt="-Os")
        assert obj.warnings == ""
        undefined = set(target.undefined_symbols(obj.obj))
        assert undefined <= FIXED_HELPERS and not undefined & DIV64, undefined
        assert target.float_instructions(obj.obj) == [] and target.float_helpers(obj.obj) == []


@pytest.mark.parametrize("cpu", ["m4f", "m3"])
def test_qemu_set_age_bit_for_bit_with_the_host(cpu):
    """The aged C on the emulated core and on the host (cffi), every recorded state field
    (voltage, SOC, u_diff) bit for bit: float and fixed on the M4F, fixed on the M3."""
    if target.skip_reason(qemu=True):
        pytest.skip(target.skip_reason(qemu=True))
    t, i, temps = _drive(1200)
    for efc in (412.0, 5000.0):
        res = target.qemu_equivalence(_model(), t, i, 0.9, cpu=cpu, temperature_c=temps,
                                      efc=efc)
        assert res["variants"] and all(v["bit_exact"] for v in res["variants"].values()), res
