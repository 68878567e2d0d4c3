"""The SOC estimator in C ([c] estimator = "ekf", ecmgen.c.estc): generated next to the
model's step, bit-identical to its float32 reference (ecmgen.c.estref) at every step and
every covariance entry over real cycles (cffi), within a small SOC tolerance of the float64
Python filter (ecmgen.estimate), refusals for what it does not take."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
import numpy as np
import pytest

from ecmgen.c import cref
from ecmgen.c.cbuild import compile_spec
from ecmgen.c.codegen import generate_c, prepare, render
from ecmgen.c.estc import est_state_bytes, prepare_estimator
from ecmgen.c.estcheck import bits_equal, python_filter_soc, run_estimator_c
from ecmgen.c.estref import simulate_estimator_f32
from ecmgen.config import EstimatorConfig
from ecmgen.errors import InputError
from ecmgen.estimate.run import run_filter
from ecmgen.model.model import load_model
from ecmgen.model.simulate import simulate

from conftest import REPO, SHARED_DATA, need, synthetic_nca_model
from test_estimate import ALL_EFFECTS, drive_profile, model_over_temperature
from test_pipeline import synthetic_project  # noqa: F401 (fixture)

MODEL = REPO / "tests" / "data" / "panasonic-temperature-model.json"
CYCLES = [("25degC", "us06"), ("25degC", "hwfet-a"), ("0degC", "us06"), ("0degC", "hwfet"),
          ("n10degC", "us06"), ("n10degC", "hwfet"), ("n20degC", "us06"), ("n20degC", "hwfet")]
SOC_TOL = 2e-4            # |SOC(float32 C) - SOC(float64 Python filter)| on the slices
SCENARIO = dict(guess=0.8, offset=0.029, gain=1.01)   # the full-cell sensor scenario


@pytest.fixture(scope="module")
def model():
    return load_model(MODEL)


@pytest.fixture(scope="module")
def built(model):
    spec = prepare(model, "float", None, "ecm")
    est = prepare_estimator(model, spec, EstimatorConfig())
    return compile_spec(spec, estimator=est)


def _check(model, cm, t, i_seen, v, guess, temp, tol=SOC_TOL):
    dt = cref.dt_from_time(t)
    got = run_estimator_c(cm, i_seen, dt, v, guess, temp)
    ref = simulate_estimator_f32(cm.spec, cm.estimator, i_seen, dt, v, guess, temp)
    assert bits_equal(got, ref), _first_difference(got, ref)
    P = got.p
    assert np.array_equal(P, np.swapaxes(P, 1, 2))              # exactly symmetric
    assert np.all(np.diagonal(P, axis1=1, axis2=2) >= 0)      # 0: an RC pair settled at rest
    assert np.all(P[:, 0, 0] > 0)
    assert np.all((got.soc >= 0) & (got.soc <= 1)) and np.all(np.isfinite(got.x))
    if tol is None:
        return got, None
    soc64 = python_filter_soc(model, t, i_seen, v, guess, cm.estimator.settings, temp)
    d = float(np.max(np.abs(got.soc - soc64)))
    assert d < tol, d
    return got, d


def _first_difference(got, ref):
    for f in ("v_pred", "x", "p"):
        a, b = getattr(got, f), getattr(ref, f)
        bad = np.argwhere(a.view(np.uint32) != b.view(np.uint32))
        if bad.size:
            k = tuple(bad[0])
            return f"{f} differs first at {k}: C {a[k]!r} reference {b[k]!r}"
    return "identical"


def _cycle(folder, name):
    from ecmgen.data.measure import read_timeseries

    path = need(SHARED_DATA / f"panasonic-18650pf-{folder}" / f"{name}.mat")
    return read_timeseries(path, capacity_ah=2.9)


def test_scalar_exp_is_the_runtimes():
    """estref.omexp, the scalar 1 - exp(-x) of the per-sample reference, is cref's."""
    from ecmgen.c.estref import omexp

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(0, 0.05, 3000), np.exp(rng.uniform(-30, 5, 3000)),
                        [0.0, -0.0, -1.0, 0.03125, 0.0312499981, 0.346573591, 86.9, 87.0,
                         1e30, np.inf, np.nan]]).astype(np.float32)
    want = cref.one_minus_exp_neg_f32(x)
    got = np.array([omexp(v) for v in x], dtype=np.float32)
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))


# -- generation -------------------------------------------------------------------------

def test_generated_files_deterministic_and_absent_by_default(model, tmp_path):
    a = generate_c(model, tmp_path / "a", estimator=EstimatorConfig())
    b = generate_c(model, tmp_path / "b", estimator=EstimatorConfig())
    names = sorted(p.name for p in a)
    assert names == sorted(p.name for p in b)
    assert {"ecm_est_f32.h", "ecm_est_f32.c", "ecmrt_est_f32.h"} <= set(names)
    for p in a:
        assert p.read_bytes() == (tmp_path / "b" / p.name).read_bytes()
    src = (tmp_path / "a" / "ecm_est_f32.c").read_text()
    assert "void ecm_est_init_f32(ecm_est_f32_t *e, float soc0)" in src
    assert "_est_" not in (tmp_path / "a" / "ecm_ecm_f32.c").read_text()  # in its own files
    assert ".model_error = 0.189999998f" in src          # the settings, baked in
    plain = render(prepare(model, "float", None, "ecm"))
    assert "est" not in "".join(plain) and "_est_" not in plain["ecm_ecm_f32.c"]
    mk = (tmp_path / "a" / "ecm_ecm_f32_files.mk").read_text()
    assert "ecm_est_f32.h" in mk and "ecm_est_f32.c" in mk and "ecmrt_est_f32.h" in mk


def test_strict_flags_at_every_optimisation_level_give_the_same_bits(model):
    spec = prepare(model, "float", None, "bms")
    est = prepare_estimator(model, spec, EstimatorConfig())
    t, i, temp = drive_profile(600, seed=3)
    v = simulate(model, t, i, 0.6, temp).voltage_v
    dt = cref.dt_from_time(t)
    cms = [compile_spec(spec, opt=(o,), estimator=est) for o in ("-O0", "-O2", "-Os")]
    assert cms[0].lib.ecmh_est_size() == est_state_bytes(spec, est)
    runs = [run_estimator_c(cm, i, dt, v, 0.9, temp) for cm in cms]
    assert bits_equal(runs[0], runs[1]) and bits_equal(runs[0], runs[2])
    ref = simulate_estimator_f32(spec, est, i, dt, v, 0.9, temp)
    assert bits_equal(runs[0], ref), _first_difference(runs[0], ref)


def test_first_call_takes_any_dt(model):
    """est_init is the state at the first sample: the first call's dt is not used, so a
    loop that passes its nominal period from the start gets the filter of dt = 0 there."""
    spec = prepare(model, "float", None, "bms")
    est = prepare_estimator(model, spec, EstimatorConfig(start_polarization_c=0.5))
    t, i, temp = drive_profile(300, seed=5)
    v = simulate(model, t, i, 0.6, temp).voltage_v
    dt = cref.dt_from_time(t)
    cm = compile_spec(spec, estimator=est)
    runs = [run_estimator_c(cm, i, np.concatenate([[d0], dt[1:]]), v, 0.8, temp)
            for d0 in (0.0, 1.0, 3600.0)]
    assert bits_equal(runs[0], runs[1]) and bits_equal(runs[0], runs[2])
    ref = simulate_estimator_f32(spec, est, i, np.concatenate([[1.0], dt[1:]]), v, 0.8, temp)
    assert bits_equal(runs[1], ref)


@pytest.mark.parametrize("case, needle", [
    ("fixed", "float32 only"), ("dt", "variable-dt"), ("kind", "c.estimator")])
def test_refusals(case, needle):
    """What the C estimator still refuses, in one line (models with effects and the offset
    state it takes: tests/test_codegen_estimator_effects.py)."""
    m = model_over_temperature(effects=ALL_EFFECTS)
    spec = prepare(m, "fixed" if case == "fixed" else "float", 0.1 if case == "dt" else None)
    cfg = EstimatorConfig(offset_state=True)
    with pytest.raises(InputError) as exc:
        prepare_estimator(m, spec, cfg, kind="ukf" if case == "kind" else "ekf")
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_cli_codegen_estimator(tmp_path):
    out = tmp_path / "c"
    res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "codegen", str(MODEL), "--out",
                          str(out), "--estimator", "ekf", "--prefix", "cell"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert (out / "cell_est_f32.h").is_file() and "cell_est_step_f32" in (out / "cell_est_f32.c").read_text()
    res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "codegen", str(MODEL), "--out",
                          str(tmp_path / "d"), "--estimator", "ekf", "--numeric", "fixed"],
                         capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.startswith("ecmgen: error:")
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "d").exists()


# -- equivalence ----------------------------------------------------------------------

@pytest.mark.parametrize("diffusion, bv, one_temp", [(True, False, False), (False, True, False),
                                                     (False, False, True), ("curve", True, False),
                                                     ("curve", False, False)],
                         ids=["diffusion", "butler-volmer", "plain-2rc", "curve-layout",
                              "curve-layout-tau-per-direction"])
def test_switch_combinations_dt_zero_gaps_and_missing_voltages(diffusion, bv, one_temp):
    """Synthetic models over the runtime's switches (own OCV grid, no temperature axis, the
    curve fit's layout: uniform SOC grids and time constants over temperature only, ...):
    random currents both ways, repeated time stamps, gaps up to 20000 s (at rest: the truth
    stays within 0.66..0.73), temperatures beyond the table ends, measured voltages with
    noise and a few NaN (no update); and the raw profile, which holds its currents over the
    gaps and drains the truth far below empty (SOC pinned at 0: bit-identical, finite)."""
    if diffusion == "curve":
        from test_codegen_helpers import fitter_layout_model

        m = fitter_layout_model(rows=slice(2, 9), branches=bv, same_tau=bv)
    else:
        m = synthetic_nca_model() if one_temp else model_over_temperature(diffusion, bv)
    t, i_raw, temp = drive_profile(1500, seed=1)
    i = i_raw - i_raw.mean()
    i[np.diff(t, prepend=t[0]) > 60.0] = 0.0
    temp = None if one_temp else temp
    noise = 0.003 * np.random.default_rng(2).standard_normal(t.size)
    v = simulate(m, t, i, 0.7, temp).voltage_v + noise
    v_nan = v.copy()
    v_nan[[5, 700, 701]] = np.nan
    spec = prepare(m, "float", None, "syn")
    cm = compile_spec(spec, estimator=prepare_estimator(m, spec, EstimatorConfig()))
    _check(m, cm, t, i, v, 0.5, temp, tol=2e-5)
    _check(m, cm, t, i_raw, simulate(m, t, i_raw, 0.7, temp).voltage_v + noise, 0.5, temp,
           tol=None)
    dt = cref.dt_from_time(t)
    got = run_estimator_c(cm, i, dt, v_nan, 0.5, temp)
    assert bits_equal(got, simulate_estimator_f32(spec, cm.estimator, i, dt, v_nan, 0.5, temp))
    assert np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.p))


def irregular_model(ocv_uniform: bool = False):
    """The test model on irregular SOC grids: the RC tables (time constants varying along
    SOC) on one, the OCV on its own (the runtime's searched grids, the OCV's own segment;
    ``ocv_uniform``: a uniform one of 26 points)."""
    from ecmgen.model.model import OcvOverTemperature

    m = load_model(MODEL)
    rc_soc = np.array([0.0, 0.03, 0.1, 0.18, 0.3, 0.45, 0.5, 0.62, 0.8, 0.9, 0.97, 1.0])
    ocv_soc = (np.linspace(0.0, 1.0, 26) if ocv_uniform else
               np.array([0.0, 0.02, 0.05, 0.11, 0.2, 0.33, 0.5, 0.7, 0.85, 0.93, 1.0]))

    def on(grid, old, rows):
        return np.array([np.interp(grid, old, r) for r in np.atleast_2d(rows)])

    tables = {}
    for name in ("charge", "discharge"):
        t = m.table(name)
        shape = (t.r0_ohm.shape[0], rc_soc.size)
        tables[name] = replace(t, soc=rc_soc, fit_error=np.zeros(shape),
                               converged=np.ones(shape, dtype=bool),
                               **{f: on(rc_soc, t.soc, getattr(t, f)) *
                                  (1 + 0.3 * rc_soc if f.startswith("tau") else 1)
                                  for f in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm",
                                            "tau_slow_s")})
    ocv = OcvOverTemperature(m.ocv.temperature_c, ocv_soc, on(ocv_soc, m.ocv.soc, m.ocv.ocv_v))
    return replace(m, ocv=ocv, charge=tables["charge"], discharge=tables["discharge"])


@pytest.mark.parametrize("folder, name, ocv_uniform", [("25degC", "us06", False),
                                                      ("n20degC", "hwfet", True)])
def test_irregular_grids_own_ocv_grid(folder, name, ocv_uniform):
    m = irregular_model(ocv_uniform)
    spec = prepare(m, "float", None, "irr")
    cm = compile_spec(spec, estimator=prepare_estimator(m, spec, EstimatorConfig()))
    s = _cycle(folder, name)
    seen = SCENARIO["gain"] * s.current_a + SCENARIO["offset"]
    sl = slice(0, 1500)
    _check(m, cm, s.time_s[sl], seen[sl], s.voltage_v[sl], SCENARIO["guess"],
           s.temperature_c[sl], tol=5e-4)


def test_dt_zero_changes_nothing_and_a_long_gap_relaxes(built):
    """After the first sample, dt = 0 neither integrates nor updates; a day's gap at rest
    lets the RC voltages decay to 0."""
    t = np.array([0.0, 1.0, 1.0, 86401.0])
    i = np.array([0.0, -3.0, -3.0, 0.0])
    v = np.array([4.1, 4.0, 3.5, 4.05])
    got = run_estimator_c(built, i, cref.dt_from_time(t), v, 0.9, 20.0)
    assert np.array_equal(got.x[2], got.x[1]) and np.array_equal(got.p[2], got.p[1])
    assert np.all(np.abs(got.x[3, 1:]) < 1e-6)


@pytest.mark.parametrize("folder, name", CYCLES)
def test_real_cycle_slices_bit_identical(model, built, folder, name):
    """The start of every shared cycle in the full-cell scenario (guess 0.8 for a full cell,
    current offset 29 mA and gain 1.01 in what the filter sees), and a slice from the middle
    started from 0.5: C == float32 reference at every step; SOC within SOC_TOL of the float64
    filter."""
    s = _cycle(folder, name)
    seen = SCENARIO["gain"] * s.current_a + SCENARIO["offset"]
    sl = slice(0, 2000)
    _check(model, built, s.time_s[sl], seen[sl], s.voltage_v[sl], SCENARIO["guess"],
           s.temperature_c[sl])
    mid = s.time_s.size // 2
    sl = slice(mid, mid + 1000)
    _check(model, built, s.time_s[sl], seen[sl], s.voltage_v[sl], 0.5, s.temperature_c[sl])


@pytest.mark.parametrize("first_dt", [0.0, 0.1])
def test_a_loaded_first_sample_leaves_the_rc_voltages_unknown(model, built, first_dt):
    """Started under load in the middle of a cycle with start_polarization_c > 0: the first
    step gives every RC voltage the start variance (r_j start_a)^2, the first sample does
    not set the SOC (dt = 0: no information; dt > 0: R with the error's correlation), C ==
    float32 reference; the default (a rested start) counts the first sample fully."""
    s = _cycle("25degC", "us06")
    k0 = s.time_s.size // 2 + int(np.argmax(np.abs(s.current_a[s.time_s.size // 2:]) > 2.0))
    sl = slice(k0, k0 + 300)
    seen = SCENARIO["gain"] * s.current_a[sl] + SCENARIO["offset"]
    dt = cref.dt_from_time(s.time_s[sl])
    dt[0] = first_dt
    args = (seen, dt, s.voltage_v[sl], 0.5, s.temperature_c[sl])
    anywhere = compile_spec(built.spec, estimator=prepare_estimator(
        model, built.spec, EstimatorConfig(start_polarization_c=0.5)))
    got = run_estimator_c(anywhere, *args)
    assert bits_equal(got, simulate_estimator_f32(anywhere.spec, anywhere.estimator, *args))
    assert abs(float(got.soc[0]) - 0.5) < 0.01
    rested = run_estimator_c(built, *args)
    assert abs(float(rested.soc[0]) - 0.5) > 0.05          # the loaded voltage taken as OCV
    p0_u = built.estimator.noise["p0_u"]
    assert np.all(np.diagonal(got.p[0])[1:4] > np.diagonal(rested.p[0])[1:4] + 5 * p0_u)


def test_the_soc_read_from_the_ocv_alone(model, built):
    """resistance_slopes = false: the Jacobians take the RC tables as flat in SOC; C ==
    float32 reference, bit for bit, and follows the float64 filter; H's SOC entry is the
    OCV's slope alone (its SOC sigma differs from the filter with the slopes)."""
    cfg = EstimatorConfig(start_polarization_c=0.5, resistance_slopes=False,
                          polarization_soc_sigma=0.02)
    _, ref, again = _c_against_references(model, built, ("0degC", "us06"),
                                          slice(5000, 8000), cfg)
    sloped = again(replace(cfg, resistance_slopes=True))
    assert abs(ref.soc_sigma[-1] - sloped.soc_sigma[-1]) > 1e-4


def test_the_ocv_slope_over_the_socs_spread(model, built):
    """ocv_slope_spread = 1: H's OCV slope is the secant over soc +- sigma_soc; C == float32
    reference, bit for bit, and follows the float64 filter; started 0.2 off, the secant
    moves the SOC and its sigma otherwise than the tangent does."""
    cfg = EstimatorConfig(start_polarization_c=0.5, resistance_slopes=False,
                          ocv_slope_spread=1.0)
    _, ref, again = _c_against_references(model, built, ("0degC", "us06"),
                                          slice(5000, 8000), cfg)
    tangent = again(replace(cfg, ocv_slope_spread=0.0))
    assert abs(ref.soc_sigma[-1] - tangent.soc_sigma[-1]) > 1e-4


def _c_against_references(model, built, cycle, sl, cfg):
    """The C filter with ``cfg`` on a slice of a shared cycle (SCENARIO's sensor errors,
    start 0.6): bit-exact to its float32 reference and within 0.1 % SOC of the float64
    filter. Returns (the compiled filter, the float64 run, a float64 run with other
    settings)."""
    s = _cycle(*cycle)
    seen = SCENARIO["gain"] * s.current_a[sl] + SCENARIO["offset"]
    compiled = compile_spec(built.spec, estimator=prepare_estimator(model, built.spec, cfg))
    args = (seen, cref.dt_from_time(s.time_s[sl]), s.voltage_v[sl], 0.6,
            s.temperature_c[sl])
    got = run_estimator_c(compiled, *args)
    assert bits_equal(got, simulate_estimator_f32(compiled.spec, compiled.estimator, *args))

    def again(settings):
        return run_filter(model, s.time_s[sl], seen, s.voltage_v[sl], 0.6, settings,
                          s.temperature_c[sl])

    ref = again(cfg)
    assert np.max(np.abs(got.soc - ref.soc)) < 1e-3
    return compiled, ref, again


def test_the_model_error_held_after_a_current_step(model, built):
    """error_memory_s > 0: the overpotential the model error scales with is held and
    decays after a current step; C == float32 reference, bit for bit; its SOC follows the
    float64 filter; a held overpotential only widens R, so the SOC sigma ends no smaller;
    <prefix>_est_t holds it (4 B more than without)."""
    cfg = EstimatorConfig(start_polarization_c=0.5, polarization_error=0.2,
                          error_memory_s=60.0)
    held, ref, again = _c_against_references(model, built, ("25degC", "us06"),
                                             slice(0, 3000), cfg)
    assert held.lib.ecmh_est_size() == est_state_bytes(held.spec, held.estimator) \
        == est_state_bytes(built.spec, built.estimator) + 4         # the held eta_v
    plain = again(replace(cfg, error_memory_s=0.0))
    assert ref.soc_sigma[-1] >= plain.soc_sigma[-1]


@pytest.mark.slow
def test_whole_cycles_bit_identical(model, built):
    """Every shared cycle, whole, in the full-cell scenario: bit-identical at every step and
    covariance entry; the largest SOC difference from the float64 filter is printed."""
    worst = 0.0
    for folder, name in CYCLES:
        s = _cycle(folder, name)
        seen = SCENARIO["gain"] * s.current_a + SCENARIO["offset"]
        _, d = _check(model, built, s.time_s, seen, s.voltage_v, SCENARIO["guess"],
                      s.temperature_c, tol=1e-3)
        print(f"{folder} {name}: {s.time_s.size} steps, max |dSOC| vs float64 {d:.2e}")
        worst = max(worst, d)
    print(f"worst max |dSOC| {worst:.2e}")


def test_config_c_estimator(tmp_path):
    from ecmgen.config import load_config

    for name in ("a.csv", "cycle.csv"):
        (tmp_path / name).write_text("time_s,current_a,voltage_v\n0,0,3.7\n")
    head = ('[cell]\ncapacity_ah = 2.9\n[data]\ncycle = "cycle.csv"\n'
            '[[data.pulse_tests]]\nfile = "a.csv"\n')
    cfg = tmp_path / "cell.toml"
    for text, needle in [('estimator = "ukf"', "c.estimator"),
                         ('estimator = "ekf"\nnumeric = "fixed"', "float"),
                         ('estimator = "ekf"\ndt_s = 0.1', "variable-dt")]:
        cfg.write_text(head + "[c]\n" + text + "\n")
        with pytest.raises(InputError) as exc:
            load_config(cfg)
        assert needle in str(exc.value)
    cfg.write_text(head + '[c]\nestimator = "ekf"\n')
    assert load_config(cfg).c_estimator == "ekf"
    cfg.write_text(head)
    assert load_config(cfg).c_estimator is None


def test_build_json_reports_the_estimator(synthetic_project):
    """`ecmgen build --json` with [c] estimator = "ekf": the float C gets the filter and its
    block in "c" carries the estimator's figures beside the step's."""
    import contextlib
    import io
    import json

    from ecmgen.cli import main

    tmp_path, cfg, _ = synthetic_project
    t = np.arange(0, 1800.0, 1.0)                     # the fixture's cycle
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\nocv = "ocv.csv"\n'
                   'cycle = "cycle.csv"\n[fit]\nrelax_s = 900\nmethods = ["lm"]\n'
                   '[c]\nnumeric = ["float", "fixed"]\nestimator = "ekf"\n')
    out = tmp_path / "out"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["build", str(cfg), "--out", str(out), "--json", "--no-plots", "--quiet"]) == 0
    c = json.loads(buf.getvalue())["c"]
    est = c["float"]["estimator"]
    assert est["bit_exact_vs_reference"] is True and est["steps"] == t.size
    assert est["max_abs_soc_diff_vs_python"] < 1e-4 and est["states"][0] == "soc"
    assert c["float"]["bit_exact_vs_reference"] is True
    assert c["float"]["ocv_soc_step"] == c["fixed"]["rc_soc_step"] == 1   # the flash options
    assert "c/float/ecm_est_f32.h" in c["float"]["files"] and "estimator" not in c["fixed"]
    assert "c/float/ecm_est_f32_vectors.h" in c["float"]["files"]   # its golden vectors
    assert main(["verify", str(out)]) == 0
    assert (out / "c" / "float" / "ecmrt_est_f32.h").is_file()
    assert not (out / "c" / "fixed" / "ecm_est_f32.h").exists()
    # model_error / error_correlation_s not in the config: measured on the validation cycle
    # and baked in
    from ecmgen.c.codegen import c_float

    assert est["settings_from"] == "validation cycles" and est["model_error"] != 0.19
    src = (out / "c" / "float" / "ecm_est_f32.c").read_text()
    assert f".model_error = {c_float(est['model_error'])}" in src
    assert f".corr_s = {c_float(est['error_correlation_s'])}" in src
