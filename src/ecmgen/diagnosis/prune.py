"""An effect named early must still be needed once the later ones have joined.

The greedy search adds one effect a round, and an effect found in a later round can
describe what an earlier one stood in for (an OCV error taken first where the record
misses a temperature dependence and an entropic term: the temperature dependence found
next does the work the OCV error did). After the search each named effect is judged
again: it is dropped from the final model, the rest refitted without it, and it stays
named only where the final model beats that one on the held-out part by the test any
candidate must pass. Of the effects that are no longer needed the one whose drop leaves
the lowest held-out error goes first, and the others are judged again without it.

An effect dropped this way is a look-alike of the later effects that took its place: they
are judged against it in their place at the end, as their round's look-alikes are
(:mod:`ecmgen.diagnosis.lookalike`), so that where the data cannot tell it from them the
verdict says so rather than name one. Where the model without it is worse on the held-out
part but better on the fit part, the data favour each on one part: the effect and those
found after it are a group the data cannot tell apart, as look-alikes are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class Fitted:
    """A model the search judged: the record's faults corrected (``fixes``), the effects
    fitted (``added``: (name, values, specs)), the model, its held-out simulation, error
    and MAE, the fit part's MAE and error."""

    fixes: list
    added: list
    model: object
    judge_sim: object
    e_judge: np.ndarray
    mae_v: float
    fit_mae_v: float
    e_fit: np.ndarray


@dataclass(frozen=True)
class Dropped:
    """A named effect that the final model did not need: the held-out error with it and
    after it was dropped and the rest refitted."""

    name: str
    mae_with_v: float
    mae_without_v: float


def still_needed(names: list[str], final: Fitted, without: Callable[[Fitted, str], Fitted | None],
                 verdict: Callable[[Fitted, Fitted], str], keep: set[str] = frozenset()
                 ) -> tuple[Fitted, list[str], list[Dropped], list[tuple[str, ...]]]:
    """Drop, one at a time, the named effects the model does not need.

    ``without(state, name)`` is ``state`` with ``name`` dropped and the rest refitted (None
    where that fails or leaves a parameter on its bound: the effect is kept);
    ``verdict(state, alt)`` is "needed" where ``state`` beats ``alt`` by the held-out test
    and ``alt`` does not beat it on the fit part, "tie" where each wins on one part, else
    "not needed"; effects in ``keep`` are not judged (a base refitted for one: dropping it
    would need the other base). Returns the final state, the names left (in their order),
    those dropped, and the ties (each effect named with those found after it, or with the
    others where it is the last: the data cannot tell it from them)."""
    names = list(names)
    dropped: list[Dropped] = []
    while True:
        best, ties = None, []
        for n in names if len(names) >= 2 else ():
            if n in keep:
                continue
            alt = without(final, n)
            said = "needed" if alt is None else verdict(final, alt)
            if said == "tie":
                ties.append(n)
            elif said != "needed" and (best is None or alt.mae_v < best[1].mae_v):
                best = (n, alt)
        if best is None:
            break
        n, alt = best
        dropped.append(Dropped(n, final.mae_v, alt.mae_v))
        names.remove(n)
        final = alt
    groups = []
    for n in ties:
        after = names[names.index(n) + 1:] or [m for m in names if m != n]
        groups.append((n, *after))
    return final, names, dropped, groups
