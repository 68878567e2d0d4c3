"""Property-based tests (hypothesis): random current / dt sequences through the C (cffi) and
the Python references must agree bit for bit; on physically sensible inputs the C must stay
within the stated tolerances of the float64 model."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ecmgen.c import cbuild, cref
from ecmgen.c.codegen import c_float
from test_codegen_helpers import realistic_model

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@functools.lru_cache(maxsize=None)
def _model():
    return realistic_model(n_rc=12, seed=7)


@functools.lru_cache(maxsize=None)
def _cm(numeric: str, dt_s):
    return cbuild.build(_model(), numeric=numeric, dt_s=dt_s, prefix="prop")


I_LIM = 512.0                 # beyond the 128 A saturation of the realistic model

wild_current = st.one_of(
    st.floats(-I_LIM, I_LIM, allow_nan=False, width=32),
    st.sampled_from([0.0, 0.029, -0.029, 0.0290001, 128.0, -128.0, 1e-30, -1e6, 1e6]),
)
wild_dt = st.one_of(st.floats(0.0, 20.0, width=32), st.sampled_from([0.0, 0.1, 1e-7, 3600.0, 1e5]))


@st.composite
def profiles(draw, current=wild_current, dt=wild_dt, max_size=300):
    n = draw(st.integers(1, max_size))
    # runs of constant current, as real load profiles have
    runs = draw(st.lists(st.tuples(current, st.integers(1, 40)), min_size=1, max_size=30))
    cur = np.repeat([c for c, _ in runs], [k for _, k in runs])
    cur = np.resize(cur, n).astype(np.float64)
    dts = np.array(draw(st.lists(dt, min_size=n, max_size=n)), dtype=np.float64)
    soc0 = draw(st.floats(-0.3, 1.3))
    return cur, dts, soc0


def _check_bits(numeric, dt_s, cur, dts, soc0):
    cm = _cm(numeric, dt_s)
    i_n, dt_n, s0 = cm.native_inputs(cur, dts if dt_s is None else None, soc0)
    got = cm.trace_native(i_n, dt_n, s0)
    ref = cm.reference(cur, dts, soc0)
    for f in ("v", "soc", "u_fast", "u_slow", "charging"):
        a, b = getattr(got, f), getattr(ref, f)
        if a.dtype == np.float32:
            assert np.array_equal(a.view(np.uint32), b.astype(np.float32).view(np.uint32)), f
        else:
            assert np.array_equal(a.astype(np.int64), b.astype(np.int64)), f
    return cm, got


@SETTINGS
@given(profiles())
def test_float_variable_dt_bit_exact(p):
    cm, got = _check_bits("float", None, *p)
    assert np.all(np.isfinite(got.v)) and np.all(np.abs(got.soc) <= 2.0)


@SETTINGS
@given(profiles())
def test_float_fixed_dt_bit_exact(p):
    _, got = _check_bits("float", 0.1, *p)
    assert np.all(np.isfinite(got.v))


@SETTINGS
@given(profiles())
def test_fixed_variable_dt_bit_exact(p):
    _check_bits("fixed", None, *p)


@SETTINGS
@given(profiles())
def test_fixed_fixed_dt_bit_exact(p):
    _check_bits("fixed", 0.1, *p)


@SETTINGS
@given(profiles(current=st.floats(-30.0, 12.0), dt=st.floats(0.0, 2.0), max_size=400))
def test_close_to_float64_model(p):
    cur, dts, soc0 = p
    soc0 = float(np.clip(soc0, 0.0, 1.0))
    t = np.cumsum(dts) - dts[0]
    v64 = cbuild.python_voltage(_model(), t, cur, soc0)
    for numeric, tol in (("float", 0.5e-3), ("fixed", 2e-3)):
        v = _cm(numeric, None).simulate(cur, cref.dt_from_time(t), soc0)
        assert np.max(np.abs(v - v64)) <= tol, numeric
    v64d = cbuild.python_voltage(_model(), None, cur, soc0, dt_s=0.1)
    for numeric, tol in (("float", 0.5e-3), ("fixed", 2e-3)):
        v = _cm(numeric, 0.1).simulate(cur, None, soc0)
        assert np.max(np.abs(v - v64d)) <= tol, numeric


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False, width=32))
def test_float_literal_round_trip(x):
    s = c_float(x)
    assert np.float32(float(s[:-1])).view(np.uint32) == np.float32(x).view(np.uint32)


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_chunked_runs_equal_one_run(numeric):
    """The state carries everything: stepping in pieces equals stepping at once."""
    cm = _cm(numeric, None)
    rng = np.random.default_rng(11)
    cur = rng.uniform(-20, 10, 500)
    dts = rng.uniform(0, 0.3, 500)
    i_n, dt_n, s0 = cm.native_inputs(cur, dts, 0.6)
    whole = cm.run_native(i_n, dt_n, s0)
    s = cm.new_state(s0)
    step = getattr(cm.lib, cm.names["step"])
    parts = [step(s, int(a) if numeric == "fixed" else float(a), 0,
                  int(b) if numeric == "fixed" else float(b)) for a, b in zip(i_n, dt_n)]
    assert np.array_equal(np.asarray(parts, dtype=whole.dtype), whole)
