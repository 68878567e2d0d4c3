"""One-temperature models from the shared cold Panasonic pulse tests, on that temperature's
drive cycles, against the peer's figures (PyBOP 26.3, Thevenin 2RC per SOC level on the
same HPPC file and OCV, tables assembled by hand).

The drive cycles warm the cell (0 degC US06: 0.5 -> 14 degC; -20 degC US06: -20 -> 0 degC)
while a model from one pulse test holds that test's resistances. Per temperature, four
builds of the whole-test fit (`ecmgen.build`, OCV from the test's rests, soc0 = 1.0):

- ``hppc``: the HPPC file alone (``data.pulses``), as the peer was fitted;
- ``hppc + steps``: with its SOC-step file (the 1C discharges between the pulse levels,
  logged apart; ``[[data.pulse_tests]] steps``): the relaxation of a sustained discharge;
- each of the two with ``[model] activation_k``: the resistances follow the cell
  temperature by Arrhenius about the test's. Ea/R is measured on the cell's OTHER
  pulse tests, not this one: per pair of them, the median over their common (SOC,
  C-rate) of d ln R(10 s) / d(1/T); then the median over the pairs.

    .venv/bin/python bench/one_temperature.py

Cells: MAE in mV per cycle.
"""

from __future__ import annotations

import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
FOLDERS = ("25degC", "0degC", "n10degC", "n20degC")
HELD = ("0degC", "n20degC")
PEER_MV = {"0degC": (38.7, 30.1), "n20degC": (187.0, 65.7)}
CAPACITY_AH = 2.9
R_TIME_S = 10.0           # the DC-IR time whose Ea/R is measured: the whole pulse's R


def folder(name: str) -> Path:
    return DATA / f"panasonic-18650pf-{name}"


def dcir_and_temperature(name: str):
    """The HPPC's discharge R(10 s) by (SOC level, C-rate), and the median cell temperature
    during its pulses (degC)."""
    from ecmgen.data.dcir import extract_dcir, find_pulses
    from ecmgen.data.measure import read_timeseries

    s = read_timeseries(folder(name) / "hppc.mat", capacity_ah=CAPACITY_AH)
    pulses = [p for p in find_pulses(s, CAPACITY_AH, soc0=1.0) if not p.cut_short]
    tab = extract_dcir(s, pulses, (0.1, R_TIME_S))
    ix = np.concatenate([np.arange(p.start, p.stop) for p in pulses])
    r = {(round(float(soc), 1), float(c)): float(v)
         for soc, d, c, v in zip(tab.soc, tab.direction, tab.c_rate, tab.r_ohm[:, 1])
         if d == "discharge" and np.isfinite(v) and soc >= 0.2}
    return r, float(np.median(s.temperature_c[ix]))


def activation_k(tests: dict, leave_out: str) -> tuple[float, list[str]]:
    """Ea/R (K) from the pairs of tests other than ``leave_out`` (module docstring)."""
    from ecmgen.model.temperature import activation_slope_k

    slopes, words = [], []
    for a, b in itertools.combinations([n for n in tests if n != leave_out], 2):
        (ra, ta), (rb, tb) = tests[a], tests[b]
        keys = [k for k in ra if k in rb]
        ea = activation_slope_k(ta, tb, np.array([ra[k] for k in keys]),
                                np.array([rb[k] for k in keys]))
        slopes.append(ea)
        words.append(f"{a}/{b} {ea:.0f} K")
    return float(np.median(slopes)), words


def config_text(name: str, steps: bool, ea: float) -> str:
    f = folder(name)
    head = (f'[cell]\ncapacity_ah = {CAPACITY_AH}\n[data]\ncycle = "{f / "us06.mat"}"\n'
            f'extra_cycles = ["{f / "hwfet.mat"}"]\nsoc0 = 1.0\nocv = "pulses"\n')
    if steps:
        head += (f'[[data.pulse_tests]]\nfile = "{f / "hppc.mat"}"\nsoc0 = 1.0\n'
                 f'steps = "{f / "hppc-soc-steps.mat"}"\n')
    else:
        head += f'pulses = "{f / "hppc.mat"}"\npulses_soc0 = 1.0\n'
    head += '[fit]\nmethods = ["curve"]\n'
    return head + (f"[model]\nactivation_k = {ea:.0f}\n" if ea else "")


def run(name: str, steps: bool, ea: float) -> list[float]:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "one.toml"
        cfg.write_text(config_text(name, steps, ea))
        r = build(load_config(cfg), Path(tmp) / "out", plots=False, c_code=False)
    return [1e3 * v.overall.mae_v for v in r.validations["curve"].values()]


def main() -> int:
    tests = {n: dcir_and_temperature(n) for n in FOLDERS}
    print("pulse tests' median cell temperature: "
          + ", ".join(f"{n} {t:.1f} degC" for n, (_, t) in tests.items()))
    print(f"{'test':8s} {'build':32s} | {'US06 mV':>8s} {'HWFET mV':>8s} | ahead of the peer")
    for name in HELD:
        ea, words = activation_k(tests, name)
        print(f"{name}: Ea/R {ea:.0f} K from the other tests ({', '.join(words)})")
        peer = PEER_MV[name]
        print(f"{name:8s} {'peer (PyBOP, hppc)':32s} | {peer[0]:8.1f} {peer[1]:8.1f} |")
        for steps in (False, True):
            for k in (0.0, ea):
                label = ("hppc + steps" if steps else "hppc") + \
                    (f", activation_k {k:.0f}" if k else "")
                mae = run(name, steps, k)
                ahead = " ".join("yes" if m < p else "no" for m, p in zip(mae, peer))
                print(f"{name:8s} {label:32s} | {mae[0]:8.1f} {mae[1]:8.1f} | {ahead}",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
