"""The joint smoothing refit of the five-point fits (ecmgen.fit.smooth): known truth."""

import numpy as np

from ecmgen.fit.lm import fit_lm
from ecmgen.fit.points import _prepare, default_bounds
from ecmgen.fit.smooth import _Direction, smooth_point_fit

T_S = np.array([0.1, 1.0, 3.0, 6.0, 10.0])


def _truth(soc):
    r0 = 0.020 + 0.010 * (1 - soc) ** 2
    rf = 0.004 + 0.004 * (1 - soc)
    rs = 0.006 + 0.002 * soc
    return r0, rf, 1.5 + 0 * soc, rs, 25.0 + 0 * soc


def _rows(noise_ohm: float, seed: int = 0):
    soc = np.linspace(0.1, 0.95, 10)
    r0, rf, tf, rs, ts = _truth(soc)
    t = T_S[None, :]
    r = r0[:, None] + rf[:, None] * (1 - np.exp(-t / tf[:, None])) + \
        rs[:, None] * (1 - np.exp(-t / ts[:, None]))
    r = r + np.random.default_rng(seed).normal(0.0, noise_ohm, r.shape)
    return soc, np.array(["discharge"] * soc.size), r


def _roughness(p):
    lp = np.log(p)
    return float(np.max(np.abs(lp[1:-1] - 0.5 * (lp[:-2] + lp[2:]))))


def test_jacobian_matches_finite_differences():
    soc, _, r = _rows(2e-5)
    r[3, 0] = 0.001          # a row whose R0 barrier is active
    data = _prepare(T_S, r)
    prob = _Direction(data, np.arange(soc.size), soc, default_bounds(T_S, r))
    x = np.log(np.tile([1.0, 15.0, 0.003, 0.005], soc.size))
    x += np.random.default_rng(1).normal(0.0, 0.1, x.size)
    w = np.ones(soc.size)
    w[4] = 0.0
    for tied in (False, True):
        prob.tied = tied
        jac = prob.jacobian(x, 0.3, w)
        eps = 1e-7
        num = np.column_stack([(prob.residual(x + eps * e, 0.3, w)
                                - prob.residual(x - eps * e, 0.3, w)) / (2 * eps)
                               for e in np.eye(x.size)])
        assert np.max(np.abs(jac - num)) < 1e-6 * max(1.0, np.max(np.abs(jac)))


def test_smoothing_recovers_smooth_tables_from_noisy_levels():
    soc, direction, r = _rows(4e-5)
    raw = fit_lm(T_S, r)
    fit, notes = smooth_point_fit(T_S, r, soc, direction, raw)
    assert notes and "leave one level out" in notes[0]
    r0, rf, tf, rs, ts = _truth(soc)
    for p in (fit.r0_ohm, fit.r_fast_ohm, fit.r_slow_ohm, fit.tau_fast_s, fit.tau_slow_s):
        assert np.all(p > 0)
        assert _roughness(p) < 0.35
    # the exactly determined per-level fit is rougher than the joint one
    assert max(_roughness(raw.r_fast_ohm), _roughness(raw.tau_slow_s)) > \
        max(_roughness(fit.r_fast_ohm), _roughness(fit.tau_slow_s))
    assert np.allclose(fit.r0_ohm, r0, rtol=0.05)
    assert np.all(fit.tau_fast_s < fit.tau_slow_s)
    total = fit.r_fast_ohm + fit.r_slow_ohm * (1 - np.exp(-10.0 / fit.tau_slow_s))
    want = rf + rs * (1 - np.exp(-10.0 / ts))
    assert np.allclose(total, want, rtol=0.1)


def test_time_constants_no_level_can_place_follow_soc_on_a_line():
    """A 1 s logger: R(1 s) is R0's own sample, so each level has three points after R(t_0)
    for four parameters. The time constants then lie on a straight line (in ln) over SOC,
    the resistances still follow the levels, and the curve R(t) is kept."""
    soc, direction, r = _rows(4e-5, seed=5)
    r[:, 1] = np.nan
    raw = fit_lm(T_S, r)
    fit, notes = smooth_point_fit(T_S, r, soc, direction, raw)
    assert "time constants on a straight line over SOC (3 DC-IR points" in notes[0], notes
    for tau in (fit.tau_fast_s, fit.tau_slow_s):
        assert np.max(np.abs(np.diff(np.log(tau), 2))) < 0.02, tau
    r0, rf, tf, rs, ts = _truth(soc)
    # without R(1 s) the split of R(0.1 s) between r0 and the fast branch is the fit's
    assert np.allclose(fit.r0_ohm, r0, rtol=0.06)
    for t in (3.0, 6.0, 10.0):            # the measured R(t) kept
        got = fit.r0_ohm + fit.r_fast_ohm * (1 - np.exp(-t / fit.tau_fast_s)) + \
            fit.r_slow_ohm * (1 - np.exp(-t / fit.tau_slow_s))
        want = r0 + rf * (1 - np.exp(-t / tf)) + rs * (1 - np.exp(-t / ts))
        assert np.allclose(got, want, rtol=0.01), (t, got / want)
    # five points per level: each level keeps its own time constants (no line)
    soc5, direction5, r5 = _rows(4e-5, seed=5)
    _, notes5 = smooth_point_fit(T_S, r5, soc5, direction5, fit_lm(T_S, r5))
    assert "straight line" not in notes5[0], notes5


def test_smoothing_is_deterministic():
    soc, direction, r = _rows(4e-5, seed=3)
    raw = fit_lm(T_S, r)
    a, _ = smooth_point_fit(T_S, r, soc, direction, raw)
    b, _ = smooth_point_fit(T_S, r, soc, direction, raw)
    assert np.array_equal(a.r_slow_ohm, b.r_slow_ohm)


def test_two_nearly_equal_time_constants_keep_their_names_over_soc():
    """One RC in truth (tau 4.5 s): the refit's two branches cross along SOC, and named
    level by level the resistance went from one table to the other and back (a synthetic
    cell's r_fast alternated 0.007 <-> 28 mOhm). Named by the majority, each table keeps
    its branch; where the two cross they become one time constant."""
    from ecmgen.fit.smooth import _named

    tf = np.array([4.50, 4.52, 4.49, 4.40, 4.36, 4.30])
    ts = np.array([4.60, 4.47, 4.55, 4.45, 4.33, 4.40])
    rf = np.full(6, 0.028)
    rs = np.full(6, 0.0001)
    nf, ns, nrf, nrs = _named(tf, ts, rf, rs)
    assert np.array_equal(nrf, rf) and np.array_equal(nrs, rs)
    assert np.all(nf < ns)
    cross = tf >= ts
    assert np.allclose(nf[cross], np.sqrt(tf * ts)[cross])
    assert np.array_equal(nf[~cross], tf[~cross])
    # the majority the other way round: every level swapped
    sf, ss, srf, srs = _named(ts, tf, rs, rf)
    assert np.array_equal(srf, rf) and np.all(sf < ss)


def test_batched_normal_equations_are_those_of_the_single_jacobians():
    """The weight's choice solves every left-out fit at once: each row of the batch has the
    residual of that fit alone (bit for bit), and the gradient and Gauss-Newton matrix of
    its Jacobian (to rounding)."""
    soc, _, r = _rows(2e-5)
    r[3, 0] = 0.001          # a row whose R0 barrier is active
    data = _prepare(T_S, r)
    prob = _Direction(data, np.arange(soc.size), soc, default_bounds(T_S, r))
    rng = np.random.default_rng(2)
    xs = rng.uniform(prob.lo, prob.hi, size=(3, prob.lo.size))
    lams = np.array([1e-4, 0.3, 100.0])
    weights = np.ones((3, soc.size))
    weights[[0, 1, 2], [2, 5, 8]] = 0.0
    for tied in (False, True):
        prob.tied = tied
        res = prob.residuals(xs, lams, weights)
        g, h = prob.normal_equations(xs, lams, weights)
        for k in range(3):
            one = prob.residual(xs[k], lams[k], weights[k])
            jac = prob.jacobian(xs[k], lams[k], weights[k])
            assert np.array_equal(res[k], one)
            assert np.allclose(g[k], jac.T @ one, rtol=1e-12, atol=1e-12 * np.abs(g[k]).max())
            assert np.allclose(h[k], jac.T @ jac, rtol=1e-12, atol=1e-12 * np.abs(h[k]).max())


def test_the_cheap_solver_reaches_the_full_solvers_minimum():
    """Leaving a level out, the projected Levenberg-Marquardt steps of the weight's choice
    end where the full solver does: the same left-out error within 1e-4, a hundredth of
    the 1 % within which the choice takes two weights as equally good (CV_TIE)."""
    from ecmgen.fit.smooth import LOO_STEPS, _descend

    soc, _, r = _rows(4e-5, seed=2)
    data = _prepare(T_S, r)
    prob = _Direction(data, np.arange(soc.size), soc, default_bounds(T_S, r))
    x0 = np.log(np.tile([1.5, 25.0, 0.005, 0.007], soc.size))
    for lam in (1e-3, 1.0):
        full = prob.solve(x0, lam, np.ones(soc.size))
        w = np.ones(soc.size)
        w[4] = 0.0
        exact = prob.held_out(prob.solve(full, lam, w), 4)
        cheap = _descend(prob, full[None, :], np.array([lam]), w[None, :], LOO_STEPS)[0]
        assert abs(prob.held_out(cheap, 4) - exact) <= 1e-4 * exact
