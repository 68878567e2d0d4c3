"""OCV from a table, a low-rate test (real Panasonic C/20, real CALCE charge branch) and
pulse-test rests."""

import numpy as np
import pytest

from conftest import CALCE, PANASONIC, need
from ecmgen.errors import InputError
from ecmgen.data.measure import TimeSeries, read_timeseries
from ecmgen.data.ocv import ocv_from_low_rate, read_ocv_table


def test_table_in_percent_and_fraction(tmp_path):
    p = tmp_path / "ocv.csv"
    p.write_text("soc,ocv_v\n0,3.0\n50,3.6\n100,4.2\n")
    t = read_ocv_table(p)
    assert t.soc.tolist() == [0.0, 0.5, 1.0]
    assert float(t.ocv_at(0.25)) == pytest.approx(3.3)
    assert float(t.soc_at(3.9)) == pytest.approx(0.75)


@pytest.mark.parametrize("body,needle", [
    ("soc,ocv_v\n0,3.0\n0.5,3.9\n1,3.8\n", "not monotonic"),
    ("soc,ocv_v\n0,3.0\n0.5,3.9\n0.5,4.0\n", "not strictly increasing"),
    ("soc,volts\n0,3.0\n1,4.0\n", "missing column 'ocv_v'"),
    ("soc,ocv_v\n0,3000\n1,4200\n", "mV given as V"),
    ("soc,ocv_v\n0,3.0\n1,abc\n", "not a number"),
])
def test_bad_tables(tmp_path, body, needle):
    p = tmp_path / "ocv.csv"
    p.write_text(body)
    with pytest.raises(InputError) as exc:
        read_ocv_table(p)
    assert str(exc.value).startswith(str(p)) and needle in str(exc.value)
    assert "\n" not in str(exc.value)


def test_synthetic_low_rate_branches_average_to_the_true_ocv():
    ocv = lambda s: 3.0 + 1.1 * s + 0.1 * np.sin(6 * s)  # noqa: E731
    q, i_ = 2.0, 0.1
    hours = q / i_
    t = np.linspace(0, hours * 3600, 400)
    soc_d = 1 - t / 3600 * i_ / q
    soc_c = t / 3600 * i_ / q
    # branches sit +-20 mV (I*R + hysteresis) around the OCV
    series = TimeSeries(np.concatenate([t, t + t[-1] + 60]),
                        np.concatenate([np.full(400, -i_), np.full(400, i_)]),
                        np.concatenate([ocv(soc_d) - 0.02, ocv(soc_c) + 0.02]), source="lr")
    table, notes = ocv_from_low_rate(series, q)
    assert "average" in notes[0]
    assert np.max(np.abs(table.ocv_v - ocv(table.soc))) < 2e-3


def test_panasonic_c20_has_both_branches():
    s = read_timeseries(need(PANASONIC / "ocv-c20.mat"), capacity_ah=2.9)
    table, notes = ocv_from_low_rate(s, 2.9)
    assert "average" in notes[0]
    assert 3.0 < table.ocv_v[0] < 3.4 and 4.1 < table.ocv_v[-1] < 4.25
    assert np.all(np.diff(table.ocv_v) > 0)


def test_calce_single_charge_branch_is_used_with_a_warning():
    s = read_timeseries(need(CALCE / "ocv-charge-c22.csv"), capacity_ah=1.1)
    table, notes = ocv_from_low_rate(s, 1.1)
    assert "only the charge branch" in notes[0]
    # LFP: a flat plateau near 3.3 V, made strictly increasing
    assert 3.25 < float(table.ocv_at(0.5)) < 3.40
    assert np.all(np.diff(table.ocv_v) > 0)


def test_fast_test_is_not_an_ocv_test():
    t = np.arange(0, 3600.0, 10)
    s = TimeSeries(t, np.full(t.size, -2.9), 4.0 - 1e-4 * t, source="fast.csv")
    with pytest.raises(InputError, match="fast.csv.*not a low-rate OCV test"):
        ocv_from_low_rate(s, 2.9)
