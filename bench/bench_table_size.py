"""Flash of the tables against accuracy: what coarser grids and 16-bit storage would cost.

Builds the bundled Panasonic demo (no C, no plots), then for each option changes the best
model's tables the way the option would store them and re-runs every validation cycle
(simulate.py at the cycle's cell temperature, from its start SOC) against the measured
voltage:

- ``ocv/2``, ``ocv/4``     the OCV on every 2nd / 4th SOC breakpoint (ends kept);
- ``rc/2``                 the RC tables on every 2nd SOC breakpoint;
- ``16-bit affine``        every table value stored as an unsigned 16-bit code with a
                           per-table offset and scale (rounded to the nearest code);
- ``float16``              every table value rounded to IEEE binary16.

Table bytes are the generated C's (``describe(prepare(...))``, float and fixed) for the grid
options; for the 16-bit storage options they are estimated as half of the value arrays
(the grids stay 32-bit). Nothing here is an option of ``ecmgen build`` yet: this measures
whether one is worth having.

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
RC_EXTRA = ("fit_error", "converged")


def _every(x: np.ndarray, k: int) -> np.ndarray:
    idx = np.arange(0, x.shape[-1], k)
    if idx[-1] != x.shape[-1] - 1:
        idx = np.append(idx, x.shape[-1] - 1)
    return idx


def coarse_ocv(m, k: int):
    idx = _every(m.ocv.soc, k)
    return replace(m, ocv=replace(m.ocv, soc=m.ocv.soc[idx], ocv_v=m.ocv.ocv_v[:, idx]))


def coarse_rc(m, k: int):
    def one(t):
        idx = _every(t.soc, k)
        return replace(t, soc=t.soc[idx], **{f: getattr(t, f)[:, idx] for f in RC_FIELDS + RC_EXTRA})
    return replace(m, charge=one(m.charge), discharge=one(m.discharge))


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
    rows = [("ocv/2", coarse_ocv(model, 2), None), ("ocv/4", coarse_ocv(model, 4), None),
            ("rc/2", coarse_rc(model, 2), None),
            ("16-bit affine", stored(model, _q16), "half"), ("float16", stored(model, _f16), "half")]
    for name, m, how in rows:
        mae = mean_mae(m, vals)
        if how == "half":
            value_bytes = {n: b0[n] - _grid_bytes(model, n) for n in b0}
            b = {n: b0[n] - value_bytes[n] // 2 for n in b0}
        else:
            b = table_bytes(m)
        print(f"{name:16s} {b['float']:8d} {b['fixed']:8d} {1e3 * mae:12.3f} {1e3 * (mae - base):+9.3f}")
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
