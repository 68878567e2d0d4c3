"""Leaving one level out for every smoothing weight at once (ecmgen.fit.curve_cv) and the
bounded solve it shares across the weights (ecmgen.fit.lsq.solve_bounded_many): the same
solutions and held-out errors as one weight at a time."""

import numpy as np

from ecmgen.fit.curve_cv import held_out_errors
from ecmgen.fit.lsq import solve_bounded, solve_bounded_many


def _systems(rng, n=12, n_free=4, weights=(0.0, 1e-3, 1.0, 30.0)):
    """Normal equations of a random least-squares problem, with a penalty on the bounded
    unknowns only (as the smoothing weights'), one system per weight."""
    z = rng.normal(size=(60, n))
    y = z @ rng.normal(size=n) + 0.3 * rng.normal(size=60)
    m, q = z.T @ z, z.T @ y
    free = np.zeros(n, bool)
    free[-n_free:] = True
    d = np.diff(np.eye(n - n_free), 2, axis=0)
    out = []
    for lam in weights:
        mk = m.copy()
        mk[:n - n_free, :n - n_free] += lam * d.T @ d
        out.append((mk, q.copy()))
    return out, free


def test_solve_bounded_many_is_solve_bounded_bit_for_bit():
    rng = np.random.default_rng(0)
    negative = 0
    for _ in range(40):
        systems, free = _systems(rng)
        many = solve_bounded_many(systems, free)
        for k, (m, q) in enumerate(systems):
            one = solve_bounded(m, q, free)
            assert np.array_equal(many[k], one)
            negative += int(np.any(one[~free] == 0.0))
    assert negative > 0           # the bounds were active in some (Lawson-Hanson ran)


def test_solve_bounded_many_with_different_free_rows_solves_each():
    rng = np.random.default_rng(1)
    systems, free = _systems(rng)
    m, q = systems[1]
    m = m.copy()
    m[-1, -1] += 1.0              # a free row that differs: no shared elimination
    systems[1] = (m, q)
    many = solve_bounded_many(systems, free)
    for k, (mk, qk) in enumerate(systems):
        assert np.array_equal(many[k], solve_bounded(mk, qk, free))


class _Prob:
    """The parts of the whole-test fit's problem that leaving a level out uses."""

    def __init__(self, rng, rows=90, n=8, n_free=3):
        self.yw = rng.normal(size=rows)
        self.free = np.zeros(n, bool)
        self.free[-n_free:] = True
        self.d = np.diff(np.eye(n - n_free), 2, axis=0)
        self.n_fixed = n - n_free

    def regularised(self, gram, g, lay, lam):
        m = gram.copy()
        m[:self.n_fixed, :self.n_fixed] += lam * self.d.T @ self.d
        m[np.diag_indices_from(m)] += 1e-12 * float(np.mean(np.diag(gram))) + 1e-300
        return m, g.copy(), 0.0

    def regularised_many(self, gram, g, lay, penalties):
        return [self.regularised(gram, g, lay, lam) for lam in penalties]


def test_held_out_errors_are_those_of_one_weight_at_a_time():
    rng = np.random.default_rng(3)
    prob = _Prob(rng)
    z = np.abs(rng.normal(size=(90, 8)))
    z[:30, -1] = 0.0              # a free column that the first level does not see
    z[30:60, -2] = z[30:60, -3]   # two free columns equal on the second level (rank 1)
    lay = {"free": prob.free}
    levels = [np.arange(0, 30), np.arange(30, 60), np.arange(60, 90)]
    weights = (1e-4, 1e-2, 1.0, 100.0)
    got = held_out_errors(prob, z, lay, weights, levels)
    gram, g = z.T @ z, z.T @ prob.yw
    for k, lam in enumerate(weights):
        e = 0.0
        for r in levels:
            zk, yk = z[r], prob.yw[r]
            m, q, _ = prob.regularised(gram - zk.T @ zk, g - zk.T @ yk, lay, lam)
            res = yk - zk @ solve_bounded(m, q, prob.free)
            f = zk[:, prob.free]
            res = res - f @ np.linalg.lstsq(f, res, rcond=None)[0]
            e += float(res @ res)
        assert abs(got[k] - e) <= 1e-10 * e
