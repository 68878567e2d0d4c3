"""Acceptance: the fit on the real cells of ../shared/data, with the table checks.

Builds (no C, no plots) the bundled Panasonic 18650PF demo (25, 0, -10, -20 degC, eight drive
cycles) and the Nissan Leaf from both shared HPPC files (tests/data/nissan-leaf/config.toml,
25 and 40 degC, no validation cycle: no file records the cell's temperature while cycling)
and the A123 LFP cell from its four OCV files and a dynamic test (examples/a123-dynamic),
and prints per cell and method the table quality (ecmgen.fit.quality: roughness, values
<= 0, time constants on a bound) and the validation MAE per cycle (overall, above 10 % SOC).

    python bench/real_cells.py [--cells panasonic,leaf,a123]

Done-when of the fit: roughness <= 0.5, no value <= 0, every time constant on a bound said.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CELLS = {
    "panasonic": REPO / "examples" / "panasonic-temperature" / "config.toml",
    "leaf": REPO / "tests" / "data" / "nissan-leaf" / "config.toml",
    "a123": REPO / "examples" / "a123-dynamic" / "config.toml",
}


def _above_10(v) -> str:
    """The MAE above 10 % SOC (simulated), or '-' where the cycle never gets there."""
    m = v.soc_above_10.mae_v
    return f"{1e3 * m:.1f} above 10 % SOC" if m == m else "never above 10 % SOC"


def main(argv=None) -> int:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default=",".join(CELLS))
    args = ap.parse_args(argv)
    print(f"{'cell':10s} {'method':6s} {'rough':>6s} {'<=0':>4s} {'on bound':28s} "
          f"{'fit s':>6s}  cycle MAE mV")
    for name in args.cells.split(","):
        cfg = load_config(CELLS[name])
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            result = build(cfg, Path(tmp) / "out", plots=False, c_code=False)
        secs = time.perf_counter() - t0
        for method, q in result.quality.items():
            maes = " ".join(f"{label}: {1e3 * v.overall.mae_v:.1f} "
                            f"({_above_10(v)})"
                            for label, v in result.validations.get(method, {}).items())
            print(f"{name:10s} {method:6s} {q.roughness:6.2f} {q.non_positive:4d} "
                  f"{', '.join(q.on_bound) or '-':28s} {secs:6.1f}  {maes or '-'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
