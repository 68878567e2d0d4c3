"""Acceptance: `diagnose` on ../shared/diagnose-suite/ (synthetic cells from an independent
generator, one hidden effect each, truth kept apart and read only to score).

Per cell: the base model's tables are smooth and positive (roughness <= 0.35, no value
<= 0), a control cell gets nothing named, and the cells named right today stay right. A
hysteresis named explains what it names: the held-out error it leaves is within 3x the
voltage noise (the spec's figure for a named effect).
``python bench/diagnose_suite.py`` prints the whole table (named first, held-out drop)."""

from __future__ import annotations

import importlib.util
import json

import pytest

from conftest import REPO

SUITE = REPO.parent / "shared" / "diagnose-suite"
CELLS = sorted(p.parent.name for p in SUITE.glob("*/truth.json"))
# named wrong today (strict known misses): c12 (an extra RC of 391 s that the base's slow
# pair takes up: held-out error 1.7 mV against 1.15 mV of noise; nothing named)
KNOWN_MISSES = {"c12"}


def _bench():
    spec = importlib.util.spec_from_file_location("diagnose_suite",
                                                  REPO / "bench" / "diagnose_suite.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
@pytest.mark.parametrize("cell", [
    pytest.param(c, marks=pytest.mark.xfail(strict=True, reason="named wrong today"))
    if c in KNOWN_MISSES else c for c in CELLS] or ["(none)"])
def test_diagnose_suite_cell(cell):
    if not CELLS:
        pytest.skip(f"diagnose suite not found at {SUITE}")
    row = _bench().run_case(str(SUITE / cell))
    truth = json.loads((SUITE / cell / "truth.json").read_text())["effect"]
    assert row["roughness"] <= 0.35, row
    assert row["non_positive"] == 0, row
    if truth == "none":
        assert row["named"] == [] and not row["unexplained"], row
    else:
        assert row["named"][:1] == [truth], row
        assert row["drop"] >= 0.4, row
        if truth == "hysteresis":
            assert row["mae_after_mv"] <= 3.0 * row["noise_mv"], row
