"""Start SOC of a record from its rested voltages and the OCV.

A *rest* is a run of samples with |current| at most ``rest_a``; its *rested point* is
its last sample (the most relaxed one). Where a record leaves out a stretch in which
current flowed (a logged Ah column that jumps while the logged current is zero: the
Panasonic HPPC file omits its SOC moves), a rest is cut there: what follows is a new
rest after that (unlogged) current, its length counted from the last sample before the
gap (an upper bound: the cell rested for at most that long).

* A pulse test (:func:`pulse_test_start_soc`): 1.0 when it opens rested at or above the
  top of the OCV; otherwise the start SOC is fitted so that every rested voltage matches
  the OCV at its coulomb-counted SOC, by least squares over all
  rests, with one free voltage offset for the rests after a discharge and one for those
  after a charge (hysteresis: the rested cell sits below the OCV after a discharge and
  above it after a charge, by an amount the OCV table does not know). A weak prior keeps
  the offsets small where the data cannot tell them from a SOC shift.
* A drive cycle or any other record (:func:`record_start_soc`): SOC 1.0 at the end of
  a constant-voltage charge it opens with; else the last (most relaxed) sample of the
  rest it opens with, where the OCV is steep enough to tell SOC from one voltage; else
  the same fit over its rests where it has several spread over the SOC range; a record
  opening with a charge is never judged by a rest after a later discharge.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from .measure import TimeSeries

MAX_OFFSET_PRIOR_V = 0.02    # prior scale of the hysteresis offsets (LFP: 10-30 mV)
# an offset beyond three times the prior's scale is no hysteresis but an OCV that does not
# describe the rests (a flat hold beyond its measured span, another temperature or cell)
OFFSET_WARN_V = 3 * MAX_OFFSET_PRIOR_V
MIN_FIT_SPAN = 0.2           # a record's rests spanning this much SOC are fitted together
NOISE_V = 0.002              # scale of a rested voltage's own scatter


@dataclass(frozen=True)
class Rests:
    """The rests of a record, one entry per rest (arrays of equal length)."""

    index: np.ndarray        # last sample of the rest (its rested point)
    duration_s: np.ndarray   # from the end of the current before it (or the record start)
    after: np.ndarray        # +1 after a charge, -1 after a discharge (the net charge of
                             # the 5 minutes of current before), 0 at the record start
    charge_ah: np.ndarray    # cumulative charge at the rested point (0 at the first sample)
    voltage_v: np.ndarray

    def __len__(self) -> int:
        return int(self.index.size)

    def select(self, mask) -> "Rests":
        m = np.asarray(mask)
        return Rests(self.index[m], self.duration_s[m], self.after[m], self.charge_ah[m],
                     self.voltage_v[m])


def find_rests(series: TimeSeries, rest_a: float, min_rest_s: float = 0.0) -> Rests:
    """Every rest of the record lasting at least ``min_rest_s`` (see the module doc). The
    rest a record opens with always counts: a record is taken to start rested (how long
    the cell rested before the file began is not known)."""
    i, t = series.current_a, series.time_s
    from .steps import pulse_test_gaps

    rested = np.abs(i) <= rest_a
    gap = np.zeros(len(i), bool)
    gap[pulse_test_gaps(series) + 1] = True     # charge flowed that the file does not show
    q = series.coulomb_ah()
    idx, dur, after = [], [], []
    k, n = 0, len(i)
    while k < n:
        if not rested[k]:
            k += 1
            continue
        a = k
        while k + 1 < n and rested[k + 1] and not gap[k + 1]:
            k += 1
        b = k                       # rest [a, b]
        if a == 0:
            start_t, d = t[0], 0
        elif gap[a]:   # after unlogged current: rested for at most the time of the gap
            start_t, d = t[a - 1], int(np.sign(q[a] - q[a - 1]))
        else:   # the direction of the net charge over the last 5 minutes of current
            w = (t >= t[a - 1] - 300.0) & (np.arange(n) < a)
            d = int(np.sign(q[a - 1] - q[np.argmax(w)])) or int(np.sign(i[a - 1]))
            start_t = t[a - 1]
        if a == 0 or t[b] - start_t >= min_rest_s:
            idx.append(b)
            dur.append(t[b] - start_t)
            after.append(d)
        k += 1
    ix = np.array(idx, dtype=int)
    return Rests(ix, np.array(dur, dtype=np.float64), np.array(after, dtype=int), q[ix],
                 series.voltage_v[ix])


@dataclass(frozen=True)
class StartSoc:
    soc0: float
    rms_v: float                   # rested voltage - (OCV + offset), RMS
    offset_v: dict                 # {"after discharge": v, "after charge": v}
    n: int
    note: str


def fit_start_soc(ocv, capacity_ah: float, rests: Rests, source="", *,
                  bounds: tuple[float, float] | None = None) -> StartSoc:
    """Least-squares start SOC of a record from its rests (see the module doc).

    The search runs over the start SOCs that keep every rest's SOC within [-0.02, 1.02]
    (or within ``bounds``)."""
    if len(rests) == 0:
        raise InputError(source, "no rest to find the start SOC from; give the start SOC")
    x = rests.charge_ah / capacity_ah
    v = rests.voltage_v
    groups = [g for g in (-1, 1) if np.any(rests.after == g)]
    # rests at the record start count with the discharge group (a record starts after
    # a charge and a rest, or in the middle of a test): no group of their own
    sign = np.where(rests.after == 0, groups[0] if groups else -1, rests.after)
    lo = -0.02 - float(x.min()) if bounds is None else bounds[0]
    hi = 1.02 - float(x.max()) if bounds is None else bounds[1]
    if hi < lo:
        raise InputError(source, f"the record moves {np.ptp(x) * capacity_ah:.4g} Ah between "
                                 f"its rests, more than cell.capacity_ah = {capacity_ah:g} Ah")
    ridge = (NOISE_V / MAX_OFFSET_PRIOR_V) ** 2

    def solve(s0):
        r = v - ocv.ocv_at(s0 + x)
        off = {}
        res = r.copy()
        for g in np.unique(sign):
            m = sign == g
            c = float(np.sum(r[m]) / (m.sum() + ridge))
            off[int(g)] = c
            res[m] -= c
        cost = float(res @ res) + ridge * sum(c * c for c in off.values())
        return cost, off, res

    grid = np.linspace(lo, hi, max(3, int(np.ceil((hi - lo) / 0.002)) + 1))
    costs = np.array([solve(s)[0] for s in grid])
    k = int(np.argmin(costs))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    for _ in range(40):                       # golden-section refinement around the best
        m1, m2 = a + 0.382 * (b - a), a + 0.618 * (b - a)
        if solve(m1)[0] <= solve(m2)[0]:
            b = m2
        else:
            a = m1
    s0 = 0.5 * (a + b)
    if solve(grid[k])[0] < solve(s0)[0]:
        s0 = float(grid[k])
    _, off, res = solve(s0)
    rms = float(np.sqrt(np.mean(res ** 2)))
    names = {-1: "after discharge", 1: "after charge"}
    offsets = {names[g]: c for g, c in off.items()}
    text = ", ".join(f"{c * 1e3:+.1f} mV {n}" for n, c in offsets.items())
    note = (f"start SOC {s0:.3f} fitted so that {len(rests)} rested voltages match the OCV "
            f"(RMS {rms * 1e3:.1f} mV; hysteresis offset {text})")
    worst = max((abs(c) for c in offsets.values()), default=0.0)
    if worst > OFFSET_WARN_V:
        note += (f"; warning: an offset of {worst * 1e3:.0f} mV is beyond any hysteresis "
                 f"({OFFSET_WARN_V * 1e3:.0f} mV): the OCV does not describe these rests "
                 "(SOC beyond its measured span, another temperature or cell), so this "
                 "start SOC is uncertain; give it (soc0) if it is known")
    return StartSoc(float(s0), rms, offsets, len(rests), note)


def opening_cv_charge(series: TimeSeries, capacity_ah: float, rest_a: float,
                      min_rest_s: float = 60.0, *, after_discharge: bool = False
                      ) -> tuple[float, str] | None:
    """The start SOC of a record that opens with a charge ending in a constant-voltage
    phase (SOC 1.0 at its end, the charge before it counted back), and how it was found;
    None for any other record. A charge logged from an empty cell (the Leaf's HPPC files)
    tells the start SOC better than any rest: no OCV is needed.

    ``after_discharge``: the first charge that moves at least CV_CHARGE_SHARE of the
    capacity counts even after a discharge (a pulse test that first empties the cell,
    as the Leaf's 40 degC file does); a drive cycle's regen pulses never do."""
    i = series.current_a
    q = series.coulomb_ah()
    k = 0
    while True:
        moving = np.flatnonzero(np.abs(i[k:]) > rest_a)
        if moving.size == 0:
            return None
        first = k + int(moving[0])
        if i[first] < 0:
            if not after_discharge:
                return None
            up = np.flatnonzero(i[first:] > rest_a)
            if up.size == 0:
                return None
            first += int(up[0])
        b = _charge_end(series, first, rest_a, min_rest_s)
        charged = float(q[b - 1] - q[first])
        if not after_discharge or charged >= CV_CHARGE_SHARE * capacity_ah:
            break
        k = b                      # a charge pulse: look on
    if not _cv_end(series, first, b):
        return None
    end = float(q[b - 1])
    return 1.0 - end / capacity_ah, (f"SOC 1.0 at the end of the constant-voltage charge "
                                     f"the record opens with ({charged:.4g} Ah, ending "
                                     f"{series.time_s[b - 1] - series.time_s[0]:.0f} s after "
                                     f"its start)")


CV_CHARGE_SHARE = 0.05


CAPACITY_SCALES = np.round(np.arange(0.70, 1.4001, 0.005), 3)   # as capacity_error's range
CAPACITY_RMS_GAIN = 0.5   # another capacity is taken when it halves the rests' RMS misfit


def pulse_test_start_soc(ocv, capacity_ah: float, rests: Rests, source="") -> StartSoc:
    """Start SOC of a pulse test from its rests (``find_rests``): 1.0 when the rest it
    opens with sits at or above the top of the OCV (a full cell: nothing else is
    consistent with that voltage, and a fit would trade the OCV's offset for a shift in
    SOC), else :func:`fit_start_soc` over all of them."""
    if len(rests) and rests.after[0] == 0 and rests.charge_ah[0] == 0 and \
            rests.voltage_v[0] >= float(np.ravel(ocv.ocv_v)[-1]):
        return StartSoc(1.0, float("nan"), {}, 1,
                        f"start SOC 1.0: its opening rest ({rests.voltage_v[0]:.4f} V) is at "
                        f"or above the top of the OCV ({float(np.ravel(ocv.ocv_v)[-1]):.4f} V)")
    return fit_start_soc(ocv, capacity_ah, rests, source)


def pulse_test_start_soc_and_capacity(ocv, capacity_ah: float, rests: Rests, source=""
                                      ) -> tuple[StartSoc, float]:
    """Start SOC and the capacity the rests imply, fitted together: a pulse test run by a
    wrong nominal capacity moves the SOC by other steps than it says, and a start SOC fitted
    with the nominal one spreads that error over every level. Returns (start SOC, capacity):
    the configured capacity unless another (CAPACITY_SCALES) fits the rests with at most
    CAPACITY_RMS_GAIN of the misfit (measured on the synthetic cells of
    ../shared/diagnose-suite: the two with a capacity error 11.2 -> 1.8 mV and 17.2 -> 1.1 mV
    at 0.880 / 1.140 of nominal, true 0.885 / 1.138; the ten others unchanged)."""
    start = pulse_test_start_soc(ocv, capacity_ah, rests, source)
    if len(rests) < 4:
        return start, capacity_ah
    # a full start (the opening rest at the top of the OCV) stays full
    bounds = None if np.isfinite(start.rms_v) else (start.soc0, start.soc0)
    nominal = start if bounds is None else fit_start_soc(ocv, capacity_ah, rests, source,
                                                          bounds=bounds)
    best, scale = nominal, 1.0
    for k in CAPACITY_SCALES:
        try:
            fit = fit_start_soc(ocv, capacity_ah * float(k), rests, source, bounds=bounds)
        except InputError:          # the rests move more charge than that capacity holds
            continue
        if fit.rms_v < best.rms_v:
            best, scale = fit, float(k)
    if scale == 1.0 or best.rms_v > CAPACITY_RMS_GAIN * nominal.rms_v:
        return start, capacity_ah
    q = capacity_ah * scale
    note = (f"{best.note}, with the capacity the rests imply, {q:.4g} Ah = {scale:.3f} x "
            f"cell.capacity_ah ({nominal.rms_v * 1e3:.1f} mV RMS with {capacity_ah:g} Ah): the "
            f"pulse test's SOC axis uses it, the model keeps {capacity_ah:g} Ah")
    return replace(best, note=note), q


# --------------------------------------------------------------------------- records

def _cv_end(series: TimeSeries, a: int, b: int) -> bool:
    """True when the charge [a, b) ends in a constant-voltage phase: over its last part
    the current falls below half its median while the voltage stays within 5 mV."""
    i, v = series.current_a[a:b], series.voltage_v[a:b]
    if i.size < 5:
        return False
    typical = float(np.median(i))
    tail = np.flatnonzero(i < 0.5 * typical)
    if tail.size == 0 or tail[0] < 2:
        return False
    return bool(np.ptp(v[tail[0]:]) <= 0.005)


REST_VOLTAGE_V = 0.005       # how far a rested voltage may sit from the OCV table
WEAK_REST_SOC = 0.02         # (hysteresis, relaxation left): the SOC error that buys


def _soc_error(ocv, v: float) -> float:
    """The SOC error of inverting a rested voltage ``v`` that is REST_VOLTAGE_V off."""
    return float(abs(ocv.soc_at(v + REST_VOLTAGE_V) - ocv.soc_at(v - REST_VOLTAGE_V)) / 2.0)


def _charge_end(series: TimeSeries, a: int, rest_a: float, min_rest_s: float) -> int:
    """End (exclusive) of the charge starting at sample ``a``: the first discharge sample
    or the start of the first rest of at least ``min_rest_s`` after it."""
    i, t = series.current_a, series.time_s
    dis = np.flatnonzero(i[a:] < -rest_a)
    stop = a + int(dis[0]) if dis.size else len(i)
    rested = np.abs(i[a:stop]) <= rest_a
    k = a
    while k < stop:
        if rested[k - a]:
            m = k
            while m + 1 < stop and rested[m + 1 - a]:
                m += 1
            if t[m] - t[k] >= min_rest_s or m + 1 == stop:
                return k
            k = m + 1
        else:
            k += 1
    return stop


SHORT_REST_S = 10.0          # the stops of a drive cycle count as rests of an unrelaxed record
RELAXED_DRIFT_V = 0.001      # a rest whose voltage moves more over its last half is unrelaxed


def _window_means(series: TimeSeries, end: int) -> tuple[np.ndarray, float] | None:
    """The voltage of the rest 0..end averaged over three windows of a fifth of its
    length, at its start, middle and end (equally spaced, so a pure exponential
    relaxation gives a geometric sequence), and the noise of such a mean (V); None for a
    rest under 3 samples or 5 s."""
    t, v = series.time_s[:end + 1], series.voltage_v[:end + 1]
    if t.size < 3 or t[-1] - t[0] < 5.0:
        return None
    w = 0.2 * (t[-1] - t[0])
    centres = (t[0] + 0.5 * w, 0.5 * (t[0] + t[-1]), t[-1] - 0.5 * w)
    means = []
    for c in centres:
        inside = np.abs(t - c) <= 0.5 * w + 1e-9
        means.append(float(np.mean(v[inside])) if inside.any() else float(np.interp(c, t, v)))
    d = np.diff(v)
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0) if d.size else 0
    n = max(int(np.count_nonzero(np.abs(t - centres[2]) <= 0.5 * w + 1e-9)), 1)
    return np.array(means), noise / np.sqrt(n)


def _unrelaxed(series: TimeSeries, end: int) -> str | None:
    """Why the rest a record opens with (samples 0..end) cannot be taken as relaxed, or
    None: its voltage still moves from the middle to the end of it by more than
    RELAXED_DRIFT_V and its noise, or it is too short to tell (under 3 samples or 5 s)."""
    t = series.time_s
    got = _window_means(series, end)
    if got is None:
        return f"the rest it opens with, {t[end] - t[0]:.0f} s, is too short to tell its OCV"
    means, noise = got
    moved = float(means[2] - means[1])
    if abs(moved) <= max(RELAXED_DRIFT_V, 4.0 * noise):
        return None
    return (f"the rest it opens with is unrelaxed: its voltage still moved "
            f"{moved * 1e3:+.1f} mV over its last half")


def _relaxed_voltage(series: TimeSeries, end: int) -> float | None:
    """Where the relaxation of the rest 0..end is heading, from its start, middle and end
    voltages (window means) taken as steps of a geometric (exponential) approach (Aitken's
    delta squared); None where the rest does not slow down as a relaxation does."""
    got = _window_means(series, end)
    if got is None:
        return None
    m = got[0]
    d1, d2 = float(m[1] - m[0]), float(m[2] - m[1])
    if d1 * d2 <= 0 or abs(d2) >= abs(d1):
        return None
    return float(m[2] + d2 * d2 / (d1 - d2))


def settled_opening(series: TimeSeries, capacity_ah: float, rest_a: float, ocv_top_v: float,
                    min_rest_s: float = 300.0) -> bool:
    """Whether the record opens where its voltage tells the SOC without a model: with a
    charge ending in a constant-voltage phase, or one of at least CV_CHARGE_SHARE of the
    capacity that ends at or above ``ocv_top_v`` (a full charge), or with a rest of at
    least ``min_rest_s`` whose voltage has stopped moving (:func:`_unrelaxed`). A record
    cut from a drive (under load, in a stop of a few seconds, mid-relaxation) does not."""
    if opening_cv_charge(series, capacity_ah, rest_a) is not None:
        return True
    i, t, v = series.current_a, series.time_s, series.voltage_v
    moving = np.flatnonzero(np.abs(i) > rest_a)
    if moving.size == 0:
        return True
    first = int(moving[0])
    if i[first] > 0:
        b = _charge_end(series, first, rest_a, 60.0)
        q = series.coulomb_ah()
        return bool(q[b - 1] - q[first] >= CV_CHARGE_SHARE * capacity_ah
                    and v[b - 1] >= ocv_top_v)
    if first == 0 or t[first - 1] - t[0] < min_rest_s:
        return False
    return _unrelaxed(series, first - 1) is None


def record_start_soc(ocv, capacity_ah: float, series: TimeSeries, rest_a: float,
                     min_rest_s: float = 60.0, fit_rest_s: float = 300.0
                     ) -> tuple[float, str]:
    """Start SOC of a record (a drive cycle) and how it was found, in this order:

    1. it opens with a charge that ends in a constant-voltage phase: SOC 1.0 there;
    2. it opens with a rest where the OCV is steep enough that 5 mV of hysteresis or
       relaxation move the SOC by at most 2 %: the OCV of that rest's last (most
       relaxed) sample;
    3. it has at least 3 rests of ``fit_rest_s`` (or its opening rest) spanning
       MIN_FIT_SPAN of SOC (an LFP plateau, or no opening rest): :func:`fit_start_soc`
       over all of them; else the opening rest as in 2.;
    4. it opens with a charge: the rest right after that charge, else SOC 1.0 if the
       charge ended above the top of the OCV, else the OCV of its last voltage (an upper
       bound); never a rest after a later discharge;
    5. the end of its first rest of at least ``min_rest_s``, else its first rested
       sample."""
    i, v = series.current_a, series.voltage_v
    q = series.coulomb_ah()
    moving = np.flatnonzero(np.abs(i) > rest_a)

    def at(k: int, what: str) -> tuple[float, str]:
        return float(ocv.soc_at(v[k])) - float(q[k]) / capacity_ah, what

    if moving.size == 0:
        return at(len(i) - 1, "the OCV of its last sample (the record never moves)")
    first = int(moving[0])
    opens_with_charge = bool(i[first] > 0)
    cv = opening_cv_charge(series, capacity_ah, rest_a, min_rest_s)
    if cv is not None:
        return cv
    if opens_with_charge:
        b = _charge_end(series, first, rest_a, min_rest_s)
    opening = first - 1 if np.abs(i[0]) <= rest_a else None
    drift = None if opening is None else _unrelaxed(series, opening)
    if drift is not None and v[opening] < float(ocv.ocv_v[-1]):
        extrapolated = _relaxed_voltage(series, opening)
        if extrapolated is not None:
            soc = float(ocv.soc_at(extrapolated)) - float(q[opening]) / capacity_ah
            return soc, (f"the OCV of {extrapolated:.4f} V, where the relaxation of the rest "
                         f"it opens with is heading ({drift}; its last sample "
                         f"{v[opening]:.4f} V)")
        rests = find_rests(series, rest_a, SHORT_REST_S)
        if len(rests) >= 3 and np.ptp(rests.charge_ah) / capacity_ah >= MIN_FIT_SPAN:
            fit = fit_start_soc(ocv, capacity_ah, rests, series.source)
            return fit.soc0, f"a fit to its rests ({drift}): {fit.note}"
    # one rested voltage tells the SOC to REST_VOLTAGE_V / slope; where the OCV is that
    # flat (an LFP plateau), all the record's rests are fitted together instead
    weak = opening is not None and _soc_error(ocv, v[opening]) > WEAK_REST_SOC
    rests = find_rests(series, rest_a, fit_rest_s)
    if (opening is None or weak) and len(rests) >= 3 and \
            np.ptp(rests.charge_ah) / capacity_ah >= MIN_FIT_SPAN:
        fit = fit_start_soc(ocv, capacity_ah, rests, series.source)
        return fit.soc0, f"a fit to its rests: {fit.note}"
    if opening is not None:
        return at(opening, "the OCV of the last sample of the rest it opens with")
    if opens_with_charge:
        after = find_rests(series, rest_a, min_rest_s)
        nxt = np.flatnonzero(i[b:] < -rest_a)
        stop = b + int(nxt[0]) if nxt.size else len(i)
        ends = after.index[(after.index >= b) & (after.index < stop)]
        if ends.size:
            return at(int(ends[0]), "the OCV of the rest after the charge the record opens with")
        if v[b - 1] >= float(ocv.ocv_v[-1]):
            return 1.0 - float(q[b - 1]) / capacity_ah, (
                "SOC 1.0 at the end of the charge the record opens with (above the top of "
                "the OCV)")
        return at(b - 1, "the OCV of the last voltage of the charge the record opens with "
                         "(no rest after it: an upper bound)")
    rests = find_rests(series, rest_a, min_rest_s)
    if len(rests):
        return at(int(rests.index[0]), "the OCV of the end of its first rest")
    rested = np.flatnonzero(np.abs(i) <= rest_a)
    if rested.size == 0:
        raise InputError(series.source, "no rested sample to find the start SOC from; "
                                         "give soc0")
    return at(int(rested[0]), "the OCV of its first rested sample")
