"""Robustness of the generated C: SOC outside [0, 1], currents beyond the range, dt = 0 and
huge dt, NaN/inf inputs, 10^7-step runs; saturation where the header says; and a build with
-fsanitize=undefined,address (plus float-cast-overflow) driven through all of it."""

from __future__ import annotations

import functools
import subprocess
from dataclasses import replace

import numpy as np
import pytest

from ecmgen.c import cbuild, cref
from ecmgen.c.codegen import file_names, generate_c
from conftest import REPO
from test_codegen_helpers import realistic_model

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]
VARIANT_IDS = ["float-vdt", "float-dt0.1", "fixed-vdt", "fixed-dt0.1"]


@functools.lru_cache(maxsize=None)
def _model():
    return realistic_model(n_rc=20, seed=3)


@functools.lru_cache(maxsize=None)
def _cm(numeric, dt_s):
    return cbuild.build(_model(), numeric=numeric, dt_s=dt_s, prefix="rb")


@pytest.mark.parametrize("numeric,dt_s,n", [("float", None, 10**7), ("fixed", None, 10**7),
                                            ("float", 0.1, 10**6), ("fixed", 0.1, 10**6)],
                         ids=VARIANT_IDS)
def test_long_random_runs_stay_finite_and_bounded(numeric, dt_s, n):
    """Pseudo-random currents over the whole input range (float: up to 4x the limit and the
    odd 1e30 A), random dt up to 10 s, n steps in a C loop."""
    cm = _cm(numeric, dt_s)
    r = cm.stress(n, seed=12345, soc0=None, dt_max=10.0)
    assert r["bad"] == 0
    v_lim = 2.0 ** (31 - cm.spec.q["Q_V"]) if numeric == "fixed" else 50.0
    assert -v_lim <= r["v_min"] <= r["v_max"] <= v_lim
    assert -2.0 <= r["soc_min"] <= r["soc_max"] <= 2.0
    # the current saturates, so |v - ocv| <= i_lim * (r0 + r_fast + r_slow) at most
    m = _model()
    rmax = sum(max(np.max(getattr(t, k)) for t in (m.charge, m.discharge))
               for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"))
    bound = cm.spec.i_lim_a * rmax * 1.001
    assert r["v_max"] <= m.ocv.ocv_v[0, -1] + bound and r["v_min"] >= m.ocv.ocv_v[0, 0] - bound


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_soc_saturates_where_the_header_says(numeric, dt_s):
    cm = _cm(numeric, dt_s)
    n = 200000
    for sign in (1.0, -1.0):
        cur = np.full(n, sign * 1000.0)            # beyond the current limit too
        dts = np.full(n, 10.0)
        i_n, dt_n, s0 = cm.native_inputs(cur, dts if dt_s is None else None, 0.5)
        got = cm.trace_native(i_n, dt_n, s0)
        if numeric == "float":
            assert got.soc[-1] == np.float32(2.0 * sign)
            assert np.all(np.isfinite(got.v))
        else:
            assert got.soc[-1] == (2**31 - 1 if sign > 0 else -(2**31))
        assert np.all(np.diff(got.soc.astype(np.float64)) * sign >= 0)   # monotonic: no wrap
        # the table ends hold beyond SOC 1 / 0: constant voltage once the RC states settle
        assert got.v[-1] == got.v[-2]


def test_float_input_sanitising():
    cm = _cm("float", None)
    lim = np.float32(cm.spec.i_lim_a)
    base = np.array([-3.0, -3.0, 5.0, 0.0, -10.0], np.float32)
    dts = np.full(5, 0.1, np.float32)

    def run(i, dt, soc0=0.7):
        return cm.trace_native(np.asarray(i, np.float32), np.asarray(dt, np.float32), soc0)

    ref = run(base, dts)
    nan_i = base.copy()
    nan_i[3] = np.nan
    assert np.array_equal(run(nan_i, dts).v, ref.v)                  # NaN A counts as 0 A
    big = base.copy()
    big[2] = np.inf
    lim_i = base.copy()
    lim_i[2] = lim
    assert np.array_equal(run(big, dts).v, run(lim_i, dts).v)         # saturated at the limit
    for bad_dt in (np.nan, -1.0, -np.inf):
        d = dts.copy()
        d[2] = bad_dt
        z = dts.copy()
        z[2] = 0.0
        assert np.array_equal(run(base, d).v, run(base, z).v)         # counts as dt = 0
    d = dts.copy()
    d[2] = np.inf
    m = dts.copy()
    m[2] = 32767.0
    assert np.array_equal(run(base, d).v, run(base, m).v)             # saturated dt
    assert np.all(np.isfinite(run(base, dts, soc0=float("nan")).v))
    d0 = dts.copy()
    d0[0] = 0.0
    assert run(base, d0, soc0=1e30).soc[0] == np.float32(2.0)        # soc0 saturated too
    assert run(base, d0, soc0=float("nan")).soc[0] == np.float32(0.0)


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_dt_zero_changes_nothing_but_the_direction(numeric):
    cm = _cm(numeric, None)
    cur = np.array([-5.0, -5.0, 3.0, 3.0, 0.0])
    dts = np.array([0.0, 1.0, 0.0, 0.0, 0.0])
    i_n, dt_n, s0 = cm.native_inputs(cur, dts, 0.5)
    got = cm.trace_native(i_n, dt_n, s0)
    assert got.u_fast[0] == 0 and got.u_slow[0] == 0 and got.soc[0] == s0
    assert got.soc[1] != got.soc[0] and got.soc[1] == got.soc[2] == got.soc[3] == got.soc[4]
    assert got.u_fast[2] == got.u_fast[1] and got.u_slow[4] == got.u_slow[1]
    assert got.charging.tolist() == [0, 0, 1, 1, 1]


def test_huge_dt_reaches_steady_state():
    m = _model()
    for numeric in ("float", "fixed"):
        cm = _cm(numeric, None)
        i_n, dt_n, s0 = cm.native_inputs([-4.0, -4.0], [0.0, 30000.0], 0.5)
        got = cm.trace_native(i_n, dt_n, s0)
        soc = float(got.soc[-1]) / (2**30 if numeric == "fixed" else 1.0)
        p = m.discharge.at(soc)
        scale = 2.0 ** -cm.spec.q["Q_V"] if numeric == "fixed" else 1.0
        assert abs(got.u_fast[-1] * scale - p["r_fast_ohm"] * -4.0) < 2e-6
        assert abs(got.u_slow[-1] * scale - p["r_slow_ohm"] * -4.0) < 2e-6


@pytest.mark.parametrize("numeric", ["float", "fixed"])
@pytest.mark.parametrize("soc0", [-0.3, 1.25])
def test_soc_outside_table_matches_clamped_python(numeric, soc0):
    cm = _cm(numeric, None)
    rng = np.random.default_rng(4)
    cur = rng.uniform(-3, 3, 3000)
    t = np.arange(3000) * 0.1
    v = cm.simulate(cur, cref.dt_from_time(t), soc0)
    v64 = cbuild.python_voltage(_model(), t, cur, soc0)
    assert np.max(np.abs(v - v64)) < (0.5e-3 if numeric == "float" else 2e-3)


def test_currents_beyond_limit_equal_python_on_the_saturated_current():
    for numeric in ("float", "fixed"):
        cm = _cm(numeric, None)
        lim = cm.spec.i_lim_a
        cur = np.array([-3 * lim, -lim * 1.5, 2 * lim, 0.0, -lim])
        t = np.arange(cur.size) * 0.01
        v = cm.simulate(cur, cref.dt_from_time(t), 0.5)
        v64 = cbuild.python_voltage(_model(), t, np.clip(cur, -lim, lim), 0.5)
        # the spec's max |dv| against the float64 model: float 0.5 mV, fixed 2 mV
        assert np.max(np.abs(v - v64)) <= (0.5e-3 if numeric == "float" else 2e-3), numeric


# --- sanitizer build ---------------------------------------------------------------------

SAN_MAIN = (REPO / "tests" / "c" / "codegen_sanitize_main.c").read_text()


def test_sanitized_build_has_no_undefined_behaviour(tmp_path):
    cc = _sanitizer_cc(tmp_path)
    srcs = []
    for prefix, (numeric, dt_s) in zip(("fv", "fd", "qv", "qd"), VARIANTS):
        generate_c(_model(), tmp_path, prefix=prefix, numeric=numeric, dt_s=dt_s)
        srcs.append(tmp_path / file_names(prefix, numeric)["source"])
    run = _sanitized_run(cc, tmp_path, srcs, SAN_MAIN, "10000000", fx=False)
    assert "fails 0 qfails 0" in run.stdout


def _sanitizer_cc(tmp_path) -> list[str]:
    """The host compiler, or a skip when it cannot build with the sanitizers."""
    cc = cbuild.host_cc()
    probe = subprocess.run([*cc, *cbuild.SANITIZE_FLAGS, "-x", "c", "-", "-o", tmp_path / "probe"],
                           input="int main(void){return 0;}\n", capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"compiler cannot build with sanitizers: {probe.stderr.strip()[:200]}")
    return cc


def _sanitized_run(cc, tmp_path, srcs, main: str, steps: str, fx: bool
                   ) -> subprocess.CompletedProcess:
    """The generated sources and ``main`` built with the sanitizers (SAN_FX = ``fx``: the
    models have effect states) and run for ``steps``: no runtime error, exit status 0."""
    (tmp_path / "main.c").write_text(main)
    exe = tmp_path / "san"
    flags = [f for f in cbuild.STRICT_CFLAGS if f != "-Werror"]
    proc = subprocess.run([*cc, *flags, *cbuild.SANITIZE_FLAGS, "-O1", f"-DSAN_FX={int(fx)}",
                           "-I", str(tmp_path),
                           *map(str, srcs), str(tmp_path / "main.c"), "-o", str(exe)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    run = subprocess.run([str(exe), steps], capture_output=True, text=True, timeout=300)
    assert "runtime error" not in run.stderr and "AddressSanitizer" not in run.stderr, run.stderr
    assert run.returncode == 0, run.stdout + run.stderr
    return run


# --- models with effects -----------------------------------------------------------------------
# Every effect each numeric mode carries (float: hysteresis, extra_rc,
# current_dependent_resistance, capacity_error; fixed: the same, g from an integer table),
# with the parameters of test_codegen_effects, on the 20-breakpoint model above.

FX_DT = {None: None, 0.1: 0.1}


def _fx_model(numeric):
    from test_codegen_effects import EFFECTS

    from ecmgen.c.codegen import C_EFFECTS

    return _model().with_effects([e for n, e in EFFECTS.items() if n in C_EFFECTS[numeric]])


@functools.lru_cache(maxsize=None)
def _fx_cm(numeric, dt_s):
    cm = cbuild.build(_fx_model(numeric), numeric=numeric, dt_s=dt_s, prefix="rbx")
    assert cm.spec.has_fx
    return cm


def _fx_v_bound(numeric, i_lim):
    """max |v - ocv| of the effect model with the current saturated at i_lim: the resistances
    (r0 and r_fast times the current-dependent factor, <= scale_at_zero), the extra RC pair and
    the hysteresis terms at |h| = |s| = 1."""
    by = {e.name: e for e in _fx_model(numeric).effects}
    m = _model()
    big = {k: max(np.max(getattr(t, k)) for t in (m.charge, m.discharge))
           for k in ("r0_ohm", "r_fast_ohm", "r_slow_ohm")}
    g = by["current_dependent_resistance"].scale_at_zero * (1.0 + 1e-5)   # fixed: table max
    h = by["hysteresis"]
    r = g * (big["r0_ohm"] + big["r_fast_ohm"]) + big["r_slow_ohm"] + by["extra_rc"].r_ohm
    return i_lim * r + (abs(h.m_v) + abs(h.m0_v)) * (1.0 + abs(h.ocv_table_state))


@pytest.mark.parametrize("numeric,dt_s,n", [("float", None, 2 * 10**6), ("fixed", None, 2 * 10**6),
                                            ("float", 0.1, 10**6), ("fixed", 0.1, 10**6)],
                         ids=VARIANT_IDS)
def test_effects_long_random_runs_stay_finite_and_bounded(numeric, dt_s, n):
    """n pseudo-random steps in C (float: currents up to 4x the limit and the odd 1e30 A; dt
    up to 10 s) through the model with all effects: finite, SOC within its saturation, the
    voltage within what the saturated current can produce."""
    cm = _fx_cm(numeric, dt_s)
    r = cm.stress(n, seed=777, soc0=None, dt_max=10.0)
    assert r["bad"] == 0, r
    assert -2.0 <= r["soc_min"] <= r["soc_max"] <= 2.0, r
    m = _model()
    bound = _fx_v_bound(numeric, cm.spec.i_lim_a) * 1.001 + 1e-6
    assert r["v_max"] <= m.ocv.ocv_v[0, -1] + bound and r["v_min"] >= m.ocv.ocv_v[0, 0] - bound, r
    fin = r["final"]
    if numeric == "float":
        assert all(np.isfinite(float(fin[k])) for k in fin), fin


@pytest.mark.parametrize("numeric,dt_s", VARIANTS, ids=VARIANT_IDS)
def test_effects_soc_and_hysteresis_saturate(numeric, dt_s):
    """±1000 A (beyond the limit) for 200 000 steps of 10 s: SOC runs into its saturation at
    ±2 and stays there (no wrap), h stays in [-1, 1] and ends at the direction's ±1, u_x
    settles at r_x * i_lim, the voltage is finite and constant at the end."""
    cm = _fx_cm(numeric, dt_s)
    by = {e.name: e for e in _fx_model(numeric).effects}
    one = float(cref.ONE30) if numeric == "fixed" else 1.0
    vscale = 2.0 ** -cm.spec.q["Q_V"] if numeric == "fixed" else 1.0
    n = 200000
    for sign in (1.0, -1.0):
        cur = np.full(n, sign * 1000.0)
        i_n, dt_n, s0 = cm.native_inputs(cur, np.full(n, 10.0) if dt_s is None else None, 0.5)
        got = cm.trace_native(i_n, dt_n, s0)
        if numeric == "float":
            assert got.soc[-1] == np.float32(2.0 * sign)
            for f in ("v", "u_fast", "u_slow", "h", "u_x"):
                assert np.all(np.isfinite(getattr(got, f))), f
        else:
            assert got.soc[-1] == (2**31 - 1 if sign > 0 else -(2**31))
        assert np.all(np.diff(got.soc.astype(np.float64)) * sign >= 0)     # monotonic: no wrap
        h = got.h.astype(np.float64) / one
        assert np.all(np.abs(h) <= 1.0)
        # float32 h += c_h (s - h) stops within ~2^-25 / c_h of s (c_h ~ 0.025 at dt 0.1 s):
        # 1.25e-6 here, i.e. m_v * 1.25e-6 = 25 nV
        assert abs(h[-1] - sign) < 1e-4
        ux = got.u_x[-1] * vscale
        assert abs(ux - by["extra_rc"].r_ohm * sign * cm.spec.i_lim_a) < 1e-3 * abs(ux) + 1e-6
        assert got.v[-1] == got.v[-2]


def test_effects_float_input_sanitising():
    """NaN A counts as 0 A, ±inf A as the limit, NaN/negative dt as 0, +inf dt as 32767 s - on
    every output and state, effect states included; NaN / huge soc0 saturate."""
    cm = _fx_cm("float", None)
    lim = np.float32(cm.spec.i_lim_a)
    base = np.array([-3.0, -3.0, 5.0, 0.0, -10.0, 2.0], np.float32)
    dts = np.full(base.size, 0.1, np.float32)
    fields = ("v", "soc", "u_fast", "u_slow", "charging", "h", "u_x")

    def run(i, dt, soc0=0.7):
        return cm.trace_native(np.asarray(i, np.float32), np.asarray(dt, np.float32), soc0)

    def same(a, b):
        for f in fields:
            x, y = getattr(a, f), getattr(b, f)
            assert np.array_equal(x.view(np.uint32) if x.dtype == np.float32 else x,
                                  y.view(np.uint32) if y.dtype == np.float32 else y), f

    def with_(a, k, val):
        a = a.copy()
        a[k] = val
        return a

    same(run(with_(base, 3, np.nan), dts), run(base, dts))                     # base[3] = 0 A
    same(run(with_(base, 2, np.inf), dts), run(with_(base, 2, lim), dts))
    same(run(with_(base, 4, -np.inf), dts), run(with_(base, 4, -lim), dts))
    same(run(with_(base, 4, -1e30), dts), run(with_(base, 4, -lim), dts))
    for bad_dt in (np.nan, -1.0, -np.inf):
        same(run(base, with_(dts, 2, bad_dt)), run(base, with_(dts, 2, 0.0)))
    same(run(base, with_(dts, 2, np.inf)), run(base, with_(dts, 2, 32767.0)))
    for s0, want in ((float("nan"), 0.0), (1e30, 2.0), (-1e30, -2.0)):
        got = run(base, with_(dts, 0, 0.0), soc0=s0)
        assert got.soc[0] == np.float32(want)
        for f in ("v", "h", "u_x"):
            assert np.all(np.isfinite(getattr(got, f))), (s0, f)
    # dt = 0 moves no state but the direction (and the hysteresis' instantaneous term with it)
    z = run(np.array([-5.0, 3.0, 3.0], np.float32), np.array([1.0, 0.0, 0.0], np.float32))
    assert z.h[1] == z.h[0] and z.u_x[1] == z.u_x[0] and z.soc[1] == z.soc[0]
    assert z.charging.tolist() == [0, 1, 1] and z.v[1] == z.v[2]



def _temperature_fx_model(numeric):
    """Tables over 5 temperatures on one SOC grid with the diffusion pair, the Butler-Volmer
    branch, temperature_dependence and the effects above: every switch of the runtime on."""
    from test_codegen_helpers import temperature_model

    from ecmgen.model import effects as fx

    return temperature_model(5, 20, seed=3, branches=True, ocv_on_rc_grid=True).with_effects(
        list(_fx_model(numeric).effects) +
        [fx.make_effect("temperature_dependence", activation_k=3500.0, t_ref_c=25.0)])


@pytest.mark.parametrize("family", ["effects", "temperature", "surface"])
def test_effects_sanitized_build_has_no_undefined_behaviour(tmp_path, family):
    """ASan + UBSan (+ float-cast-overflow) build of the four variants with all effects (and,
    for "temperature", tables over temperature with every branch and temperature_dependence),
    driven through NaN/inf/extreme currents, temperatures and dt, SOC far outside [0, 1], and
    5*10^6 (temperature: 2*10^6) random steps: no sanitizer report, no non-finite output,
    every state finite, h within [-1, 1]. "surface": the temperature family with the surface
    SOC (surface_soc_gain 0.5) in every variant."""
    cc = _sanitizer_cc(tmp_path)
    srcs = []
    for prefix, (numeric, dt_s) in zip(("fv", "fd", "qv", "qd"), VARIANTS):
        model = _fx_model(numeric) if family == "effects" else _temperature_fx_model(numeric)
        if family == "surface":
            model = replace(model, surface_soc_gain=0.5)
        generate_c(model, tmp_path, prefix=prefix, numeric=numeric, dt_s=dt_s)
        src = (tmp_path / file_names(prefix, numeric)["config"]).read_text()
        features = src[src.index("Features:"):src.index("*/", src.index("Features:"))]
        assert "hysteresis" in features
        assert ("surface SOC" in features) == (family == "surface")
        if family != "effects":
            assert all(k in features for k in ("temperature rows", "diffusion pair",
                                                "Butler-Volmer branch", "temperature_dependence")), prefix
        srcs.append(tmp_path / file_names(prefix, numeric)["source"])
    run = _sanitized_run(cc, tmp_path, srcs, SAN_MAIN,
                         "5000000" if family == "effects" else "2000000", fx=True)
    print("\n", run.stdout)
    assert "fails 0 qfails 0" in run.stdout
