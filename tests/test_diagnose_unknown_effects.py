"""`diagnose` on cells whose missing effect it has no candidate for: a wrong name is worse
than "unexplained" (the spec: a wrong name on at most 2 % of cells).

The cells come from bench/diagnose_cells.py (numpy physics, no ecmgen import), in its quick
form (half the pulse levels and cycle), one per kind at consecutive seeds fixed before they
were first diagnosed. Those a look-alike candidate describes within the naming rule's
yardstick are strict known misses."""

from __future__ import annotations

import pytest

from conftest import diagnose_generated

KINDS = {9300000: "current_offset", 9300001: "current_gain", 9300002: "ocv_error",
         9300003: "voltage_lag", 9300004: "entropic_ocv", 9300005: "diffusion"}
# named wrong today: a capacity error describes a current gain and an OCV error (SOC moves
# the wrong size), a hysteresis an entropic OCV, each within 3x the noise and the misfit
KNOWN_WRONG = {9300001: "capacity_error", 9300002: "capacity_error", 9300004: "hysteresis"}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=f"named {KNOWN_WRONG[s]}"))
    if s in KNOWN_WRONG else s for s in KINDS])
def test_an_effect_without_a_candidate_is_not_named(seed, tmp_path):
    result = diagnose_generated(seed, (KINDS[seed],), tmp_path)
    assert result.effects == (), result.verdict


@pytest.mark.slow
def test_a_candidate_that_leaves_the_error_unexplained_is_not_named(tmp_path):
    """The naming rule itself, on a cell where it acts (found while building it, so a test
    of the mechanism, not a score): an OCV error whose SOC scale a capacity error takes up
    part of (12.6 -> 3.9 mV held out, against 0.73 mV noise and 0.75 mV on the pulse test).
    The capacity error passes the held-out test, is not named, and the verdict says why."""
    result = diagnose_generated(9200005, ("ocv_error",), tmp_path)
    assert result.effects == ()
    assert [s.name for s in result.not_named] == ["capacity_error"]
    assert result.unexplained and "not named" in result.verdict
    # model.json is the base: what was tried is not in it
    assert result.model is result.base_model or result.model.effects == ()
