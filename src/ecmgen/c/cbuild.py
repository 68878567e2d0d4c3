"""Compile generated C on the host (cffi) and prove it equal to the Python models.

The generated model and a small test harness are compiled as objects with the project's
strict flags (``STRICT_CFLAGS``: C99, every warning an error, ``-ffp-contract=off``);
cffi then links them into an extension module. Modules live in a cache folder
(``$ECMGEN_CACHE``, else ``$XDG_CACHE_HOME/ecmgen`` or ``~/.cache/ecmgen``) under a name
derived from the hash of every source byte, the flags and the compiler, so a rebuild
only happens when something changed, and concurrent builds never see half a file.

:func:`c_equivalence` is what ``ecmgen build --json`` reports under ``"c"``.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.util
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import cref
from .spec import aged_efc
from .codegen import CSpec, file_names, prepare, render, state_fields
from .names import c_names

STRICT_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow",
                 "-Wdouble-promotion", "-Werror", "-ffp-contract=off")
HOST_OPT = ("-O2",)
SANITIZE_FLAGS = ("-fsanitize=undefined,address,float-cast-overflow",
                  "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g")


class CBuildError(RuntimeError):
    """The C could not be compiled or run (message carries the compiler output)."""


class CToolchainMissing(CBuildError):
    """No usable host compiler (or cffi cannot build a module here): the C cannot be
    checked on this machine, which says nothing about the C itself."""


def cache_dir() -> Path:
    env = os.environ.get("ECMGEN_CACHE")
    if env:
        base = Path(env)
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ecmgen"
    base.mkdir(parents=True, exist_ok=True)
    return base


def host_cc() -> list[str]:
    """The C compiler: $CC, else the one Python was built with, else cc."""
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    cmd = shlex.split(cc)
    if not shutil.which(cmd[0]):
        cmd = ["cc"]
    if not shutil.which(cmd[0]):
        raise CToolchainMissing("no C compiler found (set CC, or install gcc: apt-get install gcc)")
    return cmd


@functools.lru_cache(maxsize=None)
def _cc_identity(cc: tuple[str, ...]) -> str:
    try:
        out = subprocess.run([*cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except OSError as exc:
        raise CToolchainMissing(f"cannot run the C compiler {cc[0]}: {exc}") from None
    return out.splitlines()[0] if out else cc[0]


def run_cc(args: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the compiler; any failure (with -Werror: any warning) raises CBuildError."""
    proc = subprocess.run(args, capture_output=True, text=True, cwd=cwd)
    if proc.returncode != 0:
        raise CBuildError(f"compile failed: {' '.join(args)}\n{proc.stderr}")
    return proc


# --------------------------------------------------------------------------------------
# harness (test helpers compiled with the generated model, strict flags too)
# --------------------------------------------------------------------------------------

EXTRA_STATES = ("u_diff", "h", "u_x")    # state fields a model may add, recorded by the trace


def _vt(spec: CSpec) -> str:
    return "int32_t" if spec.fixed else "float"


def extra_states(spec: CSpec) -> tuple[str, ...]:
    """The optional state fields of this model (diffusion pair, effect states)."""
    names = {name for _, name, _ in state_fields(spec)}
    return tuple(f for f in EXTRA_STATES if f in names)


def _signatures(spec: CSpec) -> tuple[str, str]:
    """(trace, stress) prototypes of the harness."""
    p, t = c_names(spec.prefix, spec.numeric)["state"], _vt(spec)
    dt_arg = f"const {t} *dt, " if spec.variable_dt else ""
    extra = "".join(f", {t} *{f}" for f in extra_states(spec))
    trace = (f"void ecmh_trace({p} *s, const {t} *i, const {t} *temp, {dt_arg}{t} *v, "
             f"{t} *soc, {t} *uf, {t} *us, uint8_t *chg{extra}, size_t n)")
    if spec.fixed:
        stress = (f"void ecmh_stress({p} *s, uint32_t seed, size_t n, int32_t dt_max, "
                  "int32_t *lo, int32_t *hi, uint32_t *bad)")
    else:
        stress = (f"void ecmh_stress({p} *s, uint32_t seed, size_t n, float i_amp, "
                  "float dt_max, float *lo, float *hi, uint32_t *bad)")
    return trace, stress


def _cdef(spec: CSpec) -> str:
    nm, t = c_names(spec.prefix, spec.numeric), _vt(spec)
    st = nm["state"]
    fields = " ".join(f"{ct} {name};" for ct, name, _ in state_fields(spec))
    trace, stress = _signatures(spec)
    dt_arg = f"const {t} *dt, " if spec.variable_dt else ""
    return "\n".join([
        f"typedef struct {{ {fields} }} {st};",
        f"void {nm['init']}({st} *s, {t} soc0);",
        (f"{t} {nm['step']}({st} *s, {t} i, {t} temperature, {t} dt);" if spec.variable_dt
         else f"{t} {nm['step']}({st} *s, {t} i, {t} temperature);"),
        f"void {nm['run']}({st} *s, const {t} *i, const {t} *temperature, {dt_arg}{t} *v, "
        "size_t n);",
        trace + ";",
        stress + ";",
        "size_t ecmh_state_size(void);",
    ] + ([f"void {nm['set_age']}({st} *s, {t} efc);"] if spec.age is not None else []))


# --------------------------------------------------------------------------------------
# compile + load
# --------------------------------------------------------------------------------------

_LOADED: dict[str, object] = {}
CACHE_KEEP = 200          # modules kept in the cache folder (least recently built go first)


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except FileNotFoundError:           # pruned by another process sharing the cache
        return 0.0


def _prune(cache: Path, keep: int = CACHE_KEEP) -> None:
    mods = sorted(cache.glob("_ecmgen_c_*"), key=_mtime, reverse=True)
    for p in mods[keep:]:
        if p.stem.split(".")[0] not in _LOADED:
            p.unlink(missing_ok=True)


def _load(name: str, path: Path):
    if name in _LOADED:
        return _LOADED[name]
    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
    spec = importlib.util.spec_from_file_location(name, str(path), loader=loader)
    mod = importlib.util.module_from_spec(spec)
    loader.exec_module(mod)
    _LOADED[name] = mod
    return mod


def _harness_texts(spec: CSpec, estimator=None) -> tuple[str, str]:
    """(ecmh_harness.h, ecmh_harness.c) from templates/harness.{h,c}.j2, with the
    estimator's trace when there is one."""
    from .codegen import _env

    trace, stress = _signatures(spec)
    nm = c_names(spec.prefix, spec.numeric)
    ctx = {"p": spec.prefix, "nm": nm, "fixed": spec.fixed, "vdt": spec.variable_dt,
           "extra": extra_states(spec), "trace_sig": trace, "stress_sig": stress,
           "est": estimator, "est_trace_sig": None}
    if estimator is not None:
        from .estc import est_trace_signature

        ctx["est_trace_sig"] = est_trace_signature(spec)
    env = _env()
    return (env.get_template("harness.h.j2").render(ctx),
            env.get_template("harness.c.j2").render(ctx))


def write_sources(spec: CSpec, out_dir: Path, harness: bool = True,
                  estimator=None) -> list[Path]:
    """Generated files (+ harness.c) into out_dir; returns the .c files."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, text in render(spec, None, estimator).items():
        (out_dir / name).write_text(text)
    srcs = [out_dir / file_names(spec.prefix, spec.numeric)["source"]]
    if estimator is not None:
        srcs.append(out_dir / c_names(spec.prefix, "float")["est_source"])
    if harness:
        header, source = _harness_texts(spec, estimator)
        (out_dir / "ecmh_harness.h").write_text(header)
        (out_dir / "ecmh_harness.c").write_text(source)
        srcs.append(out_dir / "ecmh_harness.c")
    return srcs


def compile_spec(spec: CSpec, cache: Path | None = None, opt=HOST_OPT,
                 estimator=None) -> "CModel":
    """Compile (or fetch from the cache) the C of ``spec`` (with the SOC filter of
    ``estimator``, an ecmgen.c.estc.EstSpec) and return a :class:`CModel`."""
    import cffi

    cache = Path(cache) if cache is not None else cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    cc = host_cc()
    files = render(spec, None, estimator)
    harness = "".join(_harness_texts(spec, estimator))
    cdef = _cdef(spec)
    if estimator is not None:
        from . import estc

        cdef += "\n" + estc.cdef(spec, estimator)
    flags = [*STRICT_CFLAGS, *opt, "-fPIC"]
    h = hashlib.sha256()
    for part in [*(f"{k}\0{v}" for k, v in sorted(files.items())), harness, cdef, " ".join(flags),
                 _cc_identity(tuple(cc)), cffi.__version__, sys.implementation.cache_tag or ""]:
        h.update(part.encode())
        h.update(b"\0")
    key = h.hexdigest()[:24]
    name = f"_ecmgen_c_{key}"
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    so = cache / f"{name}{suffix}"
    if not so.exists():
        build = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=cache))
        try:
            objs = []
            for src in write_sources(spec, build, estimator=estimator):
                obj = src.with_suffix(".o")
                run_cc([*cc, *flags, "-I", str(build), "-c", str(src), "-o", str(obj)])
                objs.append(str(obj))
            ffi = cffi.FFI()
            ffi.cdef(cdef)
            ffi.set_source(name, '#include "ecmh_harness.h"\n', include_dirs=[str(build)],
                           extra_objects=objs)
            try:
                built = Path(ffi.compile(tmpdir=str(build), verbose=False))
            except Exception as exc:  # distutils/setuptools errors
                raise CToolchainMissing(f"cffi could not build the module: {exc}") from None
            os.replace(built, so)
        finally:
            shutil.rmtree(build, ignore_errors=True)
        _prune(cache)
    mod = _load(name, so)
    return CModel(spec, mod.ffi, mod.lib, so, estimator)


@dataclass
class CModel:
    """A compiled model. All runs start from a fresh state at ``soc0``. The temperature
    (degC, or Q8 raw for native fixed-point runs) may be left out (None) for a model that
    does not read it; the C then gets 0."""

    spec: CSpec
    ffi: object
    lib: object
    path: Path
    estimator: object = None       # the EstSpec of the SOC filter compiled with it, or None

    @property
    def _t(self):
        return np.int32 if self.spec.fixed else np.float32

    @property
    def names(self) -> dict[str, str]:
        return c_names(self.spec.prefix, self.spec.numeric)

    def new_state(self, soc0, efc=None):
        """A state from init(soc0), then set_age(efc) unless efc is None (native values)."""
        s = self.ffi.new(f"{self.names['state']} *")
        getattr(self.lib, self.names["init"])(s, soc0)
        if efc is not None:
            getattr(self.lib, self.names["set_age"])(s, efc)
        return s

    def native_efc(self, efc):
        """Equivalent full cycles as the C caller passes them (float32, or Q8 raw)."""
        if efc is None:
            return None
        return cref.efc_to_raw(efc) if self.spec.fixed else float(np.float32(efc))

    def _buf(self, a):
        return self.ffi.from_buffer(f"{'int32_t' if self.spec.fixed else 'float'}[]", a)

    def _temp(self, temp, n: int) -> np.ndarray:
        if temp is None:
            if self.spec.uses_temperature:
                raise ValueError("this model reads the cell temperature: give it")
            temp = 0
        t = np.asarray(temp, dtype=self._t)
        return np.ascontiguousarray(np.broadcast_to(t, (n,)) if t.ndim == 0 else t)

    def trace_native(self, i, dt=None, soc0=None, temp=None, efc=None) -> cref.RefResult:
        """Run on native inputs (float32 arrays, or int32 raw), recording the state."""
        t = self._t
        i = np.ascontiguousarray(i, dtype=t)
        n = i.size
        if soc0 is None:
            soc0 = cref.ONE30 if self.spec.fixed else 1.0
        s = self.new_state(soc0, efc)
        v, soc, uf, us = (np.empty(n, dtype=t) for _ in range(4))
        chg = np.empty(n, dtype=np.uint8)
        temp = self._temp(temp, n)
        if temp.size != n:
            raise ValueError("current and temperature differ in length")
        args = [s, self._buf(i), self._buf(temp)]
        if self.spec.variable_dt:
            if dt is None:
                raise ValueError("variable-dt model: give dt")
            dt = np.ascontiguousarray(dt, dtype=t)
            if dt.size != n:
                raise ValueError("current and dt differ in length")
            args.append(self._buf(dt))
        args += [self._buf(a) for a in (v, soc, uf, us)]
        args += [self.ffi.from_buffer("uint8_t[]", chg)]
        extra = {f: np.empty(n, dtype=t) for f in extra_states(self.spec)}
        args += [self._buf(a) for a in extra.values()]
        self.lib.ecmh_trace(*args, n)
        return cref.RefResult(v, soc, uf, us, chg, **extra)

    def run_native(self, i, dt=None, soc0=None, temp=None, efc=None) -> np.ndarray:
        """Voltages only, through the generated <prefix>_run loop."""
        t = self._t
        i = np.ascontiguousarray(i, dtype=t)
        if soc0 is None:
            soc0 = cref.ONE30 if self.spec.fixed else 1.0
        s = self.new_state(soc0, efc)
        v = np.empty(i.size, dtype=t)
        temp = self._temp(temp, i.size)
        run = getattr(self.lib, self.names["run"])
        if self.spec.variable_dt:
            dt = np.ascontiguousarray(dt, dtype=t)
            run(s, self._buf(i), self._buf(temp), self._buf(dt), self._buf(v), i.size)
        else:
            run(s, self._buf(i), self._buf(temp), self._buf(v), i.size)
        return v

    def native_inputs(self, current_a, dt_s=None, soc0: float = 1.0):
        """SI inputs -> what a C caller passes (float32, or raw Q integers)."""
        if self.spec.fixed:
            i = cref.current_to_raw(self.spec, current_a).astype(np.int32)
            dt = None if dt_s is None else cref.dt_to_raw(dt_s).astype(np.int32)
            return i, dt, cref.soc_to_raw(soc0)
        i = np.asarray(current_a, dtype=np.float64).astype(np.float32)
        dt = None if dt_s is None else np.asarray(dt_s, dtype=np.float64).astype(np.float32)
        return i, dt, float(np.float32(soc0))

    def native_temperature(self, temperature_c, n: int):
        """The temperature (degC, one value or per step) as the C caller passes it: float32,
        or Q8 raw; None stays None."""
        if temperature_c is None:
            return None
        t = np.broadcast_to(np.asarray(temperature_c, dtype=np.float64), (n,))
        return (cref.temperature_to_raw(t).astype(np.int32) if self.spec.fixed
                else t.astype(np.float32))

    def simulate(self, current_a, dt_s=None, soc0: float = 1.0, temperature_c=None,
                 efc=None) -> np.ndarray:
        """Voltage in V (float64) for SI inputs (``efc``: the age, equivalent full cycles)."""
        i, dt, s0 = self.native_inputs(current_a, dt_s if self.spec.variable_dt else None, soc0)
        v = self.run_native(i, dt, s0, self.native_temperature(temperature_c, i.size),
                            self.native_efc(efc))
        return cref.volts(self.spec, v) if self.spec.fixed else v.astype(np.float64)

    def reference(self, current_a, dt_s=None, soc0: float = 1.0,
                  temperature_c=None, efc=None) -> cref.RefResult:
        """The Python reference (float32 or bit-true) on the same SI inputs."""
        dt = dt_s if self.spec.variable_dt else None
        if self.spec.fixed:
            return cref.simulate_fixed(self.spec, current_a, dt, soc0, temperature_c, efc)[0]
        return cref.simulate_f32(self.spec, current_a, dt, soc0, temperature_c, efc)

    def stress(self, n: int, seed: int = 1, soc0=None, i_amp: float | None = None,
               dt_max: float = 10.0) -> dict:
        """n pseudo-random steps in a C loop (temperatures -40 .. 80 degC and the odd absurd
        one); extremes of v and SOC and a count of bad steps (non-finite values, SOC
        outside its saturation range)."""
        t = self._t
        s = self.new_state(soc0 if soc0 is not None else (cref.ONE30 if self.spec.fixed else 1.0))
        lo = np.array([np.iinfo(t).max if self.spec.fixed else np.inf] * 2, dtype=t)
        hi = np.array([np.iinfo(t).min if self.spec.fixed else -np.inf] * 2, dtype=t)
        bad = self.ffi.new("uint32_t *")
        if self.spec.fixed:
            self.lib.ecmh_stress(s, seed, n, int(cref.dt_to_raw([dt_max])[0]),
                                 self._buf(lo), self._buf(hi), bad)
            conv = [lambda r: float(cref.volts(self.spec, r)), lambda r: float(r) / cref.ONE30]
        else:
            amp = 4.0 * self.spec.i_lim_a if i_amp is None else i_amp
            self.lib.ecmh_stress(s, seed, n, amp, dt_max, self._buf(lo), self._buf(hi), bad)
            conv = [float, float]
        final = {"soc": s.soc, "u_fast": s.u_fast, "u_slow": s.u_slow}
        final.update({f: getattr(s, f) for f in extra_states(self.spec)})
        return {"v_min": conv[0](lo[0]), "v_max": conv[0](hi[0]), "soc_min": conv[1](lo[1]),
                "soc_max": conv[1](hi[1]), "bad": int(bad[0]), "final": final}


def build(model, numeric: str = "float", dt_s: float | None = None, prefix: str = "ecm",
          i_max_a: float | None = None, cache: Path | None = None) -> CModel:
    """prepare() + compile_spec() in one call."""
    return compile_spec(prepare(model, numeric=numeric, dt_s=dt_s, prefix=prefix, i_max_a=i_max_a),
                        cache=cache)


# --------------------------------------------------------------------------------------
# equivalence report
# --------------------------------------------------------------------------------------

def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype.kind == "f":
        return a.shape == b.shape and np.array_equal(a.view(np.uint32), b.astype(a.dtype).view(np.uint32))
    return a.shape == b.shape and np.array_equal(a.astype(np.int64), b.astype(np.int64))


def python_voltage(model, time_s, current_a, soc0: float, dt_s: float | None = None,
                   temperature_c=None, efc=None) -> np.ndarray:
    """The float64 model (simulate.py, with the model's diagnose effects, all of which the C
    implements) the C is compared with, at the cell temperature ``temperature_c`` (degC per
    sample or one value; None for a model that does not read it).

    dt_s None: on the record's own time stamps (dt_0 = 0, as the variable-dt C).
    dt_s given (fixed-dt C, whose every step lasts dt_s, the first one included): on the
    uniform time line t_0 + k dt_s, preceded by one rested sample so that Python's step k
    is the C's step k (simulate.py gives its first sample dt = 0)."""
    from ..model.simulate import simulate

    model = model.at_age(efc)
    current_a = np.asarray(current_a, dtype=np.float64)
    temps = None
    if temperature_c is not None:
        temps = np.broadcast_to(np.asarray(temperature_c, dtype=np.float64), current_a.shape)
    if dt_s is None:
        return simulate(model, np.asarray(time_s, dtype=np.float64), current_a, soc0,
                        temps).voltage_v
    t = dt_s * np.arange(current_a.size + 1, dtype=np.float64)
    if temps is not None:
        temps = np.concatenate((temps[:1], temps))
    return simulate(model, t, np.concatenate(([0.0], current_a)), soc0, temps).voltage_v[1:]


def compare(model, cm: CModel, time_s, current_a, soc0: float, measured_v=None,
            temperature_c=None, efc=None) -> dict:
    """Drive the compiled model and its reference over (time, current, temperature; at the
    age ``efc``, equivalent full cycles, set after init) and compare with the float64 Python
    model (simulate.py, with the model's effects) and the measurement."""
    time_s = np.asarray(time_s, dtype=np.float64)
    current_a = np.asarray(current_a, dtype=np.float64)
    dt = cref.dt_from_time(time_s)
    i_n, dt_n, s0 = cm.native_inputs(current_a, dt if cm.spec.variable_dt else None, soc0)
    got = cm.trace_native(i_n, dt_n, s0, cm.native_temperature(temperature_c, i_n.size),
                          cm.native_efc(efc))
    ref = cm.reference(current_a, dt, soc0, temperature_c, efc)
    fields = ("v", "soc", "u_fast", "u_slow", "charging") + extra_states(cm.spec)
    exact = all(_bits_equal(getattr(got, f), getattr(ref, f)) for f in fields)
    if cm.spec.fixed:
        v_c, v_ref = cref.volts(cm.spec, got.v), cref.volts(cm.spec, ref.v)
    else:
        v_c, v_ref = got.v.astype(np.float64), ref.v.astype(np.float64)
    v64 = python_voltage(model, time_s, current_a, soc0,
                         None if cm.spec.variable_dt else cm.spec.dt_s, temperature_c, efc)
    out = {
        "steps": int(time_s.size),
        "dt": "variable" if cm.spec.variable_dt else cm.spec.dt_s,
        "bit_exact_vs_reference": bool(exact),
        "max_abs_diff_vs_reference_v": float(np.max(np.abs(v_c - v_ref))) if v_c.size else 0.0,
        "max_abs_diff_vs_python_v": float(np.max(np.abs(v_c - v64))) if v_c.size else 0.0,
    }
    if temperature_c is not None and np.size(temperature_c):
        out["temperature_range_c"] = [float(np.min(temperature_c)), float(np.max(temperature_c))]
    if measured_v is not None:
        m = np.asarray(measured_v, dtype=np.float64)
        mae_c = float(np.mean(np.abs(v_c - m)))
        mae_py = float(np.mean(np.abs(v64 - m)))
        out.update({"mae_v": mae_c, "python_mae_v": mae_py, "delta_mae_v": abs(mae_c - mae_py)})
    return out


def resample_uniform(time_s, current_a, voltage_v, dt_s: float):
    """A record on a uniform grid t0 + k dt_s (current: zero-order hold as the model reads it,
    i.e. the sample whose interval (t_{k-1}, t_k] holds the instant; voltage: linear)."""
    t = np.asarray(time_s, dtype=np.float64)
    n = int(np.floor((t[-1] - t[0]) / dt_s)) + 1
    tu = t[0] + dt_s * np.arange(n)
    # tolerance: t0 + k dt_s lands a rounding error after a sample taken at that instant
    idx = np.clip(np.searchsorted(t, tu - 1e-6 * dt_s, side="left"), 0, t.size - 1)
    iu = np.asarray(current_a, dtype=np.float64)[idx]
    vu = None if voltage_v is None else np.interp(tu, t, np.asarray(voltage_v, dtype=np.float64))
    return tu, iu, vu


def c_equivalence(model, series, soc0: float | None = None, *, dt_s: float | None = None,
                  prefix: str = "ecm", i_max_a: float | None = None,
                  cache: Path | None = None, numerics=("float", "fixed")) -> dict:
    """The ``"c"`` block of ``ecmgen build --json``: for numeric float and fixed, the C's MAE
    against the measured voltage and its largest difference from the float64 Python model,
    plus bit-exactness against the float32 / bit-true references. The C and Python both run
    at the record's cell temperature (``series.temperature_c``; needed by a model over
    temperature).

    ``dt_s=None`` (default): variable-dt builds driven by the record's own time stamps.
    ``dt_s`` given: fixed-dt builds; the record is resampled to the uniform grid of dt_s
    (see resample_uniform) and the float64 Python model is driven on that same grid.
    ``model``: EcmModel or model.json path; ``soc0`` None: from the record's first rested
    sample (simulate.initial_soc), as validation does. Raises CBuildError without a compiler."""
    from ..model.simulate import initial_soc
    from .codegen import _as_model

    model = _as_model(model)
    if soc0 is None:
        soc0 = float(initial_soc(model, series))
    temps = series.temperature_c
    if dt_s is None:
        t, i, v = series.time_s, series.current_a, series.voltage_v
    else:
        t, i, v = resample_uniform(series.time_s, series.current_a, series.voltage_v, dt_s)
        if temps is not None:
            temps = resample_uniform(series.time_s, temps, None, dt_s)[1]
    out = {}
    for numeric in numerics:
        cm = build(model, numeric=numeric, dt_s=dt_s, prefix=prefix, i_max_a=i_max_a, cache=cache)
        out[numeric] = compare(model, cm, t, i, soc0, v, temps)
        if model.ageing is not None:    # and the cell at the law's middle age
            efc = aged_efc(model.ageing.equivalent_full_cycles)
            out[numeric]["aged"] = dict(compare(model, cm, t, i, soc0, None, temps, efc),
                                        equivalent_full_cycles=efc)
    return out

