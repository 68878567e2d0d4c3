"""data.ocv_rests_first: an OCV file that the pulse test's relaxed rests contradict at the
test's own temperature gives way to the rests (ecmgen.data.ocv.rests_should_lead), on a
synthetic cell of known OCV. The bound: the OCV check's own threshold."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_ocv_branches import LOW_SOC, _cell, _test_record

from ecmgen.data import ocv as ocv_mod
from ecmgen.data.soc import find_rests

OFFSET_V = 0.03       # the file's error: three times the check's 10 mV threshold


def _assemble(file_c, rests_first=True, test_c=25.0):
    """The cell's pulse test at ``test_c`` and a file of its OCV + OFFSET_V measured at
    ``file_c`` (None: a table without a temperature), given alone as data.ocv."""
    model = _cell()
    series, _ = _test_record(model)
    series = replace(series, temperature_c=np.full(len(series), test_c))
    grid = ocv_mod.GRID
    curve = ocv_mod.OcvCurve("file.csv", grid, model.ocv.ocv_at(grid) + OFFSET_V,
                             temperature_c=file_c)
    q = model.capacity_ah
    rests = find_rests(series, 0.02 * q, ocv_mod.MIN_OCV_REST_S)
    table, notes, report = ocv_mod.assemble(
        ("file.csv",), {"file.csv": curve}, {"file.csv": "file.csv"}, rests, LOW_SOC, q,
        series=series, rests_first=rests_first)
    err = table.ocv_at(np.array([0.3, 0.5, 0.7])) - model.ocv.ocv_at(np.array([0.3, 0.5, 0.7]))
    return notes, report, err


def test_rests_lead_a_file_they_contradict_at_the_same_temperature():
    notes, report, err = _assemble(file_c=25.4)
    assert report.sources[0] == "pulses" and "file.csv" in report.sources
    assert any("the pulse test's rests first" in n for n in notes)
    assert report.check.rms_v <= report.check.threshold_v      # the rests and the file
    assert np.max(np.abs(err)) < report.check.threshold_v      # the OCV, not the file's


@pytest.mark.parametrize("kw", [dict(file_c=0.0), dict(file_c=None),
                                dict(file_c=25.0, rests_first=False)],
                         ids=["another temperature", "no temperature", "never"])
def test_the_file_is_kept_as_given_otherwise(kw):
    notes, report, err = _assemble(**kw)
    assert report.sources == ("file.csv",)
    assert not any("the pulse test's rests first" in n for n in notes)
    assert report.check.warning                                # and the check says so
    # the file as given, up to 0.1 mV: linear between the 0.01-SOC grid points of a curved OCV
    assert np.allclose(err, OFFSET_V, atol=1e-4)
