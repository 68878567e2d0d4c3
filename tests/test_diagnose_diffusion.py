"""Solid diffusion against a further RC pair (ecmgen.diagnosis.diffusion), and a round's
candidates that beat its winner only beyond their bounds (ecmgen.diagnosis.lookalike): the
mechanics on known-truth arrays and records made by ecmgen's own simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ecmgen.diagnosis import diffusion as dd
from ecmgen.diagnosis.lookalike import beyond_bounds
from ecmgen.diagnosis.problems import _Spec


def test_the_sphere_modes_are_the_roots_of_tan_x_equals_x():
    """lambda_k in (k pi, k pi + pi / 2) with tan(lambda) = lambda; the weights 10 /
    lambda^2 (sum over all roots 2 / lambda^2 = 1 / 5) sum to one over the modes kept."""
    k = np.arange(1, dd.N_MODES + 1)
    assert np.all((dd.ROOTS > k * math.pi) & (dd.ROOTS < k * math.pi + math.pi / 2))
    assert np.allclose(np.tan(dd.ROOTS), dd.ROOTS, rtol=1e-6)
    assert dd.ROOTS[0] == pytest.approx(4.4934, abs=1e-4)       # tables of tan x = x
    assert np.sum(2.0 / dd._roots(2000) ** 2) == pytest.approx(0.2, abs=2e-4)
    assert dd.WEIGHTS.sum() == pytest.approx(1.0)


def test_the_diffusion_voltage_of_a_current_step():
    """After a step of current i the voltage rises as sqrt(t) first (the flux into a
    half-space: doubling t multiplies it by sqrt 2 while t << tau_d / lambda_1^2) and
    settles to r i."""
    t = np.arange(0.0, 40000.0, 0.5)
    v = dd.sphere_voltage(t, np.full_like(t, 2.0), 0.01, 8000.0)
    assert v[-1] == pytest.approx(0.02, rel=1e-4)
    k1, k2 = np.searchsorted(t, [20.0, 40.0])
    assert v[k2] / v[k1] == pytest.approx(math.sqrt(2.0), rel=0.08)


def test_the_pulse_test_names_the_shape_it_fits_better():
    """pair_or_diffusion on a stand-in for the pulse test's refit (a linear fit: its mean
    square is the distance to a diffusion of known parameters plus a noise of 1 mV): a
    third pair that fits better than that diffusion by PAIR_MARGIN is an extra RC; one that
    fits worse, or within the margin, is not told from diffusion. The search finds the
    diffusion to a few per cent."""
    t = np.arange(0.0, 20000.0, 2.0)
    i = np.where((t // 3000) % 2 == 0, -2.0, 0.0)

    class Series:
        time_s, current_a = t, i
    truth = dd.sphere_voltage(t, i, 0.01, 9000.0)

    def refit(v):
        return None, float(np.sqrt(np.mean((v - truth) ** 2) + 1e-6))

    for pair_rms, want in ((1.2e-3, None), (0.9e-3, "extra_rc"), (0.995e-3, None)):
        shape = dd.pair_or_diffusion(refit, Series, np.zeros_like(t), pair_rms, 0.0035,
                                     9000.0 / dd.ROOTS[0] ** 2 / 1.3)
        assert shape.name == want, shape
    assert shape.sphere_rms_v == pytest.approx(1e-3, rel=5e-3)
    assert shape.r_ohm == pytest.approx(0.01, rel=0.03)
    assert shape.tau_d_s == pytest.approx(9000.0, rel=0.05)


def test_a_candidate_beyond_its_bound_that_beats_the_winner_is_its_look_alike():
    """Rows as the search keeps them: a candidate that did not pass only because it ended
    on its bound, and beats the winner on the held-out part by the test, is returned with
    its parameter; one on its bound that does not beat the winner, and one that passed, are
    not."""
    rng = np.random.default_rng(0)
    e_win = 2e-3 * rng.standard_normal(2000)
    better = 0.3 * e_win
    spec = {"k": _Spec(-1.5e-3, 1.5e-3, False, limit_lo=True, limit_hi=True)}

    def row(name, passed, value, e):
        return (passed, float(np.mean(np.abs(e))), name, [{"k": value}], spec, None, None, e)

    win = row("capacity_error", True, 0.0, e_win)
    rows = [win, row("entropic_ocv", False, 1.5e-3, better),
            row("ocv_error", False, -1.5e-3, 1.2 * e_win), row("current_gain", True, 0.0, better),
            row("hysteresis", False, 0.0, better)]
    got = beyond_bounds(rows, win, 50, 0.99, 0)
    assert [(c[2], bound) for c, bound in got] == [("entropic_ocv", "k = 0.0015")]
