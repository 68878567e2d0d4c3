"""GA and casadi-LM fits of the paper's DC-IR point curves (ecmgen.fit: points, ga, lm).

Truth tables are synthesised from known 2RC parameters; measured resistances are made
the way a DC-IR extraction makes them: R(t) = (V(t) - V_rest) / I from noisy voltages.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares

from ecmgen.fit import Bounds, PointFit, curve_r_ohm, default_bounds, fit_ga, fit_lm
from ecmgen.fit import lm as lm_mod
from ecmgen.fit import points as fp

PAPER_T = np.array([0.1, 1.0, 3.0, 6.0, 10.0])
# Aras & Yonel (2017) Table 1: 70 % SOC, charge, 25 degC
TABLE1_R = np.array([[0.0002, 0.0012, 0.0021, 0.0023, 0.0025]])
# Eq. 5 optimum of Table 1 under the default bounds, R0 >= 0 and tau_fast < tau_slow,
# computed independently with scipy differential_evolution (popsize 40, tol 1e-14,
# 4 seeds, all agreeing): tau_fast 1.228 s, tau_slow 50 s (= upper bound), 100.126 uOhm
TABLE1_EQ5_OPT = 100.1261e-6

FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")


def r_model(theta, t):
    r0, rf, tf, rs, ts = theta
    return r0 + rf * (1 - np.exp(-t / tf)) + rs * (1 - np.exp(-t / ts))


def measured_table(truths, t, current_a, noise_v, rng, rest_samples=50):
    """R(t) = (V(t) - V_rest)/I with Gaussian voltage noise on every sample; V_rest is the
    mean of ``rest_samples`` noisy rest samples before the pulse (OCV cancels)."""
    rows = []
    for theta, i_a in zip(truths, np.broadcast_to(current_a, len(truths))):
        ocv = 3.6
        v = ocv + i_a * r_model(theta, t) + noise_v * rng.standard_normal(t.size)
        v_rest = ocv + noise_v * rng.standard_normal(rest_samples).mean()
        rows.append((v - v_rest) / i_a)
    return np.array(rows)


def params(fit: PointFit) -> np.ndarray:
    return np.stack([getattr(fit, k) for k in FIELDS], axis=1)


def check_physical(fit: PointFit, bounds: Bounds, rows=slice(None)):
    """Bounds, tau_fast < tau_slow and R0 >= 0 on the fitted rows."""
    for name, (lo, hi) in (("tau_fast_s", bounds.tau_fast_s), ("tau_slow_s", bounds.tau_slow_s),
                           ("r_fast_ohm", bounds.r_fast_ohm), ("r_slow_ohm", bounds.r_slow_ohm)):
        v = getattr(fit, name)[rows]
        assert np.all((v >= lo) & (v <= hi)), (name, v, lo, hi)
    assert np.all(fit.tau_fast_s[rows] < fit.tau_slow_s[rows])
    assert np.all(fit.r0_ohm[rows] >= 0)


# -- the paper's Table 1 ------------------------------------------------------------------
def test_table1_no_pinned_2rc_curve_gets_within_20_uohm():
    """The brief asked for both fits within 20 uOhm of every Table-1 point. No curve
    R0 + Rf(1-e^-t/tf) + Rs(1-e^-t/ts) through the first point can do that, whatever
    its parameters (negative R, any tau, R0 < 0 all allowed here): the least-squares
    optimum over the four later points has an RMS deviation of ~31.7 uOhm (reached in
    the limit tau_slow -> infinity), and max |dev| >= RMS for any curve. So the Table-1
    tests below check the achievable optimum instead of 20 uOhm."""
    t, r = PAPER_T, TABLE1_R[0] * 1e3                      # mOhm for conditioning
    d = r[1:] - r[0]

    def res(x):
        tf, ts = np.exp(x[0]), np.exp(x[1])
        return (x[2] * (np.exp(-t[0] / tf) - np.exp(-t[1:] / tf))
                + x[3] * (np.exp(-t[0] / ts) - np.exp(-t[1:] / ts)) - d)

    best = np.inf
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        best = _best_rms(res)
    assert 31e-3 < best < 32.5e-3          # mOhm: 31.7 uOhm RMS > 20 uOhm


def _best_rms(res):
    best = np.inf
    for lf in np.linspace(-3, 3, 7):
        for ls in np.linspace(0, 10, 6):
            for rf, rs in ((2.0, 2.0), (-1.0, 3.0)):
                sol = least_squares(res, [lf, ls, rf, rs], method="lm", max_nfev=400)
                if np.all(np.isfinite(sol.fun)):
                    best = min(best, np.sqrt(np.mean(sol.fun ** 2)))
    return best


def test_table1_ga_and_lm():
    bounds = default_bounds(PAPER_T, TABLE1_R)
    ga = fit_ga(PAPER_T, TABLE1_R, seed=0)
    lm = fit_lm(PAPER_T, TABLE1_R)
    lm_ga = fit_lm(PAPER_T, TABLE1_R, x0=ga)
    for f in (ga, lm, lm_ga):
        assert f.converged.all()
        check_physical(f, bounds)
        curve = curve_r_ohm(f, PAPER_T)
        assert curve.shape == (1, 5)
        # R0 convention: the curve passes exactly through the first point
        assert abs(curve[0, 0] - TABLE1_R[0, 0]) < 1e-15
        # Eq. 5 as reported
        assert f.fitness_ohm[0] == pytest.approx(np.sum(np.abs(curve - TABLE1_R)[0, 1:]), rel=1e-9)
    # GA reaches the global Eq.-5 optimum (within 1e-5 relative)
    assert ga.fitness_ohm[0] == pytest.approx(TABLE1_EQ5_OPT, rel=1e-5)
    # the L1 optimum concentrates the misfit on one point; LM (least squares) spreads it:
    # a smaller worst point and, by its definition, no larger a sum of squares
    miss_ga = curve_r_ohm(ga, PAPER_T) - TABLE1_R
    miss_lm = curve_r_ohm(lm, PAPER_T) - TABLE1_R
    assert np.max(np.abs(miss_lm)) < np.max(np.abs(miss_ga))
    assert np.sum(miss_lm ** 2) <= np.sum(miss_ga ** 2) * (1 + 1e-9)
    assert lm_ga.fitness_ohm[0] <= ga.fitness_ohm[0]


# -- known truth ----------------------------------------------------------------------
# Noise-free curves at the paper's five times: five points pin the four free
# parameters (exact interpolation), for fast taus 0.5-2 s and slow taus 5-20 s.
TRUTH_5PT = np.array([
    # R0      R_fast  tau_fast R_slow  tau_slow     (ohm, s)
    (0.030, 0.012, 0.6, 0.015, 6.0),
    (0.026, 0.010, 0.8, 0.013, 8.0),
    (0.023, 0.009, 1.0, 0.012, 10.0),
    (0.021, 0.008, 1.5, 0.012, 15.0),
    (0.020, 0.008, 2.0, 0.011, 20.0),
    (0.022, 0.009, 0.5, 0.012, 5.0),
])

# With 1 mV voltage noise, five points cannot identify the parameters to 5 %: for
# mOhm-scale R and 15 A pulses the Cramer-Rao standard deviations at t = 0.1, 1, 3, 6,
# 10 s are 5-18 % on R_fast and tau_fast and 10-70 % on tau_slow (e.g. R0 30 mOhm,
# R_fast 12 mOhm / 1.5 s, R_slow 15 mOhm / 12 s: 17 %, 13 %, 22 %, 71 %), and far
# worse at a few A. No fitter can beat that, so the noisy known-truth test samples the
# same 10 s pulse densely (50 Hz, 496 points; the API takes any t_s) at 15 A. Even then
# tau_slow beyond ~6 s is not identifiable to 5 % within a 10 s pulse, so these truths
# (18650-like, low-to-high SOC) have tau_slow 3-5 s. The largest error is tau_fast
# (~1.3-1.6 % RMS), dominated by the noise of the single pinned first sample (the R0
# convention). Monte Carlo over noise draws of this whole 5-cell table (all 25
# parameters within 5 %): LM 199 of 200 draws (worst draw 5.4 %), GA 40 of 40 draws
# (worst 3.7 %). The seed used here is simply the first one tried (worst: GA 1.5 %,
# LM 1.3 %).
TRUTH_DENSE = np.array([
    (0.035, 0.016, 0.5, 0.020, 3.0),
    (0.030, 0.014, 0.6, 0.018, 4.0),
    (0.027, 0.013, 0.7, 0.017, 5.0),
    (0.025, 0.012, 0.6, 0.016, 4.5),
    (0.024, 0.012, 0.5, 0.016, 4.0),
])
DENSE_T = np.round(np.arange(0.1, 10.0 + 1e-9, 0.02), 10)


@pytest.fixture(scope="module")
def dense_fits():
    rng = np.random.default_rng(0)
    table = measured_table(TRUTH_DENSE, DENSE_T, current_a=15.0, noise_v=1e-3, rng=rng)
    ga = fit_ga(DENSE_T, table, seed=0)
    lm = fit_lm(DENSE_T, table)
    lm_ga = fit_lm(DENSE_T, table, x0=ga)
    return table, ga, lm, lm_ga


@pytest.mark.parametrize("method", ["ga", "lm"])
def test_known_truth_five_points_noise_free(method):
    table = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT])
    fit = fit_ga(PAPER_T, table, seed=0) if method == "ga" else fit_lm(PAPER_T, table)
    assert fit.method == method
    assert fit.converged.all()
    err = np.abs(params(fit) / TRUTH_5PT - 1)
    assert err.max() < 1e-3, err            # measured: GA 4e-6, LM 4e-10


@pytest.mark.parametrize("method", ["ga", "lm", "lm_ga"])
def test_known_truth_dense_noisy(dense_fits, method):
    table, ga, lm, lm_ga = dense_fits
    fit = {"ga": ga, "lm": lm, "lm_ga": lm_ga}[method]
    assert fit.converged.all()
    check_physical(fit, default_bounds(DENSE_T, table))
    err = np.abs(params(fit) / TRUTH_DENSE - 1)
    assert err.max() < 0.05, np.round(err * 100, 2)


def test_lm_from_ga_never_worse_in_eq5(dense_fits):
    table, ga, _, lm_ga = dense_fits
    assert np.all(lm_ga.fitness_ohm <= ga.fitness_ohm)
    # and on a noisy five-point table, where the L1 and L2 optima differ most
    rng = np.random.default_rng(3)
    table5 = measured_table(np.tile(TRUTH_5PT, (3, 1)), PAPER_T, [2.0, 5.0, 15.0] * 6, 1e-3, rng)
    ga5 = fit_ga(PAPER_T, table5, seed=1)
    lm5 = fit_lm(PAPER_T, table5, x0=ga5)
    assert np.all(lm5.fitness_ohm <= ga5.fitness_ohm)
    assert lm5.converged.all() and ga5.converged.all()


# -- GA determinism -------------------------------------------------------------------
def test_ga_same_seed_bit_identical_and_other_seed_still_good():
    rng = np.random.default_rng(11)
    table = measured_table(np.tile(TRUTH_5PT, (2, 1)), PAPER_T, 15.0, 1e-3, rng)
    table[3, 4] = np.nan                          # one short pulse, for good measure
    a = fit_ga(PAPER_T, table, seed=5)
    b = fit_ga(PAPER_T, table, seed=5)
    for f in dataclasses.fields(PointFit):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype, f.name
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f.name
        else:
            assert x == y
    c = fit_ga(PAPER_T, table, seed=6)
    assert not np.array_equal(a.tau_fast_s, c.tau_fast_s)     # a different stream ...
    assert c.converged.all()
    # ... reaching the same Eq.-5 optimum (to 1e-3 relative, or 1 nOhm where ~0)
    assert np.all(np.abs(c.fitness_ohm - a.fitness_ohm) <= 1e-3 * a.fitness_ohm + 1e-9)
    clean = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT])
    for seed in (1, 2):
        err = np.abs(params(fit_ga(PAPER_T, clean, seed=seed)) / TRUTH_5PT - 1)
        assert err.max() < 1e-3


# -- masking, non-convergence, bounds -------------------------------------------------
def test_nan_points_are_ignored_and_short_rows_reported():
    clean = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT[:3]])
    table = np.vstack([
        clean[0],
        np.where(np.arange(5) == 4, np.nan, clean[1]),    # pulse cut before 10 s: 3 points left
        np.where(np.arange(5) == 0, np.nan, clean[2]),    # first point missing: pinned at 1 s
        np.where(np.arange(5) >= 3, np.nan, clean[0]),    # only 2 points after the first
        np.full(5, np.nan),                               # nothing
    ])
    for fit in (fit_ga(PAPER_T, table, seed=0), fit_lm(PAPER_T, table)):
        assert fit.converged.tolist() == [True, True, True, False, False]
        for k in FIELDS + ("fitness_ohm",):
            v = getattr(fit, k)
            assert v.shape == (5,)
            assert np.all(np.isfinite(v[:3])) and np.all(np.isnan(v[3:])), k
        # three noise-free points after the first still pin the curve at those points
        curve = curve_r_ohm(fit, PAPER_T)
        ok = np.isfinite(table[:3])
        assert np.max(np.abs(curve[:3][ok] - table[:3][ok])) < 1e-9
        # row 0 is identified from all five points
        assert np.max(np.abs(params(fit)[0] / TRUTH_5PT[0] - 1)) < 1e-3
        # row 2: pinned at its first valid point (t = 1 s)
        assert abs(curve[2, 1] - table[2, 1]) < 1e-15


def test_nan_column_equals_dropping_it():
    clean = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT[:2]])
    t6 = np.array([0.1, 1.0, 2.0, 3.0, 6.0, 10.0])
    with_nan = np.insert(clean, 2, np.nan, axis=1)
    a, b = fit_lm(t6, with_nan), fit_lm(PAPER_T, clean)
    np.testing.assert_allclose(params(a), params(b), rtol=1e-8)
    # the GA drops all-NaN columns before evolving: same result for the same seed
    a, b = fit_ga(t6, with_nan, seed=3, bounds=default_bounds(PAPER_T, clean)), \
        fit_ga(PAPER_T, clean, seed=3, bounds=default_bounds(PAPER_T, clean))
    np.testing.assert_array_equal(params(a), params(b))


def test_iteration_caps_are_reported_as_not_converged():
    table = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT])
    ga = fit_ga(PAPER_T, table, seed=0, max_generations=5)
    assert not ga.converged.any() and np.all(ga.iterations == 5)
    assert np.all(np.isfinite(ga.fitness_ohm))
    lm = fit_lm(PAPER_T, table, max_iterations=2)
    assert not lm.converged.any() and np.all(lm.iterations == 2)
    full = fit_lm(PAPER_T, table)
    assert full.converged.all() and np.all(full.iterations > 2)


def test_custom_bounds_are_respected():
    """A box that excludes the truth: the fits stop on its faces, never beyond."""
    table = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT])
    bounds = Bounds(tau_fast_s=(0.7, 1.2), tau_slow_s=(4.0, 9.0),
                    r_fast_ohm=(0.002, 0.011), r_slow_ohm=(0.0, 0.014))
    ga = fit_ga(PAPER_T, table, bounds=bounds, seed=0)
    lm = fit_lm(PAPER_T, table, bounds=bounds)
    lm_ga = fit_lm(PAPER_T, table, bounds=bounds, x0=ga)
    for f in (ga, lm, lm_ga):
        check_physical(f, bounds)
        assert np.all(np.abs(curve_r_ohm(f, PAPER_T)[:, 0] - table[:, 0]) < 1e-15)
    assert np.any(ga.tau_slow_s == 9.0) and np.any(ga.tau_fast_s == 0.7)
    assert np.all(lm_ga.fitness_ohm <= ga.fitness_ohm)


def test_r0_constraint_active():
    """Data whose unconstrained optimum has R0 < 0: the fits hold R0 = 0 exactly."""
    t = PAPER_T
    theta = (0.0, 0.010, 0.4, 0.008, 6.0)         # R0 = 0 and a fast branch at t0
    table = r_model(theta, t)[None, :] - np.array([[0.0003, 0, 0, 0, 0]])
    ga, lm = fit_ga(t, table, seed=0), fit_lm(t, table)
    assert lm.r0_ohm[0] == 0.0                    # LM: projected onto R0 = 0
    assert 0.0 <= ga.r0_ohm[0] < 1e-7 * table[0, 0]   # GA: to its stall tolerance
    for f in (ga, lm):
        assert f.converged.all()
        assert curve_r_ohm(f, t)[0, 0] == pytest.approx(table[0, 0], abs=1e-15)


def test_default_bounds_follow_the_data():
    r = np.array([r_model(th, PAPER_T) for th in TRUTH_5PT])
    b = default_bounds(PAPER_T, r)
    assert b.tau_fast_s[0] > 0 and b.tau_fast_s[0] < b.tau_slow_s[1]
    # the paper's times: tau in [max(0.9/10, 0.1/5), 9.9] and [.., 5 x 10 s]
    assert b.tau_fast_s == pytest.approx((0.09, 9.9))
    assert b.tau_slow_s == pytest.approx((0.09, 50.0))
    # scale-free: x10 resistance -> x10 R bounds, x2 time -> x2 tau bounds
    b10 = default_bounds(PAPER_T, 10 * r)
    assert b10.r_fast_ohm[1] == pytest.approx(10 * b.r_fast_ohm[1])
    b2 = default_bounds(2 * PAPER_T, r)
    assert b2.tau_slow_s == pytest.approx((2 * b.tau_slow_s[0], 2 * b.tau_slow_s[1]))
    # the truths lie well inside
    for th in TRUTH_5PT:
        assert b.r_fast_ohm[0] <= th[1] <= b.r_fast_ohm[1] / 2
        assert b.r_slow_ohm[0] <= th[3] <= b.r_slow_ohm[1] / 2
    with pytest.raises(ValueError):
        Bounds((1.0, 0.5), (1, 10), (0, 1), (0, 1))
    with pytest.raises(ValueError):
        fit_ga(PAPER_T[::-1], r)


# -- casadi Jacobian ------------------------------------------------------------------
def test_casadi_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    data = fp._prepare(PAPER_T, np.array([r_model(th, PAPER_T) for th in TRUTH_5PT[:3]]))
    b = default_bounds(PAPER_T, data.r)
    prob = lm_mod._LmProblem(data, np.arange(3), b)
    ix = np.arange(3)
    z = np.column_stack([np.log([0.7, 1.1, 0.5]), np.log([6.0, 9.0, 20.0]),
                         rng.uniform(0.2, 0.8, 3), rng.uniform(0.2, 0.8, 3)])
    r, jac, c, dc = prob.eval(z, ix)
    h = 1e-6
    for k in range(4):
        zp, zm = z.copy(), z.copy()
        zp[:, k] += h
        zm[:, k] -= h
        rp, _, cp, _ = prob.eval(zp, ix)
        rm, _, cm, _ = prob.eval(zm, ix)
        np.testing.assert_allclose(jac[:, k, :], (rp - rm) / (2 * h), atol=1e-7)
        np.testing.assert_allclose(dc[:, k], (cp - cm) / (2 * h), atol=1e-7)
    # and the residual / constraint match the numpy model
    tf, ts, rf, rs = prob.to_params(z, ix)
    fit = PointFit(fp._r0(data.ra, data.t0, tf, ts, rf, rs), rf, tf, rs, ts,
                   np.zeros(3), np.ones(3, bool), np.zeros(3, int), "lm")
    model = curve_r_ohm(fit, PAPER_T)
    np.testing.assert_allclose(r[:, 1:] * data.scale[:, None], (model - data.r)[:, 1:], atol=1e-15)
    np.testing.assert_allclose(c * data.scale, fit.r0_ohm, atol=1e-15)


# --------------------------------------------------------------------------------------
# which rows the five-point fits take (five_point_rows)
# --------------------------------------------------------------------------------------
def _table(rows):
    """A DcirTable from (soc, c_rate, R(t) row) triples, discharge."""
    from ecmgen.data.dcir import DcirTable

    return DcirTable(np.array([r[0] for r in rows]), np.array(["discharge"] * len(rows)),
                     np.array([r[1] for r in rows]), PAPER_T, np.array([r[2] for r in rows]))


def test_five_point_rows_take_the_highest_complete_c_rate_per_level():
    full = TABLE1_R[0]
    cut = np.array([full[0], full[1], np.nan, np.nan, np.nan])   # reached 1 s only
    table = _table([(0.90, 1.0, full), (0.90, 6.0, 1.1 * full),
                    (0.50, 1.0, full), (0.49, 6.0, cut), (0.49, 4.0, 1.2 * full),
                    (0.10, 1.0, cut), (0.10, 2.0, cut)])
    with np_warnings_as_errors():
        rows, notes = fp.five_point_rows(table, "max")
    assert rows.soc.tolist() == pytest.approx([0.9, 0.49])
    assert rows.c_rate.tolist() == [6.0, 4.0]
    assert np.all(np.isfinite(rows.r_ohm))
    assert np.allclose(rows.r_ohm[1], 1.2 * full)
    assert any("6C at SOC 0.90, 4C at SOC 0.49" in n for n in notes)
    assert any("no complete pulse at SOC 0.100" in n and "interpolated" in n for n in notes)
    near, _ = fp.five_point_rows(table, 2.0)
    assert near.c_rate.tolist() == [1.0, 1.0]
    every, _ = fp.five_point_rows(table, "all")
    assert len(every) == 3 and np.isfinite(every.r_ohm[2, :2]).all()


def np_warnings_as_errors():
    import warnings

    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")

    class _Exit:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            ctx.__exit__(*exc)
            return False
    return _Exit()


@pytest.mark.parametrize("temp,levels,rates", [("n10degC", 11, {4.0, 2.0, 1.0, 0.5}),
                                               ("n20degC", 10, {2.0, 1.0, 0.5})])
def test_cold_pulse_tests_give_a_row_at_every_level(temp, levels, rates):
    """At -10/-20 degC the voltage limit cuts most 4C/6C pulses: the file's top rate has
    no complete row (once 'no table cell could be fitted' after numpy's 'Mean of empty
    slice'); the highest complete rate per level has one at every level."""
    from conftest import SHARED_DATA, need
    from ecmgen.data.dcir import extract_dcir, find_pulses
    from ecmgen.data.measure import read_timeseries

    path = need(SHARED_DATA / f"panasonic-18650pf-{temp}" / "hppc.mat")
    series = read_timeseries(path, capacity_ah=2.9)
    with np_warnings_as_errors():
        table = extract_dcir(series, find_pulses(series, 2.9, soc0=1.0))
        rows, notes = fp.five_point_rows(table, "max")
        fit = fit_ga(rows.t_s, rows.r_ohm, seed=0)
    assert len(rows) == levels and set(rows.c_rate) == rates
    assert np.all(np.isfinite(rows.r_ohm)) and np.all(np.isfinite(fit.r0_ohm))
    assert not any("no complete pulse" in n for n in notes)
