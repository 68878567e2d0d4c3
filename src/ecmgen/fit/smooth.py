"""Smooth tables from the five-point fits (GA, LM): one joint refit over the SOC levels.

Each level's five-point fit (:mod:`ecmgen.fit.points`) has four free parameters for four
points after the pinned R(t_0): it is exactly determined, so measurement noise goes straight
into the parameters and neighbouring levels can differ by a factor of several (a table that
zig-zags, a branch at 0 ohm). Here the levels of one direction are refitted together, in
least squares, with the parameters as logarithms (so every value stays > 0)::

    min  sum_levels sum_points ((R_fit - R_meas) / scale_level)^2
         + lam * sum_params |D2 ln p|^2 + (R0 < 0 barrier)

where D2 is the second difference over the levels' SOC (:func:`ecmgen.fit.curve_levels.
second_difference`). lam is chosen by leaving one level out: each interior level in turn is
dropped from the data, its parameters then follow from the smoothness alone, and its
measured R(t) is compared with the curve they give; the largest lam within CV_TIE of the
smallest held-out error is kept. Where a level has fewer DC-IR points after R(t_0) than
its four parameters (a 1 s logger), the time constants are not the level's to place: their
second difference is held near 0 (TIED), a straight line in ln tau over SOC. The refit
starts from the method's own per-level result; where the joint problem has one optimum
(the demo, the Leaf) GA and LM end at the same tables. R0 stays R(t_0) minus what the two
branches add by t_0, as in the paper.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .curve_levels import CV_TIE, second_difference
from .points import _LOG_GAP, Bounds, PointFit, _phi, _prepare, _r0, _result, default_bounds

# candidate smoothing weights (relative squared units: a residual of 1 is one data scale)
SMOOTHING = tuple(10.0 ** np.arange(-4.0, 2.01, 1.0))
_BARRIER = 1e3            # weight of R0 < 0 against a data scale
# smoothing weight of time constants that no level determines on its own: a second
# difference of 0.01 in ln tau costs as much as one data scale (a straight line over SOC)
TIED = 1e4


class _Direction:
    """The joint problem of one direction's levels (sorted by SOC)."""

    def __init__(self, data, ix: np.ndarray, soc: np.ndarray, b: Bounds):
        self.n = ix.size
        self.t0 = data.t0[ix]
        self.ra = data.ra[ix]
        self.tm = data.tm[ix]
        self.d = data.d[ix]
        self.mask = data.mask[ix].astype(float)
        self.scale = data.scale[ix]
        self.d2 = second_difference(soc)
        # points after R(t_0) per level: with fewer than the four parameters (a 1 s logger
        # gives R(t) at 3, 6 and 10 s only) a level cannot place its time constants, which
        # then follow SOC on a straight line (in ln) instead of the points' noise
        self.points = int(np.median(self.mask.sum(axis=1)))
        self.tied = self.points < 4
        lo = np.array([b.tau_fast_s[0], b.tau_slow_s[0],
                       max(b.r_fast_ohm[1], 1e-30) * 1e-6, max(b.r_slow_ohm[1], 1e-30) * 1e-6])
        hi = np.array([b.tau_fast_s[1], b.tau_slow_s[1], b.r_fast_ohm[1], b.r_slow_ohm[1]])
        self.lo = np.tile(np.log(lo), self.n)
        self.hi = np.tile(np.log(hi), self.n)

    def parts(self, x):
        p = np.exp(x.reshape(self.n, 4))
        return p[:, 0], p[:, 1], p[:, 2], p[:, 3]

    def curves(self, x):
        tf, ts, rf, rs = self.parts(x)
        col = lambda a: a[:, None]  # noqa: E731
        t0 = col(self.t0)
        return col(rf) * _phi(self.tm, t0, col(tf)) + col(rs) * _phi(self.tm, t0, col(ts))

    def residual(self, x, lam: float, weight: np.ndarray):
        fit = self.curves(x)
        data = ((fit - self.d) / self.scale[:, None] * self.mask * weight[:, None]).ravel()
        tf, ts, rf, rs = self.parts(x)
        r0 = _r0(self.ra, self.t0, tf, ts, rf, rs)
        barrier = _BARRIER * np.minimum(r0, 0.0) / self.scale
        smooth = (np.sqrt(self.weights(lam)) * (self.d2 @ x.reshape(self.n, 4))).ravel()
        return np.concatenate([data, barrier, smooth])

    def jacobian(self, x, lam: float, weight: np.ndarray):
        """d residual / d x (x = ln of tau_fast, tau_slow, r_fast, r_slow per level)."""
        n, n_t = self.n, self.d.shape[1]
        tf, ts, rf, rs = self.parts(x)
        col = lambda a: a[:, None]  # noqa: E731
        t0, tm = col(self.t0), self.tm
        w = self.mask * weight[:, None] / col(self.scale)
        jac = np.zeros((n * n_t + n + 4 * self.d2.shape[0], 4 * n))
        for q, (tau, r) in enumerate(((tf, rf), (ts, rs))):
            e0, e = np.exp(-t0 / col(tau)), np.exp(-tm / col(tau))
            phi = e0 - e
            dphi = (t0 / col(tau)) * e0 - (tm / col(tau)) * e      # tau d phi / d tau
            for k in range(n):
                jac[k * n_t:(k + 1) * n_t, 4 * k + q] = r[k] * dphi[k] * w[k]
                jac[k * n_t:(k + 1) * n_t, 4 * k + 2 + q] = r[k] * phi[k] * w[k]
        r0 = _r0(self.ra, self.t0, tf, ts, rf, rs)
        active = (r0 < 0) * _BARRIER / self.scale
        for k in range(n):
            row = n * n_t + k
            for q, (tau, r) in enumerate(((tf, rf), (ts, rs))):
                jac[row, 4 * k + q] = active[k] * r[k] * np.exp(-self.t0[k] / tau[k]) * \
                    self.t0[k] / tau[k]
                jac[row, 4 * k + 2 + q] = active[k] * r[k] * np.expm1(-self.t0[k] / tau[k])
        base = n * n_t + n
        root = np.sqrt(self.weights(lam))
        for j in range(self.d2.shape[0]):
            for q in range(4):
                jac[base + 4 * j + q, q::4] = root[q] * self.d2[j]
        return jac

    def weights(self, lam: float) -> np.ndarray:
        """The smoothing weight of each parameter (tau_fast, tau_slow, r_fast, r_slow)."""
        return np.array([TIED if self.tied else lam] * 2 + [lam] * 2)

    def solve(self, x0, lam: float, weight: np.ndarray):
        x0 = np.clip(x0, self.lo + 1e-9, self.hi - 1e-9)
        sol = least_squares(self.residual, x0, jac=self.jacobian, bounds=(self.lo, self.hi),
                            args=(lam, weight), method="trf", tr_solver="exact",
                            xtol=1e-10, ftol=1e-10, max_nfev=200)
        return sol.x

    def held_out(self, x, k: int) -> float:
        e = (self.curves(x)[k] - self.d[k]) / self.scale[k] * self.mask[k]
        return float(e @ e)


def _start(fit: PointFit, ix: np.ndarray, b: Bounds) -> np.ndarray:
    """The per-level fit as the start, a branch at 0 ohm lifted to a small share."""
    tf = np.nan_to_num(fit.tau_fast_s[ix], nan=np.sqrt(b.tau_fast_s[0] * b.tau_fast_s[1]))
    ts = np.nan_to_num(fit.tau_slow_s[ix], nan=np.sqrt(b.tau_slow_s[0] * b.tau_slow_s[1]))
    floor = 1e-3 * max(b.r_fast_ohm[1], b.r_slow_ohm[1])
    rf = np.maximum(np.nan_to_num(fit.r_fast_ohm[ix], nan=floor), floor)
    rs = np.maximum(np.nan_to_num(fit.r_slow_ohm[ix], nan=floor), floor)
    return np.log(np.column_stack([tf, ts, rf, rs])).ravel()


def _named(tf, ts, rf, rs):
    """The two branches are interchangeable in the curve: the one faster at most levels is
    named fast at every level (named level by level, two nearly equal time constants that
    cross would hand the resistance from one table to the other and back). Where the two
    still cross, they act as one branch: both take their geometric mean there (kept
    apart by the fit's smallest ratio)."""
    if np.median(np.log(tf) - np.log(ts)) > 0:
        tf, ts, rf, rs = ts, tf, rs, rf
    cross = tf >= ts
    mean = np.sqrt(tf * ts)
    gap = np.exp(0.5 * _LOG_GAP)
    return np.where(cross, mean / gap, tf), np.where(cross, mean * gap, ts), rf, rs


def _choose(prob: _Direction, x_full: dict) -> float:
    """The smoothing weight by leaving one interior level out."""
    if prob.n < 4:
        return SMOOTHING[-1]
    errors = {}
    for lam in SMOOTHING:
        e = 0.0
        for k in range(1, prob.n - 1):
            w = np.ones(prob.n)
            w[k] = 0.0
            e += prob.held_out(prob.solve(x_full[lam], lam, w), k)
        errors[lam] = e
    best = min(errors.values())
    return max(k for k, v in errors.items() if v <= (1.0 + CV_TIE) * best)


def smooth_point_fit(t_s, r_ohm, soc, direction, fit: PointFit,
                     bounds: Bounds | None = None) -> tuple[PointFit, list[str]]:
    """The five-point fit ``fit`` of the rows (t_s, r_ohm, soc, direction) refitted jointly
    per direction with a smoothness penalty chosen by leaving one level out (module
    docstring). Returns the refitted PointFit (same rows, same order) and notes."""
    data = _prepare(t_s, r_ohm)
    b = bounds if bounds is not None else default_bounds(t_s, r_ohm)
    soc = np.asarray(soc, dtype=float)
    direction = np.asarray(direction)
    out = {k: np.array(getattr(fit, k), dtype=float)
           for k in ("tau_fast_s", "tau_slow_s", "r_fast_ohm", "r_slow_ohm")}
    notes = []
    for d in ("charge", "discharge"):
        ix = np.flatnonzero((direction == d) & data.ok)
        if ix.size < 3:
            continue
        ix = ix[np.argsort(soc[ix])]
        prob = _Direction(data, ix, soc[ix], b)
        x0 = _start(fit, ix, b)
        ones = np.ones(prob.n)
        x_full = {lam: prob.solve(x0, lam, ones) for lam in SMOOTHING}
        lam = _choose(prob, x_full)
        tf, ts, rf, rs = prob.parts(x_full[lam])
        tf, ts, rf, rs = _named(tf, ts, rf, rs)
        for key, v in zip(("tau_fast_s", "tau_slow_s", "r_fast_ohm", "r_slow_ohm"),
                          (tf, ts, rf, rs)):
            out[key][ix] = v
        notes.append(f"{fit.method}: {d} tables refitted over the {prob.n} SOC levels together, "
                     f"smoothing weight {lam:g} (leave one level out)"
                     + (f"; time constants on a straight line over SOC ({prob.points} DC-IR "
                        "points after R(t_0) per level for four parameters)" if prob.tied
                        else ""))
    result = _result(data, out["tau_fast_s"], out["tau_slow_s"], out["r_fast_ohm"],
                     out["r_slow_ohm"], np.asarray(fit.converged), fit.iterations, fit.method)
    return result, notes
