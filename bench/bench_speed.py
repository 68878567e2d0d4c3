"""Build and fit time and peak memory, now against a reference checkout measured in the same
run, as ratios against a committed baseline.

    python bench/bench_speed.py [--ref REF] [--only NAME,...] [--repeat N]
                                [--check [BASELINE]] [--update [BASELINE]] [--json PATH]

Cases (each one command line, run in a fresh process from the tree measured, the inputs the
same for both trees: this tree's example configs and the shared data):

- ``demo``: ``ecmgen build examples/panasonic-temperature/config.toml --out DIR`` as
  ``make demo`` runs it (plots and C; the C compiler's cache warm after the first run).
- ``fit25``: ``ecmgen fit examples/panasonic-25degC/config.toml --method curve``, the
  one-temperature whole-test fit of the 25 degC HPPC test.
- ``a123``: ``ecmgen build examples/a123-dynamic/config.toml`` (its shared-data paths made
  absolute), the largest memory of the examples.

The reference is a git worktree of REF (default: the baseline's reference, the commit before
the speed work) made in a temporary folder and removed after. Each round runs every case for
the reference and for this tree, the order alternating round to round (so a cold cache or a
busy neighbour falls on both); of ``--repeat`` rounds, each time is the least (the load
adds to it) and each memory the largest (the demo's workers overlap more or less from run
to run, and its summed PSS with them). Figures:
wall seconds; the largest process's peak resident memory (the kernel's high-water mark,
VmHWM, of every process of the run, the fork server's workers too); the whole run's peak
proportional set size (PSS summed over its processes, sampled every 0.1 s: forked workers'
shared pages counted once); CPU seconds of every process (sampled, shown, not gated).
``--check`` exits 1 when a ratio now / ref of the first three is worse than the baseline's
ratio by more than 25 %: ratios, not seconds, since machines differ; a ratio is measured in
one run, both sides under the same load. ``--update`` writes the baseline
(bench/baseline/speed.json; docs/make_docs.py shows it in docs/results.md).

The shared data: ../shared/data beside the repository, or $ECMGEN_SHARED_DATA.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ECMGEN_SHARED_DATA") or REPO.parent / "shared" / "data")
BASELINE = REPO / "bench" / "baseline" / "speed.json"
# the commit before the speed work (the fit's accuracy re-baselined): the reference
DEFAULT_REF = "e681728c8f9c56deef698c3648c2ba64980e30f2"
TOLERANCE = 0.25            # a ratio worse than the baseline's by more than this fails
GATED = ("wall_s", "peak_mb", "pss_mb")
MEMORY = ("peak_mb", "pss_mb")  # the largest of the rounds; the times the least
FIGURES = (*GATED, "cpu_s")     # CPU seconds: sampled, shown, not gated
SAMPLE_S = 0.1
TICKS = os.sysconf("SC_CLK_TCK")
A123_DATA = "../../../shared/data/plett-a123-lfp"


@dataclass(frozen=True)
class Case:
    name: str
    config: Path
    argv: tuple[str, ...]       # after the config; --out DIR added


def cases() -> dict[str, Case]:
    ex = REPO / "examples"
    out = [Case("demo", ex / "panasonic-temperature" / "config.toml", ("build",)),
           Case("fit25", ex / "panasonic-25degC" / "config.toml", ("fit", "--method", "curve")),
           Case("a123", ex / "a123-dynamic" / "config.toml", ("build",))]
    return {c.name: c for c in out}


def config_for(case: Case, tmp: Path) -> Path:
    """The case's config; for the A123 a copy with its shared-data paths absolute."""
    if case.name != "a123":
        return case.config
    text = case.config.read_text()
    if A123_DATA not in text:
        raise SystemExit(f"{case.config}: {A123_DATA!r} not found")
    path = tmp / "a123.toml"
    path.write_text(text.replace(A123_DATA, str(DATA / "plett-a123-lfp")))
    return path


def _session(sid: int) -> dict[tuple[int, int], float]:
    """The processes of session ``sid`` (the run and every process it started, a fork
    server's workers too, which are not the run's children): {(pid, start): CPU seconds}."""
    pids = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            stat = Path(entry.path, "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[3]) == sid:          # after the name: state ppid pgrp session ...
            cpu = (int(fields[11]) + int(fields[12])) / TICKS      # utime + stime
            pids[(int(entry.name), int(fields[19]))] = cpu          # by pid and start time
    return pids


def _status_kb(pid: int, key: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _pss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def measure(cmd: list[str], env: dict[str, str], log: Path) -> dict:
    """One run of ``cmd``: wall seconds, the largest process's peak RSS and the run's
    peak summed PSS, in MB."""
    hwm: dict[int, int] = {}
    cpu: dict[tuple[int, int], float] = {}
    pss_peak = 0
    with open(log, "w") as fh:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                wall = time.perf_counter() - t0
                break
            pss = 0
            seen = _session(proc.pid)
            cpu.update(seen)
            for p, _ in seen:
                hwm[p] = max(hwm.get(p, 0), _status_kb(p, "VmHWM"))
                pss += _pss_kb(p)
            pss_peak = max(pss_peak, pss)
            time.sleep(SAMPLE_S)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {proc.returncode}\n{log.read_text()[-3000:]}")
    peak_kb = max([usage.ru_maxrss, *hwm.values()])     # the run's own, after it ended too
    own = usage.ru_utime + usage.ru_stime       # the run's and its reaped children's
    return {"wall_s": round(wall, 2), "peak_mb": round(peak_kb / 1024, 1),
            "pss_mb": round(pss_peak / 1024, 1),
            "cpu_s": round(max(own, sum(cpu.values())), 1)}


def tree_env(src: Path) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(src), ECMGEN_SHARED_DATA=str(DATA))
    found = subprocess.run([sys.executable, "-c", "import ecmgen; print(ecmgen.__file__)"],
                           env=env, capture_output=True, text=True, check=True).stdout.strip()
    if not Path(found).resolve().is_relative_to(src.resolve()):
        raise SystemExit(f"ecmgen from {found}, not from {src}")
    return env


def run(names: list[str], ref_tree: Path, repeat: int, progress=print) -> dict:
    """Every named case for the reference and this tree, ``repeat`` rounds: the least of
    each time, the largest of each memory."""
    trees = {"ref": tree_env(ref_tree / "src"), "now": tree_env(REPO / "src")}
    best: dict[str, dict[str, dict]] = {n: {} for n in names}
    with tempfile.TemporaryDirectory(prefix="bench-speed-") as tmp:
        tmp = Path(tmp)
        for k in range(repeat):
            order = ("ref", "now") if k % 2 == 0 else ("now", "ref")
            for name in names:
                case = cases()[name]
                config = config_for(case, tmp)
                for side in order:
                    out = tmp / f"out-{name}-{side}"
                    shutil.rmtree(out, ignore_errors=True)
                    cmd = [sys.executable, "-m", "ecmgen.cli", case.argv[0], str(config),
                           *case.argv[1:], "--out", str(out), "-q"]
                    fig = measure(cmd, trees[side], tmp / f"{name}-{side}.log")
                    progress(f"round {k + 1} {name} {side}: {fig['wall_s']:.1f} s, "
                             f"peak {fig['peak_mb']:.0f} MB, PSS {fig['pss_mb']:.0f} MB")
                    old = best[name].get(side)
                    best[name][side] = fig if old is None else \
                        {f: (max if f in MEMORY else min)(old[f], fig[f]) for f in fig}
    return {n: {**sides, "ratio": {f: round(sides["now"][f] / sides["ref"][f], 3)
                                   for f in FIGURES}} for n, sides in best.items()}


def table(results: dict, ref: str) -> str:
    head = ("| case | wall s ref | now | now/ref | peak RSS MB ref | now | now/ref "
            "| peak PSS MB ref | now | now/ref | CPU s ref | now | now/ref |\n|---|"
            + "---|" * 12 + "\n")
    rows = []
    for name, r in results.items():
        cells = []
        for f in FIGURES:
            digits = 0 if f.endswith("_mb") else 1
            cells += [f"{r['ref'][f]:.{digits}f}", f"{r['now'][f]:.{digits}f}",
                      f"{r['ratio'][f]:.2f}"]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return head + "\n".join(rows) + (f"\n\n(ref: {ref[:12]}; the least time and the largest "
                                      "memory of the rounds)\n")


def worse(results: dict, baseline: dict) -> list[str]:
    out = []
    for name, r in results.items():
        base = baseline["cases"].get(name)
        if base is None:
            out.append(f"{name}: not in the baseline")
            continue
        for f in GATED:
            bound = base["ratio"][f] * (1 + TOLERANCE)
            if r["ratio"][f] > bound:
                out.append(f"{name} {f}: now/ref {r['ratio'][f]:.3f} against baseline "
                           f"{base['ratio'][f]:.3f} (bound {bound:.3f})")
    return out


def reference_tree(ref: str, tmp: Path) -> Path:
    path = tmp / "ref"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet",
                    str(path), ref], check=True)
    return path


def read_baseline(path: Path) -> dict | str:
    try:
        doc = json.loads(path.read_text())
        if isinstance(doc.get("cases"), dict) and isinstance(doc.get("ref"), str):
            return doc
        why = "no cases or ref"
    except (OSError, ValueError, AttributeError) as exc:
        why = str(exc) if isinstance(exc, ValueError) else type(exc).__name__
    return f"{path}: not a bench_speed baseline ({why})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", help="the reference commit (default: the baseline's, else "
                                  f"{DEFAULT_REF[:12]})")
    ap.add_argument("--only", help="NAME[,NAME...] (default: all): " + ", ".join(cases()))
    ap.add_argument("--repeat", type=int, default=2, help="rounds (the best of each figure)")
    ap.add_argument("--check", type=Path, nargs="?", const=BASELINE,
                    help="exit 1 on a ratio worse than this baseline's by more than 25 %%")
    ap.add_argument("--update", type=Path, nargs="?", const=BASELINE,
                    help="write the results as this baseline")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else list(cases())
    unknown = [n for n in names if n not in cases()]
    if unknown or args.repeat < 1:
        print(f"bench_speed: unknown case {', '.join(unknown)}" if unknown
              else "bench_speed: --repeat must be at least 1", file=sys.stderr)
        return 2
    if "a123" in names and not DATA.is_dir():
        print(f"bench_speed: no shared data at {DATA} (set ECMGEN_SHARED_DATA)",
              file=sys.stderr)
        return 2
    baseline = read_baseline(args.check) if args.check is not None else None
    if isinstance(baseline, str):
        print(baseline, file=sys.stderr)
        return 2
    ref = args.ref or (baseline or {}).get("ref") or DEFAULT_REF
    found = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet",
                            ref + "^{commit}"], capture_output=True, text=True)
    if found.returncode != 0:
        print(f"bench_speed: no commit {ref} in {REPO} (a shallow clone? fetch it)",
              file=sys.stderr)
        return 2
    ref = found.stdout.strip()
    if baseline is not None and baseline["ref"] != ref:
        print(f"bench_speed: the baseline's ratios are against {baseline['ref'][:12]}, "
              f"not {ref[:12]}", file=sys.stderr)
        return 2
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-speed-ref-") as tmp:
        tree = reference_tree(ref, Path(tmp))
        try:
            results = run(names, tree, args.repeat,
                          lambda m: print(m, file=sys.stderr, flush=True))
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force",
                            str(tree)], check=False)
    print(table(results, ref))
    print(f"load average {load:.1f} before, {os.getloadavg()[0]:.1f} after, "
          f"{os.cpu_count()} cores")
    doc = {"note": "bench/bench_speed.py: wall s, peak RSS MB (largest process), peak PSS MB "
                   "(all processes); ratio now / ref in one run", "ref": ref, "cases": results}
    if args.json is not None:
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    if args.update is not None:
        old = read_baseline(args.update) if args.update.exists() else None
        if isinstance(old, dict) and old["ref"] == ref:     # --only keeps the other cases
            doc["cases"] = {**old["cases"], **results}
        args.update.parent.mkdir(parents=True, exist_ok=True)
        args.update.write_text(json.dumps(doc, indent=1) + "\n")
    if args.check is not None:
        bad = worse(results, baseline)
        if bad:
            print("worse than the baseline by more than 25 % as a ratio to the reference:\n  "
                  + "\n  ".join(bad), file=sys.stderr)
            return 1
        print(f"no ratio worse than {args.check}'s by more than 25 %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
