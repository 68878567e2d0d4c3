"""Find where simulation and measurement disagree, name the missing effect, add it.

``diagnose(base_model, fit_series, judge_series=None)``:

1. simulate the base model over the measured cycle and take the residual
   (measured - simulated voltage);
2. test each effect's *signature* on the fit part: the least-squares share of the
   residual explained by the effect's first-order voltage sensitivity (residual against
   the sign and history of the current for ``hysteresis``, against |I| for
   ``current_dependent_resistance``, against low-pass-filtered current for ``extra_rc``,
   against Ah throughput for ``capacity_error``, against temperature for
   ``temperature_dependence``);
3. greedily, one effect at a time: add each remaining candidate, fit its parameters on
   the fit part (least squares on the voltage time series with a soft-L1 loss; casadi
   forward sensitivities of the discrete step of :mod:`ecmgen.model.effects` give the exact
   Jacobian, scipy's bounded trust-region Gauss-Newton the steps; a few starts from
   the signature regressions for the nonconvex shape parameters), and judge every candidate on
   the held-out part, simulated at full resolution with :func:`ecmgen.model.simulate.simulate`.
   A candidate passes when the held-out MAE falls by at least ``min_rel_gain`` (relative),
   by at least ``min_gain_noise`` times the voltage noise (estimated from the rests) and
   by more than noise explains: the lower ``confidence`` bound of a circular block
   bootstrap of the per-sample gain |e_before| - |e_after| must be positive. Of the
   passing candidates the one with the lowest MAE over all the data (fit and held-out
   parts) is added, and all added effects are refitted jointly; when none passes, the
   search stops and nothing more is named.

Besides the model's effects, the faults of the record are candidates
(:mod:`ecmgen.diagnosis.corrections`: a current sensor's offset and gain, an OCV table
that is off); one that is added corrects the data the later rounds fit and judge (an
offset the record's rests read goes first). A candidate is named only where it beats its
look-alikes (the other candidates of its round that it does not beat, each judged again in
its place among all that was added at the end, and those that beat it beyond their bounds)
by the held-out test; otherwise the verdict is "X or Y - the data cannot tell them apart"
(:mod:`ecmgen.diagnosis.lookalike`). An extra RC found as a third pair of the pulse test
is named only where that test's shape tells it from solid diffusion
(:mod:`ecmgen.diagnosis.diffusion`).

The held-out part is ``judge_series`` when given (a second cycle), else the last
``1 - split`` of the fit cycle's duration (the model is simulated over the whole cycle;
only the first part is fitted).

The candidate problems of step 3 are :mod:`ecmgen.diagnosis.problems`; what diagnose
writes (model, report, plots) is :mod:`ecmgen.diagnosis.output`.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..data.measure import TimeSeries
from ..model import effects as fx
from ..model.model import EcmModel
from ..model.simulate import initial_soc, simulate
from ..parallel import one_blas_thread
from . import corrections as cx
from .options import CANDIDATE_NAMES, diagnose_options  # noqa: F401
from .lookalike import (beyond_bounds, block_bootstrap_low, lookalikes,  # noqa: F401
                        near_rivals, rivals, told_apart, with_beyond)
from .prune import Fitted, still_needed
from .problems import _Problem, _fit, _fixed, _specs
from .diffusion import told_from_diffusion
from .refits import PulseRefit, hysteresis_on_refitted_base, third_pair
from .result import (UNEXPLAINED_RATIO, Candidate, DiagnoseResult, DiagnoseStep,  # noqa: F401
                     Signature, explained_floor)
from .signatures import (JUDGE_SOC_MIN, MIN_JUDGED, NothingToJudge,  # noqa: F401
                         _context, _judged_samples, _lowpass, _mae, _on_bound, _starts,
                         decimate, noise_std, signatures)

FIT_ERRORS = (ValueError, ArithmeticError, RuntimeError)   # a candidate's fit that failed


@dataclass(frozen=True)
class SearchSettings:
    """How :func:`diagnose` searches and judges (the keyword arguments it takes).

    split            the fitted fraction of the fit cycle when no judge cycle is given
    candidates       effect names to try (default all); effects already in the base model
                     are kept as they are and not tried again
    max_effects      at most this many effects are added
    min_rel_gain, min_gain_noise, min_gain_v, confidence
                     the held-out test (module doc); ``block_s`` is the bootstrap block
                     length (default: 1/20 of the held-out duration, at least 60 s)
    judge_soc_min    held-out samples where the base model's SOC is at or below this are
                     not judged (the end-of-discharge knee of the OCV: there the error
                     measures where the cell ends, not the effect; the validation's MAE
                     above 10 % SOC leaves them out for the same reason);
                     :class:`NothingToJudge` when fewer than ``MIN_JUDGED`` are above
    max_fit_samples  longer fit parts are block-averaged to this many samples for the
                     parameter fits (judging is always at full resolution)
    max_nfev         Gauss-Newton iterations per fit
    loss_scale_v     scale of the soft-L1 loss of the fits (default: max(3 x noise,
                     half the base MAE on the fit part, 1 mV))
    seed             of the block bootstrap
    """

    split: float = 0.6
    candidates: tuple = CANDIDATE_NAMES
    max_effects: int = 4
    min_rel_gain: float = 0.08
    min_gain_noise: float = 1.0
    min_gain_v: float = 2e-4
    confidence: float = 0.99
    block_s: float | None = None
    judge_soc_min: float = JUDGE_SOC_MIN
    max_fit_samples: int = 12000
    max_nfev: int = 40
    loss_scale_v: float | None = None
    seed: int = 0


SETTING_NAMES = tuple(f.name for f in fields(SearchSettings))


@one_blas_thread
def diagnose(base_model: EcmModel, fit_series: TimeSeries,
             judge_series: TimeSeries | None = None, soc0: float | None = None,
             judge_soc0: float | None = None, *, settings: SearchSettings | None = None,
             progress: Callable[[str], None] | None = None, base_refits: dict | None = None,
             pulse_refit: PulseRefit | None = None, **overrides) -> DiagnoseResult:
    """Find the effects missing from ``base_model`` on ``fit_series`` (see module doc).

    judge_series     a second cycle to judge on; None: the last ``1 - split`` of the
                     fit cycle's duration is held out
    soc0, judge_soc0 start SOC of the cycles (default: from the OCV of the first rested
                     voltage, :func:`ecmgen.model.simulate.initial_soc`)
    settings         how it searches and judges (:class:`SearchSettings`); ``overrides``
                     replace single fields of it (``candidates=("extra_rc",)``)
    progress         called with one line of text per step
    base_refits      effect name -> callable returning (base model refitted with the
                     effect, the effect, a note) or None: the candidate is that model, judged
                     as it is (the test that made the base shows the effect's parameters
                     better than the cycle's fit part); None: fitted on the cycle as others
    pulse_refit      the pulse test that made the base: a hysteresis is also tried on the
                     base refitted there with it taken out (:mod:`.refits`), and kept so
                     where that fits the cycle's fit part better
    Raises ValueError for unknown candidates, a bad split or too short records."""
    unknown_settings = sorted(set(overrides) - set(SETTING_NAMES))
    if unknown_settings:
        raise TypeError(f"diagnose() got unknown settings {unknown_settings}; "
                        f"known: {list(SETTING_NAMES)}")
    settings = replace(settings or SearchSettings(), **overrides)
    search = _Search(base_model, fit_series, judge_series, soc0, judge_soc0, settings,
                     progress, base_refits, pulse_refit)
    while search.order and len(search.steps) < settings.max_effects:
        if not search.round():
            break
    if len(search.steps) >= 2:
        search.prune()
    search.name_only_what_explains()
    search.tell_apart()
    search.pair_or_diffusion()
    return search.result()


class _Search:
    """One diagnosis: the record split into a fit and a held-out part, the base judged on
    both, the candidates in the order of their signatures, and what was added so far (the
    effects fitted, the record's faults corrected). :func:`diagnose` calls its phases."""

    def __init__(self, base_model: EcmModel, fit_series: TimeSeries,
                 judge_series: TimeSeries | None, soc0: float | None,
                 judge_soc0: float | None, settings: SearchSettings,
                 progress: Callable[[str], None] | None, base_refits: dict | None,
                 pulse_refit: PulseRefit | None):
        self.t_start = _time.perf_counter()
        self.say = progress or (lambda _m: None)
        self.st = settings
        self.base0 = self.base_model = base_model
        self.refits = dict(base_refits or {})
        self.refitted: dict = {}
        self.base_notes: dict[str, str] = {}
        self.pulse_refit = pulse_refit
        self.base_by: list[str] = []     # the candidates whose pulse-test refit is the base
        self.third_seen = self.pair_refit = None    # an extra RC's pulse-test refit
        unknown = [c for c in settings.candidates if c not in CANDIDATE_NAMES]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {list(CANDIDATE_NAMES)}")
        self._split(fit_series, judge_series, soc0, judge_soc0)
        self._judge_the_base()
        self._order_the_candidates()
        self.fixed_effects = [(e.name, e.params(), {}) for e in base_model.effects]
        self.added: list[tuple[str, dict, dict]] = []      # (name, values, specs) so far
        self.current = base_model
        self.e_cur, self.ef_cur = self.e_j0, self.e_fit0
        self.mae_cur, self.fit_mae_cur = self.mae0, self.fit_mae0
        self.judge_sim = self.base_judge_sim
        self.steps: list[DiagnoseStep] = []
        self.cands: list[Candidate] = []
        self.rnd = 0
        self.notes: list[str] = []
        self.applied: list = []     # the record's faults found so far (corrected in the data)
        self.alikes: list = []      # per step: (its look-alikes in its round, on a refitted base)
        self.beyond: dict = {}      # step -> the candidates of its round better on a bound
        self.dropped: list = []
        self.prune_ties: list = []
        self.not_named: tuple = ()
        self.cannot_tell: list = []
        self.left_v = None

    # -- set-up ------------------------------------------------------------------------------

    def _split(self, fit_series, judge_series, soc0, judge_soc0) -> None:
        """The fit part and the held-out part, their start SOCs, the noise and the block of
        the bootstrap."""
        base_model, st = self.base_model, self.st
        if soc0 is None:
            soc0 = initial_soc(base_model, fit_series)
        self.soc0 = soc0 = float(soc0)
        t = fit_series.time_s
        if judge_series is None:
            if not 0.1 <= st.split <= 0.9:
                raise ValueError("split must be in [0.1, 0.9]")
            t_cut = t[0] + st.split * (t[-1] - t[0])
            fit_stop = int(np.searchsorted(t, t_cut, side="right"))
            judge_start, judge, judge_soc0 = fit_stop, fit_series, soc0
            name = Path(fit_series.source).name or "the cycle"
            words = (f"the last {100 * (1 - st.split):.0f} % of {name} (from t = "
                     f"{t[fit_stop]:.0f} s; the first {100 * st.split:.0f} % was fitted)")
        else:
            fit_stop, judge_start, judge = len(fit_series), 0, judge_series
            if judge_soc0 is None:
                judge_soc0 = initial_soc(base_model, judge_series)
            judge_soc0 = float(judge_soc0)
            words = (f"all of {Path(judge_series.source).name or 'the judge cycle'} "
                     f"(all of {Path(fit_series.source).name or 'the fit cycle'} was fitted)")
        if fit_stop < 50 or len(judge) - judge_start < 50:
            raise ValueError("too few samples to fit and judge on")
        self.fit_series, self.judge, self.judge_soc0 = fit_series, judge, judge_soc0
        self.fit_stop, self.judge_start, self.split_words = fit_stop, judge_start, words
        rest_a = max(base_model.direction_deadband_a, base_model.capacity_ah / 100.0)
        self.sample_s = float(np.median(np.diff(t)))
        self.noise = noise_std(fit_series, rest_a)
        self.floor_v = max(st.min_gain_v, st.min_gain_noise * self.noise)
        self.same = judge_series is None
        tj = judge.time_s[judge_start:]
        block_s = st.block_s if st.block_s is not None else max(60.0, (tj[-1] - tj[0]) / 20.0)
        self.block = max(1, int(round(block_s / max(np.median(np.diff(tj)), 1e-6))))
        # the records as read (the faults found are not corrected in these)
        self.fit_record, self.judge_record = fit_series, judge
        self.rest_a = cx.rest_current(fit_series.slice(0, fit_stop), base_model.capacity_ah)

    def _judge_the_base(self) -> None:
        """The base simulated on both parts, the held-out samples judged, its errors."""
        base_model, fit_stop, judge_start = self.base_model, self.fit_stop, self.judge_start
        self.base_fit_sim = self.sim_fit(base_model)
        self.base_judge_sim = self.base_fit_sim if self.same else self.sim_judge(base_model)
        self.keep, below = _judged_samples(self.base_judge_sim.soc[judge_start:],
                                           self.st.judge_soc_min)
        if below:
            self.split_words += (f", above {100 * self.st.judge_soc_min:.0f} % SOC ({below} "
                                 "samples below left out)")
        self.vj = self.judge.voltage_v[judge_start:][self.keep]
        soc = self.base_fit_sim.soc[:fit_stop]
        self.soc_range = (float(np.min(soc)), float(np.max(soc)))
        self.e_fit0 = (self.base_fit_sim.voltage_v[:fit_stop]
                       - self.fit_series.voltage_v[:fit_stop])
        self.e_j0 = self.base_judge_sim.voltage_v[judge_start:][self.keep] - self.vj
        self.mae0, self.fit_mae0 = _mae(self.e_j0), _mae(self.e_fit0)
        self.say(f"base model: held-out MAE {self.mae0 * 1e3:.2f} mV, fit-part MAE "
                 f"{self.fit_mae0 * 1e3:.2f} mV, noise {self.noise * 1e3:.2f} mV")

    def _order_the_candidates(self) -> None:
        """The signatures, the candidates in their order (the record's faults last), the
        fit part's data (block averages when long) and the loss scale."""
        base_model, fit_series, fit_stop = self.base_model, self.fit_series, self.fit_stop
        candidates = self.st.candidates
        self.ctx = ctx = _context(base_model, fit_series, fit_stop)
        sigs = signatures(base_model, fit_series, self.base_fit_sim, np.arange(fit_stop), ctx)
        self.sigs = sigs
        existing = {e.name for e in base_model.effects}
        order = [n for n in sorted(sigs, key=lambda n: -sigs[n].r2)
                 if n in candidates and sigs[n].applicable and n not in existing]
        order += [n for n in cx.CORRECTION_NAMES if n in candidates and cx.applicable(
            n, base_model, sigs[fx.TemperatureDependence.name].applicable)]
        self.order = order
        for n in sorted(sigs, key=lambda n: -sigs[n].r2):
            self.say(f"signature {n}: {sigs[n].r2:.3f}  {sigs[n].detail}")
        fit_part = fit_series.slice(0, fit_stop)
        self.factor = max(1, int(math.ceil(fit_stop / self.st.max_fit_samples)))
        self.fit_data = decimate(fit_part, self.factor)
        self.rows = np.arange(len(self.fit_data))
        self.f_scale = (self.st.loss_scale_v if self.st.loss_scale_v is not None
                        else max(3.0 * self.noise, 0.5 * self.fit_mae0, 1e-3))
        self.cap_scale = sigs[fx.CapacityError.name].guess.get("capacity_scale", 1.0)

    # -- simulating, judging and fitting ----------------------------------------------------

    def sim_judge(self, model, series=None):
        s = self.judge if series is None else series
        return simulate(model, s.time_s, s.current_a, self.judge_soc0, s.temperature_c)

    def sim_fit(self, model, series=None):
        s = self.fit_series if series is None else series
        return simulate(model, s.time_s, s.current_a, self.soc0, s.temperature_c)

    def judged(self, effects, base=None, fixes=None):
        """The model with ``effects`` on ``base``, the record's faults ``fixes`` (default:
        those found so far) corrected, simulated on the held-out and fit parts: (model,
        held-out simulation, held-out error, its MAE, the fit part's MAE, its error)."""
        fixes = self.applied if fixes is None else fixes
        model = cx.corrected_model(self.base_model if base is None else base,
                                   fixes).with_effects(effects)
        judge = self.judge
        sj = self.sim_judge(model, cx.apply_all(self.judge_record, fixes))
        # a lagging voltage channel is compared on the model's side
        sj = replace(sj, voltage_v=cx.channel_voltage(fixes, judge.time_s, sj.voltage_v))
        e1 = sj.voltage_v[self.judge_start:][self.keep] - self.vj
        if self.same:
            v_fit = sj.voltage_v
        else:
            v_fit = cx.channel_voltage(fixes, self.fit_record.time_s, self.sim_fit(
                model, cx.apply_all(self.fit_record, fixes)).voltage_v)
        ef = v_fit[:self.fit_stop] - self.fit_record.voltage_v[:self.fit_stop]
        return model, sj, e1, _mae(e1), _mae(ef), ef

    def fit_data_for(self, fixes):
        s = cx.apply_all(self.fit_record, fixes).slice(0, self.fit_stop)
        if any(isinstance(c, cx.VoltageLag) for c in fixes):
            # what the lag shows of the model as it is, taken out of the record's voltage
            # for the later fits (judging compares on the model's side)
            v = self.sim_fit(cx.corrected_model(self.base_model, fixes).with_effects(
                self.current.effects), s).voltage_v
            s = replace(s, voltage_v=s.voltage_v - cx.channel_voltage(fixes, s.time_s, v) + v)
        return decimate(s, self.factor)

    def fit_fault(self, name, model, fixes):
        """The record's fault ``name`` fitted with ``model`` on the record with ``fixes``
        corrected (a lag at full resolution: block averages would hide it)."""
        if name == cx.VoltageLag.name:
            data = cx.apply_all(self.fit_record, fixes).slice(0, self.fit_stop)
            at = np.arange(self.fit_stop)
        elif name == cx.CurrentOffset.name and self.rest_a is not None:
            # what the sensor reads at rest is its offset (the other faults found so far
            # corrected: a gain scales it)
            return cx.CurrentOffset(self.rest_a if not fixes else cx.rest_current(
                cx.apply_all(self.fit_record, fixes).slice(0, self.fit_stop),
                self.base_model.capacity_ah) or 0.0)
        else:
            data, at = self.fit_data_for(fixes), self.rows
        return cx.fit(name, model, data, self.soc0, at, self.cap_scale, self.f_scale,
                      self.st.max_nfev, self.ctx["t_ref_c"], self.soc_range)

    def fitted(self, layout, starts_native, fixed, base=None, fixes=None):
        """Fit the free parameters of the last layout entry (and of any other entry
        that has specs) from the best of the starts, on the record with ``fixes``
        (default: the faults found so far) corrected; returns the effects."""
        name, _, specs = layout[-1]
        prob = _Problem(cx.corrected_model(base or self.base_model,
                                           self.applied if fixes is None else fixes
                                           ).with_effects(()),
                        self.fit_data if fixes is None else self.fit_data_for(fixes),
                        self.soc0, layout[:-1] + [(name, dict(starts_native[0], **fixed), specs)])
        z_starts = []
        for start in starts_native:
            prob.values[-1] = dict(start, **fixed)
            z_starts.append(prob.z0())
        z, _ = _fit(prob, self.rows, z_starts, self.st.max_nfev, self.f_scale)
        return prob.native(z, snap=True), prob.effects_of(z)

    def refit_on(self, base, layout, name, start):
        """``name`` fitted on ``base`` from ``start`` (an effect): (the effect, the fit
        part's MAE, (values, effects, specs) and what :meth:`judged` gives)."""
        ctx_b = _context(base, self.fit_series, self.fit_stop)
        specs_b, fixed_b = _specs(name, base, ctx_b), _fixed(name, ctx_b)
        vals_b, effects_b = self.fitted(layout + [(name, None, specs_b)], [start.params()],
                                        fixed_b, base=base)
        j = self.judged(effects_b, base)
        return effects_b[-1], j[4], ((vals_b, effects_b, specs_b), j)

    # -- the rounds -----------------------------------------------------------------------

    def round(self) -> bool:
        """Every candidate left fitted and judged; of those that pass the held-out test the
        best is added. False when none passes."""
        self.rnd += 1
        tried = [c for c in map(self._try, self.order) if c is not None]
        passing = [c for c in tried if c[0]]
        if not passing:
            return False
        read = [c for c in passing if c[2] == cx.CurrentOffset.name and self.rest_a is not None]
        if read:
            # a fault the record shows where the current is zero goes before what the
            # voltage alone suggests (a capacity error takes up an offset's SOC drift)
            self._add(read)
            return True
        self._add(passing)
        win, st = passing[0], self.st
        self.alikes[-1][0].extend(near_rivals(tried, win, self.alikes[-1][0], self._valid,
                                              self.block, st.confidence, st.seed + self.rnd))
        self._beyond_bounds(tried, win)
        return True

    def _valid(self, c) -> bool:
        """A candidate's fit is one the effect can be: finite, inside its bounds, a lag the
        record resolves."""
        return bool(np.isfinite(c[1]) and not _on_bound(c[3][-1], c[4]) and not (
            c[11] is not None and hasattr(c[11], "words") and cx.unresolved(c[11],
                                                                            self.sample_s)))

    def _beyond_bounds(self, tried, win) -> None:
        """The round's candidates that beat its winner ``win`` but end on a bound are its
        look-alikes at the end (:func:`.lookalike.beyond_bounds`, :meth:`tell_apart`)."""
        st = self.st
        out = beyond_bounds(tried, win, self.block, st.confidence, st.seed + self.rnd)
        for c, bound in out:
            self.notes.append(f"{c[2]}: held-out MAE {c[1] * 1e3:.2f} mV against "
                              f"{win[1] * 1e3:.2f} with {win[2]}, but with {bound} on its "
                              "bound")
            self.say(self.notes[-1])
        if out:
            self.beyond[win[2]] = [c[2] for c, _ in out]

    def _try(self, name):
        """Candidate ``name`` fitted with what was added so far kept as it is, and judged:
        (passes, held-out MAE, name, values, specs, model, held-out simulation and error,
        the bootstrap's lower bound, fit MAE, its refitted base or None, the effect or
        fault, the fit part's error), or None where its fit failed."""
        t0 = _time.perf_counter()
        layout = self.fixed_effects + [(n, dict(v), {}) for n, v, _ in self.added]
        if name in self.refits and name not in self.refitted:
            self.refitted[name] = self.refits[name]()
        new_base = corr = None
        try:
            if name in cx.CORRECTION_TYPES:
                corr = self.fit_fault(name, self.current, self.applied)
                specs = cx.specs(name, self.base_model.capacity_ah)
                vals = [dict(v) for _, v, _ in layout] + [corr.params()]
                effects = list(self.current.effects)
            elif self.refitted.get(name) is not None:
                new_base, effect, _note = self.refitted[name]
                specs = {}
                vals = [dict(v) for _, v, _ in layout] + [effect.params()]
                effects = list(self.current.effects) + [effect]
            else:
                specs, fixed = _specs(name, self.base_model, self.ctx), _fixed(name, self.ctx)
                vals, effects = self.fitted(layout + [(name, None, specs)],
                                            _starts(name, self.sigs[name], self.ctx, specs),
                                            fixed)
        except FIT_ERRORS as exc:
            nan = float("nan")
            self.cands.append(Candidate(self.rnd, name, None, nan, nan, nan, nan, nan, False,
                                        _time.perf_counter() - t0, f"fit failed: {exc}"))
            return None
        model, sj, e1, mae1, fit_mae1, ef1 = self.judged(
            effects, new_base, None if corr is None else self.applied + [corr])
        if name == fx.Hysteresis.name and self.pulse_refit is not None and \
                self.base_model is self.base0:
            alt = hysteresis_on_refitted_base(
                self.pulse_refit, self.base0.ocv, effects[-1],
                lambda b, start: self.refit_on(b, layout, name, start))
            if alt is not None and alt[2][1][4] < fit_mae1:
                new_base, self.base_notes[name] = alt[0], alt[1]
                (vals, effects, specs), (model, sj, e1, mae1, fit_mae1, ef1) = alt[2]
        if name == fx.ExtraRc.name:
            alt = self._third_pair(layout)
            if alt is not None and (alt[2][1][4] < fit_mae1 or _on_bound(vals[-1], specs)):
                new_base, self.base_notes[name] = alt[0], alt[1]
                (vals, effects, specs), (model, sj, e1, mae1, fit_mae1, ef1) = alt[2]
        ok, low, gain, rel, why = self._test(e1, mae1, vals[-1], specs, corr)
        new = corr if corr is not None else effects[-1]
        self.cands.append(Candidate(self.rnd, name, new, fit_mae1, mae1, gain, rel, low, ok,
                                    _time.perf_counter() - t0, why))
        self.say(f"round {self.rnd} {name}: held-out MAE {mae1 * 1e3:.2f} mV (gain "
                 f"{gain * 1e3:.2f} mV, {100 * rel:.1f} %, lower bound {low * 1e3:.2f} mV), "
                 f"fit MAE {fit_mae1 * 1e3:.2f} mV [{_time.perf_counter() - t0:.1f} s] "
                 f"{new.summary()}")
        return (ok, mae1, name, vals, specs, model, sj, e1, low, fit_mae1, new_base, new, ef1)

    def _third_pair(self, layout):
        """The extra RC on the base refitted on its pulse test with a third RC pair
        (:func:`.refits.third_pair`; a hysteresis found on a refitted base taken out of the
        test first): (base, note, ((values, effects, specs), what :meth:`judged` gives)) of
        the pair as the test gives it or fitted on the cycle's fit part from there, whichever
        fits the fit part better; None without a pulse test, on a base refitted for another
        effect, or where the test shows no third pair."""
        if self.pulse_refit is None or set(self.base_by) - {fx.Hysteresis.name} or \
                self.base0.discharge.has_diffusion:
            return None
        hyst = next((e for e in self.current.effects if e.name == fx.Hysteresis.name),
                    None) if self.base_by else None
        got = third_pair(self.pulse_refit, hyst)
        if got is None:
            return None
        self.third_seen = got
        base, effect, note = got.base, got.effect, got.note
        as_is = list(self.current.effects) + [effect]
        options = [(([dict(v) for _, v, _ in layout] + [effect.params()], as_is, {}),
                    self.judged(as_is, base))]
        try:
            _, _, (fitted, judged) = self.refit_on(base, layout, fx.ExtraRc.name, effect)
            if not _on_bound(fitted[0][-1], fitted[2]):
                options.append((fitted, judged))
        except FIT_ERRORS:
            pass
        return base, note, min(options, key=lambda o: o[1][4])

    def _test(self, e1, mae1, values, specs, corr):
        """The held-out test of a candidate (module doc): (passes, the bootstrap's lower
        bound, the gain, the relative gain, why it does not pass)."""
        st = self.st
        d = np.abs(self.e_cur) - np.abs(e1)
        d = np.where(np.isfinite(d), d, 0.0)
        low = block_bootstrap_low(d, self.block, st.confidence, seed=st.seed + self.rnd)
        gain = self.mae_cur - mae1
        rel = gain / self.mae_cur if self.mae_cur > 0 else 0.0
        bound = _on_bound(values, specs)
        short = "" if corr is None else cx.unresolved(corr, self.sample_s)
        # an offset the rests read is not chosen by the voltage: the bootstrap's question,
        # whether noise could give its gain, is not its test
        read = isinstance(corr, cx.CurrentOffset) and self.rest_a is not None
        ok = bool(np.isfinite(mae1) and rel >= st.min_rel_gain and (low > 0.0 or read)
                  and gain >= self.floor_v and not bound and not short)
        if ok:
            why = ""
        elif short:
            why = short
        elif bound:
            why = (f"{bound} on its bound: the effect's best fit lies outside what it "
                   "can be, so it does not explain the residual")
        elif not np.isfinite(mae1) or gain <= 0:
            why = "held-out error did not fall"
        elif low <= 0.0:
            why = "held-out gain within what noise explains (bootstrap)"
        elif gain < self.floor_v:
            why = f"held-out gain below {self.floor_v * 1e3:.2f} mV (noise level)"
        else:
            why = f"held-out gain {100 * rel:.1f} % < {100 * st.min_rel_gain:.0f} %"
        return ok, low, gain, rel, why

    def _add(self, passing) -> None:
        """The winner of a round added (the record's fault corrected in the data), all that
        was added refitted jointly, its look-alikes kept for the end."""
        st = self.st
        # of the candidates that pass the held-out test, the one with the lowest MAE over
        # all the data (fit part and held-out part, weighted by their samples)
        n_fit, n_judge = self.fit_stop, len(self.vj)
        passing.sort(key=lambda c: (n_judge * c[1] + n_fit * c[9]) / (n_judge + n_fit))
        plain = [c for c in passing if c[10] is None]
        if passing[0][10] is not None and plain and block_bootstrap_low(
                np.abs(plain[0][7]) - np.abs(passing[0][7]), self.block, st.confidence,
                seed=st.seed + self.rnd) <= 0.0:
            # a candidate on a base refitted for it has the pulse test's freedom too: it
            # wins over one on the base as it is only by the held-out test any candidate
            # must pass
            passing.insert(0, plain[0])
        _, mae1, name, vals, specs, model, sj, e1, low, fit_mae1, new_base, new, ef1 = passing[0]
        # the others that passed are judged again at the end, each in the winner's place
        # among all that was added (a winner on a refitted base: its look-alikes here)
        if name == cx.CurrentOffset.name and self.rest_a is not None:
            # what the rests read is the offset itself, whatever else the voltage allows
            self.alikes.append(([], True))
        else:
            self.alikes.append((lookalikes(passing, self.block, st.confidence,
                                           st.seed + self.rnd)
                                if new_base is not None else rivals(passing),
                                new_base is not None))
        if new_base is not None:
            # the effect came with its own base tables: later candidates build on them
            self.base_model = new_base
            self.base_by.append(name)
            if name == fx.ExtraRc.name:
                self.pair_refit = self.third_seen
            self.notes.append(self.base_notes.get(name) or self.refitted[name][2])
        n_fixed = len(self.fixed_effects)
        if name in cx.CORRECTION_TYPES:
            # a fault of the record: the data corrected, later candidates fitted on it
            self.applied.append(new)
            self.fit_data = self.fit_data_for(self.applied)
            new_added = [(n, v, sp) for (n, _, sp), v in zip(self.added, vals[n_fixed:])]
        else:
            new_added = [(n, v, sp) for (n, _, sp), v in
                         zip(self.added + [(name, None, specs)], vals[n_fixed:])]
        if self.added:
            joint = self._joint_refit(new_added, mae1)
            if joint is not None:
                (model, sj, e1, mae1, fit_mae1, ef1), new_added = joint
        self.added = new_added
        self.steps.append(DiagnoseStep(name, new if name in cx.CORRECTION_TYPES
                                       else model.effects[-1], self.mae_cur, mae1, low))
        self.say(f"added {name}: held-out MAE {self.mae_cur * 1e3:.2f} -> {mae1 * 1e3:.2f} mV")
        self.current, self.e_cur, self.mae_cur = model, e1, mae1
        self.judge_sim, self.fit_mae_cur, self.ef_cur = sj, fit_mae1, ef1
        self.order = [n for n in self.order if n != name]

    def _joint_refit(self, new_added, mae1):
        """All added effects refitted jointly, from where they are: (what :meth:`judged`
        gives, the effects) where the held-out error does not get worse and no parameter
        ends on its search bound (a candidate that ends there does not pass either), else
        None."""
        n_fixed = len(self.fixed_effects)
        try:
            layout = self.fixed_effects + [(n, dict(v), sp) for n, v, sp in new_added]
            vals_j, effects_j = self.fitted(layout, [layout[-1][1]], {})
            judged_j = self.judged(effects_j)
            bound_j = any(_on_bound(v, sp) for (_, _, sp), v in
                          zip(new_added, vals_j[n_fixed:]))
        except FIT_ERRORS:
            return None
        if judged_j[3] <= mae1 and not bound_j:
            self.say(f"joint refit: held-out MAE {judged_j[3] * 1e3:.2f} mV")
            return judged_j, [(n, v, sp) for (n, _, sp), v in zip(new_added, vals_j[n_fixed:])]
        return None

    # -- after the rounds ---------------------------------------------------------------

    def _state(self) -> Fitted:
        return Fitted(list(self.applied), list(self.added), self.current, self.judge_sim,
                      self.e_cur, self.mae_cur, self.fit_mae_cur, self.ef_cur)

    def without(self, state: Fitted, drop: str) -> Fitted | None:
        """``state`` with the named ``drop`` taken out: each fault left refitted on the
        record without it, then the effects left jointly; None where a fit fails or ends on
        a bound."""
        fixes = [c for c in state.fixes if c.name != drop]
        kept = [(n, dict(v), sp) for n, v, sp in state.added if n != drop]
        effects = [e for e in state.model.effects if e.name != drop]
        base_model, fixed_effects = self.base_model, self.fixed_effects
        try:
            for k, c in enumerate(fixes):
                others = fixes[:k] + fixes[k + 1:]
                fixes[k] = self.fit_fault(c.name, cx.corrected_model(
                    base_model, others).with_effects(effects), others)
                if _on_bound(fixes[k].params(), cx.specs(c.name, base_model.capacity_ah)) or \
                        cx.unresolved(fixes[k], self.sample_s):
                    return None
            if kept:
                vals, effects = self.fitted(fixed_effects + kept, [kept[-1][1]], {},
                                            fixes=fixes)
                vals = vals[len(fixed_effects):]
                if any(_on_bound(v, sp) for (_, _, sp), v in zip(kept, vals)):
                    return None
                kept = [(n, v, sp) for (n, _, sp), v in zip(kept, vals)]
        except FIT_ERRORS:
            return None
        model, sj, e1, mae1, fit_mae1, ef1 = self.judged(effects, None, fixes)
        self.say(f"without {drop}, the rest refitted: held-out MAE {mae1 * 1e3:.2f} mV "
                 f"(with it {state.mae_v * 1e3:.2f})")
        return Fitted(fixes, kept, model, sj, e1, mae1, fit_mae1, ef1)

    def needed(self, state: Fitted, alt: Fitted) -> str:
        """Whether ``state`` needs what ``alt`` lacks: it beats ``alt`` on the held-out part
        by the test a candidate passes ("needed", or "tie" where ``alt`` beats it on the fit
        part by the bootstrap: the data favour each on one part), else "not needed"."""
        st = self.st
        gain = alt.mae_v - state.mae_v
        d = np.abs(alt.e_judge) - np.abs(state.e_judge)
        low = block_bootstrap_low(np.where(np.isfinite(d), d, 0.0), self.block,
                                  st.confidence, seed=st.seed + 50)
        if not (np.isfinite(alt.mae_v) and gain >= self.floor_v and low > 0.0
                and gain >= st.min_rel_gain * alt.mae_v):
            return "not needed"
        d = np.abs(state.e_fit) - np.abs(alt.e_fit)
        low = block_bootstrap_low(np.where(np.isfinite(d), d, 0.0), self.block,
                                  st.confidence, seed=st.seed + 51)
        return "tie" if low > 0.0 else "needed"

    def prune(self) -> None:
        """An effect named early must still be needed once the later ones joined
        (:mod:`.prune`)."""
        state, left, self.dropped, self.prune_ties = still_needed(
            [st.name for st in self.steps], self._state(), self.without, self.needed,
            {st.name for st, (_, rb) in zip(self.steps, self.alikes) if rb})
        if not self.dropped:
            return
        self.applied, self.added, self.current = state.fixes, state.added, state.model
        self.judge_sim, self.e_cur, self.mae_cur = state.judge_sim, state.e_judge, state.mae_v
        self.fit_mae_cur, self.ef_cur = state.fit_mae_v, state.e_fit
        gone = {d.name for d in self.dropped}
        self.alikes = [(names + [g for g in sorted(gone) if g not in names], rb) if not rb
                       else (names, rb) for st, (names, rb) in zip(self.steps, self.alikes)
                       if st.name not in gone]
        self.steps = [st for st in self.steps if st.name not in gone]
        for d in self.dropped:
            self.notes.append(f"{d.name}: not needed with {', '.join(left)}: dropped, the rest "
                              f"refitted without it leave {d.mae_without_v * 1e3:.2f} mV held "
                              f"out ({d.mae_with_v * 1e3:.2f} with it)")
            self.say(self.notes[-1])

    def name_only_what_explains(self) -> None:
        """Each step reports its effect as it is in the final model; what was added is not
        named where it lowers the error but does not explain it."""
        final = {e.name: e for e in self.current.effects}
        self.steps = [replace(st, effect=final.get(st.name, st.effect)) for st in self.steps]
        if self.factor > 1:
            self.notes.append(f"fit on {len(self.fit_data)} samples (block averages of "
                              f"{self.factor})")
        misfit = None if self.pulse_refit is None else self.pulse_refit.rms_v
        if self.steps and misfit is not None and \
                self.mae_cur > UNEXPLAINED_RATIO * explained_floor(self.noise, misfit):
            # naming it would send a user after the wrong physics (a look-alike of an
            # effect without a candidate)
            self.not_named, self.steps = tuple(self.steps), []
            self._back_to_the_base()
            self.say(f"not named: {', '.join(st.name for st in self.not_named)} left "
                     f"{self.not_named[-1].mae_after_v * 1e3:.2f} mV, above "
                     f"{UNEXPLAINED_RATIO:g}x max(noise, the base's misfit on its pulse test)")

    def _back_to_the_base(self) -> None:
        self.current, self.mae_cur = self.base0, self.mae0
        self.fit_mae_cur, self.judge_sim = self.fit_mae0, self.base_judge_sim

    def swapped(self, k: int, other: str):
        """(held-out error, fit part's error) with step k's effect replaced by ``other``,
        refitted with the other effects added (a fault of the record: fitted with them as
        they are, then they refitted on the record it corrects); None where a fit fails or
        ends on a bound."""
        drop, base_model = self.steps[k].name, self.base_model
        fixes = [c for c in self.applied if c.name != drop]
        kept = [e for e in self.current.effects if e.name != drop]
        layout = self.fixed_effects + [(n, dict(v), sp) for n, v, sp in self.added if n != drop]
        try:
            if other in cx.CORRECTION_TYPES:
                corr = self.fit_fault(other, cx.corrected_model(base_model, fixes).with_effects(
                    kept), fixes)
                if _on_bound(corr.params(), cx.specs(other, base_model.capacity_ah)) or \
                        cx.unresolved(corr, self.sample_s):
                    return None
                fixes = fixes + [corr]
                if any(sp for _, _, sp in layout):
                    vals, kept = self.fitted(layout, [layout[-1][1]], {}, fixes=fixes)
                    if any(_on_bound(v, sp) for (_, _, sp), v in zip(layout, vals)):
                        return None
                return self.judged(kept, None, fixes)[2::3]
            specs = _specs(other, base_model, self.ctx)
            layout = layout + [(other, None, specs)]
            vals, effects = self.fitted(layout, _starts(other, self.sigs[other], self.ctx, specs),
                                        _fixed(other, self.ctx), fixes=fixes)
        except FIT_ERRORS:
            return None
        if any(_on_bound(v, sp) for (_, _, sp), v in zip(layout, vals)):
            return None
        return self.judged(effects, None, fixes)[2::3]

    def tell_apart(self) -> None:
        """A named effect stays named only where it beats its look-alikes in its place
        (:mod:`.lookalike`); where it does not, nothing of its group is named and the model
        is the base (what was named beside them was fitted with one of them)."""
        if self.steps:
            named = {st.name for st in self.steps}
            self.cannot_tell = told_apart(
                self.steps, self.alikes, self.swapped, (self.e_cur, self.ef_cur), self.block,
                self.st.confidence, self.st.seed) + [g for g in self.prune_ties if g[0] in named]
            self.cannot_tell = with_beyond(self.cannot_tell, self.steps, self.beyond)
            for group in self.cannot_tell:
                self.say(f"{' or '.join(group)}: the data cannot tell them apart")
        if self.cannot_tell:
            self.left_v = self.mae_cur
            self._back_to_the_base()
            tied = {n for g in self.cannot_tell for n in g}
            self.steps = [st for st in self.steps if st.name not in tied]

    def pair_or_diffusion(self) -> None:
        """An extra RC found as a third pair of the pulse test is named only where the
        test's shape tells it from solid diffusion (:func:`.diffusion.told_from_diffusion`);
        otherwise "extra_rc or diffusion" (or its group with diffusion), the model the base."""
        g = next((g for g, group in enumerate(self.cannot_tell) if fx.ExtraRc.name in group),
                 None)
        if g is not None and self.third_seen is not None:
            # not named anyway: what it cannot be told from includes diffusion
            self.cannot_tell[g] += ("diffusion",) * ("diffusion" not in self.cannot_tell[g])
        k = next((k for k, st in enumerate(self.steps) if st.name == fx.ExtraRc.name), None)
        if k is None or self.pair_refit is None or fx.ExtraRc.name not in self.base_by:
            return
        told, note = told_from_diffusion([st.name for st in self.steps], self.pulse_refit,
                                         self.pair_refit)
        self.notes.append(note)
        self.say(note)
        if not told:
            self.cannot_tell.append((fx.ExtraRc.name, "diffusion"))
            self.left_v = self.mae_cur if self.left_v is None else self.left_v
            self._back_to_the_base()
            del self.steps[k]

    def result(self) -> DiagnoseResult:
        return DiagnoseResult(
            base_model=self.base0, model=self.current, steps=tuple(self.steps),
            candidates=tuple(self.cands), signatures=self.sigs, mae_before_v=self.mae0,
            mae_after_v=self.mae_cur, fit_mae_before_v=self.fit_mae0,
            fit_mae_after_v=self.fit_mae_cur, noise_v=self.noise, split=self.split_words,
            fit_series=self.fit_record, judge_series=self.judge_record,
            fit_stop=self.fit_stop, judge_start=self.judge_start, soc0=self.soc0,
            judge_soc0=self.judge_soc0, base_fit_sim=self.base_fit_sim,
            base_judge_sim=self.base_judge_sim, judge_sim=self.judge_sim,
            seconds=_time.perf_counter() - self.t_start, notes=tuple(self.notes),
            misfit_v=None if self.pulse_refit is None else self.pulse_refit.rms_v,
            not_named=self.not_named, cannot_tell=tuple(self.cannot_tell),
            dropped=tuple(self.dropped),
            cannot_tell_mae_v=self.left_v if self.cannot_tell else None)
