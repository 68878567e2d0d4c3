"""`diagnose` names the effects it has a candidate for, on cells it does not share equations
with: bench/diagnose_cells.py (numpy physics, no ecmgen import), in its quick form (half
the pulse levels and cycle; each cell a pulse test, an OCV table and a drive record with
its truth kept apart), diagnosed from its case.toml as a user would.

The seeds are a block fixed before any of these cells was diagnosed: two consecutive seeds
per kind from 9400000, then two controls. The bounds are the diagnose spec's: a cell whose
one missing effect diagnose has a candidate for gets that effect named, and nothing else (a
wrong name is worse than a miss), with the held-out error down by >= 40 %; a control gets
nothing named and no "unexplained" (no false alarm). A cell whose effect is missed is a
strict known miss, with what it got in words; a wrong name fails there too."""

from __future__ import annotations

import pytest

from conftest import diagnose_generated

pytestmark = pytest.mark.slow

FIRST_SEED = 9400000
PER_KIND = 2
KINDS = ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error",
         "temperature_dependence")
CELLS = {FIRST_SEED + PER_KIND * k + j: kind for k, kind in enumerate(KINDS)
         for j in range(PER_KIND)}
CONTROLS = (FIRST_SEED + PER_KIND * len(KINDS), FIRST_SEED + PER_KIND * len(KINDS) + 1)
# what these cells get today where it is not what the spec asks: misses, no wrong name. The
# pulse test that makes the base shows the effect too, and the base fitted on it leaves a
# held-out error within 3x the noise, so nothing is named (for the extra RC the base's slow
# pair came out at 314 s, against 41 s true; the base refitted with a third pair takes the
# held-out error from 1.72 to 0.97 mV, a gain below the 1.15 mV noise)
KNOWN_MISSES = {
    9400002: "extra RC of 408 s not named: held-out gain 0.75 mV, below 1.15 mV noise",
    9400004: "current-dependent resistance (i0 0.55 A) not named: held-out error 1.63 mV "
             "against 1.05 mV noise",
    9400005: "current-dependent resistance (i0 0.10 A) not named: held-out error 1.94 mV "
             "against 1.05 mV noise",
}


def _params(seeds):
    # raises=AssertionError: a known miss that turns into a wrong name (pytest.fail below)
    # fails, it is not passed off as the miss
    return [pytest.param(s, marks=pytest.mark.xfail(strict=True, raises=AssertionError,
                                                    reason=KNOWN_MISSES[s]))
            if s in KNOWN_MISSES else s for s in seeds]


@pytest.mark.parametrize("seed", _params(CELLS))
def test_the_missing_effect_is_named_and_the_held_out_error_falls(seed, tmp_path):
    kind = CELLS[seed]
    r = diagnose_generated(seed, (kind,), tmp_path)
    wrong = [name for name in r.effects if name != kind]
    if wrong:
        pytest.fail(f"named {wrong} on a cell missing {kind}: {r.verdict}")
    assert r.effects == (kind,), r.verdict
    assert r.mae_after_v <= 0.6 * r.mae_before_v, r.verdict     # the spec's 40 % drop


@pytest.mark.parametrize("seed", _params(CONTROLS))
def test_a_cell_missing_nothing_gets_nothing(seed, tmp_path):
    r = diagnose_generated(seed, (), tmp_path)
    if r.effects:
        pytest.fail(f"named {list(r.effects)} on a cell missing nothing: {r.verdict}")
    assert not r.unexplained, r.verdict
    # what a user reads: the base as it is, and a report that says nothing is missing
    assert r.mae_after_v == r.mae_before_v and r.model.effects == ()
    d = r.to_json_dict()
    assert d["effects"] == [] and d["mae_before_v"] == d["mae_after_v"]
    assert "Nothing is missing" in (tmp_path / "out" / "report.md").read_text()
