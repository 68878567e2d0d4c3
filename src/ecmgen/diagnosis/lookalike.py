"""Look-alikes: candidates the held-out part cannot tell apart.

Several candidates can lower the held-out error alike (a capacity error, a current
sensor's gain and an OCV table's SOC scale all move the SOC by the wrong amount for the
charge counted). A name is given only where the winner beats each such look-alike on the
held-out part by the test any candidate must pass (the lower bound of a circular block
bootstrap of the per-sample gain above 0); otherwise the verdict is "X or Y - the data
cannot tell them apart". Each look-alike is judged in the winner's place among all that
was added, so that an effect found later can tell two apart that its round could not.
"""

from __future__ import annotations

import math

import numpy as np

from .signatures import _on_bound


def block_bootstrap_low(d: np.ndarray, block: int, confidence: float, n_boot: int = 2000,
                        seed: int = 0) -> float:
    """Lower ``confidence`` bound of mean(d) by a circular block bootstrap."""
    n = d.size
    if n == 0:
        return float("nan")
    block = int(min(max(block, 1), n))
    nb = int(math.ceil(n / block))
    ext = np.concatenate([d, d[:block]])
    csum = np.concatenate([[0.0], np.cumsum(ext)])
    block_sum = csum[block:block + n] - csum[:n]          # sum of d[s:s+block] (circular)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n, size=(n_boot, nb))
    means = block_sum[starts].sum(axis=1) / (nb * block)
    return float(np.quantile(means, 1.0 - confidence))


def _beats(e_a: np.ndarray, e_b: np.ndarray, block: int, confidence: float,
           seed: int) -> bool:
    """Error ``e_a`` is lower than ``e_b`` by more than noise explains (the held-out test
    a candidate must pass: the block bootstrap's lower bound of |e_b| - |e_a| above 0)."""
    d = np.abs(e_b) - np.abs(e_a)
    d = np.where(np.isfinite(d), d, 0.0)
    return block_bootstrap_low(d, block, confidence, seed=seed) > 0.0


def alike(win: tuple, other: tuple, block: int, confidence: float, seed: int) -> bool:
    """``other`` (held-out error, fit part's error) is a look-alike of ``win``: the winner
    does not beat it on the held-out part, or it beats the winner on the fit part (the data
    favour each on one part)."""
    return not _beats(win[0], other[0], block, confidence, seed) or \
        _beats(other[1], win[1], block, confidence, seed)


def rivals(passing: list) -> list[str]:
    """Names of the other passing candidates (rows of the search: name at [2]; on a base
    refitted for it where [10] is set). A candidate on a refitted base that lost to one on
    the base as it is is no rival: it has the pulse test's freedom too, and the held-out
    test already chose the simpler."""
    win = passing[0]
    out: list[str] = []
    for c in passing[1:]:
        if c[2] != win[2] and c[2] not in out and not (c[10] is not None and win[10] is None):
            out.append(c[2])
    return out


def lookalikes(passing: list, block: int, confidence: float, seed: int) -> list[str]:
    """The :func:`rivals` (held-out error at [7], fit part's error at [12]) that are
    look-alikes of the first (:func:`alike`)."""
    win = passing[0]
    by_name = {c[2]: c for c in reversed(passing[1:])}
    return [n for n in rivals(passing) if alike((win[7], win[12]), (by_name[n][7],
                                                                    by_name[n][12]),
                                                block, confidence, seed)]


def told_apart(steps, alikes, swapped, final, block: int, confidence: float,
               seed: int) -> list[tuple[str, ...]]:
    """The look-alike groups the data cannot tell apart: for each step, the look-alikes of
    its round (``alikes[k]``: names, and whether the step came on a refitted base) that
    are still look-alikes (:func:`alike`) of the final model (``final``: its held-out and
    fit part's errors) in its place among all that was added (``swapped(k, name)``: those
    errors, None where it does not fit). A step on a refitted base keeps its round's
    verdict (swapping it out would need another base). A look-alike that is named itself
    (found in a later round, and still needed with the step: :mod:`.prune`) is no
    alternative to it."""
    groups = []
    named = {st.name for st in steps}
    for k, (names, refitted) in enumerate(alikes[:len(steps)]):
        still = []
        for other in names:
            if other in named:
                # named beside it: not one instead of the other
                continue
            if refitted:
                still.append(other)
                continue
            e = swapped(k, other)
            if e is not None and alike(final, e, block, confidence, seed + 100 + k):
                still.append(other)
        if still:
            groups.append((steps[k].name, *still))
    return groups


def beyond_bounds(tried: list, win: tuple, block: int, confidence: float,
                  seed: int) -> list[tuple[tuple, str]]:
    """The candidates of a round (rows of the search: passed at [0], values at [3], specs at
    [4], held-out error at [7]) that did not pass only because they ended on a bound, yet
    beat its winner ``win`` on the held-out part by the test a candidate must pass, each
    with the parameter on its bound. The record shows more of such an effect than it can
    be, and the winner is then no more than a look-alike of it (an OCV that moves by 2.5
    mV/K with temperature, beyond the entropic term's 1.5, described better than by the
    capacity error that won)."""
    out = []
    for c in tried:
        bound = "" if c[0] or c[2] == win[2] else _on_bound(c[3][-1], c[4])
        if bound and _beats(c[7], win[7], block, confidence, seed):
            out.append((c, bound))
    return out


def near_rivals(tried: list, win: tuple, taken, valid, block: int, confidence: float,
                seed: int) -> list[str]:
    """The candidates of a round that did not pass their test against what was there, but
    that its winner ``win`` does not beat either (:func:`alike`): as much its look-alikes as
    those that passed. ``taken``: names it has already; ``valid(row)``: the fit is one the
    effect can be (one beyond its bounds is :func:`beyond_bounds`'s)."""
    return [c[2] for c in tried if not c[0] and c[2] != win[2] and c[2] not in taken and
            valid(c) and alike((win[7], win[12]), (c[7], c[12]), block, confidence, seed)]


def with_beyond(groups: list, steps, beyond: dict) -> list:
    """``groups`` with each step's look-alikes beyond their bounds (``beyond``: step name ->
    names, :func:`beyond_bounds`) joined to the step's group, or as a group of their own;
    one that is named itself is no alternative to it."""
    named = {st.name for st in steps}
    groups = list(groups)
    for step in steps:
        extra = [n for n in beyond.get(step.name, ()) if n not in named]
        k = next((k for k, g in enumerate(groups) if g[0] == step.name), None)
        if extra and k is not None:
            groups[k] += tuple(n for n in extra if n not in groups[k])
        elif extra:
            groups.append((step.name, *extra))
    return groups
