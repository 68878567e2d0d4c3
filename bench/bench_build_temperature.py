"""Benchmark: `ecmgen build` over temperature from the four Panasonic pulse tests (25, 0,
-10, -20 degC; the bundled copies of the shared data, examples/panasonic-temperature), every
method, C included, validated on the eight drive cycles; one run, printed as a stage
breakdown (wall seconds).

  fit         the pulse tests on `--workers` processes (each: read, pulses, DC-IR, OCV,
              then every method), joined over temperature; per test below
  validate    every model on every cycle (each cycle read once)
  c           C generation and the host equivalence check of the best model
  plots       PNGs; write: model.json, DC-IR tables, report

Target: under 30 s on the 2-core machine.

Run:  python bench/bench_build_temperature.py [--workers 2] [--methods ga lm curve]
                                               [--no-c] [--no-plots] [--config CFG]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "panasonic-temperature" / "config.toml"


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
    ap.add_argument("--config", type=Path, default=EXAMPLE)
    args = ap.parse_args()
    cfg = load_config(args.config)
    cfg = replace(cfg, methods=tuple(args.methods),
                  best=cfg.best if cfg.best in args.methods else args.methods[-1],
                  c_numeric=() if args.no_c else cfg.c_numeric)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        result = build(cfg, Path(tmp) / "out", plots=not args.no_plots,
                       c_code=not args.no_c, workers=args.workers)
        total = time.perf_counter() - t0
    print(f"ecmgen build {args.config.name}, {len(cfg.pulse_tests)} pulse tests, methods "
          f"{' '.join(args.methods)}, {args.workers} worker(s), C "
          f"{'off' if args.no_c else '+'.join(cfg.c_numeric)}")
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
