#!/usr/bin/env python3
"""Benchmark of the generated C SOC estimator, in one run:

1. instructions per estimator step (valgrind callgrind, host x86-64 gcc -O2 with the strict
   flags, only what runs inside <prefix>_est_step, the model's step included), beside the
   model's step alone on the same samples;
2. flash and RAM on Cortex-M4F (arm-none-eabi-gcc -Os): the estimator's code (object with it
   minus object without it), the caller's <prefix>_est_t, the stack frames on the
   est_step call path (-fstack-usage);
3. per shared Panasonic cycle (25, 0, -10, -20 degC; US06 and HWFET), the full-cell scenario
   (--soc0 1 --soc0-guess 0.8 --current-offset-a 0.029 --current-gain 1.01): SOC RMSE and
   max |error| after 600 s of the float32 C and of the float64 Python filter against the
   reference (coulomb counting the measured current from the true start), the largest
   |SOC(C) - SOC(float64)|, C == float32 reference bit for bit (every step, state and
   covariance entry), and plain coulomb counting with the same sensor errors;
4. the covariance's dynamic range over those runs (the fixed-point question);
5. models with diagnose effects: 1. and 2. for the test model with a hysteresis effect and
   with every effect (hysteresis, extra_rc, current_dependent_resistance, capacity_error,
   temperature_dependence), and the SOC on synthetic LFP-like cells with hysteresis
   (ecmgen.diagnosis.synthcell, whole drive cycle, guess 0.6 for 0.95, offset C/100, gain
   1.01) with the filter's hysteresis state and on the model without it; and 1. and 2. for
   the test model with the surface SOC (surface_soc_gain 0.5);
6. the current-offset state ([estimator] offset_state = true): its cost in 5.'s table, and
   per shared cycle the C filter's SOC with it (the scenario's 29 mA offset) and the offset
   it estimates by the end.

Model: tests/data/panasonic-temperature-model.json, [estimator] defaults.
Usage: python bench/bench_estimator_c.py [--steps N] [--json] [--no-reference]
       python bench/bench_estimator_c.py --cost-only [--set NAME=VALUE ...]   (1. and 2.)
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
DATA = ROOT.parent / "shared" / "data"
MODEL = ROOT / "tests" / "data" / "panasonic-temperature-model.json"
CYCLES = [("25degC", "us06"), ("25degC", "hwfet-a"), ("0degC", "us06"), ("0degC", "hwfet"),
          ("n10degC", "us06"), ("n10degC", "hwfet"), ("n20degC", "us06"), ("n20degC", "hwfet")]
GUESS, OFFSET_A, GAIN = 0.8, 0.029, 1.01

from ecmgen.c import cbuild, cref, target  # noqa: E402
from ecmgen.c.codegen import prepare, render  # noqa: E402
from ecmgen.c.estc import prepare_estimator  # noqa: E402
from ecmgen.c.estcheck import bits_equal, python_filter_soc, run_estimator_c  # noqa: E402
from ecmgen.c.estref import simulate_estimator_f32  # noqa: E402
from ecmgen.c.esttarget import estimator_sizes  # noqa: E402
from ecmgen.config import EstimatorConfig  # noqa: E402
from ecmgen.data.measure import read_timeseries  # noqa: E402
from ecmgen.estimate.run import SocMetrics, coulomb_count  # noqa: E402
from ecmgen.model.effects import make_effect  # noqa: E402
from ecmgen.model.model import load_model  # noqa: E402

HYSTERESIS = make_effect("hysteresis", m_v=0.015, decay_ah=0.15, m0_v=0.002,
                         ocv_table_state=0.0, initial_state=1.0)
EVERY_EFFECT = (HYSTERESIS, make_effect("extra_rc", r_ohm=0.01, tau_s=900.0),
                make_effect("current_dependent_resistance", scale_at_zero=1.1, i0_a=5.0),
                make_effect("capacity_error", capacity_scale=0.97),
                make_effect("temperature_dependence", activation_k=2000.0, t_ref_c=25.0))



def _cycle(folder, name):
    return read_timeseries(DATA / f"panasonic-18650pf-{folder}" / f"{name}.mat", capacity_ah=2.9)


def instructions_per_step(model, n: int, cfg=None) -> dict:
    if shutil.which("valgrind") is None:
        return {"skipped": "valgrind not found (apt-get install valgrind)"}
    s = _cycle("25degC", "us06")
    n = min(n, s.time_s.size)
    seen = GAIN * s.current_a[:n] + OFFSET_A
    arrays = [seen, s.temperature_c[:n], cref.dt_from_time(s.time_s[:n]), s.voltage_v[:n]]
    spec = prepare(model, "float", None, "bench")
    est = prepare_estimator(model, spec, cfg or EstimatorConfig())
    cc = cbuild.host_cc()
    out = {"samples": n, "cycle": "25degC us06 (scenario)"}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for name, text in render(spec, None, est).items():
            (d / name).write_text(text)
        (d / "in.bin").write_bytes(b"".join(np.asarray(a, dtype=np.float32).tobytes()
                                            for a in arrays))
        (d / "main.c").write_text((Path(__file__).parent / "c" / "callgrind_est_main.c").read_text())
        for src in ("bench_ecm_f32", "bench_est_f32"):
            subprocess.run([*cc, *cbuild.STRICT_CFLAGS, "-O2", "-I", str(d), "-c",
                            str(d / f"{src}.c"), "-o", str(d / f"{src}.o")], check=True)
        subprocess.run([*cc, "-O2", "-I", str(d), str(d / "main.c"), str(d / "bench_ecm_f32.o"),
                        str(d / "bench_est_f32.o"), "-o", str(d / "a.out")], check=True)
        for label, fn, flag in (("est_step", "bench_est_step_f32", "1"),
                                ("model step", "bench_step_f32", "0")):
            cg = d / f"cg.{flag}"
            subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}",
                            f"--toggle-collect={fn}", str(d / "a.out"), str(d / "in.bin"),
                            str(n), flag], check=True, capture_output=True)
            total = int(re.search(r"^summary:\s+(\d+)", cg.read_text(), re.M).group(1))
            out[label] = round(total / n, 1)
    return out


def flash_ram(model, cfg=None) -> dict:
    reason = target.skip_reason(qemu=False)
    if reason:
        return {"skipped": reason}
    sz = estimator_sizes(model, cfg, cpu="m4f", opt="-Os")
    fr = sz["stack_frames"]
    update = next((v for k, v in fr.items() if k.startswith(("fe_est_update", "ecmrt_est_f32_update"))), 0)
    inner = max(fr.get("fe_step_f32", 0) + fr.get("ecmrt_f32_locate", 0),
                next((v for k, v in fr.items() if k.startswith(("fe_est_params", "ecmrt_est_f32_params"))), 0)
                + fr.get("ecmrt_f32_locate", 0), fr.get("ecmrt_est_f32_gain", 0))
    sz["stack_est_step_path"] = fr.get("fe_est_step_f32", 0) + update + inner
    return sz


def accuracy(model, reference: bool) -> tuple[list, dict]:
    spec = prepare(model, "float", None, "acc")
    est = prepare_estimator(model, spec, EstimatorConfig())
    cm = cbuild.compile_spec(spec, estimator=est)
    rows, p_abs_max, p_abs_min, p00, cancel = [], np.zeros((est.n, est.n)), \
        np.full((est.n, est.n), np.inf), [np.inf, 0.0], np.inf
    for folder, name in CYCLES:
        s = _cycle(folder, name)
        seen = GAIN * s.current_a + OFFSET_A
        dt = cref.dt_from_time(s.time_s)
        t0 = time.perf_counter()
        got = run_estimator_c(cm, seen, dt, s.voltage_v, GUESS, s.temperature_c)
        c_s = time.perf_counter() - t0
        exact = None
        if reference:
            ref = simulate_estimator_f32(spec, est, seen, dt, s.voltage_v, GUESS, s.temperature_c)
            exact = bits_equal(got, ref)
        soc64 = python_filter_soc(model, s.time_s, seen, s.voltage_v, GUESS,
                                  EstimatorConfig(), s.temperature_c)
        truth = coulomb_count(model, s.time_s, s.current_a, 1.0)
        cc = coulomb_count(model, s.time_s, seen, GUESS)
        mc = SocMetrics.of(s.time_s, got.soc.astype(np.float64), truth)
        m64 = SocMetrics.of(s.time_s, soc64, truth)
        mcc = SocMetrics.of(s.time_s, cc, truth)
        rows.append({"cycle": f"{folder} {name}", "steps": int(s.time_s.size),
                     "c_rmse": mc.soc_rmse, "c_max600": mc.soc_max_abs_after_600s,
                     "py_rmse": m64.soc_rmse, "py_max600": m64.soc_max_abs_after_600s,
                     "max_dsoc": float(np.max(np.abs(got.soc - soc64))),
                     "cc_rmse": mcc.soc_rmse, "cc_max600": mcc.soc_max_abs_after_600s,
                     "bit_exact": exact, "c_us_per_step_host": 1e6 * c_s / s.time_s.size})
        a = np.abs(got.p.astype(np.float64))
        p_abs_max = np.maximum(p_abs_max, a.max(axis=0))
        nz = np.where(a > 0, a, np.inf)
        p_abs_min = np.minimum(p_abs_min, nz.min(axis=0))
        p00 = [min(p00[0], float(got.p[:, 0, 0].min())), max(p00[1], float(got.p[:, 0, 0].max()))]
        # how much of the SOC variance one update removes (bits the Joseph form cancels)
        prior = got.p[:-1, 0, 0].astype(np.float64)
        cancel = min(cancel, float(np.min(got.p[1:, 0, 0] / np.maximum(prior, 1e-45))))
    rng = {"p00_start": float(est.noise["p0_soc"]), "p00_min": p00[0], "p00_max": p00[1],
           "diag_min_nonzero": np.diag(p_abs_min).tolist(), "diag_max": np.diag(p_abs_max).tolist(),
           "abs_max": p_abs_max.tolist(), "abs_min_nonzero": p_abs_min.tolist(),
           "span_decades": float(np.log10(p_abs_max.max() / p_abs_min.min())),
           "min_p00_ratio_per_step": cancel}
    return rows, rng


def effects(model, steps: int) -> dict:
    """Section 5: cost of the effects' states and factors, and the LFP cells' SOC."""
    from ecmgen.diagnosis.synthcell import random_cell
    from ecmgen.model.simulate import simulate

    cost = []
    for label, fx, off in (("none", (), False), ("hysteresis", (HYSTERESIS,), False),
                           ("every effect", EVERY_EFFECT, False), ("offset state", (), True),
                           ("every effect + offset state", EVERY_EFFECT, True),
                           ("surface SOC (gain 0.5)", (), False)):
        m = model.with_effects(fx)
        if label.startswith("surface"):
            m = replace(m, surface_soc_gain=0.5)
        spec = prepare(m, "float", None, "cost")
        cfg = EstimatorConfig(offset_state=off)
        cost.append({"effects": label, "states": prepare_estimator(m, spec, cfg).n,
                     "instructions": instructions_per_step(m, steps, cfg),
                     "flash_ram": flash_ram(m, cfg)})
    lfp = []
    for seed in (1, 2, 3):
        cell = random_cell(seed, "hysteresis", chemistry="lfp")
        cyc = cell.drive_cycle()
        t = cyc.time_s
        seen = GAIN * cyc.current_a + 0.01 * cell.capacity_ah
        truth = simulate(cell.hidden, t, cyc.current_a, 0.95, cyc.temperature_c).soc
        row = {"seed": seed, "steps": int(t.size), "m_v": cell.hidden.effects[0].m_v}
        for label, m in (("hysteresis", cell.hidden), ("without", cell.hidden.with_effects(()))):
            spec = prepare(m, "float", None, "lfp")
            est = prepare_estimator(m, spec, EstimatorConfig())
            got = run_estimator_c(cbuild.compile_spec(spec, estimator=est), seen,
                                  cref.dt_from_time(t), cyc.voltage_v, 0.6, cyc.temperature_c)
            err = (got.soc.astype(np.float64) - truth)[t > 600]
            row[label] = (float(np.sqrt(np.mean(err ** 2))), float(np.max(np.abs(err))))
        lfp.append(row)
    return {"cost": cost, "lfp": lfp, "offset": offset_state(model)}


def offset_state(model) -> list:
    """Section 6: the C filter with the current-offset state over every shared cycle."""
    spec = prepare(model, "float", None, "off")
    cm = cbuild.compile_spec(spec, estimator=prepare_estimator(
        model, spec, EstimatorConfig(offset_state=True)))
    rows = []
    for folder, name in CYCLES:
        s = _cycle(folder, name)
        seen = GAIN * s.current_a + OFFSET_A
        got = run_estimator_c(cm, seen, cref.dt_from_time(s.time_s), s.voltage_v, GUESS,
                              s.temperature_c)
        mc = SocMetrics.of(s.time_s, got.soc.astype(np.float64),
                           coulomb_count(model, s.time_s, s.current_a, 1.0))
        rows.append({"cycle": f"{folder} {name}", "c_rmse": mc.soc_rmse,
                     "c_max600": mc.soc_max_abs_after_600s, "offset_end_a": float(got.x[-1, -1])})
    return rows


def print_effects(fx: dict) -> None:
    print("\n5. models with diagnose effects (the test model; instructions as in 1., Cortex-M4F "
          "-Os as in 2.)")
    print("| effects | states | est_step instr. | model step instr. | estimator code B | "
          "est_t B | stack B |")
    print("|---|---|---|---|---|---|---|")
    for r in fx["cost"]:
        ins, fr = r["instructions"], r["flash_ram"]
        i1 = "- | -" if "skipped" in ins else f"{ins['est_step']:.0f} | {ins['model step']:.0f}"
        f1 = ("- | - | -" if "skipped" in fr else
              f"{fr['code_estimator']} | {fr['state_bytes']} | {fr['stack_est_step_path']}")
        print(f"| {r['effects']} | {r['states']} | {i1} | {f1} |")
    print("   LFP-like cells with hysteresis, SOC RMSE / max after 600 s, %: with the filter's "
          "hysteresis state | on the model without it")
    for r in fx["lfp"]:
        h, w = r["hysteresis"], r["without"]
        print(f"   seed {r['seed']} ({r['steps']} steps, m_v {1000 * r['m_v']:.1f} mV): "
              f"{100 * h[0]:.2f} / {100 * h[1]:.2f} | {100 * w[0]:.2f} / {100 * w[1]:.2f}")
    print(f"\n6. the current-offset state on the shared cycles (scenario offset {OFFSET_A} A): "
          "C SOC RMSE / max after 600 s, %; the offset state at the end, A")
    for r in fx["offset"]:
        print(f"   {r['cycle']}: {100 * r['c_rmse']:.2f} / {100 * r['c_max600']:.2f}; "
              f"{r['offset_end_a']:.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000, help="samples for callgrind")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the float32 reference (about 1 min per million samples)")
    ap.add_argument("--cost-only", action="store_true",
                    help="only 1. and 2. (instructions, flash and RAM)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="an [estimator] setting for 1. and 2. (e.g. resistance_slopes=false)")
    args = ap.parse_args(argv)
    model = load_model(MODEL)
    if args.cost_only:
        cfg = EstimatorConfig()
        for kv in args.set:
            k, v = kv.split("=", 1)
            old = getattr(cfg, k)
            cfg = replace(cfg, **{k: v.lower() in ("1", "true") if isinstance(old, bool)
                                  else float(v)})
        print(json.dumps({"settings": str(cfg),
                          "instructions": instructions_per_step(model, args.steps, cfg),
                          "flash_ram": flash_ram(model, cfg)}, indent=1))
        return 0
    res = {"model": MODEL.name, "instructions": instructions_per_step(model, args.steps),
           "flash_ram": flash_ram(model)}
    res["cycles"], res["covariance"] = accuracy(model, not args.no_reference)
    res["effects"] = effects(model, args.steps)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    ins = res["instructions"]
    print(f"model: {MODEL.name}; scenario: guess {GUESS}, offset {OFFSET_A} A, gain {GAIN}")
    print("\n1. instructions per step (callgrind, host x86-64 gcc -O2)")
    if "skipped" in ins:
        print(f"   skipped: {ins['skipped']}")
    else:
        print(f"   est_step {ins['est_step']:.0f} (model step inside it included); model step "
              f"alone {ins['model step']:.0f}; {ins['samples']} samples of {ins['cycle']}")
    fr = res["flash_ram"]
    print("\n2. Cortex-M4F (arm-none-eabi-gcc -Os)")
    if "skipped" in fr:
        print(f"   skipped: {fr['skipped']}")
    else:
        print(f"   code: estimator {fr['code_estimator']} B (model + estimator {fr['code_total']} B); "
              f"tables {fr['tables_total']} B (estimator adds {fr['tables_estimator']} B); "
              f"static RAM {fr['ram_static']} B")
        print(f"   RAM: <prefix>_est_t {fr['state_bytes']} B (caller-owned); stack on the "
              f"est_step path {fr['stack_est_step_path']} B (frames {fr['stack_frames']}); "
              f"libgcc/libc calls {fr['libgcc'] or 'none'}")
    print("\n3. SOC per cycle, % (reference: coulomb count of the measured current from soc0 = 1)")
    print("| cycle | steps | C RMSE | C max600 | f64 RMSE | f64 max600 | max abs dSOC C-f64 | "
          "CC RMSE | CC max600 | C == f32 ref |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in res["cycles"]:
        ex = "-" if r["bit_exact"] is None else ("identical" if r["bit_exact"] else "DIFFERENT")
        print(f"| {r['cycle']} | {r['steps']} | {100 * r['c_rmse']:.2f} | {100 * r['c_max600']:.2f} | "
              f"{100 * r['py_rmse']:.2f} | {100 * r['py_max600']:.2f} | {r['max_dsoc']:.1e} | "
              f"{100 * r['cc_rmse']:.2f} | {100 * r['cc_max600']:.2f} | {ex} |")
    worst = max(res["cycles"], key=lambda r: r["c_rmse"])
    print(f"   worst C RMSE {100 * worst['c_rmse']:.2f} % ({worst['cycle']}); worst max after "
          f"600 s {100 * max(r['c_max600'] for r in res['cycles']):.2f} %; worst abs dSOC "
          f"{max(r['max_dsoc'] for r in res['cycles']):.1e}")
    cv = res["covariance"]
    print(f"\n4. covariance over all runs: P_soc {cv['p00_start']:.2e} at the start, then in "
          f"[{cv['p00_min']:.2e}, {cv['p00_max']:.2e}]; diagonal (soc, u...) nonzero min "
          + " ".join(f"{v:.1e}" for v in cv["diag_min_nonzero"]) + ", max "
          + " ".join(f"{v:.1e}" for v in cv["diag_max"])
          + f"; all nonzero |P_ij| span {cv['span_decades']:.1f} decades; after the first "
          f"sample one update leaves at least {cv['min_p00_ratio_per_step']:.3f} of the SOC "
          "variance")
    print_effects(res["effects"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
