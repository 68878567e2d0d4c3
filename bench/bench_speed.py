"""Build and fit time and peak memory, against a committed baseline.

    python bench/bench_speed.py [--only NAME,...] [--repeat N] [--check BASELINE]
                                [--update BASELINE] [--json PATH]

Cases, each run as the command line runs it (a fresh process, one BLAS thread):

- ``demo``: ``ecmgen build examples/panasonic-temperature/config.toml`` (four pulse tests,
  every method, eight cycles, plots, C; 2 worker processes). The C cache is warmed by one
  untimed build first, as a user's second build finds it.
- ``fit25``: ``ecmgen fit`` of the 25 degC Panasonic pulse test alone with the whole-test
  fit (``pulses``, ``pulses_soc0 = 1``, OCV from its rests, ``methods = ["curve"]``).
- ``a123``: ``ecmgen build examples/a123-dynamic/config.toml`` (OCV files, the dynamic
  test, two cycles, plots, C).

The machine is shared, so a wall time alone says little: each case is timed as a ratio to a
reference computation measured in the same run just before and after it (a fixed numpy
matrix product and solve loop on one thread, about 2 s on an idle core); the ratio is what
is compared. CPU seconds and peak memory are sampled every 50 ms (psutil, with the test extras) over the
command's process and every process under it: the largest sum of their resident memory
and the largest single process's, which do not depend on the load and are compared as
they are. ``--check`` exits 1 when a case's time ratio or peak memory is more than 25 %
above the baseline's; ``--update`` writes the baseline (bench/baseline/speed.json). The
shared data: ../shared/data beside the repository, or $ECMGEN_SHARED_DATA.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ECMGEN_SHARED_DATA") or REPO.parent / "shared" / "data")
BASELINE = REPO / "bench" / "baseline" / "speed.json"
TOLERANCE = 0.25
ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
FIT25 = """[cell]
capacity_ah = 2.9
[data]
pulses = {pulses}
pulses_soc0 = 1.0
ocv = "pulses"
[fit]
methods = ["curve"]
"""
REFERENCE = """
import time, numpy as np
rng = np.random.default_rng(0)
a = rng.standard_normal((400, 400)); a = a @ a.T + 400 * np.eye(400)
b = rng.standard_normal((400, 20))
t = time.perf_counter()
for _ in range(240):
    x = np.linalg.solve(a, b)
    c = a @ a
    a = 0.5 * (c / np.linalg.norm(c) * 400 + a)
print(time.perf_counter() - t)
"""


def _env() -> dict:
    env = dict(os.environ, **ONE_THREAD)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src")] + ([env["PYTHONPATH"]]
                                                             if env.get("PYTHONPATH") else []))
    return env


def reference_s() -> float:
    """Wall seconds of the reference computation (in a fresh process, one BLAS thread)."""
    out = subprocess.run([sys.executable, "-c", REFERENCE], capture_output=True, text=True,
                         env=_env(), check=True)
    return float(out.stdout.strip())


def _tree(pid: int) -> list:
    import psutil

    try:
        proc = psutil.Process(pid)
        return [proc] + proc.children(recursive=True)
    except psutil.Error:
        return []


def run_command(args: list[str], cwd: Path) -> dict:
    """Run ``python -m ecmgen.cli ARGS``: wall seconds; CPU seconds and the peak of the
    summed resident memory of its process and every process under it (sampled every 50 ms:
    a build's workers are forked from a fork server, whose CPU the kernel never hands back
    to this process), and the largest single process's memory, in MB."""
    import psutil

    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "ecmgen.cli", *args], cwd=cwd, env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak, largest, cpu = [0], [0], {}

    def sample():
        while proc.poll() is None:
            total = 0
            for p in _tree(proc.pid):
                try:
                    with p.oneshot():
                        rss = p.memory_info().rss
                        t = p.cpu_times()
                except psutil.Error:
                    continue
                total += rss
                largest[0] = max(largest[0], rss)
                cpu[(p.pid, p.create_time())] = t.user + t.system
            peak[0] = max(peak[0], total)
            time.sleep(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    _, err = proc.communicate()
    wall = time.perf_counter() - t0
    sampler.join()
    if proc.returncode != 0:
        raise SystemExit(f"bench_speed: ecmgen {' '.join(args)} failed:\n{err}")
    return {"wall_s": wall, "cpu_s": sum(cpu.values()), "peak_mb": peak[0] / 1e6,
            "largest_process_mb": largest[0] / 1e6}


def cases(tmp: Path) -> dict:
    """Name -> (ecmgen arguments, whether to warm the C cache with one untimed run)."""
    fit25 = tmp / "fit25.toml"
    pulses = DATA / "panasonic-18650pf-25degC" / "hppc.mat"
    fit25.write_text(FIT25.format(pulses=json.dumps(str(pulses))))
    return {
        "demo": (["build", str(REPO / "examples" / "panasonic-temperature" / "config.toml"),
                  "--out", str(tmp / "demo-out"), "-q"], True),
        "fit25": (["fit", str(fit25), "--out", str(tmp / "fit25.json"), "-q"], False),
        "a123": (["build", str(REPO / "examples" / "a123-dynamic" / "config.toml"),
                  "--out", str(tmp / "a123-out"), "-q"], True),
    }


def measure(names: list[str], repeat: int, progress=print) -> dict:
    """Each case ``repeat`` times, each run between two reference runs; the best ratio."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        table = cases(tmp)
        for name in names:
            args, warm = table[name]
            if warm:
                run_command(args, tmp)
            best = None
            for _ in range(repeat):
                ref0 = reference_s()
                got = run_command(args, tmp)
                ref = 0.5 * (ref0 + reference_s())
                got.update(reference_s=ref, ratio=got["wall_s"] / ref)
                if best is None or got["ratio"] < best["ratio"]:
                    best = got
            out[name] = {k: (round(v, 3) if isinstance(v, float) else v)
                         for k, v in best.items()}
            progress(f"{name}: {best['wall_s']:.2f} s wall ({best['ratio']:.2f} x the "
                     f"reference {best['reference_s']:.2f} s), {best['cpu_s']:.2f} s CPU")
    return out


def table(results: dict, baseline: dict | None) -> str:
    rows = [("| case | wall s | CPU s | reference s | ratio | baseline ratio | peak MB "
             "(tree) | largest process MB | baseline peak MB |"),
            "|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        b = (baseline or {}).get("cases", {}).get(name, {})
        peak = f"{r['peak_mb']:.0f}"
        rows.append(f"| {name} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | {r['reference_s']:.2f} "
                    f"| {r['ratio']:.2f} | {b.get('ratio', '-')} | {peak} | "
                    f"{r['largest_process_mb']:.0f} | {b.get('peak_mb', '-')} |")
    return "\n".join(rows)


def worse(results: dict, baseline: dict) -> list[str]:
    """Each case whose time ratio or peak memory is above the baseline's by more than 25 %."""
    out = []
    for name, r in results.items():
        b = baseline.get("cases", {}).get(name)
        if b is None:
            out.append(f"{name}: not in the baseline")
            continue
        for key, what in (("ratio", "time ratio"), ("peak_mb", "peak memory MB"),
                          ("largest_process_mb", "largest process MB")):
            if b.get(key) is not None and r.get(key) is not None and \
                    r[key] > (1.0 + TOLERANCE) * b[key]:
                out.append(f"{name} {what}: {r[key]:.2f} against baseline {b[key]:.2f}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="NAME[,NAME...] of demo, fit25, a123 (default: all)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per case (the best counts)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--check", type=Path, help="exit 1 on a case 25 %% worse than this baseline")
    ap.add_argument("--update", type=Path, help="write the results as this baseline")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else ["demo", "fit25", "a123"]
    unknown = [n for n in names if n not in ("demo", "fit25", "a123")]
    if unknown:
        print(f"bench_speed: unknown case {', '.join(unknown)}", file=sys.stderr)
        return 2
    if not DATA.is_dir():
        print(f"bench_speed: no shared data at {DATA} (set ECMGEN_SHARED_DATA)",
              file=sys.stderr)
        return 2
    baseline = None
    if args.check is not None:
        try:
            baseline = json.loads(args.check.read_text())
        except (OSError, ValueError) as exc:
            print(f"{args.check}: not a speed baseline ({exc})", file=sys.stderr)
            return 2
    load = os.getloadavg()[0]
    results = measure(names, max(1, args.repeat),
                      lambda m: print(m, file=sys.stderr, flush=True))
    print(table(results, baseline))
    print(f"\nload average {load:.1f} before, {os.getloadavg()[0]:.1f} after, "
          f"{os.cpu_count()} cores")
    doc = {"note": "bench/bench_speed.py: ratio = wall / the reference computation's wall "
                   "in the same run; memory in MB", "cases": results}
    if args.json is not None:
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    if args.update is not None:
        old = {}
        if args.update.exists():
            old = json.loads(args.update.read_text()).get("cases", {})
        doc["cases"] = {**old, **results}
        args.update.parent.mkdir(parents=True, exist_ok=True)
        args.update.write_text(json.dumps(doc, indent=1) + "\n")
    if baseline is not None:
        bad = worse(results, baseline)
        if bad:
            print("more than 25 % worse than the baseline:\n  " + "\n  ".join(bad),
                  file=sys.stderr)
            return 1
        print(f"no case more than 25 % worse than {args.check}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
