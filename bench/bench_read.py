#!/usr/bin/env python3
"""Benchmark: how fast ``read_timeseries`` reads the shared measurement files (the timing
asserts that were in tests/test_measure.py: a test asserts behaviour, a bench measures).

Each file is read REPEAT times; the table gives the best time, the rows and the rows per
second. The bars the tests used to hold: a Panasonic .mat (about 100 k rows) under 2 s, the
CALCE CSV (26 k rows) under 1 s; the rows per second of the .mat and the CSV readers in one
run are the figures to compare.

    python bench/bench_read.py [--repeat 3] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FILES = ("panasonic-18650pf-25degC/hppc.mat", "panasonic-18650pf-25degC/us06.mat",
         "panasonic-18650pf-25degC/hwfet-a.mat", "panasonic-18650pf-25degC/ocv-c20.mat",
         "calce-a123-lfp/dynamics-dst-us06-fuds.csv", "calce-a123-lfp/ocv-charge-c22.csv",
         "nissan-leaf/NissanLeaf-cell-Low-Current-HPPC-25C-2.csv")


def main() -> None:
    from ecmgen.data.measure import read_timeseries

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args()
    print(f"{'file':50} {'rows':>8} {'best s':>8} {'rows/s':>10}")
    for name in FILES:
        path = args.data / name
        if not path.is_file():
            print(f"{name:50} (not found)")
            continue
        best, n = float("inf"), 0
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            n = len(read_timeseries(path))
            best = min(best, time.perf_counter() - t0)
        print(f"{name:50} {n:>8} {best:>8.3f} {n / best:>10.0f}")


if __name__ == "__main__":
    main()
