"""Accuracy over temperature: per-temperature curve fits, assembled over temperature, on the 8 cycles.

Builds the whole-test ("curve") fit of each shared Panasonic pulse test
(bench_fit_temperature.fit_pulse_test), assembles the multi-temperature model the way the
findings (notes/temperature-findings.md, section 11) describe -- breakpoints at the pulse
tests' median cell temperatures, a derived 45 degC breakpoint, Arrhenius interpolation
resampled onto a uniform 5 K grid, the rests' OCV per temperature -- and validates it
with ecmgen.model.simulate.validate on each cycle's measured cell temperature
(soc0 = 1.0): all four pulse tests, and leave-one-temperature-out (LOTO).

:func:`assemble_arrhenius_5k` was the stand-in for the pipeline's assembly;
``--pipeline-assembly`` uses ecmgen.model.temperature.assemble_over_temperature instead.

``--build [CONFIG]`` goes through the build chain instead, for every method of the config
(default: the bundled examples/panasonic-temperature/config.toml, the demo): each pulse
test fitted once by ecmgen.pipeline.fit_pulse_tests (as `ecmgen build` does, 2 processes),
then per method the model from all four tests and, for each temperature, the model from
the other three, fitted again without it (a test between two others is offered their time
constants), assembled by model.temperature.assemble_over_temperature with the config's
[model] settings, validated on the cycles.

Cells: MAE / RMSE / max |error| in mV.

Run:  OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/loto_temperature.py [--no-loto]
      [--no-steps] [--no-bv] [--no-diffusion]
      .venv/bin/python bench/loto_temperature.py --build [CONFIG] [--step-c 5] [--lag 1]
      [--surface-soc-gain 0.5]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench_fit_temperature import CAPACITY_AH, CYCLES, TEMPS, fit_pulse_test, folder
from ecmgen.data.measure import read_timeseries
from ecmgen.model.model import EcmModel, OcvOverTemperature, RcTable
from ecmgen.model.simulate import validate

KELVIN = 273.15
RES = ("r0_ohm", "r_fast_ohm", "r_slow_ohm")
TAUS = ("tau_fast_s", "tau_slow_s")


def _inv_k(t_c):
    return 1.0 / (np.asarray(t_c, dtype=np.float64) + KELVIN)


def _extrapolate(temps, rows, in_range, t_new):
    """Derived breakpoint at t_new from the nearest measured row, scaled by ONE activation
    energy: the median over in-range SOC nodes of the two-point Arrhenius slope between the
    two nearest breakpoints (>= 0: a resistance does not rise with temperature)."""
    order = np.argsort(np.abs(np.asarray(temps) - t_new))
    a, b = int(order[0]), int(order[1])
    ra, rb = np.maximum(rows[a], 1e-9), np.maximum(rows[b], 1e-9)
    m = in_range[a] & in_range[b]
    slope = np.log(rb[m] / ra[m]) / (_inv_k(temps[b]) - _inv_k(temps[a]))
    ea = max(float(np.median(slope)), 0.0) if slope.size else 0.0
    return rows[a] * np.exp(ea * (_inv_k(t_new) - _inv_k(temps[a])))


def _arrhenius_resample(temps, rows, grid):
    """ln(value) linear in 1/T between breakpoints, clamped beyond: rows (n_T, m) -> (n_g, m)."""
    x = _inv_k(temps)[::-1]                      # increasing
    y = np.log(np.maximum(np.asarray(rows, dtype=np.float64), 1e-12))[::-1]
    xg = _inv_k(np.clip(grid, min(temps), max(temps)))
    return np.exp(np.column_stack([np.interp(xg, x, y[:, j]) for j in range(y.shape[1])]))


def assemble_arrhenius_5k(parts, *, t_hi_c: float = 45.0, step_k: float = 5.0,
                          capacity_ah: float = CAPACITY_AH) -> EcmModel:
    """One model over temperature from one-temperature fits.

    parts: list of dict(temperature_c, curve=CurveFit, ocv=OcvTable). Resistances, time
    constants, r_diff and i0 (as 1/i0) interpolate Arrhenius-wise (ln p linear in 1/T_K)
    between the breakpoints plus a derived ``t_hi_c`` breakpoint, resampled onto a uniform
    ``step_k`` grid (the model interpolates linearly between its rows); the OCV is the rests'
    OCV per breakpoint, linear in T; everything clamps beyond the ends."""
    parts = sorted(parts, key=lambda p: p["temperature_c"])
    temps = [p["temperature_c"] for p in parts]
    tables = {}
    for d in ("charge", "discharge"):
        cols = [p["curve"].rc_columns(d) for p in parts]
        soc = cols[0]["soc"]
        in_range = [np.asarray(c["converged"], bool) for c in cols]
        val = {k: [np.asarray(c[k], dtype=np.float64) for c in cols] for k in RES + TAUS}
        bv = all("i0_a" in c for c in cols)
        diff = all("r_diff_ohm" in c for c in cols)
        if bv:
            val["inv_i0"] = [np.full(soc.size, 1.0 / c["i0_a"][0]) for c in cols]
        if diff:
            val["r_diff_ohm"] = [np.full(soc.size, c["r_diff_ohm"][0]) for c in cols]
            val["tau_diff_s"] = [np.full(soc.size, c["tau_diff_s"][0]) for c in cols]
        bp = list(temps)
        if t_hi_c > max(temps) and len(temps) > 1:
            ones = [np.ones(soc.size, bool)] * len(temps)
            for k in list(val):
                if k in RES:
                    new = _extrapolate(temps, val[k], in_range, t_hi_c)
                elif k in ("inv_i0", "r_diff_ohm"):
                    new = _extrapolate(temps, val[k], ones, t_hi_c)
                else:                               # time constants of the warmest
                    new = val[k][-1].copy()
                val[k].append(new)
            bp.append(t_hi_c)
        lo = np.floor(min(bp) / step_k) * step_k
        grid = np.arange(lo, max(bp) + 0.5 * step_k, step_k)
        res = {k: _arrhenius_resample(bp, np.vstack(v), grid) for k, v in val.items()}
        near = np.array([int(np.argmin(np.abs(np.array(temps) - g))) for g in grid])
        kw = {k: res[k] for k in RES + TAUS}
        if bv:
            kw["i0_a"] = 1.0 / res["inv_i0"][:, 0]
        if diff:
            kw["r_diff_ohm"] = res["r_diff_ohm"][:, 0]
            kw["tau_diff_s"] = res["tau_diff_s"][:, 0]
        tables[d] = RcTable(soc=soc, temperature_c=grid,
                            fit_error=np.vstack([cols[n]["fit_error"] for n in near]),
                            converged=np.vstack([cols[n]["converged"] for n in near]), **kw)
    grid_soc = parts[0]["ocv"].soc
    ocv = OcvOverTemperature(np.array(temps), grid_soc,
                             np.vstack([np.interp(grid_soc, p["ocv"].soc, p["ocv"].ocv_v)
                                        for p in parts]))
    return EcmModel(capacity_ah=capacity_ah, ocv=ocv, charge=tables["charge"],
                    discharge=tables["discharge"], method="curve",
                    direction_deadband_a=0.01 * capacity_ah)


def assemble_pipeline(parts, *, t_hi_c: float = 45.0, capacity_ah: float = CAPACITY_AH
                      ) -> EcmModel:
    """The same parts through the pipeline's assembly (ecmgen.model.temperature)."""
    from ecmgen.model.temperature import assemble_over_temperature

    models = [EcmModel(capacity_ah=capacity_ah, ocv=p["ocv"],
                       charge=RcTable(**p["curve"].rc_columns("charge")),
                       discharge=RcTable(**p["curve"].rc_columns("discharge")),
                       method="curve", direction_deadband_a=0.01 * capacity_ah)
              for p in parts]
    return assemble_over_temperature(models, [p["temperature_c"] for p in parts],
                                     warm_c=t_hi_c)


_CYCLE_CACHE: dict = {}


def cycle(temp: str, name: str):
    key = (temp, name)
    if key not in _CYCLE_CACHE:
        _CYCLE_CACHE[key] = read_timeseries(folder(temp) / f"{name}.mat", None,
                                            capacity_ah=CAPACITY_AH)
    return _CYCLE_CACHE[key]


def validate_on(model, temps, lag: int = 0):
    """MAE/RMSE/max in mV on each cycle of ``temps`` (soc0 = 1.0, the file's cell
    temperature); ``lag`` > 0 drives the model with the current ``lag`` samples earlier
    (the drive-cycle files' voltage lags their current by about one sample, findings 8)."""
    from dataclasses import replace

    out = {}
    for temp in temps:
        for name in CYCLES[temp]:
            s = cycle(temp, name)
            if lag:
                s = replace(s, current_a=np.concatenate((np.zeros(lag), s.current_a[:-lag])))
            m = validate(model, s, soc0=1.0).overall
            out[(temp, name)] = (m.mae_v * 1e3, m.rmse_v * 1e3, m.max_abs_v * 1e3)
    return out


def row(label, res):
    cells = []
    for temp in TEMPS:
        for name in CYCLES[temp]:
            v = res.get((temp, name))
            cells.append("-" if v is None else f"{v[0]:.1f}/{v[1]:.1f}/{v[2]:.0f}")
    return f"| {label} | " + " | ".join(cells) + " |"


def header():
    cols = [f"{t} {c}" for t in TEMPS for c in CYCLES[t]]
    return "| model | " + " | ".join(cols) + " |\n|" + "---|" * (len(cols) + 1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-loto", action="store_true")
    ap.add_argument("--no-steps", action="store_true")
    ap.add_argument("--no-bv", action="store_true", help="no Butler-Volmer branch (i0 none)")
    ap.add_argument("--no-diffusion", action="store_true")
    ap.add_argument("--t-hi", type=float, default=45.0, help="derived warm breakpoint, degC")
    ap.add_argument("--rows-per-decade", type=float, default=20.0)
    ap.add_argument("--min-weight-s", type=float, default=1.0)
    ap.add_argument("--lag", type=int, default=0, help="samples of current-to-voltage lag")
    ap.add_argument("--pipeline-assembly", action="store_true",
                    help="assemble with ecmgen.model.temperature instead of the stand-in")
    ap.add_argument("--build", nargs="?", const=str(EXAMPLE_CONFIG), metavar="CONFIG",
                    help="every method through the build chain (default config: the demo)")
    ap.add_argument("--step-c", type=float, help="--build: [model] temperature_step_c")
    ap.add_argument("--surface-soc-gain", type=float,
                    help="--build: [model] surface_soc_gain (default: the config's)")
    a = ap.parse_args(argv)
    if a.build:
        return main_build(a)
    t0 = time.perf_counter()
    parts = {}
    for temp in TEMPS:
        f = fit_pulse_test(temp, steps=not a.no_steps, methods=("curve",),
                           diffusion=not a.no_diffusion, rows_per_decade=a.rows_per_decade,
                           min_weight_s=a.min_weight_s)
        if a.no_bv:
            from ecmgen.fit.curve import CurveOptions, fit_pulse_curves

            f.curve = fit_pulse_curves(f.series, f.pulses, f.ocv, CAPACITY_AH,
                                       CurveOptions(diffusion=not a.no_diffusion), i0_a=None,
                                       steps=None if a.no_steps else
                                       __import__("bench_fit_temperature").read_steps(
                                           folder(temp) / "hppc-soc-steps.mat"))
        c = f.curve
        print(f"{temp}: T {f.temperature_c:.1f} degC, i0 {c.i0_a}, taus {c.tau_fast_s:.3f}/"
              f"{c.tau_slow_s:.2f}/{c.tau_diff_s}, fit RMS {c.rms_error_v * 1e3:.2f} mV, "
              f"{f.times['curve']:.2f} s", flush=True)
        parts[temp] = dict(temperature_c=f.temperature_c, curve=c, ocv=f.ocv)
    print(f"fits: {time.perf_counter() - t0:.1f} s\n")
    print(header())
    assemble = assemble_pipeline if a.pipeline_assembly else assemble_arrhenius_5k
    model = assemble(list(parts.values()), t_hi_c=a.t_hi)
    print(row("all 4", validate_on(model, TEMPS, a.lag)), flush=True)
    if not a.no_loto:
        loto = {}
        for temp in TEMPS:
            m = assemble([p for k, p in parts.items() if k != temp], t_hi_c=a.t_hi)
            loto.update(validate_on(m, (temp,), a.lag))
        print(row("LOTO", loto), flush=True)
    print(f"\ntotal {time.perf_counter() - t0:.1f} s")


EXAMPLE_CONFIG = (Path(__file__).resolve().parents[1] / "examples" / "panasonic-temperature" /
                  "config.toml")


def main_build(a) -> None:
    """--build: the per-test fits of the build chain, assembled all-4 and leave-one-out."""
    from dataclasses import replace

    from ecmgen.config import load_config
    from ecmgen.model.temperature import assemble_over_temperature
    from ecmgen.pipeline import fit_pulse_tests, with_surface_soc

    t0 = time.perf_counter()
    cfg = load_config(a.build)
    if a.step_c is not None:
        cfg = replace(cfg, temperature_step_c=a.step_c)
    if a.surface_soc_gain is not None:
        cfg = replace(cfg, surface_soc_gain=a.surface_soc_gain)
    warm = cfg.warm_row_c if a.t_hi == 45.0 else a.t_hi
    tests = fit_pulse_tests(cfg, workers=2)
    keys = [_temperature_key(t.temperature_c) for t in tests]
    print(f"fits ({', '.join(f'{k} {t.seconds:.1f} s' for k, t in zip(keys, tests))}): "
          f"{time.perf_counter() - t0:.1f} s wall; grid {cfg.temperature_step_c:g} K, "
          f"warm row {warm} degC\n")
    # leaving a test out changes the others' fits (a test between two others is offered
    # their time constants): the other three are fitted again as a build of them would
    loto_tests = {} if a.no_loto else {
        temp: fit_pulse_tests(replace(cfg, pulse_tests=tuple(
            p for p, k in zip(cfg.pulse_tests, keys) if k != temp)), workers=2)
        for temp in TEMPS}
    print(header())
    for method in cfg.methods:
        def model(sel):
            m = assemble_over_temperature([t.models[method] for t in sel],
                                          [t.temperature_c for t in sel],
                                          step_c=cfg.temperature_step_c, warm_c=warm)
            return with_surface_soc(cfg, {method: m})[method]

        print(row(f"{method}, all 4", validate_on(model(tests), TEMPS, a.lag)), flush=True)
        if not a.no_loto:
            loto = {}
            for temp in TEMPS:
                loto.update(validate_on(model(loto_tests[temp]), (temp,), a.lag))
            print(row(f"{method}, LOTO", loto), flush=True)
    print(f"\ntotal {time.perf_counter() - t0:.1f} s")


def _temperature_key(t_c: float) -> str:
    """The TEMPS key of a pulse test at t_c degC (the nearest of 25, 0, -10, -20)."""
    nominal = {"25degC": 25.0, "0degC": 0.0, "n10degC": -10.0, "n20degC": -20.0}
    return min(nominal, key=lambda k: abs(nominal[k] - t_c))


if __name__ == "__main__":
    main()
