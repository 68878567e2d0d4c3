"""The C SOC estimator on models with the surface SOC (model.surface_soc_gain): the step
reads its RC tables at clamp(soc + sv u_diff, 0, 1), the filter's F and H go through it
(d soc_s/d soc = 1 + dsv/dsoc u_diff, d soc_s/d u_diff = sv). Bit-identical to the float32
reference at every step, state and covariance entry, close to the float64 Python filter,
its Jacobians those of the C step (finite differences), on the emulated Cortex-M4F, under
ASan/UBSan and on random records (tests/test_codegen_estimator_robust.py holds those)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ecmgen.c import cref
from ecmgen.c.estcheck import bits_equal, run_estimator_c
from ecmgen.c.estref import simulate_estimator_f32
from ecmgen.config import EstimatorConfig
from ecmgen.model.model import load_model
from ecmgen.model.simulate import simulate

from test_codegen_estimator import MODEL, _check, _cycle
from test_codegen_estimator_effects import _compiled, _grids, jacobian_run, step_derivatives
from test_estimate import ALL_EFFECTS, drive_profile, model_over_temperature


def surface_est_model(case: str):
    if case == "one-temperature":        # one temperature row, searched grids (the float C's)
        from test_codegen_helpers import temperature_model

        return replace(temperature_model(1, 10, seed=5, branches=True), surface_soc_gain=0.5)
    if case == "irregular":              # searched RC and OCV grids, time constants over SOC
        from test_codegen_estimator import irregular_model

        return replace(irregular_model(False), surface_soc_gain=0.5)
    if case == "no-bv":
        return replace(model_over_temperature(True, False), surface_soc_gain=0.7)
    return replace(model_over_temperature(effects=ALL_EFFECTS if case.startswith("effects")
                                          else ()), surface_soc_gain=0.5)


@pytest.mark.parametrize("case", ["plain", "no-bv", "effects", "effects-offset",
                                  "one-temperature", "irregular", "effects-offset-flat"])
def test_bit_identical_with_gaps_and_missing_voltages(case):
    """Random currents both ways, dt = 0, gaps, temperatures beyond the tables, noisy
    voltages with a few NaN: C == float32 reference bit for bit; SOC within 2e-5 of the
    float64 Python filter. "-flat": started anywhere, the SOC read from the OCV alone, a
    held model error."""
    flat = case.endswith("-flat")
    case = case.removesuffix("-flat")
    m = surface_est_model(case)
    offset = case.endswith("offset")
    cm = _compiled(m, "sf", EstimatorConfig(
        offset_state=offset, **(dict(start_polarization_c=0.5, resistance_slopes=False,
                                     error_memory_s=60.0, polarization_soc_sigma=0.02,
                                     ocv_slope_spread=1.0)
                                if flat else {})))
    assert cm.spec.surface is not None
    t, i_raw, temp = drive_profile(1500, seed=1)
    i = i_raw - i_raw.mean()
    i[np.diff(t, prepend=t[0]) > 60.0] = 0.0
    noise = 0.003 * np.random.default_rng(2).standard_normal(t.size)
    v = simulate(m, t, i, 0.7, temp).voltage_v + noise
    _, d = _check(m, cm, t, i + 0.05 * offset, v, 0.5, temp, tol=2e-5)
    print(f"{case}: max |SOC(C) - SOC(float64)| {d:.2e}")
    v[[5, 700, 701]] = np.nan
    dt = cref.dt_from_time(t)
    got = run_estimator_c(cm, i, dt, v, 0.5, temp)
    assert bits_equal(got, simulate_estimator_f32(cm.spec, cm.estimator, i, dt, v, 0.5, temp))
    assert np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.p))


@pytest.mark.parametrize("case", ["plain", "effects-offset", "irregular"])
def test_jacobians_are_those_of_the_c_step(case):
    """F (with its u_diff column through the surface SOC) and H against central
    differences of the generated C step (the state before sample k perturbed): F = d
    state' / d state, H F = d v / d state but for u_diff (see below)."""
    m = surface_est_model(case)
    cm = _compiled(m, "sj", EstimatorConfig(offset_state=case.endswith("offset")))
    est = cm.estimator
    t, i, temp, dt, ref = jacobian_run(m, cm)
    N = est.n
    iu = est.names.index("u_diff_v")
    grids = _grids(m)
    checked = with_column = 0
    for k in range(1, t.size, 5):
        if abs(i[k]) < 0.2 or dt[k] <= 0:
            continue
        x0 = ref.x[k - 1].astype(np.float64)
        s1 = x0[0] + i[k] * dt[k] / (3600 * m.capacity_ah)
        # the tables' SOC: the surface SOC (about; sv <= lam / 0.3 V)
        near = np.min(np.abs(grids[None, :] - (s1 + np.linspace(-2, 2, 9)[:, None]
                                                 * abs(x0[iu]))))
        if near < 3e-3 or not 0.05 < ref.x[k, 0] < 0.95:
            continue
        F, dv = step_derivatives(cm, x0, i[k], temp[k], dt[k],
                                {"m.soc": 1e-3, "m.u_diff": 1e-3})
        Fr, Hr = ref.f[k].astype(np.float64), ref.h[k].astype(np.float64)
        np.testing.assert_allclose(F, Fr, rtol=2e-3, atol=3e-5, err_msg=f"F at sample {k}")
        # d v / d u_diff(k-1) has r0's term through the surface SOC besides H F: the filter
        # (as ecmgen.estimate) holds the u_diff before the step as the sample's input
        keep = np.arange(N) != iu
        np.testing.assert_allclose(dv[keep], (Hr @ Fr)[keep], rtol=2e-3, atol=3e-4,
                                   err_msg=f"H at {k}")
        checked += 1
        with_column += bool(np.any(Fr[1:3, iu] != 0))
    print(f"{case}: {checked} samples checked, {with_column} with a u_diff column")
    assert checked >= 15 and with_column >= 10, (checked, with_column)


@pytest.mark.parametrize("folder, name", [("25degC", "us06"), ("n20degC", "hwfet")])
def test_real_cycle_slices(folder, name):
    """The test model with surface_soc_gain 0.5 over the first 3000 samples of shared
    Panasonic cycles in the full-cell scenario (guess 0.8, 29 mA offset, gain 1.01): C ==
    float32 reference at every step, state and covariance entry; SOC within 2e-4 of the
    float64 Python filter."""
    m = replace(load_model(MODEL), surface_soc_gain=0.5)
    cm = _compiled(m, "sr")
    s = _cycle(folder, name)
    sl = slice(0, 3000)
    _, d = _check(m, cm, s.time_s[sl], 1.01 * s.current_a[sl] + 0.029, s.voltage_v[sl], 0.8,
                  s.temperature_c[sl], tol=2e-4)
    print(f"{folder} {name} surface 0.5: max |SOC(C) - SOC(float64)| {d:.2e}")
