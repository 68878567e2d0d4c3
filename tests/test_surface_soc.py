"""The surface SOC (model.surface_soc_gain): the RC tables read at
soc + lam * u_diff / max(dOCV/dSOC, 0.3 V). Known truth against a plain loop, the
model.json round trip, the config key, the C estimator and the Python filter taking it."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ecmgen.errors import InputError
from ecmgen.model.effects import make_effect
from ecmgen.model.model import (EcmModel, OcvOverTemperature, RcTable, interp_2d,
                                load_model, stack_rc_tables)
from ecmgen.model.simulate import simulate

REPO = Path(__file__).resolve().parents[1]
SOC = np.linspace(0.0, 1.0, 11)
# an OCV with a steep low end, a plateau below 0.3 V per unit SOC and a steep top
OCV25 = np.array([3.0, 3.3, 3.45, 3.5, 3.52, 3.54, 3.6, 3.7, 3.85, 4.0, 4.2])
TEMPS = (-10.0, 25.0)
LAM = 0.5



def demo_config(tmp_path, edit=lambda src: src, name="config.toml"):
    """The demo config, edited, written into tmp_path with its data paths made absolute
    (nothing is written into the source tree)."""
    base = REPO / "examples/panasonic-temperature"
    src = (base / "config.toml").read_text()
    src = re.sub(r'"([^"]+\.mat)"', lambda m: '"' + (base / m.group(1)).resolve().as_posix() + '"',
                 src)
    # the demo sets its own gain; the tests set theirs
    src = "".join(line for line in src.splitlines(keepends=True)
                  if not line.startswith("surface_soc_gain"))
    path = tmp_path / name
    path.write_text(edit(src))
    return path

def _row(scale: float, r_diff: float, tau_diff: float) -> RcTable:
    return RcTable(soc=SOC, r0_ohm=scale * (0.02 + 0.03 * (1 - SOC) ** 3),
                   r_fast_ohm=scale * (0.01 + 0.02 * (1 - SOC) ** 2),
                   tau_fast_s=2.0 + 3.0 * (1 - SOC), r_slow_ohm=scale * (0.02 + 0.01 * SOC),
                   tau_slow_s=60.0 - 20.0 * SOC, fit_error=np.zeros(SOC.size),
                   converged=np.ones(SOC.size, bool), r_diff_ohm=[r_diff],
                   tau_diff_s=[tau_diff])


def surface_model(gain: float = LAM) -> EcmModel:
    """Two temperatures, a diffusion pair, SOC-varying resistances and time constants."""
    table = stack_rc_tables([_row(3.0, 0.08, 600.0), _row(1.0, 0.02, 400.0)], list(TEMPS))
    ocv = OcvOverTemperature(np.array(TEMPS), SOC, np.vstack([OCV25 - 0.02 * (1 - SOC), OCV25]))
    return EcmModel(capacity_ah=2.9, ocv=ocv, charge=table, discharge=table,
                    method="synthetic", direction_deadband_a=0.029, surface_soc_gain=gain)


def plain_loop(m: EcmModel, t, i, temp, soc0: float, lam: float, g_of_i=None):
    """The step written out sample by sample, independently of ecmgen.model.simulate."""
    soc, u, prev_t, out = soc0, [0.0, 0.0, 0.0], t[0], []
    grid, rows = list(SOC), [list(r) for r in m.ocv.ocv_v]
    for k in range(t.size):
        dt = t[k] - prev_t
        prev_t = t[k]
        soc += i[k] * dt / (3600 * m.capacity_ah)
        tk = min(max(temp[k], TEMPS[0]), TEMPS[1])
        w = (tk - TEMPS[0]) / (TEMPS[1] - TEMPS[0])
        # lam / max(slope, 0.3 V) at each OCV breakpoint (the slope over its neighbours),
        # linear in SOC between them (clamped), then in temperature
        n = len(grid)
        j = 0
        while j < n - 2 and soc >= grid[j + 1]:
            j += 1
        ws = min(max((soc - grid[j]) / (grid[j + 1] - grid[j]), 0.0), 1.0)
        per = []
        for r in rows:
            node = [lam / max((r[min(q + 1, n - 1)] - r[max(q - 1, 0)]) /
                              (grid[min(q + 1, n - 1)] - grid[max(q - 1, 0)]), 0.3)
                    for q in (j, j + 1)]
            per.append(node[0] + (node[1] - node[0]) * ws)
        per_volt = per[0] + (per[1] - per[0]) * w
        surface = min(max(soc + per_volt * u[2], 0.0), 1.0)      # u[2]: u_diff of k - 1
        p = {key: float(interp_2d(m.discharge.temperature_c, SOC, getattr(m.discharge, key),
                                  surface, tk))
             for key in ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")}
        g = 1.0 if g_of_i is None else g_of_i(i[k])
        r_d = 0.08 + (0.02 - 0.08) * w
        tau_d = 600.0 + (400.0 - 600.0) * w
        for n, (r, tau) in enumerate(((p["r_fast_ohm"] * g, p["tau_fast_s"]),
                                      (p["r_slow_ohm"], p["tau_slow_s"]), (r_d, tau_d))):
            a = math.exp(-dt / tau)
            u[n] = a * u[n] + r * (1 - a) * i[k]
        ocv = float(m.ocv.ocv_at(soc, tk))                    # the OCV at the mean SOC
        out.append(ocv + p["r0_ohm"] * g * i[k] + sum(u))
    return np.array(out)


def _profile(seed: int = 5):
    t = np.concatenate([np.arange(0.0, 300.0, 0.5), np.arange(300.0, 6000.0, 5.0)])
    rng = np.random.default_rng(seed)
    i = rng.uniform(-14.0, 4.0, t.size)
    i[(t > 2000) & (t < 2600)] = 0.0                          # a rest: the surface refills
    temp = np.linspace(-15.0, 30.0, t.size)
    return t, i, temp


def test_surface_soc_matches_a_plain_loop():
    m = surface_model()
    t, i, temp = _profile()
    sim = simulate(m, t, i, 0.95, temp)
    expected = plain_loop(m, t, i, temp, 0.95, LAM)
    np.testing.assert_allclose(sim.voltage_v, expected, rtol=0, atol=1e-12)
    # the surface runs below the mean SOC in discharge, by up to tenths here, and is
    # what the tables were read at
    gap = sim.soc - sim.soc_surface
    assert gap.max() > 0.05 and sim.soc_surface.min() >= 0.0
    # the effect is not small: lam = 0 differs by many mV
    off = simulate(replace(m, surface_soc_gain=0.0), t, i, 0.95, temp)
    assert off.soc_surface is None and np.abs(off.voltage_v - sim.voltage_v).max() > 0.02
    np.testing.assert_allclose(off.voltage_v, plain_loop(m, t, i, temp, 0.95, 0.0),
                               rtol=0, atol=1e-12)


def test_surface_soc_with_parameter_effects_keeps_their_factors():
    cdr = make_effect("current_dependent_resistance", scale_at_zero=1.2, i0_a=3.0)
    m = surface_model().with_effects([cdr])
    t, i, temp = _profile(7)
    sim = simulate(m, t, i, 0.9, temp)
    expected = plain_loop(m, t, i, temp, 0.9, LAM, g_of_i=lambda x: float(cdr.factor(x)))
    np.testing.assert_allclose(sim.voltage_v, expected, rtol=0, atol=1e-12)


def test_surface_model_fits_its_own_synthetic_cell():
    """A cell with the effect: the model with the right gain reproduces it exactly, the
    model without it (what the build made before) does not."""
    m = surface_model()
    t, i, temp = _profile(11)
    measured = plain_loop(m, t, i, temp, 1.0, LAM)
    err_on = np.abs(simulate(m, t, i, 1.0, temp).voltage_v - measured).mean()
    err_off = np.abs(simulate(replace(m, surface_soc_gain=0.0), t, i, 1.0, temp).voltage_v
                     - measured).mean()
    assert err_on < 1e-12 and err_off > 0.005


def test_round_trip_and_absent_key(tmp_path):
    m = surface_model()
    raw = m.to_json_dict()
    assert raw["surface_soc_gain"] == 0.5
    back = load_model(m.save(tmp_path / "m.json"))
    assert back.surface_soc_gain == 0.5 and back.to_json() == m.to_json()
    # 0 is not written, so older models stay byte-identical; absent loads as 0
    off = replace(m, surface_soc_gain=0.0)
    assert "surface_soc_gain" not in off.to_json_dict()
    assert load_model(off.save(tmp_path / "off.json")).surface_soc_gain == 0.0


@pytest.mark.parametrize("value, match", [(-0.1, "surface_soc_gain must be"),
                                          ("0.5", "surface_soc_gain must be"),
                                          (True, "surface_soc_gain must be"),
                                          (11.0, "surface_soc_gain must be"),
                                          (float("nan"), "surface_soc_gain must be")])
def test_bad_gain_in_model_json_refused(tmp_path, value, match):
    raw = surface_model().to_json_dict()
    raw["surface_soc_gain"] = value
    path = tmp_path / "m.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(InputError, match=match) as exc:
        load_model(path)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_gain_needs_the_diffusion_pair(tmp_path):
    m = surface_model()
    plain = replace(m.discharge, r_diff_ohm=None, tau_diff_s=None)
    with pytest.raises(ValueError, match="diffusion RC pair"):
        replace(m, charge=plain, discharge=plain)
    raw = replace(m, surface_soc_gain=0.0, charge=plain, discharge=plain).to_json_dict()
    raw["surface_soc_gain"] = 0.5
    path = tmp_path / "m.json"
    path.write_text(json.dumps(raw))
    with pytest.raises(InputError, match="diffusion RC pair"):
        load_model(path)


def test_c_estimator_takes_it_and_the_python_filter_too(tmp_path):
    from ecmgen.c.codegen import generate_c
    from ecmgen.config import EstimatorConfig

    m = surface_model()
    files = generate_c(m, tmp_path / "c", prefix="x", numeric="float",
                       estimator=EstimatorConfig())
    assert any(Path(f).name == "x_est_f32.h" for f in files)  # (test_codegen_estimator_surface)
    model_path = m.save(tmp_path / "m.json")
    csv = tmp_path / "cycle.csv"
    t, i, temp = _profile()
    i = 0.2 * i                 # 0.95 down to about 0.4
    v = simulate(m, t, i, 0.95, temp).voltage_v
    csv.write_text("time_s,current_a,voltage_v,temperature_c\n" + "".join(
        f"{a!r},{b!r},{c!r},{d!r}\n" for a, b, c, d in zip(t.tolist(), i.tolist(),
                                                            v.tolist(), temp.tolist())))
    r = subprocess.run([sys.executable, "-m", "ecmgen.cli", "codegen", str(model_path),
                        "--out", str(tmp_path / "out"), "--estimator", "ekf"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    assert list((tmp_path / "out").glob("*_est_f32.h"))
    # the Python filter takes it: started 0.2 off, it finds the SOC of the cell
    r = subprocess.run([sys.executable, "-m", "ecmgen.cli", "estimate", str(model_path),
                        str(csv), "--soc0", "0.95", "--soc0-guess", "0.75", "--json"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["soc_max_abs_after_600s"] <= 0.03    # the spec's 3 % after 600 s


def test_config_key(tmp_path):
    from ecmgen.config import load_config
    from ecmgen.pipeline import with_surface_soc

    def cfg_with(line: str):
        return load_config(demo_config(
            tmp_path, lambda src: src.replace("[model]\n", f"[model]\n{line}\n"),
            name=f"surface-{abs(hash(line))}.toml"))

    from ecmgen.config import SURFACE_SOC_GAIN_MAX
    from ecmgen.model.model import SURFACE_SOC_GAIN_MAX as MODEL_MAX

    assert SURFACE_SOC_GAIN_MAX == MODEL_MAX
    assert cfg_with("").surface_soc_gain is None      # unset: the build's default
    cfg = cfg_with("surface_soc_gain = 0.5")
    assert cfg.surface_soc_gain == 0.5
    for bad in ("surface_soc_gain = -1", "surface_soc_gain = \"x\"", "surface_soc_gain = 20"):
        with pytest.raises(InputError, match="model.surface_soc_gain"):
            cfg_with(bad)
    # the build's models: the gain where the diffusion pair is, a note where it is not
    m = surface_model(0.0)
    plain = replace(m.discharge, r_diff_ohm=None, tau_diff_s=None)
    got = with_surface_soc(cfg, {"curve": m, "lm": replace(m, charge=plain, discharge=plain)})
    assert got["curve"].surface_soc_gain == 0.5 and got["lm"].surface_soc_gain == 0.0
    assert "no diffusion RC pair" in got["lm"].notes[-1]
    # unset: SURFACE_SOC_GAIN_OVER_TEMPERATURE over temperature (no note where the pair is
    # missing: nothing was asked for), 0 for a model from one test; 0 set: off
    from ecmgen.config import SURFACE_SOC_GAIN_OVER_TEMPERATURE as OVER_T

    unset = cfg_with("")
    got = with_surface_soc(unset, {"curve": m, "lm": replace(m, charge=plain, discharge=plain)})
    assert got["curve"].surface_soc_gain == OVER_T and got["lm"].notes == m.notes
    one_test = replace(unset, pulse_tests=unset.pulse_tests[:1])
    assert with_surface_soc(one_test, {"curve": m})["curve"] is m
    assert with_surface_soc(cfg_with("surface_soc_gain = 0"), {"curve": m})["curve"] is m


@pytest.mark.parametrize("numeric,tol_v", [("float", 0.5e-3), ("fixed", 2e-3)])
def test_c_takes_it(tmp_path, numeric, tol_v):
    from ecmgen.c import cbuild, cref
    from ecmgen.c.codegen import generate_c

    m = surface_model()
    cm = cbuild.build(m, numeric=numeric, prefix="sf")
    assert cm.spec.switches["SURFACE"] == 1 and not cm.spec.ocv_shared
    t, i, temp = _profile()
    dt = cref.dt_from_time(t)
    v = cm.simulate(i, dt, 0.95, temp)
    v64 = simulate(m, t, i, 0.95, temp).voltage_v
    assert np.abs(v - v64).max() < tol_v
    ref = cm.reference(i, dt, 0.95, temp)
    assert np.array_equal(cref.volts(cm.spec, ref.v) if cm.spec.fixed else ref.v,
                          v if cm.spec.fixed else v.astype(np.float32))
    off = cbuild.build(replace(m, surface_soc_gain=0.0), numeric=numeric, prefix="sf")
    assert np.abs(off.simulate(i, dt, 0.95, temp) - v).max() > 0.02
    files = generate_c(m, tmp_path / "c", prefix="sf", numeric=numeric)
    header = next(f for f in files if f.name in ("sf_ecm_f32.h", "sf_ecm_q.h")).read_text()
    assert "surface SOC" in header
    if numeric == "fixed":
        assert "SF_ECM_Q_SV" in header
    assert "surface SOC" in next(f for f in files if f.name.endswith("report.md")).read_text()


@pytest.mark.slow
def test_build_passes_it_on(tmp_path):
    """The demo config with surface_soc_gain = 0.5 and the C (float and fixed point): the
    curve model carries it, the report says so, the C takes it, and the cold cycles improve
    (README figures)."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    def edit(src):
        src = src.replace("[model]\n", "[model]\nsurface_soc_gain = 0.5\n")
        return "\n".join(line for line in src.splitlines()
                         if not line.startswith("estimator =")) + "\n"

    result = build(load_config(demo_config(tmp_path, edit)), tmp_path / "out", plots=False)
    best = result.models["curve"]
    assert best.surface_soc_gain == 0.5 and result.models["ga"].surface_soc_gain == 0.0
    assert json.loads((tmp_path / "out/model.json").read_text())["surface_soc_gain"] == 0.5
    assert "Surface SOC" in (tmp_path / "out/report.md").read_text()
    for numeric in ("float", "fixed"):
        assert result.c_report[numeric]["bit_exact_vs_reference"], numeric
    mae = {name: v.overall.mae_v for name, v in result.validations["curve"].items()}
    cold = [v for name, v in mae.items() if name.startswith(("n10degC", "n20degC"))]
    # the cold cycles better than the same build with it off (52.0 mV mean: the generated
    # surface-off block of docs/results.md, docs/make_docs.py)
    assert len(cold) == 4 and np.mean(cold) < 0.052
