"""``fit_ga``: the paper's GA on Eq. 5, every cell of a DC-IR table at once.

The curve, the constraints and Eq. 5 are described in :mod:`ecmgen.fit.points`. The GA
evolves (log tau_fast, log tau_slow, R_fast, R_slow) and sets the two resistances of
every individual to their exact L1 optimum for its taus (``_l1_resistances``: vertex
enumeration for a handful of points, reweighted least squares for dense curves).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..parallel import one_blas_thread
from .points import (_LOG_GAP, Bounds, PointFit, Progress, _bounds_for, _clip_params, _phi,
                     _prepare, _result)

_PENALTY = 1e3            # GA: fitness penalty per ohm of constraint violation


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


def _repair_and_score(u, arrs, space):
    """Repaired genes and their fitness (Eq. 5 plus constraint penalties); ``space`` is
    (lo, hi, width, the resistances' box, exact L1 resistances)."""
    lo, hi, width, box, exact = space
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


def _offspring(rng, u, fit, rows, g: int, expo: float, o: dict):
    """One generation's offspring of the population ``u`` (cells x pop x 4 genes in
    [0, 1]) with fitness ``fit``: tournament selection, crossover, mutation (the draws in
    a fixed order: same seed, same offspring)."""
    n, pop = fit.shape
    half = pop // 2
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
    return kids


def _survivors(u, fit, kids, kfit, pop: int):
    """The best ``pop`` of parents and offspring per cell (their genes and fitness)."""
    n = u.shape[0]
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
    return u, fit


@one_blas_thread
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

    Long: most of it is this docstring, the method's reference (paper Eq. 5).
    """
    data = _prepare(t_s, r_ohm)
    b = _bounds_for(data, bounds)
    pop = int(population)
    if pop < 4:
        raise ValueError("population must be at least 4")
    pop += pop % 2
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
    space = (lo, hi, width, (lo[2], hi[2], lo[3], hi[3]), exact)

    arrs = cell_arrays(act)
    u, fit = _repair_and_score(rng.random((act.size, pop, 4)), arrs, space)
    fzero = np.sum(np.abs(data.d), axis=1)     # Eq. 5 of the zero model, per cell
    hist = np.full((act.size, stall + 1), np.inf)
    hist[:, 0] = fit.min(axis=1)
    rows = np.arange(act.size)[:, None]
    expo = 1.0 / (o["eta_c"] + 1.0)

    g = 0
    while act.size and g < max_generations:
        g += 1
        kids = _offspring(rng, u, fit, rows, g, expo, o)
        kids, kfit = _repair_and_score(kids, arrs, space)
        u, fit = _survivors(u, fit, kids, kfit, pop)
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
