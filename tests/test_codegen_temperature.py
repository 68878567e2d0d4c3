"""The generated C over temperature : tables over (temperature, SOC), the
diffusion pair, the Butler-Volmer fast branch and temperature_dependence, float and fixed.

C == float32 / bit-true references on every step and state; within 0.5 mV (float) and 2 mV
(fixed) of the float64 model on every shared drive cycle at every temperature, driven with
the file's cell temperature; hypothesis with random currents, temperatures and dt."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ecmgen.c import cbuild, cref
from ecmgen.c.codegen import file_names, generate_c, prepare, render
from ecmgen.c.spec import state_fields
from ecmgen.errors import InputError
from ecmgen.model import effects as fx
from ecmgen.model.model import OcvOverTemperature, RcTable
from test_codegen_helpers import (assert_fields_equal, check_c_equivalence, fitter_layout_model,
                                  load_cycle_t, temperature_fitted_model, temperature_model)

TOL = {"float": (0.05e-3, 0.5e-3), "fixed": (0.5e-3, 2e-3)}     # |dMAE|, max |dv|
CYCLES = [("panasonic-18650pf-25degC", "us06.mat"), ("panasonic-18650pf-25degC", "hwfet-a.mat"),
          ("panasonic-18650pf-0degC", "us06.mat"), ("panasonic-18650pf-0degC", "hwfet.mat"),
          ("panasonic-18650pf-n10degC", "us06.mat"), ("panasonic-18650pf-n10degC", "hwfet.mat"),
          ("panasonic-18650pf-n20degC", "us06.mat"), ("panasonic-18650pf-n20degC", "hwfet.mat")]
ARR = fx.make_effect("temperature_dependence", activation_k=3500.0, t_ref_c=25.0)
FIELDS = ("v", "soc", "u_fast", "u_slow", "charging")


def _plain(model):
    """The model without its diffusion and Butler-Volmer branches."""
    none = {k: None for k in ("r_diff_ohm", "tau_diff_s", "i0_a")}
    return replace(model, charge=replace(model.charge, **none),
                   discharge=replace(model.discharge, **none))


@functools.lru_cache(maxsize=None)
def _fitted():
    return temperature_fitted_model()


@functools.lru_cache(maxsize=None)
def _fitter_layout():
    """The curve fit's layout (uniform SOC grids, time constants over temperature only, the
    same in both directions: ECMRT_RC_UNIFORM, ECMRT_OCV_UNIFORM, ECMRT_TAU_T, ECMRT_TAU_SAME)
    with the branches."""
    return fitter_layout_model(branches=True)


@functools.lru_cache(maxsize=None)
def _synthetic(kind: str):
    if kind == "tau_t":                   # ECMRT_TAU_T, each direction its own time constants
        return fitter_layout_model(rows=slice(2, 9), same_tau=False)
    if kind == "fitter":
        return _fitter_layout()
    if kind == "branches":
        return temperature_model(4, 10, seed=5, branches=True)
    if kind == "plain":
        return temperature_model(4, 10, seed=5)
    if kind == "surface":                 # the curve fit's layout with the surface SOC
        return replace(_fitter_layout(), surface_soc_gain=0.5)
    if kind == "surface_rows":            # searched grids, time constants over SOC, and T
        return replace(temperature_model(4, 10, seed=5, branches=True), surface_soc_gain=0.7)
    if kind == "surface_one":             # one temperature row
        return replace(temperature_model(1, 10, seed=5, branches=True), surface_soc_gain=0.5)
    if kind == "arr":                     # one temperature row and the Arrhenius effect
        return temperature_model(1, 10, seed=5).with_effects([ARR])
    if kind == "everything":              # rows, branches, a shared OCV grid, effects
        return temperature_model(5, 10, seed=5, branches=True, ocv_on_rc_grid=True).with_effects(
            [ARR, fx.make_effect("hysteresis", m_v=0.02, decay_ah=0.15, m0_v=0.004),
             fx.make_effect("extra_rc", r_ohm=0.01, tau_s=300.0),
             fx.make_effect("current_dependent_resistance", scale_at_zero=1.2, i0_a=3.0)])
    raise KeyError(kind)


@functools.lru_cache(maxsize=None)
def _cm(kind: str, numeric: str, dt_s):
    return cbuild.build(_synthetic(kind), numeric=numeric, dt_s=dt_s, prefix="tc")


def _fields_equal(cm, got, ref):
    assert_fields_equal(got, ref, FIELDS + cbuild.extra_states(cm.spec))


def _run_both(cm, cur, dts, temps, soc0):
    """C and its reference on the same native inputs (temperatures degC; NaN/inf allowed)."""
    i_n, dt_n, s0 = cm.native_inputs(cur, dts if cm.spec.variable_dt else None, soc0)
    t_n = cm.native_temperature(temps, cur.size)
    got = cm.trace_native(i_n, dt_n, s0, t_n)
    if cm.spec.fixed:
        ref = cref.simulate_fixed_raw(cm.spec, i_n.astype(np.int64),
                                      None if dt_n is None else dt_n.astype(np.int64), s0,
                                      t_n.astype(np.int64))
    else:
        ref = cref.simulate_f32(cm.spec, cur, dts, soc0, t_n)
    return got, ref


# --- real drive cycles at every temperature --------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("folder,name", CYCLES, ids=[f"{f.split('-')[-1]}-{n[:-4]}" for f, n in CYCLES])
def test_real_cycles_every_temperature(folder, name):
    """The acceptance figures of the C over temperature: the 14 x 21 test model with diffusion and
    Butler-Volmer branches, variable dt, on the cycle's own time stamps and cell temperature
    (Battery_Temp_degC), started full (the files start from a full charge); as fitted (time
    constants over SOC, the OCV on the RC grid) and in the curve fit's layout."""
    s = load_cycle_t(folder, name)
    for model, layout in ((_fitted(), "time constants over SOC"),
                          (_fitter_layout(), "the curve fit's layout")):
        res = cbuild.c_equivalence(model, s, 1.0)
        t = res["float"]["temperature_range_c"]
        print(f"\n{folder}/{name} ({len(s)} steps, {t[0]:.1f} .. {t[1]:.1f} degC), {layout}:")
        check_c_equivalence(res, len(s), TOL)


@pytest.mark.slow
@pytest.mark.parametrize("folder,name", [CYCLES[2], CYCLES[7]], ids=["0degC-us06", "n20degC-hwfet"])
def test_real_cycles_fixed_dt_and_without_branches(folder, name):
    """Fixed dt 0.1 s (the record resampled) with the branches, and variable dt without them."""
    s = load_cycle_t(folder, name)
    for model, dt_s in ((_fitted(), 0.1), (_plain(_fitted()), None)):
        res = cbuild.c_equivalence(model, s, 1.0, dt_s=dt_s)
        for numeric in ("float", "fixed"):
            r = res[numeric]
            print(f"\n{folder}/{name} dt {dt_s} branches {model.charge.has_diffusion} {numeric}: "
                  f"bit-exact {r['bit_exact_vs_reference']}, max|dv| "
                  f"{r['max_abs_diff_vs_python_v'] * 1e3:.4f} mV")
            assert r["bit_exact_vs_reference"]
            assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]


@pytest.mark.slow
@pytest.mark.parametrize("numeric", ["float", "fixed"])
@pytest.mark.parametrize("folder,name", [CYCLES[0], CYCLES[4], CYCLES[7]],
                         ids=["25degC-us06", "n10degC-us06", "n20degC-hwfet"])
def test_real_cycles_surface_soc(folder, name, numeric):
    """The surface SOC (surface_soc_gain 0.5) in the float and the fixed-point C: the test
    model as fitted and in the curve fit's layout, variable and fixed dt, on the cycle's cell
    temperature."""
    s = load_cycle_t(folder, name)
    for model in (_fitted(), _fitter_layout()):
        model = replace(model, surface_soc_gain=0.5)
        for dt_s in (None, 0.1):
            r = cbuild.c_equivalence(model, s, 1.0, dt_s=dt_s, numerics=(numeric,))[numeric]
            print(f"\n{folder}/{name} surface {numeric} dt {dt_s}: bit-exact "
                  f"{r['bit_exact_vs_reference']}, max|dv| "
                  f"{r['max_abs_diff_vs_python_v'] * 1e3:.4f} mV")
            assert r["bit_exact_vs_reference"]
            assert r["max_abs_diff_vs_python_v"] <= TOL[numeric][1]


# --- hypothesis ------------------------------------------------------------------------------

SURFACE = ("surface", "surface_rows", "surface_one")

SETTINGS = settings(max_examples=25, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
current = st.one_of(st.floats(-300.0, 300.0, allow_nan=False, width=32),
                    st.sampled_from([0.0, 0.029, -0.029, 1e-30, -1e6, 1e6]))
temperature = st.one_of(st.floats(-80.0, 120.0, width=32),
                        st.sampled_from([-20.0, -15.0, 25.0, -40.0, 85.0, 1e9, -1e9]))
wild_temperature = st.one_of(temperature, st.sampled_from([np.nan, np.inf, -np.inf]))
step_dt = st.one_of(st.floats(0.0, 20.0, width=32), st.sampled_from([0.0, 0.1, 1e-7, 3600.0, 1e5]))


@st.composite
def profiles(draw, temp=temperature, max_size=150):
    n = draw(st.integers(1, max_size))
    runs = draw(st.lists(st.tuples(current, st.integers(1, 30)), min_size=1, max_size=15))
    cur = np.resize(np.repeat([c for c, _ in runs], [k for _, k in runs]), n).astype(np.float64)
    truns = draw(st.lists(st.tuples(temp, st.integers(1, 40)), min_size=1, max_size=8))
    temps = np.resize(np.repeat([t for t, _ in truns], [k for _, k in truns]), n).astype(np.float64)
    dts = np.array(draw(st.lists(step_dt, min_size=n, max_size=n)), dtype=np.float64)
    return cur, dts, temps, draw(st.floats(-0.3, 1.3))


@SETTINGS
@given(profiles(temp=wild_temperature))
def test_property_float_bit_exact(p):
    cur, dts, temps, soc0 = p
    for kind in ("branches", "everything", "fitter", "tau_t") + SURFACE:
        for dt_s in (None, 0.5):
            cm = _cm(kind, "float", dt_s)
            got, ref = _run_both(cm, cur, dts, temps, soc0)
            _fields_equal(cm, got, ref)
            assert np.all(np.isfinite(got.v))


@SETTINGS
@given(profiles())
def test_property_fixed_bit_exact(p):
    cur, dts, temps, soc0 = p
    for kind in ("branches", "everything", "arr", "fitter", "tau_t") + SURFACE:
        for dt_s in (None, 0.5):
            cm = _cm(kind, "fixed", dt_s)
            _fields_equal(cm, *_run_both(cm, cur, dts, temps, soc0))


@SETTINGS
@given(profiles(max_size=300))
def test_property_close_to_float64(p):
    cur, dts, temps, soc0 = p
    cur = np.clip(cur, -30.0, 12.0)
    dts = np.clip(dts, 0.0, 2.0)
    temps = np.clip(np.nan_to_num(temps, nan=0.0), -30.0, 60.0)
    soc0 = float(np.clip(soc0, 0.0, 1.0))
    t = np.cumsum(dts) - dts[0]
    for kind in ("branches", "everything", "arr", "fitter", "tau_t") + SURFACE:
        model = _synthetic(kind)
        # a current within float32 rounding of the deadband (the strategy's +-0.029 A with
        # the fitted model's deadband 0.028999999999999998) may turn the direction in float64
        # and not in float32: another table, not an error of the step (bit-exactness covers it)
        db = model.direction_deadband_a
        cur = np.where(np.abs(np.abs(cur) - db) <= 1e-7 * db, 0.0, cur)
        v64 = cbuild.python_voltage(model, t, cur, soc0, temperature_c=temps)
        # The absolute bound holds in a cell's voltage window; far outside it (30 A into a
        # cold Arrhenius-scaled resistance at SOC 0 gives -17 V) the fixed-point resistance
        # keeps its relative resolution, not an absolute one: 1e-4 of the distance beyond.
        beyond_v = np.maximum(np.abs(v64 - 3.5) - 1.5, 0.0)
        for numeric in ("float", "fixed"):
            v = _cm(kind, numeric, None).simulate(cur, cref.dt_from_time(t), soc0, temps)
            assert np.all(np.abs(v - v64) <= TOL[numeric][1] + 1e-4 * beyond_v), (kind, numeric)


def test_fixed_size_build_is_the_same():
    """-Os builds of the fixed-point step evaluate the polynomials by a Horner loop on a
    table instead of unrolled (less code): the same results bit for bit."""
    rng = np.random.default_rng(9)
    n = 3000
    cur = np.repeat(rng.uniform(-30, 10, n // 20 + 1), 20)[:n]
    temps = np.repeat(rng.uniform(-40, 70, n // 7 + 1), 7)[:n]
    dts = rng.uniform(0, 2, n)
    for kind, dt_s in (("everything", None), ("everything", 0.5), ("fitter", None)):
        spec = prepare(_synthetic(kind), numeric="fixed", dt_s=dt_s, prefix="tcs")
        small = cbuild.compile_spec(spec, opt=("-Os",))
        got, ref = _run_both(small, cur, dts, temps, 0.6)
        _fields_equal(small, got, ref)


# --- semantics ---------------------------------------------------------------------------------

@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_temperature_clamps_at_the_table_ends(numeric):
    """Below the first / above the last breakpoint the first / last row holds (float: NaN and
    -inf count as the first row, +inf as the last)."""
    cm = _cm("branches", numeric, None)
    n = 50
    cur = np.where(np.arange(n) % 10 < 5, -10.0, 3.0)
    dts = np.full(n, 0.5)
    lo, hi = cm.spec.temp_grid.x[0], cm.spec.temp_grid.x[-1]
    scale = 256.0 if numeric == "fixed" else 1.0
    ends = {"lo": float(lo) / scale, "hi": float(hi) / scale}
    cases = [("lo", -60.0), ("lo", -1e9), ("hi", 80.0), ("hi", 1e9)]
    if numeric == "float":
        cases += [("lo", np.nan), ("lo", -np.inf), ("hi", np.inf)]
    for end, t in cases:
        a, _ = _run_both(cm, cur, dts, np.full(n, ends[end]), 0.7)
        b, _ = _run_both(cm, cur, dts, np.full(n, t), 0.7)
        assert np.array_equal(a.v, b.v), (end, t)


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_one_temperature_model_ignores_the_temperature(numeric):
    from test_codegen_helpers import realistic_model

    cm = cbuild.build(realistic_model(n_rc=8), numeric=numeric, prefix="one")
    assert not cm.spec.uses_temperature
    n = 40
    cur, dts = np.linspace(-10, 5, n), np.full(n, 0.2)
    i_n, dt_n, s0 = cm.native_inputs(cur, dts, 0.6)
    runs = [cm.trace_native(i_n, dt_n, s0, cm.native_temperature(t, n)).v
            for t in (-30.0, 25.0, 60.0)]
    assert np.array_equal(runs[0], runs[1]) and np.array_equal(runs[1], runs[2])
    assert "_USES_TEMPERATURE 0" in render(cm.spec)[file_names("one", cm.spec.numeric)["header"]]


def test_temperature_dependence_effect_close_to_python():
    """temperature_dependence is generated now: on a one-row model its Arrhenius factor
    follows the temperature (C == reference, within tolerance of simulate.py)."""
    m = _synthetic("arr")
    rng = np.random.default_rng(4)
    n = 3000
    t = np.cumsum(rng.uniform(0.05, 0.5, n))
    t -= t[0]
    cur = np.repeat(rng.uniform(-15, 6, n // 30 + 1), 30)[:n]
    temps = np.linspace(-30.0, 50.0, n)
    v64 = cbuild.python_voltage(m, t, cur, 0.8, temperature_c=temps)
    base = cbuild.python_voltage(replace(m, effects=()), t, cur, 0.8, temperature_c=temps)
    assert np.max(np.abs(v64 - base)) > 0.05                       # the effect acts
    for numeric in ("float", "fixed"):
        cm = _cm("arr", numeric, None)
        assert cm.spec.uses_temperature and not cm.spec.temp
        r = cbuild.compare(m, cm, t, cur, 0.8, temperature_c=temps)
        assert r["bit_exact_vs_reference"] and r["max_abs_diff_vs_python_v"] <= TOL[numeric][1], r
    # saturated to [-40, 85] degC in the C (documented; simulate.py extrapolates)
    f = cref.arrhenius_f32(np.array([-300.0, -40.0, 85.0, 500.0, np.nan], np.float32),
                           prepare(m).fx["a_k"], prepare(m).fx["a_inv_ref"])
    assert f[0] == f[1] == f[4] and f[2] == f[3]


def test_tables_on_different_temperature_grids():
    """OCV, charge and discharge with their own temperature breakpoints (and a one-row
    table): the C puts them on the union grid, which is the same bilinear function."""
    base = temperature_model(4, 10, seed=8)
    t3 = np.array([-12.0, 7.0, 31.0])
    ocv = OcvOverTemperature(t3, base.ocv.soc, np.vstack(
        [base.ocv.ocv_at(base.ocv.soc, t) + 1e-3 * k for k, t in enumerate(t3)]))
    ch = base.charge
    one_row = replace(base.discharge.row(1), temperature_c=np.array([np.nan]))
    m = replace(base, ocv=ocv, charge=RcTable(
        soc=ch.soc, temperature_c=ch.temperature_c + 2.5, fit_error=ch.fit_error,
        converged=ch.converged, **{k: getattr(ch, k) for k in
                                   ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")}),
        discharge=one_row)
    spec = prepare(m, numeric="float")
    assert spec.temp_grid.n == 7 and spec.ocv.shape[0] == 7
    n = 4000
    t = np.arange(n) * 0.2
    cur = np.where((t % 80) < 40, -8.0, 4.0)
    temps = np.linspace(-25.0, 40.0, n)
    for numeric in ("float", "fixed"):
        cm = cbuild.build(m, numeric=numeric, prefix="ug")
        r = cbuild.compare(m, cm, t, cur, 0.9, temperature_c=temps)
        assert r["bit_exact_vs_reference"] and r["max_abs_diff_vs_python_v"] <= TOL[numeric][1], r


# --- generated files, refusals -------------------------------------------------------------------

def test_header_documents_temperature_and_state(tmp_path):
    m = _synthetic("everything")
    for numeric in ("float", "fixed"):
        spec = prepare(m, numeric=numeric, prefix="bt")
        h = render(spec)[file_names("bt", numeric)["header"]]
        M = "BT_ECM_Q" if numeric == "fixed" else "BT_ECM_F32"
        assert f"{M}_TEMPERATURE_ROWS 5" in h and f"{M}_USES_TEMPERATURE 1" in h
        q = spec.q if numeric == "fixed" else {}
        assert ("bt_step_q(bt_state_q_t *s, bt_amp_q{Q_I}_t i, bt_degc_q8_t temperature, "
                "bt_sec_q16_t dt)".format(**q) if numeric == "fixed" else
                "bt_step_f32(bt_state_f32_t *s, float i, float temperature, float dt)") in h
        for _, name, _ in state_fields(spec):
            assert f" {name};" in h, name
        if numeric == "fixed":
            assert "Q8 degC" in h and "BT_ECM_Q_TEMP 8" in h and "BT_ECM_Q_GT " in h
        assert "diffusion" in h and "Butler-Volmer" in h and "temperature_dependence" in h
    plain = prepare(temperature_model(1, 6), numeric="fixed")
    names = [n for _, n, _ in state_fields(plain)]
    assert "u_diff" not in names and "k_t" not in names and "t_in" not in names


def test_bv_i0_too_small_for_fixed_refused_with_hint(tmp_path):
    m = _synthetic("branches")
    tiny = {"i0_a": np.full(4, 1e-4)}
    m = replace(m, charge=replace(m.charge, **tiny), discharge=replace(m.discharge, **tiny))
    with pytest.raises(InputError, match=r"Butler-Volmer i0_a .* too small.*numeric=\"float\""):
        generate_c(m, tmp_path / "out", numeric="fixed")
    assert not (tmp_path / "out").exists()
    assert prepare(m, numeric="float").has_bv


def test_arrhenius_too_steep_for_fixed_refused(tmp_path):
    m = _synthetic("plain").with_effects([fx.make_effect("temperature_dependence",
                                                         activation_k=50000.0, t_ref_c=25.0)])
    with pytest.raises(InputError, match="temperature_dependence.*numeric=\"float\""):
        generate_c(m, tmp_path / "out", numeric="fixed")
    assert prepare(m, numeric="float").fx["arr"] == 1
