"""The plots' shared style (ecmgen.plots.style) and what the validation plot leaves out: a
long rest before the drive, a line across a logging gap; every title says where."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ecmgen.plots.style import _plt, break_gaps, degrees, temperature_colours

from conftest import synthetic_nca_model


def test_no_line_is_drawn_across_a_logging_gap():
    t = np.array([0.0, 1.0, 2.0, 2002.0, 2003.0])
    t2, y2 = break_gaps(t, np.arange(5.0))
    assert t2.size == 6 and np.isnan(y2[3]) and t2[3] == 1002.0
    slow_rest = np.array([0.0, 0.1, 0.2, 60.2, 120.2, 120.3])    # a rest logged every 60 s
    assert break_gaps(slow_rest, np.arange(6.0))[0].size == 6


def test_every_temperature_has_a_visible_colour():
    colours = temperature_colours(_plt(), [-20.0, -10.0, 0.6, 25.7, 45.0])
    for c in colours:
        assert min(c[:3]) < 0.75, c            # nothing near white
    assert temperature_colours(_plt(), [float("nan")]) == ["tab:blue"]
    assert degrees(-9.94) == "-9.9 °C" and degrees(float("nan")) == ""


def test_a_long_rest_before_the_drive_is_not_drawn(tmp_path):
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import validate
    from ecmgen.plots.figures import _drive_window, validation_png

    m = synthetic_nca_model()
    t = np.concatenate([np.arange(0.0, 3000.0, 10.0), 3000.0 + np.arange(0.0, 1000.0, 1.0)])
    i = np.where(t >= 3000.0, -2.9 * (1 + np.sin(t / 17.0)) / 2, 0.0)
    temp = np.where(t < 3000.0, 20.0 - t / 300.0, 10.0 + (t - 3000.0) / 200.0)
    from ecmgen.model.simulate import simulate

    v = simulate(m, t, i, 0.9).voltage_v
    val = validate(m, TimeSeries(t, i, v, temp, None, "cycle.csv"), 0.9)
    keep, skipped = _drive_window(val)
    assert 2900.0 <= skipped <= 2950.0 and val.sim.time_s[keep][0] >= 2900.0
    lo, hi = val.temperature_range_c             # over the drive only
    assert lo >= 10.0 and hi <= 15.0
    png = validation_png({"lm": val, "curve": val}, "cycle.csv", best="curve")
    assert png.startswith(b"\x89PNG")


def test_derived_rows_are_the_ones_the_notes_derive():
    """Dashed in the parameters plot: the warm row of a model over temperature, and the
    cold row too only for a model derived from one pulse test; a grid row just beyond
    the coldest test is resampled, not derived."""
    from dataclasses import replace

    from ecmgen.model.model import load_model
    from ecmgen.plots.figures import derived_rows

    model = load_model(Path(__file__).parent / "data" / "panasonic-temperature-model.json")
    measured = [-19.4, -9.9, 0.6, 25.7]          # the -20 degC grid row is 0.6 K below
    assert derived_rows(model, measured) == ()
    warm = replace(model, notes=("derived warm row at 45 degC (not measured): ...",))
    assert derived_rows(warm, measured) == (45.0,)
    one = replace(model, notes=("tables over temperature derived from one pulse test at "
                                "5.0 degC ...",))
    assert derived_rows(one, [5.0]) == (-20.0, 45.0)
    assert derived_rows(one, None) == ()
