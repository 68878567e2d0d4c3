"""Tables over (temperature, SOC): interpolation, model.json schema 2 (and 1), simulation
on the cell temperature."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ecmgen.data.measure import TimeSeries, write_timeseries_csv
from ecmgen.errors import InputError
from ecmgen.model.model import (EcmModel, OcvOverTemperature, OcvTable, RcTable, interp_2d,
                                load_model, model_from_json_dict, stack_rc_tables)
from ecmgen.model.simulate import simulate, validate

REPO = Path(__file__).resolve().parents[1]
SOC = np.linspace(0.0, 1.0, 6)


def _row(scale: float, temperature_c=None) -> RcTable:
    n = SOC.size
    return RcTable(soc=SOC, r0_ohm=scale * np.linspace(0.03, 0.02, n),
                   r_fast_ohm=scale * np.full(n, 0.01), tau_fast_s=np.full(n, 2.0 * scale),
                   r_slow_ohm=scale * np.full(n, 0.02), tau_slow_s=np.full(n, 60.0),
                   fit_error=np.zeros(n), converged=np.ones(n, bool),
                   temperature_c=temperature_c)


def _model(two_temperatures: bool = True) -> EcmModel:
    ocv25 = 3.0 + 1.2 * SOC
    if not two_temperatures:
        return EcmModel(capacity_ah=2.9, ocv=OcvTable(SOC, ocv25), charge=_row(1.0),
                        discharge=_row(1.0), method="synthetic", direction_deadband_a=0.029)
    rows = [_row(3.0), _row(1.0)]
    table = stack_rc_tables(rows, [-10.0, 25.0])
    ocv = OcvOverTemperature(np.array([-10.0, 25.0]), SOC, np.vstack([ocv25 - 0.01, ocv25]))
    return EcmModel(capacity_ah=2.9, ocv=ocv, charge=table, discharge=table,
                    method="synthetic", direction_deadband_a=0.029)


def test_interp_2d_is_bilinear_and_clamped():
    tg, sg = np.array([0.0, 20.0]), np.array([0.0, 1.0])
    values = np.array([[1.0, 3.0], [5.0, 7.0]])
    assert interp_2d(tg, sg, values, 0.5, 10.0) == pytest.approx(4.0)
    assert interp_2d(tg, sg, values, 0.25, 0.0) == pytest.approx(1.5)
    # clamped in both axes
    assert interp_2d(tg, sg, values, 2.0, 99.0) == pytest.approx(7.0)
    assert interp_2d(tg, sg, values, -1.0, -40.0) == pytest.approx(1.0)
    # per-sample temperatures
    out = interp_2d(tg, sg, values, np.array([0.0, 1.0]), np.array([20.0, 0.0]))
    np.testing.assert_allclose(out, [5.0, 3.0])
    # one row: the temperature does not matter
    assert interp_2d(tg[:1], sg, values[:1], 0.5, 123.0) == pytest.approx(2.0)


def test_one_temperature_table_from_1d_columns():
    t = _row(1.0)
    assert t.n_temperatures == 1 and t.r0_ohm.shape == (1, SOC.size)
    assert np.isnan(t.temperature_c[0])
    p = t.at(0.5, 40.0)
    assert p["r0_ohm"] == pytest.approx(0.025)


def test_stack_resamples_onto_a_common_grid():
    a = _row(1.0)
    b = RcTable(soc=np.array([0.0, 0.5, 1.0]), r0_ohm=[0.1, 0.2, 0.3], r_fast_ohm=[0.0] * 3,
                tau_fast_s=[1.0] * 3, r_slow_ohm=[0.0] * 3, tau_slow_s=[10.0] * 3,
                fit_error=[0.0] * 3, converged=[True, False, True])
    s = stack_rc_tables([a, b], [0.0, 25.0])
    assert s.n_temperatures == 2 and s.soc.size == 7          # union of the breakpoints
    np.testing.assert_allclose(s.at(0.75, 25.0)["r0_ohm"], 0.25)
    np.testing.assert_allclose(s.r0_ohm[0], np.interp(s.soc, SOC, a.r0_ohm[0]))
    assert not s.converged[1, 3] and s.converged[1, 0]


def test_bad_temperature_axis_refused():
    with pytest.raises(ValueError, match="strictly increasing"):
        stack_rc_tables([_row(1.0), _row(2.0)], [25.0, 25.0])
    with pytest.raises(ValueError, match="2 temperatures for 1"):
        _row(1.0, temperature_c=[0.0, 10.0])


def test_schema2_round_trip_is_byte_identical(tmp_path):
    m = _model()
    path = m.save(tmp_path / "model.json")
    raw = json.loads(path.read_text())
    assert raw["schema_version"] == 2
    assert raw["rc"]["charge"]["temperature_c"] == [-10.0, 25.0]
    assert len(raw["rc"]["charge"]["r0_ohm"]) == 2
    back = load_model(path)
    assert back.to_json() == m.to_json()
    assert back.needs_temperature and list(back.temperatures_c) == [-10.0, 25.0]


def test_one_temperature_model_has_null_temperature(tmp_path):
    m = _model(two_temperatures=False)
    raw = m.to_json_dict()
    assert raw["ocv"]["temperature_c"] == [None]
    assert raw["rc"]["discharge"]["temperature_c"] == [None]
    back = model_from_json_dict(json.loads(m.to_json()))
    assert back.to_json() == m.to_json() and not back.needs_temperature


def test_schema1_file_still_loads(tmp_path):
    """A model.json written before the temperature axis (SOC-only lists) loads as one row."""
    m = _model(two_temperatures=False)
    raw = m.to_json_dict()
    raw["schema_version"] = 1
    del raw["ocv"]["temperature_c"]
    raw["ocv"]["ocv_v"] = raw["ocv"]["ocv_v"][0]
    for d in ("charge", "discharge"):
        t = raw["rc"][d]
        del t["temperature_c"]
        for k, v in list(t.items()):
            if k != "soc":
                t[k] = v[0]
    path = tmp_path / "old.json"
    path.write_text(json.dumps(raw))
    back = load_model(path)
    assert back.to_json() == m.to_json()


def test_schema2_bad_tables_refused(tmp_path):
    raw = _model().to_json_dict()
    raw["rc"]["charge"]["temperature_c"] = [25.0, -10.0]
    with pytest.raises(InputError, match="strictly increasing"):
        model_from_json_dict(raw, "m.json")
    raw = _model().to_json_dict()
    raw["rc"]["charge"]["tau_slow_s"] = raw["rc"]["charge"]["tau_slow_s"][:1]
    with pytest.raises(InputError, match="different numbers of rows"):
        model_from_json_dict(raw, "m.json")
    raw = _model().to_json_dict()
    raw["ocv"]["temperature_c"] = [25.0]
    with pytest.raises(InputError, match="one temperature per row"):
        model_from_json_dict(raw, "m.json")


def test_simulation_follows_the_cell_temperature():
    m = _model()
    t = np.arange(0.0, 600.0, 1.0)
    i = np.where((t > 60) & (t < 300), -5.0, 0.0)
    cold_row = replace(m, charge=m.charge.row(0), discharge=m.discharge.row(0),
                       ocv=OcvOverTemperature(m.ocv.temperature_c[:1], m.ocv.soc,
                                              m.ocv.ocv_v[:1]))
    # at (or beyond) a breakpoint the model is that row's model
    v_cold = simulate(m, t, i, 0.9, np.full(t.size, -10.0)).voltage_v
    v_colder = simulate(m, t, i, 0.9, -30.0).voltage_v          # clamped
    v_row = simulate(cold_row, t, i, 0.9).voltage_v
    np.testing.assert_allclose(v_cold, v_row, atol=1e-12)
    np.testing.assert_allclose(v_colder, v_row, atol=1e-12)
    # in between, the parameters (and OCV) are interpolated: the drop lies between
    v_warm = simulate(m, t, i, 0.9, 25.0).voltage_v
    v_mid = simulate(m, t, i, 0.9, 7.5).voltage_v
    k = 200
    assert v_cold[k] < v_mid[k] < v_warm[k]
    sim = simulate(m, t, i, 0.9, 7.5)
    assert sim.ocv_v[0] == pytest.approx(3.0 + 1.2 * 0.9 - 0.005)


def test_a_model_over_temperature_needs_the_temperature(tmp_path):
    m = _model()
    t = np.arange(0.0, 100.0, 1.0)
    series = TimeSeries(t, np.full(t.size, -1.0), np.full(t.size, 3.9), source="cycle.csv")
    with pytest.raises(InputError, match="cycle.csv.*temperature_c column.*--temperature-c"):
        validate(m, series, 0.9)
    val = validate(m, series, 0.9, temperature_c=10.0)
    assert val.temperature_range_c == (10.0, 10.0)
    # the record's own column wins over the option
    with_col = replace(series, temperature_c=np.full(t.size, 20.0))
    assert validate(m, with_col, 0.9, temperature_c=10.0).temperature_range_c == (20.0, 20.0)
    with pytest.raises(InputError, match="not finite"):
        simulate(m, t, series.current_a, 0.9, np.full(t.size, np.nan))


def test_cli_validate_temperature_option(tmp_path):
    m = _model()
    mpath = m.save(tmp_path / "model.json")
    t = np.arange(0.0, 300.0, 1.0)
    i = np.where(t > 30, -3.0, 0.0)
    v = simulate(m, t, i, 0.8, 0.0).voltage_v
    write_timeseries_csv(TimeSeries(t, i, v), tmp_path / "cycle.csv")

    def run(*extra):
        return subprocess.run([sys.executable, "-m", "ecmgen.cli", "validate", str(mpath),
                               str(tmp_path / "cycle.csv"), "--soc0", "0.8", *extra],
                              capture_output=True, text=True, cwd=REPO)

    bad = run("--json")
    assert bad.returncode == 2 and bad.stdout == ""
    assert bad.stderr.count("\n") == 1 and "cycle.csv" in bad.stderr
    assert "temperature" in bad.stderr
    ok = run("--json", "--temperature-c", "0")
    assert ok.returncode == 0, ok.stderr
    out = json.loads(ok.stdout)
    assert out["mae_v"] < 1e-9 and out["temperature_c"] == {"min": 0.0, "max": 0.0}


def _branch_model() -> EcmModel:
    """Two temperatures with a diffusion pair and a Butler-Volmer fast branch."""
    rows = [replace(_row(3.0), r_diff_ohm=[0.08], tau_diff_s=[600.0], i0_a=[1.0]),
            replace(_row(1.0), r_diff_ohm=[0.02], tau_diff_s=[400.0], i0_a=[15.0])]
    table = stack_rc_tables(rows, [-10.0, 25.0])
    return replace(_model(), charge=table, discharge=table)


def test_diffusion_and_butler_volmer_branches_match_a_plain_loop():
    import math

    m = _branch_model()
    t = np.concatenate([np.arange(0.0, 300.0, 0.5), np.arange(300.0, 2000.0, 7.0)])
    rng = np.random.default_rng(3)
    i = rng.uniform(-12.0, 4.0, t.size)
    temp = np.linspace(-15.0, 30.0, t.size)
    sim = simulate(m, t, i, 0.95, temp)
    soc, u = 0.95, [0.0, 0.0, 0.0]
    prev = t[0]
    for k in range(t.size):
        dt = t[k] - prev
        prev = t[k]
        soc += i[k] * dt / (3600 * 2.9)
        tk = min(max(temp[k], -10.0), 25.0)
        w = (tk + 10.0) / 35.0
        p = {key: float(interp_2d(m.charge.temperature_c, SOC, getattr(m.charge, key), soc, tk))
             for key in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")}
        r_d = 0.08 + (0.02 - 0.08) * w
        tau_d = 600.0 + (400.0 - 600.0) * w
        i0 = 1.0 + (15.0 - 1.0) * w
        x = max(abs(i[k]) / i0, 1e-12)
        g = math.asinh(x) / x
        for j, (r, tau) in enumerate(((p["r_fast_ohm"] * g, p["tau_fast_s"]),
                                      (p["r_slow_ohm"], p["tau_slow_s"]), (r_d, tau_d))):
            a = math.exp(-dt / tau)
            u[j] = a * u[j] + r * (1 - a) * i[k]
        ocv = float(m.ocv.ocv_at(soc, tk))
        v = ocv + p["r0_ohm"] * i[k] + sum(u)
        assert sim.voltage_v[k] == pytest.approx(v, abs=1e-12)
    assert sim.u_diff_v is not None and np.abs(sim.u_diff_v).max() > 0.01


def test_branches_round_trip_and_rows(tmp_path):
    m = _branch_model()
    raw = m.to_json_dict()
    assert raw["rc"]["charge"]["r_diff_ohm"] == [0.08, 0.02]
    assert raw["rc"]["charge"]["i0_a"] == [1.0, 15.0]
    back = load_model(m.save(tmp_path / "m.json"))
    assert back.to_json() == m.to_json() and back.charge.has_butler_volmer
    one = back.charge.row(1)
    assert one.n_temperatures == 1 and list(one.i0_a) == [15.0]
    # a plain model does not write the keys at all
    assert "r_diff_ohm" not in _model().to_json_dict()["rc"]["charge"]


def test_branches_bad_values_refused():
    with pytest.raises(ValueError, match="both r_diff_ohm and tau_diff_s"):
        replace(_row(1.0), r_diff_ohm=[0.01])
    with pytest.raises(ValueError, match="i0_a must be finite and positive"):
        replace(_row(1.0), i0_a=[0.0])
    with pytest.raises(ValueError, match="one direction"):
        replace(_model(two_temperatures=False),
                charge=replace(_row(1.0), i0_a=[5.0]))
    raw = _branch_model().to_json_dict()
    raw["rc"]["discharge"]["tau_diff_s"] = [1.0]
    with pytest.raises(InputError, match="one value per temperature row"):
        model_from_json_dict(raw, "m.json")
    raw = _branch_model().to_json_dict()
    del raw["rc"]["discharge"]["tau_diff_s"]
    with pytest.raises(InputError, match="go together"):
        model_from_json_dict(raw, "m.json")


def test_neighbour_time_constants_interpolate_ln_tau_in_inverse_kelvin():
    from types import SimpleNamespace

    from ecmgen.model.temperature import neighbour_time_constants

    def fit(fast, slow, diff=None):
        return SimpleNamespace(tau_fast_s=fast, tau_slow_s=slow, tau_diff_s=diff)

    temps = [25.0, -20.0, 0.0]          # not sorted: the order of the config
    fits = [fit(1.0, 30.0, 300.0), fit(0.5, 20.0, 700.0), fit(9.0, 99.0, 999.0)]
    got = neighbour_time_constants(temps, fits)
    assert got[0] is None and got[1] is None
    w = (1 / 273.15 - 1 / 298.15) / (1 / 253.15 - 1 / 298.15)
    for k, a, b in (("fast", 1.0, 0.5), ("slow", 30.0, 20.0), ("diff", 300.0, 700.0)):
        assert got[2][k] == pytest.approx(a ** (1 - w) * b ** w, rel=1e-12)
    # a neighbour without the diffusion pair, a missing curve fit, two tests only: none
    assert neighbour_time_constants(temps, [fit(1.0, 30.0), fits[1], fits[2]])[2] is None
    assert neighbour_time_constants(temps, [None, fits[1], fits[2]])[2] is None
    assert neighbour_time_constants(temps[:2], fits[:2]) == [None, None]
