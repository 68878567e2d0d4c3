"""Generated C for models with diagnose effects (hysteresis, extra_rc,
current_dependent_resistance, capacity_error): C == float32 / bit-true references bit for bit
on every step and state (h, u_x included), and within the stated tolerances of the float64
model (simulate.py with the effects); unsupported effects refused before any file is written."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import PANASONIC, need
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_codegen_helpers import load_mat, realistic_model, soc0_of

from ecmgen.c import cbuild, cref
from ecmgen.model import effects as fx
from ecmgen.c.codegen import C_EFFECTS, file_names, generate_c, prepare, render
from ecmgen.c.qformat import cdr_nodes
from ecmgen.errors import InputError

TOL = {"float": (0.05e-3, 0.5e-3), "fixed": (0.5e-3, 2e-3)}     # |dMAE|, max |dv|
EFFECTS = {
    "hysteresis": fx.make_effect("hysteresis", m_v=0.02, decay_ah=0.15, m0_v=0.004,
                                 ocv_table_state=0.3, initial_state=0.5),
    "extra_rc": fx.make_effect("extra_rc", r_ohm=0.015, tau_s=700.0),
    "current_dependent_resistance": fx.make_effect("current_dependent_resistance",
                                                   scale_at_zero=1.2, i0_a=3.0),
    "capacity_error": fx.make_effect("capacity_error", capacity_scale=0.93),
}
FIELDS = ("v", "soc", "u_fast", "u_slow", "charging", "h", "u_x")


@functools.lru_cache(maxsize=None)
def _base():
    return realistic_model(n_rc=12, seed=5)


def _model(names):
    return _base().with_effects([EFFECTS[n] for n in names])


def _all(numeric):
    return tuple(n for n in EFFECTS if n in C_EFFECTS[numeric])


@functools.lru_cache(maxsize=None)
def _cm(names: tuple, numeric: str, dt_s):
    return cbuild.build(_model(names), numeric=numeric, dt_s=dt_s, prefix="fxt")


def _profile(n=8000, seed=2):
    """Non-uniform, repeated time stamps; discharge pulses, charge, rests, deadband."""
    rng = np.random.default_rng(seed)
    dt = np.where(rng.random(n) < 0.1, 0.1, 1.0)
    dt[rng.random(n) < 0.01] = 0.0
    dt[0] = 0.0
    t = np.cumsum(dt)
    cur = np.repeat(rng.normal(-2.0, 4.0, n // 20 + 1), 20)[:n]
    cur[1000:1400] = 0.0
    cur[3000:3100] = 0.01                       # inside the deadband
    cur[5000:5600] = 1.5                        # a charge stretch
    return t, cur


def _fields_equal(got, ref):
    for f in FIELDS:
        a, b = getattr(got, f), getattr(ref, f)
        if a is None and b is None and f in ("h", "u_x"):
            continue                    # capacity_error alone: the plain runtime, no effect state
        assert a is not None and b is not None, f
        if a.dtype == np.float32:
            a, b = a.view(np.uint32), np.asarray(b).astype(np.float32).view(np.uint32)
        else:
            a, b = a.astype(np.int64), np.asarray(b).astype(np.int64)
        bad = np.flatnonzero(a != b)
        assert bad.size == 0, f"{f} differs at {bad.size} steps, first {bad[:5]}"


CASES = [((n,), num) for num in ("float", "fixed") for n in EFFECTS if n in C_EFFECTS[num]]
CASES += [(_all("float"), "float"), (_all("fixed"), "fixed")]


@pytest.mark.parametrize("dt_s", [None, 1.0], ids=["vdt", "dt1"])
@pytest.mark.parametrize("names,numeric", CASES, ids=[f"{num}-{'+'.join(n)}" for n, num in CASES])
def test_effects_bit_exact_and_close(names, numeric, dt_s):
    cm = _cm(names, numeric, dt_s)
    t, cur = _profile()
    if dt_s is not None:
        t = dt_s * np.arange(t.size, dtype=np.float64)
    dt = cref.dt_from_time(t)
    i_n, dt_n, s0 = cm.native_inputs(cur, dt if dt_s is None else None, 0.8)
    got = cm.trace_native(i_n, dt_n, s0)
    _fields_equal(got, cm.reference(cur, dt, 0.8))
    assert np.array_equal(cm.run_native(i_n, dt_n, s0), got.v)
    r = cbuild.compare(_model(names), cm, t, cur, 0.8)
    assert r["bit_exact_vs_reference"], r
    assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1], r
    # the effect really acts: the C differs from the plain model by more than the tolerance
    if dt_s is None:
        plain = cbuild.python_voltage(_base(), t, cur, 0.8)
        v_c = cm.simulate(cur, dt, 0.8)
        assert np.max(np.abs(v_c - plain)) > 5 * TOL[numeric][1]


def test_state_starts_at_initial_hysteresis():
    cm = _cm(("hysteresis",), "float", None)
    s = cm.new_state(0.5)
    assert s.h == np.float32(0.5)
    assert "u_x" not in dir(s)              # the state has only the fields the model needs
    cmq = _cm(("hysteresis", "extra_rc"), "fixed", None)
    sq = cmq.new_state(cref.ONE30 // 2)
    assert sq.h == 2**29 and sq.u_x == 0


def test_real_panasonic_stretch():
    """A real US06 stretch (measured, non-uniform time stamps) through every variant."""
    s = load_mat(need(PANASONIC / "us06.mat"))
    n = min(len(s.time_s), 6000)
    from ecmgen.data.measure import TimeSeries

    part = TimeSeries(s.time_s[:n], s.current_a[:n], s.voltage_v[:n], source="us06.mat")
    for numeric in ("float", "fixed"):
        model = _model(_all(numeric))
        soc0 = soc0_of(model, part)
        r = cbuild.c_equivalence(model, part, soc0, numerics=(numeric,))[numeric]
        print(f"\nus06[:{n}] {numeric} effects {_all(numeric)}: bit-exact "
              f"{r['bit_exact_vs_reference']}, |dMAE| {r['delta_mae_v'] * 1e3:.2e} mV, "
              f"max|dv| {r['max_abs_diff_vs_python_v'] * 1e3:.2e} mV")
        assert r["bit_exact_vs_reference"]
        assert r["delta_mae_v"] <= TOL[numeric][0]
        assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]
    # fixed dt (resampled to 1 s)
    for numeric in ("float", "fixed"):
        model = _model(_all(numeric))
        r = cbuild.c_equivalence(model, part, soc0_of(model, part), dt_s=1.0,
                                 numerics=(numeric,))[numeric]
        print(f"us06[:{n}] {numeric} dt 1 s: bit-exact {r['bit_exact_vs_reference']}, "
              f"max|dv| {r['max_abs_diff_vs_python_v'] * 1e3:.2e} mV")
        assert r["bit_exact_vs_reference"] and r["dt"] == 1.0
        assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]


# --- hypothesis --------------------------------------------------------------------------

SETTINGS = settings(max_examples=25, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
current = st.one_of(st.floats(-300.0, 300.0, allow_nan=False, width=32),
                    st.sampled_from([0.0, 0.029, -0.029, 1e-30, -1e6, 1e6]))
step_dt = st.one_of(st.floats(0.0, 20.0, width=32), st.sampled_from([0.0, 0.1, 1e-7, 3600.0, 1e5]))


@st.composite
def profiles(draw, max_size=200):
    n = draw(st.integers(1, max_size))
    runs = draw(st.lists(st.tuples(current, st.integers(1, 30)), min_size=1, max_size=20))
    cur = np.resize(np.repeat([c for c, _ in runs], [k for _, k in runs]), n).astype(np.float64)
    dts = np.array(draw(st.lists(step_dt, min_size=n, max_size=n)), dtype=np.float64)
    return cur, dts, draw(st.floats(-0.3, 1.3))


@SETTINGS
@given(profiles())
def test_property_all_effects_bit_exact(p):
    cur, dts, soc0 = p
    for numeric in ("float", "fixed"):
        for dt_s in (None, 1.0):
            cm = _cm(_all(numeric), numeric, dt_s)
            i_n, dt_n, s0 = cm.native_inputs(cur, dts if dt_s is None else None, soc0)
            got = cm.trace_native(i_n, dt_n, s0)
            _fields_equal(got, cm.reference(cur, dts, soc0))
            if numeric == "float":
                assert np.all(np.isfinite(got.v)) and np.all(np.abs(got.h) <= 1.0)


@SETTINGS
@given(profiles())
def test_property_close_to_float64(p):
    cur, dts, soc0 = p
    cur = np.clip(cur, -30.0, 12.0)
    dts = np.clip(dts, 0.0, 2.0)
    soc0 = float(np.clip(soc0, 0.0, 1.0))
    t = np.cumsum(dts) - dts[0]
    for numeric in ("float", "fixed"):
        model = _model(_all(numeric))
        v64 = cbuild.python_voltage(model, t, cur, soc0)
        v = _cm(_all(numeric), numeric, None).simulate(cur, cref.dt_from_time(t), soc0)
        assert np.max(np.abs(v - v64)) <= TOL[numeric][1], numeric


# --- unit checks of the runtime's asinh pieces -----------------------------------------------

def test_asinh_factor_accuracy():
    x = np.logspace(-12, 8, 5000).astype(np.float32)
    g = cref.cdr_factor_f32(x, 1.0, 1.0).astype(np.float64)
    x64 = x.astype(np.float64)
    assert np.max(np.abs(g / (np.arcsinh(x64) / x64) - 1.0)) < 1e-6


def _cdr_model(scale, i0):
    return _base().with_effects([fx.make_effect("current_dependent_resistance",
                                                scale_at_zero=scale, i0_a=i0)])


@pytest.mark.parametrize("scale,i0", [(1.2, 3.0), (0.05, 0.02), (7.5, 40.0), (100.0, 1.0),
                                      (1.0, 0.002)])
def test_fixed_cdr_factor_accuracy_and_format(scale, i0):
    """The integer g(|i|) of ecmrt_q_fx_cdr_factor (cref.cdr_factor_q) against float64
    scale asinh(x)/x over the whole int32 current range: relative error < 3e-5; its Q format
    is the largest <= 30 that holds the table's maximum (~scale)."""
    spec = prepare(_cdr_model(scale, i0), numeric="fixed")
    f = spec.fx
    assert f["CDR_QG"] == min(30, int(np.floor(np.log2((2**31 - 1) / f["g_max"]))))
    assert int(np.max(f["g_tab"])) <= 2**31 - 1 and int(np.min(f["g_tab"])) > 0
    q_i = spec.q["Q_I"]
    rng = np.random.default_rng(1)
    node = np.round(cdr_nodes(f["CDR_E"]) * i0 * 2.0**q_i).astype(np.int64)   # x at the nodes
    ai = np.unique(np.concatenate([
        np.arange(0, 5000), 2**31 - np.arange(0, 5000), rng.integers(0, 2**31, 200000),
        np.round(np.logspace(0, 31, 100000, base=2.0)).astype(np.int64),
        node - 1, node, node + 1]))
    ai = ai[(ai >= 0) & (ai <= 2**31)]
    g = cref.cdr_factor_q(ai, f) / 2.0**f["CDR_QG"]
    x = np.maximum(ai / 2.0**q_i / i0, 1e-12)
    g64 = scale * np.arcsinh(x) / x
    err = np.max(np.abs(g / g64 - 1.0))
    print(f"\nscale {scale} i0 {i0}: Q{f['CDR_QG']}, x < 2^{f['CDR_E']}, {f['g_tab'].size} nodes, "
          f"max rel err {err:.2e}")
    # interpolation < 3.5e-5 relative, plus the rounding of nodes and interpolation (1 LSB)
    assert np.all(np.abs(g - g64) <= 3.5e-5 * g64 + 2.0**-f["CDR_QG"])
    if f["CDR_E"] <= 8:
        assert err < 2.5e-5


@pytest.mark.parametrize("scale,i0", [(1.2, 3.0), (7.5, 0.4), (0.3, 200.0)])
@pytest.mark.parametrize("dt_s", [None, 1.0], ids=["vdt", "dt1"])
def test_fixed_cdr_table_edges_bit_exact(scale, i0, dt_s):
    """Currents on and next to every table node and binade boundary, 0, the int32 extremes:
    C == bit-true reference on every step and state."""
    cm = cbuild.build(_cdr_model(scale, i0), numeric="fixed", dt_s=dt_s, prefix="cdr")
    f = cm.spec.fx
    node = np.round(cdr_nodes(f["CDR_E"]) * i0 * 2.0**cm.spec.q["Q_I"]).astype(np.int64)
    raw = np.concatenate([node - 1, node, node + 1, [0, 1, 2**31 - 1, -2**31, -2**31 + 1]])
    raw = np.clip(np.concatenate([raw, -raw]), -2**31, 2**31 - 1).astype(np.int32)
    n = raw.size
    dt = np.full(n, 65536 // 10, dtype=np.int32) if dt_s is None else None
    got = cm.trace_native(raw, dt, cref.ONE30 // 2)
    ref = cref.simulate_fixed_raw(cm.spec, raw.astype(np.int64),
                                  None if dt is None else dt.astype(np.int64), cref.ONE30 // 2)
    _fields_equal(got, ref)


# --- refusals and generated files --------------------------------------------------------------

@pytest.mark.parametrize("numeric", ["float", "fixed"])
@pytest.mark.parametrize("dt_s", [None, 1.0], ids=["vdt", "dt1"])
def test_temperature_dependence_generated(numeric, dt_s):
    """temperature_dependence (refused before the step had a temperature input): with the
    other effects, C == reference bit for bit and within tolerance of simulate.py at a
    temperature sweeping -30 .. 50 degC."""
    m = _model(_all(numeric)).with_effects(
        list(_model(_all(numeric)).effects) +
        [fx.make_effect("temperature_dependence", activation_k=4000.0, t_ref_c=25.0)])
    cm = cbuild.build(m, numeric=numeric, dt_s=dt_s, prefix="fxa")
    assert cm.spec.fx["arr"] == 1 and cm.spec.uses_temperature
    t, cur = _profile(4000)
    if dt_s is not None:
        t = dt_s * np.arange(t.size, dtype=np.float64)
    temps = np.linspace(-30.0, 50.0, t.size)
    r = cbuild.compare(m, cm, t, cur, 0.8, temperature_c=temps)
    assert r["bit_exact_vs_reference"], r
    assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1], r


def test_cdr_i0_too_small_for_fixed_refused_with_hint(tmp_path):
    """fixed point sizes its g table for |i| / i0_a < 2^16; float takes up to 1e9."""
    m = _base().with_effects([fx.make_effect("current_dependent_resistance", scale_at_zero=1.2,
                                             i0_a=1e-3)])
    with pytest.raises(InputError, match=r"current_dependent_resistance: i0_a = 0.001 A is too "
                                         r"small.*numeric=\"float\""):
        generate_c(m, tmp_path / "out", numeric="fixed")
    assert not (tmp_path / "out").exists()
    assert prepare(m, numeric="float").fx["cdr"] == 1


def test_repeated_effect_refused(tmp_path):
    m = _base().with_effects([EFFECTS["extra_rc"], fx.make_effect("extra_rc", r_ohm=0.01, tau_s=90.0)])
    with pytest.raises(InputError, match="more than once"):
        generate_c(m, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_files_and_documentation(tmp_path):
    plain = render(prepare(_base(), numeric="float"))
    assert "hysteresis" not in plain["ecm_ecm_f32_config.h"] and " h;" not in plain["ecm_ecm_f32.h"]
    assert "ecmrt_f32_fx_hyst(" not in plain["ecm_ecm_f32.c"] and "h_k" not in plain["ecm_ecm_f32_config.h"]
    # capacity_error alone is only a different k_soc: plain runtime, a note in the header
    cap = prepare(_model(("capacity_error",)), numeric="float")
    assert not cap.has_fx and cap.k_soc != prepare(_base(), numeric="float").k_soc
    assert "capacity_error" in render(cap)["ecm_ecm_f32.h"]
    for numeric in ("float", "fixed"):
        spec = prepare(_model(_all(numeric)), numeric=numeric, prefix="bat")
        files = render(spec)
        nm = file_names("bat", numeric)
        assert set(files) == {*nm["runtime"], nm["header"], nm["source"], nm["config"],
                              nm["filelist"], nm["report"]}
        hdr = files[nm["header"]]
        assert "hysteresis" in hdr and "extra_rc" in hdr and " h;" in hdr and " u_x;" in hdr
        assert "hysteresis" in files[nm["config"]] and " h_k;" in files[nm["config"]]
        assert f"ecmrt_{'f32' if numeric == 'float' else 'q'}_fx_hyst(&s->h" in files[nm["source"]]
        assert files == render(spec)                           # deterministic
        written = generate_c(_model(_all(numeric)), tmp_path / numeric, numeric=numeric, prefix="bat")
        assert {p.name for p in written} == set(files)


@pytest.mark.parametrize("numeric,cpu", [("float", "m4f"), ("fixed", "m4f"), ("fixed", "m0")])
def test_cortex_m_build_with_effects(tmp_path, numeric, cpu):
    """Strict cross-compilation: no libm (the float asinh/log/sqrt/exp are hand-written), no
    floating point at all in the fixed-point variant, no mutable globals."""
    from ecmgen.c import target

    reason = target.skip_reason(qemu=False)
    if reason:
        pytest.skip(reason)
    for dt_s in (None, 1.0):
        obj = target.cross_compile(prepare(_model(_all(numeric)), numeric=numeric, dt_s=dt_s),
                                   tmp_path / str(dt_s), cpu=cpu)
        assert obj.warnings == ""
        sz = target.sizes(obj.obj)
        assert sz["data"] == 0 and sz["bss"] == 0, sz
        if numeric == "float":
            assert target.undefined_symbols(obj.obj) == []
        else:
            assert target.float_instructions(obj.obj) == [] and target.float_helpers(obj.obj) == []


def test_build_c_outputs_for_a_model_with_effects(tmp_path):
    """pipeline's C stage (codegen.build_c_outputs -> cbuild.c_equivalence) on a model with
    effects: compared with simulate.py *with* the effects, bit-exact, in tolerance."""
    from types import SimpleNamespace

    from ecmgen.c.check import build_c_outputs
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate, validate

    model = _model(("hysteresis", "extra_rc", "capacity_error"))
    t = np.arange(3000) * 0.5
    cur = np.where((t % 120) < 60, -3.0, 1.0)
    v = simulate(model, t, cur, 0.9).voltage_v + 0.002
    val = validate(model, TimeSeries(t, cur, v, source="cycle.csv"), soc0=0.9)
    result = SimpleNamespace(models={"curve": model}, best="curve",
                             validations={"curve": {"cycle.csv": val}})
    cfg = SimpleNamespace(c_prefix="pk", c_numeric=("float", "fixed"), c_dt_s=None)
    block = build_c_outputs(cfg, result, tmp_path)
    for n, r in block.items():
        assert r["bit_exact_vs_reference"], n
        # the 2 mV offset, to the spec's |dMAE| and max |dv|
        assert abs(r["mae_v"] - 0.002) <= TOL[n][0] and r["max_abs_diff_vs_python_v"] <= TOL[n][1]
        assert f"c/{n}/{file_names('pk', n)['runtime'][-1]}" in r["files"]
