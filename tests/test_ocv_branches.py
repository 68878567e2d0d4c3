"""The OCV where a pulse test's rests do not reach, from its own charge and discharge
branches (ecmgen.data.ocv.curve_from_branches), on a synthetic cell of known OCV."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from conftest import synthetic_nca_model

from ecmgen.data import ocv as ocv_mod
from ecmgen.data.measure import TimeSeries
from ecmgen.data.ocv import SETTLE_S
from ecmgen.data.soc import find_rests
from ecmgen.model.simulate import simulate

LOW_SOC = 0.03        # the opening charge starts here, the closing discharge ends here
REST_LEVELS = (0.8, 0.6, 0.4, 0.2)


def _cell():
    """Symmetric resistances (the same table both ways): the branch mean is then the OCV
    up to the RC pairs' part that has not settled."""
    model = synthetic_nca_model()
    return replace(model, charge=model.discharge)


def _test_record(model, rate_c=1 / 3):
    """Opens with a C/3 charge from LOW_SOC to full, rests; steps down at 1C with a
    20-minute rest at each level (the rests end at SOC 0.2); closes with a C/3
    discharge to LOW_SOC. 1 s samples, Ah column."""
    q = model.capacity_ah
    parts = [(3600.0 * (1.0 - LOW_SOC) / rate_c, rate_c * q), (1200.0, 0.0)]
    soc = 1.0
    for level in REST_LEVELS:
        parts += [(3600.0 * (soc - level), -q), (1200.0, 0.0)]
        soc = level
    parts.append((3600.0 * (soc - LOW_SOC) / rate_c, -rate_c * q))
    i = np.concatenate([np.full(int(round(d)), a) for d, a in parts])
    t = np.arange(1.0, i.size + 1.0)
    sim = simulate(model, t, i, LOW_SOC)
    return TimeSeries(t, i, sim.voltage_v, None, (sim.soc - LOW_SOC) * q, "synthetic"), sim


def _assemble(series, model):
    q = model.capacity_ah
    rests = find_rests(series, 0.02 * q, ocv_mod.MIN_OCV_REST_S)
    return ocv_mod.assemble(("pulses",), {}, {"pulses": "synthetic"}, rests, LOW_SOC, q,
                            series=series)


def test_branches_give_the_ocv_below_the_rests():
    model = _cell()
    series, _ = _test_record(model)
    table, notes, _ = _assemble(series, model)
    assert any("from the pulse test's own" in n for n in notes), notes
    # the bound: half the part of each RC pair not yet settled SETTLE_S after the current
    # started, at the branch current (the current-weighted mean of two branches whose
    # linear overpotentials cancel; the model's tables are the same both ways)
    p = model.discharge.at(0.1)
    i = model.capacity_ah / 3
    bound = 0.5 * i * sum(float(p[f"r_{k}_ohm"]) * np.exp(-SETTLE_S / float(p[f"tau_{k}_s"]))
                          for k in ("fast", "slow"))
    soc = np.arange(0.06, 0.19, 0.01)
    err = table.ocv_at(soc) - model.ocv.ocv_at(soc)
    assert np.max(np.abs(err)) <= bound, (err, bound)
    # held flat at the lowest rest instead, the OCV there would be this far off
    flat = model.ocv.ocv_at(0.2) - model.ocv.ocv_at(soc)
    assert np.max(np.abs(err)) < 0.1 * np.max(flat)


def test_no_branches_beyond_the_rests_leaves_the_ocv_as_it_was():
    model = _cell()
    series, _ = _test_record(model)
    # the same record without its opening charge: the rests alone, held flat below 0.2
    start = int(np.flatnonzero(series.current_a < 0)[0])
    cut = series.slice(start, len(series))
    cut = replace(cut, charge_ah=cut.charge_ah - cut.charge_ah[0])
    q = model.capacity_ah
    rests = find_rests(cut, 0.02 * q, ocv_mod.MIN_OCV_REST_S)
    with_series = ocv_mod.assemble(("pulses",), {}, {"pulses": "s"}, rests, 1.0, q,
                                   series=cut)
    without = ocv_mod.assemble(("pulses",), {}, {"pulses": "s"}, rests, 1.0, q)
    assert np.array_equal(with_series[0].ocv_v, without[0].ocv_v)
    assert any("held flat beyond it" in n for n in with_series[1])
