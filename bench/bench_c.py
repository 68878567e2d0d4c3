#!/usr/bin/env python3
"""Benchmark of the generated C, in one run:

1. instructions per step (valgrind callgrind, host build -O2 with the strict flags, only the
   instructions inside <prefix>_step counted), float and fixed, variable and fixed dt;
2. flash and RAM bytes of the step code and of the tables for a 20-point table on
   Cortex-M4F and Cortex-M0 (arm-none-eabi-gcc -Os, arm-none-eabi-size), plus the caller's
   state struct and the step's stack frame;
3. simulation throughput in steps/s: C through cffi (looping in C) against the float64
   Python model and the float32 / bit-true references.

Usage: python bench/bench_c.py [--steps N] [--json]
Targets (issue): < 150 instructions per step for float; < 2 KiB of flash for the code.
Missing tools (valgrind, arm-none-eabi-gcc) are reported and their part skipped.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from ecmgen.c import cbuild, cref, target  # noqa: E402
from ecmgen.c.codegen import prepare, render  # noqa: E402
from ecmgen.model.simulate import simulate  # noqa: E402

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]


def model20():
    from test_codegen_helpers import realistic_model

    return realistic_model(n_rc=20, seed=3)


def drive_profile(n: int):
    """Current and time of a real drive cycle (US06, its mean removed so that repeating it
    keeps the SOC in range) if the data is there, else a synthetic one of the same character."""
    from test_codegen_helpers import PANASONIC, load_mat

    path = PANASONIC / "us06.mat"
    if path.exists():
        s = load_mat(path)
        reps = int(np.ceil(n / len(s)))
        cur = np.tile(s.current_a - np.mean(s.current_a), reps)[:n]
        dt = np.tile(cref.dt_from_time(s.time_s), reps)[:n]
        src = "US06 (real, mean current removed, repeated)"
    else:
        rng = np.random.default_rng(0)
        cur = np.repeat(rng.uniform(-20, 8, n // 20 + 1), 20)[:n]
        dt = rng.uniform(0.09, 0.11, n)
        src = "synthetic"
    dt[0] = 0.0
    return cur, dt, np.cumsum(dt), src


def label(numeric, dt_s):
    return f"{numeric:5s} {'variable dt' if dt_s is None else f'dt = {dt_s} s':11s}"


# --- 1. instructions per step ---------------------------------------------------------

CG_MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include "bench_ecm.h"
int main(int argc, char **argv)
{
    FILE *f = fopen(argv[1], "rb");
    size_t n = (size_t)atol(argv[2]), k;
    T *i = malloc(n * sizeof *i), *dt = malloc(n * sizeof *dt);
    bench_state_t s;
    double acc = 0.0;
    if (!f || fread(i, sizeof *i, n, f) != n || fread(dt, sizeof *dt, n, f) != n) return 1;
    bench_init(&s, SOC0);
    for (k = 0; k < n; k++) acc += (double)bench_step(&s, i[k] DTARG);
    printf("%g\n", acc);
    (void)argc;
    return 0;
}
"""


def instructions_per_step(model, cur, dt, n) -> dict:
    if shutil.which("valgrind") is None:
        return {"skipped": "valgrind not found (apt-get install valgrind)"}
    out = {}
    cc = cbuild.host_cc()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for numeric, dt_s in VARIANTS:
            d = tmp / f"{numeric}_{dt_s}"
            d.mkdir()
            spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix="bench")
            for name, text in render(spec).items():
                (d / name).write_text(text)
            if spec.fixed:
                i_n = cref.current_to_raw(spec, cur).astype(np.int32)
                dt_n = cref.dt_to_raw(dt).astype(np.int32)
                t, soc0 = "int32_t", str(cref.soc_to_raw(0.95))
            else:
                i_n, dt_n = cur.astype(np.float32), dt.astype(np.float32)
                t, soc0 = "float", "0.95f"
            (d / "in.bin").write_bytes(i_n[:n].tobytes() + dt_n[:n].tobytes())
            main = CG_MAIN.replace("T *", f"{t} *").replace("SOC0", soc0)
            main = main.replace("DTARG", ", dt[k]" if dt_s is None else "")
            (d / "main.c").write_text(main)
            subprocess.run([*cc, *cbuild.STRICT_CFLAGS, "-O2", "-I", str(d), "-c", str(d / "bench_ecm.c"),
                            "-o", str(d / "m.o")], check=True)
            subprocess.run([*cc, "-O2", "-I", str(d), str(d / "main.c"), str(d / "m.o"), "-o",
                            str(d / "a.out")], check=True)
            cg = d / "cg.out"
            subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}",
                            "--toggle-collect=bench_step", str(d / "a.out"), str(d / "in.bin"), str(n)],
                           check=True, capture_output=True)
            total = int(re.search(r"^summary:\s+(\d+)", cg.read_text(), re.M).group(1))
            out[label(numeric, dt_s).strip()] = round(total / n, 1)
    return out


# --- 2. flash and RAM -----------------------------------------------------------------

def flash_ram(model) -> dict:
    reason = target.skip_reason(qemu=False)
    if reason:
        return {"skipped": reason}
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for cpu in ("m4f", "m0"):
            for numeric, dt_s in VARIANTS:
                if cpu == "m0" and numeric == "float":
                    continue
                spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix="bench")
                obj = target.cross_compile(spec, Path(tmp) / f"{cpu}_{numeric}_{dt_s}", cpu=cpu, opt="-Os")
                sz = target.sizes(obj.obj)
                su = target.stack_usage(obj.obj)
                res[f"{target.CPUS[cpu]['name']}: {label(numeric, dt_s).strip()}"] = {
                    "code": sz["code"], "tables": sz["tables"], "data+bss": sz["ram"],
                    "state": 24 if spec.fixed else 20,
                    "stack_step": sum(v for k, v in su.items() if k not in ("bench_run", "bench_init")),
                    "libgcc": [s for s in target.undefined_symbols(obj.obj)],
                    "warnings": obj.warnings,
                }
    return res


# --- 3. throughput --------------------------------------------------------------------

def throughput(model, cur, dt, t, n_c: int, n_py: int) -> dict:
    res = {}
    for numeric, dt_s in VARIANTS:
        cm = cbuild.build(model, numeric=numeric, dt_s=dt_s, prefix="bench")
        i_n, dt_n, s0 = cm.native_inputs(cur[:n_c], dt[:n_c] if dt_s is None else None, 0.95)
        best = np.inf
        for _ in range(3):                                  # best of 3
            t0 = time.perf_counter()
            cm.run_native(i_n, dt_n, s0)
            best = min(best, time.perf_counter() - t0)
        res[f"C (cffi, {label(numeric, dt_s).strip()})"] = n_c / best
    t0 = time.perf_counter()
    simulate(model, t[:n_py], cur[:n_py], 0.95)
    res["Python float64 simulate()"] = n_py / (time.perf_counter() - t0)
    for numeric in ("float", "fixed"):
        spec = prepare(model, numeric=numeric)
        t0 = time.perf_counter()
        if numeric == "float":
            cref.simulate_f32(spec, cur[:n_py], dt[:n_py], 0.95)
        else:
            cref.simulate_fixed(spec, cur[:n_py], dt[:n_py], 0.95)
        res[f"Python {'float32' if numeric == 'float' else 'bit-true int'} reference"] = \
            n_py / (time.perf_counter() - t0)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=5_000_000, help="C throughput steps")
    ap.add_argument("--json", action="store_true", help="print JSON only")
    args = ap.parse_args(argv)
    model = model20()
    cur, dt, t, src = drive_profile(max(args.steps, 200_000))
    report = {
        "model": "20-point RC tables per direction, 41-point OCV (tests/test_codegen_helpers.py)",
        "profile": src,
        "instructions_per_step": instructions_per_step(model, cur, dt, 20_000),
        "flash_ram_bytes": flash_ram(model),
        "steps_per_s": throughput(model, cur, dt, t, args.steps, 200_000),
    }
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(f"ecmgen C benchmark - {report['model']}; profile {src}\n")
    print("1. instructions per step (callgrind, host x86-64 gcc -O2, inside <prefix>_step)")
    ips = report["instructions_per_step"]
    for k, v in ips.items():
        note = ""
        if k.startswith("float") and isinstance(v, float):
            note = "  (target < 150: " + ("met)" if v < 150 else "not met)")
        print(f"   {k:28s} {v}{note}")
    print("\n2. flash / RAM bytes, arm-none-eabi-gcc -Os (code = .text, tables = .rodata)")
    fr = report["flash_ram_bytes"]
    if "skipped" in fr:
        print(f"   skipped: {fr['skipped']}")
    else:
        head = ["code", "tables", "data+bss", "state", "stack"]
        print(f"   {'build':52s} " + " ".join(f"{h:>{max(5, len(h))}s}" for h in head) + "  libgcc")
        for k, v in fr.items():
            print(f"   {k:52s} {v['code']:5d} {v['tables']:6d} {v['data+bss']:8d} {v['state']:5d} "
                  f"{v['stack_step']:5d}  {' '.join(v['libgcc']) or '-'}")
        worst = max(v["code"] for v in fr.values())
        print(f"   largest code: {worst} B (target < 2048: {'met' if worst < 2048 else 'not met'})")
    print("\n3. throughput, steps/s")
    for k, v in report["steps_per_s"].items():
        print(f"   {k:40s} {v:14,.0f}")
    py = report["steps_per_s"]["Python float64 simulate()"]
    best_c = report["steps_per_s"]["C (cffi, float variable dt)"]
    print(f"   C float (variable dt) / Python float64: {best_c / py:,.0f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
