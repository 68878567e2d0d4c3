"""The pulse test reduced to the samples the whole-test fit needs (:mod:`ecmgen.fit.curve`):
rows, their weights, the folded rests, and the RC unit responses on that record."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from ..data.measure import TimeSeries, charging_direction
from ..data.ocv import OcvTable
from ..data.steps import pulse_test_gaps

W_SPAN_S = (1.0, 300.0)    # a row's weight is sqrt(the seconds it stands for), within these


@dataclass(frozen=True)
class Record:
    """The pulse test reduced to the samples the fit needs (see the module docstring)."""

    t: np.ndarray        # (n,) s
    dt: np.ndarray       # (n,) own ZOH interval
    gap: np.ndarray      # (n,) rest folded in before the interval (no input there)
    i: np.ndarray        # (n,) A (rest current zeroed)
    soc: np.ndarray      # (n,)
    y: np.ndarray        # (n,) v - ocv(soc)
    v: np.ndarray        # (n,) measured voltage
    row: np.ndarray      # (n,) bool: a row of the least squares
    w: np.ndarray        # (n,) weight of the row (0 elsewhere)
    dir_mask: dict       # direction -> (n,) bool, the samples run on that direction's table
    restart: np.ndarray  # indices of the first samples after gaps the file does not cover
    rest_used_s: float   # the longest stretch of rest after a change that has rows


def pulse_record(series: TimeSeries, soc0: float, ocv: OcvTable, capacity_ah: float, *,
            directions: tuple[str, ...], deadband_a: float,
            relax_s: float, rows_per_decade: float, min_weight_s: float = W_SPAN_S[0]) -> Record:
    t = series.time_s
    i = series.current_a.copy()
    dt = np.diff(t, prepend=t[0])
    soc = soc0 + series.coulomb_ah() / capacity_ah
    on_a = max(0.02 * capacity_ah, 1e-3)
    i[np.abs(i) <= 1e-3 * capacity_ah] = 0.0              # rest: no input
    on = np.abs(i) > on_a
    gaps = pulse_test_gaps(series)
    # a current change, or the end of an unlogged gap (the states restart there)
    change = np.union1d(np.flatnonzero(np.abs(np.diff(i, prepend=0.0)) > on_a), gaps + 1)
    last = np.full(t.size, -1)
    last[change] = change
    np.maximum.accumulate(last, out=last)
    since = np.where(last >= 0, t - t[np.maximum(last, 0)], np.inf)
    coarse = dt > 5.0            # a coarsely logged record (the SOC steps): every sample
    rest = ~on & (since <= relax_s)
    # rest rows log-spaced in the time since the change: the last sample of each bucket
    # stands for the bucket; each sample counts clip(dt, 1 s, 300 s) seconds
    bucket = np.floor(rows_per_decade * np.log10(np.maximum(since, 0.1) / 0.1))
    bucket = np.where(np.isfinite(since), bucket, -1.0)
    last_of_bucket = np.concatenate(((bucket[1:] != bucket[:-1]) | (last[1:] != last[:-1]),
                                     [True]))
    row = on | coarse | (rest & last_of_bucket)
    row[0] = False
    keep = row | (i != 0.0)
    keep[0] = True
    idx = np.flatnonzero(keep)
    # the rest folded into each kept sample: time since the previous kept sample minus its dt
    t_prev = np.concatenate(([t[0]], t[idx[:-1]]))
    gap = np.maximum(t[idx] - t_prev - dt[idx], 0.0)
    counts = np.where(on | coarse | rest, np.clip(dt, min_weight_s, W_SPAN_S[1]), 0.0)
    cum = np.cumsum(counts)
    rix = np.flatnonzero(row)
    w2 = np.diff(cum[rix], prepend=0.0)
    w2[on[rix]] = counts[rix][on[rix]]
    w_all = np.zeros(t.size)
    w_all[rix] = np.sqrt(w2)
    w = w_all[idx]
    # after a gap the file does not cover, the states are unknown: they restart from free
    # values there (see _Problem), and the first sample, whose current stands for the gap,
    # is no row
    restart = np.searchsorted(idx, gaps + 1)
    w[restart] = 0.0
    charging = charging_direction(i, deadband_a)        # the simulator's rule
    if len(directions) == 1:
        masks = {directions[0]: np.ones(idx.size, bool)}
    else:
        masks = {"charge": charging[idx], "discharge": ~charging[idx]}
    s = soc[idx]
    return Record(t[idx], dt[idx], gap, i[idx], s, series.voltage_v[idx] - ocv.ocv_at(s),
                   series.voltage_v[idx], row[idx], w, masks, restart,
                   float(np.max(since[row & rest], initial=0.0)))


def after_charge(i: np.ndarray) -> np.ndarray:
    """True where the last current (this sample's included) was a charge."""
    k = np.where(i != 0.0, np.arange(i.size), -1)
    np.maximum.accumulate(k, out=k)
    return np.where(k >= 0, i[np.maximum(k, 0)] > 0, False)


def side_by_side(blocks, widths=None) -> np.ndarray:
    """The blocks side by side in one Fortran-ordered array (no transposing copy). With
    their ``widths`` given, ``blocks`` may be an iterator that makes each block as it is
    copied in (no block list beside the array)."""
    if widths is None:
        blocks = list(blocks)
        widths = [b.shape[1] for b in blocks]
    out = None
    at = 0
    for b, width in zip(blocks, widths):
        if out is None:
            out = np.empty((b.shape[0], sum(widths)), order="F")
        out[:, at:at + width] = b
        at += width
    return out


def hats(soc: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Hat functions on ``nodes`` at ``soc`` (n, n_nodes), flat beyond the end nodes (one
    node: a constant)."""
    if nodes.size == 1:
        return np.ones((soc.size, 1))
    x = np.clip(soc, nodes[0], nodes[-1])
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
    w = (x - nodes[j]) / (nodes[j + 1] - nodes[j])
    h = np.zeros((soc.size, nodes.size))
    h[np.arange(soc.size), j] = 1.0 - w
    h[np.arange(soc.size), j + 1] += w
    return h


def rc_response(rec: Record, tau: float, u: np.ndarray) -> np.ndarray:
    """x_k = exp(-(gap_k + dt_k)/tau) x_{k-1} + (1 - exp(-dt_k/tau)) u_k for every column
    of u (n, m), plus one column per restart r: a unit state from sample r on (x_r = 1,
    decaying). A unit-lower-bidiagonal solve (LAPACK tbtrs), exact and compiled; a restart
    column, with no input after its unit, is the running product of the decays, which is
    what the solve works out there too (each x_{k-1} decay_k rounded once, no input)."""
    n, m = rec.t.size, u.shape[1]
    decay = np.exp(-(rec.gap[1:] + rec.dt[1:]) / tau)
    ab = np.zeros((2, n))
    ab[1, :-1] = -decay
    out = np.zeros((n, m + rec.restart.size), order="F")
    np.multiply(u, -np.expm1(-rec.dt / tau)[:, None], out=out[:, :m])
    x, info = lapack.dtbtrs(ab, out[:, :m], uplo="L", diag="U", overwrite_b=1)
    if info != 0:  # pragma: no cover - unit diagonal: never singular
        raise RuntimeError(f"dtbtrs info {info}")
    if not np.shares_memory(x, out):  # pragma: no cover - solved in place where it can
        out[:, :m] = x
    for j, r in enumerate(rec.restart):
        out[r, m + j] = 1.0
        np.multiply.accumulate(decay[r:], out=out[r + 1:, m + j])
    return out


class ResponseCache:
    """The weighted unit-response blocks of a record by (branch, ln tau): the searches
    revisit time constants. The least recently used go beyond ``max_bytes``; shared by the
    problems of one record with the same rows, weights and inputs (the OCV offsets' two node
    sets) and safe across threads (a block is the same whoever computes it)."""

    def __init__(self, max_bytes: int = 64 * 2 ** 20):
        self.max_bytes = max_bytes
        self._blocks: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            block = self._blocks.get(key)
            if block is not None:
                self._blocks.move_to_end(key)
            return block

    def put(self, key, block: np.ndarray) -> np.ndarray:
        with self._lock:
            if key in self._blocks:
                return self._blocks[key]
            self._blocks[key] = block
            self._bytes += block.nbytes
            while self._bytes > self.max_bytes and len(self._blocks) > 1:
                self._bytes -= self._blocks.popitem(last=False)[1].nbytes
            return block


class NormalEquations:
    """(Z'Z, Z'y) of a problem's weighted design Z = [r0 columns | a block per branch] at
    given time constants, by (branches, time constants met): the fit forms them again at
    the time constants the search ended at (the solve with r0 held, leaving a level out,
    the penalty on ln r). Without Z given, Z is made in one buffer per set of branches
    whose r0 columns are copied once and whose blocks only when their time constant
    changed. The same Z, the same products: the fit's figures do not depend on which
    path made them. The least recently used go beyond ``max_bytes``."""

    def __init__(self, max_bytes: int = 16 * 2 ** 20):
        self.max_bytes = max_bytes
        self._done: OrderedDict = OrderedDict()
        self._bytes = 0
        self._buffers: dict = {}       # branches -> (Z, the time constant of each block)

    def get(self, prob, kinds, met, z: np.ndarray | None = None):
        key = (tuple(kinds), tuple(met))
        got = self._done.get(key)
        if got is not None:
            self._done.move_to_end(key)
            return got
        if z is None:
            z = self._fill(prob, key)
        got = (z.T @ z, z.T @ prob.yw)
        self._done[key] = got
        self._bytes += got[0].nbytes + got[1].nbytes
        while self._bytes > self.max_bytes and len(self._done) > 1:
            old = self._done.popitem(last=False)[1]
            self._bytes -= old[0].nbytes + old[1].nbytes
        return got

    def drop_buffers(self) -> None:
        """Let go of the design buffers (a search's evaluations are done)."""
        self._buffers.clear()

    def _fill(self, prob, key) -> np.ndarray:
        kinds, met = key
        widths = [prob.width(k) for k in kinds]
        if kinds not in self._buffers:
            z = np.empty((prob.rows.size, prob.r0w.shape[1] + sum(widths)), order="F")
            z[:, :prob.r0w.shape[1]] = prob.r0w
            self._buffers[kinds] = (z, [None] * len(kinds))
        z, held = self._buffers[kinds]
        at = prob.r0w.shape[1]
        for n, (k, tau, width) in enumerate(zip(kinds, met, widths)):
            if held[n] != tau:
                held[n] = None             # a block half copied is no block
                prob.block_into(k, tau, z[:, at:at + width])
                held[n] = tau
            at += width
        return z


class RevisitedTaus:
    """The time constant a problem's response block is made at: of those whose ln tau
    rounds to the same 9 decimals, the first met since the book was last cleared (beyond
    97 entries). The searches meet a time constant again a rounding away (a grid point
    reached from the simplex, exp(ln tau)); the fit has always taken the block first made
    for it, and this keeps that, whatever the blocks' own cache (:class:`ResponseCache`,
    by the exact tau) holds."""

    def __init__(self):
        self._taus: dict = {}

    def state(self) -> dict:
        return dict(self._taus)

    def restore(self, state: dict) -> None:
        self._taus = dict(state)

    def tau(self, kind: str, tau: float) -> float:
        key = (kind, round(float(np.log(tau)), 9))
        first = self._taus.get(key)
        if first is None:
            if len(self._taus) > 96:
                self._taus.clear()
            first = self._taus[key] = float(tau)
        return first


def node_set_searches(searches: list, k: int) -> dict:
    """The time-constant searches of OCV-offset node set ``k`` in ``searches`` (one dict
    per node set; a new one added for a node set met the first time)."""
    while len(searches) <= k:
        searches.append({})
    return searches[k]


def remembered(search, prob, ranges: dict, progress=None):
    """``search(prob, ranges, progress)``, or what it gave for these ranges before
    (``prob.searches``: the same test fitted again, offered its neighbours' time constants,
    searches as it did the first time). Only a problem's first search is kept and taken,
    with the time constants it met (:class:`RevisitedTaus`): what follows then meets the
    same blocks as after the search itself. Returns a copy."""
    key = tuple((k, tuple(float(v) for v in r)) for k, r in ranges.items())
    first = not prob._taus.state()
    got = prob.searches.get(key) if first else None
    if got is not None:
        result, met = got
        prob._taus.restore(met)
    else:
        result = search(prob, ranges, progress)
        if first:
            prob.searches[key] = (result, prob._taus.state())
    taus, x, cost, n_eval, notes = result
    return dict(taus), np.array(x, copy=True), cost, n_eval, list(notes)


def share_responses(prob, other) -> None:
    """``prob`` (a whole-test fit's problem, :class:`ecmgen.fit.curve._Problem`) takes
    ``other``'s inputs and response blocks where they are its own too: the same record,
    rows, weights and inputs (the other OCV-offset node set)."""
    same = prob.rec is other.rec and all(
        np.array_equal(getattr(prob, k), getattr(other, k))
        for k in ("rows", "w", "u_fast", "u_slow", "u_diff"))
    if same:
        prob.u_fast, prob.u_slow, prob.u_diff = other.u_fast, other.u_slow, other.u_diff
        prob._cache = other._cache


# a sign test at 99 %: the level diagnose's rest-hysteresis F test uses too
DRIFT_P = 0.01


@dataclass(frozen=True)
class RestDrift:
    """The residual of a fit over the later half of each rest of the test, its slope the
    way a relaxation goes (up after a discharge, down after a charge)."""

    drifting: int        # rests whose residual drifts that way
    judged: int          # rests with enough rows and a non-zero slope
    p: float             # one-sided sign test: P(>= drifting of judged | no drift)

    @property
    def shown(self) -> bool:
        return self.p < DRIFT_P

    def words(self) -> str:
        return (f"the residual drifts at the ends of {self.drifting} of {self.judged} rests the "
                f"way a slower relaxation would, sign test p = {self.p:.2g}")


def rests_still_relax(rec: Record, rows: np.ndarray, residual_v: np.ndarray,
                      min_rows: int = 3) -> RestDrift:
    """Does the test show a relaxation slower than a fit resolves? ``residual_v``: the fit's
    residual (measured - fitted, V) at ``rows`` of ``rec``. A fit whose pairs relax within
    the rests leaves noise at their ends, drifting either way; a slower process left out
    makes it drift the relaxation's way at rest after rest. Rests across an unlogged gap
    and the opening one are not judged."""
    from math import comb

    t, i = rec.t, rec.i
    row_of = np.full(t.size, -1)
    row_of[rows] = np.arange(rows.size)
    idle = np.concatenate([[0], (i == 0.0).astype(np.int8), [0]])
    edges = np.flatnonzero(np.diff(idle))
    drifting = judged = 0
    for a, b in zip(edges[::2], edges[1::2]):
        if a == 0 or np.any((rec.restart > a) & (rec.restart < b)):
            continue
        k = np.arange(a, b)
        k = k[(t[k] >= 0.5 * (t[a] + t[b - 1])) & (row_of[k] >= 0)]
        if k.size < min_rows:
            continue
        slope = np.polyfit(t[k] - t[k[0]], residual_v[row_of[k]], 1)[0] * -np.sign(i[a - 1])
        if slope != 0.0:
            judged += 1
            drifting += int(slope > 0.0)
    p = sum(comb(judged, j) for j in range(drifting, judged + 1)) / 2.0 ** judged
    return RestDrift(drifting, judged, float(p))
