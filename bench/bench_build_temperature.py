"""Benchmark: `ecmgen build` over temperature from the four shared pulse tests (25, 0, -10,
-20 degC), every method, C included, validated on the eight shared drive cycles; one run,
printed as a stage breakdown (wall seconds).

  fit         the pulse tests on `--workers` processes (each: read, pulses, DC-IR, OCV,
              then every method), joined over temperature; per test below
  validate    every model on every cycle (each cycle read once)
  c           C generation and the host equivalence check of the best model
  plots       PNGs; write: model.json, DC-IR tables, report

Target (issue 8): under 30 s on the 2-core machine.

Run:  python bench/bench_build_temperature.py [--workers 2] [--methods ga lm curve]
                                               [--no-c] [--no-plots]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from shared_temperature import write_config  # noqa: E402


def main() -> int:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build
    from ecmgen.report import validation_table

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--methods", nargs="+", default=["ga", "lm", "curve"])
    ap.add_argument("--no-c", action="store_true")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--table", action="store_true", help="also print the validation table")
    ap.add_argument("--config-extra", default="", help="TOML appended to the config")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cfg_path = write_config(Path(tmp) / "cell.toml", methods=tuple(args.methods),
                                c_numeric=() if args.no_c else ("float", "fixed"),
                                extra=args.config_extra.replace("\\n", "\n"))
        cfg = load_config(cfg_path)
        t0 = time.perf_counter()
        result = build(cfg, Path(tmp) / "out", plots=not args.no_plots,
                       c_code=not args.no_c, workers=args.workers)
        total = time.perf_counter() - t0
    print(f"ecmgen build, 4 pulse tests, methods {' '.join(args.methods)}, "
          f"{args.workers} worker(s), C {'off' if args.no_c else 'float+fixed'}")
    print(f"{'stage':<34} {'s':>7}")
    for stage, s in result.timings.items():
        print(f"{stage:<34} {s:7.2f}")
    print(f"{'total':<34} {total:7.2f}   (target < 30 s)")
    print()
    steps = list(dict.fromkeys(k for t in result.tests for k in t.timings))
    print(f"{'pulse test':<12} " + " ".join(f"{k[:24]:>24}" for k in steps) + f" {'total':>7}")
    for t in result.tests:
        print(f"{t.label:<12} " + " ".join(f"{t.timings.get(k, 0.0):24.2f}" for k in steps) +
              f" {t.seconds:7.2f}")
    busy = sum(t.seconds for t in result.tests)
    print(f"sum over tests {busy:.2f} s in {result.timings['fit']:.2f} s of fit wall time "
          f"({busy / result.timings['fit']:.2f} processes busy on average)")
    if args.table:
        print()
        print(validation_table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
