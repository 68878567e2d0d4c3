"""The base model refitted on the pulse test that made it, with a hysteresis taken out, or
with a third RC pair (an extra RC as the test shows it, :func:`third_pair`).

A 10 s pulse moves a hysteresis state by tens of per cent and a 10 % SOC move sets it to
one branch, so the pulse test shows a hysteresis as a voltage that follows the direction of
the charge moved. The whole-test fit knows no hysteresis: it takes that voltage into the
base's resistances and OCV correction, and a hysteresis fitted on the cycle on top of that
base is fitted to what the contamination left (the shared suite's c04: 27.9 mV against the
true 9.9). Here the hysteresis is first read where the pulse test shows it alone, at the
ends of its long rests, and the pulse test is fitted again with its voltage taken out. A
hysteresis that is there fits the pulse test better that way; one that is not, worse, and
the refit is not used: the pulse test is a second record judging the candidate.

The pipeline hands diagnose a :class:`PulseRefit`; everything about the candidate is here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from ..data.measure import TimeSeries, charging_direction
from ..model import effects as fx
from ..model.effects import hysteresis_state, hysteresis_voltage

# a refit is used only where it fits the pulse test this much better than the base did
# (the same 1 % the current-dependence refit asks for)
MIN_RMS_GAIN = 0.01
# F test of the direction memory in the relaxed voltages
REST_CONFIDENCE = 0.99
# a relaxation at least this long ends with the RC pairs settled to a fraction of a mV
# (the whole-test fit's slow pairs are below 500 s; the shared tests rest 10-60 min)
MIN_REST_S = 120.0


@dataclass(frozen=True)
class PulseRefit:
    """The test that made the base, and how to fit it again.

    series      the pulse test as the base fit read it
    rms_v       the base fit's RMS on it
    refit       ``refit(voltage_v, third_pair=False)`` -> (model, rms_v): the whole-test
                fit on ``series`` with ``voltage_v`` subtracted from its voltage (with
                ``third_pair``: with a third RC pair, the tables' diffusion pair)
    capacity_ah the capacity of the base
    deadband_a  the base's direction deadband
    pulses      the pulses found in it (ecmgen.data.dcir.Pulse)
    soc_capacity_ah  the capacity of its SOC axis
    memo        what the candidates need of it once per diagnosis, whatever the round
    """

    series: TimeSeries
    rms_v: float
    refit: Callable
    capacity_ah: float
    deadband_a: float
    pulses: tuple = ()
    soc_capacity_ah: float | None = None
    memo: dict = field(default_factory=dict, compare=False, repr=False)


def _voltage_from(effect: fx.Hysteresis, series: TimeSeries, deadband_a: float,
                  h0: float) -> np.ndarray:
    """The voltage ``effect`` adds on ``series`` from state ``h0``."""
    return hysteresis_voltage(replace(effect, initial_state=h0), series.time_s,
                              series.current_a, charging_direction(series.current_a,
                                                                   deadband_a))


def refit_without(pr: PulseRefit, effect: fx.Hysteresis):
    """(base refitted on the pulse test with ``effect``'s voltage taken out, its RMS, a
    note), or None where that fits the pulse test no better than the base (MIN_RMS_GAIN).
    The test may start on either branch: the one that fits better."""
    best = None
    for h0 in (1.0, -1.0):
        model, rms = pr.refit(_voltage_from(effect, pr.series, pr.deadband_a, h0))
        if best is None or rms < best[1]:
            best = (model, rms, h0)
    model, rms, h0 = best
    if not rms < (1.0 - MIN_RMS_GAIN) * pr.rms_v:
        return None
    branch = "charge" if h0 > 0 else "discharge"
    return model, rms, (f"hysteresis: the base tables refitted on the pulse test with it "
                        f"taken out, the test starting on the {branch} branch (fit RMS "
                        f"{1e3 * pr.rms_v:.2f} -> {1e3 * rms:.2f} mV)")


def _rest_ends(pr: PulseRefit) -> np.ndarray:
    t = pr.series.time_s
    return np.array(sorted({p.next_start - 1 for p in pr.pulses if p.next_start > p.stop
                            and t[p.next_start - 1] - t[p.stop] >= MIN_REST_S}
                           | {p.rest_index for p in pr.pulses}))


def rest_hysteresis(pr: PulseRefit, ocv) -> fx.Hysteresis | None:
    """A hysteresis as the pulse test's relaxed voltages show it, or None where they do not.

    At the end of every relaxation of at least MIN_REST_S the RC pairs have settled and
    v - OCV(soc) is the hysteresis, regressed on the direction memory h (its decay from a
    log grid, the test starting on either branch) and the last direction:
    v - OCV = m h + m0 s + c. Named only where the memory explains the relaxed voltages
    beyond a constant offset (an F test at REST_CONFIDENCE, the searched decay counted as
    one more parameter)."""
    from scipy.stats import f as f_dist

    s = pr.series
    if not pr.pulses:
        return None
    ends = _rest_ends(pr)
    if ends.size < 8:
        return None
    t, i, v = s.time_s, s.current_a, s.voltage_v
    ah = s.coulomb_ah()
    p0 = pr.pulses[0]
    soc = p0.soc + (ah - ah[p0.rest_index]) / (pr.soc_capacity_ah or pr.capacity_ah)
    r = v[ends] - ocv.ocv_at(soc[ends])
    ch = charging_direction(i, pr.deadband_a)
    sgn = np.where(ch, 1.0, -1.0)[ends]
    best = None
    for frac in np.geomspace(0.002, 0.2, 12):
        for h0 in (1.0, -1.0):
            h = hysteresis_state(fx.Hysteresis(0.01, frac * pr.capacity_ah, 0.0, 0.0, h0),
                                 t, i, ch)[ends]
            X = np.column_stack([h, sgn, np.ones(ends.size)])
            coef, *_ = np.linalg.lstsq(X, r, rcond=None)
            res = r - X @ coef
            sse = float(res @ res)
            if coef[0] > 0 and (best is None or sse < best[0]):
                best = (sse, frac, coef)
    if best is None:
        return None
    sse, frac, (m, m0, c) = best
    sse0 = float(np.sum((r - r.mean()) ** 2))
    dof = ends.size - 4
    if dof < 4 or not sse < sse0 or \
            (sse0 - sse) / 3.0 / (sse / dof) < float(f_dist.ppf(REST_CONFIDENCE, 3, dof)):
        return None
    m0 = max(float(m0), 0.0)
    table_state = float(np.clip(-c / max(m + m0, 1e-9), -1.0, 1.0))
    # within the candidate's search ranges (a 0.3 V band is not a hysteresis)
    return fx.Hysteresis(float(min(m, 0.29)), float(frac * pr.capacity_ah),
                         float(min(m0, 0.09)), table_state, 0.0)


def hysteresis_on_refitted_base(pr: PulseRefit, ocv, fitted: fx.Hysteresis, fit_on):
    """The hysteresis candidate on a base refitted without it: the best (by the fit part's
    error) of two rounds of 'refit the base with the hysteresis taken out, fit the
    hysteresis on the cycle on that base', starting from what the pulse test's rests show.
    ``fit_on(base, start)`` fits the candidate on the cycle from ``start`` on ``base`` and
    returns (its effect, the fit part's MAE, anything to keep). Returns (base, note, that
    result), or None where the rests do not show a hysteresis (a test without rested
    pulses: a dynamic test) or no refit fits the pulse test better than the base."""
    if "hysteresis" not in pr.memo:
        # the rests and the first refit do not depend on the round: refit_without starts
        # the test on either branch whatever the candidate's initial state
        rested = rest_hysteresis(pr, ocv)
        pr.memo["hysteresis"] = (rested, None if rested is None else refit_without(pr, rested))
    rested, got = pr.memo["hysteresis"]
    if rested is None:
        return None
    effect = replace(rested, initial_state=fitted.initial_state)
    best = None
    for k in range(2):
        if k:
            got = refit_without(pr, effect)
        if got is None:
            break
        base, _, note = got
        effect, fit_mae_v, kept = fit_on(base, effect)
        if best is None or fit_mae_v < best[0]:
            best = (fit_mae_v, base, note, kept)
    return None if best is None else best[1:]


def _without_third_pair(model):
    """``model`` with its tables' diffusion pair taken out."""
    def plain(t):
        return replace(t, r_diff_ohm=None, tau_diff_s=None)
    return replace(model, charge=plain(model.charge), discharge=plain(model.discharge))


@dataclass(frozen=True)
class ThirdPair:
    """An extra RC pair as the pulse test shows it (:func:`third_pair`): the base tables of
    the test's fit with it (the pair taken out of them), the pair, a note, that fit's RMS and
    the voltage taken out of the test before it (a hysteresis found, or zeros)."""

    base: object
    effect: fx.ExtraRc
    note: str
    rms_v: float
    voltage_v: np.ndarray


def third_pair(pr: PulseRefit, hysteresis: fx.Hysteresis | None = None) -> ThirdPair | None:
    """An extra RC pair as the pulse test shows it: the whole-test fit with a third RC
    pair (the diffusion pair of the build's ``curve_branches``), with ``hysteresis``'s
    voltage taken out (the test starting on the branch that fits better); the pair as an
    extra RC is its time constant and the mean of the two directions' resistances. None
    where the pair is dropped (its time constant on a bound) or the test fits no better
    with it (MIN_RMS_GAIN) than the plain 2RC fitted on the same voltage.

    The pulse test shows a pair of minutes in its rests (5-60 min after pulses and SOC
    moves); a plain 2RC fit lumps it with its slow pair (a slow pair of 218 s where the
    cell has 88 s and 588 s), and an extra RC fitted on the cycle above that slow pair has
    nothing left to describe."""
    key = ("third_pair", None if hysteresis is None else tuple(hysteresis.params().values()))
    if key in pr.memo:
        return pr.memo[key]
    best = None
    for h0 in (1.0, -1.0) if hysteresis is not None else (None,):
        v = np.zeros(len(pr.series)) if h0 is None else \
            _voltage_from(hysteresis, pr.series, pr.deadband_a, h0)
        model, rms = pr.refit(v, third_pair=True)
        if best is None or rms < best[1]:
            best = (model, rms, v)
    model, rms, v = best
    plain_rms = pr.rms_v if hysteresis is None else pr.refit(v)[1]
    out = None
    tab = model.discharge
    if tab.r_diff_ohm is not None and rms < (1.0 - MIN_RMS_GAIN) * plain_rms:
        r = 0.5 * float(tab.r_diff_ohm[0] + model.charge.r_diff_ohm[0])
        tau = float(tab.tau_diff_s[0])
        if r > 0:
            out = ThirdPair(_without_third_pair(model), fx.ExtraRc(r, tau),
                            f"extra_rc: the base tables refitted on the pulse test with a "
                            f"third RC pair ({tau:.0f} s; fit RMS {1e3 * plain_rms:.2f} -> "
                            f"{1e3 * rms:.2f} mV)", rms, v)
    pr.memo[key] = out
    return out
