"""The generated SOC estimator on Cortex-M: cross-compile it, measure it, and run it under
QEMU bit for bit against the host build (the estimator's counterpart of
:mod:`ecmgen.c.target`, whose startup code, linker script and QEMU runner it reuses).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from . import target
from .cbuild import STRICT_CFLAGS, CBuildError, compile_spec
from .codegen import CSpec, prepare, render
from .names import c_names
from .estc import EstSpec, prepare_estimator
from .estcheck import run_estimator_c
from .target import CPUS, GCC, SECTION_FLAGS, _array, _run


def cross_compile_estimator(spec: CSpec, est: EstSpec, out_dir, cpu: str = "m4f",
                            opt: str = "-Os", extra=()) -> tuple[target.CrossObject, ...]:
    """<prefix>_ecm_f32.c and <prefix>_est_f32.c -> objects for ``cpu`` (STRICT_CFLAGS):
    (the model's, the estimator's)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, text in render(spec, None, est).items():
        (out_dir / name).write_text(text)
    nm = c_names(spec.prefix, spec.numeric)
    objs = []
    for src in (nm["source"], nm["est_source"]):
        obj = out_dir / f"{src[:-2]}.{cpu}.o"
        proc = _run([GCC, *CPUS[cpu]["flags"], *STRICT_CFLAGS, opt, *SECTION_FLAGS, *extra,
                     "-I", out_dir, "-c", out_dir / src, "-o", obj], cwd=out_dir)
        objs.append(target.CrossObject(obj, cpu, opt, proc.stderr.strip()))
    return tuple(objs)


def firmware_main(spec: CSpec, est: EstSpec, i, temp, dt, v, soc0: float) -> str:
    """main(): est_init, est_step over the inputs, then the predicted voltages, states and
    covariances (n x (1 + N + N^2) floats) written through semihosting."""
    nm, n, N = c_names(spec.prefix, "float"), int(np.size(i)), est.n
    p = spec.prefix
    arrays = "".join(_array(f"{p}_in_{k}", a, False) for k, a in
                     (("i", i), ("t", temp), ("dt", dt), ("v", v)))
    return target.render_main([{
        "p": p, "nm": nm, "est": True, "n": n, "header": nm["est_header"], "t": "float",
        "w": 1 + N + N * N, "nn": N * N, "fields": est.fields, "size": (1 + N + N * N) * n,
        "soc0": f"{float(np.float32(soc0)).hex()}f", "arrays": arrays}])


def build_firmware(spec: CSpec, est: EstSpec, inputs: tuple, soc0: float, out_dir,
                   cpu: str = "m4f", opt: str = "-O2") -> Path:
    out_dir = Path(out_dir)
    flags = CPUS[cpu]["flags"]
    objs = [o.obj for o in cross_compile_estimator(spec, est, out_dir, cpu=cpu, opt=opt)]
    (out_dir / "startup.c").write_text(target.STARTUP)
    (out_dir / "fw_main.c").write_text(firmware_main(spec, est, *inputs, soc0))
    (out_dir / "link.ld").write_text(target.LINKER_SCRIPT)
    for name in ("startup.c", "fw_main.c"):
        obj = out_dir / name.replace(".c", ".o")
        _run([GCC, *flags, "-std=gnu99", "-O2", "-ffp-contract=off", "-I", out_dir, "-c",
              out_dir / name, "-o", obj], cwd=out_dir)
        objs.append(obj)
    elf = out_dir / f"fw_est_{cpu}.elf"
    _run([GCC, *flags, "-nostartfiles", "-T", out_dir / "link.ld", *objs, "-lgcc", "-o", elf],
         cwd=out_dir)
    return elf


def qemu_estimator_equivalence(model, time_s, current_a, voltage_v, soc0: float,
                               temperature_c=None, cfg=None, cpu: str = "m4f", opt: str = "-O2",
                               cache=None) -> dict:
    """The estimator over a record on the emulated Cortex-M4F and on the host (cffi): every
    predicted voltage, state and covariance entry compared bit for bit."""
    from . import cref

    if CPUS[cpu]["machine"] is None or cpu != "m4f":
        raise CBuildError("the float estimator runs on the Cortex-M4F (hard float) image")
    spec = prepare(model, numeric="float", prefix="fe")
    est = prepare_estimator(model, spec, cfg)
    f32 = np.float32
    n = int(np.size(current_a))
    dt = cref.dt_from_time(np.asarray(time_s, dtype=np.float64))
    temp = np.broadcast_to(np.asarray(0.0 if temperature_c is None else temperature_c,
                                      dtype=np.float64), (n,))
    inputs = tuple(np.asarray(a, dtype=np.float64).astype(f32)
                   for a in (current_a, temp, dt, voltage_v))
    host = run_estimator_c(compile_spec(spec, cache=cache, estimator=est), *inputs[:1],
                           inputs[2], inputs[3], soc0, inputs[1])
    with tempfile.TemporaryDirectory(prefix="ecmgen-qemu-est-") as tmp:
        raw = target.run_qemu(build_firmware(spec, est, inputs, soc0, tmp, cpu, opt), cpu=cpu)
    N = est.n
    w = 1 + N + N * N
    if len(raw) != 4 * w * n:
        raise CBuildError(f"target wrote {len(raw)} bytes, expected {4 * w * n}")
    arr = np.frombuffer(raw, dtype=np.uint32).reshape(n, w)
    fields = {"v_pred": (arr[:, 0], host.v_pred), "x": (arr[:, 1:1 + N], host.x),
              "p": (arr[:, 1 + N:], host.p.reshape(n, N * N))}
    per = {k: int(np.count_nonzero(a != np.ascontiguousarray(b).view(np.uint32)))
           for k, (a, b) in fields.items()}
    return {"cpu": CPUS[cpu]["name"], "machine": CPUS[cpu]["machine"], "steps": n,
            "mismatches": per, "bit_exact": sum(per.values()) == 0}


def estimator_sizes(model, cfg=None, cpu: str = "m4f", opt: str = "-Os") -> dict:
    """Flash / RAM of the estimator on ``cpu``: its object (code, tables) beside the
    model's, sizeof(<prefix>_est_t) and the stack frames of est_step and of what it calls
    (from -fstack-usage, both objects)."""
    from .estc import est_state_bytes

    spec = prepare(model, numeric="float", prefix="fe")
    est = prepare_estimator(model, spec, cfg)
    with tempfile.TemporaryDirectory(prefix="ecmgen-est-size-") as tmp:
        m_obj, e_obj = (o.obj for o in cross_compile_estimator(spec, est, Path(tmp), cpu=cpu,
                                                                opt=opt))
        a, b = target.sizes(e_obj), target.sizes(m_obj)
        su = target.stack_usage(m_obj) | target.stack_usage(e_obj)
        funcs = sorted(set(target.undefined_symbols(e_obj)) - {spec.prefix + "_step_f32",
                                                               spec.prefix + "_init_f32",
                                                               spec.prefix + "_model_f32"})
    frames = {k: v for k, v in su.items() if not k.endswith(("_init_f32", "_run_f32"))}
    return {"cpu": CPUS[cpu]["name"], "opt": opt,
            "code_total": a["code"] + b["code"], "code_estimator": a["code"],
            "tables_total": a["tables"] + b["tables"], "tables_estimator": a["tables"],
            "ram_static": a["ram"] + b["ram"], "state_bytes": est_state_bytes(spec, est),
            "stack_frames": frames,
            "stack_est_step": sum(frames.values()),     # est_step + what it calls, at most
            "libgcc": funcs}
