"""The whole-test fit's unit responses (ecmgen.fit.curve_record.rc_response): the restart
columns as running products of the decays are, bit for bit, the banded solve's."""

import numpy as np
from scipy.linalg import lapack

from ecmgen.fit.curve_record import Record, rc_response


def _record(n: int, restart: np.ndarray, seed: int) -> Record:
    rng = np.random.default_rng(seed)
    dt = np.concatenate([[0.0], rng.choice([0.1, 1.0, 10.0], n - 1)])
    gap = np.where(rng.uniform(size=n) < 0.05, rng.uniform(0.0, 3000.0, n), 0.0)
    gap[0] = 0.0
    t = np.cumsum(dt + gap)
    zeros = np.zeros(n)
    return Record(t, dt, gap, zeros, zeros, zeros, zeros, np.ones(n, bool), np.ones(n),
                  {"discharge": np.ones(n, bool)}, restart, 0.0)


def _solved(rec: Record, tau: float, u: np.ndarray) -> np.ndarray:
    """Every column, the restart units too, by the unit-lower-bidiagonal solve alone."""
    n = rec.t.size
    ab = np.zeros((2, n))
    ab[1, :-1] = -np.exp(-(rec.gap[1:] + rec.dt[1:]) / tau)
    b = np.zeros((n, u.shape[1] + rec.restart.size), order="F")
    np.multiply(u, -np.expm1(-rec.dt / tau)[:, None], out=b[:, :u.shape[1]])
    b[rec.restart, u.shape[1] + np.arange(rec.restart.size)] = 1.0
    return lapack.dtbtrs(ab, b, uplo="L", diag="U")[0]


def test_restart_columns_are_the_solve_bit_for_bit():
    n = 3000
    rec = _record(n, np.array([0, 17, 1500, n - 2, n - 1]), seed=3)
    rng = np.random.default_rng(4)
    # inputs with exact zeros of either sign, as a direction's masked hat columns have
    u = rng.standard_normal((n, 4)) * (rng.uniform(size=(n, 4)) < 0.3)
    u[rng.uniform(size=(n, 4)) < 0.2] *= -0.0
    for tau in (0.05, 1.0, 30.0, 900.0, 1e5):
        got, want = rc_response(rec, tau, u), _solved(rec, tau, u)
        assert got.shape == want.shape
        assert np.array_equal(got.view(np.int64), want.view(np.int64))
