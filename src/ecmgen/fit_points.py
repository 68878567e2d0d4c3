"""Fit the paper's DC-IR point curves: a GA and a casadi Levenberg-Marquardt.

Aras & Yonel (2017) fit, for every table cell (SOC x direction x C-rate), the DC-IR
values R(t) = dV/dI measured at a few times into a pulse (0.1, 1, 3, 6, 10 s) with

    R(t) = R0 + R_fast (1 - exp(-t/tau_fast)) + R_slow (1 - exp(-t/tau_slow)).

R0 is not a free parameter: the curve is pinned to the first valid point t_0,

    R0 = R(t_0) - R_fast (1 - exp(-t_0/tau_fast)) - R_slow (1 - exp(-t_0/tau_slow)),

which is the paper's "R0 = R(0.1 s)" with four free parameters, while the model
still reproduces R(t_0) exactly. With d_k = R(t_k) - R(t_0) the fitted curve is

    d_k ~ R_fast phi(t_k; tau_fast) + R_slow phi(t_k; tau_slow),
    phi(t; tau) = exp(-t_0/tau) - exp(-t/tau),

and the paper's fitness (Eq. 5) is sum_k |d_k - fitted_k| over the valid points after
the first. Constraints everywhere: the bounds, tau_fast < tau_slow, and R0 >= 0.

fit_ga   real-coded GA, vectorised over the population and all cells at once
         (arrays (n_cells, pop, 4)); minimises Eq. 5; MATLAB-``ga``-like stall rule.
fit_lm   Levenberg-Marquardt (paper Eqs. 6-8, x <- x - (J'J + mu I)^-1 J'r) on the
         squared residuals with a casadi residual/Jacobian mapped over all cells;
         Nielsen's adaptive mu; scaled variables (log tau, R / data scale).

NaN entries of ``r_ohm`` (points a pulse did not reach) are masked out. A row with
fewer than 3 valid points after its first valid point gets NaN parameters and
``converged=False``.

``progress`` callbacks are called as ``progress(done, total)`` (generations or
iterations), like the other fitters of the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np

Progress = Callable[[int, int], None]

PARAM_FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")
MIN_POINTS = 3            # valid points after the first one needed for a fit
_LOG_GAP = 1e-6           # tau_slow >= tau_fast * exp(_LOG_GAP): strict ordering
_PENALTY = 1e3            # GA: fitness penalty per ohm of constraint violation


# --------------------------------------------------------------------------------------
# public types
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Bounds:
    """Search box, as (lo, hi) pairs; the same for every cell of a table."""

    tau_fast_s: tuple[float, float]
    tau_slow_s: tuple[float, float]
    r_fast_ohm: tuple[float, float]
    r_slow_ohm: tuple[float, float]

    def __post_init__(self):
        for name in ("tau_fast_s", "tau_slow_s", "r_fast_ohm", "r_slow_ohm"):
            pair = getattr(self, name)
            if len(pair) != 2:
                raise ValueError(f"Bounds.{name} must be a (lo, hi) pair, got {pair!r}")
            lo, hi = float(pair[0]), float(pair[1])
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(f"Bounds.{name} needs finite lo < hi, got {pair!r}")
            if name.startswith("tau") and lo <= 0:
                raise ValueError(f"Bounds.{name} must be positive, got {pair!r}")
            object.__setattr__(self, name, (lo, hi))
        if self.tau_fast_s[0] * np.exp(2 * _LOG_GAP) >= self.tau_slow_s[1]:
            raise ValueError("Bounds leave no room for tau_fast < tau_slow: "
                             f"tau_fast_s {self.tau_fast_s}, tau_slow_s {self.tau_slow_s}")

    def lo(self) -> np.ndarray:
        """Lower bounds in the order (tau_fast, tau_slow, r_fast, r_slow)."""
        return np.array([self.tau_fast_s[0], self.tau_slow_s[0],
                         self.r_fast_ohm[0], self.r_slow_ohm[0]])

    def hi(self) -> np.ndarray:
        return np.array([self.tau_fast_s[1], self.tau_slow_s[1],
                         self.r_fast_ohm[1], self.r_slow_ohm[1]])


@dataclass(frozen=True)
class PointFit:
    """One fit of a whole table; every array has shape (n_cells,)."""

    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    tau_fast_s: np.ndarray
    r_slow_ohm: np.ndarray
    tau_slow_s: np.ndarray
    fitness_ohm: np.ndarray    # Eq. 5: sum |R_meas - R_fit| over the points after the first
    converged: np.ndarray      # bool: stopping rule met (not just the iteration cap)
    iterations: np.ndarray     # generations (GA) / iterations (LM) per cell
    method: str                # "ga" | "lm"


def default_bounds(t_s: np.ndarray, r_ohm: np.ndarray) -> Bounds:
    """Search box derived from the sampling times and the data's magnitude.

    With t_0 the first time, t_end the last, span = t_end - t_0 and dt the smallest
    spacing:

    * tau_fast in [tau_lo, span], tau_slow in [tau_lo, 5 t_end], where
      tau_lo = max(dt / 10, t_0 / 5). Much faster dynamics than the sampling step or
      than t_0 (they are over before the pinned first point) are invisible.
      Beyond ~5 t_end the slow branch is a straight line over the window
      (1 - exp(-t/tau) ~ t/tau within 10 %), so only R_slow/tau_slow would be
      identifiable and R_slow would run away. Ordering tau_fast < tau_slow is a
      constraint, not part of the box.
    * R_fast, R_slow in [0, 10 rise], rise = largest R(t) - R(t_0) in the table
      (falls back to the largest |R| if the table never rises). A slow branch with
      tau = 5 t_end reaches 18 % of R_slow at t_end, i.e. needs R_slow ~ 5.5 rise;
      10 leaves margin for noise.
    """
    t = _check_t(t_s)
    r = _check_r(r_ohm, t.size)
    t0, t_end = float(t[0]), float(t[-1])
    span = t_end - t0
    dt = float(np.min(np.diff(t)))
    tau_lo = max(dt / 10.0, t0 / 5.0)
    valid = np.isfinite(r)
    rise = 0.0
    if valid.any():
        first = np.argmax(valid, axis=1)
        anchor = r[np.arange(r.shape[0]), first]
        with np.errstate(invalid="ignore"):
            rises = np.nanmax(np.where(valid, r - anchor[:, None], np.nan), axis=1)
        if np.any(np.isfinite(rises)):
            rise = float(np.nanmax(rises))
        if not rise > 0:
            rise = float(np.nanmax(np.abs(r)))
    if not rise > 0:
        rise = 1e-3
    r_hi = 10.0 * rise
    return Bounds(tau_fast_s=(tau_lo, max(span, 2 * tau_lo)),
                  tau_slow_s=(tau_lo, max(5.0 * t_end, 4 * tau_lo)),
                  r_fast_ohm=(0.0, r_hi), r_slow_ohm=(0.0, r_hi))


def curve_r_ohm(fit: PointFit, t_s) -> np.ndarray:
    """The fitted model curve R(t), shape (n_cells, n_t)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))[None, :]
    col = lambda a: np.asarray(a, dtype=np.float64)[:, None]  # noqa: E731
    with np.errstate(invalid="ignore", divide="ignore"):
        return (col(fit.r0_ohm)
                - col(fit.r_fast_ohm) * np.expm1(-t / col(fit.tau_fast_s))
                - col(fit.r_slow_ohm) * np.expm1(-t / col(fit.tau_slow_s)))


# --------------------------------------------------------------------------------------
# shared data preparation and model pieces
# --------------------------------------------------------------------------------------
def _check_t(t_s) -> np.ndarray:
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"t_s must be a 1-D array of at least 2 times, got shape {t.shape}")
    if not np.all(np.isfinite(t)) or t[0] < 0 or np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be finite, >= 0 and strictly increasing")
    return t


def _check_r(r_ohm, n_t: int) -> np.ndarray:
    r = np.asarray(r_ohm, dtype=np.float64)
    if r.ndim == 1:
        r = r[None, :]
    if r.ndim != 2 or r.shape[1] != n_t:
        raise ValueError(f"r_ohm must have shape (n_cells, {n_t}), got {np.shape(r_ohm)}")
    if np.any(np.isinf(r)):
        raise ValueError("r_ohm has infinite values (use NaN for points not reached)")
    return r


@dataclass(frozen=True)
class _Data:
    t: np.ndarray        # (n_t,)
    r: np.ndarray        # (n_c, n_t) as given (NaN = missing)
    mask: np.ndarray     # (n_c, n_t) valid points after the first valid one
    ok: np.ndarray       # (n_c,) enough points to fit
    t0: np.ndarray       # (n_c,) time of the pinned first point (0 where none)
    ra: np.ndarray       # (n_c,) R at the pinned point (0 where none)
    d: np.ndarray        # (n_c, n_t) R - ra on the mask, 0 elsewhere
    tm: np.ndarray       # (n_c, n_t) t on the mask, t0 elsewhere (phi = 0 there)
    scale: np.ndarray    # (n_c,) magnitude of d, for scaling (> 0)


def _prepare(t_s, r_ohm) -> _Data:
    t = _check_t(t_s)
    r = _check_r(r_ohm, t.size)
    n_c, n_t = r.shape
    valid = np.isfinite(r)
    has = valid.any(axis=1)
    first = np.argmax(valid, axis=1)
    rows = np.arange(n_c)
    mask = valid & (np.arange(n_t)[None, :] > first[:, None])
    ok = has & (mask.sum(axis=1) >= MIN_POINTS)
    t0 = np.where(has, t[first], 0.0)
    ra = np.where(has, r[rows, first], 0.0)
    d = np.where(mask, r - ra[:, None], 0.0)
    tm = np.where(mask, t[None, :], t0[:, None])
    scale = np.max(np.abs(d), axis=1, initial=0.0)
    scale = np.where(scale > 0, scale, np.where(np.abs(ra) > 0, np.abs(ra), 1.0))
    return _Data(t, r, mask, ok, t0, ra, d, tm, scale)


def _phi(tm, t0, tau):
    """exp(-t0/tau) - exp(-t/tau), written to stay accurate for t close to t0."""
    return -np.exp(-t0 / tau) * np.expm1(-(tm - t0) / tau)


def _r0(ra, t0, tf, ts, rf, rs):
    return ra + rf * np.expm1(-t0 / tf) + rs * np.expm1(-t0 / ts)


def _eq5(data: _Data, tf, ts, rf, rs) -> np.ndarray:
    """Eq. 5 per cell for parameter arrays of shape (n_c,)."""
    col = lambda a: a[:, None]  # noqa: E731
    t0 = col(data.t0)
    fitted = col(rf) * _phi(data.tm, t0, col(tf)) + col(rs) * _phi(data.tm, t0, col(ts))
    return np.sum(np.where(data.mask, np.abs(data.d - fitted), 0.0), axis=1)


def _result(data: _Data, tf, ts, rf, rs, converged, iterations, method) -> PointFit:
    ok = data.ok
    nan = np.full(ok.shape, np.nan)
    tf, ts, rf, rs = (np.where(ok, a, nan) for a in (tf, ts, rf, rs))
    r0 = _r0(data.ra, data.t0, tf, ts, rf, rs)
    # rounding only: the constraint keeps R0 >= 0 up to a few ulps of R(t_0)
    tiny = 1e-12 * np.maximum(np.abs(data.ra), data.scale)
    r0 = np.where((r0 < 0) & (r0 > -tiny), 0.0, r0)
    fitness = np.where(ok, _eq5(data, tf, ts, rf, rs), np.nan)
    return PointFit(r0_ohm=r0, r_fast_ohm=rf, tau_fast_s=tf, r_slow_ohm=rs, tau_slow_s=ts,
                    fitness_ohm=fitness, converged=np.asarray(converged, bool) & ok,
                    iterations=np.asarray(iterations, dtype=np.int64), method=method)


def _bounds_for(data: _Data, bounds: Bounds | None) -> Bounds:
    if bounds is None:
        return default_bounds(data.t, data.r)
    if not isinstance(bounds, Bounds):
        raise TypeError(f"bounds must be a Bounds, got {type(bounds).__name__}")
    return bounds


# --------------------------------------------------------------------------------------
# Eq. 5 over the two resistances for fixed time constants (GA inner solve)
# --------------------------------------------------------------------------------------
_EXACT_MAX_POINTS = 8     # up to this many fitted points: exact vertex enumeration


@lru_cache(maxsize=16)
def _pairs(m: int):
    return np.triu_indices(m, 1)


def _vertices(pf, ps, d, mask, cf, cs, ra, box):
    """Candidate optima of the 2-variable L1 problem: every intersection of two of
    the lines {d_k = x pf_k + y ps_k}, x = xl|xh, y = yl|yh and cf x + cs y = ra.
    Returns x, y, ok with a trailing candidate axis."""
    xl, xh, yl, yh = box
    n = pf.shape[-1]
    shp = cf.shape
    ra = np.broadcast_to(ra, shp)
    xs, ys, oks = [], [], []

    def add(x, y, ok):
        xs.append(np.broadcast_to(x, shp + x.shape[len(shp):]))
        ys.append(np.broadcast_to(y, shp + y.shape[len(shp):]))
        oks.append(np.broadcast_to(ok, shp + ok.shape[len(shp):]))

    tiny = 1e-12
    if n >= 2:                                             # two residual lines
        i, j = _pairs(n)
        det = pf[..., i] * ps[..., j] - pf[..., j] * ps[..., i]
        ok = mask[..., i] & mask[..., j] & (np.abs(det) > tiny)
        sd = np.where(ok, det, 1.0)
        add((d[..., i] * ps[..., j] - d[..., j] * ps[..., i]) / sd,
            (pf[..., i] * d[..., j] - pf[..., j] * d[..., i]) / sd, ok)
    okf = mask & (np.abs(pf) > tiny)
    oks_ = mask & (np.abs(ps) > tiny)
    spf, sps = np.where(okf, pf, 1.0), np.where(oks_, ps, 1.0)
    for c in (xl, xh):                                     # residual line x vertical box side
        add(np.full(pf.shape, c), (d - c * pf) / sps, oks_)
    for c in (yl, yh):                                     # residual line x horizontal side
        add((d - c * ps) / spf, np.full(pf.shape, c), okf)
    # residual line x R0 line: [pf ps; cf cs] [x y]' = [d ra]'
    det = pf * cs[..., None] - ps * cf[..., None]
    ok = mask & (np.abs(det) > tiny)
    sd = np.where(ok, det, 1.0)
    add((d * cs[..., None] - ps * ra[..., None]) / sd,
        (pf * ra[..., None] - d * cf[..., None]) / sd, ok)
    # corners of the box, and box sides x R0 line
    cx = np.array([xl, xl, xh, xh])
    cy = np.array([yl, yh, yl, yh])
    add(np.broadcast_to(cx, shp + (4,)), np.broadcast_to(cy, shp + (4,)),
        np.ones(shp + (4,), bool))
    okc, oks2 = cs > tiny, cf > tiny
    scs, scf = np.where(okc, cs, 1.0), np.where(oks2, cf, 1.0)
    add(np.stack([np.full(shp, xl), np.full(shp, xh),
                  (ra - cs * yl) / scf, (ra - cs * yh) / scf], axis=-1),
        np.stack([(ra - cf * xl) / scs, (ra - cf * xh) / scs,
                  np.full(shp, yl), np.full(shp, yh)], axis=-1),
        np.stack([okc, okc, oks2, oks2], axis=-1))
    return (np.concatenate(xs, axis=-1), np.concatenate(ys, axis=-1),
            np.concatenate(oks, axis=-1))


def _l1_resistances(pf, ps, d, mask, cf, cs, ra, box, scale, exact: bool):
    """argmin over (x, y) = (R_fast, R_slow) of sum mask |d - x pf - y ps|
    subject to box = (xl, xh, yl, yh) and cf x + cs y <= ra (i.e. R0 >= 0).

    pf, ps, d, mask: (..., n); cf, cs: (...); ra, scale: broadcastable to (...).
    exact=True: the problem is a 2-variable LP, whose optimum lies on a vertex of the
    arrangement of the lines {residual_k = 0} and the constraint lines; all pairwise
    intersections are enumerated (fine for a handful of points). exact=False:
    iteratively reweighted least squares (8 sweeps) then projection on the
    constraints, an approximation for long (dense) curves.
    """
    xl, xh, yl, yh = box
    if exact:
        x, y, ok = _vertices(pf, ps, d, mask, cf, cs, ra, box)
        tx, ty = 1e-9 * (xh - xl), 1e-9 * (yh - yl)
        ok &= (x >= xl - tx) & (x <= xh + tx) & (y >= yl - ty) & (y <= yh + ty)
        x, y = np.clip(x, xl, xh), np.clip(y, yl, yh)
        ok &= cf[..., None] * x + cs[..., None] * y \
            <= np.asarray(ra)[..., None] + 1e-9 * np.asarray(scale)[..., None]
        res = np.abs(d[..., None, :] - x[..., None] * pf[..., None, :]
                     - y[..., None] * ps[..., None, :])
        obj = np.where(ok, np.einsum("...cn,...n->...c", res, mask.astype(np.float64)), np.inf)
        k = np.argmin(obj, axis=-1)[..., None]
        found = np.isfinite(np.take_along_axis(obj, k, axis=-1)[..., 0])
        x = np.where(found, np.take_along_axis(x, k, axis=-1)[..., 0], xl)
        y = np.where(found, np.take_along_axis(y, k, axis=-1)[..., 0], yl)
        return x, y
    w = mask.astype(np.float64)
    eps = 1e-6 * np.asarray(scale)[..., None]
    for sweep in range(9):
        a11, a12, a22 = (w * pf * pf).sum(-1), (w * pf * ps).sum(-1), (w * ps * ps).sum(-1)
        b1, b2 = (w * pf * d).sum(-1), (w * ps * d).sum(-1)
        ridge = 1e-12 * (a11 + a22) + 1e-300
        a11, a22 = a11 + ridge, a22 + ridge
        det = a11 * a22 - a12 * a12
        x, y = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
        if sweep < 8:
            w = mask / np.maximum(np.abs(d - x[..., None] * pf - y[..., None] * ps), eps)
    x, y = np.clip(x, xl, xh), np.clip(y, yl, yh)
    load = cf * x + cs * y
    over = load > ra
    k = np.where(over, np.maximum(ra, 0.0) / np.where(over, load, 1.0), 1.0)
    return np.maximum(x * k, xl), np.maximum(y * k, yl)


# --------------------------------------------------------------------------------------
# genetic algorithm
# --------------------------------------------------------------------------------------
_GA = dict(eta_c=10.0, p_sbx=0.5, line_ext=0.25, p_mut=0.25, sigma0=0.2, sigma_half=100.0,
           decades=5.0, dedup=True, crowding=False,
           inner=True)


def fit_ga(t_s, r_ohm, *, bounds: Bounds | None = None, seed: int = 0, population: int = 48,
           max_generations: int = 2000, stall_generations: int = 50,
           function_tolerance: float = 1e-6, progress: Progress | None = None) -> PointFit:
    """Real-coded GA on Eq. 5, every cell of the table at once.

    Genes live in the unit cube [0, 1]^4 over (log tau_fast, log tau_slow, R_fast,
    R_slow) mapped onto ``bounds``. Each generation, for every cell at once:

    * selection: binary tournaments;
    * crossover: per pair of parents either simulated binary crossover (SBX, per
      gene) or extended line recombination (one random factor for all genes, which
      lets the offspring move along the curved tau-R valleys of this problem);
    * mutation: per gene, a Gaussian-signed step whose size is log-uniform over
      ``decades`` decades below sigma_g, sigma_g = sigma0 / (1 + g / sigma_half)
      shrinking over the generations (multi-scale steps keep both exploration and
      the fine precision the stall rule asks for);
    * repair: clip to the box, order the taus by swapping the branches, and scale
      R_fast/R_slow down where R0 would go negative (the curve stays pinned to the
      first point); what repair cannot fix is penalised;
    * survivors: the paper's BestFit(P, P_new): the best ``population`` of parents
      plus offspring (elitist).

    Stopping rule per cell (MATLAB ``ga`` FunctionTolerance in spirit): the best
    fitness improved by at most ``function_tolerance`` x max(best fitness, 1e-3 x
    the fitness of the zero model) over the last ``stall_generations`` generations.
    Cells stop independently; a cell that reaches ``max_generations`` is reported not
    converged. Same ``seed`` => bit-identical result. The random stream is shared by
    the table's cells, so a cell's result depends on the whole table (not only on its
    own data) through the draws.
    """
    data = _prepare(t_s, r_ohm)
    b = _bounds_for(data, bounds)
    pop = int(population)
    if pop < 4:
        raise ValueError("population must be at least 4")
    pop += pop % 2
    half = pop // 2
    stall = max(int(stall_generations), 1)
    n_c = data.r.shape[0]
    rng = np.random.default_rng(seed)
    o = _GA

    lo = np.array([np.log(b.tau_fast_s[0]), np.log(b.tau_slow_s[0]),
                   b.r_fast_ohm[0], b.r_slow_ohm[0]])
    hi = np.array([np.log(b.tau_fast_s[1]), np.log(b.tau_slow_s[1]),
                   b.r_fast_ohm[1], b.r_slow_ohm[1]])
    width = hi - lo

    best_u = np.full((n_c, 4), np.nan)
    out_conv = np.zeros(n_c, bool)
    out_iter = np.zeros(n_c, np.int64)
    act = np.flatnonzero(data.ok)              # cells still evolving

    def cell_arrays(ix):
        return (data.tm[ix][:, None, used], data.t0[ix][:, None], data.d[ix][:, None, used],
                data.mask[ix][:, None, used], data.ra[ix][:, None], data.scale[ix][:, None])

    # only the columns some cell fits (drops the pinned first column, for instance)
    used = data.mask.any(axis=0)
    exact = int(used.sum()) <= _EXACT_MAX_POINTS
    box = (lo[2], hi[2], lo[3], hi[3])

    def repair_and_score(u, arrs):
        """Repaired genes and their fitness (Eq. 5 plus constraint penalties)."""
        tm, t0, d, mask, ra, scale = arrs
        x = lo + np.clip(u, 0.0, 1.0) * width
        lf, ls = x[..., 0], x[..., 1]
        # tau_fast > tau_slow: swap the two time constants where the box allows
        swap = (lf > ls) & (ls <= hi[0]) & (lf >= lo[1])
        lf, ls = np.where(swap, ls, lf), np.where(swap, lf, ls)
        tf, ts = np.exp(lf), np.exp(ls)
        pf = _phi(tm, t0[..., None], tf[..., None])
        ps = _phi(tm, t0[..., None], ts[..., None])
        cf, cs = -np.expm1(-t0 / tf), -np.expm1(-t0 / ts)   # 1 - exp(-t0/tau)
        if o["inner"]:
            rf, rs = _l1_resistances(pf, ps, d, mask, cf, cs, ra, box, scale, exact)
        else:
            rf, rs = np.clip(x[..., 2], lo[2], hi[2]), np.clip(x[..., 3], lo[3], hi[3])
            load = rf * cf + rs * cs
            over = load > ra
            k = np.where(over, np.maximum(ra, 0.0) / np.where(over, load, 1.0), 1.0)
            rf, rs = np.maximum(rf * k, lo[2]), np.maximum(rs * k, lo[3])
        u = np.clip(np.stack([lf, ls, rf, rs], axis=-1) - lo, 0.0, width) / width
        fit = np.sum(np.where(mask, np.abs(d - rf[..., None] * pf - rs[..., None] * ps), 0.0),
                     axis=-1)
        r0 = ra - rf * cf - rs * cs
        viol = np.maximum(-r0, 0.0) + np.maximum(lf - ls + _LOG_GAP, 0.0) * scale
        return u, fit + _PENALTY * viol

    arrs = cell_arrays(act)
    u, fit = repair_and_score(rng.random((act.size, pop, 4)), arrs)
    fzero = np.sum(np.abs(data.d), axis=1)     # Eq. 5 of the zero model, per cell
    hist = np.full((act.size, stall + 1), np.inf)
    hist[:, 0] = fit.min(axis=1)
    rows = np.arange(act.size)[:, None]
    expo = 1.0 / (o["eta_c"] + 1.0)

    g = 0
    while act.size and g < max_generations:
        g += 1
        n = act.size
        # -- selection: binary tournaments ---------------------------------------------
        if o["crowding"]:
            win = np.argsort(rng.random((n, pop)), axis=1)
        else:
            cand = rng.integers(0, pop, size=(n, pop, 2))
            fc = np.take_along_axis(fit, cand.reshape(n, -1), axis=1).reshape(n, pop, 2)
            win = np.where(fc[..., 0] <= fc[..., 1], cand[..., 0], cand[..., 1])
        pa, pb = u[rows, win[:, :half]], u[rows, win[:, half:]]
        # -- crossover: SBX or extended line recombination, per pair -------------------
        w = rng.random((n, half, 4))
        beta = np.where(w <= 0.5, (2.0 * w) ** expo, (0.5 / (1.0 - w)) ** expo)
        beta = np.where(rng.random((n, half, 4)) < 0.5, beta, 1.0)
        ext = o["line_ext"]
        alpha = rng.uniform(-ext, 1.0 + ext, size=(n, half, 1))
        sbx = rng.random((n, half, 1)) < o["p_sbx"]
        c1 = np.where(sbx, 0.5 * ((1 + beta) * pa + (1 - beta) * pb), pa + alpha * (pb - pa))
        c2 = np.where(sbx, 0.5 * ((1 - beta) * pa + (1 + beta) * pb), pb + alpha * (pa - pb))
        kids = np.concatenate([c1, c2], axis=1)
        # -- mutation: multi-scale steps, shrinking over the generations ---------------
        sigma = o["sigma0"] / (1.0 + g / o["sigma_half"])
        step = sigma * 10.0 ** (-o["decades"] * rng.random((n, pop, 4))) \
            * rng.standard_normal((n, pop, 4))
        kids = kids + np.where(rng.random((n, pop, 4)) < o["p_mut"], step, 0.0)
        kids, kfit = repair_and_score(kids, arrs)
        if o["crowding"]:
            k1, k2 = kids[:, :half], kids[:, half:]
            f1, f2 = kfit[:, :half], kfit[:, half:]
            dist = lambda x, y: np.sum((x - y) ** 2, axis=-1)  # noqa: E731
            cross = dist(k1, pa) + dist(k2, pb) > dist(k1, pb) + dist(k2, pa)
            ka = np.where(cross[..., None], k2, k1)
            kb = np.where(cross[..., None], k1, k2)
            fa = np.where(cross, f2, f1)
            fb = np.where(cross, f1, f2)
            ia, ib = win[:, :half], win[:, half:]
            fpa = np.take_along_axis(fit, ia, axis=1)
            fpb = np.take_along_axis(fit, ib, axis=1)
            ra_ = fa <= fpa
            rb_ = fb <= fpb
            u = u.copy()
            fit = fit.copy()
            u[rows, ia] = np.where(ra_[..., None], ka, pa)
            u[rows, ib] = np.where(rb_[..., None], kb, pb)
            fit[rows, ia] = np.where(ra_, fa, fpa)
            fit[rows, ib] = np.where(rb_, fb, fpb)
            # keep the best individual first (the stall rule and the result read u[:, 0])
            j = np.argmin(fit, axis=1)
            u[:, [0]], u[rows, j[:, None]] = u[rows, j[:, None]], u[:, [0]]
            fit[:, [0]], fit[rows, j[:, None]] = fit[rows, j[:, None]], fit[:, [0]]
        # -- survivors: best of parents + offspring ------------------------------------
        else:
            allu = np.concatenate([u, kids], axis=1)
            allf = np.concatenate([fit, kfit], axis=1)
            order = np.argsort(allf, axis=1, kind="stable")
            if o["dedup"]:
                # exact clones (same fitness as the better neighbour) go to the back: keeps
                # the population diverse instead of filling it with copies of the elite
                fs = np.take_along_axis(allf, order, axis=1)
                dup = np.concatenate([np.zeros((n, 1), bool), fs[:, 1:] == fs[:, :-1]], axis=1)
                order = np.take_along_axis(order, np.argsort(dup, axis=1, kind="stable"), axis=1)
            keep = order[:, :pop]
            u = np.take_along_axis(allu, keep[..., None], axis=1)
            fit = np.take_along_axis(allf, keep, axis=1)
        # -- stall rule ----------------------------------------------------------------
        best = fit[:, 0]
        if g > stall:
            hist[:, :-1] = hist[:, 1:]
        hist[:, min(g, stall)] = best
        ref = np.maximum(best, 1e-3 * fzero[act])
        stalled = (g >= stall) & (hist[:, 0] - best <= function_tolerance * ref)
        done = stalled | (g >= max_generations)
        if done.any():
            ix = act[done]
            best_u[ix] = u[done, 0]
            out_conv[ix] = stalled[done]
            out_iter[ix] = g
            left = ~done
            act, u, fit, hist = act[left], u[left], fit[left], hist[left]
            arrs = cell_arrays(act)
            rows = np.arange(act.size)[:, None]
        if progress is not None:
            progress(g, max_generations)

    x = lo + best_u * width
    return _result(data, np.exp(x[:, 0]), np.exp(x[:, 1]), x[:, 2], x[:, 3],
                   out_conv, out_iter, "ga")


# --------------------------------------------------------------------------------------
# Levenberg-Marquardt with a casadi Jacobian
# --------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _lm_cell_function(n_t: int):
    """casadi Function for one cell: (z, t, d, w, t0) -> (residual, Jacobian).

    z = (log tau_fast, log tau_slow, R_fast/s, R_slow/s); d = (R - R(t_0))/s on the
    mask, w = mask weights (0/1); residual_k = w_k (fitted_k - d_k).
    """
    import casadi as ca

    z = ca.SX.sym("z", 4)
    t = ca.SX.sym("t", n_t)
    d = ca.SX.sym("d", n_t)
    w = ca.SX.sym("w", n_t)
    t0 = ca.SX.sym("t0")
    tf, ts = ca.exp(z[0]), ca.exp(z[1])
    # exp(-t0/tau) - exp(-t/tau) = exp(-t0/tau) (1 - exp(-(t - t0)/tau))
    phf = ca.exp(-t0 / tf) * (1 - ca.exp(-(t - t0) / tf))
    phs = ca.exp(-t0 / ts) * (1 - ca.exp(-(t - t0) / ts))
    res = w * (z[2] * phf + z[3] * phs - d)
    jac = ca.jacobian(res, z)
    return ca.Function("dcir_residual", [z, t, d, w, t0], [res, jac],
                       ["z", "t", "d", "w", "t0"], ["r", "J"])


@lru_cache(maxsize=64)
def _lm_mapped(n_t: int, n_cols: int):
    return _lm_cell_function(n_t).map(n_cols)


class _LmProblem:
    """All LM columns (cells x starts) evaluated together through the mapped casadi Function."""

    def __init__(self, data: _Data, cols: np.ndarray, b: Bounds):
        self.cols = cols                                    # cell index of every column
        self.s = data.scale[cols]
        self.t = np.ascontiguousarray(data.tm[cols].T)      # (n_t, N) for casadi
        self.d = np.ascontiguousarray((data.d[cols] / self.s[:, None]).T)
        self.w = np.ascontiguousarray(data.mask[cols].T.astype(np.float64))
        self.t0 = data.t0[cols][None, :]
        self.ra = data.ra[cols] / self.s                    # pinned R, scaled
        self.n_t = data.t.size
        self.fn = _lm_mapped(self.n_t, cols.size)
        self.lo = np.stack([np.full(cols.size, np.log(b.tau_fast_s[0])),
                            np.full(cols.size, np.log(b.tau_slow_s[0])),
                            b.r_fast_ohm[0] / self.s, b.r_slow_ohm[0] / self.s], axis=1)
        self.hi = np.stack([np.full(cols.size, np.log(b.tau_fast_s[1])),
                            np.full(cols.size, np.log(b.tau_slow_s[1])),
                            b.r_fast_ohm[1] / self.s, b.r_slow_ohm[1] / self.s], axis=1)

    def eval(self, z):
        r, jac = self.fn(z.T, self.t, self.d, self.w, self.t0)
        r = r.full().T                                                  # (N, n_t)
        jac = jac.full().reshape(self.n_t, -1, 4).transpose(1, 0, 2)    # (N, n_t, 4)
        return r, jac

    def project(self, z):
        """Feasible point near z: box, tau_fast < tau_slow (swap branches), R0 >= 0."""
        z = np.clip(z, self.lo, self.hi)
        sw = z[:, 0] > z[:, 1]
        zs = z[:, [1, 0, 3, 2]]
        sw &= np.all((zs >= self.lo) & (zs <= self.hi), axis=1)
        z = np.where(sw[:, None], zs, z)
        gap = z[:, 1] - z[:, 0]
        tight = gap < 2 * _LOG_GAP
        if tight.any():   # separate the taus symmetrically, then re-clip
            mid = 0.5 * (z[:, 0] + z[:, 1])
            z[:, 0] = np.where(tight, mid - _LOG_GAP, z[:, 0])
            z[:, 1] = np.where(tight, mid + _LOG_GAP, z[:, 1])
            z = np.clip(z, self.lo, self.hi)
        t0 = self.t0[0]
        gf, gs = -np.expm1(-t0 / np.exp(z[:, 0])), -np.expm1(-t0 / np.exp(z[:, 1]))
        load = z[:, 2] * gf + z[:, 3] * gs
        over = load > self.ra
        k = np.where(over, np.maximum(self.ra, 0.0) / np.where(over, load, 1.0), 1.0)
        z[:, 2] = np.maximum(z[:, 2] * k, self.lo[:, 2])
        z[:, 3] = np.maximum(z[:, 3] * k, self.lo[:, 3])
        return z

    def linear_r(self, sl: slice, lf, ls):
        """Least-squares R_fast/s, R_slow/s for fixed taus on columns ``sl`` (LM starts)."""
        t0 = self.t0[0][sl, None]
        t = self.t.T[sl]
        w = self.w.T[sl]
        pf = _phi(t, t0, np.exp(lf)[:, None]) * w
        ps = _phi(t, t0, np.exp(ls)[:, None]) * w
        d = self.d.T[sl]
        a11, a12, a22 = (pf * pf).sum(1), (pf * ps).sum(1), (ps * ps).sum(1)
        b1, b2 = (pf * d).sum(1), (ps * d).sum(1)
        ridge = 1e-9 * (a11 + a22) + 1e-300
        a11, a22 = a11 + ridge, a22 + ridge
        det = a11 * a22 - a12 * a12
        return (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det

    def to_params(self, z, ix):
        """(tau_fast, tau_slow, R_fast, R_slow) of the columns ``ix``."""
        s = self.s[ix]
        return np.exp(z[:, 0]), np.exp(z[:, 1]), z[:, 2] * s, z[:, 3] * s


def _lm_iterate(prob: _LmProblem, z, max_iterations: int, progress: Progress | None,
                xtol=1e-10, ftol=1e-12, gtol=1e-12, ctol=1e-26):
    """Projected Levenberg-Marquardt (Eq. 8) with Nielsen's mu update, all columns at once."""
    n = z.shape[0]
    eye = np.eye(4)
    r, jac = prob.eval(z)
    cost = 0.5 * np.sum(r * r, axis=1)
    a = np.einsum("nki,nkj->nij", jac, jac)
    mu = 1e-3 * np.max(np.diagonal(a, axis1=1, axis2=2), axis=1) + 1e-12
    nu = np.full(n, 2.0)
    active = np.isfinite(cost)
    conv = np.zeros(n, bool)
    iters = np.zeros(n, np.int64)
    for it in range(1, max_iterations + 1):
        if not active.any():
            break
        g = np.einsum("nk,nki->ni", r, jac)
        a = np.einsum("nki,nkj->nij", jac, jac)
        # projected gradient (box only): zero where a bound blocks the descent
        blocked = ((z <= prob.lo) & (g > 0)) | ((z >= prob.hi) & (g < 0))
        small_grad = np.max(np.abs(np.where(blocked, 0.0, g)), axis=1) <= gtol
        # active set: a variable held at its bound by the gradient stays there, and the
        # step of the others is solved with it fixed (projected Newton, Bertsekas)
        free = ~blocked
        pair = free[:, :, None] & free[:, None, :]
        m = np.where(pair, a, 0.0) + np.where(free, mu[:, None], 1.0)[:, :, None] * eye
        h = np.linalg.solve(m, np.where(free, -g, 0.0)[..., None])[..., 0]
        z_try = prob.project(z + h)
        step = z_try - z
        r_try, jac_try = prob.eval(z_try)
        cost_try = 0.5 * np.sum(r_try * r_try, axis=1)
        pred = -(np.einsum("ni,ni->n", g, step)
                 + 0.5 * np.einsum("ni,nij,nj->n", step, a, step))
        ared = cost - cost_try
        accept = active & np.isfinite(cost_try) & (ared > 0)
        rho = np.where(pred > 0, ared / np.where(pred > 0, pred, 1.0), 0.0)
        small_step = np.linalg.norm(step, axis=1) <= xtol * (np.linalg.norm(z, axis=1) + xtol)
        small_red = accept & (ared <= ftol * cost) & (np.abs(pred) <= ftol * cost)
        # updates (frozen where inactive)
        z = np.where(accept[:, None], z_try, z)
        r = np.where(accept[:, None], r_try, r)
        jac = np.where(accept[:, None, None], jac_try, jac)
        cost = np.where(accept, cost_try, cost)
        mu_acc = mu * np.maximum(1 / 3, 1 - (2 * rho - 1) ** 3)
        mu = np.where(accept, mu_acc, np.where(active, mu * nu, mu))
        nu = np.where(accept, 2.0, np.where(active, nu * 2, nu))
        iters = np.where(active, it, iters)
        stop = active & (small_grad | small_step | small_red | (cost <= ctol)
                         | ~np.isfinite(mu) | (mu > 1e300))
        good = stop & (small_grad | small_step | small_red | (cost <= ctol))
        conv |= good
        active &= ~stop
        if progress is not None:
            progress(it, max_iterations)
    return z, cost, conv, iters


# fractions of the log-tau ranges used by the deterministic multi-start
_START_FAST = (0.15, 0.4, 0.65)
_START_SLOW = (0.35, 0.6, 0.85)


def fit_lm(t_s, r_ohm, *, bounds: Bounds | None = None, x0: PointFit | None = None,
           max_iterations: int = 200, progress: Progress | None = None) -> PointFit:
    """Levenberg-Marquardt fit of every cell at once (paper Eqs. 6-8).

    The residual and its Jacobian come from one casadi SX Function for a single
    cell, mapped over all columns (cells x starts) and evaluated once per
    iteration; the step x <- P(x - (J'J + mu I)^-1 J'r) is solved in numpy for all
    columns together, P being the projection on the constraints (box, tau_fast <
    tau_slow, R0 >= 0). Variables are scaled: log tau, R / (largest |R(t) - R(t_0)|
    of the cell). mu follows Nielsen's rule. A cell stops on a small step, a small
    projected gradient, a negligible relative cost reduction, or an (almost) exact
    fit; hitting ``max_iterations`` is reported as not converged.

    Start: ``x0`` (e.g. the GA result) where it has finite parameters, otherwise a
    deterministic multi-start over log-spaced (tau_fast, tau_slow) pairs with
    least-squares R's; the start with the lowest squared error wins. When started
    from ``x0``, a cell whose LM result has a worse Eq.-5 fitness than ``x0`` (LM
    minimises squares, Eq. 5 is absolute values) keeps ``x0`` (projected on the
    constraints), so the result is never worse than the start in Eq. 5.
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

    x0_params = None
    from_x0 = np.zeros(n_c, bool)
    if x0 is not None:
        if not isinstance(x0, PointFit):
            raise TypeError("x0 must be a PointFit")
        x0_params = np.stack([np.asarray(x0.tau_fast_s, float), np.asarray(x0.tau_slow_s, float),
                              np.asarray(x0.r_fast_ohm, float), np.asarray(x0.r_slow_ohm, float)],
                             axis=1)
        if x0_params.shape[0] != n_c:
            raise ValueError(f"x0 has {x0_params.shape[0]} cells, the table has {n_c}")
        from_x0 = np.all(np.isfinite(x0_params), axis=1) & (x0_params[:, 0] > 0) \
            & (x0_params[:, 1] > 0) & data.ok

    # columns: one per x0-started cell, len(pairs) per multi-started cell
    lf_lo, lf_hi = np.log(b.tau_fast_s)
    ls_lo, ls_hi = np.log(b.tau_slow_s)
    pairs = [(lf_lo + qf * (lf_hi - lf_lo), ls_lo + qs * (ls_hi - ls_lo))
             for qf in _START_FAST for qs in _START_SLOW]
    pairs = [(f, s) for f, s in pairs if s - f > np.log(1.5)] or \
        [(lf_lo + 0.3 * (lf_hi - lf_lo), ls_lo + 0.7 * (ls_hi - ls_lo))]
    multi = cells[~from_x0[cells]]
    single = cells[from_x0[cells]]
    cols = np.concatenate([single, np.repeat(multi, len(pairs))])
    prob = _LmProblem(data, cols, b)

    z = np.empty((cols.size, 4))
    ns = single.size
    if ns:
        p = x0_params[single]
        z[:ns] = np.stack([np.log(p[:, 0]), np.log(p[:, 1]),
                           p[:, 2] / prob.s[:ns], p[:, 3] / prob.s[:ns]], axis=1)
    if multi.size:
        lf = np.tile([p[0] for p in pairs], multi.size)
        ls = np.tile([p[1] for p in pairs], multi.size)
        sl = slice(ns, None)
        z[sl, 0], z[sl, 1] = lf, ls
        z[sl, 2], z[sl, 3] = prob.linear_r(sl, lf, ls)
    z = prob.project(z)
    z_start = z.copy()
    z, cost, cconv, citers = _lm_iterate(prob, z, int(max_iterations), progress)

    # best start per multi-started cell (lowest squared error; first on ties)
    if multi.size:
        k = len(pairs)
        c_m = cost[ns:].reshape(multi.size, k)
        c_m = np.where(np.isfinite(c_m), c_m, np.inf)
        pick = ns + np.arange(multi.size) * k + np.argmin(c_m, axis=1)
    else:
        pick = np.zeros(0, np.int64)
    chosen = np.concatenate([np.arange(ns), pick]).astype(np.int64)
    target = cols[chosen]
    params = np.stack(prob.to_params(z[chosen], chosen), axis=1)
    out[target] = params
    conv[target] = cconv[chosen]
    iters[target] = citers[chosen]

    if ns:
        # never worse than the start in Eq. 5: keep x0 (as given if it is feasible)
        start = np.stack(prob.to_params(z_start[:ns], np.arange(ns)), axis=1)
        given = x0_params[single]
        feasible = np.all(np.isclose(start, given, rtol=1e-12, atol=0.0), axis=1)
        start = np.where(feasible[:, None], given, start)
        sub = _prepare(data.t, data.r[single])
        f_lm = _eq5(sub, *out[single].T)
        f_st = _eq5(sub, *start.T)
        worse = ~(f_lm <= f_st)
        out[single[worse]] = start[worse]
    return _result(data, *out.T, conv, iters, "lm")
