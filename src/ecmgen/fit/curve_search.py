"""The time-constant search of the whole-test fit (:mod:`ecmgen.fit.curve`, its module
docstring says why): every combination of a log grid per branch solved on blocks of one
Gram matrix, then Nelder-Mead in log tau from the grid's best point and from its best
point favouring slow dynamics, and the tie-break between the local minima found."""

from __future__ import annotations

import numpy as np

from .curve_record import side_by_side
from .lsq import log_grid, nelder_mead

TIE = 1e-2                 # local minima within this (relative objective) are equally good
SLOW_START = 0.02          # grid start favouring slow dynamics: objective tilt per ln(tau)
NM_EVALS = 60              # exact evaluations per local refinement


def _grid_evaluations(prob, kinds: list, grids: dict, lay) -> dict:
    """The fit at every grid point with tau_fast < tau_slow < tau_diff, from one Gram
    matrix of every grid block side by side: rounded log taus -> (x, objective)."""
    # every grid block side by side, each made as it is copied in (no block list beside it)
    z = side_by_side((prob.block(k, tau) if k else prob.r0w for k, tau in
                      [(None, None)] + [(k, tau) for k in kinds for tau in grids[k]]),
                     [prob.r0w.shape[1]] + [prob.width(k) for k in kinds for _ in grids[k]])
    gram = z.T @ z
    g = z.T @ prob.yw
    del z
    width = {k: prob.width(k) for k in kinds}
    start, off = {}, prob.r0w.shape[1]
    for k in kinds:
        start[k] = off
        off += width[k] * grids[k].size
    base = np.arange(prob.r0w.shape[1])
    evals: dict = {}
    for ix in np.ndindex(*(grids[k].size for k in kinds)):
        logt = np.log([grids[k][ix[n]] for n, k in enumerate(kinds)])
        if np.any(np.diff(logt) <= 0):
            continue
        c = np.concatenate([base] + [start[k] + ix[n] * width[k] + np.arange(width[k])
                                     for n, k in enumerate(kinds)])
        evals[tuple(np.round(logt, 9))] = prob.solve(gram[np.ix_(c, c)], g[c], lay)
    return evals


def search(prob, ranges: dict, progress=None):
    """The time constants of a whole-test fit's problem (:mod:`ecmgen.fit.curve`): grid over cached unit responses, local
    refinement from the grid's best point and from the best point favouring slow dynamics,
    then the tie-break between the local minima found. Returns (taus dict, x, objective,
    number of evaluations, notes)."""
    kinds = list(ranges)
    grids = {k: log_grid(*ranges[k]) for k in kinds}
    lay = prob.layout(kinds)
    evals = _grid_evaluations(prob, kinds, grids, lay)
    if not evals:
        raise ValueError("the time-constant ranges leave no tau_fast < tau_slow < tau_diff")
    if progress:
        progress(1, 3)

    def exact(logt):
        key = tuple(np.round(logt, 9))
        if key not in evals:
            taus = np.exp(logt)
            if np.any(np.diff(logt) <= 0):
                evals[key] = (None, np.inf)
            else:
                evals[key] = prob.solve(*prob.normal(kinds, prob.taus_met(kinds, taus)), lay)
        return key, evals[key][1]

    lo = np.log([ranges[k][0] for k in kinds])
    hi = np.log([ranges[k][1] for k in kinds])
    step = np.array([np.log(grids[k][1] / grids[k][0]) for k in kinds])

    def refine(here):
        """Nelder-Mead in log tau from a grid point (simplex of one grid step)."""
        best = nelder_mead(lambda z: exact(np.clip(z, lo, hi))[1], here, step, NM_EVALS,
                           xtol=0.002, ftol=1e-5)
        return exact(np.clip(best, lo, hi))[0]

    grid_keys = list(evals)
    c_ref = min(evals[k][1] for k in grid_keys)
    best = min(grid_keys, key=lambda k: evals[k][1])
    # the grid's best when slow dynamics are favoured (a start for the search only)
    slow = min(grid_keys, key=lambda k: evals[k][1] / c_ref - SLOW_START * sum(k[1:]))
    found = [refine(np.array(best))]
    if np.any(np.abs(np.array(slow) - np.array(found[0])) > 1.01 * step):
        found.append(refine(np.array(slow)))          # a start outside the first's basin
    found = sorted(set(found), key=lambda k: evals[k][1])
    if progress:
        progress(2, 3)
    # tie-break: of local minima within TIE of the best, the slowest (see module docstring)
    c_best = evals[found[0]][1]
    close = [k for k in found if evals[k][1] <= (1.0 + TIE) * c_best]
    key = max(close, key=lambda k: sum(k[1:]))
    notes = []
    if len(found) > 1:
        other = [k for k in found if k != key][0]
        d = 100.0 * (evals[other][1] / evals[key][1] - 1.0)
        notes.append("curve: two local minima of the fit, tau_slow "
                     f"{np.exp(key[1]):.3g} s / {np.exp(other[1]):.3g} s "
                     f"(objective {'+' if d >= 0 else ''}{d:.2f} % for the second): "
                     f"{'the slower one is kept (within ' + f'{100 * TIE:g} %)' if key != found[0] else 'the better one is kept'}")
    x, cost = evals[key]
    if prob.r0_held.size:      # the chosen time constants' fit with r0 held
        gram, g = prob.normal(kinds, prob.taus_met(kinds, np.exp(key)))
        x, cost = prob.solve(gram, g, lay, hold_r0=True)
    prob.drop_design_buffers()
    return dict(zip(kinds, np.exp(np.array(key)))), x, cost, len(evals), notes
