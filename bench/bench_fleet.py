"""Benchmark: `ecmgen fleet` throughput on a synthetic ageing study, with 1 and 2 Dask
workers on this machine, the memory per worker, and on paper the time for 10 000
check-ups on a 64-worker cluster.

A study of CELLS x CHECKUPS check-ups (ecmgen.diagnosis.synthstudy: a short pulse test,
a C/10 capacity test and a short drive cycle each; the five-point fits, no C) is built
into a fresh folder once per worker count (LocalCluster, single-threaded workers; no
trend plots). Builds per minute count the rows from the first submitted to the last one
back (the cluster's start and the fleet table apart, both printed). Memory per worker:
the largest peak resident set of a worker process after its builds (ru_maxrss). Then the
fleet runs again with nothing changed (what a resumed run pays per row that is done).

On paper: 10 000 check-ups on 64 workers take ceil(10 000 / 64) x the mean build time
of one row (its CPU time: what a core of its own takes), plus the cluster's start; the scheduler's own
cost (about 1 ms per task in Dask's documentation) runs beside the builds.

    nice -n 10 python bench/bench_fleet.py [--cells 8] [--checkups 3]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path


def run(manifest: Path, out: Path, workers: int) -> tuple:
    from ecmgen.fleet import run_fleet

    t0 = time.perf_counter()
    r = run_fleet(manifest, out, workers=workers, plots=False)
    return r, time.perf_counter() - t0


def per_worker_peak_mb(result) -> dict[str, float]:
    peak: dict[str, float] = {}
    for o in result.outcomes:
        if o.peak_rss_mb is not None:
            peak[o.worker] = max(peak.get(o.worker, 0.0), o.peak_rss_mb)
    return peak


def main(argv=None) -> int:
    from ecmgen.diagnosis.synthstudy import make_study, write_study

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=8)
    ap.add_argument("--checkups", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        manifest = write_study(make_study(args.cells, args.checkups, args.seed), tmp / "study")
        rows = args.cells * args.checkups
        size = sum(p.stat().st_size for p in (tmp / "study").rglob("*.csv")) / rows / 1e6
        print(f"study: {args.cells} cells x {args.checkups} check-ups = {rows} rows, "
              f"{size:.2f} MB of CSV per check-up, written in {time.perf_counter() - t0:.1f} s")
        print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} "
              "(other work on the machine slows both runs)")
        bpm, task_s, cpu_s = {}, {}, {}
        for w in (1, 2):
            r, wall = run(manifest, tmp / f"out-{w}", w)
            assert r.count("failed") == 0, r.as_dict()["failures"]
            bpm[w] = rows / r.rows_seconds * 60.0
            task_s[w] = [o.seconds for o in r.outcomes]
            cpu_s[w] = [o.cpu_seconds for o in r.outcomes]
            peak = per_worker_peak_mb(r)
            print(f"{w} worker{'s' if w > 1 else ' '}: {r.rows_seconds:6.1f} s for {rows} "
                  f"builds = {bpm[w]:5.1f} builds/min; per build {min(task_s[w]):.2f}.."
                  f"{max(task_s[w]):.2f} s (mean {sum(task_s[w]) / rows:.2f} s, CPU "
                  f"{sum(cpu_s[w]) / rows:.2f} s); "
                  f"run {wall:.1f} s with the cluster's start and the table; peak memory "
                  f"per worker {max(peak.values()):.0f} MB ({len(peak)} workers)")
            if w == 2:
                again, wall = run(manifest, tmp / f"out-{w}", w)
                assert again.count("unchanged") == rows
                print(f"  rerun, nothing changed: {rows} rows in {again.rows_seconds:.2f} s "
                      f"({again.rows_seconds / rows * 1e3:.0f} ms a row: hash and check), "
                      f"run {wall:.1f} s")
        ratio = bpm[2] / bpm[1]
        cpu = sum(cpu_s[1]) / rows
        print(f"scaling 1 -> 2 workers: x{ratio:.2f} (ideal x2.00); with a core each, a "
              f"build's CPU time ({cpu:.2f} s) gives {60 / cpu:.0f} builds/min per worker")
        mean = sum(cpu_s[1]) / rows
        waves = math.ceil(10_000 / 64)
        print(f"on paper, 10 000 check-ups on 64 workers (a core each): {waves} builds per "
              f"worker x {mean:.2f} s (the CPU time of a build) = {waves * mean / 60:.1f} min "
              f"of builds, plus "
              f"the cluster's start; the scheduler's ~1 ms a task (10 s in all) runs beside "
              f"them. A build of the bundled Panasonic example (about 60 s, the whole-test "
              f"fit) would take {waves * 60 / 3600:.1f} h.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
