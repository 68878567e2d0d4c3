"""``fit_lm``: Levenberg-Marquardt (paper Eqs. 6-8) with a casadi Jacobian, every cell at once.

The curve, the constraints and Eq. 5 are described in :mod:`ecmgen.fit.points`; casadi
is imported only when a fit runs.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..parallel import one_blas_thread
from .points import (_LOG_GAP, Bounds, PointFit, Progress, _Data, _bounds_for, _clip_params,
                     _eq5, _prepare, _result)


# --------------------------------------------------------------------------------------
# Levenberg-Marquardt with a casadi Jacobian
# --------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _lm_cell_function(n_t: int):
    """casadi Function for one cell: (z, t, d, w, t0, te, ra) -> (r, J, c, dc).

    Variables z = (log tau_fast, log tau_slow, v_fast, v_slow), where v is a branch's
    contribution at the cell's last point t_e in units of the data scale s:
    R = s v / phi(t_e). With psi(t) = phi(t) / phi(t_e) in [0, 1] the fitted deviation
    is v_fast psi_fast + v_slow psi_slow; as tau grows past the window psi tends to the
    straight line (t - t_0)/(t_e - t_0), so the slow branch's near-degenerate
    "long tau, large R" valley becomes a flat, straight direction (plain R would make
    it a curved valley that LM crawls along).

    d = (R - R(t_0))/s on the mask, w = mask (0/1), r_k = w_k (fitted_k - d_k),
    J = dr/dz; c = R0/s (>= 0 is feasible) with ra = R(t_0)/s, dc = dc/dz.
    """
    import casadi as ca

    z = ca.SX.sym("z", 4)
    t = ca.SX.sym("t", n_t)
    d = ca.SX.sym("d", n_t)
    w = ca.SX.sym("w", n_t)
    t0 = ca.SX.sym("t0")
    te = ca.SX.sym("te")
    ra = ca.SX.sym("ra")
    tf, ts = ca.exp(z[0]), ca.exp(z[1])
    ef, es = -ca.expm1(-(te - t0) / tf), -ca.expm1(-(te - t0) / ts)
    psf = -ca.expm1(-(t - t0) / tf) / ef
    pss = -ca.expm1(-(t - t0) / ts) / es
    res = w * (z[2] * psf + z[3] * pss - d)
    jac = ca.jacobian(res, z)
    # R = v / phi(t_e), phi(t_e) = exp(-t0/tau) ef;  R0 = ra - R (1 - exp(-t0/tau))
    rf = z[2] / (ca.exp(-t0 / tf) * ef)
    rs = z[3] / (ca.exp(-t0 / ts) * es)
    c = ra + rf * ca.expm1(-t0 / tf) + rs * ca.expm1(-t0 / ts)
    return ca.Function("dcir_residual", [z, t, d, w, t0, te, ra],
                       [res, jac, c, ca.gradient(c, z)],
                       ["z", "t", "d", "w", "t0", "te", "ra"], ["r", "J", "c", "dc"])


@lru_cache(maxsize=64)
def _lm_mapped(n_t: int, n_cols: int):
    """The cell Function mapped over ``n_cols`` columns, with a numpy buffer interface
    (casadi ``Function.buffer``: no DM conversions on every call)."""
    fn = _lm_cell_function(n_t).map(n_cols)
    return fn.buffer()


def _bucket(n: int) -> int:
    """Column count the mapped Function is built for: the next power of two (>= 8), so
    that a shrinking set of active columns re-uses a handful of Functions."""
    return max(8, 1 << (int(n) - 1).bit_length())


class _LmProblem:
    """All LM columns (cells x starts), evaluated through the mapped casadi Function."""

    def __init__(self, data: _Data, cols: np.ndarray, b: Bounds):
        self.cols = cols                                    # cell index of every column
        self.s = data.scale[cols]
        self.n_t = data.t.size
        # C-ordered (column, point) arrays == casadi's column-major (point, column)
        self.t = np.ascontiguousarray(data.tm[cols])
        self.d = np.ascontiguousarray(data.d[cols] / self.s[:, None])
        self.w = np.ascontiguousarray(data.mask[cols], dtype=np.float64)
        self.t0 = np.ascontiguousarray(data.t0[cols][:, None])
        self.te = np.ascontiguousarray(np.max(self.t, axis=1)[:, None])
        self.ra = np.ascontiguousarray((data.ra[cols] / self.s)[:, None])
        self.ltau_lo = np.log([b.tau_fast_s[0], b.tau_slow_s[0]])
        self.ltau_hi = np.log([b.tau_fast_s[1], b.tau_slow_s[1]])
        self.r_lo = np.array([b.r_fast_ohm[0], b.r_slow_ohm[0]])
        self.r_hi = np.array([b.r_fast_ohm[1], b.r_slow_ohm[1]])

    def eval(self, z, ix):
        """Residuals (n, n_t), Jacobians (n, 4, n_t), R0/s (n,) and its gradient (n, 4)
        of the columns ``ix`` at z (n, 4)."""
        n = ix.size
        m = _bucket(n)
        pad = np.concatenate([ix, np.full(m - n, ix[0])])
        zz = np.ascontiguousarray(np.concatenate([z, np.repeat(z[:1], m - n, axis=0)]))
        args = [zz, self.t[pad], self.d[pad], self.w[pad], self.t0[pad], self.te[pad],
                self.ra[pad]]
        r = np.empty((m, self.n_t))
        jac = np.empty((m, 4, self.n_t))
        c = np.empty(m)
        dc = np.empty((m, 4))
        buf, run = _lm_mapped(self.n_t, m)
        for k, arg in enumerate(args):
            buf.set_arg(k, memoryview(arg))
        for k, res in enumerate((r, jac, c, dc)):
            buf.set_res(k, memoryview(res))
        run()
        return r[:n], jac[:n], c[:n], dc[:n]

    def phi_end(self, ltau, ix):
        """phi(t_e; tau) = exp(-t0/tau) - exp(-t_e/tau), shape (n, 2) for ltau (n, 2)."""
        tau = np.exp(ltau)
        t0, te = self.t0[ix], self.te[ix]
        return -np.exp(-t0 / tau) * np.expm1(-(te - t0) / tau)

    def to_r(self, z, ix):
        """(R_fast, R_slow) in ohm of z (n, 4)."""
        return z[:, 2:] * self.s[ix, None] / self.phi_end(z[:, :2], ix)

    def from_r(self, ltau, r, ix):
        return r * self.phi_end(ltau, ix) / self.s[ix, None]

    def box(self, z, ix):
        """Bounds of z at the current taus (the v bounds move with tau)."""
        pe = self.phi_end(z[:, :2], ix) / self.s[ix, None]
        n = ix.size
        lo = np.concatenate([np.broadcast_to(self.ltau_lo, (n, 2)), self.r_lo * pe], axis=1)
        hi = np.concatenate([np.broadcast_to(self.ltau_hi, (n, 2)), self.r_hi * pe], axis=1)
        return lo, hi

    def project(self, z, ix):
        """Feasible point near z: box, tau_fast < tau_slow (swap branches), R0 >= 0."""
        lt = np.clip(z[:, :2], self.ltau_lo, self.ltau_hi)
        r = self.to_r(np.concatenate([lt, z[:, 2:]], axis=1), ix)
        sw = lt[:, 0] > lt[:, 1]
        lts, rs_ = lt[:, ::-1], r[:, ::-1]
        sw &= np.all((lts >= self.ltau_lo) & (lts <= self.ltau_hi), axis=1) & \
            np.all((rs_ >= self.r_lo) & (rs_ <= self.r_hi), axis=1)
        lt = np.where(sw[:, None], lts, lt)
        r = np.where(sw[:, None], rs_, r)
        tight = lt[:, 1] - lt[:, 0] < 2 * _LOG_GAP
        if tight.any():   # separate the taus symmetrically, then re-clip
            mid = 0.5 * (lt[:, 0] + lt[:, 1])
            lt = lt.copy()
            lt[:, 0] = np.where(tight, mid - _LOG_GAP, lt[:, 0])
            lt[:, 1] = np.where(tight, mid + _LOG_GAP, lt[:, 1])
            lt = np.clip(lt, self.ltau_lo, self.ltau_hi)
        r = np.clip(r, self.r_lo, self.r_hi)
        t0 = self.t0[ix]
        g = -np.expm1(-t0 / np.exp(lt))                     # 1 - exp(-t0/tau)
        load = np.sum(r * g, axis=1)
        ra = self.ra[ix, 0] * self.s[ix]
        over = load > ra
        k = np.where(over, np.maximum(ra, 0.0) / np.where(over, load, 1.0), 1.0)
        r = np.maximum(r * k[:, None], self.r_lo)
        return np.concatenate([lt, self.from_r(lt, r, ix)], axis=1)

    def grid_starts(self, ix, lt_grid, k):
        """The ``k`` best (log tau pairs, v) per column of ``ix`` over a grid of log tau
        pairs (g, 2), each scored with its non-negative least-squares v's."""
        t0, te = self.t0[ix][:, None, :], self.te[ix][:, None, :]
        w = self.w[ix][:, None, :]
        tt = self.t[ix][:, None, :]
        tau = np.exp(lt_grid)[None, :, :]                              # (1, g, 2)
        pf = np.expm1(-(tt - t0) / tau[..., :1]) / np.expm1(-(te - t0) / tau[..., :1]) * w
        ps = np.expm1(-(tt - t0) / tau[..., 1:]) / np.expm1(-(te - t0) / tau[..., 1:]) * w
        d = self.d[ix][:, None, :]
        a11, a12, a22 = (pf * pf).sum(-1), (pf * ps).sum(-1), (ps * ps).sum(-1)
        b1, b2 = (pf * d).sum(-1), (ps * d).sum(-1)
        dd = (d * d * w).sum(-1)
        ridge = 1e-9 * (a11 + a22) + 1e-300
        a11, a22 = a11 + ridge, a22 + ridge
        det = a11 * a22 - a12 * a12
        cand = [np.stack([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det], -1),
                np.stack([np.maximum(b1 / a11, 0), np.zeros_like(b1)], -1),
                np.stack([np.zeros_like(b1), np.maximum(b2 / a22, 0)], -1)]
        best_sse, best_v = np.full(a11.shape, np.inf), np.zeros(a11.shape + (2,))
        for v in cand:
            x, y = v[..., 0], v[..., 1]
            sse = dd - 2 * (x * b1 + y * b2) + x * x * a11 + 2 * x * y * a12 + y * y * a22
            better = (x >= 0) & (y >= 0) & (sse < best_sse)
            best_sse = np.where(better, sse, best_sse)
            best_v = np.where(better[..., None], v, best_v)
        top = np.argsort(best_sse, axis=1, kind="stable")[:, :k]       # (n, k)
        lt = lt_grid[top]                                              # (n, k, 2)
        v = np.take_along_axis(best_v, top[..., None], axis=1)         # (n, k, 2)
        return lt, v

    def to_params(self, z, ix):
        """(tau_fast, tau_slow, R_fast, R_slow) of the columns ``ix``."""
        r = self.to_r(z, ix)
        return np.exp(z[:, 0]), np.exp(z[:, 1]), r[:, 0], r[:, 1]


def _lm_step(prob: _LmProblem, zi, ri, ji, c_i, dc_i, mu_i, ix, eye):
    """One projected LM step of the columns ``ix`` (Eq. 8, active sets of the box and of
    R0 >= 0): (the step, the gradient J'r, J'J, the projected gradient)."""
    lo, hi = prob.box(zi, ix)
    g = np.einsum("nik,nk->ni", ji, ri)
    a = np.einsum("nik,njk->nij", ji, ji)
    # box active set: a variable held at its bound by the gradient stays there
    blocked = ((zi <= lo) & (g > 0)) | ((zi >= hi) & (g < 0))
    free = ~blocked
    m = np.where(free[:, :, None] & free[:, None, :], a, 0.0) \
        + np.where(free, mu_i[:, None], 1.0)[:, :, None] * eye
    gf = np.where(free, g, 0.0)
    minv_g = np.linalg.solve(m, gf[..., None])[..., 0]
    h = -minv_g
    # R0 >= 0 active set: stay on the (linearised) constraint if the step would cross it
    ca_ = np.where(free, dc_i, 0.0)
    on = (c_i <= 1e-7) & (c_i + np.einsum("ni,ni->n", ca_, h) < 0)
    if on.any():
        minv_a = np.linalg.solve(m, ca_[..., None])[..., 0]
        den = np.einsum("ni,ni->n", ca_, minv_a)
        lam = np.where(on & (den > 0), (c_i + np.einsum("ni,ni->n", ca_, h))
                       / np.where(den > 0, den, 1.0), 0.0)
        h = h - lam[:, None] * minv_a
    # stationarity: projected gradient (box, and the tangent of an active R0 = 0)
    gp = gf
    at_r0 = (c_i <= 1e-7) & (np.einsum("ni,ni->n", ca_, gf) > 0)
    if at_r0.any():
        na = np.einsum("ni,ni->n", ca_, ca_)
        gp = np.where(at_r0[:, None], gf - ca_ * (np.einsum("ni,ni->n", ca_, gf)
                                                  / np.where(na > 0, na, 1.0))[:, None], gf)
    return h, g, a, gp


def _lm_iterate(prob: _LmProblem, z, max_iterations: int, progress: Progress | None,
                xtol=1e-10, ftol=1e-12, gtol=1e-10, ctol=1e-26):
    """Projected Levenberg-Marquardt (Eq. 8) with Nielsen's mu update, all columns at once.

    Constraints: variables held at a bound by the gradient are fixed for the step
    (active set); when R0 = 0 is active and the step would make it negative, the
    step is solved on the linearised constraint (one KKT elimination); P() then
    restores exact feasibility. Only the columns still iterating are evaluated.
    """
    n = z.shape[0]
    allix = np.arange(n)
    eye = np.eye(4)
    r, jac, c, dc = prob.eval(z, allix)
    cost = 0.5 * np.sum(r * r, axis=1)
    a = np.einsum("nik,njk->nij", jac, jac)
    mu = 1e-3 * np.max(np.diagonal(a, axis1=1, axis2=2), axis=1) + 1e-12
    nu = np.full(n, 2.0)
    active = np.isfinite(cost)
    conv = np.zeros(n, bool)
    iters = np.zeros(n, np.int64)
    for it in range(1, max_iterations + 1):
        ix = np.flatnonzero(active)
        if ix.size == 0:
            break
        zi, ri, ji, c_i, dc_i = z[ix], r[ix], jac[ix], c[ix], dc[ix]
        h, g, a, gp = _lm_step(prob, zi, ri, ji, c_i, dc_i, mu[ix], ix, eye)
        small_grad = np.max(np.abs(gp), axis=1) <= gtol
        z_try = prob.project(zi + h, ix)
        step = z_try - zi
        r_try, j_try, c_try, dc_try = prob.eval(z_try, ix)
        cost_i = cost[ix]
        cost_try = 0.5 * np.sum(r_try * r_try, axis=1)
        pred = -(np.einsum("ni,ni->n", g, step) + 0.5 * np.einsum("ni,nij,nj->n", step, a, step))
        ared = cost_i - cost_try
        accept = np.isfinite(cost_try) & (ared > 0)
        rho = np.where(pred > 0, ared / np.where(pred > 0, pred, 1.0), 0.0)
        small_step = np.linalg.norm(step, axis=1) <= xtol * (np.linalg.norm(zi, axis=1) + xtol)
        small_red = accept & (ared <= ftol * cost_i) & (np.abs(pred) <= ftol * cost_i)
        z[ix] = np.where(accept[:, None], z_try, zi)
        r[ix] = np.where(accept[:, None], r_try, ri)
        jac[ix] = np.where(accept[:, None, None], j_try, ji)
        c[ix] = np.where(accept, c_try, c_i)
        dc[ix] = np.where(accept[:, None], dc_try, dc_i)
        cost[ix] = np.where(accept, cost_try, cost_i)
        mui, nui = mu[ix], nu[ix]
        mu[ix] = np.where(accept, mui * np.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), mui * nui)
        nu[ix] = np.where(accept, 2.0, nui * 2)
        iters[ix] = it
        good = small_grad | small_step | small_red | (cost[ix] <= ctol)
        stop = good | ~np.isfinite(mu[ix]) | (mu[ix] > 1e300)
        conv[ix] |= good
        active[ix[stop]] = False
        if progress is not None:
            progress(it, max_iterations)
    return z, cost, conv, iters


# deterministic multi-start: a _GRID x _GRID grid of log-spaced (tau_fast, tau_slow)
# pairs is scored with non-negative least-squares resistances; LM starts from the best
# _N_STARTS pairs of every cell and keeps the lowest squared error
_GRID = 12
_N_STARTS = 4


@one_blas_thread
def fit_lm(t_s, r_ohm, *, bounds: Bounds | None = None, x0: PointFit | None = None,
           max_iterations: int = 200, progress: Progress | None = None) -> PointFit:
    """Levenberg-Marquardt fit of every cell at once (paper Eqs. 6-8).

    Minimises the squared residuals (Eq. 7) of the points after the first. The
    residual and its Jacobian come from one casadi SX Function for a single cell
    (``_lm_cell_function``), mapped over all columns (cells x starts) and evaluated
    through a numpy buffer once per iteration; the step of Eq. 8,
    x <- P(x - (J'J + mu I)^-1 J'r), is solved in numpy for all columns together.
    mu follows Nielsen's rule (mu x max(1/3, 1 - (2 rho - 1)^3) on an accepted step,
    mu x nu, nu x 2 on a rejected one). P projects on the constraints (box,
    tau_fast < tau_slow, R0 >= 0); bounds held active by the gradient and an active
    R0 = 0 are also honoured inside the step (active set). Variables are scaled:
    log tau, and each branch's contribution at the last point in units of the cell's
    largest |R(t) - R(t_0)| (see ``_lm_cell_function``). A column stops on a small
    step, a small projected gradient, a negligible relative cost reduction, or an
    exact fit; reaching ``max_iterations`` is reported as not converged.

    Start: ``x0`` (e.g. the GA result) where it has finite parameters, otherwise a
    deterministic multi-start: a 12 x 12 grid of log-spaced (tau_fast, tau_slow) pairs
    is scored with non-negative least-squares resistances and LM runs from the best 4
    pairs of every cell, keeping the lowest squared error. When started from ``x0``,
    a cell whose LM result has a worse Eq.-5 fitness than ``x0`` (LM minimises
    squares, Eq. 5 is absolute values) keeps ``x0`` (projected on the constraints if
    it was infeasible), so the result is never worse than the start in Eq. 5.

    Long: most of it is this docstring, the method's reference (paper Eqs. 6-8).
    """
    data = _prepare(t_s, r_ohm)
    b = _bounds_for(data, bounds)
    n_c = data.r.shape[0]
    cells = np.flatnonzero(data.ok)
    out = np.full((n_c, 4), np.nan)
    conv = np.zeros(n_c, bool)
    iters = np.zeros(n_c, np.int64)
    if cells.size == 0:
        return _result(data, *out.T, conv, iters, "lm")

    x0_params, from_x0 = _x0_columns(x0, data)

    # columns: one per x0-started cell, _N_STARTS per multi-started cell
    lf = np.linspace(*np.log(b.tau_fast_s), _GRID)
    ls = np.linspace(*np.log(b.tau_slow_s), _GRID)
    grid = np.array([(f, s_) for f in lf for s_ in ls if s_ - f > np.log(1.5)])
    if grid.size == 0:
        grid = np.array([[lf[0], ls[-1]]])
    n_starts = min(_N_STARTS, len(grid))
    multi = cells[~from_x0[cells]]
    single = cells[from_x0[cells]]
    cols = np.concatenate([single, np.repeat(multi, n_starts)])
    prob = _LmProblem(data, cols, b)

    z = np.empty((cols.size, 4))
    ns = single.size
    if ns:
        p = x0_params[single]
        lt = np.log(p[:, :2])
        z[:ns] = np.concatenate([lt, prob.from_r(lt, p[:, 2:], np.arange(ns))], axis=1)
    if multi.size:
        first = ns + np.arange(multi.size) * n_starts     # one column of each cell
        lt, v = prob.grid_starts(first, grid, n_starts)
        # keep the v's off zero: a branch started at R = 0 has no gradient in its tau
        z[ns:] = np.concatenate([lt, np.maximum(v, 0.05)], axis=-1).reshape(-1, 4)
    z = prob.project(z, np.arange(cols.size))
    z_start = z.copy()
    z, cost, cconv, citers = _lm_iterate(prob, z, int(max_iterations), progress)

    # best start per multi-started cell (lowest squared error; first on ties)
    if multi.size:
        k = n_starts
        c_m = cost[ns:].reshape(multi.size, k)
        c_m = np.where(np.isfinite(c_m), c_m, np.inf)
        pick = ns + np.arange(multi.size) * k + np.argmin(c_m, axis=1)
    else:
        pick = np.zeros(0, np.int64)
    chosen = np.concatenate([np.arange(ns), pick]).astype(np.int64)
    target = cols[chosen]
    params = np.stack(_clip_params(b, *prob.to_params(z[chosen], chosen)), axis=1)
    out[target] = params
    conv[target] = cconv[chosen]
    iters[target] = citers[chosen]

    if ns:
        _never_worse_than_x0(prob, data, b, out, single, z_start[:ns], x0_params[single])
    return _result(data, *out.T, conv, iters, "lm")


def _x0_columns(x0: PointFit | None, data):
    """``x0``'s parameters per cell ((n, 4): tau_fast, tau_slow, r_fast, r_slow; None
    without x0) and the cells that start from them (finite, positive time constants)."""
    n_c = data.r.shape[0]
    if x0 is None:
        return None, np.zeros(n_c, bool)
    if not isinstance(x0, PointFit):
        raise TypeError("x0 must be a PointFit")
    x0_params = np.stack([np.asarray(x0.tau_fast_s, float), np.asarray(x0.tau_slow_s, float),
                          np.asarray(x0.r_fast_ohm, float), np.asarray(x0.r_slow_ohm, float)],
                         axis=1)
    if x0_params.shape[0] != n_c:
        raise ValueError(f"x0 has {x0_params.shape[0]} cells, the table has {n_c}")
    from_x0 = np.all(np.isfinite(x0_params), axis=1) & (x0_params[:, 0] > 0) \
        & (x0_params[:, 1] > 0) & data.ok
    return x0_params, from_x0


def _never_worse_than_x0(prob, data, b, out, single, z_start, given) -> None:
    """Never worse than the start in Eq. 5: the cells ``single`` started from x0 (``given``,
    ``z_start`` its projection) keep x0 where LM's result is worse (x0 as given if it is
    feasible); in place in ``out``."""
    ns = single.size
    start = np.stack(_clip_params(b, *prob.to_params(z_start, np.arange(ns))), axis=1)
    feasible = np.all(np.isclose(start, given, rtol=1e-12, atol=0.0), axis=1)
    start = np.where(feasible[:, None], given, start)
    sub = _prepare(data.t, data.r[single])
    f_lm = _eq5(sub, *out[single].T)
    f_st = _eq5(sub, *start.T)
    worse = ~(f_lm <= f_st)
    out[single[worse]] = start[worse]
