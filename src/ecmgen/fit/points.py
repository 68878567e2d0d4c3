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
         (arrays (n_cells, pop, 4)); minimises Eq. 5 (exactly-solved resistances for
         each individual's taus); MATLAB-``ga``-like stall rule.
fit_lm   Levenberg-Marquardt (paper Eqs. 6-8, x <- x - (J'J + mu I)^-1 J'r) on the
         squared residuals with a casadi residual/Jacobian mapped over all cells;
         Nielsen's adaptive mu; scaled variables (log tau, branch amplitudes in
         units of the data); never worse than its x0 in Eq. 5.

Note on Table 1 of the paper: no curve of this form through the first point gets
within ~32 uOhm of all five points (whatever the parameters), so the fits there
differ from the data by 42 uOhm (LM) / 91 uOhm (GA's L1 optimum) at one point.

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
        rise = float(np.max(np.where(valid, r - anchor[:, None], -np.inf)))
        if not rise > 0:
            rise = float(np.max(np.abs(r[valid])))
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
    # rounding only: at an active constraint R0 = 0 comes out a few ulps of R(t_0) off,
    # of either sign; snap it to exactly 0. Above 0 only by ulps of R(t_0): a GA stall
    # at R0 ~ 1e-14 R(t_0) is a fitted value that the curve R(t_0) depends on.
    tiny = 1e-12 * np.maximum(np.abs(data.ra), data.scale)
    ulps = 4 * np.spacing(np.abs(data.ra))
    r0 = np.where((r0 > -tiny) & (r0 < ulps), 0.0, r0)
    fitness = np.where(ok, _eq5(data, tf, ts, rf, rs), np.nan)
    return PointFit(r0_ohm=r0, r_fast_ohm=rf, tau_fast_s=tf, r_slow_ohm=rs, tau_slow_s=ts,
                    fitness_ohm=fitness, converged=np.asarray(converged, bool) & ok,
                    iterations=np.asarray(iterations, dtype=np.int64), method=method)


def _clip_params(b: Bounds, tf, ts, rf, rs):
    """Params clipped to the box: removes exp(log(tau)) rounding at an active bound."""
    return (np.clip(tf, *b.tau_fast_s), np.clip(ts, *b.tau_slow_s),
            np.clip(rf, *b.r_fast_ohm), np.clip(rs, *b.r_slow_ohm))


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
_IRLS_SWEEPS = 8          # beyond: reweighted least-squares sweeps


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
        res = x[..., None] * pf[..., None, :]
        res += y[..., None] * ps[..., None, :]
        res -= d[..., None, :]
        np.abs(res, out=res)
        obj = np.where(ok, np.einsum("...cn,...n->...c", res, mask.astype(np.float64)), np.inf)
        k = np.argmin(obj, axis=-1)[..., None]
        found = np.isfinite(np.take_along_axis(obj, k, axis=-1)[..., 0])
        x = np.where(found, np.take_along_axis(x, k, axis=-1)[..., 0], xl)
        y = np.where(found, np.take_along_axis(y, k, axis=-1)[..., 0], yl)
        return x, y
    w = mask.astype(np.float64)
    eps = 1e-6 * np.asarray(scale)[..., None]
    sweeps = _IRLS_SWEEPS
    for sweep in range(sweeps + 1):
        a11, a12, a22 = (w * pf * pf).sum(-1), (w * pf * ps).sum(-1), (w * ps * ps).sum(-1)
        b1, b2 = (w * pf * d).sum(-1), (w * ps * d).sum(-1)
        ridge = 1e-12 * (a11 + a22) + 1e-300
        a11, a22 = a11 + ridge, a22 + ridge
        det = a11 * a22 - a12 * a12
        x, y = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
        if sweep < sweeps:
            w = mask / np.maximum(np.abs(d - x[..., None] * pf - y[..., None] * ps), eps)
    x, y = np.clip(x, xl, xh), np.clip(y, yl, yh)
    load = cf * x + cs * y
    over = load > ra
    k = np.where(over, np.maximum(ra, 0.0) / np.where(over, load, 1.0), 1.0)
    return np.maximum(x * k, xl), np.maximum(y * k, yl)


# --------------------------------------------------------------------------------------
# genetic algorithm
# --------------------------------------------------------------------------------------
_GA = dict(eta_c=2.0, p_sbx=0.5, line_ext=0.5, p_mut=0.5, sigma0=0.2, sigma_half=100.0,
           decades=5.0, floor=1e-3)


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
    * repair and evaluation: clip to the box, order the taus (swap), then set the two
      resistance genes to their exact Eq.-5 optimum for the individual's taus under
      the box and R0 >= 0 (Lamarckian inner solve, see ``_l1_resistances``); what
      repair cannot fix is penalised;
    * survivors: the paper's BestFit(P, P_new): the best ``population`` of parents
      plus offspring (elitist), exact clones moved behind distinct individuals.

    Why the inner solve: for fixed taus Eq. 5 is a convex piecewise-linear function of
    (R_fast, R_slow), whose minimum is cheap to find exactly, while in all four genes
    the optimum of Eq. 5 lies on narrow curved kinks (several residuals zero at once)
    that a GA with coordinate-wise operators cannot follow: without it the GA stalled
    at 105-130 uOhm on the paper's Table 1 (optimum 100.1 uOhm) for every seed and
    population tried. The GA still evolves all four genes; only its evaluation of an
    individual includes the optimal resistances.

    Stopping rule per cell (MATLAB ``ga`` FunctionTolerance in spirit): the best
    fitness improved by at most ``function_tolerance`` x max(best fitness, 1e-3 x
    the fitness of the zero model R_fast = R_slow = 0) over the last
    ``stall_generations`` generations (the floor keeps the rule meaningful when the
    data can be matched exactly and the best fitness tends to zero).
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
        rf, rs = _l1_resistances(pf, ps, d, mask, cf, cs, ra, box, scale, exact)
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
        # -- survivors: best of parents + offspring; exact clones (same fitness as the
        #    better neighbour) go to the back so the elite does not fill the population
        allu = np.concatenate([u, kids], axis=1)
        allf = np.concatenate([fit, kfit], axis=1)
        order = np.argsort(allf, axis=1, kind="stable")
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
        ref = np.maximum(best, o["floor"] * fzero[act])
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
    params = _clip_params(b, np.exp(x[:, 0]), np.exp(x[:, 1]), x[:, 2], x[:, 3])
    return _result(data, *params, out_conv, out_iter, "ga")


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
        lo, hi = prob.box(zi, ix)
        g = np.einsum("nik,nk->ni", ji, ri)
        a = np.einsum("nik,njk->nij", ji, ji)
        # box active set: a variable held at its bound by the gradient stays there
        blocked = ((zi <= lo) & (g > 0)) | ((zi >= hi) & (g < 0))
        free = ~blocked
        m = np.where(free[:, :, None] & free[:, None, :], a, 0.0) \
            + np.where(free, mu[ix, None], 1.0)[:, :, None] * eye
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
        # never worse than the start in Eq. 5: keep x0 (as given if it is feasible)
        start = np.stack(_clip_params(b, *prob.to_params(z_start[:ns], np.arange(ns))), axis=1)
        given = x0_params[single]
        feasible = np.all(np.isclose(start, given, rtol=1e-12, atol=0.0), axis=1)
        start = np.where(feasible[:, None], given, start)
        sub = _prepare(data.t, data.r[single])
        f_lm = _eq5(sub, *out[single].T)
        f_st = _eq5(sub, *start.T)
        worse = ~(f_lm <= f_st)
        out[single[worse]] = start[worse]
    return _result(data, *out.T, conv, iters, "lm")
