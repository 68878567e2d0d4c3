"""model.json -> C for BMS microcontrollers: ``<prefix>_ecm.h`` / ``<prefix>_ecm.c``.

The generated C holds only ``static const`` tables and three thin functions; the step
itself is the hand-written runtime in ``c_runtime/`` (copied beside the generated files).
Two numerics:

``float``  IEEE binary32 tables, literals with 9 significant digits (they round-trip).
``fixed``  int32 tables in Q formats chosen here from the model's value ranges; int64
           intermediates, rounding half up, saturation; no floating point at all.

Two time-step modes:

variable dt (``dt_s=None``)  ``step(state, i, dt)``; the coefficients c = 1 - exp(-dt/tau)
    are computed at run time from the interpolated tau, exactly as ``simulate.py`` does
    (float: a deterministic exp built from + - * ; fixed: integer exp). This is the mode
    that runs the measured, non-uniform drive cycles.
fixed dt (``dt_s`` given)    ``step(state, i)``; D = 1 / (1 - exp(-dt_s/tau)) is precomputed
    per breakpoint, interpolated in SOC, and the step divides by it (no exp). D = tau/dt +
    1/2 + dt/(12 tau) + ... is nearly linear in tau, so this matches ``simulate.py`` (which
    interpolates tau) exactly at the breakpoints and to second order in dt/tau between them;
    interpolating c itself would not (c ~ dt/tau is convex in tau).

Every constant the C uses is computed once here (float64 maths, then rounded once to
float32 or quantised once to an integer, :mod:`ecmgen.c.qformat`) into a :class:`CSpec`;
both the renderer and the Python references in :mod:`ecmgen.c.cref` read that spec, so
"what the C does" has one definition. Same model + options -> byte-identical files.

This module only writes C; compiling it and proving it equal to the references is
:mod:`ecmgen.c.cbuild`, and the build's C stage (generate, then check) is
:mod:`ecmgen.c.check`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import InputError
from ..files import write_atomic
from ..model.model import DIRECTIONS, RC_FIELDS, EcmModel, load_model
from .qformat import CDR_E_MAX, INT32_MAX, Q30, Q_D, _q_fit, cdr_table, quantize

NUMERICS = ("float", "fixed")
RUNTIME_FILES = {"float": ("ecmrt.h", "ecmrt_f32.h"), "fixed": ("ecmrt.h", "ecmrt_q.h")}
# extra runtime headers of a model that carries diagnose effects (the last one is included)
RUNTIME_FX_FILES = {"float": ("ecmrt_fx.h", "ecmrt_f32_fx.h"), "fixed": ("ecmrt_fx.h", "ecmrt_q_fx.h")}
# effects (ecmgen.model.effects) the generated C implements, per numeric
C_EFFECTS = {"float": ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error"),
             "fixed": ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error")}
CDR_X_MAX = 1e9             # largest |i| / i0_a the float asinh handles (x^2 must stay finite)
MAX_POINTS = 255            # segment hints are uint8_t
DEFAULT_I_MAX_C = 32.0      # default current range: 32 C, rounded up to a power of two

_PREFIX_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")
_RESERVED = {"ecmrt", "int", "float", "double", "char", "void", "static", "const", "return"}


def _find_dir(name: str) -> Path:
    """templates/ and c_runtime/: inside the installed package (a wheel or sdist carries
    them as ecmgen/templates and ecmgen/c_runtime, see pyproject.toml), else at the
    repository root (an editable install of a checkout, src/ecmgen -> ../../)."""
    here = Path(__file__).resolve().parents[1]    # the ecmgen package (this is ecmgen/c/)
    for cand in (here / name, here.parents[1] / name):
        if cand.is_dir():
            return cand
    raise FileNotFoundError(f"ecmgen: {name}/ not found (looked in {here} and "
                            f"{here.parents[1]}): a broken installation")


def templates_dir() -> Path:
    return _find_dir("templates")


def runtime_dir() -> Path:
    return _find_dir("c_runtime")


# --------------------------------------------------------------------------------------
# the spec: every number the C contains
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CGrid:
    """SOC breakpoints and 1/spacing, as emitted (float32 values or int64 raw integers)."""

    x: np.ndarray
    inv_dx: np.ndarray

    @property
    def n(self) -> int:
        return int(self.x.size)


@dataclass(frozen=True)
class CDir:
    """Tables of one current direction. k_fast/k_slow: tau (variable dt) or
    D = 1/(1 - exp(-dt/tau)) (fixed dt)."""

    grid: CGrid
    r0: np.ndarray
    r_fast: np.ndarray
    k_fast: np.ndarray
    r_slow: np.ndarray
    k_slow: np.ndarray


@dataclass(frozen=True)
class CSpec:
    """Everything the generated C holds, for one (model, numeric, dt) choice.

    numeric "float": arrays are np.float32, scalars np.float32.
    numeric "fixed": arrays are np.int64 holding int32 raw values; ``q`` the formats."""

    prefix: str
    numeric: str
    variable_dt: bool
    dt_s: float | None
    ocv_grid: CGrid
    ocv: np.ndarray
    dirs: tuple[CDir, CDir]            # (discharge, charge), index = state.charging
    deadband: object                   # float32 A or int Q_I
    k_soc: object                      # float32 or int (scaled by the formats in q)
    i_lim_a: float                     # saturation of the current (power of two)
    q: dict = field(default_factory=dict)
    model_sha256: str = ""
    tool_version: str = __version__
    capacity_ah: float = 0.0
    notes: tuple[str, ...] = ()
    fx: dict = field(default_factory=dict)   # effects: {} for a plain 2RC model, else
                                             # "hyst"/"xrc"/"cdr" flags + their constants

    @property
    def fixed(self) -> bool:
        return self.numeric == "fixed"

    @property
    def has_fx(self) -> bool:
        return bool(self.fx)


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------

def _as_model(model) -> EcmModel:
    if isinstance(model, EcmModel):
        return model
    if isinstance(model, (str, Path)):
        return load_model(model)
    raise TypeError(f"expected an EcmModel or a model.json path, got {type(model).__name__}")


def check_options(prefix: str, numeric: str, dt_s, i_max_a) -> None:
    if not isinstance(prefix, str) or not _PREFIX_RE.match(prefix) or prefix.lower() in _RESERVED:
        raise InputError(None, f"[c] prefix {prefix!r} is not usable: it must be a C identifier "
                               "of 1-32 letters, digits or '_' starting with a letter")
    if numeric not in NUMERICS:
        raise InputError(None, f"[c] numeric must be \"float\" or \"fixed\", got {numeric!r}")
    if dt_s is not None:
        if not isinstance(dt_s, (int, float)) or not math.isfinite(dt_s) or not 0 < dt_s <= 3600:
            raise InputError(None, f"[c] dt_s must be a number of seconds in (0, 3600], got {dt_s!r}")
    if i_max_a is not None:
        if not isinstance(i_max_a, (int, float)) or not math.isfinite(i_max_a) or not 0 < i_max_a <= 1e5:
            raise InputError(None, f"[c] i_max_a must be a current in (0, 1e5] A, got {i_max_a!r}")


def check_effects(model: EcmModel, numeric: str, i_lim_a: float | None = None) -> None:
    """Refuse, with one clear line, an effect the C of ``numeric`` does not implement."""
    seen = set()
    for e in getattr(model, "effects", ()) or ():
        name = e.name
        if name == "temperature_dependence":
            raise InputError(None, "[c] effect temperature_dependence is not supported in the "
                                   "generated C (it needs a cell temperature input the C step "
                                   "does not have); remove it from the model to generate C")
        if name not in C_EFFECTS.get(numeric, ()):
            other = [n for n in NUMERICS if name in C_EFFECTS[n]]
            hint = f"; use numeric=\"{other[0]}\"" if other else ""
            raise InputError(None, f"[c] effect {name} is not supported in numeric={numeric!r} "
                                   f"yet{hint}")
        if name in seen and name != "capacity_error":
            raise InputError(None, f"[c] effect {name} appears more than once; the C supports "
                                   "each effect once")
        seen.add(name)
        if name == "current_dependent_resistance" and i_lim_a is not None \
                and i_lim_a / e.i0_a > CDR_X_MAX:
            raise InputError(None, f"[c] effect current_dependent_resistance: i0_a = {e.i0_a:g} A "
                                   f"is too small for the current range {i_lim_a:g} A")


def validate_for_c(model: EcmModel, path=None) -> None:
    """Refuse, with one clear line, a model the C cannot represent. (load_model already
    refuses bad schema versions, missing tables and non-finite values in model.json; this
    repeats the checks for models built in memory and adds the C limits.)"""
    def arr(a, name):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 1 or a.size == 0:
            raise InputError(path, f"{name} must be a non-empty 1-D table")
        if not np.all(np.isfinite(a)):
            raise InputError(path, f"{name} has non-finite values (NaN or inf)")
        return a

    cap = float(model.capacity_ah)
    if not math.isfinite(cap) or cap <= 0:
        raise InputError(path, f"capacity_ah must be a positive number, got {model.capacity_ah!r}")
    db = float(model.direction_deadband_a)
    if not math.isfinite(db) or db < 0:
        raise InputError(path, f"direction_deadband_a must be >= 0, got {model.direction_deadband_a!r}")
    if model.charge.has_diffusion or model.charge.has_butler_volmer:
        # TODO(issue 8): the diffusion pair and the Butler-Volmer fast branch in the C step
        raise InputError(path, "C generation for a model with a diffusion RC pair or a "
                               "Butler-Volmer fast branch is not supported yet")
    if model.needs_temperature:
        # TODO(issue 8): the C step over (temperature, SOC) tables
        raise InputError(path, "C generation for a model with tables over temperature is not "
                               "supported yet")
    grids = {"ocv": arr(model.ocv.soc, "ocv.soc")}
    ocv = arr(model.ocv.ocv_v[0], "ocv.ocv_v")
    if ocv.size != grids["ocv"].size:
        raise InputError(path, "ocv.soc and ocv.ocv_v differ in length")
    if np.any(ocv <= 0) or np.any(ocv > 100):
        raise InputError(path, "ocv.ocv_v must lie in (0, 100] V")
    for d in DIRECTIONS:
        t = model.table(d)
        grids[d] = arr(t.soc, f"rc.{d}.soc")
        for k in RC_FIELDS:
            a = arr(getattr(t, k)[0], f"rc.{d}.{k}")
            if a.size != grids[d].size:
                raise InputError(path, f"rc.{d}.{k} has {a.size} values, soc has {grids[d].size}")
            if k.startswith("tau"):
                if np.any(a <= 0) or np.any(a > 1e6):
                    raise InputError(path, f"rc.{d}.{k} must lie in (0, 1e6] s")
                if np.any(a < 1e-3):
                    raise InputError(path, f"rc.{d}.{k} has time constants below 1 ms")
            elif np.any(a < 0) or np.any(a > 100):
                raise InputError(path, f"rc.{d}.{k} must lie in [0, 100] ohm")
    for name, x in grids.items():
        where = "ocv.soc" if name == "ocv" else f"rc.{name}.soc"
        if x.size > MAX_POINTS:
            raise InputError(path, f"{where} has {x.size} points; the C supports at most {MAX_POINTS}")
        if x[0] < 0 or x[-1] > 1:
            raise InputError(path, f"{where} must lie within [0, 1]")
        if x.size > 1 and np.min(np.diff(x)) < 1e-6:
            raise InputError(path, f"{where} breakpoints must be strictly increasing, at least 1e-6 apart")


# --------------------------------------------------------------------------------------
# spec preparation
# --------------------------------------------------------------------------------------

def _f32(values, name: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise InputError(None, f"{name} does not fit float32")
    return a


def _expand(soc: np.ndarray, cols: list[np.ndarray]):
    """A one-point table is constant: give it the grid [0, 1] (same as np.interp)."""
    if soc.size >= 2:
        return soc, cols
    return np.array([0.0, 1.0]), [np.repeat(c, 2) for c in cols]


def _coef(dt_s: float, tau: np.ndarray) -> np.ndarray:
    """c = 1 - exp(-dt/tau), computed without cancellation."""
    return -np.expm1(-dt_s / tau)


def _inv_coef(dt_s: float, tau: np.ndarray) -> np.ndarray:
    """D = 1 / (1 - exp(-dt/tau)) >= 1: the fixed-dt tables."""
    return 1.0 / _coef(dt_s, tau)


# fields of ecmrt_f32_fx_model_t / ecmrt_q_fx_model_t after the base model, in order
FX_FLOAT_KEYS = ("h_init", "h_k", "h_m", "h_m0", "h_ref", "x_r", "x_k", "g_scale", "g_inv_i0")
FX_FIXED_KEYS = ("h_init", "h_k", "h_m", "h_m0", "h_ref", "x_r", "x_k")


def _fx_float(effects, by_name: dict, dt_s: float | None) -> dict:
    """Constants of ecmrt_f32_fx_model_t ({} when the model has no effects)."""
    if not any(e.name in ("hysteresis", "extra_rc", "current_dependent_resistance") for e in effects):
        return {}                   # capacity_error alone is only a different k_soc
    z = np.float32(0.0)
    fx = {"hyst": 0, "xrc": 0, "cdr": 0, "h_init": z, "h_k": z, "h_m": z, "h_m0": z,
          "h_ref": z, "x_r": z, "x_k": z, "g_scale": z, "g_inv_i0": z}
    h = by_name.get("hysteresis")
    if h is not None:
        k = 1.0 / (3600.0 * h.decay_ah) if dt_s is None else dt_s / (3600.0 * h.decay_ah)
        fx.update(hyst=1, h_init=np.float32(h.initial_state), h_k=_f32(k, "hysteresis decay_ah"),
                  h_m=np.float32(h.m_v), h_m0=np.float32(h.m0_v), h_ref=np.float32(h.ocv_table_state))
    x = by_name.get("extra_rc")
    if x is not None:
        k = x.tau_s if dt_s is None else float(_inv_coef(dt_s, np.array([x.tau_s]))[0])
        k32 = _f32(k, "extra_rc tau_s")
        if not k32 > 0:
            raise InputError(None, "[c] effect extra_rc: tau_s underflows float32")
        fx.update(xrc=1, x_r=np.float32(x.r_ohm), x_k=k32)
    g = by_name.get("current_dependent_resistance")
    if g is not None:
        fx.update(cdr=1, g_scale=np.float32(g.scale_at_zero), g_inv_i0=_f32(1.0 / g.i0_a, "1/i0_a"))
    return fx


def _fx_fixed(hyst, xrc, q: dict, dt_s: float | None, i_lim: float, cdr=None) -> dict:
    """Constants (raw integers) and shifts of ecmrt_q_fx_model_t; see ecmrt_q_fx.h."""
    q_i, q_v = q["Q_I"], q["Q_V"]
    fx = {"hyst": 0, "xrc": 0, "cdr": 0, "h_init": 0, "h_k": 0, "h_m": 0, "h_m0": 0, "h_ref": 0,
          "x_r": 0, "x_k": 0}

    def one(v, qf):
        return int(quantize([v], qf)[0])

    if hyst is not None:
        k = 1.0 / (3600.0 * hyst.decay_ah) if dt_s is None else dt_s / (3600.0 * hyst.decay_ah)
        q_hk = _q_fit(k)
        if dt_s is None:
            q_hr = _q_fit(i_lim * k * 1.001)
            fx["SH_HR"] = q_i + q_hk - q_hr
            fx["SH_HX"] = q_hr + Q_D - 26
        else:
            fx["SH_HX"] = q_i + q_hk - 26
        vm = max(hyst.m_v, hyst.m0_v)
        q_hm = min(_q_fit(vm), 40) if vm > 0 else 30
        fx["SH_HM"] = q_hm + Q30 - q_v
        for name in ("SH_HR", "SH_HX", "SH_HM"):
            if name in fx and not 1 <= fx[name] <= 62:
                raise InputError(None, f"[c] effect hysteresis (decay_ah = {hyst.decay_ah:g} Ah) does "
                                       f"not fit the fixed-point formats ({name} = {fx[name]}); "
                                       "use numeric=\"float\"")
        fx.update(hyst=1, h_init=one(hyst.initial_state, Q30), h_k=one(k, q_hk),
                  h_m=one(hyst.m_v, q_hm), h_m0=one(hyst.m0_v, q_hm),
                  h_ref=one(hyst.ocv_table_state, Q30), Q_HK=q_hk, Q_HM=q_hm)
        if fx["h_k"] <= 0:
            raise InputError(None, "[c] effect hysteresis: decay_ah too large for fixed point; "
                                   "use numeric=\"float\"")
    if xrc is not None:
        q_xr = min(_q_fit(xrc.r_ohm), 62 - q_i + q_v, 40 if xrc.r_ohm == 0 else 62)
        fx["SH_XR"] = q_xr + q_i - q_v
        if not 1 <= fx["SH_XR"] <= 62:
            raise InputError(None, f"[c] effect extra_rc: r_ohm = {xrc.r_ohm:g} does not fit the "
                                   "fixed-point formats; use numeric=\"float\"")
        if dt_s is None:
            x_k = one(xrc.tau_s, q["Q_T"])
        else:
            x_k = int(quantize(_coef(dt_s, np.array([xrc.tau_s])), Q30)[0])
        if x_k <= 0:
            raise InputError(None, f"[c] effect extra_rc: tau_s = {xrc.tau_s:g} s does not fit the "
                                   "fixed-point formats; use numeric=\"float\"")
        fx.update(xrc=1, x_r=one(xrc.r_ohm, q_xr), x_k=x_k, Q_XR=q_xr)
    if cdr is not None:
        # x = |i| / i0 = rshr(|i| g_k, SH_GX) in Q(CDR_QX) with CDR_QX = 31 - E: x < 2^E
        # for every int32 current (|i| <= 2^31), so x fits int31 and indexes the table
        q_k = _q_fit(1.0 / cdr.i0_a)
        g_k = one(1.0 / cdr.i0_a, q_k)
        e_bins = max(1, math.ceil(math.log2(i_lim / cdr.i0_a)))
        while True:
            q_x = 31 - e_bins
            sh = q_i + q_k - q_x
            if e_bins > CDR_E_MAX or not 1 <= sh <= 62 or g_k <= 0:
                raise InputError(None, f"[c] effect current_dependent_resistance: i0_a = "
                                       f"{cdr.i0_a:g} A is too small for the fixed-point current "
                                       f"range {i_lim:g} A (|i|/i0_a must stay below "
                                       f"2^{CDR_E_MAX}); use numeric=\"float\"")
            if ((2**31 * g_k + (1 << (sh - 1))) >> sh) < 2**31:
                break
            e_bins += 1
        tab = cdr_table(cdr.scale_at_zero, e_bins)
        q_g = min(Q30, _q_fit(float(np.max(tab))))
        fx.update(cdr=1, g_k=g_k, g_tab=quantize(tab, q_g), SH_GX=sh, CDR_QX=q_x, CDR_QG=q_g,
                  Q_GK=q_k, CDR_E=e_bins, g_max=float(np.max(tab)))
    return fx


def prepare(model, numeric: str = "float", dt_s: float | None = None, prefix: str = "ecm",
            i_max_a: float | None = None) -> CSpec:
    """The tables and constants the C will hold (see :class:`CSpec`). Raises InputError
    for a model or an option the C cannot represent."""
    model = _as_model(model)
    check_options(prefix, numeric, dt_s, i_max_a)
    validate_for_c(model)
    dt_s = None if dt_s is None else float(dt_s)
    variable_dt = dt_s is None
    cap = float(model.capacity_ah)
    if i_max_a is None:
        i_max_a = DEFAULT_I_MAX_C * cap
    q_i = int(min(30, max(0, 31 - math.ceil(math.log2(i_max_a)))))
    i_lim = math.ldexp(1.0, 31 - q_i)
    notes = []
    check_effects(model, numeric, i_lim)
    effects = tuple(getattr(model, "effects", ()) or ())
    by_name = {e.name: e for e in effects}
    cap_scale = 1.0
    for e in effects:
        if e.name == "capacity_error":
            cap_scale *= float(e.capacity_scale)

    ocv_soc, (ocv_v,) = _expand(np.asarray(model.ocv.soc, float), [np.asarray(model.ocv.ocv_v[0], float)])
    raw_dirs = []
    for d in ("discharge", "charge"):
        t = model.table(d)
        soc, cols = _expand(np.asarray(t.soc, float), [np.asarray(getattr(t, k)[0], float) for k in RC_FIELDS])
        raw_dirs.append((soc, dict(zip(RC_FIELDS, cols))))

    def k_tables(cols):
        if variable_dt:
            return cols["tau_fast_s"], cols["tau_slow_s"]
        return _inv_coef(dt_s, cols["tau_fast_s"]), _inv_coef(dt_s, cols["tau_slow_s"])

    common = dict(prefix=prefix, numeric=numeric, variable_dt=variable_dt, dt_s=dt_s,
                  i_lim_a=i_lim, model_sha256=model.sha256(), capacity_ah=cap)
    q_eff = cap * cap_scale if cap_scale != 1.0 else cap
    if cap_scale != 1.0:
        notes.append(f"effect capacity_error: the SOC counts against capacity_ah * {cap_scale:.6g} "
                     f"= {q_eff:.6g} Ah")
    k_soc64 = 1.0 / (3600.0 * q_eff) if variable_dt else dt_s / (3600.0 * q_eff)

    if numeric == "float":
        def fgrid(x, name):
            x32 = _f32(x, name)
            dx = np.diff(x32.astype(np.float64))
            if np.any(dx <= 0):
                raise InputError(None, f"{name} breakpoints collapse in float32")
            return CGrid(x32, _f32(1.0 / dx, name + " spacing"))

        dirs = []
        for (soc, cols), name in zip(raw_dirs, ("discharge", "charge")):
            kf, ks = k_tables(cols)
            kf32, ks32 = _f32(kf, name), _f32(ks, name)
            if variable_dt and (np.any(kf32 <= 0) or np.any(ks32 <= 0)):
                raise InputError(None, f"rc.{name} time constants underflow float32")
            dirs.append(CDir(fgrid(soc, f"rc.{name}.soc"), _f32(cols["r0_ohm"], name),
                             _f32(cols["r_fast_ohm"], name), kf32,
                             _f32(cols["r_slow_ohm"], name), ks32))
        return CSpec(ocv_grid=fgrid(ocv_soc, "ocv.soc"), ocv=_f32(ocv_v, "ocv_v"), dirs=tuple(dirs),
                     deadband=np.float32(model.direction_deadband_a), k_soc=np.float32(k_soc64),
                     q={}, notes=tuple(notes), fx=_fx_float(effects, by_name, dt_s), **common)

    # ---- fixed point: formats from the value ranges --------------------------------
    def vmax(key):
        return max(float(np.max(c[key])) for _, c in raw_dirs)

    q = {"Q_I": q_i}
    v_bound = float(np.max(ocv_v)) + i_lim * (vmax("r0_ohm") + vmax("r_fast_ohm") + vmax("r_slow_ohm"))
    hyst, xrc = by_name.get("hysteresis"), by_name.get("extra_rc")
    if hyst is not None:
        v_bound += 2.0 * (hyst.m_v + hyst.m0_v)
    if xrc is not None:
        v_bound += i_lim * xrc.r_ohm
    cdr = by_name.get("current_dependent_resistance")
    if cdr is not None:             # r0 and r_fast times g <= max of the g table
        g_max = float(np.max(cdr_table(cdr.scale_at_zero, 1)))
        v_bound += i_lim * (vmax("r0_ohm") + vmax("r_fast_ohm")) * max(0.0, g_max - 1.0)
    q["Q_V"] = min(30, _q_fit(v_bound * 1.001))
    for key, name in (("r0_ohm", "Q_R0"), ("r_fast_ohm", "Q_RF"), ("r_slow_ohm", "Q_RS")):
        q[name] = min(_q_fit(vmax(key)), 62 - q_i + q["Q_V"], 40 if vmax(key) == 0 else 62)
        sh = q[name] + q_i - q["Q_V"]
        if not 1 <= sh <= 62:
            raise InputError(None, f"cannot choose a fixed-point format for {key} (shift {sh})")

    xs = [quantize(ocv_soc, Q30)] + [quantize(soc, Q30) for soc, _ in raw_dirs]
    dx_min = min(int(np.min(np.diff(x))) for x in xs)
    if dx_min < 2:
        raise InputError(None, "SOC breakpoints too close for Q30")
    g = math.floor(math.log2(INT32_MAX * dx_min)) - 30
    while math.floor(math.ldexp(1.0, 30 + g) / dx_min + 0.5) > INT32_MAX:
        g -= 1
    q["Q_G"] = g

    def qgrid(xq):
        dx = np.diff(xq).astype(np.float64)
        return CGrid(xq, np.floor(np.ldexp(1.0, 30 + g) / dx + 0.5).astype(np.int64))

    if variable_dt:
        tau_max = max(vmax("tau_fast_s"), vmax("tau_slow_s"), xrc.tau_s if xrc is not None else 0.0)
        q["Q_T"] = min(21, _q_fit(tau_max))
        if q["Q_T"] < -10:
            raise InputError(None, "time constants too large for the fixed-point format")
        tau_min = min(float(np.min(c[k])) for _, c in raw_dirs for k in ("tau_fast_s", "tau_slow_s"))
        if math.ldexp(tau_min, q["Q_T"]) < 1024:
            notes.append(f"the smallest time constant {tau_min:.3g} s has under 10 bits in Q{q['Q_T']}")
        q["Q_K"] = _q_fit(k_soc64)
        q["Q_RATE"] = _q_fit(i_lim * k_soc64 * 1.001)
        q["SH_RATE"] = q_i + q["Q_K"] - q["Q_RATE"]
        q["SH_DSOC"] = q["Q_RATE"] + Q_D - Q30
        k_soc = int(quantize([k_soc64], q["Q_K"])[0])
    else:
        q["Q_K"] = _q_fit(k_soc64)
        q["SH_DSOC"] = q_i + q["Q_K"] - Q30
        k_soc = int(quantize([k_soc64], q["Q_K"])[0])
        for key, qd, qc in (("tau_fast_s", "Q_DF", "Q_CF"), ("tau_slow_s", "Q_DS", "Q_CS")):
            dmax = max(float(np.max(_inv_coef(dt_s, c[key]))) for _, c in raw_dirs)
            dmin = min(float(np.min(_inv_coef(dt_s, c[key]))) for _, c in raw_dirs)
            q[qd] = _q_fit(dmax)
            q[qc] = min(_q_fit(1.0 / dmin, bits=30), 62 - q[qd])
            if q[qd] < 0 or q[qc] < 2:
                raise InputError(None, f"dt_s = {dt_s} s is too small for the time constants in fixed point")
    for name in ("SH_RATE", "SH_DSOC"):
        if name in q and not 1 <= q[name] <= (62 if name == "SH_RATE" else 61):
            raise InputError(None, f"capacity {cap} Ah with current range {i_lim} A does not fit "
                                   f"the fixed-point SOC update ({name} = {q[name]})")

    dirs = []
    for (soc, cols), xq in zip(raw_dirs, xs[1:]):
        kf, ks = k_tables(cols)
        if variable_dt:
            kfq, ksq = quantize(kf, q["Q_T"]), quantize(ks, q["Q_T"])
            if np.any(kfq <= 0) or np.any(ksq <= 0):
                raise InputError(None, "time constants too small for the fixed-point format")
        else:
            kfq, ksq = quantize(kf, q["Q_DF"]), quantize(ks, q["Q_DS"])
        dirs.append(CDir(qgrid(xq), quantize(cols["r0_ohm"], q["Q_R0"]),
                         quantize(cols["r_fast_ohm"], q["Q_RF"]), kfq,
                         quantize(cols["r_slow_ohm"], q["Q_RS"]), ksq))
    db = int(quantize([model.direction_deadband_a], q_i)[0])
    fx = (_fx_fixed(hyst, xrc, q, dt_s, i_lim, cdr)
          if (hyst is not None or xrc is not None or cdr is not None) else {})
    return CSpec(ocv_grid=qgrid(xs[0]), ocv=quantize(ocv_v, q["Q_V"]), dirs=tuple(dirs),
                 deadband=db, k_soc=k_soc, q=q, notes=tuple(notes), fx=fx, **common)


# --------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------

def c_float(v) -> str:
    """A float32 as a C literal that reads back to the same bits: 9 significant digits + f."""
    f = np.float32(v)
    if not np.isfinite(f):
        raise ValueError(f"non-finite float {v!r}")
    s = f"{float(f):.9g}"
    if not any(ch in s for ch in ".e"):
        s += ".0"
    assert np.float32(float(s)) == f
    return s + "f"


def _body(values, fmt, per_line: int) -> str:
    items = [fmt(v) for v in values]
    lines = [", ".join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
    return ",\n    ".join(lines)


@dataclass
class _Arrays:
    """Emitted arrays, deduplicated by content (identical tables are emitted once)."""

    ctype: str
    fmt: object
    per_line: int
    items: list = field(default_factory=list)
    by_content: dict = field(default_factory=dict)

    def add(self, name: str, values, comment: str) -> str:
        key = tuple(np.asarray(values).tolist())
        if key in self.by_content:
            return self.by_content[key]
        self.by_content[key] = name
        self.items.append({"name": name, "n": len(key), "comment": comment,
                           "body": _body(key, self.fmt, self.per_line)})
        return name

    @property
    def nbytes(self) -> int:
        return 4 * sum(a["n"] for a in self.items)


def _ranges(spec: CSpec) -> list[dict]:
    """Rows of the fixed-point format table in the header."""
    q = spec.q

    def row(name, qf, what, rng):
        return {"name": name, "q": qf, "lsb": f"{math.ldexp(1.0, -qf):.3g}", "what": what, "range": rng}

    i_lim = spec.i_lim_a
    v_lim = math.ldexp(1.0, 31 - q["Q_V"])
    rows = [row("current i", q["Q_I"], "A, positive = charge (input)", f"+-{i_lim:g} A (int32 range)"),
            row("voltage", q["Q_V"], "V: OCV table, u_fast, u_slow, output",
                f"+-{v_lim:g} V, saturated"),
            row("SOC", Q30, "state of charge, breakpoints", "[-2, 2), saturated"),
            row("weight w", Q30, "interpolation weight", "[0, 1]"),
            row("inv_dx", q["Q_G"], "1 / breakpoint spacing (per unit SOC)", "raw < 2^31")]
    for key, what in (("Q_R0", "r0"), ("Q_RF", "r_fast"), ("Q_RS", "r_slow")):
        rows.append(row(what, q[key], "ohm", f"[0, {math.ldexp(INT32_MAX, -q[key]):.4g}]"))
    if spec.variable_dt:
        rows.append(row("dt", Q_D, "s (input; negative -> 0)", "[0, 32768) s"))
        rows.append(row("tau_fast, tau_slow", q["Q_T"], "s", f"(0, {math.ldexp(INT32_MAX, -q['Q_T']):.4g}]"))
        rows.append(row("c (run time)", Q30, "1 - exp(-dt/tau)", "[0, 1]"))
        rows.append(row("k_soc", q["Q_K"], "1/(3600 Q) per A s", "-"))
    else:
        rows.append(row("inv_c_fast", q["Q_DF"], "D = 1/(1 - exp(-dt/tau_fast))", ">= 1"))
        rows.append(row("inv_c_slow", q["Q_DS"], "D = 1/(1 - exp(-dt/tau_slow))", ">= 1"))
        rows.append(row("c_fast (run time)", q["Q_CF"], "1/D_fast", "(0, 1]"))
        rows.append(row("c_slow (run time)", q["Q_CS"], "1/D_slow", "(0, 1]"))
        rows.append(row("k_soc", q["Q_K"], "dt/(3600 Q) per A", "-"))
    fx = spec.fx
    if fx.get("hyst"):
        rows.append(row("h, h_init, h_ref", Q30, "hysteresis state", "[-1, 1]"))
        rows.append(row("h_k", fx["Q_HK"], "1/(3600 decay_ah)" + (" per A s" if spec.variable_dt
                                                                  else " * dt per A"), "-"))
        rows.append(row("m, m0", fx["Q_HM"], "V, hysteresis amplitudes", "-"))
        rows.append(row("x (run time)", 26, "|i| dt / (3600 decay_ah)", "[0, 21.5]"))
    if fx.get("xrc"):
        rows.append(row("r_x", fx["Q_XR"], "ohm, extra RC pair (u_x in Q_V)", "-"))
        if spec.variable_dt:
            rows.append(row("tau_x", q["Q_T"], "s, extra RC pair", "-"))
        else:
            rows.append(row("c_x", Q30, "1 - exp(-dt/tau_x), extra RC pair", "(0, 1]"))
    if fx.get("cdr"):
        rows.append(row("g_k", fx["Q_GK"], "1/i0_a per A", "-"))
        rows.append(row("x_cdr (run time)", fx["CDR_QX"], "|i| / i0_a", f"[0, 2^{fx['CDR_E']})"))
        rows.append(row("g_cdr (run time)", fx["CDR_QG"], "scale asinh(x)/x, table + linear interp.",
                        f"(0, {fx['g_max']:.6g}], saturated"))
    return rows


def _context(spec: CSpec) -> dict:
    p = spec.prefix
    fixed = spec.fixed
    if fixed:
        arrays = _Arrays("int32_t", lambda v: str(int(v)), 5)
    else:
        arrays = _Arrays("float", c_float, 5)
    kname = ("tau_fast_s", "tau_slow_s") if spec.variable_dt else ("inv_c_fast", "inv_c_slow")

    def grid(g: CGrid, tag: str) -> dict:
        return {"x": arrays.add(f"{tag}_soc", g.x, f"{tag}: SOC breakpoints"),
                "inv_dx": arrays.add(f"{tag}_inv_dx", g.inv_dx, f"{tag}: 1 / breakpoint spacing"),
                "n": g.n}

    def rows_of(cols) -> np.ndarray:
        """Fixed point: the columns row by row. Float: each column as pairs (y[k], y[k+1] -
        y[k]) (float32 difference, 0 in the last row): ecmrt_f32_lerp's table layout."""
        if fixed:
            return np.stack(cols, axis=1).reshape(-1)
        out = []
        for col in cols:
            col = np.asarray(col, dtype=np.float32)
            dy = np.zeros_like(col)
            dy[:-1] = col[1:] - col[:-1]               # float32 subtraction, as the runtime's
            out += [col, dy]
        return np.stack(out, axis=1).reshape(-1)

    pair = "" if fixed else " (each with the difference to the next breakpoint)"
    ocv_grid = grid(spec.ocv_grid, "ocv")
    ocv = arrays.add("ocv_v", rows_of([spec.ocv]), "open-circuit voltage" + pair)
    dirs = []
    for d, tag in zip(spec.dirs, ("dis", "chg")):
        rows = rows_of([d.r0, d.r_fast, d.k_fast, d.r_slow, d.k_slow])
        dirs.append({
            "g": grid(d.grid, tag),
            "rows": arrays.add(f"{tag}_rows", rows, f"{tag}: per breakpoint r0, r_fast, "
                               f"{kname[0]}, r_slow, {kname[1]}" + pair),
        })
    if fixed:
        scalars = {"deadband": str(int(spec.deadband)), "k_soc": str(int(spec.k_soc))}
    else:
        scalars = {"deadband": c_float(spec.deadband), "i_max": c_float(spec.i_lim_a),
                   "k_soc": c_float(spec.k_soc)}
    fxc = _fx_context(spec, arrays) if spec.has_fx else None     # may add the g table
    return {
        "p": p, "P": p.upper(), "fixed": fixed, "variable_dt": spec.variable_dt,
        "dt_s": spec.dt_s, "dt_s_c": None if spec.dt_s is None or fixed else c_float(spec.dt_s),
        "dt_q16": None if spec.dt_s is None else int(quantize([spec.dt_s], Q_D)[0]),
        "version": spec.tool_version, "sha": spec.model_sha256, "capacity_ah": spec.capacity_ah,
        "arrays": arrays.items, "table_bytes": arrays.nbytes, "ocv_grid": ocv_grid, "ocv": ocv,
        "dirs": dirs, "scalars": scalars, "q": spec.q, "ranges": _ranges(spec) if fixed else [],
        "i_lim": f"{spec.i_lim_a:g}", "n_ocv": spec.ocv_grid.n,
        "n_dis": spec.dirs[0].grid.n, "n_chg": spec.dirs[1].grid.n,
        "runtime": (RUNTIME_FX_FILES if spec.has_fx else RUNTIME_FILES)[spec.numeric][-1],
        "notes": spec.notes,
        "rt": ("ecmrt_q" if fixed else "ecmrt_f32") + ("_fx" if spec.has_fx else ""),
        "vt": "int32_t" if fixed else "float",
        "fx": fxc,
    }


def _fx_context(spec: CSpec, arrays: "_Arrays") -> dict:
    """Effect constants as C text, in the order of the runtime's fx model struct."""
    fx = spec.fx
    fmt = (lambda v: str(int(v))) if spec.fixed else c_float
    out = {"hyst": int(fx["hyst"]), "xrc": int(fx["xrc"]), "cdr": int(fx["cdr"])}
    keys = FX_FIXED_KEYS if spec.fixed else FX_FLOAT_KEYS
    out["values"] = [(k, fmt(fx[k])) for k in keys]
    if spec.fixed and fx["cdr"]:        # fields present only with ECMRT_FX_CDR = 1
        tab = arrays.add("cdr_g", fx["g_tab"], f"current_dependent_resistance: g = scale "
                         f"asinh(x)/x in Q{fx['CDR_QG']} at x = k/64 (k < 64), then 64 "
                         f"points per binade up to 2^{fx['CDR_E']}")
        out["values"] += [("g_k", fmt(fx["g_k"])), ("g_tab", tab)]
        out["e"] = int(fx["CDR_E"])
    out["q"] = {k: v for k, v in fx.items() if k.startswith(("SH_", "CDR_Q"))}
    return out


def _env():
    import jinja2

    return jinja2.Environment(loader=jinja2.FileSystemLoader(str(templates_dir())),
                              undefined=jinja2.StrictUndefined, keep_trailing_newline=True,
                              trim_blocks=True, lstrip_blocks=True, autoescape=False)


def file_names(prefix: str, numeric: str, effects: bool = False) -> dict[str, str]:
    """Names of the generated files; ``effects``: the model carries effects in the C
    (CSpec.has_fx), which adds the effect runtime headers."""
    rt = list(RUNTIME_FILES[numeric]) + (list(RUNTIME_FX_FILES[numeric]) if effects else [])
    return {"header": f"{prefix}_ecm.h", "source": f"{prefix}_ecm.c",
            "filelist": f"{prefix}_ecm_files.mk", "report": f"{prefix}_ecm_report.md",
            "runtime": rt}


def _equivalence_rows(eq: dict | None) -> list[dict]:
    rows = []
    for numeric, r in (eq or {}).items():
        if not isinstance(r, dict):
            continue

        def mv(key):
            return "-" if r.get(key) is None else f"{1e3 * float(r[key]):.4g}"

        rows.append({"numeric": numeric, "dt": r.get("dt", "-"), "steps": r.get("steps", "-"),
                     "exact": "yes" if r.get("bit_exact_vs_reference") else "NO",
                     "mae": mv("mae_v"), "dmae": mv("delta_mae_v"),
                     "dmax": mv("max_abs_diff_vs_python_v")})
    return rows


def render(spec: CSpec, equivalence: dict | None = None) -> dict[str, str]:
    """File name -> text of every file generate_c writes (runtime headers included).
    ``equivalence``: the dict of cbuild.c_equivalence, tabulated in the report."""
    env = _env()
    ctx = _context(spec)
    ctx["equivalence"] = _equivalence_rows(equivalence)
    names = file_names(spec.prefix, spec.numeric, spec.has_fx)
    ctx["files"] = names
    out = {names["header"]: env.get_template("ecm.h.j2").render(ctx),
           names["source"]: env.get_template("ecm.c.j2").render(ctx)}
    rdir = runtime_dir()
    for name in names["runtime"]:
        out[name] = (rdir / name).read_text()
    out[names["filelist"]] = env.get_template("files.mk.j2").render(ctx)
    out[names["report"]] = env.get_template("report.md.j2").render(ctx)
    return out


def describe(spec: CSpec) -> dict:
    """A short JSON-able summary (for `ecmgen build --json` and the report)."""
    ctx = _context(spec)
    d = {"prefix": spec.prefix, "numeric": spec.numeric,
         "dt": "variable" if spec.variable_dt else spec.dt_s,
         "points": {"ocv": ctx["n_ocv"], "discharge": ctx["n_dis"], "charge": ctx["n_chg"]},
         "table_bytes": ctx["table_bytes"], "current_limit_a": spec.i_lim_a,
         "model_sha256": spec.model_sha256, "notes": list(spec.notes)}
    if spec.fixed:
        d["q"] = dict(spec.q)
    return d


def generate_c(model, out_dir, prefix: str = "ecm", numeric: str = "float",
               dt_s: float | None = None, i_max_a: float | None = None,
               equivalence: dict | None = None) -> list[Path]:
    """Write ``<prefix>_ecm.h``, ``<prefix>_ecm.c``, the runtime headers, a make include
    listing them and a short report into ``out_dir``; return the paths written.

    ``model`` is an EcmModel or a model.json path; ``dt_s`` None gives the variable-dt step,
    a number the fixed-dt one; ``i_max_a`` sets the current range (default 32 C, rounded up
    to a power of two); ``equivalence`` (the dict of cbuild.c_equivalence) is tabulated in
    the report. Everything is checked and rendered in memory first: a bad model or option
    raises InputError before any file is written."""
    spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix=prefix, i_max_a=i_max_a)
    files = render(spec, equivalence)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in files.items():
        path = out_dir / name
        if not (path.exists() and path.read_text() == text):
            write_atomic(path, text)
        written.append(path)
    return written
