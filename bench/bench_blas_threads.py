"""Benchmark: BLAS threads in the command line's process, one (as shipped) or one per
core (numpy's default, which the command line no longer takes), measured as a lab or a
`make -j` runs ecmgen: ``--jobs`` runs of `ecmgen diagnose` on the bundled one-temperature
example side by side, then one alone. Printed: wall time of the batch and CPU time
(user + system of every process), each setting's best of ``--repeat``, the settings
taking turns.

    python bench/bench_blas_threads.py [--jobs 4] [--repeat 1]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ecmgen.fleet.run import cores as usable_cores
from ecmgen.parallel import ONE_BLAS_THREAD

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "panasonic-25degC" / "config.toml"
ECMGEN = Path(sys.executable).with_name("ecmgen")


def _cpu_of_children() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def _batch(jobs: int, threads: str, folder: Path) -> tuple[float, float]:
    env = {k: v for k, v in os.environ.items() if k not in ONE_BLAS_THREAD}
    if threads != "as shipped":
        env.update({k: threads for k in ONE_BLAS_THREAD})
    cpu0, t0 = _cpu_of_children(), time.perf_counter()
    runs = [subprocess.Popen([str(ECMGEN), "diagnose", str(EXAMPLE), "--out",
                              str(folder / f"run{i}"), "-q", "--no-plots"], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for i in range(jobs)]
    if any(run.wait() for run in runs):
        sys.exit("bench_blas_threads: a diagnose run failed")
    return time.perf_counter() - t0, _cpu_of_children() - cpu0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    cores = usable_cores()
    settings = ("as shipped", str(cores))
    best: dict[tuple[str, int], tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeat):
            for jobs in (args.jobs, 1):
                for threads in settings:
                    folder = Path(tmp) / f"{threads}-{jobs}"
                    wall, cpu = _batch(jobs, threads, folder)
                    shutil.rmtree(folder, ignore_errors=True)
                    old = best.get((threads, jobs), (float("inf"), float("inf")))
                    best[(threads, jobs)] = (min(old[0], wall), min(old[1], cpu))
    print(f"`ecmgen diagnose` on {EXAMPLE.parent.name}, {cores} cores")
    print(f"{'BLAS threads':<22} {'runs':>4} {'wall s':>8} {'CPU s':>8} {'wall ratio':>10}")
    for jobs in (args.jobs, 1):
        shipped = best[("as shipped", jobs)][0]
        for threads in settings:
            wall, cpu = best[(threads, jobs)]
            name = "1 (as shipped)" if threads == "as shipped" else f"{threads} (numpy's default)"
            print(f"{name:<22} {jobs:>4} {wall:>8.1f} {cpu:>8.1f} {wall / shipped:>10.2f}")


if __name__ == "__main__":
    main()
