"""The pulse levels of a pulse test as the whole-test fit sees them (:mod:`ecmgen.fit.curve`):
the SOC nodes each direction's tables are free at, the levels rows belong to (for leaving one
out), the time-constant ranges the record can show, the choice of the smoothing weight by
leaving one level out, the r0 columns held beyond the levels that pin r0, and each level's
measured and fitted voltage (the fit plots)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..data.dcir import Pulse
from ..data.measure import TimeSeries, charging_direction
from .curve_record import hats
from .curve_cv import held_out_errors
from .lsq import GRID_RATIO
from .points import SOC_LEVEL_GAP, soc_levels

# candidate weights of the second-difference penalty (relative to the column scale); up to
# 1e3: on the Leaf's 1 mV-resolution tests the held-out optimum lies at 30-100
PENALTIES = tuple(10.0 ** np.arange(-6.0, 3.01, 0.5))
BOTH_WAYS_SHARE = 0.1  # a dynamic test's blocks are levels of a direction that moves this
                       # share of their charge (a drive profile's regen)
CV_TIE = 0.01      # held-out errors this close (relative) are one: the smoother is kept
# below this share of its run's largest value a resistance's penalty is on r, not ln r (ln r
# of a weakly pinned node slides towards 0 without bound: the Leaf's charge r_fast went to
# 0.02 mOhm at 0.01; 0.1 and 0.2 give the same tables on the three shared cells)
LOG_FLOOR = 0.1


def _clusters(socs: np.ndarray) -> list[np.ndarray]:
    """Indices grouped by SOC (falling): a group takes what is within SOC_LEVEL_GAP of its
    first member."""
    order = np.argsort(-socs, kind="stable")
    groups: list[list[int]] = []
    for k in order:
        if groups and abs(socs[groups[-1][0]] - socs[k]) <= SOC_LEVEL_GAP:
            groups[-1].append(int(k))
        else:
            groups.append([int(k)])
    return [np.array(g) for g in groups]


def pulse_mid_soc(p: Pulse, capacity_ah: float) -> float:
    """SOC half-way through the pulse (the level a pulse measures)."""
    return float(p.soc + 0.5 * p.current_a * p.duration_s / 3600.0 / capacity_ah)


def level_nodes(complete: list[Pulse], direction: str, capacity_ah: float) -> np.ndarray:
    """The SOC nodes of one direction's table: the mean mid-pulse SOC of each of its levels
    with a complete pulse, rising."""
    ps = [p for p in complete if p.direction == direction]
    if not ps:
        return np.zeros(0)
    mids = np.array([pulse_mid_soc(p, capacity_ah) for p in ps])
    nodes = np.array([mids[g].mean() for g in _clusters(np.array([p.soc for p in ps]))])
    return np.clip(np.sort(nodes), 0.0, 1.0)


def level_windows(complete: list[Pulse], t: np.ndarray, t_rec: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(SOC of each level of either direction, rising; the level each sample of ``t_rec``
    belongs to, -1 between levels). A level's samples run from the rest before its first
    pulse to the end of the relaxation after its last."""
    socs = np.array([p.soc for p in complete])
    groups = _clusters(socs)
    order = np.argsort([socs[g].mean() for g in groups])
    level = np.full(t_rec.size, -1)
    nodes = []
    for n, gi in enumerate(order):
        g = groups[gi]
        nodes.append(float(socs[g].mean()))
        t0 = t[min(complete[k].rest_index for k in g)]
        t1 = t[min(max(complete[k].next_start for k in g), t.size - 1)]
        level[(t_rec >= t0) & (t_rec <= t1)] = n
    return np.array(nodes), level


def data_tau_ranges(ranges: dict, sampling_s: float, relaxation_s: float,
                    pulse_s: float | None = None) -> tuple[dict, list]:
    """The search ranges cut to what the record can show: no time constant shorter than the
    sampling in the pulses, no slow or diffusion one longer than the longest relaxation
    after a current change; and a fast one as long as the longest pulse (``pulse_s``)
    where that is more than one grid step (GRID_RATIO) beyond the fast range: pulses that
    long show a pair that slow inside them (the Leaf's 30 s pulses: with tau_fast held at
    10 s its pair and the slow one traded resistance down to 0 at the ends of the SOC
    range; up to 30 s, no value near 0 and roughness 0.12 / 0.15 at 25 / 40 degC).
    Returns (ranges, notes)."""
    out, notes = {}, []
    for k, (lo, hi) in ranges.items():
        lo2 = max(lo, sampling_s) if k == "fast" else lo
        hi2 = min(hi, relaxation_s) if k in ("slow", "diff") and relaxation_s > 0 else hi
        if k == "fast" and pulse_s is not None and pulse_s > hi * GRID_RATIO:
            hi2 = pulse_s
        if hi2 <= lo2 * 1.5:          # nothing left to search: keep the configured range
            lo2, hi2 = lo, hi
        why = [w for w, moved in (("sampling", lo2 > lo * 1.01),
                                  ("longest pulse", hi2 > hi * 1.01),
                                  ("longest relaxation", hi2 < hi / 1.01)) if moved]
        if why:
            notes.append(f"curve: tau_{k} searched in {lo2:.3g} .. {hi2:.3g} s (the "
                         f"{' and the '.join(why)} of the test)")
        out[k] = (float(lo2), float(hi2))
    return out, notes


def choose_penalty(prob, z: np.ndarray, lay: dict, penalties=PENALTIES, normal=None
                   ) -> tuple[float, dict]:
    """The smoothing weight by leaving one SOC level out: for each candidate weight and
    level, fit on the other rows and measure the left-out level's rows after refitting only
    the free nuisance columns there (the OCV correction, restart states); ``normal``: (z'z,
    z'y), if known. Returns the weight (the largest within CV_TIE of the best) and
    {weight: held-out SSE}."""
    levels = [np.flatnonzero(prob.level == k) for k in range(int(prob.level.max()) + 1)]
    levels = [r for r in levels if r.size]
    if len(levels) < 3:
        return prob.penalty, {}
    errors = dict(zip((float(lam) for lam in penalties),
                      (float(e) for e in held_out_errors(prob, z, lay, penalties, levels,
                                                                normal))))
    best = min(errors.values())
    lam = max(k for k, v in errors.items() if v <= (1.0 + CV_TIE) * best)
    return lam, errors


def tied_slow_pairs(complete: list[Pulse], t: np.ndarray) -> tuple[dict, list[str]]:
    """The directions whose slow and diffusion pairs are the other direction's: those whose
    complete pulses run into another current (median rest after them shorter than the
    pulses) while the other direction's relax. Without a relaxation after the pulse its
    slow polarisation decays under the next current's own response, and the split between
    the fast and slow pairs is not identified (a ridge the least squares walk along to a
    zero resistance). Returns ({direction: source direction}, notes)."""
    def relaxes(d):
        ps = [p for p in complete if p.direction == d]
        rest = [t[min(p.next_start, t.size - 1)] - t[p.stop - 1] for p in ps]
        return bool(np.median(rest) >= np.median([p.duration_s for p in ps]))

    dirs = sorted({p.direction for p in complete})
    if len(dirs) < 2:
        return {}, []
    ok = {d: relaxes(d) for d in dirs}
    tied = {d: o for d, o in zip(dirs, dirs[::-1]) if not ok[d] and ok[o]}
    return tied, [f"curve: the {d} pulses run into another current (no rest after them): "
                  f"the {d} slow pair is the {s} one's" for d, s in tied.items()]


def log_references(x: np.ndarray, smooth) -> dict:
    """Per smoothed run (start, size, direction) with a positive value: the references the
    penalty on ln r is linearised about (the run's values, floored at LOG_FLOOR of its
    largest)."""
    out = {}
    for a, n, _ in smooth:
        r = np.asarray(x[a:a + n], dtype=np.float64)
        top = float(np.max(r))
        if top > 0:
            out[a] = np.maximum(r, LOG_FLOOR * top)
    return out


def log_penalty(dd: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The second-difference penalty on ln r about ``ref`` as a quadratic in r: with
    ln r ~ ln ref + r / ref - 1 (and D 1 = 0), |D ln r|^2 ~ |W r - b|^2 for
    W = D diag(1 / ref), b = -D ln ref, both scaled by the run's mean reference so that
    the weight compares with the penalty on r. Returns (W^T W, W^T b, b^T b): the terms
    added to the normal equations' matrix and right-hand side, and the constant."""
    s = float(np.mean(ref))
    w = dd * (s / ref)[None, :]
    b = -s * (dd @ np.log(ref))
    return w.T @ w, w.T @ b, float(b @ b)


def second_difference(nodes: np.ndarray) -> np.ndarray:
    """Second divided differences on (possibly uneven) nodes, scaled by the mean spacing
    squared: [1, -2, 1] on an even grid; no rows for fewer than three nodes."""
    n = nodes.size
    if n < 3:
        return np.zeros((0, n))
    h = np.diff(nodes)
    hbar = float(np.mean(h))
    d = np.zeros((n - 2, n))
    for k in range(1, n - 1):
        h1, h2 = h[k - 1], h[k]
        c = 2.0 / (h1 + h2) * hbar ** 2
        d[k - 1, k - 1:k + 2] = (c / h1, -c * (1.0 / h1 + 1.0 / h2), c / h2)
    return d


def taus_on_bound(taus: dict, ranges: dict) -> list[str]:
    """The branches whose time constant ended within 1 % of a search bound."""
    return [k for k in ranges
            if taus[k] <= ranges[k][0] * 1.01 or taus[k] >= ranges[k][1] / 1.01]


def level_fit_windows(series, complete, rec, resid):
    """Per SOC level: measured and fitted voltage from its first pulse to the next level."""
    out = []
    socs = np.array([p.soc for p in complete])
    dirs = np.array([p.direction for p in complete])
    groups = soc_levels(socs, dirs)
    t = series.time_s
    for g in groups:
        ps = [complete[k] for k in g]
        t0 = t[min(p.rest_index for p in ps)]
        t1 = t[min(max(p.next_start for p in ps), t.size - 1)]
        m = rec.row & (rec.t >= t0) & (rec.t <= t1)
        if not m.any():
            continue
        meas = rec.v[m]
        fit = meas - resid[m]
        rms = float(np.sqrt(np.mean(resid[m] ** 2)))
        edge = t[min(p.start for p in ps)]
        out.append((float(np.mean(socs[g])), ps[0].direction, rms,
                    [(rec.t[m] - edge, meas, fit)]))
    return tuple(out)


def r0_holds(bases, offsets, directions, spans) -> tuple[np.ndarray, np.ndarray]:
    """The r0 columns held and, for each, its source column: per direction, the level
    nodes beyond the nodes nearest to the ends of the levels that pin r0 (the source: that
    nearest node)."""
    held, source = [], []
    for basis, off, d in zip(bases, offsets, directions):
        if d not in spans:
            continue
        lo, hi, low, high, _ = spans[d]
        k_lo = int(np.argmin(np.abs(basis - lo))) if lo > low else 0
        k_hi = int(np.argmin(np.abs(basis - hi))) if hi < high else basis.size - 1
        k_hi = max(k_hi, k_lo)
        for k in range(basis.size):
            if k < k_lo or k > k_hi:
                held.append(off + k)
                source.append(off + (k_lo if k < k_lo else k_hi))
    return np.array(held, dtype=int), np.array(source, dtype=int)


def both_ways(blocks, series: TimeSeries, deadband_a: float,
              min_share: float = BOTH_WAYS_SHARE) -> tuple[list, list[str]]:
    """A dynamic test's blocks as levels of both directions, when the samples under current
    of the blocks run the other way than their net charge for at least ``min_share`` of
    the charge they move (a drive profile's regen): each direction's tables are then free
    at every block. Returns (the levels, notes)."""
    i, dt = series.current_a, np.diff(series.time_s, prepend=series.time_s[0])
    ix = np.concatenate([np.arange(p.start, p.stop) for p in blocks])
    charging = charging_direction(i[ix], deadband_a)
    moved = np.abs(i[ix]) * dt[ix]
    share = {d: float(moved[m].sum() / max(moved.sum(), 1e-300))
             for d, m in (("charge", charging), ("discharge", ~charging))}
    have = {p.direction for p in blocks}
    add = [d for d in ("charge", "discharge") if d not in have and share[d] >= min_share]
    if not add:
        return blocks, []
    other = [replace(p, direction=d) for d in add for p in blocks]
    return blocks + other, [f"curve: the blocks run both ways ({100 * share[add[0]]:.0f} % of "
                            f"their charge moved on {add[0]}): each direction's tables are "
                            "free at every block"]


def ocv_node_sets(nodes: np.ndarray) -> list[np.ndarray]:
    """The OCV correction's nodes: the levels, and the levels with their midpoints."""
    if nodes.size < 2:
        return [nodes]
    return [nodes, np.sort(np.concatenate([nodes, 0.5 * (nodes[1:] + nodes[:-1])]))]


def pulse_sampling_s(series: TimeSeries, complete) -> float:
    """The median sampling interval inside the complete pulses."""
    dt = np.concatenate([np.diff(series.time_s[p.start:p.stop]) for p in complete])
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else 0.0


def node_error(rec, prob, resid, nodes, mask, default):
    """The weighted RMS residual of the rows near each SOC node (``default`` where none)."""
    h = hats(rec.soc[prob.rows], nodes) * mask[prob.rows][:, None]
    w2 = (prob.w ** 2)[:, None] * h
    tot = w2.sum(axis=0)
    e2 = (w2 * (resid[prob.rows] ** 2)[:, None]).sum(axis=0)
    return np.where(tot > 0, np.sqrt(e2 / np.maximum(tot, 1e-300)), default)


def r0_spans(complete, directions, min_rates: int) -> dict:
    """Per direction: (lo, hi), the SOC range of the pulses of the levels whose complete
    pulses span at least ``need`` C-rates (``min_rates``, or as many as the best level has
    if fewer), (low, high), that of all complete pulses, and ``need``."""
    socs = np.array([p.soc for p in complete])
    dirs = np.array([p.direction for p in complete])
    rates = np.array([p.c_rate for p in complete])
    out = {}
    for d in directions:
        levels = [g for g in soc_levels(socs, dirs) if dirs[g[0]] == d]
        n = [np.unique(rates[g]).size for g in levels]
        need = min(min_rates, max(n))
        pinned = np.concatenate([g for g, k in zip(levels, n) if k >= need])
        every = np.concatenate(levels)
        out[d] = (float(socs[pinned].min()), float(socs[pinned].max()),
                  float(socs[every].min()), float(socs[every].max()), need)
    return out
