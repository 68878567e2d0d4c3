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
smallest held-out error is kept. The fits that choose lam (every lam's fit of all levels,
and each fit leaving a level out) are projected Levenberg-Marquardt steps of all of them at
once (:func:`_descend`); the exact trust-region solver fits the chosen lam alone. Where a level has fewer DC-IR points after R(t_0) than
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
# steps of the cheap solver (:func:`_descend`) of each fit leaving a level out, from the
# joint fit: the choice of the weight as with the full solver (:meth:`_Direction.solve`) on
# the demo's and the Leaf's tests and the synthetic cells, at a tenth of the time
LOO_STEPS = 100
# its steps for each weight's fit of all levels (the starts of those leaving one out): with
# GA and LM the tables of every Panasonic configuration of bench/accuracy_matrix.py and of
# the demo are the ones the exact solver's starts gave, and the demo's fit takes 60 % of
# the CPU time; the Leaf's charge tables take the weight 10 for 100 (the two within CV_TIE;
# its cycles' MAE within 0.02 mV)
FULL_STEPS = 200


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
        n, n_t, m = self.n, self.d.shape[1], self.d2.shape[0]
        tf, ts, rf, rs = self.parts(x)
        t0, tm = self.t0[:, None], self.tm
        w = self.mask * weight[:, None] / self.scale[:, None]
        jac = np.zeros((n * n_t + n + 4 * m, 4 * n))
        data = jac[:n * n_t].reshape(n, n_t, n, 4)       # level k's rows, level k's columns
        barrier = jac[n * n_t:n * n_t + n].reshape(n, n, 4)
        k = np.arange(n)
        r0 = _r0(self.ra, self.t0, tf, ts, rf, rs)
        active = (r0 < 0) * _BARRIER / self.scale
        for q, (tau, r) in enumerate(((tf, rf), (ts, rs))):
            e0, e = np.exp(-t0 / tau[:, None]), np.exp(-tm / tau[:, None])
            phi = e0 - e
            dphi = (t0 / tau[:, None]) * e0 - (tm / tau[:, None]) * e      # tau d phi / d tau
            data[k, :, k, q] = r[:, None] * dphi * w
            data[k, :, k, 2 + q] = r[:, None] * phi * w
            barrier[k, k, q] = active * r * np.exp(-self.t0 / tau) * self.t0 / tau
            barrier[k, k, 2 + q] = active * r * np.expm1(-self.t0 / tau)
        root = np.sqrt(self.weights(lam))
        smooth = jac[n * n_t + n:].reshape(m, 4, n, 4)
        for q in range(4):
            smooth[:, q, :, q] = root[q] * self.d2
        return jac

    def residuals(self, xs, lam, weights, smooth_of=None):
        """:meth:`residual` of several x at once: xs (F, 4n), lam a weight or one per x
        (F,), weights (F, n) -> (F, rows). ``smooth_of``: lam's :class:`_SmoothTerms`."""
        f, n = xs.shape[0], self.n
        p = np.exp(xs.reshape(f, n, 4))
        tf, ts, rf, rs = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
        t0 = self.t0[:, None]
        fit = rf[..., None] * _phi(self.tm, t0, tf[..., None]) + \
            rs[..., None] * _phi(self.tm, t0, ts[..., None])
        data = ((fit - self.d) / self.scale[:, None] * self.mask * weights[..., None])
        r0 = _r0(self.ra, self.t0, tf, ts, rf, rs)
        barrier = _BARRIER * np.minimum(r0, 0.0) / self.scale
        root = (smooth_of.root(lam) if smooth_of is not None
                else np.sqrt(self._weights_each(lam, f))[:, None, :])
        smooth = root * (self.d2 @ xs.reshape(f, n, 4))
        return np.concatenate([data.reshape(f, -1), barrier, smooth.reshape(f, -1)], axis=1)

    def normal_equations(self, xs, lam, weights, smooth_of=None):
        """The gradient J'r and the Gauss-Newton matrix J'J of :meth:`residuals` at several
        x at once ((F, 4n), (F, 4n, 4n)). A level's data and R0 rows depend on its own four
        parameters only, and the smoothness rows are linear in x: J'J is a 4 x 4 block per
        level plus the constant D2'D2 of each parameter's weight, built as such
        (``smooth_of``: lam's :class:`_SmoothTerms`, that constant made once)."""
        f, n, n_t = xs.shape[0], self.n, self.d.shape[1]
        p = np.exp(xs.reshape(f, n, 4))
        tf, ts, rf, rs = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
        t0, tm = self.t0[:, None], self.tm
        w = self.mask * weights[..., None] / self.scale[:, None]          # (F, n, n_t)
        local = np.zeros((f, n, n_t + 1, 4))          # each level's data rows, its R0 row
        r0 = _r0(self.ra, self.t0, tf, ts, rf, rs)
        active = (r0 < 0) * _BARRIER / self.scale
        fit = np.zeros((f, n, n_t))
        for q, (tau, r) in enumerate(((tf, rf), (ts, rs))):
            e0, e = np.exp(-t0 / tau[..., None]), np.exp(-tm / tau[..., None])
            phi = -e0 * np.expm1(-(tm - t0) / tau[..., None])
            fit += r[..., None] * phi
            local[:, :, :n_t, q] = r[..., None] * ((t0 / tau[..., None]) * e0 -
                                                   (tm / tau[..., None]) * e) * w
            local[:, :, :n_t, 2 + q] = r[..., None] * (e0 - e) * w
            local[:, :, n_t, q] = active * r * np.exp(-self.t0 / tau) * self.t0 / tau
            local[:, :, n_t, 2 + q] = active * r * np.expm1(-self.t0 / tau)
        res = np.concatenate([(fit - self.d) * w, (_BARRIER * np.minimum(r0, 0.0)
                                                    / self.scale)[..., None]], axis=2)
        # the smoothness rows: residual sqrt(w) D2 x, so J'r = S x and J'J = S
        h = smooth_of.hessian(lam) if smooth_of is not None else self.smooth_hessian(lam, f)
        g = np.einsum("fij,fj->fi", h.reshape(f, 4 * n, 4 * n), xs) + \
            np.einsum("fkti,fkt->fki", local, res).reshape(f, 4 * n)
        k = np.arange(n)
        h[:, k, :, k, :] += np.moveaxis(np.einsum("fkti,fktj->fkij", local, local), 1, 0)
        return g, h.reshape(f, 4 * n, 4 * n)

    def smooth_hessian(self, lam, f: int) -> np.ndarray:
        """The smoothness rows' part of J'J, (F, n, 4, n, 4) for ``f`` problems."""
        return np.einsum("ab,fq,qr->faqbr", self.d2.T @ self.d2, self._weights_each(lam, f),
                         np.eye(4))

    def weights(self, lam: float) -> np.ndarray:
        """The smoothing weight of each parameter (tau_fast, tau_slow, r_fast, r_slow)."""
        return np.array([TIED if self.tied else lam] * 2 + [lam] * 2)

    def _weights_each(self, lam, f: int) -> np.ndarray:
        """:meth:`weights` for each of ``f`` problems (lam a weight or one per problem)."""
        lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), (f,))
        taus = np.full(f, TIED) if self.tied else lam
        return np.column_stack([taus, taus, lam, lam])

    def solve(self, x0, lam: float, weight: np.ndarray):
        x0 = np.clip(x0, self.lo + 1e-9, self.hi - 1e-9)
        sol = least_squares(self.residual, x0, jac=self.jacobian, bounds=(self.lo, self.hi),
                            args=(lam, weight), method="trf", tr_solver="exact",
                            xtol=1e-10, ftol=1e-10, max_nfev=200)
        return sol.x

    def held_out(self, x, k: int) -> float:
        e = (self.curves(x)[k] - self.d[k]) / self.scale[k] * self.mask[k]
        return float(e @ e)


class _SmoothTerms:
    """The terms of the smoothness rows that depend on the weight alone (part of J'J, the
    residual's root weights), made once per distinct weight of a batch of problems and
    handed out for any of them: the values each problem's own would have."""

    def __init__(self, prob: _Direction, lam: np.ndarray):
        self._lam = np.unique(lam)
        self._hessian = prob.smooth_hessian(self._lam, self._lam.size)
        self._root = np.sqrt(prob._weights_each(self._lam, self._lam.size))[:, None, :]

    def hessian(self, lam: np.ndarray) -> np.ndarray:
        return self._hessian[np.searchsorted(self._lam, lam)]

    def root(self, lam: np.ndarray) -> np.ndarray:
        return self._root[np.searchsorted(self._lam, lam)]


def _descend(prob: _Direction, x0: np.ndarray, lam: np.ndarray, weights: np.ndarray,
             max_iter: int) -> np.ndarray:
    """Several problems of one direction at once (x0 (F, 4n), lam (F,), weights (F, n)):
    projected Levenberg-Marquardt steps in the box, each problem until its cost stops
    falling (relative 1e-12) or after ``max_iter`` steps. The cheap solver of the smoothing
    weight's choice; the tables themselves come from :meth:`_Direction.solve`."""
    lo, hi = prob.lo, prob.hi
    terms = _SmoothTerms(prob, lam)
    x = np.clip(x0, lo + 1e-9, hi - 1e-9)
    r = prob.residuals(x, lam, weights, terms)
    cost = np.einsum("fr,fr->f", r, r)
    del r
    mu = np.full(x.shape[0], 1e-3)
    going = np.ones(x.shape[0], bool)
    eye = np.eye(x.shape[1], dtype=bool)
    for _ in range(max_iter):
        ix = np.flatnonzero(going)
        if not ix.size:
            break
        g, h = prob.normal_equations(x[ix], lam[ix], weights[ix], terms)
        # a variable on a bound that the gradient pushes out stays there
        held = ((x[ix] <= lo) & (g > 0)) | ((x[ix] >= hi) & (g < 0))
        h = np.where(held[:, :, None] | held[:, None, :], 0.0, h)
        diag = np.einsum("fii->fi", h)
        scale = np.maximum(diag, 1e-12 * np.max(diag, axis=1, keepdims=True) + 1e-300)
        rhs = np.where(held, 0.0, -g)
        todo = np.ones(ix.size, bool)
        for _ in range(25):                 # raise mu until the step lowers the cost
            t = np.flatnonzero(todo)
            a = h[t] + np.where(eye, (mu[ix[t]][:, None] * scale[t] + held[t])[:, None, :], 0.0)
            xn = np.clip(x[ix[t]] + np.linalg.solve(a, rhs[t][..., None])[..., 0], lo, hi)
            rn = prob.residuals(xn, lam[ix[t]], weights[ix[t]], terms)
            cn = np.einsum("fr,fr->f", rn, rn)
            ok = cn < cost[ix[t]]
            step = np.max(np.abs(xn - x[ix[t]]), axis=1)
            done, fail = ix[t[ok]], ix[t[~ok]]
            gain = cost[done] - cn[ok]
            x[done], cost[done] = xn[ok], cn[ok]
            mu[done] = np.maximum(mu[done] / 3.0, 1e-12)
            going[done[(gain <= 1e-12 * cost[done]) | (step[ok] <= 1e-10)]] = False
            mu[fail] *= 4.0
            # a step too short to move x that still does not lower the cost: at a minimum
            going[fail[step[~ok] <= 1e-10]] = False
            todo[t[ok | (step <= 1e-10)]] = False
            if not todo.any():
                break
        going[ix[todo]] = False             # no step lowers the cost: at a minimum
    return x


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


def _choose(prob: _Direction, x0: np.ndarray) -> float:
    """The smoothing weight by leaving one interior level out: for each weight, the joint
    fit of every level at that weight from ``x0``, from there the fit without each interior
    level in turn (both :func:`_descend`), and the left-out level's error."""
    if prob.n < 4:
        return SMOOTHING[-1]
    n_lam = len(SMOOTHING)
    x_full = _descend(prob, np.repeat(x0[None, :], n_lam, axis=0), np.asarray(SMOOTHING),
                      np.ones((n_lam, prob.n)), FULL_STEPS)
    left_out = np.arange(1, prob.n - 1)
    folds = left_out.size
    weights = np.ones((folds, prob.n))
    weights[np.arange(folds), left_out] = 0.0
    lams = np.repeat(np.asarray(SMOOTHING), folds)
    xs = _descend(prob, np.repeat(x_full, folds, axis=0), lams,
                  np.tile(weights, (n_lam, 1)), LOO_STEPS)
    held = np.array([prob.held_out(x, k) for x, k in zip(xs, np.tile(left_out, len(SMOOTHING)))])
    errors = dict(zip(SMOOTHING, held.reshape(len(SMOOTHING), folds).sum(axis=1)))
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
        lam = _choose(prob, x0)     # by the cheap batched descent; the exact solver here
        tf, ts, rf, rs = prob.parts(prob.solve(x0, lam, np.ones(prob.n)))
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
