"""The generated C on Cortex-M: cross-compile, measure, and run it under QEMU.

* :func:`cross_compile` builds a generated model for a CPU profile (``CPUS``) with the
  project's strict flags; :func:`sizes` reads flash/RAM from ``arm-none-eabi-size -A``
  (code = ``.text*``, tables = ``.rodata*``, RAM = ``.data*`` + ``.bss*``; the caller's
  state struct and the stack come on top, see :func:`stack_usage`).
* :func:`float_instructions` / :func:`float_helpers` prove a fixed-point object free of
  floating point (no FPU instruction, no soft-float helper call).
* :func:`qemu_equivalence` links several generated models (distinct prefixes) into one
  bare-metal image for ``qemu-system-arm -M mps2-an386`` (Cortex-M4F) or ``mps2-an385``
  (Cortex-M3, soft float), runs them over a stretch of a real record with semihosting, and
  compares every output and SOC (and, for models with effects, the effect states ``h`` and
  ``u_x``) with the host build bit for bit.

Tools: Debian/Ubuntu ``apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm`` (``INSTALL_HINT``); :func:`missing_tools` tells what is absent.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cbuild import STRICT_CFLAGS, CBuildError, compile_spec, extra_states
from .codegen import CSpec, file_names, prepare, render
from .names import c_names
from .runtime import templates_dir

INSTALL_HINT = "sudo apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm"
GCC, SIZE, NM, OBJDUMP, QEMU = ("arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm",
                                "arm-none-eabi-objdump", "qemu-system-arm")

CPUS = {
    "m4f": {"flags": ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"),
            "machine": "mps2-an386", "name": "Cortex-M4F (hard float)"},
    "m3": {"flags": ("-mcpu=cortex-m3", "-mthumb", "-mfloat-abi=soft"),
           "machine": "mps2-an385", "name": "Cortex-M3 (soft float)"},
    "m0": {"flags": ("-mcpu=cortex-m0", "-mthumb", "-mfloat-abi=soft"),
           "machine": None, "name": "Cortex-M0 (soft float)"},
}
SECTION_FLAGS = ("-ffunction-sections", "-fdata-sections", "-fstack-usage")


def missing_tools(qemu: bool = True) -> list[str]:
    tools = [GCC, SIZE, NM, OBJDUMP] + ([QEMU] if qemu else [])
    return [t for t in tools if shutil.which(t) is None]


def skip_reason(qemu: bool = True) -> str | None:
    """None when the cross tools are there, else a message naming them and the install."""
    miss = missing_tools(qemu)
    if not miss:
        return None
    return f"{', '.join(miss)} not found; install with: {INSTALL_HINT}"


def _run(args, cwd=None, timeout=120) -> subprocess.CompletedProcess:
    try:
        proc = subprocess.run([str(a) for a in args], capture_output=True, text=True, cwd=cwd,
                              timeout=timeout)
    except FileNotFoundError:
        raise CBuildError(f"{args[0]} not found; install with: {INSTALL_HINT}") from None
    if proc.returncode != 0:
        raise CBuildError(f"{' '.join(map(str, args))} failed ({proc.returncode}):\n"
                          f"{proc.stdout}{proc.stderr}")
    return proc


# --------------------------------------------------------------------------------------
# compile + measure
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CrossObject:
    obj: Path
    cpu: str
    opt: str
    warnings: str        # compiler stderr (empty: no warnings; -Werror makes them fatal anyway)


def cross_compile(spec: CSpec, out_dir, cpu: str = "m4f", opt: str = "-Os",
                  extra=()) -> CrossObject:
    """Generated <prefix>_ecm.c of ``spec`` -> object for ``cpu`` with STRICT_CFLAGS."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, text in render(spec).items():
        (out_dir / name).write_text(text)
    src = out_dir / file_names(spec.prefix, spec.numeric)["source"]
    obj = out_dir / f"{spec.prefix}_ecm.{cpu}.o"
    proc = _run([GCC, *CPUS[cpu]["flags"], *STRICT_CFLAGS, opt, *SECTION_FLAGS, *extra,
                 "-I", out_dir, "-c", src, "-o", obj], cwd=out_dir)
    return CrossObject(obj, cpu, opt, proc.stderr.strip())


def sizes(obj) -> dict:
    """Bytes by kind from ``arm-none-eabi-size -A``: code (.text*), tables (.rodata*),
    data (.data*), bss (.bss*); flash = code + tables + data, ram = data + bss."""
    out = _run([SIZE, "-A", obj]).stdout
    res = {"code": 0, "tables": 0, "data": 0, "bss": 0, "sections": {}}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) < 2 or not parts[1].isdigit() or not parts[0].startswith("."):
            continue
        name, size = parts[0], int(parts[1])
        if size == 0:
            continue
        res["sections"][name] = size
        if name.startswith(".text"):
            res["code"] += size
        elif name.startswith(".rodata") or name.startswith(".data.rel.ro"):
            res["tables"] += size
        elif name.startswith(".data"):
            res["data"] += size
        elif name.startswith(".bss"):
            res["bss"] += size
    res["flash"] = res["code"] + res["tables"] + res["data"]
    res["ram"] = res["data"] + res["bss"]
    return res


def stack_usage(obj) -> dict[str, int]:
    """Frame bytes per function from the -fstack-usage file next to the object."""
    su = Path(obj).with_suffix(".su")
    out = {}
    if su.exists():
        for line in su.read_text().splitlines():
            parts = line.split("\t")
            if len(parts) >= 2 and parts[1].isdigit():
                out[parts[0].rsplit(":", 1)[-1]] = int(parts[1])
    return out


def undefined_symbols(obj) -> list[str]:
    out = _run([NM, "-u", obj]).stdout
    return sorted(line.split()[-1] for line in out.splitlines() if line.strip())


_SOFT_FLOAT = re.compile(r"^__(aeabi_(f|d|[iu]i?2[fd]|[fd]2|l2[fd]|ul2[fd]|cf|cd)|"
                         r"(add|sub|mul|div|neg)[sdt]f3|float|fix|extend|trunc)")
_VFP = re.compile(r"\s(v[a-z]+(\.[a-z0-9]+)*)\s")


def float_helpers(obj) -> list[str]:
    """Soft-float library routines the object calls (must be empty for numeric=fixed)."""
    return [s for s in undefined_symbols(obj) if _SOFT_FLOAT.match(s)]


def float_instructions(obj) -> list[str]:
    """FPU (VFP) instructions in the object's code (must be empty for numeric=fixed)."""
    out = _run([OBJDUMP, "-d", obj]).stdout
    return [line.strip() for line in out.splitlines() if _VFP.search(line + " ")]


# --------------------------------------------------------------------------------------
# bare-metal image for QEMU
# --------------------------------------------------------------------------------------

# the image's startup code and linker script (C a reviewer can lint, in templates/)
STARTUP = (templates_dir() / "target_startup.c.j2").read_text()
LINKER_SCRIPT = (templates_dir() / "target_mps2.ld.j2").read_text()

OUT_NAME = "ecmh_out.bin"


@dataclass(frozen=True)
class TargetRun:
    """One model to run on the target: its spec and the native inputs (float32 or raw int32;
    temp: the cell temperature per step, degC or Q8; None: 0, for a model that ignores it)."""

    spec: CSpec
    i: np.ndarray
    dt: np.ndarray | None
    soc0: float | int
    temp: np.ndarray | None = None
    efc: float | int | None = None      # the age set after init (native); None: not set

    @property
    def fields(self) -> tuple[str, ...]:
        """What the firmware records per step, in this order (n values each): the voltage,
        SOC and every optional state the model has (u_diff, h, u_x)."""
        return ("v", "soc") + extra_states(self.spec)


def _array(name: str, a: np.ndarray, fixed: bool) -> str:
    if fixed:
        vals = [str(int(x)) for x in np.asarray(a, dtype=np.int32)]
        ctype, wrap = "int32_t", "{}"
    else:
        vals = [f"0x{int(x):08x}u" for x in np.asarray(a, dtype=np.float32).view(np.uint32)]
        ctype, wrap = "ecmh_f32_t", "{{{}}}"
    body = ",\n".join(", ".join(wrap.format(v) for v in vals[k:k + 8]) for k in range(0, len(vals), 8))
    return f"static const {ctype} {name}[{len(vals)}] = {{\n{body}\n}};\n"


def render_main(runs: list[dict]) -> str:
    """fw_main.c from templates/target_main.c.j2: ``runs`` as :func:`firmware_main` and
    ecmgen.c.esttarget make them."""
    from .codegen import _env

    return _env().get_template("target_main.c.j2").render(runs=runs, out_name=OUT_NAME)


def firmware_main(runs: list[TargetRun]) -> str:
    """main(): every model over its inputs; voltage, SOC and the optional states of each."""
    out = []
    for r in runs:
        p, fixed, n = r.spec.prefix, r.spec.fixed, int(r.i.size)
        temp = np.zeros(n) if r.temp is None else r.temp
        ins = [("i", r.i), ("t", temp)] + ([("dt", r.dt)] if r.spec.variable_dt else [])
        out.append({"p": p, "nm": c_names(p, r.spec.numeric), "est": False, "n": n,
                    "header": c_names(p, r.spec.numeric)["header"],
                    "t": "int32_t" if fixed else "float", "f": "" if fixed else ".f",
                    "vdt": r.spec.variable_dt, "fields": r.fields, "size": len(r.fields) * n,
                    "soc0": str(int(r.soc0)) if fixed else f"{float(np.float32(r.soc0)).hex()}f",
                    "efc": None if r.efc is None else str(int(r.efc)) if fixed
                    else f"{float(np.float32(r.efc)).hex()}f",
                    "arrays": "".join(_array(f"{p}_in_{k}", a, fixed) for k, a in ins)})
    return render_main(out)


def build_firmware(runs: list[TargetRun], out_dir, cpu: str = "m4f", opt: str = "-O2") -> Path:
    """One ELF with every model of ``runs`` (distinct prefixes) and their inputs."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    flags = CPUS[cpu]["flags"]
    objs = []
    for r in runs:
        objs.append(cross_compile(r.spec, out_dir, cpu=cpu, opt=opt).obj)
    (out_dir / "startup.c").write_text(STARTUP)
    (out_dir / "fw_main.c").write_text(firmware_main(runs))
    (out_dir / "link.ld").write_text(LINKER_SCRIPT)
    for name in ("startup.c", "fw_main.c"):
        obj = out_dir / name.replace(".c", ".o")
        _run([GCC, *flags, "-std=gnu99", "-O2", "-ffp-contract=off", "-I", out_dir, "-c",
              out_dir / name, "-o", obj], cwd=out_dir)
        objs.append(obj)
    elf = out_dir / f"fw_{cpu}.elf"
    _run([GCC, *flags, "-nostartfiles", "-T", out_dir / "link.ld", *objs, "-lgcc", "-o", elf],
         cwd=out_dir)
    return elf


def run_qemu(elf, cpu: str = "m4f", timeout: float = 120) -> bytes:
    """Run the image; return what it wrote through semihosting."""
    machine = CPUS[cpu]["machine"]
    if machine is None:
        raise CBuildError(f"no QEMU machine for {cpu}")
    work = Path(elf).parent
    out = work / OUT_NAME
    out.unlink(missing_ok=True)
    try:
        proc = subprocess.run([QEMU, "-M", machine, "-nographic", "-monitor", "none",
                               "-serial", "none", "-semihosting-config", "enable=on,target=native",
                               "-kernel", str(elf)], capture_output=True, text=True, cwd=work,
                              timeout=timeout)
    except FileNotFoundError:
        raise CBuildError(f"{QEMU} not found; install with: {INSTALL_HINT}") from None
    except subprocess.TimeoutExpired:
        raise CBuildError(f"QEMU ({machine}) did not finish within {timeout} s") from None
    if proc.returncode != 0:
        raise CBuildError(f"firmware exited with status {proc.returncode} on {machine} "
                          f"(99 = fault):\n{proc.stdout}{proc.stderr}")
    return out.read_bytes()


def qemu_equivalence(model, time_s, current_a, soc0: float, cpu: str = "m4f",
                     variants=(("float", None), ("float", 0.1), ("fixed", None), ("fixed", 0.1)),
                     out_dir=None, cache=None, temperature_c=None, efc=None) -> dict:
    """Run the generated models on the emulated target and on the host (cffi) over the same
    inputs; compare voltages and SOC (and the optional states u_diff, h, u_x) bit for bit.
    ``variants``: (numeric, dt_s) pairs; a fixed-dt variant ignores the record's time
    stamps (each step lasts dt_s). ``model``: one model, or a dict numeric -> model (a model
    per numeric, e.g. with different effects). ``temperature_c``: the cell temperature per
    step (degC), for models that read it; ``efc``: the age set after init (equivalent full
    cycles, a model with an ageing law)."""
    import tempfile

    from . import cref

    if cpu != "m4f":
        variants = tuple(v for v in variants if v[0] == "fixed")   # soft-float CPUs: fixed only
    t = np.asarray(time_s, dtype=np.float64)
    dt = cref.dt_from_time(t)
    runs, host, fx_names = [], [], []
    for numeric, dt_s in variants:
        prefix = f"{'f' if numeric == 'float' else 'q'}{'v' if dt_s is None else 'd'}"
        mdl = model[numeric] if isinstance(model, dict) else model
        spec = prepare(mdl, numeric=numeric, dt_s=dt_s, prefix=prefix)
        fx_names.append([e.name for e in (getattr(mdl, "effects", ()) or ())])
        cm = compile_spec(spec, cache=cache)
        i_n, dt_n, s0 = cm.native_inputs(current_a, dt if dt_s is None else None, soc0)
        t_n = cm.native_temperature(temperature_c, i_n.size)
        e_n = cm.native_efc(efc)
        ref = cm.trace_native(i_n, dt_n, s0, t_n, e_n)
        runs.append(TargetRun(spec, i_n, dt_n, s0, t_n, e_n))
        host.append(ref)
    tmp = None
    if out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="ecmgen-qemu-")
        out_dir = tmp.name
    try:
        elf = build_firmware(runs, out_dir, cpu=cpu)
        raw = run_qemu(elf, cpu=cpu)
    finally:
        if tmp is not None:
            tmp.cleanup()
    res = {"cpu": CPUS[cpu]["name"], "machine": CPUS[cpu]["machine"], "steps": int(t.size),
           "variants": {}}
    off = 0
    for r, h, names in zip(runs, host, fx_names):
        n = r.i.size
        dtype = np.int32 if r.spec.fixed else np.float32
        nf = len(r.fields)
        if off + 4 * nf * n > len(raw):
            raise CBuildError(f"target wrote {len(raw)} bytes, expected more than {off + 4 * nf * n}")
        arr = np.frombuffer(raw, dtype=dtype, count=nf * n, offset=off)
        off += 4 * nf * n
        name = f"{r.spec.numeric}/{'variable-dt' if r.spec.variable_dt else f'dt={r.spec.dt_s}'}"
        per_field = {}
        for j, f in enumerate(r.fields):
            got = arr[j * n:(j + 1) * n].view(np.uint32 if dtype == np.float32 else np.int32)
            ref = np.ascontiguousarray(getattr(h, f), dtype=dtype)
            ref = ref.view(np.uint32) if dtype == np.float32 else ref
            per_field[f] = int(np.count_nonzero(got != ref))
        mism = sum(per_field.values())
        res["variants"][name] = {"steps": int(n), "mismatches": mism, "bit_exact": mism == 0,
                                 "fields": per_field, "effects": names}
    if off != len(raw):
        raise CBuildError(f"target wrote {len(raw)} bytes, expected {off}")
    return res
