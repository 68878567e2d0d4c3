"""Table checks (ecmgen.fit.quality): roughness over SOC, non-positive values, and what a
build says about them (report.md, --json, --strict)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ecmgen.fit.quality import ROUGHNESS_LIMIT, model_quality, quality_words, roughness


def test_roughness_is_zero_on_a_log_linear_table_and_large_on_a_zig_zag():
    soc = np.linspace(0.0, 1.0, 21)
    assert roughness(soc, 0.02 * np.exp(-2.0 * soc))[0] == pytest.approx(0.0, abs=1e-12)
    zig = 0.002 * np.where(np.arange(21) % 2 == 0, 1.06, 3.31)     # the Leaf's nodes as first fitted
    value, at = roughness(soc, zig)
    assert value == pytest.approx(np.log(3.31 / 1.06))
    # uneven nodes: the neighbours are interpolated at the node, not averaged
    uneven = np.array([0.0, 0.1, 0.4])
    assert roughness(uneven, np.exp(uneven))[0] == pytest.approx(0.0, abs=1e-12)


def test_model_quality_counts_non_positive_values_and_fails(synthetic_model):
    good = model_quality(synthetic_model)
    assert good.passes and good.non_positive == 0 and good.roughness < 0.1
    r0 = synthetic_model.discharge.r0_ohm.copy()
    r0[0, 3] = 0.0
    bad = replace(synthetic_model, discharge=replace(synthetic_model.discharge, r0_ohm=r0))
    q = model_quality(bad)
    assert not q.passes and q.non_positive == 1
    words = quality_words("curve", q)
    assert "1 table value(s) <= 0" in words and words.startswith("model 'curve' fails")
    assert q.as_dict()["roughness_limit"] == ROUGHNESS_LIMIT


def test_roughness_counts_the_fitted_span_only():
    """A table rising towards empty (ln r quadratic in SOC) and held at its end value
    below the lowest level: the bend where the hold starts is the hold's, not the fit's."""
    soc = np.linspace(0.0, 1.0, 21)
    rising = 0.01 * np.exp(40.0 * np.maximum(0.5 - soc, 0.0) ** 2)
    rising[:3] = rising[3]                                 # held below SOC 0.15
    whole, at = roughness(soc, rising)
    assert at == pytest.approx(0.15) and whole == pytest.approx(0.65)
    inside, _ = roughness(soc, rising, soc >= 0.15 - 1e-9)
    assert inside == pytest.approx(0.1)                    # 40 x 0.05^2, the fit's own bend
