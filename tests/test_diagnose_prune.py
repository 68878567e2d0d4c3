"""An effect named early must still be needed once later ones have joined
(ecmgen.diagnosis.prune), and a look-alike named beside a step is no alternative to it
(ecmgen.diagnosis.lookalike.told_apart). Mechanics on known-truth error arrays: which
model needs which effect is set by construction."""

from __future__ import annotations

import numpy as np

from ecmgen.diagnosis.lookalike import block_bootstrap_low, told_apart
from ecmgen.diagnosis.prune import Fitted, still_needed
from ecmgen.diagnosis.result import DiagnoseStep

RNG = np.random.default_rng(1)
NOISE = 1e-3 * RNG.standard_normal(3000)


def _state(names, e):
    return Fitted([], [(n, {}, {}) for n in names], tuple(names), None, e,
                  float(np.mean(np.abs(e))), 0.0, e)


def _needed(state, alt):
    """The held-out test of the search (a gain of 8 %, beyond noise: the bootstrap), and
    the fit part's the other way."""
    d = np.abs(alt.e_judge) - np.abs(state.e_judge)
    if not (alt.mae_v - state.mae_v >= 0.08 * alt.mae_v
            and block_bootstrap_low(d, 50, 0.99) > 0):
        return "not needed"
    d = np.abs(state.e_fit) - np.abs(alt.e_fit)
    return "tie" if block_bootstrap_low(d, 50, 0.99) > 0 else "needed"


def test_an_effect_the_later_ones_made_redundant_is_dropped():
    """Truth: the record misses B and C. A was named first (a look-alike of B), then B and C
    joined. Without A (B and C refitted) the error is the final one: A is dropped; without
    B or C it triples: both stay. An effect whose drop fails to fit stays."""
    final = _state(("A", "B", "C"), NOISE)

    def without(state, drop):
        left = tuple(n for n in state.model if n != drop)
        if drop == "C" and "A" not in left:
            return None
        scale = 1.0 if {"B", "C"} <= set(left) else 3.0
        return _state(left, scale * NOISE + 1e-5 * RNG.standard_normal(NOISE.size))

    state, left, dropped, ties = still_needed(["A", "B", "C"], final, without, _needed)
    assert left == ["B", "C"] and [d.name for d in dropped] == ["A"] and not ties
    assert state.model == ("B", "C")
    assert dropped[0].mae_with_v == final.mae_v
    # an effect on a base refitted for it is not judged
    state, left, dropped, _ = still_needed(["A", "B", "C"], final, without, _needed, {"A"})
    assert left == ["A", "B", "C"] and not dropped


def test_of_two_redundant_effects_the_cheaper_drop_goes_first_and_the_other_is_judged_again():
    """A and B each stand in for the other (either alone leaves the final error), C is
    needed: one of A, B is dropped (the one whose drop leaves less), the other then needed."""
    final = _state(("A", "B", "C"), NOISE)

    def without(state, drop):
        left = tuple(n for n in state.model if n != drop)
        ok = "C" in left and ("A" in left or "B" in left)
        extra = 1.01 if drop == "B" else 1.0
        return _state(left, (extra if ok else 3.0) * NOISE)

    _, left, dropped, _ = still_needed(["A", "B", "C"], final, without, _needed)
    assert [d.name for d in dropped] == ["A"] and left == ["B", "C"]


def test_an_effect_the_data_favour_on_one_part_only_is_a_tie():
    """Without A (B refitted) the held-out error doubles but the fit part's halves: the
    data favour each on one part, and A with B, found after it, is a group the data cannot
    tell apart (A is neither dropped nor needed)."""
    final = Fitted([], [], ("A", "B"), None, NOISE, float(np.mean(np.abs(NOISE))), 0.0,
                   NOISE)

    def without(state, drop):
        if drop == "B":
            return _state(("A",), 3.0 * NOISE)
        alt = _state(("B",), 2.0 * NOISE)
        alt.e_fit = 0.5 * NOISE
        return alt

    state, left, dropped, ties = still_needed(["A", "B"], final, without, _needed)
    assert left == ["A", "B"] and not dropped and ties == [("A", "B")]
    assert state is final


def test_a_lookalike_named_beside_the_step_is_no_alternative_to_it():
    """Round 1's look-alikes of A were B and D; B was named in round 2 beside A. Only D is
    judged in A's place (and is a look-alike: it does as well)."""
    steps = [DiagnoseStep("A", None, 1.0, 0.5, 0.1), DiagnoseStep("B", None, 0.5, 0.2, 0.1)]
    asked = []

    def swapped(k, other):
        asked.append(other)
        return NOISE, NOISE

    groups = told_apart(steps, [(["B", "D"], False), ([], False)], swapped, (NOISE, NOISE), 50,
                        0.99, 0)
    assert asked == ["D"] and groups == [("A", "D")]
