#!/usr/bin/env python3
"""Benchmark of the generated C, in one run:

1. instructions per step (valgrind callgrind, host build -O2 with the strict flags, only the
   instructions inside <prefix>_step counted), float and fixed, variable and fixed dt, for
   the layout the fitter gives (method "curve": RC tables on a uniform 21-point SOC grid and
   a 5 K temperature grid, time constants constant along SOC and equal in both directions,
   the OCV on its own uniform 101-point grid; from tests/data/panasonic-temperature-model.json)
   as 4 x 21 (0 .. 15 degC, the OCV rows at the same temperatures: the target case) and as
   the whole 14 x 21 model with one OCV row per pulse test, with and without the diffusion
   pair and the Butler-Volmer branch (and with them and the surface SOC, surface_soc_gain
   0.5); and for tables with time constants varying along SOC on non-uniform grids (the
   GA / LM fits' layout): 1 x 20 (one temperature), 4 x 20 (OCV on its own 41-point grid,
   or on the RC grid) and 4 x 20 with the branches;
2. flash and RAM bytes of the step code and of the tables on Cortex-M4F and Cortex-M0
   (arm-none-eabi-gcc -Os, arm-none-eabi-size), the caller's state struct, the step's stack
   frame and the libgcc helpers the object calls (no 64-bit division may appear);
3. simulation throughput in steps/s: C through cffi (looping in C) against the float64
   Python model and the float32 / bit-true references (fitted 4 x 21);
4. Cortex-M4F (QEMU mps2-an386, the step built -O2 as in the target tests): Thumb-2
   instructions executed per step, counted exactly from QEMU's translation-block trace
   (-d in_asm,exec,nochain), and an estimate of the cycles from them with the Cortex-M4
   timings (TRM table 3-1: 1 per ALU / multiply (SMULL too) / VFP add-multiply, 2 per load
   or store unless it follows one, 1+N per LDM/STM/PUSH/POP, 3 per taken branch, 14 per
   VDIV, 2-12 (12 counted) per SDIV): an estimate, as QEMU has no cycle model.

Usage: python bench/bench_c.py [--steps N] [--json]
Targets: <= 200 instructions per step for float with variable dt and <= 250 for
fixed point, 4 x 20 table (checked on the fitter's 4 x 21 layout); < 2 KiB of code on
Cortex-M4F and M0. The x86-64 count is the target's measure; 4. gives Cortex-M4 figures.
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
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from ecmgen.c import cbuild, cref, target  # noqa: E402
from ecmgen.c.names import c_names  # noqa: E402
from ecmgen.c.codegen import describe, prepare, render  # noqa: E402
from ecmgen.c.spec import state_bytes  # noqa: E402
from ecmgen.model.simulate import simulate  # noqa: E402

VARIANTS = [("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)]


TARGET_MODEL = "fitted 4 x 21"


def models() -> dict:
    """The benchmarked models by layout and table shape (temperature rows x SOC points)."""
    from test_codegen_helpers import (TEMPERATURE_MODEL, fitter_layout_model, realistic_model,
                                      temperature_model)

    out = {}
    if TEMPERATURE_MODEL.exists():
        out[TARGET_MODEL] = fitter_layout_model(rows=slice(4, 8), ocv_t_c=(0.0, 5.0, 10.0, 15.0))
        out["fitted 14 x 21, OCV 4 x 101"] = fitter_layout_model()
        out["fitted 14 x 21 + diff + BV"] = fitter_layout_model(branches=True)
        out["14 x 21 + diff + BV + surface"] = replace(   # surface_soc_gain 0.5
            fitter_layout_model(branches=True), surface_soc_gain=0.5)
    out.update({"SOC-tau 1 x 20": realistic_model(n_rc=20, seed=3),
                "SOC-tau 4 x 20": temperature_model(4, 20, seed=3),
                "SOC-tau 4 x 20, OCV on RC grid": temperature_model(4, 20, seed=3, ocv_on_rc_grid=True),
                "SOC-tau 4 x 20 + diff + BV": temperature_model(4, 20, seed=3, branches=True)})
    return out


def drive_profile(n: int):
    """Current, time and cell temperature of a real drive cycle (US06 at 0 degC: the cell
    warms from 0.5 to 14 degC, across table rows; its mean current removed so that repeating
    it keeps the SOC in range) if the data is there, else a synthetic one of the same
    character."""
    from test_codegen_helpers import SHARED_DATA, load_cycle_t

    path = SHARED_DATA / "panasonic-18650pf-0degC" / "us06.mat"
    if path.exists():
        s = load_cycle_t("panasonic-18650pf-0degC", "us06.mat")
        reps = int(np.ceil(n / len(s)))
        cur = np.tile(s.current_a - np.mean(s.current_a), reps)[:n]
        dt = np.tile(cref.dt_from_time(s.time_s), reps)[:n]
        temp = np.tile(s.temperature_c, reps)[:n]
        src = "US06 at 0 degC (real, 0.5 .. 14 degC, mean current removed, repeated)"
    else:
        rng = np.random.default_rng(0)
        cur = np.repeat(rng.uniform(-20, 8, n // 20 + 1), 20)[:n]
        dt = rng.uniform(0.09, 0.11, n)
        temp = np.linspace(0.0, 14.0, n)
        src = "synthetic"
    dt[0] = 0.0
    return cur, dt, np.cumsum(dt), temp, src


def label(numeric, dt_s):
    return f"{numeric:5s} {'variable dt' if dt_s is None else f'dt = {dt_s} s':11s}"


# --- 1. instructions per step ---------------------------------------------------------

CG_MAIN = Path(__file__).parent / "c" / "callgrind_model_main.c"

def _native(spec, cur, dt, temp):
    if spec.fixed:
        return (cref.current_to_raw(spec, cur).astype(np.int32), cref.dt_to_raw(dt).astype(np.int32),
                cref.temperature_to_raw(temp).astype(np.int32))
    return cur.astype(np.float32), dt.astype(np.float32), temp.astype(np.float32)


def instructions_per_step(model, cur, dt, temp, n) -> dict:
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
            i_n, dt_n, t_n = _native(spec, cur[:n], dt[:n], temp[:n])
            t, soc0 = ("int32_t", str(cref.soc_to_raw(0.95))) if spec.fixed else ("float", "0.95f")
            (d / "in.bin").write_bytes(i_n.tobytes() + dt_n.tobytes() + t_n.tobytes())
            nm = c_names("bench", numeric)
            model_args = [f'-DECMB_HEADER="{nm["header"]}"', f"-DECMB_T={t}",
                          f"-DECMB_STATE={nm['state']}", f"-DECMB_INIT={nm['init']}",
                          f"-DECMB_STEP={nm['step']}", f"-DECMB_SOC0={soc0}",
                          f"-DECMB_VDT={int(dt_s is None)}"]
            subprocess.run([*cc, *cbuild.STRICT_CFLAGS, "-O2", "-I", str(d), "-c", str(d / nm["source"]),
                            "-o", str(d / "m.o")], check=True)
            subprocess.run([*cc, "-O2", *model_args, "-I", str(d), str(CG_MAIN), str(d / "m.o"),
                            "-o", str(d / "a.out")], check=True)
            cg = d / "cg.out"
            subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}",
                            f"--toggle-collect={nm['step']}", str(d / "a.out"), str(d / "in.bin"), str(n)],
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
                sfx = c_names("bench", numeric)["suffix"]
                obj = target.cross_compile(spec, Path(tmp) / f"{cpu}_{numeric}_{dt_s}", cpu=cpu, opt="-Os")
                sz = target.sizes(obj.obj)
                su = target.stack_usage(obj.obj)
                res[f"{cpu} {label(numeric, dt_s).strip()}"] = {
                    "code": sz["code"], "tables": sz["tables"], "data+bss": sz["ram"],
                    "state": state_bytes(spec),
                    "stack_step": sum(v for k, v in su.items() if k not in (f"bench_run_{sfx}", f"bench_init_{sfx}")),
                    "libgcc": [s for s in target.undefined_symbols(obj.obj)],
                    "warnings": obj.warnings,
                }
    return res


# --- 3. throughput --------------------------------------------------------------------

def throughput(model, cur, dt, t, temp, n_c: int, n_py: int) -> dict:
    res = {}
    for numeric, dt_s in VARIANTS:
        cm = cbuild.build(model, numeric=numeric, dt_s=dt_s, prefix="bench")
        i_n, dt_n, s0 = cm.native_inputs(cur[:n_c], dt[:n_c] if dt_s is None else None, 0.95)
        t_n = cm.native_temperature(temp[:n_c], n_c)
        best = np.inf
        for _ in range(3):                                  # best of 3
            t0 = time.perf_counter()
            cm.run_native(i_n, dt_n, s0, t_n)
            best = min(best, time.perf_counter() - t0)
        res[f"C (cffi, {label(numeric, dt_s).strip()})"] = n_c / best
    t0 = time.perf_counter()
    simulate(model, t[:n_py], cur[:n_py], 0.95, temp[:n_py])
    res["Python float64 simulate()"] = n_py / (time.perf_counter() - t0)
    for numeric in ("float", "fixed"):
        spec = prepare(model, numeric=numeric)
        t0 = time.perf_counter()
        if numeric == "float":
            cref.simulate_f32(spec, cur[:n_py], dt[:n_py], 0.95, temp[:n_py])
        else:
            cref.simulate_fixed(spec, cur[:n_py], dt[:n_py], 0.95, temp[:n_py])
        res[f"Python {'float32' if numeric == 'float' else 'bit-true int'} reference"] = \
            n_py / (time.perf_counter() - t0)
    return res


# --- 4. Cortex-M4: instructions per step in QEMU, and a cycle estimate -------------------

_INSN = re.compile(r"^0x([0-9a-f]{8}):\s+((?:[0-9a-f]{4} ?)+)\s+(\S+)\s*(.*)$")
_TRACE = re.compile(r"^Trace \d+: \S+ \[[0-9a-f]+/([0-9a-f]+)/[0-9a-f]+/[0-9a-f]+\] (\S+)")
_BRANCH = re.compile(r"^(b|bl|blx|bx|cbz|cbnz|b[a-z]{2}|tbb|tbh)(\.w|\.n)?$")


def _m4_cycles(insns) -> float:
    """Cortex-M4 cycle estimate of a straight run of (mnemonic, operands); the branch at
    the end is counted by the caller."""
    cyc, prev_mem = 0.0, False
    for mn, ops in insns:
        m = mn.split(".")[0]
        mem = m.startswith(("ldr", "str")) and m not in ("ldrd", "strd", "ldrex", "strex")
        if m in ("push", "pop", "vpush", "vpop") or m.startswith(("ldm", "stm")):
            c = 1 + ops.count(",") + 1 + (3 if "pc" in ops else 0)
        elif m in ("ldrd", "strd"):
            c = 3
        elif mem or m in ("vldr", "vstr"):
            c = 1 if prev_mem else 2
        elif m in ("sdiv", "udiv"):
            c = 12
        elif m in ("vdiv", "vsqrt"):
            c = 14
        elif m in ("vmla", "vmls", "vnmla", "vnmls"):
            c = 3
        elif _BRANCH.match(mn):
            c = 0
        else:
            c = 1
        prev_mem = mem or m in ("vldr", "vstr")
        cyc += c
    return cyc


def m4_estimates(model, cur, dt, temp, n: int = 2000) -> dict:
    """Per step on the Cortex-M4F model in QEMU: instructions executed inside the model's
    step (and the runtime functions it calls), and a cycle estimate (see the module doc)."""
    reason = target.skip_reason(qemu=True)
    if reason:
        return {"skipped": reason}
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for numeric, dt_s in VARIANTS:
            d = Path(tmp) / f"{numeric}_{dt_s}"
            spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix="m4")
            cm = cbuild.compile_spec(spec)
            i_n, dt_n, s0 = cm.native_inputs(cur[:n], dt[:n] if dt_s is None else None, 0.95)
            run = target.TargetRun(spec, i_n, dt_n, s0, cm.native_temperature(temp[:n], n))
            elf = target.build_firmware([run], d, cpu="m4f", opt="-O2")
            log = d / "qemu.log"
            subprocess.run([target.QEMU, "-M", target.CPUS["m4f"]["machine"], "-nographic",
                            "-monitor", "none", "-serial", "none", "-semihosting-config",
                            "enable=on,target=native", "-d", "in_asm,exec,nochain", "-D", str(log),
                            "-kernel", str(elf)], check=True, capture_output=True, cwd=d, timeout=600)
            blocks, cur_pc, trace = {}, None, []
            for line in log.read_text().splitlines():
                mt = _TRACE.match(line)
                if mt:
                    trace.append((int(mt.group(1), 16), mt.group(2)))
                    cur_pc = None
                    continue
                mi = _INSN.match(line)
                if mi:
                    pc = int(mi.group(1), 16)
                    if cur_pc is None:
                        cur_pc = pc
                        blocks[pc] = []
                    blocks[cur_pc].append((pc, len(mi.group(2).replace(" ", "")) // 2,
                                           mi.group(3), mi.group(4)))
                elif line.startswith("IN:"):
                    cur_pc = None
            insns = cycles = 0.0
            ours = (f"m4_step_{cm.names['suffix']}", f"m4_coefs_{cm.names['suffix']}")
            for k, (pc, sym) in enumerate(trace):
                # the step and what it calls: the model's step and time-constant helper,
                # the runtime's out-of-line functions (and clones: name.constprop.0)
                if not (sym.split(".")[0] in ours or sym.startswith("ecmrt_")):
                    continue
                body = blocks[pc]
                insns += len(body)
                cycles += _m4_cycles([(mn, ops) for _, _, mn, ops in body])
                last_pc, size, mn, _ = body[-1]
                if _BRANCH.match(mn):
                    nxt = trace[k + 1][0] if k + 1 < len(trace) else None
                    cycles += 1 if nxt == last_pc + size else 3     # fall through / taken
            res[label(numeric, dt_s).strip()] = {"instructions": round(insns / n, 1),
                                                  "cycles_estimate": round(cycles / n, 1)}
    return res


TARGETS = {"float variable dt": 200, "fixed variable dt": 250}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=5_000_000, help="C throughput steps")
    ap.add_argument("--json", action="store_true", help="print JSON only")
    args = ap.parse_args(argv)
    mdl = models()
    cur, dt, t, temp, src = drive_profile(max(args.steps, 200_000))
    table_bytes = {name: {n: describe(prepare(m, numeric=n))["table_bytes"] for n in ("float", "fixed")}
                   for name, m in mdl.items()}
    report = {
        "models": list(mdl),
        "profile": src,
        "instructions_per_step": {name: instructions_per_step(m, cur, dt, temp, 20_000)
                                  for name, m in mdl.items()},
        "table_bytes": table_bytes,
        "flash_ram_bytes": {name: flash_ram(m) for name, m in mdl.items()},
        "m4": {name: m4_estimates(mdl[name], cur, dt, temp)
               for name in (TARGET_MODEL, "SOC-tau 4 x 20") if name in mdl},
        "steps_per_s": throughput(mdl.get(TARGET_MODEL, mdl["SOC-tau 4 x 20"]), cur, dt, t, temp,
                                  args.steps, 200_000),
    }
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(f"ecmgen C benchmark; profile {src}\n")
    print("1. instructions per step (callgrind, host x86-64 gcc -O2, inside <prefix>_step), and "
          "table bytes (variable dt)")
    ips = report["instructions_per_step"]
    cols = [label(n, d).strip() for n, d in VARIANTS]
    print(f"   {'model (T x SOC)':31s} " + " ".join(f"{c:>18s}" for c in cols) + "  bytes float / fixed")
    for name, row in ips.items():
        if "skipped" in row:
            print(f"   {name:31s} skipped: {row['skipped']}")
            continue
        tb = table_bytes[name]
        print(f"   {name:31s} " + " ".join(f"{row[c]:18.1f}" for c in cols) +
              f"  {tb['float']:6d} / {tb['fixed']:6d}")
    for name in (TARGET_MODEL, "SOC-tau 4 x 20"):
        row = ips.get(name, {})
        for c, lim in TARGETS.items():
            if c in row:
                print(f"   {name}, {c}: {row[c]} (target <= {lim}: "
                      f"{'met' if row[c] <= lim else 'NOT met'})")
    print("\n2. flash / RAM bytes, arm-none-eabi-gcc -Os (code = .text, tables = .rodata)")
    head = ["code", "tables", "data+bss", "state", "stack"]
    print(f"   {'table, build':50s} " + " ".join(f"{h:>{max(5, len(h))}s}" for h in head) + "  libgcc")
    worst = {False: 0, True: 0}          # largest code without / with the branches
    for name, fr in report["flash_ram_bytes"].items():
        if "skipped" in fr:
            print(f"   {name}: skipped: {fr['skipped']}")
            continue
        for k, v in fr.items():
            worst["BV" in name] = max(worst["BV" in name], v["code"])
            print(f"   {name + ', ' + k:50s} {v['code']:5d} {v['tables']:6d} {v['data+bss']:8d} "
                  f"{v['state']:5d} {v['stack_step']:5d}  {' '.join(v['libgcc']) or '-'}")
    for branches, w in worst.items():
        print(f"   largest code{' with diffusion + BV' if branches else ''}: {w} B "
              f"(target <= 2048: {'met' if w <= 2048 else 'NOT met'})")
    div = sorted({s for fr in report["flash_ram_bytes"].values() if "skipped" not in fr
                  for v in fr.values() for s in v["libgcc"] if "div" in s})
    print(f"   division helpers referenced: {', '.join(div) or 'none'}")
    print("\n4. Cortex-M4F (QEMU mps2-an386, -O2): instructions executed per step / estimated cycles")
    print(f"   {'model':31s} " + " ".join(f"{c:>18s}" for c in cols))
    for name, row in report["m4"].items():
        if "skipped" in row:
            print(f"   {name:31s} skipped: {row['skipped']}")
            continue
        print(f"   {name:31s} " + " ".join(
            f"{row[c]['instructions']:8.1f} /{row[c]['cycles_estimate']:7.1f}" for c in cols))
    print(f"\n3. throughput, steps/s ({TARGET_MODEL})")
    for k, v in report["steps_per_s"].items():
        print(f"   {k:40s} {v:14,.0f}")
    py = report["steps_per_s"]["Python float64 simulate()"]
    best_c = report["steps_per_s"]["C (cffi, float variable dt)"]
    print(f"   C float (variable dt) / Python float64: {best_c / py:,.0f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
