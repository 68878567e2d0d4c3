"""Whole-test fit (the "curve" method): one simulation-error fit of a complete pulse test.

Five DC-IR points within 10 s cannot see time constants of minutes; the record as a whole
(pulses, their rests and, where the cycler logged them in a file of their own, the SOC
steps between pulse sets, :func:`ecmgen.data.steps.merge_soc_steps`) can. The model is the
one :mod:`ecmgen.model.simulate` runs, with the OCV fixed to the given table (the rests'
OCV) and, per sample k (current i_k held over (t_{k-1}, t_k], positive on charge)::

    y_k = v_k - ocv(soc_k) = sum_j phi_j(soc_k) [r0_j i_k + r_fast_j x_fast,j,k + r_slow_j x_slow,j,k]
                             + r_diff x_diff,k
    x_fast,j : RC with tau_fast driven by phi_j(soc) h(i),  h(i) = i0 asinh(i / i0)  (or i)
    x_slow,j : RC with tau_slow driven by phi_j(soc) i;     x_diff: RC with tau_diff driven by i

(x_k = a_k x_{k-1} + (1 - a_k) u_k, a_k = exp(-dt_k / tau): the simulator's exact ZOH step;
h is the Butler-Volmer input of the fast branch, r_fast g(i) i with g = asinh(x)/x.) phi_j are
hat functions on SOC nodes (0, 0.05, .., 1), so r0, r_fast and r_slow are piecewise linear in
SOC exactly as the model interpolates them; a node no loaded sample weighs at least
``NODE_SUPPORT`` is not free but linear between its free neighbours. The time constants,
r_diff and i0 are one value per test. With pulses in both directions each direction has its
own resistances (shared time constants). After a gap the file does not cover (the SOC moves
of a pulse test without its step file) the states restart from free values. Given the time
constants the fit is linear: least squares on the normal equations, resistances >= 0, with a
small second-difference penalty over SOC.

Rows: every sample under current, every coarsely logged one (the SOC steps), and the rest
up to ``relax_s`` after each current change at ``rows_per_decade`` rows per decade of the
time since the change; a row's weight is sqrt(the seconds it stands for), counting each
sample as clip(dt, 1 s, 300 s) (the findings' weighting). Samples that are not rows are
folded into the next sample's decay (exact: no input there), so the states run through the
whole record at the cost of the rows only.

Time constants: the unit responses are computed once per value on a log grid per branch
(fast, slow, diffusion; ratio 2.2) and every grid combination is a small solve on blocks of
one Gram matrix. Nelder-Mead in log tau (exact evaluations) then refines from the grid's
best point and, when it lies elsewhere, from the grid's best point when slow dynamics are
favoured (``SLOW_START``). The slow and diffusion pairs together stand for a spread of
diffusion times, and a pulse test can have two local minima that fit it nearly equally well
(the -10 degC Panasonic test: tau_slow 13 s / 27 s, 0.03 .. 0.8 % apart in the objective
depending on details of the fit); of local minima within ``TIE`` (1 %: residuals this
correlated cannot tell such fits apart) of the best, the one with the slowest dynamics is
kept, as long discharges (drive cycles) need it (the 27 s fit: -10 degC US06 50 mV and LOTO
at 25 degC 44 mV, the 13 s fit: 55 / 117 mV; bench/loto_temperature.py). Resistance nodes outside the SOC levels with a complete pulse are held
at the outermost such level's value afterwards (the data there are pulses cut by the voltage
limit and the end of the steps).

r0 against the fast branch: with tau_fast a few samples long (0.35-0.5 s at 0.1 s sampling in
the cold) r0 and r_fast differ only in the first samples of each edge and in their current
dependence (r0 linear, the Butler-Volmer branch sublinear). At the low-SOC levels of a cold
test the voltage limit cuts the 1-6C pulses short, the level keeps one or two C-rates, and the
shared tau_fast cannot follow its slower response there: the least squares then trade r0 for
r_fast down to r0 = 0 (0.6 degC Panasonic: 0 mOhm at SOC 0.1-0.15, 47 at 0.3), which no
ohmic resistance does. So r0 is free only over the levels whose complete pulses span at
least ``R0_MIN_RATES`` C-rates (two unknowns per level from the current dependence, and a
check; every level if no level has that many), and held outside at the value the nearest
such level's node has in the free fit, the other resistances refitted with it (after the
time-constant search, which keeps the free fit: bench/loto_temperature.py measured the hold
inside the search moving the -10 degC test to its fast local minimum, worse on its cycles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from ..data.dcir import Pulse
from ..data.measure import TimeSeries, charging_direction
from ..data.ocv import OcvTable
from ..data.steps import merge_soc_steps, pulse_test_gaps
from ..errors import InputError
from .lsq import log_grid, nelder_mead, solve_bounded

SOC_NODES = np.round(np.linspace(0.0, 1.0, 21), 10)
DIRECTIONS = ("charge", "discharge")
PENALTY = 1e-3             # second-difference penalty, relative to each block's column scale
W_SPAN_S = (1.0, 300.0)    # a row's weight is sqrt(the seconds it stands for), within these
TIE = 1e-2                 # local minima within this (relative objective) are equally good
SLOW_START = 0.02          # grid start favouring slow dynamics: objective tilt per ln(tau)
NODE_SUPPORT = 0.25        # a node is free where a loaded sample puts this much hat weight
NM_EVALS = 60              # exact evaluations per local refinement
R0_MIN_RATES = 3           # a level pins r0 when its complete pulses span this many C-rates


@dataclass(frozen=True)
class DirectionFit:
    """Resistances of one current direction over the SOC nodes (arrays of shape (n_soc,))."""

    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    r_slow_ohm: np.ndarray
    r_diff_ohm: float | None      # one value per test (None: no diffusion branch)
    fit_error_v: np.ndarray       # weighted RMS residual of the rows near each node
    identified: np.ndarray        # bool: False where held flat (no complete pulse below)


@dataclass(frozen=True)
class CurveFit:
    """The whole-test fit of one pulse test.

    soc            (n_soc,) SOC nodes of the tables
    charge, discharge   per-direction resistances (a direction without pulses gets the
                   other's; ``directions`` says which were fitted)
    tau_fast_s, tau_slow_s, tau_diff_s, i0_a   one value per test (tau_diff_s, i0_a: None
                   when the branch is absent)
    rms_error_v    weighted RMS of the fit over its rows
    notes          what the fit did (levels held flat, time constants on a bound, rows used)
    windows        per SOC level (soc, direction, rms_v, [(t_s, measured_v, fitted_v)]): the
                   measured and fitted voltage from the level's first rest to the next level,
                   time from the level's first pulse edge (plots)
    """

    soc: np.ndarray
    charge: DirectionFit
    discharge: DirectionFit
    directions: tuple[str, ...]
    tau_fast_s: float
    tau_slow_s: float
    tau_diff_s: float | None
    i0_a: float | None
    rms_error_v: float
    n_rows: int
    notes: tuple[str, ...]
    windows: tuple = ()
    tau_ranges: dict | None = None   # {"fast": (lo, hi), "slow": ..., "diff": ...}, s
    rest_used_s: float | None = None  # the longest rest after a current change with rows

    def table(self, direction: str) -> DirectionFit:
        return self.charge if direction == "charge" else self.discharge

    def rc_columns(self, direction: str) -> dict:
        """Keyword arguments of a one-temperature ``ecmgen.model.RcTable`` for
        ``direction`` (without temperature_c): the pipeline builds the table from them."""
        d = self.table(direction)
        n = self.soc.size
        out = dict(soc=self.soc.copy(), r0_ohm=d.r0_ohm.copy(), r_fast_ohm=d.r_fast_ohm.copy(),
                   tau_fast_s=np.full(n, self.tau_fast_s), r_slow_ohm=d.r_slow_ohm.copy(),
                   tau_slow_s=np.full(n, self.tau_slow_s), fit_error=d.fit_error_v.copy(),
                   converged=d.identified.copy())
        if self.tau_diff_s is not None:
            out.update(r_diff_ohm=np.array([d.r_diff_ohm]), tau_diff_s=np.array([self.tau_diff_s]))
        if self.i0_a is not None:
            out["i0_a"] = np.array([self.i0_a])
        return out


# ----------------------------------------------------------------------------- the record
@dataclass(frozen=True)
class _Record:
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


def _record(series: TimeSeries, soc0: float, ocv: OcvTable, capacity_ah: float, *,
            directions: tuple[str, ...], deadband_a: float,
            relax_s: float, rows_per_decade: float, min_weight_s: float = W_SPAN_S[0]) -> _Record:
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
    return _Record(t[idx], dt[idx], gap, i[idx], s, series.voltage_v[idx] - ocv.ocv_at(s),
                   series.voltage_v[idx], row[idx], w, masks, restart,
                   float(np.max(since[row & rest], initial=0.0)))


def _columns(blocks) -> np.ndarray:
    """The blocks side by side in one Fortran-ordered array (no transposing copy)."""
    out = np.empty((blocks[0].shape[0], sum(b.shape[1] for b in blocks)), order="F")
    at = 0
    for b in blocks:
        out[:, at:at + b.shape[1]] = b
        at += b.shape[1]
    return out


def _hats(soc: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    x = np.clip(soc, nodes[0], nodes[-1])
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
    w = (x - nodes[j]) / (nodes[j + 1] - nodes[j])
    h = np.zeros((soc.size, nodes.size))
    h[np.arange(soc.size), j] = 1.0 - w
    h[np.arange(soc.size), j + 1] += w
    return h


def _rc_response(rec: _Record, tau: float, u: np.ndarray) -> np.ndarray:
    """x_k = exp(-(gap_k + dt_k)/tau) x_{k-1} + (1 - exp(-dt_k/tau)) u_k for every column
    of u (n, m), plus one column per restart r: a unit state from sample r on (x_r = 1,
    decaying). A unit-lower-bidiagonal solve (LAPACK tbtrs), exact and compiled."""
    n = rec.t.size
    ab = np.zeros((2, n))
    ab[1, :-1] = -np.exp(-(rec.gap[1:] + rec.dt[1:]) / tau)
    b = np.zeros((n, u.shape[1] + rec.restart.size), order="F")
    np.multiply(u, -np.expm1(-rec.dt / tau)[:, None], out=b[:, :u.shape[1]])
    b[rec.restart, u.shape[1] + np.arange(rec.restart.size)] = 1.0
    x, info = lapack.dtbtrs(ab, b, uplo="L", diag="U", overwrite_b=1)
    if info != 0:  # pragma: no cover - unit diagonal: never singular
        raise RuntimeError(f"dtbtrs info {info}")
    return x


# ------------------------------------------------------------------- the linear problem
class _Problem:
    """The rows' weighted design blocks for any time constants, and the solve."""

    def __init__(self, rec: _Record, nodes: np.ndarray, i0_a: float | None,
                 r0_spans: dict | None = None):
        self.rec = rec
        self.nodes = nodes
        self.ndir = len(rec.dir_mask)
        # free nodes: those on which some current-carrying sample puts at least a quarter
        # of its hat weight; the others follow linearly from their neighbours (no slope is
        # extrapolated across SOC ranges the test never loaded)
        on = np.abs(rec.i) > 0.0
        weight = _hats(rec.soc[on], nodes).max(axis=0) if on.any() else np.ones(nodes.size)
        free = weight >= NODE_SUPPORT
        self.basis = nodes[free]
        if self.basis.size < 2:
            k = min(int(np.argmax(weight)), nodes.size - 2)
            self.basis = nodes[k:k + 2]
        self.J = self.basis.size
        # r0 nodes held (fixed at their source node's value, see the module docstring)
        self.r0_held, self.r0_source = _r0_holds(nodes, self.basis, list(rec.dir_mask),
                                                 r0_spans or {})
        h = _hats(rec.soc, self.basis)
        hd = np.hstack([h * m[:, None] for m in rec.dir_mask.values()])     # (n, J*ndir)
        drive = rec.i if i0_a is None else i0_a * np.arcsinh(rec.i / i0_a)
        self.u_fast = np.multiply(hd, drive[:, None], order="F")
        self.u_slow = np.multiply(hd, rec.i[:, None], order="F")
        self.u_diff = np.asfortranarray(np.column_stack([m * rec.i for m in rec.dir_mask.values()]))
        self.r0_full = self.u_slow                       # r0 * i on the node basis
        self.rows = np.flatnonzero(rec.row & (rec.w > 0))
        self.w = rec.w[self.rows]
        self.yw = rec.y[self.rows] * self.w
        self.yy = float(self.yw @ self.yw)
        self.r0w = np.asfortranarray((self.r0_full.T[:, self.rows] * self.w).T)
        d2 = np.diff(np.eye(self.J), 2, axis=0)
        self.dtd = d2.T @ d2
        self._cache: dict = {}

    def block(self, kind: str, tau: float, full: bool = False) -> np.ndarray:
        """The unit responses of branch ``kind`` at ``tau``: weighted rows (cached; the
        searches revisit time constants), or every kept sample (``full``)."""
        key = (kind, round(float(np.log(tau)), 9))
        if not full and key in self._cache:
            return self._cache[key]
        u = {"fast": self.u_fast, "slow": self.u_slow, "diff": self.u_diff}[kind]
        x = _rc_response(self.rec, tau, u)
        if full:
            return x
        if len(self._cache) > 96:
            self._cache.clear()
        out = self._cache[key] = np.asfortranarray((x.T[:, self.rows] * self.w).T)
        return out

    def width(self, kind: str) -> int:
        """Columns of a branch block: its resistances, then one free restart state per gap."""
        return (self.J if kind != "diff" else 1) * self.ndir + self.rec.restart.size

    def layout(self, kinds) -> dict:
        """For the columns [r0 | block of each kind]: where each kind's resistances start,
        the free (restart) columns, and the starts of the J-column blocks to smooth."""
        jd = self.J * self.ndir
        start, off = {"r0": 0}, jd
        free = [np.zeros(jd, bool)]
        for k in kinds:
            start[k] = off
            nr = self.width(k) - self.rec.restart.size
            free.append(np.concatenate([np.zeros(nr, bool), np.ones(self.rec.restart.size, bool)]))
            off += self.width(k)
        smooth = [start[k] + d * self.J for k in ("r0", "fast", "slow") if k in start
                  for d in range(self.ndir)]
        return dict(start=start, free=np.concatenate(free), smooth=smooth)

    def solve(self, gram: np.ndarray, g: np.ndarray, lay: dict, hold_r0: bool = False
              ) -> tuple[np.ndarray, float]:
        """Penalised least squares, resistances >= 0, restart states free; returns the
        solution and the objective (weighted SSE + second-difference penalty). With
        ``hold_r0`` the held r0 nodes and their sources are then fixed at the sources'
        values and the rest solved again."""
        m = gram.copy()
        scale = np.sqrt(np.maximum(np.diag(gram), 0.0))
        for a in lay["smooth"]:
            sl = slice(a, a + self.J)
            m[sl, sl] += PENALTY * float(np.mean(scale[sl])) ** 2 * self.dtd
        # a tiny ridge: columns that no row sees (short relax_s) would make m singular
        m[np.diag_indices_from(m)] += 1e-12 * float(np.mean(np.diag(gram))) + 1e-300
        x = solve_bounded(m, g, lay["free"])
        if hold_r0 and self.r0_held.size:
            fixed = np.zeros(x.size, bool)
            fixed[self.r0_held] = fixed[self.r0_source] = True
            x[self.r0_held] = x[self.r0_source]
            ix = np.ix_(~fixed, ~fixed)
            x[~fixed] = solve_bounded(m[ix], g[~fixed] - m[np.ix_(~fixed, fixed)] @ x[fixed],
                                      lay["free"][~fixed])
        return x, self.yy - 2.0 * float(g @ x) + float(x @ m @ x)


# ---------------------------------------------------------------- the time constants
def _search(prob: _Problem, ranges: dict, progress=None):
    """The time constants (module docstring): grid over cached unit responses, local
    refinement from the grid's best point and from the best point favouring slow dynamics,
    then the tie-break between the local minima found. Returns (taus dict, x, objective,
    number of evaluations, notes)."""
    kinds = list(ranges)
    grids = {k: log_grid(*ranges[k]) for k in kinds}
    blocks = [prob.r0w] + [prob.block(k, tau) for k in kinds for tau in grids[k]]
    z = _columns(blocks)
    gram = z.T @ z
    g = z.T @ prob.yw
    width = {k: prob.width(k) for k in kinds}
    lay = prob.layout(kinds)
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
                zz = _columns([prob.r0w] + [prob.block(k, t) for k, t in zip(kinds, taus)])
                evals[key] = prob.solve(zz.T @ zz, zz.T @ prob.yw, lay)
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
        zz = _columns([prob.r0w] + [prob.block(k, t) for k, t in zip(kinds, np.exp(key))])
        x, cost = prob.solve(zz.T @ zz, zz.T @ prob.yw, lay, hold_r0=True)
    return dict(zip(kinds, np.exp(np.array(key)))), x, cost, len(evals), notes


# ------------------------------------------------------------------------------ the fit
def fit_pulse_curves(series: TimeSeries, pulses: list[Pulse], ocv: OcvTable,
                     capacity_ah: float, *, i0_a: float | None = None,
                     steps: TimeSeries | None = None, diffusion: bool = True,
                     relax_s: float = 1800.0, rows_per_decade: float = 20.0, min_weight_s: float = W_SPAN_S[0],
                     tau_fast_s: tuple[float, float] = (0.1, 10.0),
                     tau_slow_s: tuple[float, float] = (5.0, 500.0),
                     tau_diff_s: tuple[float, float] = (150.0, 3000.0),
                     soc_nodes: np.ndarray = SOC_NODES,
                     direction_deadband_a: float | None = None, progress=None) -> CurveFit:
    """Fit one pulse test as a whole (module docstring): the curve method.

    series, pulses   the pulse test and its pulses (:func:`ecmgen.data.dcir.find_pulses`;
                     their SOCs fix the record's SOC axis)
    ocv              the OCV the model will use (held fixed; e.g. the rests' OCV)
    i0_a             Butler-Volmer current of the fast branch (:func:`ecmgen.fit.rate.
                     fit_exchange_current`); None: linear fast branch
    steps            the record of the SOC steps the pulse test left out (merged into its
                     gaps, :func:`ecmgen.data.steps.merge_soc_steps`); None: the gaps are rests
    diffusion        fit the third (diffusion) RC pair
    relax_s          rest rows up to this long after each current change
    tau_*_s          search ranges (s); the fit keeps tau_fast < tau_slow < tau_diff
    progress         called as progress(done, total)
    """
    if i0_a is not None and not (np.isfinite(i0_a) and i0_a > 0):
        raise ValueError(f"i0_a must be positive, got {i0_a!r}")
    ranges = {"fast": tau_fast_s, "slow": tau_slow_s}
    if diffusion:
        ranges["diff"] = tau_diff_s
    for k, (lo, hi) in ranges.items():
        if not (0 < lo < hi and np.isfinite(hi)):
            raise ValueError(f"tau_{k}_s range must be 0 < lo < hi, got {(lo, hi)!r}")
    nodes = np.asarray(soc_nodes, dtype=np.float64)
    complete = [p for p in pulses if not p.cut_short]
    if not complete:
        raise InputError(series.source, "every pulse was cut short: nothing to fit the "
                                        "curve method on")
    first = pulses[0]
    soc0 = first.soc - float(series.coulomb_ah()[first.rest_index]) / capacity_ah
    notes: list[str] = []
    record = series
    if steps is not None:
        record, n = merge_soc_steps(series, steps)
        notes.extend(n)
    directions = tuple(d for d in DIRECTIONS if any(p.direction == d for p in complete))
    deadband = 0.01 * capacity_ah if direction_deadband_a is None else direction_deadband_a
    rec = _record(record, soc0, ocv, capacity_ah, directions=directions, deadband_a=deadband,
                  relax_s=relax_s, rows_per_decade=rows_per_decade, min_weight_s=min_weight_s)
    spans = _r0_spans(complete, directions)
    prob = _Problem(rec, nodes, i0_a, spans)
    if prob.rows.size < 4 * prob.J:
        raise InputError(series.source, f"only {prob.rows.size} samples to fit the curve "
                                        "method on")
    taus, x, cost, n_eval, search_notes = _search(prob, ranges, progress)
    notes.extend(search_notes)
    rms = float(np.sqrt(max(cost, 0.0) / float(prob.w @ prob.w)))
    # the fitted voltage at every kept sample (plots, per-node errors)
    kinds = list(ranges)
    full = _columns([prob.r0_full] + [prob.block(k, taus[k], full=True) for k in kinds])
    fitted = rec.y - full @ x                            # residual, measured minus fitted
    at = prob.layout(kinds)["start"]
    fits = {}
    for n_d, d in enumerate(rec.dir_mask):
        j0 = n_d * prob.J
        r0, rf, rs = (np.interp(nodes, prob.basis, x[at[k] + j0:at[k] + j0 + prob.J])
                      for k in ("r0", "fast", "slow"))
        rd = float(x[at["diff"] + n_d]) if diffusion else None
        low = min(p.soc for p in complete if p.direction == d)
        high = max(p.soc for p in complete if p.direction == d)
        ident = _identified(nodes, low, high)
        if not ident.all():
            held = nodes[~ident]
            notes.append(f"curve: {d} r0/r_fast/r_slow held flat at SOC "
                         f"{', '.join(f'{s:g}' for s in held)} (outside the SOC levels "
                         f"with a complete pulse, {low:.3f} .. {high:.3f})")
        held = prob.basis[prob.r0_held[(prob.r0_held >= j0) & (prob.r0_held < j0 + prob.J)]
                          - j0]
        if held.size:
            lo, hi, _, _, need = spans[d]
            notes.append(f"curve: {d} r0 held at SOC {', '.join(f'{s:g}' for s in held)} "
                         f"(r0 is pinned by the levels with complete pulses at {need} "
                         f"or more C-rates, {lo:.3f} .. {hi:.3f})")
        r0, rf, rs = (_hold(v, ident) for v in (r0, rf, rs))
        err = _node_error(rec, prob, fitted, nodes, rec.dir_mask[d], rms)
        fits[d] = DirectionFit(r0, rf, rs, rd, err, ident)
    if len(directions) == 1:
        other = "charge" if directions[0] == "discharge" else "discharge"
        fits[other] = fits[directions[0]]
        notes.append(f"curve: the test has {directions[0]} pulses only: the {other} "
                     f"parameters are the {directions[0]} parameters")
    for k in kinds:
        lo, hi = ranges[k]
        if taus[k] <= lo * 1.01 or taus[k] >= hi / 1.01:
            notes.append(f"curve: tau_{k} {taus[k]:.3g} s is on its search bound "
                         f"({lo:g} .. {hi:g} s): not resolved by the data")
    notes.append(
        f"curve: whole-test fit of {prob.rows.size} samples ({n_eval} time-constant "
        f"evaluations), rests used up to {rec.rest_used_s:.0f} s after "
        f"each current change{', the SOC-step file merged' if steps is not None else ''}: "
        f"tau_fast {taus['fast']:.3g} s, tau_slow {taus['slow']:.3g} s"
        + (f", tau_diff {taus['diff']:.3g} s" if diffusion else "")
        + (f", Butler-Volmer i0 {i0_a:.3g} A on the fast branch" if i0_a else "")
        + f"; fit RMS {rms * 1e3:.2f} mV")
    return CurveFit(nodes.copy(), fits["charge"], fits["discharge"], directions,
                    float(taus["fast"]), float(taus["slow"]),
                    float(taus["diff"]) if diffusion else None, i0_a, rms,
                    int(prob.rows.size), tuple(notes),
                    _windows(series, complete, rec, fitted), dict(ranges),
                    float(rec.rest_used_s))


def _r0_spans(complete, directions) -> dict:
    """Per direction: (lo, hi), the SOC range of the pulses of the levels whose complete
    pulses span at least ``need`` C-rates (R0_MIN_RATES, or as many as the best level has
    if fewer), (low, high), that of all complete pulses, and ``need``."""
    from .points import soc_levels

    socs = np.array([p.soc for p in complete])
    dirs = np.array([p.direction for p in complete])
    rates = np.array([p.c_rate for p in complete])
    out = {}
    for d in directions:
        levels = [g for g in soc_levels(socs, dirs) if dirs[g[0]] == d]
        n = [np.unique(rates[g]).size for g in levels]
        need = min(R0_MIN_RATES, max(n))
        pinned = np.concatenate([g for g, k in zip(levels, n) if k >= need])
        every = np.concatenate(levels)
        out[d] = (float(socs[pinned].min()), float(socs[pinned].max()),
                  float(socs[every].min()), float(socs[every].max()), need)
    return out


def _r0_holds(nodes, basis, directions, spans) -> tuple[np.ndarray, np.ndarray]:
    """The r0 columns held and, for each, its source column: per direction, the basis
    nodes the complete pulses identify (:func:`_identified`) beyond the nodes nearest to
    the ends of the levels that pin r0 (the source: that nearest node). Nodes beyond the
    complete pulses stay free here and are held flat with the other resistances."""
    held, source = [], []
    for n_d, d in enumerate(directions):
        if d not in spans:
            continue
        lo, hi, low, high, _ = spans[d]
        ident = _identified(nodes, low, high)[np.searchsorted(nodes, basis)]
        k_lo = int(np.argmin(np.abs(basis - lo))) if lo > low else 0
        k_hi = int(np.argmin(np.abs(basis - hi))) if hi < high else basis.size - 1
        k_hi = max(k_hi, k_lo)
        for k in np.flatnonzero(ident):
            if k < k_lo or k > k_hi:
                held.append(n_d * basis.size + k)
                source.append(n_d * basis.size + (k_lo if k < k_lo else k_hi))
    return np.array(held, dtype=int), np.array(source, dtype=int)


def _identified(nodes, low, high):
    """Nodes the levels with a complete pulse pin down: from the node below the lowest
    level (its pulses discharge below the level's SOC) to the node at or above the
    highest."""
    lo = nodes[max(int(np.searchsorted(nodes, low - 1e-9, side="left")) - 1, 0)]
    hi = nodes[min(int(np.searchsorted(nodes, high - 1e-9, side="left")), nodes.size - 1)]
    return (nodes >= lo) & (nodes <= hi)


def _hold(v, ident):
    """Values outside the identified nodes held at the nearest identified one."""
    ix = np.flatnonzero(ident)
    out = v.copy()
    out[: ix[0]] = v[ix[0]]
    out[ix[-1] + 1:] = v[ix[-1]]
    return out


def _node_error(rec, prob, resid, nodes, mask, default):
    h = _hats(rec.soc[prob.rows], nodes) * mask[prob.rows][:, None]
    w2 = (prob.w ** 2)[:, None] * h
    tot = w2.sum(axis=0)
    e2 = (w2 * (resid[prob.rows] ** 2)[:, None]).sum(axis=0)
    return np.where(tot > 0, np.sqrt(e2 / np.maximum(tot, 1e-300)), default)


def _windows(series, complete, rec, resid):
    """Per SOC level: measured and fitted voltage from its first pulse to the next level."""
    from .points import soc_levels

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
