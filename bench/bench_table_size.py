"""Flash of the tables against accuracy: the build's table options and 16-bit storage.

Builds the bundled Panasonic demo (no C, no plots), then for each option changes the best
model's tables the way the option stores them and re-runs every validation cycle
(simulate.py at the cycle's cell temperature, from its start SOC; the generated C equals it
to float32 rounding) against the measured voltage:

- ``[c] ocv_soc_step = n`` / ``rc_soc_step = n``  options of ``ecmgen build`` (and
  ``codegen --ocv-soc-step / --rc-soc-step``): the C's tables on every n-th SOC breakpoint,
  ends kept (ecmgen.c.spec.coarsen_tables, the function the build uses); table bytes of the
  C as generated;
- ``16-bit affine``        (not built) every table value as an unsigned 16-bit code with a
                           per-table offset and scale (rounded to the nearest code);
- ``float16``              (not built) every table value rounded to IEEE binary16;
  their bytes estimated as half of the value arrays (the grids stay 32-bit).

    python bench/bench_table_size.py
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "examples" / "panasonic-temperature" / "config.toml"
RC_FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")


def _q16(a: np.ndarray) -> np.ndarray:
    lo, hi = float(np.min(a)), float(np.max(a))
    if hi == lo:
        return a
    step = (hi - lo) / 65535.0
    return lo + np.round((a - lo) / step) * step


def _f16(a: np.ndarray) -> np.ndarray:
    return a.astype(np.float16).astype(np.float64)


def stored(m, fn):
    def one(t):
        return replace(t, **{f: fn(np.asarray(getattr(t, f), dtype=np.float64)) for f in RC_FIELDS})
    return replace(m, ocv=replace(m.ocv, ocv_v=fn(np.asarray(m.ocv.ocv_v, dtype=np.float64))),
                   charge=one(m.charge), discharge=one(m.discharge))


def mean_mae(model, vals) -> float:
    from ecmgen.model.simulate import simulate

    maes = []
    for v in vals.values():
        temps = getattr(v, "temperature_c", None)
        if temps is not None:
            temps = np.broadcast_to(np.asarray(temps, dtype=np.float64), np.shape(v.sim.time_s))
        vv = simulate(model, v.sim.time_s, v.sim.current_a, v.soc0, temps).voltage_v
        maes.append(float(np.mean(np.abs(vv - np.asarray(v.measured_v)))))
    return float(np.mean(maes))


def table_bytes(model) -> dict:
    from ecmgen.c.codegen import describe, prepare

    return {n: describe(prepare(model, numeric=n))["table_bytes"] for n in ("float", "fixed")}


def main() -> int:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    cfg = load_config(CONFIG)
    with tempfile.TemporaryDirectory() as tmp:
        result = build(cfg, Path(tmp) / "out", plots=False, c_code=False)
    model = result.models[result.best]
    vals = result.validations[result.best]
    base = mean_mae(model, vals)
    b0 = table_bytes(model)
    print(f"demo model '{result.best}', {len(vals)} validation cycles; mean MAE {1e3 * base:.3f} mV; "
          f"tables float {b0['float']} B, fixed {b0['fixed']} B")
    print(f"{'option':16s} {'float B':>8s} {'fixed B':>8s} {'mean MAE mV':>12s} {'delta mV':>9s}")
    from ecmgen.c.spec import coarsen_tables

    opts = [("ocv_soc_step = 2", 2, 1), ("ocv_soc_step = 4", 4, 1), ("ocv_soc_step = 8", 8, 1),
            ("rc_soc_step = 2", 1, 2), ("ocv 4 + rc 2", 4, 2)]
    rows = [(name, coarsen_tables(model, o, r), None) for name, o, r in opts]
    rows += [("16-bit affine *", stored(model, _q16), "half"),
             ("float16 *", stored(model, _f16), "half")]
    for name, m, how in rows:
        mae = mean_mae(m, vals)
        if how == "half":
            value_bytes = {n: b0[n] - _grid_bytes(model, n) for n in b0}
            b = {n: b0[n] - value_bytes[n] // 2 for n in b0}
        else:
            b = table_bytes(m)
        print(f"{name:16s} {b['float']:8d} {b['fixed']:8d} {1e3 * mae:12.3f} {1e3 * (mae - base):+9.3f}")
    print("* not an option of ecmgen build: bytes estimated")
    return 0


def _grid_bytes(model, numeric: str) -> int:
    """Bytes of the breakpoint and spacing arrays (they keep 32 bits)."""
    from ecmgen.c.codegen import prepare

    spec = prepare(model, numeric=numeric)
    grids = [spec.ocv_grid] + [d.grid for d in spec.dirs] + ([spec.temp_grid] if spec.temp else [])
    n = 0
    for g in grids:
        x = getattr(g, "x", None)
        if x is not None:
            n += 8 * len(x)
    return n


if __name__ == "__main__":
    sys.exit(main())
