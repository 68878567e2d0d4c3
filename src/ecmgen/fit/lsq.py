"""Small numerical pieces of the whole-test fit (:mod:`ecmgen.fit.curve`): bounded least
squares on the normal equations with free (unbounded) unknowns, and quadratic response
surfaces for the search over time constants."""

from __future__ import annotations

import numpy as np


def solve_bounded(m: np.ndarray, q: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """min 1/2 x'Mx - q'x subject to x >= 0 except where ``free`` (M symmetric positive
    definite): the free unknowns are eliminated (Schur complement), the rest solved by
    Lawson-Hanson (:func:`nnls_gram`)."""
    if free is None or not free.any():
        return nnls_gram(m, q)
    f, c = np.flatnonzero(free), np.flatnonzero(~free)
    a, b = _free_blocks(m, f, c)
    try:
        ai_b = np.linalg.solve(a, np.column_stack([b, q[f]]))
    except np.linalg.LinAlgError:
        ai_b = np.linalg.lstsq(a, np.column_stack([b, q[f]]), rcond=None)[0]
    red = m[np.ix_(c, c)] - b.T @ ai_b[:, :-1]
    xc = nnls_gram(0.5 * (red + red.T), q[c] - b.T @ ai_b[:, -1])
    x = np.zeros(q.size)
    x[c] = xc
    x[f] = ai_b[:, -1] - ai_b[:, :-1] @ xc
    return x


def _free_blocks(m: np.ndarray, f: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """M's free-free block (a state that no row sees, decayed before the next row, has a
    zero column: its diagonal lifted by a hair so it solves to 0) and its free-bounded one."""
    a = m[np.ix_(f, f)]
    a = a + np.eye(f.size) * (1e-12 * max(float(np.max(np.diag(a))), 0.0) + 1e-300)
    return a, m[np.ix_(f, c)]


def solve_bounded_many(systems: list, free: np.ndarray) -> np.ndarray:
    """:func:`solve_bounded` of several (M, q) whose free rows are the same (M[free, :] and
    q[free]; the penalties of the smoothing weights sit on bounded unknowns only): the free
    unknowns are eliminated once, the reduced systems solved side by side, and only those
    whose solution is not already >= 0 go through Lawson-Hanson. Each result is exactly
    :func:`solve_bounded`'s. Returns (n_systems, n)."""
    m0, q0 = systems[0]
    f, c = np.flatnonzero(free), np.flatnonzero(~free)
    if not f.size or not c.size or any(not np.array_equal(m[f], m0[f]) or
                                       not np.array_equal(q[f], q0[f]) for m, q in systems[1:]):
        return np.stack([solve_bounded(m, q, free) for m, q in systems])
    a, b = _free_blocks(m0, f, c)
    try:
        ai_b = np.linalg.solve(a, np.column_stack([b, q0[f]]))
    except np.linalg.LinAlgError:
        return np.stack([solve_bounded(m, q, free) for m, q in systems])
    bt_ai_b = b.T @ ai_b[:, :-1]
    bt_ai_q = b.T @ ai_b[:, -1]
    reds, rhss = [], []
    for m, q in systems:
        red = m[np.ix_(c, c)] - bt_ai_b
        reds.append(0.5 * (red + red.T))
        rhss.append(q[c] - bt_ai_q)
    try:
        first = np.linalg.solve(np.stack(reds), np.stack(rhss)[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        first = None
    out = np.zeros((len(systems), q0.size))
    for k, (red, rhs) in enumerate(zip(reds, rhss)):
        xc = first[k] if first is not None and np.all(first[k] >= 0) else nnls_gram(red, rhs)
        out[k, c] = xc
        out[k, f] = ai_b[:, -1] - ai_b[:, :-1] @ xc
    return out


def nnls_gram(m: np.ndarray, q: np.ndarray, max_iter: int | None = None) -> np.ndarray:
    """min 1/2 x'Mx - q'x subject to x >= 0 (M symmetric positive definite): Lawson-Hanson
    active set on the normal equations, started from the positive part of the
    unconstrained solution."""
    n = q.size
    tol = 1e-12 * max(float(np.max(np.abs(q))), 1e-300)
    try:
        z = np.linalg.solve(m, q)
    except np.linalg.LinAlgError:
        z = np.linalg.lstsq(m, q, rcond=None)[0]
    if np.all(z >= 0):
        return z
    passive = z > 0
    x = np.where(passive, z, 0.0)
    if passive.any():
        x = feasible(m, q, x, passive)
        passive = x > 0
    for _ in range(max_iter or 3 * n):
        grad = q - m @ x
        cand = np.where(~passive, grad, -np.inf)
        j = int(np.argmax(cand))
        if cand[j] <= tol:
            break
        passive[j] = True
        x = feasible(m, q, x, passive)
        passive = x > 0
    return x


def feasible(m, q, x, passive):
    """Inner loop of Lawson-Hanson: move from feasible x towards the passive-set solution,
    dropping variables that reach zero, until that solution is positive."""
    for _ in range(passive.size + 1):
        ix = np.flatnonzero(passive)
        z = np.zeros_like(x)
        if ix.size:
            z[ix] = np.linalg.solve(m[np.ix_(ix, ix)], q[ix])
        if np.all(z[ix] > 0):
            return z
        bad = ix[z[ix] <= 0]
        step = x[bad] / np.maximum(x[bad] - z[bad], 1e-300)
        k = int(np.argmin(step))
        x = x + float(step[k]) * (z - x)
        x[bad[k]] = 0.0
        passive = passive & (x > 1e-14 * max(float(np.max(np.abs(x))), 1e-300))
        x[~passive] = 0.0
    return np.maximum(x, 0.0)


GRID_RATIO = 2.2      # between neighbouring points of a time-constant search grid


def log_grid(lo: float, hi: float, ratio: float = GRID_RATIO) -> np.ndarray:
    n = max(2, int(np.ceil(np.log(hi / lo) / np.log(ratio))) + 1)
    return np.geomspace(lo, hi, n)


def nelder_mead(f, x0: np.ndarray, step: np.ndarray, max_evals: int, xtol: float = 0.01,
                ftol: float = 0.0) -> np.ndarray:
    """Minimise f from x0 with Nelder-Mead (standard coefficients), initial simplex x0 +
    step along each axis; stops when the simplex is within xtol in every coordinate, or
    its values within ftol (relative) of each other, or after max_evals evaluations.
    Deterministic; returns the best point."""
    n = x0.size
    pts = [np.asarray(x0, dtype=np.float64)] + [x0 + step[k] * np.eye(n)[k] for k in range(n)]
    vals = [f(p) for p in pts]
    evals = n + 1
    while evals < max_evals:
        order = np.argsort(vals, kind="stable")
        pts = [pts[k] for k in order]
        vals = [vals[k] for k in order]
        if np.max(np.abs(np.array(pts[1:]) - pts[0])) <= xtol or \
                vals[-1] - vals[0] <= ftol * abs(vals[0]):
            break
        centre = np.mean(pts[:-1], axis=0)
        refl = centre + (centre - pts[-1])
        fr = f(refl)
        evals += 1
        if fr < vals[0]:
            exp_ = centre + 2.0 * (centre - pts[-1])
            fe = f(exp_)
            evals += 1
            pts[-1], vals[-1] = (exp_, fe) if fe < fr else (refl, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = refl, fr
        else:
            inside = fr >= vals[-1]
            con = centre + 0.5 * ((pts[-1] if inside else refl) - centre)
            fc = f(con)
            evals += 1
            if fc < min(fr, vals[-1]):
                pts[-1], vals[-1] = con, fc
            else:                                   # shrink towards the best
                for k in range(1, n + 1):
                    pts[k] = pts[0] + 0.5 * (pts[k] - pts[0])
                    vals[k] = f(pts[k])
                evals += n
    return pts[int(np.argmin(vals))]
