"""Bench: identification of each Panasonic pulse test, stage times and fit RMS.

For every temperature folder of ../shared/data/panasonic-18650pf-*: read hppc.mat (and
hppc-soc-steps.mat), find the pulses, DC-IR table and rest OCV, fit the Butler-Volmer i0
(:func:`ecmgen.fit.rate.fit_exchange_current`), the whole-test "curve" fit
(:func:`ecmgen.fit.curve.fit_pulse_curves`) and the five-point GA / LM fits (rows of
:func:`ecmgen.fit.points.five_point_rows`). One run, one printed table: wall-clock per stage
(single process; the machine may be shared, so treat the times as upper bounds) and the
fits' own residuals.

Run:  OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_fit_temperature.py [--no-steps]
      [--methods curve,ga,lm] [TEMP ...]      (TEMP: 25degC 0degC n10degC n20degC)

The helpers (reading, one pulse test's fits) are shared with bench/loto_temperature.py.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ecmgen.data.dcir import extract_dcir, find_pulses
from ecmgen.data.measure import TimeSeries, read_timeseries
from ecmgen.data.ocv import ocv_from_pulse_rests
from ecmgen.errors import InputError
from ecmgen.fit.curve import CurveOptions, fit_pulse_curves
from ecmgen.fit.points import five_point_rows
from ecmgen.fit.rate import fit_exchange_current

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
CAPACITY_AH = 2.9
TEMPS = ("25degC", "0degC", "n10degC", "n20degC")
CYCLES = {"25degC": ("us06", "hwfet-a"), "0degC": ("us06", "hwfet"),
          "n10degC": ("us06", "hwfet"), "n20degC": ("us06", "hwfet")}


def folder(temp: str) -> Path:
    return DATA / f"panasonic-18650pf-{temp}"


def read_steps(path: Path) -> TimeSeries:
    """The SOC-step file. The -20 degC one ends with a 0 V row (logger switched off), which
    read_timeseries rightly refuses: here such rows are dropped (bench only)."""
    try:
        return read_timeseries(path, None, capacity_ah=CAPACITY_AH)
    except InputError:
        import scipy.io

        m = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)["meas"]
        ok = (m.Voltage > 0.5) & (m.Voltage < 6.0)
        col = lambda a: np.asarray(a, dtype=np.float64)[ok]  # noqa: E731
        return TimeSeries(col(m.Time), col(m.Current), col(m.Voltage),
                          col(m.Battery_Temp_degC), col(m.Ah), str(path))


def table_temperature_c(series: TimeSeries, pulses) -> float:
    """The temperature of a pulse test: the median cell temperature during its complete
    pulses (the chamber setting is not the cell's: 25.8 / 0.6 / -9.9 / -19.9 degC)."""
    ix = np.concatenate([np.arange(p.start, p.stop) for p in pulses if not p.cut_short])
    return float(np.median(series.temperature_c[ix]))


@dataclass
class PulseTestFit:
    temp: str
    temperature_c: float
    series: TimeSeries
    pulses: list
    ocv: object
    dcir: object
    i0: object
    curve: object = None
    points: dict = field(default_factory=dict)
    point_notes: list = field(default_factory=list)
    times: dict = field(default_factory=dict)


def fit_pulse_test(temp: str, *, steps: bool = True, methods=("curve", "ga", "lm"),
                   **curve_kw) -> PulseTestFit:
    times = {}
    t0 = time.perf_counter()
    series = read_timeseries(folder(temp) / "hppc.mat", None, capacity_ah=CAPACITY_AH)
    steps_series = read_steps(folder(temp) / "hppc-soc-steps.mat") if steps else None
    times["read"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pulses = find_pulses(series, CAPACITY_AH, soc0=1.0)
    dcir = extract_dcir(series, pulses)
    ocv, _ = ocv_from_pulse_rests(series, pulses, CAPACITY_AH, 1.0)
    times["pulses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    i0 = fit_exchange_current(dcir, CAPACITY_AH)
    times["i0"] = time.perf_counter() - t0
    out = PulseTestFit(temp, table_temperature_c(series, pulses), series, pulses, ocv, dcir,
                       i0, times=times)
    if "curve" in methods:
        t0 = time.perf_counter()
        out.curve = fit_pulse_curves(series, pulses, ocv, CAPACITY_AH, CurveOptions(**curve_kw),
                                     i0_a=i0.i0_a, steps=steps_series)
        times["curve"] = time.perf_counter() - t0
    if "ga" in methods or "lm" in methods:
        rows, out.point_notes = five_point_rows(dcir, "max")
        if "ga" in methods:
            from ecmgen.fit.ga import fit_ga

            t0 = time.perf_counter()
            out.points["ga"] = fit_ga(rows.t_s, rows.r_ohm, seed=0)
            times["ga"] = time.perf_counter() - t0
        if "lm" in methods:
            from ecmgen.fit.lm import fit_lm

            t0 = time.perf_counter()
            out.points["lm"] = fit_lm(rows.t_s, rows.r_ohm)
            times["lm"] = time.perf_counter() - t0
        out.points["rows"] = rows
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("temps", nargs="*", default=list(TEMPS))
    ap.add_argument("--no-steps", action="store_true", help="hppc.mat alone")
    ap.add_argument("--methods", default="curve,ga,lm")
    a = ap.parse_args(argv)
    methods = tuple(a.methods.split(","))
    if "lm" in methods:          # casadi builds its Function once per process: not a fit cost
        from ecmgen.fit.lm import fit_lm

        fit_lm(np.array([0.1, 1, 3, 6, 10]), np.array([[1e-3, 1.2e-3, 1.3e-3, 1.35e-3, 1.4e-3]]))
    stages = ("read", "pulses", "i0", "curve", "ga", "lm")
    print(f"| pulse test | T degC | {' | '.join(s + ' s' for s in stages)} | fit s (i0+curve+ga+lm) "
          "| curve rows | curve RMS mV | taus s (fast/slow/diff) | i0 A | ga/lm levels (converged) |")
    print("|" + "---|" * (len(stages) + 8))
    for temp in a.temps:
        f = fit_pulse_test(temp, steps=not a.no_steps, methods=methods)
        t = f.times
        fit_s = sum(t.get(k, 0.0) for k in ("i0", "curve", "ga", "lm"))
        c = f.curve
        taus = "-" if c is None else \
            f"{c.tau_fast_s:.2f}/{c.tau_slow_s:.1f}/{c.tau_diff_s or float('nan'):.0f}"
        eq5 = "/".join(f"{f.points[m].converged.size} ({int(f.points[m].converged.sum())})"
                       for m in ("ga", "lm") if m in f.points) or "-"
        print(f"| {temp} | {f.temperature_c:.1f} | "
              + " | ".join(f"{t[s]:.2f}" if s in t else "-" for s in stages)
              + f" | {fit_s:.2f} | {'-' if c is None else c.n_rows} | "
              f"{'-' if c is None else f'{c.rms_error_v * 1e3:.2f}'} | {taus} | "
              f"{'none' if f.i0.i0_a is None else f'{f.i0.i0_a:.2f}'} | {eq5} |", flush=True)


if __name__ == "__main__":
    main()
