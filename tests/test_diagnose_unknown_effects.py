"""`diagnose` on cells whose missing effect is not one of the model's five: a wrong name is
worse than "unexplained" (the spec: a wrong name on at most 2 % of cells).

The cells come from bench/diagnose_cells.py (numpy physics, no ecmgen import), in its quick
form (half the pulse levels and cycle), one per kind at consecutive seeds fixed before they
were first diagnosed. Faults of the record and an entropic OCV have candidates of their own
(ecmgen.diagnosis.corrections) and are named as such (a voltage channel that lags the current
among them); solid diffusion is never named alone: where a third RC pair of the pulse test
passes, the test's shape tells an extra RC from it or the verdict is "extra_rc or
diffusion" (ecmgen.diagnosis.diffusion). Misses are strict known failures."""

from __future__ import annotations

import pytest

from conftest import diagnose_cells, diagnose_generated

KINDS = {9300000: "current_offset", 9300001: "current_gain", 9300002: "ocv_error",
         9300003: "voltage_lag", 9300004: "entropic_ocv", 9300005: "diffusion"}
WITH_CANDIDATE = {"current_offset", "current_gain", "ocv_error", "entropic_ocv", "voltage_lag"}
# a lag this quick cell shows less than its noise: the base leaves 0.85 mV held out against
# 1.05 mV ("nothing is missing that this data can show")
KNOWN_MISSES = {9300003: "voltage_lag below the noise: nothing named"}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=KNOWN_MISSES[s]))
    if s in KNOWN_MISSES else s for s in KINDS])
def test_an_effect_is_named_only_where_diagnose_has_its_candidate(seed, tmp_path):
    kind = KINDS[seed]
    result = diagnose_generated(seed, (kind,), tmp_path)
    wrong = [n for n in result.effects if n != kind] + \
        [g for g in result.cannot_tell if kind not in g]
    assert not wrong, result.verdict
    assert result.effects == ((kind,) if kind in WITH_CANDIDATE else ()), result.verdict


@pytest.mark.slow
def test_a_candidate_that_leaves_the_error_unexplained_is_not_named(tmp_path):
    """The naming rule itself, on a cell where it acts (found while building it, so a test
    of the mechanism, not a score): an OCV error, its own candidate left out by
    ``[diagnose] effects``, whose SOC scale a capacity error takes up part of (12.6 -> 3.9
    mV held out, against 0.73 mV noise and 0.75 mV on the pulse test). The capacity error
    passes the held-out test, is not named, and the verdict says why."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import run_diagnose

    dc = diagnose_cells()
    case, extra = dc.make_case(9200005, ("ocv_error",), quick=True)
    dc.write_case(case, extra, tmp_path / "cell")
    toml = tmp_path / "cell" / "case.toml"
    toml.write_text(toml.read_text() + '\n[diagnose]\neffects = ["hysteresis", "extra_rc", '
                    '"current_dependent_resistance", "capacity_error", '
                    '"temperature_dependence"]\n')
    result, _, _ = run_diagnose(load_config(toml), tmp_path / "out", plots=False)
    assert result.effects == ()
    assert [s.name for s in result.not_named] == ["capacity_error"]
    assert result.unexplained and "not named" in result.verdict
    # model.json is the base: what was tried is not in it
    assert result.model is result.base_model or result.model.effects == ()
