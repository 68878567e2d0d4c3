"""Generated C == Python: bit for bit against the float32 / bit-true references, and within
the stated tolerances of the float64 model (simulate.py), on synthetic and real cycles."""

from __future__ import annotations

import numpy as np
import pytest

from ecmgen.c import cbuild, cref
from ecmgen.c.codegen import prepare
from ecmgen.c.runtime import runtime_dir
from conftest import C_DIR
from test_codegen_helpers import (CYCLES, assert_fields_equal, check_c_equivalence, cycle,
                                  panasonic_model, soc0_of)

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]
VARIANT_IDS = ["float-vdt", "float-dt0.1", "fixed-vdt", "fixed-dt0.1"]
# acceptance: |delta MAE| and max |delta v| against the float64 model
TOL = {"float": (0.05e-3, 0.5e-3), "fixed": (0.5e-3, 2e-3)}


def _profile(n=6000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.09, 0.11, n))
    t[rng.random(n) < 0.01] = 0.0                   # repeated stamps: dt = 0
    t = np.maximum.accumulate(np.where(t == 0, np.roll(t, 1), t))
    t -= t[0]
    cur = np.repeat(rng.uniform(-20, 8, n // 40 + 1), 40)[:n]
    cur[rng.random(n) < 0.15] = 0.0                  # rests and deadband crossings
    cur[rng.random(n) < 0.05] = 0.02
    return t, cur


def _all_fields_equal(got: cref.RefResult, ref: cref.RefResult) -> None:
    assert_fields_equal(got, ref, ("v", "soc", "u_fast", "u_slow", "charging"))


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_synthetic_bit_exact_and_close(synthetic_model, numeric, dt_s):
    cm = cbuild.build(synthetic_model, numeric=numeric, dt_s=dt_s)
    t, cur = _profile()
    dt = cref.dt_from_time(t)
    i_n, dt_n, s0 = cm.native_inputs(cur, dt if dt_s is None else None, 0.85)
    _all_fields_equal(cm.trace_native(i_n, dt_n, s0), cm.reference(cur, dt, 0.85))
    # the plain <prefix>_run loop gives the same voltages as the traced step
    run = cm.run_native(i_n, dt_n, s0)
    assert np.array_equal(run, cm.trace_native(i_n, dt_n, s0).v)
    r = cbuild.compare(synthetic_model, cm, t, cur, 0.85, measured_v=None)
    assert r["bit_exact_vs_reference"] and r["max_abs_diff_vs_reference_v"] == 0.0
    assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]


def test_starting_direction_and_deadband(synthetic_model):
    """Starts as discharge; |i| <= deadband keeps the last direction (simulate.py step 1)."""
    cm = cbuild.build(synthetic_model, numeric="float")
    db = synthetic_model.direction_deadband_a
    cur = np.array([0.0, db, 2 * db, db, 0.0, -db, -2 * db, -db / 2, 1.0])
    got = cm.trace_native(cur.astype(np.float32), np.full(cur.size, 0.1, np.float32), 0.5)
    assert got.charging.tolist() == [0, 0, 1, 1, 1, 1, 0, 0, 1]
    cmq = cbuild.build(synthetic_model, numeric="fixed")
    i_n, dt_n, s0 = cmq.native_inputs(cur, np.full(cur.size, 0.1), 0.5)
    assert cmq.trace_native(i_n, dt_n, s0).charging.tolist() == got.charging.tolist()


# --- the hand-written runtime's exp, unit-tested directly --------------------------------

@pytest.fixture(scope="module")
def exp_lib(tmp_path_factory):
    import cffi

    d = tmp_path_factory.mktemp("exp")
    ffi = cffi.FFI()
    ffi.cdef("void t_f32(const float *x, float *out, size_t n);"
             "void t_q(const int32_t *dt, const int32_t *tau, int32_t *out, size_t n);"
             "void t_recip(const uint32_t *d, uint32_t *r, uint32_t *sh, size_t n);")
    objs = []
    for name in ("runtime_math_f32", "runtime_math_q"):
        objs.append(str(d / f"{name}.o"))
        cbuild.run_cc([*cbuild.host_cc(), *cbuild.STRICT_CFLAGS, "-O2", "-fPIC", "-I",
                       str(runtime_dir()), "-c", str(C_DIR / f"{name}.c"), "-o", objs[-1]])
    ffi.set_source("_ecmgen_exp_test", "", extra_objects=objs)
    so = ffi.compile(tmpdir=str(d))
    return cbuild._load("_ecmgen_exp_test", so)


def test_runtime_exp_f32(exp_lib):
    ffi, lib = exp_lib.ffi, exp_lib.lib
    rng = np.random.default_rng(1)
    x = np.concatenate([[0.0, -1.0, np.nan, np.inf, 1e-30, 1e-7, 0.346573591, 0.3465736, 1.0,
                         86.99, 87.0, 1e30, -0.0, 1e-45, 1.2e-38, -1e-30, 0.03125, -0.03125],
                        10.0 ** rng.uniform(-8, 2.2, 20000), rng.uniform(0, 1, 5000),
                        rng.uniform(0, 0.3, 20000),    # the polynomial (x < 1/4) and its edge
                        np.nextafter(np.float32(0.25), np.float32([0, 1]))]).astype(np.float32)
    out = np.empty_like(x)
    lib.t_f32(ffi.from_buffer("float[]", x), ffi.from_buffer("float[]", out), x.size)
    ref = cref.one_minus_exp_neg_f32(x)
    assert np.array_equal(out.view(np.uint32), ref.view(np.uint32))
    ok = np.isfinite(x) & (x > 0)
    exact = -np.expm1(-x[ok].astype(np.float64))
    rel = np.abs(out[ok] - exact) / exact
    assert rel.max() < 2.5 * 2.0**-24          # within ~2 ulp of float32
    assert rel[x[ok] < 0.25].max() < 1.7 * 2.0**-24     # the polynomial: < 1.6 ulp
    assert np.signbit(out[x == 0]).sum() == 0   # -0 and +0 both give +0
    assert out[~ok & ~np.isinf(x)].tolist() == [0.0] * int(np.sum(~ok & ~np.isinf(x)))
    assert out[np.isposinf(x)][0] == 1.0


def test_runtime_exp_fixed(exp_lib):
    ffi, lib = exp_lib.ffi, exp_lib.lib
    rng = np.random.default_rng(2)
    q_t = 21
    # the domain the generator guarantees: dt >= 0 (the step clamps it), tau >= 2^-16 s
    tau = np.concatenate([[2**21, 2**(q_t - 16), 2**31 - 1, 2**(q_t - 16), 100],
                          rng.integers(2**10, 2**31 - 1, 20000)])
    dt = np.concatenate([[0, 6554, 2**31 - 1, 0, 1], rng.integers(0, 2**22, 20000)])
    tau, dt = tau.astype(np.int32), dt.astype(np.int32)
    out = np.empty_like(dt)
    lib.t_q(ffi.from_buffer("int32_t[]", dt), ffi.from_buffer("int32_t[]", tau),
            ffi.from_buffer("int32_t[]", out), dt.size)
    ref = cref.c_dt_tau_q(dt, tau, q_t)
    assert np.array_equal(out.astype(np.int64), ref)
    x = np.maximum(dt, 0) / 65536.0 / (tau / 2.0**q_t)
    exact = -np.expm1(-x) * 2**30
    # error budget in LSB of Q30: 1/tau to < 1e-8 relative (x e^-x 2^30 1e-8 < 4) + x
    # rounded to Q26 (8 e^-x) + y = x log2(e) rounded to Q26 (5.5 e^-x) + polynomial and
    # final roundings (~2): at most ~2e-8 absolute; below x = 1/4 (the polynomial, x in
    # Q30) ~2.5 LSB plus the reciprocal's error
    tol = 2 + 15 * np.exp(-x) + 4
    err = np.abs(out - exact)
    print(f"\nmax error {err.max():.2f} LSB of Q30; below x = 1/4: "
          f"{err[x < 0.25].max():.2f} LSB")
    assert np.all(err <= tol)
    assert np.all(err[x < 0.25] <= 2.5 + 1e-8 * exact[x < 0.25])
    assert out[0] == 0 and out[3] == 0 and out[2] == 2**30 and out[1] == 2**30


def test_runtime_recip(exp_lib):
    """The division-free reciprocal: C == reference bit for bit, relative error < 1e-8 and
    never above 1/d, over the whole int32 range and at every seed-table node."""
    ffi, lib = exp_lib.ffi, exp_lib.lib
    rng = np.random.default_rng(3)
    nodes = np.array([(64 + j) << 24 for j in range(64)], dtype=np.int64)
    d = np.unique(np.concatenate([np.arange(1, 5000), 2**31 - np.arange(1, 5000),
                                  rng.integers(1, 2**31, 200000), nodes, nodes - 1, nodes + 1,
                                  2 ** np.arange(31), 2 ** np.arange(1, 31) - 1]))
    d = d[(d >= 1) & (d < 2**31)].astype(np.uint32)
    r, sh = np.empty_like(d), np.empty_like(d)
    lib.t_recip(ffi.from_buffer("uint32_t[]", d), ffi.from_buffer("uint32_t[]", r),
                ffi.from_buffer("uint32_t[]", sh), d.size)
    rr, rsh = cref.recip_q(d.astype(np.int64))
    assert np.array_equal(r.astype(np.int64), rr) and np.array_equal(sh.astype(np.int64), rsh)
    approx = r.astype(np.float64) * np.ldexp(1.0, -sh.astype(np.int64)) * d.astype(np.float64)
    assert np.all(approx <= 1.0) and np.max(1.0 - approx) < 1e-8


# --- real drive cycles ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def pana():
    return panasonic_model()


@pytest.mark.slow
@pytest.mark.parametrize("name", CYCLES)
def test_real_cycles_variable_dt(pana, name):
    """Acceptance figures: the measured time stamps (non-uniform, repeated) drive both the C
    (variable-dt builds) and simulate.py."""
    s = cycle(name)
    soc0 = soc0_of(pana, s)
    res = cbuild.c_equivalence(pana, s, soc0)
    print(f"\n{name} ({len(s)} steps, soc0 {soc0:.4f}):")
    check_c_equivalence(res, len(s), TOL)


@pytest.mark.slow
def test_real_cycle_fixed_dt(pana):
    """Fixed-dt builds (dt_s = 0.1 s): the cycle resampled to the uniform grid drives the C
    and simulate.py alike."""
    s = cycle("us06.mat")
    soc0 = soc0_of(pana, s)
    res = cbuild.c_equivalence(pana, s, soc0, dt_s=0.1)
    for numeric in ("float", "fixed"):
        r = res[numeric]
        print(f"\nus06 fixed dt 0.1 s {numeric}: bit-exact {r['bit_exact_vs_reference']}, "
              f"|dMAE| {r['delta_mae_v'] * 1e3:.2e} mV, max|dv| {r['max_abs_diff_vs_python_v'] * 1e3:.2e} mV")
        assert r["bit_exact_vs_reference"] and r["dt"] == 0.1
        assert r["delta_mae_v"] <= TOL[numeric][0]
        assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]


def test_c_equivalence_block_shape(synthetic_model):
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate

    t, cur = _profile(3000, seed=5)
    v = simulate(synthetic_model, t, cur, 0.7).voltage_v + 0.001
    res = cbuild.c_equivalence(synthetic_model, TimeSeries(t, cur, v), 0.7)
    assert set(res) == {"float", "fixed"}
    for n, r in res.items():
        assert {"mae_v", "max_abs_diff_vs_python_v"} <= set(r)
        assert abs(r["mae_v"] - 0.001) <= TOL[n][0]     # the 1 mV offset, to the spec's |dMAE|
        assert all(np.isfinite(x) for x in r.values() if isinstance(x, float))


def test_resample_uniform():
    t = np.array([0.0, 0.1, 0.1, 0.25, 0.3, 0.5])
    i = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    v = np.array([3.0, 3.1, 3.2, 3.3, 3.4, 3.5])
    tu, iu, vu = cbuild.resample_uniform(t, i, v, 0.1)
    assert np.allclose(tu, [0, 0.1, 0.2, 0.3, 0.4, 0.5])
    # zero-order hold: the instant belongs to the sample whose interval (t_{k-1}, t_k] holds it
    assert iu.tolist() == [0.0, 1.0, 3.0, 4.0, 5.0, 5.0]
    assert np.allclose(vu[[0, 5]], [3.0, 3.5])


def test_fixed_spec_on_float_reference_refused(synthetic_model):
    with pytest.raises(ValueError):
        cref.simulate_f32(prepare(synthetic_model, numeric="fixed"), [0.0], [0.0])
    with pytest.raises(ValueError):
        cref.simulate_fixed_raw(prepare(synthetic_model, numeric="float"), [0])
