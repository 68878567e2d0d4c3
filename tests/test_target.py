"""Generated C on Cortex-M: strict cross-compilation, size, no floating point in the fixed
variant, and bit-for-bit equality with the host under QEMU on a real drive cycle.

Needs gcc-arm-none-eabi, libnewlib-arm-none-eabi and qemu-system-arm (installed by .ci/run);
without them every test here is skipped with the reason and the install command."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from ecmgen.c import target
from ecmgen.c.codegen import prepare
from test_codegen_helpers import (cycle, load_cycle_t, panasonic_model, realistic_model, soc0_of,
                                  temperature_fitted_model, temperature_model)

pytestmark = pytest.mark.target

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]
VARIANT_IDS = ["float-vdt", "float-dt0.1", "fixed-vdt", "fixed-dt0.1"]


def _need(qemu: bool = False):
    reason = target.skip_reason(qemu=qemu)
    if reason:
        pytest.skip(reason)


@functools.lru_cache(maxsize=None)
def _model20():
    """The bench's table size: 20 RC breakpoints per direction."""
    return realistic_model(n_rc=20, seed=3)


@functools.lru_cache(maxsize=None)
def _models():
    """The bench's models: one temperature, 4 x 20 over temperature (own OCV grid and on
    the RC grid), 4 x 20 with the diffusion pair and the Butler-Volmer branch."""
    return {"1x20": _model20(), "4x20": temperature_model(4, 20, seed=3),
            "4x20-shared-ocv": temperature_model(4, 20, seed=3, ocv_on_rc_grid=True),
            "4x20-branches": temperature_model(4, 20, seed=3, branches=True)}


# 64-bit divisions that libgcc would supply: none may appear in the fixed-point step
DIV64 = {"__aeabi_ldivmod", "__aeabi_uldivmod", "__divdi3", "__udivdi3", "__moddi3", "__umoddi3"}
# what the fixed-point step may call in libgcc: 64-bit multiply and shifts (Cortex-M0) and
# the leading-zero count (M0 has no CLZ instruction); no division of any width
FIXED_HELPERS = {"__aeabi_lmul", "__aeabi_lasr", "__aeabi_llsl", "__aeabi_llsr", "__clzsi2"}


def test_skip_message_names_the_install_command(monkeypatch):
    import shutil

    monkeypatch.setattr(shutil, "which", lambda name: None)
    msg = target.skip_reason()
    assert "arm-none-eabi-gcc" in msg and "qemu-system-arm" in msg
    assert "apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm" in msg


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
@pytest.mark.parametrize("opt", ["-Os", "-O2"])
def test_cortex_m4f_strict_build_without_warnings(tmp_path, numeric, dt_s, opt):
    _need()
    obj = target.cross_compile(prepare(_model20(), numeric=numeric, dt_s=dt_s), tmp_path,
                               cpu="m4f", opt=opt)
    assert obj.warnings == ""
    sz = target.sizes(obj.obj)
    if opt == "-Os":
        assert sz["code"] < 2048, sz                   # target: < 2 KiB of code at -Os
    assert sz["data"] == 0 and sz["bss"] == 0, sz      # no mutable globals: RAM is the caller's
    undefined = target.undefined_symbols(obj.obj)
    if numeric == "float":
        assert undefined == []                          # no libm, no soft-float helper
        assert target.float_instructions(obj.obj)       # ... because the FPU does the work
    else:
        assert target.float_instructions(obj.obj) == []
        assert target.float_helpers(obj.obj) == []
        assert set(undefined) <= FIXED_HELPERS and not set(undefined) & DIV64, undefined


@pytest.mark.parametrize("cpu", ["m0", "m3"])
@pytest.mark.parametrize("dt_s", [None, 0.1], ids=["vdt", "dt0.1"])
def test_soft_float_cores_fixed_point_has_no_float(tmp_path, cpu, dt_s):
    _need()
    obj = target.cross_compile(prepare(_model20(), numeric="fixed", dt_s=dt_s), tmp_path, cpu=cpu)
    assert obj.warnings == ""
    assert target.float_helpers(obj.obj) == [], "soft-float routines referenced"
    assert target.float_instructions(obj.obj) == []
    sz = target.sizes(obj.obj)
    assert sz["code"] < 2048 and sz["data"] == 0 and sz["bss"] == 0, sz


@pytest.mark.parametrize("name", ["1x20", "4x20", "4x20-shared-ocv", "4x20-branches"])
@pytest.mark.parametrize("cpu", ["m4f", "m0"])
@pytest.mark.parametrize("dt_s", [None, 0.1], ids=["vdt", "dt0.1"])
def test_fixed_point_has_no_64_bit_division(tmp_path, name, cpu, dt_s):
    """The fixed-point step divides nothing (reciprocals come from a seed table and
    a Newton step): the Cortex-M4F and M0 objects reference no __aeabi_ldivmod /
    __aeabi_uldivmod / __divdi3 (nor any 32-bit division helper), at -Os and -O2; and the
    code stays under 2 KiB at -Os without the branches (with them it is reported by
    bench/bench_c.py)."""
    _need()
    spec = prepare(_models()[name], numeric="fixed", dt_s=dt_s)
    for opt in ("-Os", "-O2"):
        obj = target.cross_compile(spec, tmp_path / opt, cpu=cpu, opt=opt)
        undefined = set(target.undefined_symbols(obj.obj))
        assert not undefined & DIV64, (opt, undefined)
        assert not any("div" in u for u in undefined), (opt, undefined)
        assert undefined <= FIXED_HELPERS, (opt, undefined)
        assert target.float_instructions(obj.obj) == [] and target.float_helpers(obj.obj) == []
        sz = target.sizes(obj.obj)
        assert sz["data"] == 0 and sz["bss"] == 0, sz
        if opt == "-Os" and name != "4x20-branches":
            assert sz["code"] < 2048, (name, cpu, sz)


@pytest.mark.parametrize("name", ["4x20", "4x20-shared-ocv", "4x20-branches"])
def test_float_temperature_builds_on_m4f(tmp_path, name):
    _need()
    for dt_s in (None, 0.1):
        obj = target.cross_compile(prepare(_models()[name], numeric="float", dt_s=dt_s),
                                   tmp_path / str(dt_s), cpu="m4f")
        assert obj.warnings == "" and target.undefined_symbols(obj.obj) == []
        sz = target.sizes(obj.obj)
        assert sz["data"] == 0 and sz["bss"] == 0, sz
        if name != "4x20-branches":
            assert sz["code"] < 2048, (name, sz)


def test_float_variant_on_soft_float_core_would_need_helpers(tmp_path):
    """Sanity check of the detector: float code on an M0 calls the soft-float library."""
    _need()
    obj = target.cross_compile(prepare(_model20(), numeric="float"), tmp_path, cpu="m0")
    assert target.float_helpers(obj.obj)


@pytest.mark.slow
def test_qemu_cortex_m4_bit_exact_on_real_cycle(tmp_path):
    """>= 10 000 steps of the US06 record on an emulated Cortex-M4F: the four variants (linked
    together into one image) give the host's outputs and SOC bit for bit."""
    _need(qemu=True)
    model = panasonic_model()
    s = cycle("us06.mat")
    soc0 = soc0_of(model, s)
    a, b = 0, 12000
    # start at the record's beginning so soc0 (from the rested first sample) holds
    res = target.qemu_equivalence(model, s.time_s[a:b], s.current_a[a:b], soc0, cpu="m4f",
                                  out_dir=tmp_path)
    print("\n", res)
    assert set(res["variants"]) == {"float/variable-dt", "float/dt=0.1", "fixed/variable-dt",
                                    "fixed/dt=0.1"}
    for name, r in res["variants"].items():
        assert r["steps"] >= 10000 and r["bit_exact"], (name, r)


@pytest.mark.slow
def test_qemu_cortex_m3_soft_float_fixed_bit_exact(tmp_path):
    _need(qemu=True)
    model = panasonic_model()
    s = cycle("hwfet-a.mat")
    soc0 = soc0_of(model, s)
    res = target.qemu_equivalence(model, s.time_s[:10000], s.current_a[:10000], soc0, cpu="m3",
                                  out_dir=tmp_path)
    assert set(res["variants"]) == {"fixed/variable-dt", "fixed/dt=0.1"}
    for name, r in res["variants"].items():
        assert r["steps"] == 10000 and r["bit_exact"], (name, r)


@pytest.mark.slow
@pytest.mark.parametrize("surface_soc_gain, folder", [(0.0, "panasonic-18650pf-n10degC"),
                                                      (0.5, "panasonic-18650pf-n20degC")])
def test_qemu_cortex_m4_bit_exact_over_temperature(tmp_path, surface_soc_gain, folder):
    """The 14 x 21 test model (tables over temperature, diffusion pair, Butler-Volmer branch)
    on the last 12 000 steps of a US06 record with its cell temperature (-10 degC: the cell
    cools from 17 to -10 degC, then warms), and with the surface SOC (surface_soc_gain 0.5)
    on -20 degC US06: the four variants, float and fixed point, on an emulated Cortex-M4F
    equal the host bit for bit, u_diff included."""
    from dataclasses import replace

    _need(qemu=True)
    s = load_cycle_t(folder, "us06.mat")
    a, b = len(s) - 12000, len(s)
    res = target.qemu_equivalence(replace(temperature_fitted_model(),
                                          surface_soc_gain=surface_soc_gain),
                                  s.time_s[a:b], s.current_a[a:b], 0.9, cpu="m4f",
                                  out_dir=tmp_path, temperature_c=s.temperature_c[a:b])
    print("\n", res)
    assert set(res["variants"]) == {"float/variable-dt", "float/dt=0.1", "fixed/variable-dt",
                                    "fixed/dt=0.1"}
    for name, r in res["variants"].items():
        assert r["steps"] == 12000 and r["bit_exact"] and "u_diff" in r["fields"], (name, r)


@pytest.mark.slow
def test_qemu_cortex_m3_fixed_bit_exact_over_temperature(tmp_path):
    _need(qemu=True)
    s = load_cycle_t("panasonic-18650pf-n20degC", "hwfet.mat")
    res = target.qemu_equivalence(temperature_fitted_model(), s.time_s[:10000],
                                  s.current_a[:10000], 1.0, cpu="m3", out_dir=tmp_path,
                                  temperature_c=s.temperature_c[:10000])
    assert set(res["variants"]) == {"fixed/variable-dt", "fixed/dt=0.1"}
    for name, r in res["variants"].items():
        assert r["steps"] == 10000 and r["bit_exact"], (name, r)


# --- models with effects ---------------------------------------------------------------------

def _fx_models():
    """The Panasonic-like model with every effect each numeric mode carries (the parameters of
    test_codegen_effects): both carry hysteresis, extra_rc, current_dependent_resistance and
    capacity_error."""
    from test_codegen_effects import EFFECTS

    from ecmgen.c.codegen import C_EFFECTS

    base = panasonic_model()
    return {num: base.with_effects([e for n, e in EFFECTS.items() if n in C_EFFECTS[num]])
            for num in ("float", "fixed")}


def _check_fx(res, names, steps):
    assert set(res["variants"]) == set(names), res
    for name, r in res["variants"].items():
        assert r["steps"] >= steps, (name, r)
        assert "hysteresis" in r["effects"] and "extra_rc" in r["effects"], (name, r)
        assert set(r["fields"]) == {"v", "soc", "h", "u_x"}, (name, r)   # effect states compared
        assert r["bit_exact"], (name, r)


@pytest.mark.slow
def test_qemu_cortex_m4_bit_exact_with_effects(tmp_path):
    """12 000 steps of the US06 record through models with effects (hysteresis, extra_rc,
    current_dependent_resistance, capacity_error; float and fixed alike) on an emulated
    Cortex-M4F: voltage, SOC and the effect states h and u_x equal the host's bit for bit, on
    all four variants."""
    _need(qemu=True)
    models = _fx_models()
    s = cycle("us06.mat")
    soc0 = soc0_of(models["float"], s)
    n = 12000
    res = target.qemu_equivalence(models, s.time_s[:n], s.current_a[:n], soc0, cpu="m4f",
                                  out_dir=tmp_path)
    print("\n", res)
    _check_fx(res, {"float/variable-dt", "float/dt=0.1", "fixed/variable-dt", "fixed/dt=0.1"},
              10000)
    for name in res["variants"]:
        assert "current_dependent_resistance" in res["variants"][name]["effects"], name


@pytest.mark.slow
def test_qemu_cortex_m3_soft_float_fixed_bit_exact_with_effects(tmp_path):
    _need(qemu=True)
    models = _fx_models()
    s = cycle("hwfet-a.mat")
    soc0 = soc0_of(models["fixed"], s)
    res = target.qemu_equivalence(models, s.time_s[:10000], s.current_a[:10000], soc0, cpu="m3",
                                  out_dir=tmp_path)
    print("\n", res)
    _check_fx(res, {"fixed/variable-dt", "fixed/dt=0.1"}, 10000)
    assert all("current_dependent_resistance" in r["effects"] for r in res["variants"].values())


def test_firmware_records_effect_states_only_for_models_with_effects():
    from test_codegen_effects import EFFECTS

    base = _model20()
    plain = target.TargetRun(prepare(base, numeric="float", prefix="pa"),
                             np.zeros(3, np.float32), np.zeros(3, np.float32), 0.5)
    fx = target.TargetRun(prepare(base.with_effects([EFFECTS["hysteresis"], EFFECTS["extra_rc"]]),
                                  numeric="fixed", dt_s=0.1, prefix="fx"),
                          np.zeros(3, np.int32), None, 1 << 29)
    assert plain.fields == ("v", "soc") and fx.fields == ("v", "soc", "h", "u_x")
    src = target.firmware_main([plain, fx])
    assert "pa_out[6]" in src and "fx_out[12]" in src and "s.h;" in src and "s.u_x;" in src
