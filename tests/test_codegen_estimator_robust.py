"""The C SOC estimator under stress: the emulated Cortex-M4F (QEMU mps2-an386) bit-identical
to the host, an ASan/UBSan build through absurd inputs, and hypothesis with random
currents, temperatures, dt and voltages (C == float32 reference, bit for bit)."""

from __future__ import annotations

import functools
import subprocess
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ecmgen.c import cbuild, target
from ecmgen.c.codegen import generate_c, prepare
from ecmgen.c.estc import prepare_estimator
from ecmgen.c.estcheck import bits_equal, run_estimator_c
from ecmgen.c.esttarget import qemu_estimator_equivalence
from ecmgen.c.estref import simulate_estimator_f32
from ecmgen.config import EstimatorConfig
from ecmgen.model.model import load_model
from ecmgen.model.simulate import simulate

from conftest import REPO, SHARED_DATA, need
from test_estimate import ALL_EFFECTS, drive_profile, model_over_temperature

MODEL = REPO / "tests" / "data" / "panasonic-temperature-model.json"


@functools.lru_cache(maxsize=None)
def _model():
    return load_model(MODEL)


def _effects_model():
    """Every diagnose effect (hysteresis, extra_rc, current_dependent_resistance,
    capacity_error, temperature_dependence) on the synthetic model with both branches."""
    return model_over_temperature(effects=ALL_EFFECTS)


def _surface_model():
    """The effects model with the surface SOC (surface_soc_gain 0.5)."""
    return replace(_effects_model(), surface_soc_gain=0.5)


# started anywhere, the SOC read from the OCV alone, a held model error, the RC noise
# scaled by the SOC's sigma, the OCV's secant: every setting that changes the C filter's
# arithmetic
ANYWHERE = dict(start_polarization_c=0.5, resistance_slopes=False, error_memory_s=60.0,
                polarization_soc_sigma=0.02, ocv_slope_spread=1.0)


@functools.lru_cache(maxsize=None)
def _cm(which: str):
    m = {"panasonic": _model, "synthetic": model_over_temperature,
         "effects": _effects_model, "effects-offset": _effects_model,
         "surface-offset": _surface_model}[which]()
    spec = prepare(m, "float", None, "hyp")
    cfg = EstimatorConfig(offset_state=which.endswith("offset"),
                          **(ANYWHERE if which.startswith("surface") else {}))
    return m, cbuild.compile_spec(spec, estimator=prepare_estimator(m, spec, cfg))


# -- QEMU ------------------------------------------------------------------------------

def test_qemu_cortex_m4f_bit_identical_to_the_host():
    """A real cycle's start in the full-cell scenario (guess 0.8, 29 mA offset, gain 1.01) and a
    synthetic profile with dt = 0, gaps, temperatures beyond the tables and missing
    voltages, on a model without and one with every diagnose effect and the current-offset
    state (the hysteresis state, the extra RC pair and the offset in the filter), with the
    default settings and started anywhere (``ANYWHERE``): every
    predicted voltage, state and covariance entry the same bits on the
    emulated Cortex-M4F (hard float, -O2) as on the host."""
    reason = target.skip_reason(qemu=True)
    if reason:
        pytest.skip(reason)
    from ecmgen.data.measure import read_timeseries

    s = read_timeseries(need(SHARED_DATA / "panasonic-18650pf-n20degC" / "us06.mat"),
                        capacity_ah=2.9)
    n = 2500
    res = qemu_estimator_equivalence(_model(), s.time_s[:n], 1.01 * s.current_a[:n] + 0.029,
                                     s.voltage_v[:n], 0.8, s.temperature_c[:n])
    assert res["bit_exact"], res
    t, i, temp = drive_profile(1200, seed=4)
    for m, offset in ((model_over_temperature(), False), (_effects_model(), True),
                      (_surface_model(), True)):
        v = simulate(m, t, i, 0.8, temp).voltage_v
        v[[3, 500]] = np.nan
        res = qemu_estimator_equivalence(m, t, i + 0.05, v, 0.6, temp,
                                         cfg=EstimatorConfig(offset_state=offset))
        assert res["bit_exact"], res
        res = qemu_estimator_equivalence(m, t, i + 0.05, v, 0.6, temp,
                                         cfg=EstimatorConfig(offset_state=offset, **ANYWHERE))
        assert res["bit_exact"], res


# -- sanitizers ------------------------------------------------------------------------

SAN_MAIN = (REPO / "tests" / "c" / "estimator_sanitize_main.c")


@pytest.mark.parametrize("which", ["panasonic", "effects", "surface"])
def test_sanitized_build_through_absurd_inputs(tmp_path, which):
    """ASan + UBSan (+ float-cast-overflow): every combination of absurd currents, dt,
    temperatures, measured voltages (NaN, inf, +-FLT_MAX, denormals) and start SOCs, then
    10^6 random steps: no undefined behaviour, and after every step the SOC in [0, 1], the
    states and the covariance finite (h in [-1, 1] with the effects, which are built with the
    offset state too; the surface model also started anywhere, ``ANYWHERE``), the covariance
    exactly symmetric with a non-negative diagonal."""
    cc = cbuild.host_cc()
    probe = subprocess.run([*cc, *cbuild.SANITIZE_FLAGS, "-x", "c", "-", "-o", tmp_path / "probe"],
                           input="int main(void){return 0;}\n", capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"compiler cannot build with sanitizers: {probe.stderr.strip()[:200]}")
    fx = which != "panasonic"
    generate_c({"effects": _effects_model, "surface": _surface_model,
                "panasonic": _model}[which](), tmp_path, prefix="fe",
               estimator=EstimatorConfig(offset_state=fx,
                                         **(ANYWHERE if which == "surface" else {})))
    (tmp_path / "main.c").write_text(SAN_MAIN.read_text())
    exe = tmp_path / "san"
    flags = [f for f in cbuild.STRICT_CFLAGS if f != "-Werror"]
    proc = subprocess.run([*cc, *flags, *cbuild.SANITIZE_FLAGS, "-O1", f"-DFE_FX={int(fx)}",
                           "-I", str(tmp_path),
                           str(tmp_path / "fe_ecm_f32.c"), str(tmp_path / "fe_est_f32.c"),
                           str(tmp_path / "main.c"), "-o", str(exe)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    run = subprocess.run([str(exe), "1000000"], capture_output=True, text=True, timeout=300)
    assert "runtime error" not in run.stderr and "AddressSanitizer" not in run.stderr, run.stderr
    assert run.returncode == 0 and "fails 0" in run.stdout, run.stdout + run.stderr


# -- hypothesis ------------------------------------------------------------------------

SETTINGS = settings(max_examples=25, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
current = st.one_of(st.floats(-60.0, 30.0, width=32),
                    st.sampled_from([0.0, 0.029, -0.029, 1e-30, 500.0, -500.0, np.nan]))
temperature = st.one_of(st.floats(-45.0, 70.0, width=32),
                        st.sampled_from([-20.0, 25.0, 45.0, np.nan, np.inf, -np.inf]))
dt = st.one_of(st.floats(0.0, 30.0, width=32),
               st.sampled_from([0.0, 0.1, 1e-40, 3600.0, 1e5, -1.0, np.nan]))


@st.composite
def records(draw, max_size=150):
    n = draw(st.integers(1, max_size))
    runs = draw(st.lists(st.tuples(current, temperature, st.integers(1, 30)), min_size=1,
                         max_size=12))
    cur = np.resize(np.repeat([c for c, _, _ in runs], [k for _, _, k in runs]), n)
    temp = np.resize(np.repeat([t for _, t, _ in runs], [k for _, _, k in runs]), n)
    dts = np.array(draw(st.lists(dt, min_size=n, max_size=n)), dtype=np.float64)
    noise = draw(st.lists(st.one_of(st.floats(-0.25, 0.25, width=32),
                                    st.sampled_from([np.nan, 50.0, -3.0])),
                          min_size=n, max_size=n))
    guess = draw(st.floats(-0.2, 1.2))
    return cur.astype(np.float64), temp.astype(np.float64), dts, np.asarray(noise), guess


@pytest.mark.parametrize("which", ["panasonic", "synthetic", "effects", "effects-offset",
                                   "surface-offset"])
@SETTINGS
@given(rec=records())
def test_random_records_bit_identical_and_sane(which, rec):
    """Random currents (both ways, saturated, NaN), temperatures (beyond the tables, NaN,
    inf), dt (0, denormal, negative, NaN, an hour, a day) and voltages (the model's own
    plus noise, NaN, absurd), on the test model, a synthetic one and one with every effect
    (and with the offset state):
    C == float32 reference bit for bit; SOC in [0, 1], the covariance finite, symmetric, its
    diagonal non-negative."""
    cur, temp, dts, noise, guess = rec
    m, cm = _cm(which)
    t = np.cumsum(np.where(np.isfinite(dts) & (dts > 0), dts, 0.0))
    v = simulate(m, t, np.nan_to_num(np.clip(cur, -60, 60)), 0.7,
                 np.clip(np.nan_to_num(temp, nan=25.0), -50, 80)).voltage_v + noise
    got = run_estimator_c(cm, cur, dts, v, guess, temp)
    ref = simulate_estimator_f32(cm.spec, cm.estimator, cur, dts, v, guess, temp)
    assert bits_equal(got, ref)
    assert np.all((got.soc >= 0) & (got.soc <= 1))
    assert np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.p))
    assert np.array_equal(got.p, np.swapaxes(got.p, 1, 2))
    assert np.all(np.diagonal(got.p, axis1=1, axis2=2) >= 0)
