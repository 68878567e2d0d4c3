"""Benchmark: which engine runs the independent tasks of one build -- the standard
library's process pool (ecmgen.parallel, as is), Dask's local scheduler, or a
dask.distributed LocalCluster -- measured on the build over temperature of the bundled
example (examples/panasonic-temperature: four pulse tests, eight drive cycles; every
method, plots, no C), 2 processes each.

  pool         ecmgen.parallel.Workers: a spawned concurrent.futures pool (as shipped)
  distributed  the same Workers with its pool swapped for a LocalCluster's executor
               (Client.get_executor; the cluster's start counted)
  dask local   Dask's local multiprocessing scheduler (dask.compute(scheduler=
               "processes"); itself a concurrent.futures process pool underneath) on the
               four pulse-test fits, the build's largest stage, beside the other two on
               the same four tasks
  serial       workers=1, for reference

Each variant runs ``--repeat`` times, the engines taking turns; printed are the best wall
time and the least CPU time (user + system of every process, the workers included: what
the engine costs whatever else runs on the machine).

    nice -n 10 python bench/bench_parallel_engine.py [--repeat 2]
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "panasonic-temperature" / "config.toml"


class DistributedWorkers:
    """ecmgen.parallel.Workers on a dask.distributed LocalCluster (its executor)."""

    def __new__(cls, processes: int = 2):
        from ecmgen.parallel import Workers

        class _W(Workers):
            def _start(self):
                from distributed import Client, LocalCluster

                self._cluster = LocalCluster(n_workers=self.processes, threads_per_worker=1,
                                             dashboard_address=None,
                                             silence_logs=logging.ERROR)
                self._client = Client(self._cluster)
                self._pool = self._client.get_executor()

            def close(self):
                if self._pool is not None:
                    self._client.close()
                    self._cluster.close()
                    self._pool = None

        return _W(processes)


def cpu_seconds() -> float:
    """User + system CPU of this process and of its ended (waited-for) descendants."""
    import resource

    me, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF,
                                                resource.RUSAGE_CHILDREN))
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def build_once(cfg, workers) -> tuple[float, float, dict]:
    """(wall s, CPU s of every process, the build's stage timings)."""
    from ecmgen.pipeline import build

    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), cpu_seconds()
        r = build(cfg, Path(tmp) / "out", plots=True, c_code=False, workers=workers)
        return time.perf_counter() - t0, cpu_seconds() - c0, r.timings


def whole_build(cfg, engine: str) -> tuple[float, float, dict]:
    import ecmgen.pipeline as pipeline
    from ecmgen.parallel import Workers

    if engine == "serial":
        return build_once(cfg, 1)
    if engine == "pool":
        return build_once(cfg, 2)
    original = pipeline._workers_for
    pipeline._workers_for = lambda c, w: DistributedWorkers(2)
    try:
        return build_once(cfg, 2)
    finally:
        pipeline._workers_for = original
        assert Workers is not None


def fits_only(cfg, engine: str) -> tuple[float, float]:
    """The four pulse-test fits alone (wall s, CPU s): the pool (Workers.map), Dask's
    local scheduler (dask.compute) or a LocalCluster (its executor)."""
    from ecmgen.parallel import Workers, run_collected
    from ecmgen.pipeline import fit_pulse_test

    n = len(cfg.pulse_tests)
    t0, c0 = time.perf_counter(), cpu_seconds()
    if engine in ("pool", "distributed"):
        with (Workers(2) if engine == "pool" else DistributedWorkers(2)) as w:
            w.map(fit_pulse_test, [(cfg, k) for k in range(n)])
    else:
        import dask

        tasks = [dask.delayed(run_collected)(fit_pulse_test, (cfg, k)) for k in range(n)]
        dask.compute(*tasks, scheduler="processes", num_workers=2)
    return time.perf_counter() - t0, cpu_seconds() - c0


def main(argv=None) -> int:
    from ecmgen.config import load_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args(argv)
    cfg = load_config(EXAMPLE)
    cfg = replace(cfg, c_numeric=())
    print(f"build {EXAMPLE.relative_to(REPO)}: {len(cfg.pulse_tests)} pulse tests, plots, "
          f"no C; best of {args.repeat}, the engines taking turns; load average "
          f"{os.getloadavg()[0]:.1f}")
    builds: dict[str, list] = {e: [] for e in ("pool", "distributed", "serial")}
    fits: dict[str, list] = {e: [] for e in ("pool", "dask local", "distributed")}
    for _ in range(args.repeat):
        for engine in builds:
            builds[engine].append(whole_build(cfg, engine))
        for engine in fits:
            fits[engine].append(fits_only(cfg, engine))
    for engine, runs in builds.items():
        wall, cpu, stages = min(runs, key=lambda r: r[0])
        parts = ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
        print(f"  whole build, {engine:<12} {wall:6.1f} s, CPU {min(r[1] for r in runs):6.1f} "
              f"s  (wall of each: {' '.join(f'{r[0]:.1f}' for r in runs)}; the best's "
              f"stages: {parts})")
    for engine, runs in fits.items():
        print(f"  four fits,   {engine:<12} {min(r[0] for r in runs):6.1f} s, CPU "
              f"{min(r[1] for r in runs):6.1f} s  (wall of each: "
              f"{' '.join(f'{r[0]:.1f}' for r in runs)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
