"""The cold cycles: does a surface SOC explain the error of an hour of cold discharge?

Diagnosis, not a model change. Late in the cold drive cycles the cell behaves as if it were
near its empty end (the voltage dives to the 2.5 V limit at 10 A and recovers in tens of
seconds) at a coulombic SOC (0.4 at -10 degC US06) where the pulse test, whose 20-minute
rests let the particles' surface refill, shows small resistances; early in the cycles (a
rested, full cell) the model's resistances are too high. Both follow if the resistances are
read at the depleted surface SOC instead of the mean one. The prototype here reads the SOC
tables (r0, r_fast, r_slow; the curve fit's time constants, r_diff and i0 depend on T
only) but not the OCV, to which the diffusion pair's voltage already adds the
concentration overpotential, at

    soc_surface = soc + lam * u_diff / (dOCV/dSOC)      (u_diff of the previous sample; the
                                                         OCV slope held at >= 0.3 V per unit SOC)

i.e. lam = 1 when the diffusion pair's voltage were all concentration overpotential, and
simulates the build's own curve-fit models (all four pulse tests, and each temperature left
out) on the 8 shared cycles, start SOC 1.0, their measured cell temperature. lam is chosen
leave-one-temperature-out: on the other three temperatures' cycles (the all-4 model), then
scored on the held-out temperature's cycles with the model that did not see its pulse test.
For comparison it also simulates lam = 0 on a core temperature that leads the case
thermocouple (self-heating), which the surface SOC is not.

Cells: MAE in mV.

Run:  .venv/bin/python bench/cold_surface_soc.py [CONFIG] [--per-volt]   (default: the demo's
      config; --per-volt: soc + lam u_diff, lam in 1/V, without the OCV slope)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench_fit_temperature import CYCLES, TEMPS, folder
from ecmgen.data.measure import read_timeseries
from ecmgen.model.rc import rc_recurrence
from ecmgen.model.simulate import butler_volmer_factor

LAMBDAS = np.round(np.arange(0.0, 1.01, 0.1), 2)
LEADS_S = (60.0, 120.0, 300.0)
MIN_SLOPE_V = 0.3          # OCV slope floor, V per unit SOC (the flat ends of the table)


def core_temperature(series, lead_s: float) -> np.ndarray:
    """T + lead_s dT/dt (dT/dt over the last 120 s): a core that the case thermocouple
    follows with a first-order lag of lead_s (candidate (d), self-heating)."""
    t, temp = series.time_s, series.temperature_c
    return temp + lead_s * (temp - np.interp(t - 120.0, t, temp)) / 120.0


def simulate_surface(model, series, lam: float, soc0: float = 1.0, lead_s: float = 0.0,
                     per_volt: bool = False) -> np.ndarray:
    """The model's voltage with the RC tables read at the surface SOC (module docstring);
    lam = 0 is ecmgen.model.simulate.simulate (discharge-only cycles: one direction).
    ``lead_s``: simulated on :func:`core_temperature` instead of the measured one;
    ``per_volt``: soc + lam * u_diff (lam in 1/V, no OCV slope: simpler in fixed point)."""
    t, i = series.time_s, series.current_a
    temp = core_temperature(series, lead_s) if lead_s else series.temperature_c
    dt = np.diff(t, prepend=t[0])
    soc = soc0 + np.cumsum(i * dt) / (3600.0 * model.capacity_ah)
    bulk = model.discharge.at(soc, temp)
    a = np.exp(-dt / bulk["tau_diff_s"])
    u_diff = rc_recurrence(a, bulk["r_diff_ohm"] * (1.0 - a) * i)
    if lam:
        s = np.clip(soc, 0.0, 1.0)
        lo, hi = np.clip(s - 0.01, 0.0, 1.0), np.clip(s + 0.01, 0.0, 1.0)
        slope = (model.ocv.ocv_at(hi, temp) - model.ocv.ocv_at(lo, temp)) / (hi - lo)
        slope = 1.0 if per_volt else np.maximum(slope, MIN_SLOPE_V)
        surface = soc + lam * np.r_[0.0, u_diff[:-1]] / slope
        p = model.discharge.at(surface, temp)
    else:
        p = bulk
    a_f = np.exp(-dt / p["tau_fast_s"])
    a_s = np.exp(-dt / p["tau_slow_s"])
    r_f = p["r_fast_ohm"] * butler_volmer_factor(i, p["i0_a"])
    return (model.ocv.ocv_at(soc, temp) + p["r0_ohm"] * i + u_diff
            + rc_recurrence(a_f, r_f * (1.0 - a_f) * i)
            + rc_recurrence(a_s, p["r_slow_ohm"] * (1.0 - a_s) * i))


def main(argv=None) -> None:
    from ecmgen.config import load_config
    from ecmgen.model.temperature import assemble_over_temperature
    from ecmgen.pipeline import fit_pulse_tests
    from loto_temperature import _temperature_key

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default=str(
        Path(__file__).resolve().parents[1] / "examples/panasonic-temperature/config.toml"))
    ap.add_argument("--per-volt", action="store_true",
                    help="soc + lam u_diff (lam in 1/V) instead of dividing by the OCV slope")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    cfg = load_config(a.config)
    tests = fit_pulse_tests(cfg, workers=2)
    keys = [_temperature_key(t.temperature_c) for t in tests]

    def model(use):
        sel = [t for k, t in zip(keys, tests) if k in use]
        return assemble_over_temperature([t.models["curve"] for t in sel],
                                         [t.temperature_c for t in sel],
                                         step_c=cfg.temperature_step_c, warm_c=cfg.warm_row_c)

    cycles = [(temp, name, read_timeseries(folder(temp) / f"{name}.mat", capacity_ah=cfg.capacity_ah))
              for temp in TEMPS for name in CYCLES[temp]]
    all4 = model(keys)
    loto = {temp: model([k for k in keys if k != temp]) for temp in TEMPS}

    def mae(m, series, lam):
        return 1e3 * float(np.mean(np.abs(simulate_surface(m, series, lam, per_volt=a.per_volt)
                                        - series.voltage_v)))

    full = np.array([[mae(all4, s, lam) for _, _, s in cycles] for lam in LAMBDAS])
    held = np.array([[mae(loto[temp], s, lam) for temp, _, s in cycles] for lam in LAMBDAS])
    names = [f"{temp} {Path(name).stem}" for temp, name, _ in cycles]
    print(f"fits and simulations: {time.perf_counter() - t0:.0f} s\n")
    print("| lam | " + " | ".join(names) + " | mean | cold mean |")
    print("|---" * (len(names) + 3) + "|")
    for tag, tab in (("all 4", full), ("LOTO", held)):
        for lam, r in zip(LAMBDAS, tab):
            print(f"| {tag} {lam:.1f} | " + " | ".join(f"{x:.1f}" for x in r)
                  + f" | {r.mean():.1f} | {r[2:].mean():.1f} |")
    # lam chosen on the other temperatures' cycles, scored on the held-out temperature
    temp_of = np.array([temp for temp, _, _ in cycles])
    chosen, score_all4, score_loto = {}, np.zeros(len(cycles)), np.zeros(len(cycles))
    for temp in TEMPS:
        k = int(np.argmin(full[:, temp_of != temp].mean(axis=1)))
        chosen[temp] = float(LAMBDAS[k])
        score_all4[temp_of == temp] = full[k, temp_of == temp]
        score_loto[temp_of == temp] = held[k, temp_of == temp]
    print(f"\nlam chosen leave-one-temperature-out: {chosen}")
    for tag, r, base in (("all 4", score_all4, full[0]), ("LOTO", score_loto, held[0])):
        print(f"{tag}: " + " ".join(f"{x:.1f}" for x in r) + f"  mean {r.mean():.1f} "
              f"(lam 0: {base.mean():.1f}), cold mean {r[2:].mean():.1f} "
              f"(lam 0: {base[2:].mean():.1f})")
    print("\nfor comparison, candidate (d): lam 0 on a core temperature T + lead dT/dt (all 4)")
    for lead in LEADS_S:
        r = np.array([1e3 * float(np.mean(np.abs(simulate_surface(all4, s, 0.0, lead_s=lead)
                                                  - s.voltage_v))) for _, _, s in cycles])
        print(f"lead {lead:3.0f} s: " + " ".join(f"{x:.1f}" for x in r)
              + f"  mean {r.mean():.1f}, cold mean {r[2:].mean():.1f}")


if __name__ == "__main__":
    main()
