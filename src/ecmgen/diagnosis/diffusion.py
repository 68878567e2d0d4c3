"""Solid diffusion or a further RC pair: whether the pulse test that made the base tells.

A third RC pair that the pulse test shows (:func:`.refits.third_pair`) is what a pair of
minutes leaves, and what solid diffusion leaves too: the particles' surface concentration
relaxes over a spread of time constants (a square-root-of-time tail), and a free 2RC base
with one further pair follows most of it. Where they differ is the shape, and the pulse
test's rests (minutes to an hour after pulses and SOC moves) show it: the test is fitted
again with the voltage of spherical diffusion taken out (its two parameters searched) and
compared with the fit with the third pair. An extra RC is named where the pair fits the test
better by PAIR_MARGIN; otherwise the data cannot tell them apart. Diffusion is never named
from the shape alone: a spread of time constants also fits what else a pair of fixed time
constant misses (time constants that move with SOC; a capacity off, whose SOC drift the
test's long rests show), and did so better than one pair by up to 13 % of the RMS on cells
with an extra RC and no diffusion (the development sets of bench/diagnose_cells.py), against
at most 22 % on those with diffusion.

Spherical diffusion (a particle of radius R, diffusivity D, tau_d = R^2 / D; Fick's law with
the current as the surface flux): the surface concentration's departure from the mean,
after a current step, is a sum of modes with the roots lambda_k of tan(x) = x::

    v_diff(t) = r_ohm * (1 - sum_k w_k exp(-lambda_k^2 t / tau_d)),   w_k = 10 / lambda_k^2

(sum_k 2 / lambda_k^2 = 1/5). Each mode is an RC pair driven by the current
(time constant tau_d / lambda_k^2, resistance w_k r_ohm), the first 40 of them here (the
rest, below tau_d / 16 000, are a resistance the base's r0 takes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model import effects as fx
from ..model.rc import rc_recurrence

N_MODES = 40
# effects of the cell that a pulse test shows beside an extra RC (at one temperature, its
# OCV level fitted per SOC level)
PULSE_TEST_SHOWS = (fx.Hysteresis.name, fx.CurrentDependentResistance.name)
# the search of the diffusion's two parameters: at most this many Nelder-Mead refits of the
# pulse test after the 13 of the grid, until the RMS changes by less than SEARCH_TOL of it
# (16 refits left the best diffusion 0.7 % above where 60 converge, on the shared suite's
# extra RC c01: more than the difference between the shapes there)
NM_REFITS = 60
SEARCH_TOL = 1e-3
# a third pair is named an extra RC where it fits the pulse test better than the best
# diffusion by the 1 % a refit must gain (.refits); on the development sets of
# bench/diagnose_cells.py no cell with diffusion had a pair better by more than 0.8 %
PAIR_MARGIN = 0.01


def _roots(n: int) -> np.ndarray:
    """The first n positive roots of tan(x) = x, each in (k pi, k pi + pi / 2)."""
    out = []
    for k in range(1, n + 1):
        lo, hi = k * math.pi + 1e-9, k * math.pi + math.pi / 2 - 1e-9
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if math.tan(mid) > mid else (mid, hi)
        out.append(0.5 * (lo + hi))
    return np.array(out)


ROOTS = _roots(N_MODES)
WEIGHTS = (1.0 / ROOTS ** 2) / np.sum(1.0 / ROOTS ** 2)


def sphere_voltage(time_s: np.ndarray, current_a: np.ndarray, r_ohm: float,
                   tau_d_s: float) -> np.ndarray:
    """The diffusion voltage over a record (each mode an RC pair, the current held over its
    sample as the simulator holds it)."""
    dt = np.diff(time_s, prepend=time_s[0])
    out = np.zeros(len(time_s))
    for lam, w in zip(ROOTS, WEIGHTS):
        a = np.exp(-dt * lam * lam / tau_d_s)
        out += w * rc_recurrence(a, (1.0 - a) * current_a)
    return r_ohm * out


@dataclass(frozen=True)
class Shape:
    """What the pulse test says of a third pair: ``name`` "extra_rc", or None (it cannot
    tell it from diffusion), the RMS of its fit with the pair and with the best diffusion
    found, that diffusion's parameters."""

    name: str | None
    pair_rms_v: float
    sphere_rms_v: float
    r_ohm: float
    tau_d_s: float

    def words(self) -> str:
        return (f"the pulse test fitted with one further RC pair: {1e3 * self.pair_rms_v:.3f} mV "
                f"RMS, with spherical diffusion ({1e3 * self.r_ohm:.2f} mohm, tau_d "
                f"{self.tau_d_s:.0f} s): {1e3 * self.sphere_rms_v:.3f} mV")


def pair_or_diffusion(refit, series, voltage_v: np.ndarray, pair_rms_v: float, r_ohm: float,
                      tau_s: float) -> Shape:
    """Which shape the pulse test prefers: ``refit(voltage_v)`` -> (model, RMS) is the
    plain 2RC fit of ``series`` (the test) with ``voltage_v`` taken out, ``pair_rms_v`` the
    RMS of its fit with a third pair (``r_ohm``, ``tau_s``) and the same voltage taken out.

    The diffusion's two parameters are searched about where its first mode is the pair
    (tau_d = lambda_1^2 tau_s, the first mode holding half the resistance): tau_d on a log
    grid of ratio 2 (four values), each with the resistance where the fit's squared RMS,
    nearly a parabola in r (the fit is linear in the resistances), has its minimum (the
    plain fit at r = 0 and two more give it, a fourth fit that minimum); then Nelder-Mead in
    the two logarithms from the best of them (NM_REFITS fits of the pulse test)."""
    from scipy.optimize import minimize

    t, i = series.time_s, series.current_a
    zero = refit(voltage_v)[1] ** 2
    r1 = 2.0 * r_ohm
    seen: dict = {}

    def rms(x):
        key = tuple(np.round(x, 5))
        if key not in seen:
            seen[key] = refit(voltage_v + sphere_voltage(t, i, *np.exp(x)))[1]
        return seen[key]

    def at(log_tau):
        """The best resistance's log at time constant exp(log_tau)."""
        f1, f2 = (rms((math.log(r), log_tau)) ** 2 for r in (r1, 2.0 * r1))
        curv = f2 - 2.0 * f1 + zero            # f(r) = zero + b r + c r^2, at r = 0, r1, 2 r1
        r = r1 * max(0.1, (3.0 * zero + f2 - 4.0 * f1) / (2.0 * curv) if curv > 0 else 2.0)
        rms((math.log(r), log_tau))
        return math.log(r)

    x = math.log(ROOTS[0] ** 2 * tau_s)
    for k in (-1, 0, 1, 2):
        at(x + math.log(2.0) * k)
    x0 = np.array(min(seen, key=seen.get))
    minimize(rms, x0, method="Nelder-Mead",
                   options={"maxfev": NM_REFITS, "xatol": 0.01, "fatol": SEARCH_TOL * pair_rms_v,
                            "initial_simplex": [x0, x0 + [0.15, 0.0], x0 + [0.0, 0.3]]})
    best = min(seen, key=seen.get)
    sphere = seen[best]
    name = "extra_rc" if pair_rms_v < (1.0 - PAIR_MARGIN) * sphere else None
    return Shape(name, pair_rms_v, sphere, float(math.exp(best[0])), float(math.exp(best[1])))



def told_from_diffusion(named: list[str], pr, pair) -> tuple[bool, str]:
    """Whether the pulse test ``pr`` (a :class:`.refits.PulseRefit`) tells the third pair
    ``pair`` (a :class:`.refits.ThirdPair`) from diffusion, and a note that says why. Not
    where an effect the test shows is ``named`` beside it: what that effect's model misses
    there, either shape takes up (a hysteresis whose band changes with SOC made an extra RC
    of 290 s look like diffusion)."""
    beside = [n for n in named if n in PULSE_TEST_SHOWS]
    if beside:
        return False, (f"extra_rc or diffusion: the pulse test shows their shape only where it "
                       f"shows nothing else named ({beside[0]} is)")
    shape = pair_or_diffusion(pr.refit, pr.series, pair.voltage_v, pair.rms_v,
                              pair.effect.r_ohm, pair.effect.tau_s)
    return shape.name is not None, f"{shape.name or 'extra_rc or diffusion'}: {shape.words()}"
