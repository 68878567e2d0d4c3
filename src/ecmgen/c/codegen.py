"""model.json -> C for BMS microcontrollers: ``<prefix>_ecm_<s>.h`` / ``.c`` (names:
:mod:`ecmgen.c.names`).

The generated C holds the ``const`` tables (``<prefix>_model_<s>``), the model's state type,
``<prefix>_ecm_<s>_config.h`` the layout of its tables, and its init, set_age and step: the
calls, in the step's order, of the units of the hand-written runtime in ``c_runtime/``
(copied beside the generated files) that this model has (temperature axis, diffusion pair,
Butler-Volmer branch, surface SOC, ageing law, diagnose effects: ``CSpec.switches``), so the
runtime has no compile-time switch and a model's C nothing of what it lacks. Two numerics:

``float``  IEEE binary32 tables, literals with 9 significant digits (they round-trip).
``fixed``  int32 tables in Q formats chosen from the model's value ranges; int64
           intermediates, rounding half up, saturation; no floating point, no division.

Two time-step modes:

variable dt (``dt_s=None``)  ``step(state, i, T, dt)``; the coefficients c = 1 - exp(-dt/tau)
    are computed at run time from the interpolated tau, exactly as ``simulate.py`` does
    (float: a deterministic exp built from + - * ; fixed: integer exp). This is the mode
    that runs the measured, non-uniform drive cycles.
fixed dt (``dt_s`` given)    ``step(state, i, T)``; D = 1 / (1 - exp(-dt_s/tau)) is
    precomputed per breakpoint, interpolated, and the step divides by it (no exp). D = tau/dt
    + 1/2 + dt/(12 tau) + ... is nearly linear in tau, so this matches ``simulate.py`` (which
    interpolates tau) exactly at the breakpoints and to second order in dt/tau between them;
    interpolating c itself would not (c ~ dt/tau is convex in tau).

Every model's step takes the cell temperature T (float degC; fixed point int32 Q8 degC);
a model without a temperature axis ignores it (unless it carries temperature_dependence),
so a firmware swaps a one-temperature model for one over temperature without changing a
call.

:mod:`ecmgen.c.spec` (float32) and :mod:`ecmgen.c.qspec` (fixed point) compute every
number the C holds into a :class:`CSpec`; this module renders it through ``templates/``.
Same model + options -> byte-identical files. Compiling the C and proving it equal to the
references is :mod:`ecmgen.c.cbuild`; the build's C stage is :mod:`ecmgen.c.check`.
"""

from __future__ import annotations

import functools
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import write_atomic
from .names import c_names
from .runtime import runtime_dir, templates_dir
from .qformat import INT32_MAX, Q30, Q_D, Q_TEMP, quantize
from .spec import (C_EFFECTS, FX_FIXED_KEYS, FX_FLOAT_KEYS, NUMERICS, CDir, CGrid, CSpec,
                   _as_model, begin, prepare_float, state_fields)

__all__ = ["C_EFFECTS", "NUMERICS", "CDir", "CGrid", "CSpec", "c_float", "describe", "file_names",
           "generate_c", "prepare", "render", "runtime_dir", "state_fields", "templates_dir",
           "_as_model"]

# the runtime headers a model's .c needs, the one it includes last
RUNTIME_FILES = {"float": ("ecmrt.h", "ecmrt_f32_step.h", "ecmrt_f32.h"),
                 "fixed": ("ecmrt.h", "ecmrt_q_exp.h", "ecmrt_q_step.h", "ecmrt_q.h")}


def prepare(model, numeric: str = "float", dt_s: float | None = None, prefix: str = "ecm",
            i_max_a: float | None = None) -> CSpec:
    """The tables and constants the C will hold (see :class:`CSpec`). Raises InputError
    for a model or an option the C cannot represent."""
    ctx = begin(model, numeric, dt_s, prefix, i_max_a)
    if numeric == "fixed":
        from .qspec import prepare_fixed

        return prepare_fixed(ctx)
    return prepare_float(ctx)


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


def c_floats(values) -> list[str]:
    """:func:`c_float` of every value, in one pass over the array (a model's tables are
    thousands of literals)."""
    a = np.asarray(values)
    if a.dtype.kind != "f":
        return [c_float(v) for v in values]
    f = a.reshape(-1).astype(np.float32)
    finite = np.isfinite(f)
    if not finite.all():
        c_float(a.reshape(-1)[np.argmin(finite)])      # its error
    out = [f"{x:.9g}" for x in f.astype(np.float64).tolist()]
    out = [s if "." in s or "e" in s else s + ".0" for s in out]
    assert (np.array([float(s) for s in out]).astype(np.float32) == f).all()
    return [s + "f" for s in out]


def _body(values, fmt, per_line: int) -> str:
    items = c_floats(values) if fmt is c_float else [fmt(v) for v in values]
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
        key = tuple(np.asarray(values).reshape(-1).tolist())
        if key in self.by_content:
            return self.by_content[key]
        self.by_content[key] = name
        self.items.append({"name": name, "n": len(key), "comment": comment,
                           "body": _body(key, self.fmt, self.per_line),
                           "values": np.asarray(values).reshape(-1)})
        return name

    @property
    def nbytes(self) -> int:
        return 4 * sum(a["n"] for a in self.items)


def _pairs(a: np.ndarray, axis: int) -> np.ndarray:
    """Float tables: each value with the float32 difference to the next one along ``axis``
    (0 at the last): shape (..., 2) appended - ecmrt_f32_lerp's layout."""
    a = np.asarray(a, dtype=np.float32)
    d = np.zeros_like(a)
    sl = [slice(None)] * a.ndim
    hi, lo = list(sl), list(sl)
    hi[axis], lo[axis] = slice(1, None), slice(None, -1)
    d[tuple(lo)] = a[tuple(hi)] - a[tuple(lo)]          # float32 subtraction, as the runtime's
    return np.stack([a, d], axis=-1)


def table_rows(spec: CSpec, d: CDir) -> np.ndarray:
    """A direction's parameter table as the runtime reads it: [temperature row][SOC point]
    [r0, r_fast, k_fast, r_slow, k_slow (, ocv when the OCV shares the grid)], without the
    k columns when the time constants depend on temperature only (switch TAU_T: they are in
    :func:`tau_rows`); float: each a pair along SOC (one row) or along temperature (the
    runtime interpolates in temperature first)."""
    cols = ([d.r0, d.r_fast, d.r_slow] if spec.tau_t else
            [d.r0, d.r_fast, d.k_fast, d.r_slow, d.k_slow]) + ([spec.ocv] if spec.ocv_shared else [])
    if spec.fixed:
        return np.stack(cols, axis=-1)
    return np.concatenate([_pairs(c, 0 if spec.temp else 1) for c in cols], axis=-1)


def tau_rows(spec: CSpec, d: CDir) -> np.ndarray | None:
    """Switch TAU_T: [temperature row][k_fast, k_slow], float: pairs along temperature."""
    if not spec.tau_t:
        return None
    cols = [d.k_fast[:, 0], d.k_slow[:, 0]]
    if spec.fixed:
        return np.stack(cols, axis=-1)
    return np.concatenate([_pairs(c, 0) for c in cols], axis=-1)


def branch_rows(spec: CSpec, d: CDir) -> np.ndarray | None:
    """[temperature row][r_diff, k_diff, i0 - those present], float: pairs along temperature."""
    cols = [c for c in (d.r_diff, d.k_diff, d.i0) if c is not None]
    if not cols:
        return None
    if spec.fixed:
        return np.stack(cols, axis=-1)
    return np.concatenate([_pairs(c, 0) for c in cols], axis=-1)


def ocv_rows(spec: CSpec) -> np.ndarray:
    return spec.ocv if spec.fixed else _pairs(spec.ocv, 0 if spec.temp else 1)


def surface_rows(spec: CSpec) -> np.ndarray:
    """The surface SOC's per-volt table (float), laid out as the OCV's: m->sv."""
    return _pairs(spec.surface, 0 if spec.temp else 1)


def age_rows(spec: CSpec) -> np.ndarray:
    """The ageing law's scales as the runtime reads them (m->age_scale): per breakpoint the
    resistance scale and 1 / capacity scale (float: each a pair with its difference to the
    next breakpoint)."""
    cols = (spec.age["r"], spec.age["iq"])
    if spec.fixed:
        return np.stack(cols, axis=-1)
    return np.concatenate([_pairs(c, 0) for c in cols], axis=-1)


def _ranges(spec: CSpec) -> list[dict]:
    """Rows of the fixed-point format table in the header."""
    q = spec.q

    def row(name, qf, what, rng):
        return {"name": name, "q": qf, "lsb": f"{math.ldexp(1.0, -qf):.3g}", "what": what, "range": rng}

    def top(key):
        return f"[0, {math.ldexp(INT32_MAX, -q[key]):.4g}]"

    i_lim = spec.i_lim_a
    v_lim = math.ldexp(1.0, 31 - q["Q_V"])
    rows = [row("current i", q["Q_I"], "A, positive = charge (input)", f"+-{i_lim:g} A (int32 range)"),
            row("temperature T", Q_TEMP, "degC (input)" + ("" if spec.uses_temperature else
                                                            ", not used by this model"),
                "int32 range; the tables clamp at their ends"),
            row("voltage", q["Q_V"], "V: OCV table, RC voltages, output", f"+-{v_lim:g} V, saturated"),
            row("SOC", Q30, "state of charge, breakpoints", "[-2, 2), saturated"),
            row("weight w", Q30, "interpolation weight (SOC, temperature)", "[0, 1]"),
            row("inv_dx", q["Q_G"], "1 / SOC breakpoint spacing (per unit SOC)", "raw < 2^31")]
    if spec.temp:
        rows.append(row("inv_dx_t", q["Q_GT"], "1 / temperature breakpoint spacing (per Q8 K)",
                        "raw < 2^31"))
    for key, what in (("Q_R0", "r0"), ("Q_RF", "r_fast"), ("Q_RS", "r_slow")):
        rows.append(row(what, q[key], "ohm", top(key)))
    if spec.diff:
        rows.append(row("r_diff", q["Q_RD"], "ohm, diffusion pair (u_diff in Q_V)", top("Q_RD")))
    if spec.surface is not None:
        rows.append(row("sv", q["Q_SV"], "1/V, surface SOC: lam / max(dOCV/dSOC, 0.3 V)",
                        f"[0, {math.ldexp(int(np.max(spec.surface)), -q['Q_SV']):.4g}]"))
        rows.append(row("soc_s (run time)", Q30, "soc + sv u_diff (sv u_diff rounded from "
                        f"Q{q['Q_SV'] + q['Q_V']})", "[0, 1], saturated"))
    if spec.has_bv:
        rows.append(row("i0", q["Q_I0"], "A, Butler-Volmer fast branch", top("Q_I0")))
        rows.append(row("x_bv (run time)", spec.bv["QX"], "|i| / i0",
                        f"[0, 2^{spec.bv['E']})"))
        rows.append(row("g_bv (run time)", Q30, "asinh(x)/x, table + linear interp.", "(0, 1]"))
    if spec.variable_dt:
        taus = "tau_fast, tau_slow" + (", tau_diff" if spec.diff else "")
        rows.append(row("dt", Q_D, "s (input; negative -> 0)", "[0, 32768) s"))
        rows.append(row(taus, q["Q_T"], "s", f"(0, {math.ldexp(INT32_MAX, -q['Q_T']):.4g}]"))
        rows.append(row("c (run time)", Q30, "1 - exp(-dt/tau)", "[0, 1]"))
        rows.append(row("k_soc", q["Q_K"], "1/(3600 Q) per A s", "-"))
    else:
        pairs = [("fast", "DF", "CF"), ("slow", "DS", "CS")] + ([("diff", "DD", "CD")] if spec.diff else [])
        for name, qd, qc in pairs:
            rows.append(row(f"inv_c_{name}", q[f"Q_{qd}"], f"D = 1/(1 - exp(-dt/tau_{name}))", ">= 1"))
            rows.append(row(f"c_{name} (run time)", q[f"Q_{qc}"], f"1/D_{name}", "(0, 1]"))
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
    if spec.age is not None:
        rows.append(row("efc", Q_TEMP, "equivalent full cycles (ageing input, set_age)",
                        "[0, 8388608), clamped to the law"))
        rows.append(row("inv_dx_age", q["Q_GA"], "1 / age breakpoint spacing (per Q8 cycle)",
                        "raw < 2^31"))
        rows.append(row("age_r", q["Q_AR"], "resistance scale", top("Q_AR")))
        rows.append(row("age_iq", q["Q_AQ"], "1 / capacity scale (times k_soc)", top("Q_AQ")))
    if fx.get("arr"):
        rows.append(row("B", fx["ARR_QB"], "activation_k / 233.15 K", "-"))
        rows.append(row("f_arr (run time)", fx["ARR_QF"], "Arrhenius factor, T in [-40, 85] degC",
                        f"(0, {fx['f_max']:.6g}]"))
    return rows


def _qtypes(spec: CSpec) -> list[dict]:
    """The fixed-point API's value types: name (its format in it), Q and 2^(Q+1)."""
    q = spec.q
    rows = [("amp", q["Q_I"]), ("volt", q["Q_V"]), ("soc", Q30), ("degc", Q_TEMP)] + \
        ([("sec", Q_D)] if spec.variable_dt else []) + ([("efc", Q_TEMP)] if spec.age else [])
    return [{"name": f"{name}_q{qf}", "q": qf, "twice": 2 ** (qf + 1)} for name, qf in rows]


def _api_types(spec: CSpec) -> dict[str, str]:
    """The C types of the API's arguments: float, or the fixed-point value types."""
    if not spec.fixed:
        return dict.fromkeys(("i", "v", "t", "dt", "soc", "efc"), "float")
    p, q = spec.prefix, spec.q
    return {"i": f"{p}_amp_q{q['Q_I']}_t", "v": f"{p}_volt_q{q['Q_V']}_t", "t": f"{p}_degc_q8_t",
            "dt": f"{p}_sec_q16_t", "soc": f"{p}_soc_q30_t", "efc": f"{p}_efc_q8_t"}


def _grid(arrays: "_Arrays", fixed: bool, g: CGrid, tag: str, what: str, xname: str = "soc",
          uniform: bool = False) -> dict:
    """One grid's initialiser (its arrays added to ``arrays``)."""
    if uniform:             # ecmrt_*_ugrid_t: located in O(1), no arrays
        if fixed:
            return {"init": f"{{ {(g.n - 1) << 30}, {int(g.x0)}, {int(g.inv_h)}, {g.n}u }}",
                    "n": g.n}
        return {"init": f"{{ {c_float(g.x0)}, {c_float(g.inv_h)}, {c_float(g.n - 1)}, {g.n}u }}",
                "n": g.n}
    x = arrays.add(f"{tag}_{xname}", g.x, f"{tag}: {what} breakpoints")
    inv = arrays.add(f"{tag}_inv_dx", g.inv_dx, f"{tag}: 1 / breakpoint spacing")
    return {"init": f"{{ {x}, {inv}, {g.n}u }}", "n": g.n}


def _table_notes(spec: CSpec) -> tuple[str, str]:
    """What the tables' comments add: the pairs' second value, the temperature rows."""
    rows_note = f", {spec.ocv.shape[0]} temperature rows" if spec.temp else ""
    pair = "" if spec.fixed else (" (each with the difference to the next temperature row)"
                                  if spec.temp else
                                  " (each with the difference to the next SOC breakpoint)")
    return pair, rows_note


def _dir_contexts(spec: CSpec, arrays: "_Arrays") -> list[dict]:
    """Each direction's grid, rows, time-constant and branch tables."""
    fixed, shared = spec.fixed, spec.ocv_shared
    pair, rows_note = _table_notes(spec)
    kname = ("tau_fast_s", "tau_slow_s") if spec.variable_dt else ("inv_c_fast", "inv_c_slow")
    dirs = []
    for d, tag in zip(spec.dirs, ("dis", "chg")):
        br = branch_rows(spec, d)
        tk = tau_rows(spec, d)
        names = [k for k, v in (("r_diff", d.r_diff), ("tau_diff_s" if spec.variable_dt else
                                "inv_c_diff", d.k_diff), ("i0_a", d.i0)) if v is not None]
        params = "r0, r_fast, r_slow" if spec.tau_t else f"r0, r_fast, {kname[0]}, r_slow, {kname[1]}"
        dirs.append({
            "g": _grid(arrays, fixed, d.grid, tag, "SOC", uniform=spec.rc_uniform),
            "rows": arrays.add(f"{tag}_rows", table_rows(spec, d),
                               f"{tag}: per SOC breakpoint {params}" + (", ocv" if shared else "")
                               + pair + rows_note),
            "tk": None if tk is None else arrays.add(
                f"{tag}_tau", tk, f"{tag}: per temperature row {kname[0]}, {kname[1]} (constant "
                "along SOC)" + ("" if fixed else " (each with the difference to the next row)")),
            "branch": None if br is None else arrays.add(
                f"{tag}_branch", br, f"{tag}: per temperature row {', '.join(names)}" +
                ("" if fixed else " (each with the difference to the next row)")),
        })
    return dirs


def _scalars(spec: CSpec, arrays: "_Arrays") -> list[tuple[str, str, str]]:
    """The model struct's scalar members (and the tables they point to), in order."""
    fixed = spec.fixed
    pair, rows_note = _table_notes(spec)
    if fixed:
        scalars = [("deadband", str(int(spec.deadband)), f"Q{spec.q['Q_I']} A"),
                   ("k_soc", str(int(spec.k_soc)), f"Q{spec.q['Q_K']}")]
    else:
        scalars = [("deadband_a", c_float(spec.deadband), "A"),
                   ("i_max_a", c_float(spec.i_lim_a), "current limit, A"),
                   ("k_soc", c_float(spec.k_soc), "1/(3600 Q)" if spec.variable_dt else "dt/(3600 Q)")]
    if spec.has_bv and fixed:
        scalars.append(("bv_tab", arrays.add("bv_g", spec.bv["tab"], "Butler-Volmer: asinh(x)/x "
                                             f"in Q30 at x = k/64 (k < 64), then 64 points per "
                                             f"binade up to 2^{spec.bv['E']}"), ""))
    if spec.surface is not None:
        sv = spec.surface if fixed else surface_rows(spec)
        what = "surface SOC: lam / max(dOCV/dSOC, 0.3 V) at the OCV's breakpoints, " + \
            (f"Q{spec.q['Q_SV']} 1/V" if fixed else "1/V") + pair + rows_note
        scalars.append(("sv", arrays.add("surface_per_volt", sv, what), ""))
    scalars += _fx_scalars(spec, arrays)
    if spec.age is not None:
        scalars.append(("age", _grid(arrays, fixed, spec.age["grid"], "age", "equivalent full "
                                     "cycles" + (" (Q8)" if fixed else ""), "efc")["init"], ""))
        scalars.append(("age_scale", arrays.add(
            "age_scale", age_rows(spec), "ageing law: per breakpoint the resistance scale, "
            "1 / capacity scale" + (f" (Q{spec.q['Q_AR']}, Q{spec.q['Q_AQ']})" if fixed else
                                    " (each with the difference to the next breakpoint)")), ""))
    return scalars


def _fixed_macros(spec: CSpec, nm: dict) -> tuple[list, dict, list]:
    """The fixed-point formats: (macro, Q) of the formats the header defines (but Q_I and
    Q_V, which it defines as the API's), {format key: its macro} for the step's template, and
    (macro, value) of the effects' and the Butler-Volmer branch's shifts for the config."""
    names = ["Q_I", "Q_V", "Q_G", "Q_R0", "Q_RF", "Q_RS", "SH_DSOC"]
    names += ["Q_T", "SH_RATE"] if spec.variable_dt else ["Q_DF", "Q_DS", "Q_CF", "Q_CS"]
    names += ["Q_GT"] if spec.temp else []
    names += ["Q_KR"] if spec.tau_t and spec.variable_dt else []
    names += ["Q_GU"] if spec.rc_uniform else []
    names += ["Q_GUO"] if spec.ocv_uniform else []
    names += (["Q_RD"] + ([] if spec.variable_dt else ["Q_DD", "Q_CD"])) if spec.diff else []
    names += ["Q_I0"] if spec.has_bv else []
    names += ["Q_SV"] if spec.surface is not None else []
    names += ["Q_GA", "Q_AR", "Q_AQ"] if spec.age is not None else []
    fmts = {n: f"{nm['M']}_{n[2:] if n.startswith('Q_') else n}" for n in names}
    extra = {}
    if spec.has_bv:
        extra.update(BV_QX=spec.bv["QX"], BV_K=spec.bv["K"])
    extra.update({f"FX_{k}": v for k, v in spec.fx.items() if k.startswith(("SH_", "CDR_Q", "ARR_Q"))})
    fmts.update({k: f"{nm['M']}_{k}" for k in extra})
    qm = dict.fromkeys(("Q_T", "SH_RATE", "Q_DF", "Q_DS", "Q_CF", "Q_CS", "Q_GT", "Q_KR", "Q_GU",
                        "Q_GUO", "Q_RD", "Q_DD", "Q_CD", "Q_I0", "Q_SV", "Q_GA", "Q_AR", "Q_AQ"),
                       "none") | fmts        # what the model lacks renders as "none": no C
    return ([(v, spec.q[n]) for n, v in fmts.items() if n in spec.q and n not in ("Q_I", "Q_V")],
            qm, [(fmts[k], v) for k, v in extra.items()])


def _layout(spec: CSpec) -> dict:
    """Where the step finds each parameter: per SOC point of a direction's rows (float: pairs,
    so twice the offsets), per temperature row of its branch table; the state's hints."""
    w = 1 if spec.fixed else 2
    names = (["r0", "r_fast", "r_slow"] if spec.tau_t else ["r0", "r_fast", "k_fast", "r_slow", "k_slow"]) + \
        (["ocv"] if spec.ocv_shared else [])
    key = {"r0": "r0", "r_fast": "rf", "k_fast": "kf", "r_slow": "rs", "k_slow": "ks", "ocv": "ocv"}
    p = {key[n]: w * j for j, n in enumerate(names)}
    p.setdefault("kf", None)
    p.setdefault("ks", None)
    p.setdefault("ocv", None)
    branch = [n for n, on in (("r_diff", spec.diff), ("k_diff", spec.diff), ("i0", spec.has_bv)) if on]
    b = {k: w * branch.index(n) if n in branch else None for k, n in
         (("rd", "r_diff"), ("kd", "k_diff"), ("i0", "i0"))}
    kname = ("tau_fast", "tau_slow", "tau_diff") if spec.variable_dt else ("D_fast", "D_slow", "D_diff")
    shown = {"k_fast": kname[0], "k_slow": kname[1], "k_diff": kname[2]}
    return {"npar": w * len(names), "p": p, "nb": w * len(branch), "b": b,
            "names": [shown.get(n, n) for n in names], "branch_names": [shown.get(n, n) for n in branch],
            "k_ocv": not spec.ocv_shared and not spec.ocv_uniform}


def _model_members(spec: CSpec) -> list[tuple[str, str]]:
    """The runtime's model struct for this model, as the config declares it: (declaration,
    comment), in the order of the tables' initialiser (templates/ecm.c.j2)."""
    fixed, rt = spec.fixed, "ecmrt_q" if spec.fixed else "ecmrt_f32"
    vt = "int32_t" if fixed else "float"
    out = []
    if spec.temp:
        out.append((f"{rt}_grid_t t;", "temperature breakpoints" + (" (Q8 degC)" if fixed else ", degC") +
                    ", of every table"))
    if not spec.ocv_shared:
        out += [(f"{rt}_{'ugrid_t' if spec.ocv_uniform else 'grid_t'} ocv_g;", "SOC breakpoints of the OCV"),
                (f"const {vt} *ocv;", "Q_V, temperature row after row" if fixed else
                 "pairs (ocv[k], ocv[k+1] - ocv[k]), temperature row after row")]
    if spec.surface is not None:
        out.append((f"const {vt} *sv;", ("Q_SV 1/V (>= 0)" if fixed else "1/V") +
                    " at the OCV's breakpoints, laid out as ocv"))
    out.append((f"{c_names(spec.prefix, spec.numeric)['dir_t']} dir[2];",
                "[ECMRT_DISCHARGE], [ECMRT_CHARGE]"))
    if fixed:
        out += [("int32_t deadband;", "Q_I, >= 0"),
                ("int32_t k_soc;", ("1/(3600 Q)" if spec.variable_dt else "dt/(3600 Q)") + ", scaled")]
    else:
        out += [("float deadband_a;", "|i| <= deadband keeps the last direction"),
                ("float i_max_a;", "the current is saturated to [-i_max_a, i_max_a]"),
                ("float k_soc;", "1/(3600 Q) per A s" if spec.variable_dt else "dt/(3600 Q) per A")]
    if fixed and spec.has_bv:
        out.append(("const int32_t *bv_tab;", "asinh(x)/x in Q30 at the nodes of ecmrt_q_gtab"))
    docs = {"h_init": "hysteresis: initial_state" + (", Q30" if fixed else ""),
            "h_k": "1/(3600 decay_ah) per A s" if spec.variable_dt else "dt/(3600 decay_ah) per A",
            "h_m": "m_v", "h_m0": "m0_v", "h_ref": "ocv_table_state" + (", Q30" if fixed else ""),
            "x_r": "extra_rc: r_ohm",
            "x_k": ("tau_s" + (" in Q_T" if fixed else "")) if spec.variable_dt else
            ("c_x = 1 - exp(-dt/tau_s) in Q30" if fixed else "D = 1/(1 - exp(-dt/tau_s))"),
            "g_scale": "current_dependent_resistance: scale_at_zero", "g_inv_i0": "1 / i0_a",
            "g_k": "current_dependent_resistance: 1/i0_a",
            "g_tab": "scale asinh(x)/x in Q(CDR_QG) at the nodes of ecmrt_q_gtab",
            "a_k": "temperature_dependence: activation_k, K", "a_inv_ref": "1 / (t_ref_c + 273.15)",
            "a_b": "temperature_dependence: B = activation_k / 233.15 K, Q(ARR_QB)",
            "a_fmax": "F = the factor at -40 degC, Q(ARR_QF)"}
    for flag, names in (FX_FIXED_KEYS if fixed else FX_FLOAT_KEYS).items():
        if spec.fx.get(flag):
            out += [(f"const int32_t *{k};" if k == "g_tab" else f"{vt} {k};", docs[k]) for k in names]
    if spec.age is not None:
        out += [(f"{rt}_grid_t age;", "ageing law: equivalent full cycles" + (", Q8" if fixed else "")),
                (f"const {vt} *age_scale;", "per breakpoint: resistance scale, 1 / capacity scale" +
                 (" (Q_AR, Q_AQ)" if fixed else " (pairs)"))]
    return out


def _features_text(spec: CSpec) -> str:
    """The model's features as the config header lists them: comment lines, a feature's
    name never split."""
    words = [f.replace(" ", "\0") for f in spec.features] or ["none\0(the\02RC\0step\0alone)"]
    text = textwrap.fill(", ".join(words) + ".", 90, initial_indent=" *   ",
                         subsequent_indent=" *   ", break_on_hyphens=False, break_long_words=False)
    return text.replace("\0", " ")


def _context(spec: CSpec) -> dict:
    """What the templates render: the model's tables as C arrays, its scalars and macros."""
    p = spec.prefix
    fixed = spec.fixed
    nm = c_names(p, spec.numeric)
    fmt = (lambda v: str(int(v))) if fixed else c_float
    arrays = _Arrays("int32_t" if fixed else "float", fmt, 5)
    n_t = spec.ocv.shape[0]
    pair, rows_note = _table_notes(spec)
    temp = _grid(arrays, fixed, spec.temp_grid, "temp", "temperature (degC" +
                 (" Q8)" if fixed else ")"), "c") if spec.temp else None
    shared = spec.ocv_shared
    ocv_grid = None if shared else _grid(arrays, fixed, spec.ocv_grid, "ocv", "SOC",
                                         uniform=spec.ocv_uniform)
    ocv = None if shared else arrays.add("ocv_v", ocv_rows(spec), "open-circuit voltage" + pair +
                                         rows_note)
    dirs = _dir_contexts(spec, arrays)
    scalars = _scalars(spec, arrays)
    qfmt, qm, fx_macros = _fixed_macros(spec, nm) if fixed else ([], {}, [])
    return {
        "p": p, "P": p.upper(), "nm": nm, "M": nm["M"], "fixed": fixed,
        "qtypes": _qtypes(spec) if fixed else [], "qfmt_macros": qfmt,
        "ty": _api_types(spec), "variable_dt": spec.variable_dt,
        "dt_s": spec.dt_s, "dt_s_c": None if spec.dt_s is None or fixed else c_float(spec.dt_s),
        "dt_q16": None if spec.dt_s is None else int(quantize([spec.dt_s], Q_D)[0]),
        "version": spec.tool_version, "sha": spec.model_sha256, "capacity_ah": spec.capacity_ah,
        "arrays": arrays.items, "table_bytes": arrays.nbytes, "ocv_grid": ocv_grid, "ocv": ocv,
        "temp": temp, "n_t": n_t if spec.temp else 1, "uses_t": spec.uses_temperature,
        "t_range": None if not spec.temp else (float(spec.temp_grid.x[0]) / (256.0 if fixed else 1.0),
                                               float(spec.temp_grid.x[-1]) / (256.0 if fixed else 1.0)),
        "dirs": dirs, "scalars": scalars, "q": spec.q, "ranges": _ranges(spec) if fixed else [],
        "i_lim": f"{spec.i_lim_a:g}", "n_ocv": spec.ocv_grid.n,
        "n_dis": spec.dirs[0].grid.n, "n_chg": spec.dirs[1].grid.n,
        "runtime": RUNTIME_FILES[spec.numeric][-1], "notes": spec.notes,
        "rt": "ecmrt_q" if fixed else "ecmrt_f32", "vt": "int32_t" if fixed else "float",
        "qm": qm, "fx_macros": fx_macros, "lay": _layout(spec), "members": _model_members(spec),
        "features_text": _features_text(spec),
        "state": state_fields(spec), "sw": spec.switches,
        "diff": spec.diff, "bv": spec.has_bv, "fx": spec.fx, "age": spec.age is not None,
        "age_range": None if spec.age is None else
        tuple(float(x) / (256.0 if fixed else 1.0) for x in spec.age["grid"].x[[0, -1]]),
    }


def _fx_scalars(spec: CSpec, arrays: "_Arrays") -> list[tuple[str, str, str]]:
    """Effect constants as C text: (field of the runtime's model struct, value, comment)."""
    fx = spec.fx
    fmt = (lambda v: str(int(v))) if spec.fixed else c_float
    keys = FX_FIXED_KEYS if spec.fixed else FX_FLOAT_KEYS
    out = []
    for flag, names in keys.items():
        if not fx.get(flag):
            continue
        for k in names:
            if k == "g_tab":
                out.append((k, arrays.add("cdr_g", fx["g_tab"], f"current_dependent_resistance: "
                                          f"g = scale asinh(x)/x in Q{fx['CDR_QG']} at x = k/64 "
                                          f"(k < 64), then 64 points per binade up to "
                                          f"2^{fx['CDR_E']}"), ""))
            else:
                out.append((k, fmt(fx[k]), ""))
    return out


@functools.lru_cache(maxsize=None)
def _env():
    """The templates' environment: one per process, so that each template is compiled once
    (a build renders some for every numeric and again for its golden vectors)."""
    import jinja2

    return jinja2.Environment(loader=jinja2.FileSystemLoader(str(templates_dir())),
                              undefined=jinja2.StrictUndefined, keep_trailing_newline=True,
                              trim_blocks=True, lstrip_blocks=True, autoescape=False)


def file_names(prefix: str, numeric: str) -> dict[str, str]:
    """Names of the generated files (the runtime headers are the same for every model;
    the naming rule is :mod:`ecmgen.c.names`)."""
    nm = c_names(prefix, numeric)
    return {k: nm[k] for k in ("header", "source", "config", "filelist", "report")} | \
        {"runtime": list(RUNTIME_FILES[numeric])}


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


def render(spec: CSpec, equivalence: dict | None = None, estimator=None) -> dict[str, str]:
    """File name -> text of every file generate_c writes (runtime headers included).
    ``equivalence``: the dict of cbuild.c_equivalence, tabulated in the report;
    ``estimator``: an :class:`ecmgen.c.estc.EstSpec` (the SOC filter next to the step)."""
    env = _env()
    ctx = _context(spec)
    ctx["equivalence"] = _equivalence_rows(equivalence)
    names = file_names(spec.prefix, spec.numeric)
    if estimator is not None:
        from .estc import est_file_names

        est_names = est_file_names(spec.prefix)
        names["runtime"] = names["runtime"] + est_names.pop("est_runtime")
        names.update(est_names)
    ctx["files"] = names
    out = {names["header"]: env.get_template("ecm.h.j2").render(ctx),
           names["config"]: env.get_template("ecm_config.h.j2").render(ctx),
           names["source"]: env.get_template("ecm.c.j2").render(ctx)}
    if estimator is not None:
        from .estc import render_estimator

        out.update(render_estimator(env, ctx, estimator, c_float))
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
         "points": {"ocv": ctx["n_ocv"], "discharge": ctx["n_dis"], "charge": ctx["n_chg"],
                    "temperatures": ctx["n_t"]},
         "branches": [b for b, on in (("diffusion", spec.diff), ("butler_volmer", spec.has_bv)) if on],
         "table_bytes": ctx["table_bytes"], "current_limit_a": spec.i_lim_a,
         "model_sha256": spec.model_sha256, "notes": list(spec.notes)}
    if spec.fixed:
        d["q"] = dict(spec.q)
    return d


def generate_c(model, out_dir, prefix: str = "ecm", numeric: str = "float",
               dt_s: float | None = None, i_max_a: float | None = None,
               equivalence: dict | None = None, estimator=None) -> list[Path]:
    """Write ``<prefix>_ecm.h``, ``<prefix>_ecm.c``, the runtime headers, a make include
    listing them and a short report into ``out_dir``; return the paths written.

    ``model`` is an EcmModel or a model.json path; ``dt_s`` None gives the variable-dt step,
    a number the fixed-dt one; ``i_max_a`` sets the current range (default 32 C, rounded up
    to a power of two); ``equivalence`` (the dict of cbuild.c_equivalence) is tabulated in
    the report; ``estimator`` (an EstimatorConfig) adds the SOC filter
    (``<prefix>_est_f32.h`` / ``.c``, ecmgen.c.estc).
    Everything is checked and rendered in memory first: a bad model or option
    raises InputError before any file is written."""
    spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix=prefix, i_max_a=i_max_a)
    est = None
    if estimator is not None:
        from .estc import prepare_estimator

        est = prepare_estimator(_as_model(model), spec, estimator)
    files = render(spec, equivalence, est)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in files.items():
        path = out_dir / name
        if not (path.exists() and path.read_text() == text):
            write_atomic(path, text)
        written.append(path)
    return written
