#!/usr/bin/env python3
"""What the ageing input costs the generated C, and how exact it is.

On bench_c.py's target model (the fitter's layout, 4 x 21 over 0 .. 15 degC) without and
with an ageing law of four breakpoints (0 .. 600 equivalent full cycles, resistance x1.45
and capacity x0.86 at the end):

1. instructions per step, x86-64 -O2 (callgrind, bench_c.instructions_per_step);
2. Cortex-M4F -Os: step code, tables, the caller's state, the step's stack
   (bench_c.flash_ram);
3. Cortex-M4F in QEMU (-O2): instructions per step (bench_c.m4_estimates);
4. the aged C against its references: the drive of bench_c at five ages, each numeric and
   dt mode, bit-exact steps of all (host, cffi).

Usage: python bench/bench_ageing.py [--steps N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_c  # noqa: E402
from ecmgen.c import cbuild  # noqa: E402
from ecmgen.model.ageing import AgeingLaw  # noqa: E402

LAW = AgeingLaw([0.0, 200.0, 400.0, 600.0], [1.0, 1.08, 1.19, 1.45],
                [1.0, 0.962, 0.925, 0.86], "bench_ageing.py")
AGES = (0.0, 137.0, 300.0, 599.5, 5000.0)


def exactness(model, cur, dt, t, temp, n: int) -> dict:
    out = {}
    for numeric, dt_s in bench_c.VARIANTS:
        cm = cbuild.build(model, numeric=numeric, dt_s=dt_s, prefix="bage")
        tt = t[:n] if dt_s is None else dt_s * np.arange(n)
        steps = exact = 0
        for efc in AGES:
            res = cbuild.compare(model, cm, tt, cur[:n], 0.95, None, temp[:n], efc)
            steps += res["steps"]
            exact += res["steps"] if res["bit_exact_vs_reference"] else 0
        out[bench_c.label(numeric, dt_s).strip()] = f"{exact} of {steps} steps bit-exact"
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    plain = bench_c.models()[bench_c.TARGET_MODEL]
    aged = replace(plain, ageing=LAW)
    cur, dt, t, temp, src = bench_c.drive_profile(args.steps)
    res = {"drive": src}
    for name, model in (("plain", plain), ("aged", aged)):
        res[name] = {"instructions_x86": bench_c.instructions_per_step(model, cur, dt, temp,
                                                                       args.steps),
                     "m4f_flash_ram": {k: v for k, v in bench_c.flash_ram(model).items()
                                       if k.startswith("m4f")},
                     "m4f_qemu": bench_c.m4_estimates(model, cur, dt, temp)}
    res["aged_exactness"] = exactness(aged, cur, dt, t, temp, min(args.steps, 5000))
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"drive: {src}")
    for key in ("instructions_x86", "m4f_qemu"):
        for variant, v in res["plain"][key].items():
            print(f"{key:17s} {variant:22s} {v} -> {res['aged'][key].get(variant)}")
    for variant, v in res["plain"]["m4f_flash_ram"].items():
        a = res["aged"]["m4f_flash_ram"][variant]
        print(f"m4f -Os {variant:26s} " + ", ".join(
            f"{k} {v[k]} -> {a[k]}" for k in ("code", "tables", "state", "stack_step")))
    for variant, v in res["aged_exactness"].items():
        print(f"aged C vs reference {variant:22s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
