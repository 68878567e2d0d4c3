"""Effects: parameters, model.json round trip, and each discrete update against an
independent per-sample implementation of the equations in ecmgen.model.effects."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ecmgen.model import effects as fx
from ecmgen.errors import InputError
from ecmgen.data.measure import TimeSeries
from ecmgen.model import load_model, model_from_json_dict
from ecmgen.model.simulate import simulate, validate

ALL = (
    fx.Hysteresis(m_v=0.02, decay_ah=0.15, m0_v=0.004, ocv_table_state=0.3, initial_state=0.5),
    fx.CurrentDependentResistance(scale_at_zero=1.2, i0_a=3.0),
    fx.ExtraRc(r_ohm=0.015, tau_s=700.0),
    fx.CapacityError(capacity_scale=0.93),
    fx.TemperatureDependence(activation_k=4000.0, t_ref_c=25.0),
)


def profile(n=3000, seed=1):
    rng = np.random.default_rng(seed)
    dt = np.where(rng.uniform(size=n) < 0.1, 0.1, 1.0)
    dt[0] = 0.0
    t = np.cumsum(dt)
    i = np.repeat(rng.normal(-1.5, 3.0, n // 10), 10)[:n]
    i[200:400] = 0.0
    i[1500:1600] = 0.01                  # inside the deadband: keeps the last direction
    temp = 25.0 + 6.0 * (t / t[-1]) + 0.2 * np.sin(t / 50)
    return t, i, temp


def reference(model, t, i, soc0, temp):
    """The augmented step of ecmgen.model.effects, one sample at a time, scalar math only."""
    dt = np.diff(t, prepend=t[0])
    q_eff = model.capacity_ah
    for e in model.effects:
        if e.name == "capacity_error":
            q_eff *= e.capacity_scale
    db = model.direction_deadband_a
    charging = i[0] > db
    soc = soc0
    u_f = u_s = 0.0
    h = {id(e): e.initial_state for e in model.effects if e.name == "hysteresis"}
    u3 = {id(e): 0.0 for e in model.effects if e.name == "extra_rc"}
    out = np.empty(t.size)
    for k in range(t.size):
        ik, dtk = float(i[k]), float(dt[k])
        if ik > db:
            charging = True
        elif ik < -db:
            charging = False
        s = 1.0 if charging else -1.0
        soc = soc + ik * dtk / (3600.0 * q_eff)
        tab = model.charge if charging else model.discharge
        p = {key: float(np.interp(soc, tab.soc, getattr(tab, key)[0]))
             for key in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")}
        for e in model.effects:
            if e.name == "current_dependent_resistance":
                x = max(abs(ik) / e.i0_a, 1e-12)
                g = e.scale_at_zero * math.asinh(x) / x
                p["r0_ohm"] *= g
                p["r_fast_ohm"] *= g
            elif e.name == "temperature_dependence" and temp is not None:
                f = math.exp(e.activation_k * (1 / (temp[k] + 273.15) - 1 / (e.t_ref_c + 273.15)))
                for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
                    p[key] *= f
        a_f = math.exp(-dtk / p["tau_fast_s"])
        a_s = math.exp(-dtk / p["tau_slow_s"])
        u_f = a_f * u_f + p["r_fast_ohm"] * (1 - a_f) * ik
        u_s = a_s * u_s + p["r_slow_ohm"] * (1 - a_s) * ik
        v = float(np.interp(soc, model.ocv.soc, model.ocv.ocv_v[0])) + p["r0_ohm"] * ik + u_f + u_s
        for e in model.effects:
            if e.name == "hysteresis":
                a_h = math.exp(-abs(ik) * dtk / (3600.0 * e.decay_ah))
                h[id(e)] = a_h * h[id(e)] + (1 - a_h) * s
                v += e.m_v * (h[id(e)] - e.ocv_table_state) + e.m0_v * (s - e.ocv_table_state)
            elif e.name == "extra_rc":
                a = math.exp(-dtk / e.tau_s)
                u3[id(e)] = a * u3[id(e)] + e.r_ohm * (1 - a) * ik
                v += u3[id(e)]
        out[k] = v
    return out


@pytest.mark.parametrize("effect", ALL, ids=lambda e: e.name)
def test_each_effect_matches_the_documented_update(synthetic_model, effect):
    t, i, temp = profile()
    model = synthetic_model.with_effects([effect])
    got = simulate(model, t, i, 0.8, temp).voltage_v
    want = reference(model, t, i, 0.8, temp)
    assert np.max(np.abs(got - want)) < 1e-9
    # and it changes the voltage (the effect is not a no-op)
    base = simulate(synthetic_model, t, i, 0.8, temp).voltage_v
    assert np.max(np.abs(got - base)) > 1e-3


def test_all_effects_together_match_the_reference(synthetic_model):
    t, i, temp = profile(seed=4)
    model = synthetic_model.with_effects(ALL)
    got = simulate(model, t, i, 0.7, temp)
    assert np.max(np.abs(got.voltage_v - reference(model, t, i, 0.7, temp))) < 1e-9
    # without a temperature trace the Arrhenius factor is 1
    no_t = simulate(model, t, i, 0.7, None).voltage_v
    ref = reference(model.with_effects(ALL[:4]), t, i, 0.7, None)
    assert np.max(np.abs(no_t - ref)) < 1e-9
    assert got.extra_v is not None and got.extra_v.shape == t.shape


def test_no_effects_is_bit_identical_and_neutral_effects_change_nothing(synthetic_model):
    t, i, temp = profile(seed=2)
    a = simulate(synthetic_model, t, i, 0.6, temp)
    assert a.extra_v is None
    neutral = synthetic_model.with_effects([
        fx.Hysteresis(m_v=0.0, decay_ah=0.1), fx.ExtraRc(r_ohm=0.0, tau_s=100.0),
        fx.CapacityError(capacity_scale=1.0),
        fx.TemperatureDependence(activation_k=0.0, t_ref_c=25.0)])
    b = simulate(neutral, t, i, 0.6, temp)
    np.testing.assert_array_equal(a.voltage_v, b.voltage_v)
    np.testing.assert_array_equal(a.soc, b.soc)


def test_capacity_error_changes_the_soc_trajectory(synthetic_model):
    t = np.arange(0.0, 3600.0, 1.0)
    i = np.full(t.size, -2.9)             # 1 C for an hour
    m = synthetic_model.with_effects([fx.CapacityError(capacity_scale=0.9)])
    soc = simulate(m, t, i, 1.0).soc
    expected = 1.0 - 2.9 * (t[-1]) / 3600.0 / (2.9 * 0.9)
    assert soc[-1] == pytest.approx(expected, abs=1e-12)


def test_hysteresis_state_follows_the_direction(synthetic_model):
    e = fx.Hysteresis(m_v=0.02, decay_ah=0.05, initial_state=-1.0)
    t = np.arange(0.0, 2000.0, 1.0)
    i = np.where(t < 1000, 2.9, -2.9)
    ch = i > 0
    h = fx.hysteresis_state(e, t, i, ch)
    assert h[999] > 0.99 and h[-1] < -0.99      # 0.8 Ah >> 0.05 Ah: saturated


def test_current_dependent_factor():
    e = fx.CurrentDependentResistance(scale_at_zero=1.5, i0_a=2.0)
    g = e.factor(np.array([0.0, 1e-15, 2.0, -2.0, 20.0]))
    assert g[0] == pytest.approx(1.5) and g[1] == pytest.approx(1.5)
    assert g[2] == pytest.approx(1.5 * math.asinh(1.0)) and g[3] == g[2]
    assert g[4] < g[2] < g[0]


def test_json_round_trip_through_model_json(synthetic_model, tmp_path):
    model = synthetic_model.with_effects(ALL)
    path = model.save(tmp_path / "model.json")
    back = load_model(path)
    assert back.effects == model.effects
    assert [e.name for e in back.effects] == [e.name for e in ALL]
    assert back.to_json() == model.to_json()       # byte-identical on re-save
    d = ALL[0].to_json_dict()
    assert d["name"] == "hysteresis" and all(isinstance(v, float) for k, v in d.items()
                                             if k != "name")
    t, i, temp = profile()
    np.testing.assert_array_equal(simulate(back, t, i, 0.8, temp).voltage_v,
                                  simulate(model, t, i, 0.8, temp).voltage_v)


@pytest.mark.parametrize("entry, words", [
    ({"name": "magic", "x": 1.0}, "unknown effect 'magic'"),
    ({"r_ohm": 0.01, "tau_s": 10.0}, "unknown effect None"),
    ("extra_rc", "must be an object"),
    ({"name": "extra_rc", "r_ohm": 0.01}, "missing parameter tau_s"),
    ({"name": "extra_rc", "r_ohm": "0.01", "tau_s": 10.0}, "r_ohm must be a number"),
    ({"name": "extra_rc", "r_ohm": 0.01, "tau_s": -10.0}, "tau_s must be positive"),
    ({"name": "extra_rc", "r_ohm": 0.01, "tau_s": 10.0, "tau2_s": 1.0}, "unknown parameter"),
    ({"name": "hysteresis", "m_v": 0.01, "decay_ah": 0.1, "initial_state": 2.0}, "initial_state"),
    ({"name": "capacity_error", "capacity_scale": True}, "must be a number"),
    ({"name": "temperature_dependence", "activation_k": float("nan"), "t_ref_c": 25.0},
     "finite"),
])
def test_bad_effect_entries_are_one_line_input_errors(entry, words):
    with pytest.raises(InputError) as err:
        fx.effect_from_json_dict(entry, "model.json")
    msg = str(err.value)
    assert msg.startswith("model.json: ") and words in msg and "\n" not in msg


def test_bad_effect_in_model_json_names_the_file(synthetic_model, tmp_path):
    raw = synthetic_model.with_effects([ALL[2]]).to_json_dict()
    raw["effects"][0]["tau_s"] = 0.0
    p = tmp_path / "m.json"
    p.write_text(json.dumps(raw))
    with pytest.raises(InputError, match=r"m\.json: effect extra_rc: tau_s must be positive"):
        load_model(p)
    raw["effects"] = [{"name": "nope"}]
    with pytest.raises(InputError, match="unknown effect"):
        model_from_json_dict(raw, "x.json")


def test_validate_runs_augmented_models(synthetic_model):
    t, i, temp = profile(seed=5)
    true = synthetic_model.with_effects([ALL[0], ALL[2], ALL[4]])
    v = simulate(true, t, i, 0.8, temp).voltage_v
    series = TimeSeries(t, i, v, temp, None, "cycle.csv")
    assert validate(true, series, soc0=0.8).overall.mae_v < 1e-12
    assert validate(synthetic_model, series, soc0=0.8).overall.mae_v > 1e-3
