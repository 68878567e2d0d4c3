"""Whole-test fit (the "curve" method): one simulation-error fit of a complete pulse test.

Five DC-IR points within 10 s cannot see time constants of minutes; the record as a whole
(pulses, their rests and, where the cycler logged them in a file of their own, the SOC
steps between pulse sets, :func:`ecmgen.data.steps.merge_soc_steps`) can. The model is the
one :mod:`ecmgen.model.simulate` runs, with the OCV fixed to the given table (the rests'
OCV) and, per sample k (current i_k held over (t_{k-1}, t_k], positive on charge)::

    y_k = v_k - ocv(soc_k) = sum_j phi_j(soc_k) [r0_j i_k + r_fast_j x_fast,j,k + r_slow_j x_slow,j,k]
                             + r_diff x_diff,k + sum_l psi_l,k c_l
    x_fast,j : RC with tau_fast driven by phi_j(soc) h(i),  h(i) = i0 asinh(i / i0)  (or i)
    x_slow,j : RC with tau_slow driven by phi_j(soc) i;     x_diff: RC with tau_diff driven by i

(x_k = a_k x_{k-1} + (1 - a_k) u_k, a_k = exp(-dt_k / tau): the simulator's exact ZOH step;
h is the Butler-Volmer input of the fast branch, r_fast g(i) i with g = asinh(x)/x.)

Where the tables are free: phi_j are hat functions on the SOC levels of that direction's
complete pulses (the mean SOC half-way through them), so each resistance is piecewise linear
between the levels it was measured at and flat beyond; a direction's tables are never free
where only the other direction, or only a SOC move, passed. The tables are then written on
the model's SOC grid (0, 0.05, .., 1) by that interpolation. A direction without pulses is
said and takes the other's tables.

Blind to the OCV's level: psi_l are hat functions on every pulse level (one set after a
charge, one after a discharge when the test has both), with free coefficients c_l that the
model does not keep. An OCV table a few mV off, a SOC that drifts with a wrong capacity, or a
hysteresis offset is absorbed there instead of in r_slow and tau_slow, as if each pulse were
referenced to the rest before it. The offsets sit at the levels or, where that predicts a
left-out level better (a SOC move through a curved stretch of an OCV interpolated between
the rests), also half-way between them: the half-way set is judged first at the time
constants found with the levels' set, and searched for its own only where it predicts a
left-out level better there (on none of the shared data's configurations, each of which
keeps the levels' set, bench/accuracy_matrix.py). Rows count only over the SOC the pulses reached
(``SPAN_MARGIN`` beyond): past it the OCV is extrapolated. The tables are free at the
levels and hold the end level's value beyond them; a node within ``SPAN_MARGIN`` of the
levels' mid-pulse SOC range is identified (``converged`` in the tables).

Smooth by measurement: a second-difference penalty over each direction's levels (relative to
the column scale); its weight is chosen by leaving one SOC level out (the rows from the rest
before its first pulse to the end of its relaxation), fitting the others and measuring the
left-out rows after refitting only the nuisance offsets there, over a log grid of weights
(:func:`ecmgen.fit.curve_levels.choose_penalty`); the resistances are then solved again at
that weight, at the time constants the search found (:func:`_fit_time_constants`), and
with the penalty on ln r instead where that predicts the left-out levels better.

Time constants the test can show: tau_fast not shorter than the sampling in the pulses (and
reaching the longest pulse where that is longer than its range), the slow and diffusion
ones not longer than the longest relaxation after a current change. A direction whose
pulses run straight into another current (no rest after them) takes the other direction's
slow and diffusion pairs (:func:`ecmgen.fit.curve_levels.tied_slow_pairs`). A
diffusion pair whose tau_diff ends on a bound is dropped and the rest refitted; a fast or
slow pair on a bound is kept there and said (``fit.checks`` flags it).

The time constants, r_diff and i0 are one value per test. With pulses in both directions
each direction has its own resistances (shared time constants). After a gap the file does
not cover (the SOC moves of a pulse test without its step file) the states restart from free
values. Given the time constants the fit is linear: least squares on the normal equations,
resistances >= 0, nuisance offsets and restart states free.

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
favoured (``SLOW_START``,
:mod:`ecmgen.fit.curve_search`). The slow and diffusion pairs together stand for a spread of
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

from ..data.dcir import Pulse
from ..data.measure import TimeSeries
from ..data.ocv import OcvTable
from ..data.steps import merge_soc_steps
from ..errors import InputError
from ..parallel import one_blas_thread
from .curve_levels import (CV_TIE, both_ways, choose_penalty, data_tau_ranges,
                           level_fit_windows, level_nodes, level_windows, log_penalty,
                           log_references, node_error, ocv_node_sets, pulse_sampling_s, r0_holds,
                           r0_spans, second_difference, taus_on_bound, tied_slow_pairs)
from . import curve_record as _cr
from .curve_record import (Record, W_SPAN_S, hats, pulse_record, rc_response, rests_still_relax,
                           side_by_side)
from .curve_search import search as _search
from .lsq import solve_bounded

SOC_NODES = np.round(np.linspace(0.0, 1.0, 21), 10)
DIRECTIONS = ("charge", "discharge")
PENALTY = 1e-3             # second-difference penalty, relative to each block's column scale
# rows this far (SOC) beyond the pulses' own SOC still count; nodes this far beyond the
# levels' mid-pulse SOC are identified
SPAN_MARGIN = 0.01
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
    searches: list | None = None     # per OCV-offset node set, its time-constant searches

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


# ------------------------------------------------------------------- the linear problem
class _Problem:
    """The rows' weighted design blocks for any time constants, and the solve.

    Columns: [r0 per direction and level node | OCV correction per level | each branch's
    resistances per direction and node, then its restart states]. Each direction's
    resistances are hat functions on that direction's own pulse levels (``bases``); the
    OCV correction (hats on every level, free sign) is a nuisance the model does not keep:
    it makes the fit blind to the OCV's level and to SOC drift, as each pulse referenced
    to the rest before it is."""

    def __init__(self, rec: Record, bases: dict, ocv_nodes: np.ndarray, i0_a: float | None,
                 r0_spans: dict | None = None, levels: np.ndarray | None = None,
                 split_ocv: bool = False, soc_span: tuple | None = None,
                 current_factor=None, tied: dict | None = None):
        self.rec = rec
        self.tied = dict(tied or {})     # direction -> the one whose slow pairs it uses
        self.dirs = list(rec.dir_mask)
        self.ndir = len(self.dirs)
        self.bases = [np.asarray(bases[d], dtype=np.float64) for d in self.dirs]
        self.sizes = [b.size for b in self.bases]
        self.offsets = [int(o) for o in np.cumsum([0] + self.sizes)[:-1]]
        self.jd = int(sum(self.sizes))
        ocv_cols = hats(rec.soc, ocv_nodes)
        if self.ndir == 2 and split_ocv:
            # one correction after charge, one after discharge: blind to hysteresis too
            after_charge = _cr.after_charge(rec.i)
            ocv_cols = np.hstack([ocv_cols * after_charge[:, None],
                                  ocv_cols * ~after_charge[:, None]])
        self.n_ocv = int(ocv_cols.shape[1])
        self.r0_held, self.r0_source = r0_holds(self.bases, self.offsets, self.dirs,
                                                 r0_spans or {})
        hd = np.hstack([hats(rec.soc, b) * m[:, None]
                        for b, m in zip(self.bases, rec.dir_mask.values())])
        if current_factor is not None:
            # a resistance factor of the current (a current-dependent resistance effect)
            # on r0 and r_fast, as the model's step applies it
            drive = rec.i * current_factor(rec.i)
        elif i0_a is not None:
            drive = i0_a * np.arcsinh(rec.i / i0_a)
        else:
            drive = rec.i
        self.u_fast = np.multiply(hd, drive[:, None], order="F")
        u_lin = np.multiply(hd, rec.i[:, None], order="F")
        self.u_slow = u_lin
        masks = [self._pair_mask(d) for d in self.dirs]
        if self.tied:
            # a tied direction's columns carry no rows (they solve to 0); its rows drive
            # the source direction's columns
            self.u_slow = np.multiply(np.hstack([hats(rec.soc, b) * m[:, None]
                                                 for b, m in zip(self.bases, masks)]),
                                      rec.i[:, None], order="F")
        self.u_diff = np.asfortranarray(np.column_stack([m * rec.i for m in masks]))
        # r0 * i on the node basis, then the OCV correction
        u_r0 = u_lin if current_factor is None else self.u_fast
        self.r0_full = np.asfortranarray(np.hstack([u_r0, ocv_cols]))
        inside = np.ones(rec.t.size, bool) if soc_span is None else \
            (rec.soc >= soc_span[0]) & (rec.soc <= soc_span[1])
        self.rows = np.flatnonzero(rec.row & (rec.w > 0) & inside)
        self.w = rec.w[self.rows]
        self.yw = rec.y[self.rows] * self.w
        self.yy = float(self.yw @ self.yw)
        self.r0w = np.asfortranarray((self.r0_full.T[:, self.rows] * self.w).T)
        self.dd = [second_difference(b) for b in self.bases]
        self.dtd = [d.T @ d for d in self.dd]
        self.log_ref: dict = {}          # column start -> values the penalty on ln r is about
        self.penalty = PENALTY
        self.cv_sse = float("inf")      # held-out error leaving one level out (the fit's)
        # the SOC level (index) each row belongs to, -1 between levels (leave-one-out)
        self.level = np.full(self.rows.size, -1) if levels is None else levels[self.rows]
        self._cache, self._taus, self.searches = _cr.ResponseCache(), _cr.RevisitedTaus(), {}
        self._normal = _cr.NormalEquations()

    def _pair_mask(self, d: str) -> np.ndarray:
        """The rows driving direction ``d``'s slow and diffusion columns."""
        if d in self.tied:
            return np.zeros(self.rec.t.size, bool)
        m = self.rec.dir_mask[d].copy()
        for t, src in self.tied.items():
            if src == d:
                m |= self.rec.dir_mask[t]
        return m

    def block(self, kind: str, tau: float, full: bool = False) -> np.ndarray:
        """The unit responses of branch ``kind`` at ``tau``: weighted rows (cached; the
        searches revisit time constants), or every kept sample (``full``)."""
        if full:
            return rc_response(self.rec, tau, self._inputs(kind))
        return self.block_met(kind, self._taus.tau(kind, tau))

    def _inputs(self, kind: str) -> np.ndarray:
        return {"fast": self.u_fast, "slow": self.u_slow, "diff": self.u_diff}[kind]

    def block_met(self, kind: str, tau: float) -> np.ndarray:
        """:meth:`block` at a time constant already met (:meth:`taus_met`)."""
        cached = self._cache.get((kind, tau))
        if cached is not None:
            return cached
        resp = rc_response(self.rec, tau, self._inputs(kind))
        return self._cache.put((kind, tau), self._weighted_rows(
            resp, np.empty((self.rows.size, resp.shape[1]), order="F")))

    def block_into(self, kind: str, tau: float, out: np.ndarray) -> None:
        """:meth:`block_met` written into ``out`` (a design buffer's columns): a block not
        cached is made there, not kept (a search's evaluations rarely meet a time constant
        again), the same values without the copy."""
        cached = self._cache.get((kind, tau))
        if cached is not None:
            out[...] = cached
            return
        self._weighted_rows(rc_response(self.rec, tau, self._inputs(kind)), out)

    def _weighted_rows(self, resp: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The rows of the responses ``resp`` times their weights, into ``out`` (column-
        major): column by column, each read and written in order (a row gather across the
        columns of a column-major array and its transposing copy cost ten times more)."""
        for j in range(resp.shape[1]):
            np.multiply(resp[:, j].take(self.rows), self.w, out=out[:, j])
        return out

    def taus_met(self, kinds, taus) -> tuple:
        """The time constants the blocks of ``kinds`` at ``taus`` are made at (the first
        met a rounding away, :class:`ecmgen.fit.curve_record.RevisitedTaus`), in order."""
        return tuple(self._taus.tau(k, t) for k, t in zip(kinds, taus))

    def design(self, kinds, met) -> np.ndarray:
        """The weighted design [r0 columns | a block per branch] at time constants met."""
        return side_by_side([self.r0w] + [self.block_met(k, t) for k, t in zip(kinds, met)])

    def normal(self, kinds, met, z: np.ndarray | None = None):
        """(Z'Z, Z'y) of :meth:`design` (``z``, if already made)."""
        return self._normal.get(self, kinds, met, z)

    def drop_design_buffers(self) -> None:
        self._normal.drop_buffers()

    def width(self, kind: str) -> int:
        """Columns of a branch block: its resistances, then one free restart state per gap."""
        return (self.jd if kind != "diff" else self.ndir) + self.rec.restart.size

    def layout(self, kinds) -> dict:
        """For the columns [r0 | OCV correction | block of each kind]: where each part
        starts, the free columns (OCV correction, restart states), and the (start, size,
        direction) of each resistance run to smooth over SOC."""
        start, off = {"r0": 0, "ocv": self.jd}, self.jd + self.n_ocv
        free = [np.zeros(self.jd, bool), np.ones(self.n_ocv, bool)]
        for k in kinds:
            start[k] = off
            nr = self.width(k) - self.rec.restart.size
            free.append(np.concatenate([np.zeros(nr, bool), np.ones(self.rec.restart.size, bool)]))
            off += self.width(k)
        smooth = [(start[k] + self.offsets[d], self.sizes[d], d)
                  for k in ("r0", "fast", "slow") if k in start for d in range(self.ndir)
                  if self.sizes[d] >= 3]
        return dict(start=start, free=np.concatenate(free), smooth=smooth)

    def regularised(self, gram: np.ndarray, g: np.ndarray, lay: dict,
                    penalty: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """(gram, g) + the second-difference penalty (relative to each run's column scale)
        + a tiny ridge (columns no row sees, e.g. with a short relax_s, would be singular).
        A run with references in ``log_ref`` has its penalty on ln r instead, linearised
        about them (:func:`log_penalty`); the third term is then its constant part."""
        return self.regularised_many(gram, g, lay, [self.penalty if penalty is None
                                                    else penalty])[0]

    def regularised_many(self, gram: np.ndarray, g: np.ndarray, lay: dict, penalties) -> list:
        """:meth:`regularised` at each weight of ``penalties`` (its terms worked out once)."""
        scale = np.sqrt(np.maximum(np.diag(gram), 0.0))
        runs = []
        for a, n, d in lay["smooth"]:
            ref = self.log_ref.get(a)
            terms = (self.dtd[d], None, 0.0) if ref is None else log_penalty(self.dd[d], ref)
            runs.append((slice(a, a + n), float(np.mean(scale[a:a + n])) ** 2, *terms))
        ridge = 1e-12 * float(np.mean(np.diag(gram))) + 1e-300
        out = []
        for lam in penalties:
            m, q, k = gram.copy(), g.copy(), 0.0
            for sl, s2, pm, pq, pk in runs:
                c = lam * s2
                m[sl, sl] += c * pm
                if pq is not None:
                    q[sl] += c * pq
                    k += c * pk
            m[np.diag_indices_from(m)] += ridge
            out.append((m, q, k))
        return out

    def solve(self, gram: np.ndarray, g: np.ndarray, lay: dict, hold_r0: bool = False
              ) -> tuple[np.ndarray, float]:
        """Penalised least squares, resistances >= 0, OCV correction and restart states
        free; returns the solution and the objective (weighted SSE + penalty). With
        ``hold_r0`` the held r0 nodes and their sources are then fixed at the sources'
        values and the rest solved again."""
        m, g, k = self.regularised(gram, g, lay)
        x = solve_bounded(m, g, lay["free"])
        if hold_r0 and self.r0_held.size:
            fixed = np.zeros(x.size, bool)
            fixed[self.r0_held] = fixed[self.r0_source] = True
            x[self.r0_held] = x[self.r0_source]
            ix = np.ix_(~fixed, ~fixed)
            x[~fixed] = solve_bounded(m[ix], g[~fixed] - m[np.ix_(~fixed, fixed)] @ x[fixed],
                                      lay["free"][~fixed])
        return x, self.yy + k - 2.0 * float(g @ x) + float(x @ m @ x)


# ------------------------------------------------------------------------------ the fit
@dataclass(frozen=True)
class CurveOptions:
    """The curve fit's settings (the record, its OCV and what other fits found are
    :func:`fit_pulse_curves`' own arguments).

    diffusion        fit the third (diffusion) RC pair
    relax_s          rest rows up to this long after each current change
    rows_per_decade, min_weight_s   the rest rows' density and a row's least weight
                     (:func:`ecmgen.fit.curve_record.pulse_record`)
    tau_*_s          search ranges (s); the fit keeps tau_fast < tau_slow < tau_diff
    soc_nodes        the SOC grid the tables are written on
    direction_deadband_a   |i| at or below it keeps the last direction, as the simulator's
                     rule (None: 1 % of the capacity in A)
    blocks_both_ways the pulses are blocks of a dynamic test (:mod:`ecmgen.data.dynamic`):
                     each is a level of both directions where the record runs both ways
                     (:func:`_both_ways`), and the OCV offsets are not split by the last
                     current's direction (a drive profile flips it every few seconds)
    """

    diffusion: bool = True
    relax_s: float = 1800.0
    rows_per_decade: float = 20.0
    min_weight_s: float = W_SPAN_S[0]
    tau_fast_s: tuple[float, float] = (0.1, 10.0)
    tau_slow_s: tuple[float, float] = (5.0, 500.0)
    tau_diff_s: tuple[float, float] = (150.0, 3000.0)
    soc_nodes: tuple[float, ...] = tuple(SOC_NODES.tolist())
    direction_deadband_a: float | None = None
    blocks_both_ways: bool = False


@one_blas_thread
def fit_pulse_curves(series: TimeSeries, pulses: list[Pulse], ocv: OcvTable,
                     capacity_ah: float, options: CurveOptions = CurveOptions(), *,
                     i0_a: float | None = None, steps: TimeSeries | None = None,
                     current_factor=None, neighbour_taus: dict | None = None,
                     searches: list | None = None, progress=None) -> CurveFit:
    """Fit one pulse test as a whole (module docstring): the curve method.

    series, pulses   the pulse test and its pulses (:func:`ecmgen.data.dcir.find_pulses`;
                     their SOCs fix the record's SOC axis)
    ocv              the OCV the model will use (held fixed; e.g. the rests' OCV)
    options          the fit's settings (:class:`CurveOptions`)
    i0_a             Butler-Volmer current of the fast branch (:func:`ecmgen.fit.rate.
                     fit_exchange_current`); None: linear fast branch
    steps            the record of the SOC steps the pulse test left out (merged into its
                     gaps, :func:`ecmgen.data.steps.merge_soc_steps`); None: the gaps are rests
    current_factor   f(i) -> resistance factor at current i (array in, array out) applied
                     to r0 and r_fast as a ``current_dependent_resistance`` effect of the
                     model does; the tables are then its values at zero current (not with i0_a)
    neighbour_taus   time constants from the tests of the same cell at the temperatures on
                     either side ({"fast": s, "slow": s, "diff": s}; one model over
                     temperature): kept in place of the test's own where they predict a
                     left-out level better (:func:`_neighbour_choice`)
    searches         the ``searches`` of an earlier fit of the same test with the same
                     settings: its time-constant searches are taken, not run again
    progress         called as progress(done, total)

    Long: most of it is this docstring, the reference of its ten parameters.
    """
    relax_s, blocks_both_ways = options.relax_s, options.blocks_both_ways
    ranges = _checked_ranges(options, i0_a, current_factor)
    nodes = np.asarray(options.soc_nodes, dtype=np.float64)
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
    deadband = (0.01 * capacity_ah if options.direction_deadband_a is None
                else options.direction_deadband_a)
    blocks = complete
    if blocks_both_ways:
        complete, n = both_ways(complete, series, deadband)
        notes.extend(n)
    directions = tuple(d for d in DIRECTIONS if any(p.direction == d for p in complete))
    rec = pulse_record(record, soc0, ocv, capacity_ah, directions=directions,
                       deadband_a=deadband, relax_s=relax_s,
                       rows_per_decade=options.rows_per_decade,
                       min_weight_s=options.min_weight_s)
    ranges, n = data_tau_ranges(ranges, pulse_sampling_s(series, complete), rec.rest_used_s,
                                None if blocks_both_ways else
                                max(p.duration_s for p in complete))
    notes.extend(n)
    spans = r0_spans(complete, directions, R0_MIN_RATES)
    tied, n = ({}, []) if blocks_both_ways else tied_slow_pairs(complete, series.time_s)
    notes.extend(n)
    searches = [] if searches is None else searches
    prob, got, n = _fit_problem(rec, complete, directions, capacity_ah, i0_a, spans, ranges,
                                series, progress, may_split=not blocks_both_ways,
                                current_factor=current_factor, tied=tied,
                                neighbour_taus=neighbour_taus, searches=searches)
    notes.extend(n)
    taus, x, cost, n_eval, search_notes, ranges = got
    notes.extend(search_notes)
    kinds = list(ranges)
    diffusion = "diff" in ranges
    rms = float(np.sqrt(max(cost, 0.0) / float(prob.w @ prob.w)))
    # the fitted voltage at every kept sample (plots, per-node errors)
    full = side_by_side([prob.r0_full] + [prob.block(k, taus[k], full=True) for k in kinds])
    fitted = rec.y - full @ x                            # residual, measured minus fitted
    fits = _direction_fits(prob, x, kinds, nodes, spans, fitted, rms, notes)
    if len(directions) == 1:
        other = "charge" if directions[0] == "discharge" else "discharge"
        fits[other] = fits[directions[0]]
        notes.append(f"curve: the test has {directions[0]} pulses only: the {other} "
                     f"parameters are the {directions[0]} parameters")
    shown = taus if diffusion else {k: taus[k] for k in ("fast", "slow")}
    notes.append(_fit_note(prob, rec, n_eval, shown, i0_a, rms, steps is not None))
    return CurveFit(nodes.copy(), fits["charge"], fits["discharge"], directions,
                    float(taus["fast"]), float(taus["slow"]),
                    float(taus["diff"]) if diffusion else None, i0_a, rms,
                    int(prob.rows.size), tuple(notes),
                    level_fit_windows(series, blocks, rec, fitted), dict(ranges),
                    float(rec.rest_used_s), searches)


def _checked_ranges(options: CurveOptions, i0_a, current_factor) -> dict:
    """The time-constant ranges searched (and "diff" with the diffusion pair), checked."""
    if i0_a is not None and current_factor is not None:
        raise ValueError("give i0_a or current_factor, not both")
    if i0_a is not None and not (np.isfinite(i0_a) and i0_a > 0):
        raise ValueError(f"i0_a must be positive, got {i0_a!r}")
    ranges = {"fast": options.tau_fast_s, "slow": options.tau_slow_s}
    if options.diffusion:
        ranges["diff"] = options.tau_diff_s
    for k, (lo, hi) in ranges.items():
        if not (0 < lo < hi and np.isfinite(hi)):
            raise ValueError(f"tau_{k}_s range must be 0 < lo < hi, got {(lo, hi)!r}")
    return ranges


def _fit_note(prob, rec: Record, n_eval: int, taus: dict, i0_a, rms: float,
              merged: bool) -> str:
    """The build's note on a whole-test fit (tau_diff where ``taus`` has it)."""
    levels = " / ".join(f"{b.size} {d}" for d, b in zip(prob.dirs, prob.bases))
    return (f"curve: whole-test fit of {prob.rows.size} samples ({n_eval} time-constant "
            f"evaluations), rests used up to {rec.rest_used_s:.0f} s after each current "
            f"change{', the SOC-step file merged' if merged else ''}, tables free at the "
            f"{levels} pulse levels, smoothing weight {prob.penalty:.2g} (leave one level "
            f"out): tau_fast {taus['fast']:.3g} s, tau_slow {taus['slow']:.3g} s"
            + (f", tau_diff {taus['diff']:.3g} s" if "diff" in taus else "")
            + (f", Butler-Volmer i0 {i0_a:.3g} A on the fast branch" if i0_a else "")
            + f"; fit RMS {rms * 1e3:.2f} mV")


def _fit_problem(rec: Record, complete, directions, capacity_ah: float, i0_a, spans: dict,
                 ranges: dict, series: TimeSeries, progress=None, may_split: bool = True,
                 current_factor=None, tied=None, neighbour_taus=None, searches=None):
    """The linear problem of the record and its fit (:func:`_fit_time_constants`), with the
    OCV offsets at the levels or also half-way between them (a SOC move passes where the
    OCV table is interpolated between the rests, and its curvature there must not go into
    r(soc)): the one that predicts a left-out level better. Returns (problem, the fit's
    tuple, notes)."""
    bases = {d: level_nodes(complete, d, capacity_ah) for d in directions}
    ocv_nodes, levels = level_windows(complete, series.time_s, rec.t)
    # rows only over the SOC the pulses measured: beyond it the tables are held flat and the
    # OCV is extrapolated (the discharge to the cut-off after the last level)
    ends = [p.soc + p.current_a * p.duration_s / 3600.0 / capacity_ah for p in complete]
    span = (min(min(ends), min(p.soc for p in complete)) - SPAN_MARGIN,
            max(max(ends), max(p.soc for p in complete)) + SPAN_MARGIN)
    # a correction per direction of the last current needs the current dependence (two
    # C-rates at a level) to tell it from r0 i
    split = may_split and all(len({p.c_rate for p in complete if p.direction == d}) >= 2
                              for d in directions)
    probs = []
    for nodes_ocv in ocv_node_sets(ocv_nodes):
        prob = _Problem(rec, bases, nodes_ocv, i0_a, spans, levels, split_ocv=split,
                        soc_span=span, current_factor=current_factor, tied=tied)
        if prob.rows.size < 4 * (prob.jd + prob.n_ocv):
            raise InputError(series.source, f"only {prob.rows.size} samples to fit the curve "
                                            "method on")
        if probs:
            _cr.share_responses(prob, probs[0])
        prob.searches = _cr.node_set_searches(searches, len(probs))
        probs.append(prob)
    p0 = probs[0]
    f0 = _fit_time_constants(p0, ranges, progress, neighbour_taus)
    if len(probs) == 1:
        return p0, f0, []
    p1 = probs[1]
    # the offsets half-way too, judged first at the time constants just found: their own
    # search only where they predict a left-out level better there (else they cannot win)
    cv_at = _held_out(p1, list(f0[5]), f0[0])[2]
    p1._taus.restore({})            # the screen leaves no time constant met behind
    f1 = _fit_time_constants(p1, ranges, None, neighbour_taus) if cv_at < p0.cv_sse else None
    use_mid = f1 is not None and p1.cv_sse < p0.cv_sse
    prob, got = (p1, f1) if use_mid else (p0, f0)
    notes = []
    if np.isfinite(p0.cv_sse) and p0.cv_sse > 0:
        ratio = (p1.cv_sse if f1 is not None else cv_at) / p0.cv_sse
        notes.append(f"curve: OCV offsets {'also half-way between' if use_mid else 'at'} the "
                     f"levels (leaving one level out: {ratio:.3g} x the error of offsets at "
                     "the levels only" + ("" if f1 is not None else ", at their time constants")
                     + ")")
    return prob, got[:3] + (f0[3] + (f1[3] if f1 is not None else 0),) + got[4:], notes


def _direction_fits(prob: _Problem, x: np.ndarray, kinds, nodes: np.ndarray, spans: dict,
                    fitted: np.ndarray, rms: float, notes: list) -> dict:
    """Each fitted direction's tables on the output SOC ``nodes`` (interpolated between its
    levels, flat beyond), with notes on what was held."""
    rec = prob.rec
    at = prob.layout(kinds)["start"]
    fits = {}
    for n_d, d in enumerate(rec.dir_mask):
        a0, nb, basis = prob.offsets[n_d], prob.sizes[n_d], prob.bases[n_d]
        r0, rf = (np.interp(nodes, basis, x[at[k] + a0:at[k] + a0 + nb])
                  for k in ("r0", "fast"))
        n_s = prob.dirs.index(prob.tied.get(d, d))     # the direction whose slow pairs
        s0, ns = prob.offsets[n_s], prob.sizes[n_s]
        rs = np.interp(nodes, prob.bases[n_s], x[at["slow"] + s0:at["slow"] + s0 + ns])
        rd = float(x[at["diff"] + n_s]) if "diff" in at else None
        # the nodes the levels pin down (within SPAN_MARGIN of their mid-pulse SOC range);
        # beyond it the table holds its end level's value
        ident = (nodes >= basis[0] - SPAN_MARGIN) & (nodes <= basis[-1] + SPAN_MARGIN)
        if not ident.all():
            held = nodes[~ident]
            notes.append(f"curve: {d} r0/r_fast/r_slow held flat at SOC "
                         f"{', '.join(f'{s:g}' for s in held)} (outside the SOC levels "
                         f"with a complete pulse, {basis[0]:.3f} .. {basis[-1]:.3f})")
        held = basis[prob.r0_held[(prob.r0_held >= a0) & (prob.r0_held < a0 + nb)] - a0]
        if held.size:
            lo, hi, _, _, need = spans[d]
            notes.append(f"curve: {d} r0 held at SOC {', '.join(f'{s:.3g}' for s in held)} "
                         f"(r0 is pinned by the levels with complete pulses at {need} "
                         f"or more C-rates, {lo:.3f} .. {hi:.3f})")
        err = node_error(rec, prob, fitted, nodes, rec.dir_mask[d], rms)
        fits[d] = DirectionFit(r0, rf, rs, rd, err, ident)
    return fits





def _solve_at(prob: _Problem, kinds, taus: dict, made: tuple | None = None):
    """The resistances at given time constants (r0 held as after the search); ``made``:
    their weighted design columns and time constants met (:func:`_design`), if made."""
    z, met = made if made is not None else (None, prob.taus_met(kinds, [taus[k] for k in kinds]))
    return prob.solve(*prob.normal(kinds, met, z), prob.layout(kinds), hold_r0=True)


def _design(prob: _Problem, kinds, taus: dict) -> tuple:
    """(the weighted design columns at ``taus``, the time constants met, Z'Z and Z'y)."""
    met = prob.taus_met(kinds, [taus[k] for k in kinds])
    z = prob.design(kinds, met)
    return z, met, prob.normal(kinds, met, z)


def _held_out(prob: _Problem, kinds, taus: dict) -> tuple[tuple, float, float]:
    """At ``taus``: the weighted design columns and time constants met, the smoothing
    weight chosen by leaving one level out and the held-out error at it (inf with too few
    levels to leave one out)."""
    z, met, normal = _design(prob, kinds, taus)
    lam, errors = choose_penalty(prob, z, prob.layout(kinds), normal=normal)
    return (z, met), lam, errors.get(lam, float("inf")) if errors else float("inf")


def _neighbour_choice(prob: _Problem, ranges: dict, taus: dict, fit: tuple, other: dict,
                      notes: list) -> tuple[dict, np.ndarray, float]:
    """The test's own time constants (``taus``, ``fit``: its x and objective) or ``other``,
    those of the tests on either side in temperature, whichever predicts a left-out level
    better (:func:`choose_penalty`, each at its own weight). A test's objective is flat
    between local minima (the -10 degC Panasonic test: tau_diff 283 s against 507 / 672 s at
    0.6 / -19.9 degC): the held-out error says whether the test tells its own apart. The
    search's time constants saw every level, the neighbours' none, so a tie keeps the own."""
    kinds = list(ranges)
    if set(other) != set(kinds) or not np.isfinite(prob.cv_sse):
        return taus, fit[0], fit[1]
    words = ", ".join(f"tau_{k} {other[k]:.3g} s" for k in kinds)
    if any(not ranges[k][0] < other[k] < ranges[k][1] for k in kinds):
        notes.append(f"curve: the neighbouring tests' time constants ({words}) lie beyond "
                     "the ranges this test can show: the test's own kept")
        return taus, fit[0], fit[1]
    z, lam, cv = _held_out(prob, kinds, other)
    ratio = f"{cv / prob.cv_sse:.3g} x" if prob.cv_sse > 0 else "no"
    if not cv < prob.cv_sse:
        notes.append(f"curve: the neighbouring tests' time constants ({words}) predict a "
                     f"left-out level no better ({ratio} the error): the test's own kept")
        return taus, fit[0], fit[1]
    notes.append(f"curve: the neighbouring tests' time constants ({words}; ln tau linear in "
                 f"1/T between them) predict a left-out level better ({ratio} the error of "
                 "the test's own): kept")
    prob.penalty, prob.cv_sse = lam, cv
    x, cost = _solve_at(prob, kinds, other, z)
    return other, x, cost


def _fit_time_constants(prob: _Problem, ranges: dict, progress=None, neighbour_taus=None):
    """The time-constant search (at the small default smoothing), then the smoothing weight
    chosen by leaving one level out and the resistances solved again with it at the same
    time constants, then what a time constant on its bound means: the diffusion pair on a
    bound is dropped where the two pairs alone predict a left-out level as well
    (:func:`_diffusion_on_bound`); any pair kept on a bound is fixed there, with a note. Returns (taus, x, objective, evaluations, notes, ranges actually used). With
    ``neighbour_taus``, those in place of the search's where they predict a left-out level
    better (:func:`_neighbour_choice`), before the bounds are looked at.

    The search is not repeated at the chosen weight: a stronger penalty on the SOC shape
    lets the time constants make up for it, and the tests' time constants then wander
    between local minima from one temperature to the next (measured on the shared
    Panasonic tests: tau_slow 33 / 85 / 40 / 23 s at 25.7 / 0.6 / -9.9 / -19.9 degC with the
    search repeated, 36 / 35 / 14 / 19 s without; demo cycles mean MAE 29.3 vs 27.3 mV,
    leave one temperature out 66.3 vs 56.9 mV)."""
    taus, x, cost, n_eval, notes = _cr.remembered(_search, prob, ranges, progress)
    kinds = list(ranges)
    z, lam, prob.cv_sse = _held_out(prob, kinds, taus)
    if lam != prob.penalty:
        prob.penalty = lam
        x, cost = _solve_at(prob, kinds, taus, z)
    if neighbour_taus is not None:
        taus, x, cost = _neighbour_choice(prob, ranges, taus, (x, cost), neighbour_taus, notes)
    on_bound = taus_on_bound(taus, ranges)
    if "diff" in on_bound:
        taus, x, cost, n2, ranges = _diffusion_on_bound(prob, ranges, taus, (x, cost), notes)
        n_eval += n2
        on_bound = taus_on_bound(taus, ranges)
    for k in on_bound:
        lo, hi = ranges[k]
        notes.append(f"curve: tau_{k} {taus[k]:.3g} s is on its search bound ({lo:.3g} .. "
                     f"{hi:.3g} s): {'shorter' if taus[k] <= lo * 1.01 else 'longer'} than "
                     "the test resolves; kept fixed there")
    x, cost = _smooth_in_log(prob, list(ranges), taus, (x, cost))
    return taus, x, cost, n_eval, notes, ranges


def _diffusion_on_bound(prob: _Problem, ranges: dict, taus: dict, fit: tuple, notes: list):
    """The diffusion pair whose tau_diff ended on a bound, kept there where it predicts a
    left-out level better by more than ``CV_TIE`` with a resistance above zero, and where
    the test shows something it can stand for; else dropped, the two pairs searched and
    kept.

    On the lower bound the test resolves a third pair faster than the diffusion range. On
    the shared Panasonic pulse tests without their SOC-step files the pair ends on 150 s at
    0.6 .. -19.9 degC and predicts the left-out levels 7-22 % better than two pairs (fit RMS
    6.7 against 9.9 mV at 0.6 degC): dropping it by the bound alone left the drive cycles
    without the slow polarisation.

    On the upper bound (as slow as the longest relaxation) the pair stands for a process
    slower than the test resolves, and is kept only where the rests show one: the two
    pairs' residual still drifting the relaxation's way at the rests' ends
    (:func:`~ecmgen.fit.curve_record.rests_still_relax`, a sign test at 99 %). Leaving a
    level out alone is no judge there: a 2RC synthetic cell (nine levels, 0.5 mV noise)
    kept a spurious pair by it and its cycle error went 0.7 -> 7 mV; its rests drift
    either way (p 0.06 .. 0.99 over four seeds). The Panasonic 25 degC test without its
    step files drifts at 40 of 54 rests (p = 0.0003).
    Returns (taus, x, objective, evaluations, ranges)."""
    lo, hi = ranges["diff"]
    with_diff = (taus, fit[0], fit[1], prob.penalty, prob.cv_sse)
    two = {k: v for k, v in ranges.items() if k != "diff"}
    prob.penalty = PENALTY
    taus2, _, _, n_eval, more = _cr.remembered(_search, prob, two)
    z, lam, cv = _held_out(prob, list(two), taus2)
    prob.penalty, prob.cv_sse = lam, cv
    where = f"{taus['diff']:.3g} s, on its bound ({lo:.3g} .. {hi:.3g} s)"
    r_diff = fit[0][prob.layout(list(ranges))["start"]["diff"]:][:prob.ndir]
    lower = taus["diff"] <= lo * 1.01
    better = with_diff[4] < (1.0 - CV_TIE) * cv and np.all(r_diff > 0)
    two_fit = drift = None
    if not lower:       # the rests judged on the two pairs' residual
        two_fit = _solve_at(prob, list(two), taus2, z)
        drift = rests_still_relax(prob.rec, prob.rows, (prob.yw - z[0] @ two_fit[0]) / prob.w)
    ratio = f"({with_diff[4] / cv:.3g} x their error)"
    if better and (lower or drift.shown):
        taus, x, cost, prob.penalty, prob.cv_sse = with_diff
        notes.append(f"curve: the diffusion pair's tau_diff went to {where}: "
                     + ("a third pair faster than the diffusion range, kept there as it "
                        f"predicts a left-out level better than the two pairs alone {ratio}"
                        if lower else
                        f"{drift.words()}, and the pair predicts a left-out level better "
                        f"{ratio}: kept there, a lower bound on its time constant"))
        return taus, x, cost, n_eval, ranges
    x, cost = two_fit if two_fit is not None else _solve_at(prob, list(two), taus2, z)
    notes.extend(more)
    why = ("it predicts a left-out level no better than the two pairs alone" if lower else
           f"the test does not resolve it ({drift.words()}"
           + ("" if better else f"; with it a left-out level {with_diff[4] / cv:.3g} x the "
                                    "error") + ")")
    notes.append(f"curve: the diffusion pair's tau_diff went to {where}: {why}; dropped, the "
                 "two pairs refitted")
    return taus2, x, cost, n_eval, two


def _smooth_in_log(prob: _Problem, kinds, taus: dict, fit: tuple):
    """``fit`` (x, objective) as it is, or the resistances again with the penalty on ln r
    where that predicts the levels left out better (one Gauss-Newton step about ``fit``,
    the weight chosen again leaving one level out). Resistances that span a decade over
    SOC rise exponentially towards empty and in the cold: a penalty on r flattens the
    steep end and bends the table at its knee. The choice between the OCV correction's
    node sets stays with the penalty on r, so that it does not depend on r0's hold."""
    z, met, normal = _design(prob, kinds, taus)
    lay = prob.layout(kinds)
    linear = prob.penalty
    before = choose_penalty(prob, z, lay, (linear,), normal)[1].get(linear, float("inf"))
    prob.log_ref = log_references(fit[0], lay["smooth"])
    lam, errors = choose_penalty(prob, z, lay, normal=normal)
    if not errors or errors[lam] >= before:
        prob.log_ref, prob.penalty = {}, linear
        return fit
    prob.penalty = lam
    return _solve_at(prob, kinds, taus, (z, met))
