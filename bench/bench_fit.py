"""Benchmark: fit a whole DC-IR table with ecmgen's GA and LM, and with scipy.

Table: 9 SOCs x 2 directions = 18 cells of the paper's five-point DC-IR curves
(t = 0.1, 1, 3, 6, 10 s), synthesised from a known 2RC truth for a 42 Ah LFP cell
like the paper's (mOhm-scale resistances, 2C = 84 A pulses) with 1 mV Gaussian
noise on every voltage sample.

Rows of the printed table:
  ecmgen GA          fit_ga, all cells vectorised
  ecmgen LM          fit_lm (casadi Jacobian, multi-start), all cells at once
  ecmgen GA + LM     fit_lm started from the GA result
  scipy DE           differential_evolution per cell (default settings), same
                     bounds, same objective (Eq. 5 + the same R0/ordering penalties)
  scipy DE tight     the same with tol=1e-8 (population evaluated vectorised,
                     updating="deferred", to keep the bench short): the best DE can do
  scipy LSQ trf      least_squares(method="trf") per cell, same bounds (R0 >= 0 cannot
                     be expressed there), from one generic start

Eq. 5 is summed over cells; "time" is wall-clock for the whole table (the casadi
Function construction is warmed up before timing, as it is cached per process).

Run:  python bench/bench_fit.py
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import differential_evolution, least_squares

from ecmgen.fit import PointFit, curve_r_ohm, default_bounds, fit_ga, fit_lm

T_S = np.array([0.1, 1.0, 3.0, 6.0, 10.0])
PENALTY = 1e3          # the GA's penalty per ohm of constraint violation


def make_table(seed: int = 7):
    """18 cells: truth per SOC and direction, R from noisy voltages."""
    rng = np.random.default_rng(seed)
    soc = np.linspace(0.1, 0.9, 9)
    rows, truth = [], []
    current_a = 84.0                                   # 2C of a 42 Ah cell
    for direction, k in (("discharge", 1.0), ("charge", 0.9)):
        for s in soc:
            r0 = k * 0.45e-3 * (1 + 0.8 * (1 - s) ** 2)
            rf = k * 0.9e-3 * (1 + 0.3 * (1 - s))
            tf = 1.0 + 0.5 * s
            rs = k * 1.1e-3 * (1 + 0.6 * (1 - s) ** 2)
            ts = 8.0 + 6.0 * s
            r = r0 + rf * (1 - np.exp(-T_S / tf)) + rs * (1 - np.exp(-T_S / ts))
            v_rest = 1e-3 * rng.standard_normal(20).mean()
            v = current_a * r + 1e-3 * rng.standard_normal(T_S.size)
            rows.append((v - v_rest) / current_a)
            truth.append((r0, rf, tf, rs, ts))
    return np.array(rows), np.array(truth)


def eq5_objective(r_row: np.ndarray):
    """Eq. 5 (+ penalties) of one cell for x = (log tau_fast, log tau_slow, R_fast, R_slow)."""
    t0, d = T_S[0], r_row[1:] - r_row[0]
    t = T_S[1:]

    def f(x):
        """x (4,) or (4, S) (scipy's vectorized mode) -> float or (S,)."""
        x = np.asarray(x)
        xs = x.reshape(4, -1)[..., None]                        # (4, S, 1)
        tf, ts = np.exp(xs[0]), np.exp(xs[1])
        fit = (xs[2] * (np.exp(-t0 / tf) - np.exp(-t / tf))
               + xs[3] * (np.exp(-t0 / ts) - np.exp(-t / ts)))
        r0 = r_row[0] - xs[2] * (1 - np.exp(-t0 / tf)) - xs[3] * (1 - np.exp(-t0 / ts))
        pen = np.maximum(-r0[:, 0], 0.0) + np.maximum(xs[0, :, 0] - xs[1, :, 0], 0.0)
        out = np.sum(np.abs(d - fit), axis=1) + PENALTY * pen
        return float(out[0]) if x.ndim == 1 else out

    def res(x):
        tf, ts = np.exp(x[0]), np.exp(x[1])
        return (x[2] * (np.exp(-t0 / tf) - np.exp(-t / tf))
                + x[3] * (np.exp(-t0 / ts) - np.exp(-t / ts)) - d)

    return f, res


def to_fit(xs: np.ndarray, table: np.ndarray, method: str) -> PointFit:
    """PointFit of per-cell solutions x = (log tau_fast, log tau_slow, R_fast, R_slow)."""
    lf, ls, rf, rs = xs.T
    swap = lf > ls                                 # report tau_fast < tau_slow
    lf, ls, rf, rs = (np.where(swap, ls, lf), np.where(swap, lf, ls),
                      np.where(swap, rs, rf), np.where(swap, rf, rs))
    tf, ts = np.exp(lf), np.exp(ls)
    t0 = T_S[0]
    r0 = table[:, 0] - rf * (1 - np.exp(-t0 / tf)) - rs * (1 - np.exp(-t0 / ts))
    tmp = PointFit(r0, rf, tf, rs, ts, np.zeros(len(xs)), np.ones(len(xs), bool),
                   np.zeros(len(xs), int), method)
    fitness = np.sum(np.abs(curve_r_ohm(tmp, T_S) - table)[:, 1:], axis=1)
    return PointFit(r0, rf, tf, rs, ts, fitness, tmp.converged, tmp.iterations, method)


def scipy_de(table, bounds, tol, vectorized=False):
    b = [tuple(np.log(bounds.tau_fast_s)), tuple(np.log(bounds.tau_slow_s)),
         bounds.r_fast_ohm, bounds.r_slow_ohm]
    extra = dict(vectorized=True, updating="deferred") if vectorized else {}
    xs = []
    for k, row in enumerate(table):
        f, _ = eq5_objective(row)
        xs.append(differential_evolution(f, b, seed=k, tol=tol, **extra).x)
    return to_fit(np.array(xs), table, "de")


def scipy_lsq(table, bounds):
    lo = [np.log(bounds.tau_fast_s[0]), np.log(bounds.tau_slow_s[0]),
          bounds.r_fast_ohm[0], bounds.r_slow_ohm[0]]
    hi = [np.log(bounds.tau_fast_s[1]), np.log(bounds.tau_slow_s[1]),
          bounds.r_fast_ohm[1], bounds.r_slow_ohm[1]]
    xs = []
    for row in table:
        _, res = eq5_objective(row)
        rise = max(float(np.max(row - row[0])), 1e-6)
        x0 = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), rise / 2, rise / 2]
        xs.append(least_squares(res, x0, bounds=(lo, hi), method="trf",
                                x_scale=[1.0, 1.0, rise, rise]).x)
    return to_fit(np.array(xs), table, "lsq")


def timed(fn, repeat=1):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main():
    table, truth = make_table()
    bounds = default_bounds(T_S, table)
    fit_lm(T_S, table[:2])                          # build and cache the casadi Functions

    rows = []
    t_ga, ga = timed(lambda: fit_ga(T_S, table, seed=0), repeat=3)
    rows.append(("ecmgen GA", t_ga, ga))
    t_lm, lm = timed(lambda: fit_lm(T_S, table), repeat=3)
    rows.append(("ecmgen LM", t_lm, lm))
    t_gl, gl = timed(lambda: fit_lm(T_S, table, x0=ga), repeat=3)
    rows.append(("ecmgen GA + LM", t_ga + t_gl, gl))
    t_de, de = timed(lambda: scipy_de(table, bounds, tol=0.01))
    rows.append(("scipy DE", t_de, de))
    t_det, det = timed(lambda: scipy_de(table, bounds, tol=1e-8, vectorized=True))
    rows.append(("scipy DE tight", t_det, det))
    t_ls, ls = timed(lambda: scipy_lsq(table, bounds))
    rows.append(("scipy LSQ trf", t_ls, ls))

    print(f"table: {table.shape[0]} cells x {T_S.size} points (t = {T_S.tolist()} s)")
    print(f"bounds: {bounds}")
    print()
    print(f"{'method':<16} {'time [s]':>9} {'Eq.5 sum [uOhm]':>16} {'max |dev| [uOhm]':>17} "
          f"{'worst tau err':>13}")
    for name, t, f in rows:
        dev = np.max(np.abs(curve_r_ohm(f, T_S) - table)) * 1e6
        tau_err = np.max(np.abs(np.stack([f.tau_fast_s / truth[:, 2],
                                          f.tau_slow_s / truth[:, 4]]) - 1))
        print(f"{name:<16} {t:>9.3f} {np.sum(f.fitness_ohm) * 1e6:>16.3f} {dev:>17.2f} "
              f"{tau_err * 100:>12.0f}%")
    print()
    f_ga, f_de, f_det = (np.sum(f.fitness_ohm) for f in (ga, de, det))
    print(f"GA Eq.5 / DE Eq.5         = {f_ga / f_de:.6f}   (<= 1: GA at least as good)")
    print(f"GA Eq.5 / DE-tight Eq.5   = {f_ga / f_det:.6f}")
    print(f"DE time / GA time         = {t_de / t_ga:.1f}x")
    print(f"DE-tight time / GA time   = {t_det / t_ga:.1f}x")
    print("(the tau errors against the truth show the five-point identifiability limit at "
          "1 mV, not a fitter defect: see tests/test_fit_points.py)")


if __name__ == "__main__":
    main()
