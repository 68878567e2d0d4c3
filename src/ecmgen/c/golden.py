"""Golden vectors: inputs from a real cycle and an edge-case set, with the Python reference's
outputs, for the firmware team's CI.

``ecmgen build`` writes, beside the generated C of each numeric:

``<prefix>_ecm_<s>_vectors.h``  the inputs (current, temperature, dt) exactly as the C takes
    them (float32 bit patterns, or raw Q integers) and the reference's terminal voltage and
    SOC after every step (:mod:`ecmgen.c.cref`: the float32 / bit-true references the C is
    proven equal to), in segments that each start at ``init(soc0)``; a tolerance for float
    (bit-exact is expected, a compiler that contracts a*b+c into an FMA is not) and none for
    fixed point.
``<prefix>_ecm_<s>_test.c``     a C99 program that replays them (exit status 0 / 1, one
    line on stdout; ``-DECMV_HOSTED=0`` for a target without stdio).
``test_<prefix>_ecm_<s>_equivalence.py``  a pytest file (also a script) running that check
    through :func:`ecmgen.c.verify.verify`: needs only the ecmgen wheel and a compiler.

``ecmgen verify`` (:mod:`ecmgen.c.verify`) compiles that program with the user's copy of the
C, compiler and flags. Same model, options and cycle -> the same bytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import cref
from .codegen import CSpec, _context, _env, file_names
from .fingerprint import c_statements, fingerprint
from .names import c_names
from .probes import Segment, probe_segments

CYCLE_STEPS = 3000          # steps of the cycle's start kept (a drive cycle's first minutes)
TOL_V_F32 = 1e-4            # float: a contracted or reordered build may differ by this much
TOL_SOC_F32 = 1e-6


def vector_names(prefix: str, numeric: str) -> dict[str, str]:
    stem = c_names(prefix, numeric)["source"][:-2]
    return {"vectors": f"{stem}_vectors.h", "test": f"{stem}_test.c",
            "pytest": f"test_{stem}_equivalence.py"}


def edge_segment(spec: CSpec) -> Segment:
    """Currents past the limit and inside the deadband, temperatures past the tables, dt of
    0, long and negative: every saturation and clamp of the step, from a half-full cell."""
    lim = spec.i_lim_a
    db = float(spec.deadband) / 2.0 ** spec.q["Q_I"] if spec.fixed else float(spec.deadband)
    cur = np.array([0.0, db / 2, -db / 2, 1.0, -1.0, 0.5 * lim, -0.5 * lim, 0.99 * lim, -0.99 * lim,
                    2.0 * lim, -2.0 * lim, -10.0, 10.0, 0.0, -3.0, 3.0] * 4)
    n = cur.size
    temps = np.resize(np.array([25.0, -40.0, 60.0, -80.0, 120.0, 0.0, 10.0, 45.0]), n)
    dt = None
    if spec.variable_dt:
        dt = np.resize(np.array([0.1, 0.0, 1.0, 10.0, -1.0, 100.0, 0.5, 3600.0, 0.01]), n)
    return Segment(0.5, cur, dt, temps)


def drive_segment(spec: CSpec, steps: int = 1200) -> Segment:
    """Without a measured cycle (``ecmgen codegen``): a deterministic drive from a full cell,
    1 s steps, discharge pulses of 0.5 and 1 C and charge pulses of 0.5 C between rests,
    the temperature stepping over the tables' span: the step's ordinary range."""
    c1 = float(spec.capacity_ah)                    # 1 C, A
    k = np.arange(steps)
    phase = k % 120
    cur = np.where(phase < 30, -c1, np.where(phase < 60, 0.0, np.where(
        phase < 75, -0.5 * c1, np.where(phase < 90, 0.5 * c1, 0.0))))
    if spec.temp:
        lo, hi = (float(x) / (256.0 if spec.fixed else 1.0)
                  for x in (spec.temp_grid.x[0], spec.temp_grid.x[-1]))
    else:
        lo, hi = 25.0, 25.0
    temps = lo + (hi - lo) * ((k // 300) % 5) / 4.0
    dt = np.where(k == 0, 0.0, 1.0) if spec.variable_dt else None
    return Segment(1.0, cur.astype(np.float64), dt, temps.astype(np.float64))


def cycle_segment(spec: CSpec, series, soc0: float, steps: int = CYCLE_STEPS) -> Segment:
    """The first ``steps`` of a measured cycle as the build's C check drives it: its own time
    stamps (variable dt) or resampled to the build's dt."""
    from .cbuild import resample_uniform

    n0 = np.size(series.time_s)
    temps = np.zeros(n0) if series.temperature_c is None else np.broadcast_to(
        np.asarray(series.temperature_c, dtype=np.float64), (n0,))
    if spec.variable_dt:
        t, i = series.time_s, series.current_a
    else:
        t, i, _ = resample_uniform(series.time_s, series.current_a, None, spec.dt_s)
        temps = resample_uniform(series.time_s, temps, None, spec.dt_s)[1]
    t = np.asarray(t, dtype=np.float64)[:steps]
    i = np.asarray(i, dtype=np.float64)[:steps]
    temps = np.asarray(temps, dtype=np.float64)[:steps]
    dt = cref.dt_from_time(t) if spec.variable_dt else None
    return Segment(float(soc0), i, dt, np.asarray(temps, dtype=np.float64))


def _native(spec: CSpec, seg: Segment) -> dict:
    """The segment as the C takes it, and the reference's v and SOC."""
    if spec.fixed:
        ref = cref.simulate_fixed(spec, seg.current_a, seg.dt_s, seg.soc0, seg.temperature_c,
                                  seg.efc)[0]
        return {"i": cref.current_to_raw(spec, seg.current_a).astype(np.int32),
                "age": np.int32(cref.efc_to_raw(seg.efc)),
                "t": cref.temperature_to_raw(seg.temperature_c).astype(np.int32),
                "dt": None if seg.dt_s is None else cref.dt_to_raw(seg.dt_s).astype(np.int32),
                "soc0": np.int32(cref.soc_to_raw(seg.soc0)),
                "v": np.asarray(ref.v, dtype=np.int32), "soc": np.asarray(ref.soc, dtype=np.int32)}
    ref = cref.simulate_f32(spec, seg.current_a, seg.dt_s, seg.soc0, seg.temperature_c, seg.efc)
    f = np.float32
    return {"i": seg.current_a.astype(f), "t": seg.temperature_c.astype(f), "age": f(seg.efc),
            "dt": None if seg.dt_s is None else seg.dt_s.astype(f), "soc0": f(seg.soc0),
            "v": np.asarray(ref.v, dtype=f), "soc": np.asarray(ref.soc, dtype=f)}


def c_array(ctype: str, name: str, a: np.ndarray) -> str:
    a = np.asarray(a)
    if a.dtype == np.float32:
        vals = [f"0x{int(x):08x}u" for x in a.view(np.uint32)]
    else:
        vals = [str(int(x)) for x in a]
    rows = [", ".join(vals[k:k + 8]) for k in range(0, len(vals), 8)]
    return f"static const {ctype} {name}[{len(vals)}] = {{\n    " + ",\n    ".join(rows) + "\n};\n"


def render_vectors(spec: CSpec, segments: list[Segment]) -> dict[str, str]:
    """File name -> text of the vectors header and the C test program."""
    nm = c_names(spec.prefix, spec.numeric)
    names = vector_names(spec.prefix, spec.numeric)
    parts = [_native(spec, s) for s in segments]
    cat = {k: np.concatenate([p[k] for p in parts]) for k in ("i", "t", "v", "soc")}
    if spec.variable_dt:
        cat["dt"] = np.concatenate([p["dt"] for p in parts])
    starts = np.cumsum([0] + [p["i"].size for p in parts[:-1]])
    soc0 = np.array([p["soc0"] for p in parts])
    ages = np.array([p["age"] for p in parts])
    M, vp = nm["M"], f"{spec.prefix}_vec_{nm['suffix']}"
    ctype = "int32_t" if spec.fixed else "uint32_t"
    what = "raw Q integers" if spec.fixed else "float32 bit patterns"
    lines = [
        "/* SPDX-License-Identifier: MIT */",
        f"/* {names['vectors']} - golden vectors for {nm['step']}(), generated by ecmgen "
        f"{spec.tool_version}",
        f" * from model sha256 {spec.model_sha256}. DO NOT EDIT.",
        f" * Segments (each from {nm['init']}(soc0)): the first steps of a measured cycle (or, "
        "from ecmgen codegen, a drive of pulses and rests), an edge-case set",
        " * (currents past the limit, temperatures past the tables" +
        (", dt 0, long and negative)" if spec.variable_dt else ")") + ", then probes that read "
        "every table entry",
        " * (ecmgen.c.probes: the middle of every SOC, temperature and age segment of every "
        "table)." +
        (f" Each segment sets its age with {nm['set_age']}() after init (the"
         "\n * cycle fresh, then aged; the edge-case set past the ageing law's last breakpoint)."
         if spec.age is not None else ""),
        f" * Inputs and expected outputs (voltage, SOC after the step) are {what}; the",
        " * expected outputs are the Python reference's (ecmgen.c.cref). */",
        f"#ifndef {M}_VECTORS_H", f"#define {M}_VECTORS_H", "", "#include <stdint.h>", "",
        f"#define {M}_VEC_STEPS {cat['i'].size}u",
        f"#define {M}_VEC_SEGMENTS {len(parts)}u",
        f"#define {M}_VEC_BIT_EXACT 1   /* the reference and a conforming build agree bit for bit */",
        f"#define {M}_VEC_TABLES 0x{fingerprint(spec):08x}u   /* FNV-1a of the model's tables and "
        "constants (ecmgen.c.fingerprint) */",
    ]
    if not spec.fixed:
        lines += [f"#define {M}_VEC_TOL_V {TOL_V_F32!r}f     /* accepted |dv| of a build that is "
                  "not bit-exact, V */",
                  f"#define {M}_VEC_TOL_SOC {TOL_SOC_F32!r}f"]
    lines.append("")
    body = [c_array("uint32_t", f"{vp}_seg_start", starts),
            c_array(ctype, f"{vp}_soc0", soc0)]
    if spec.age is not None:
        body.append("/* the age set after init, equivalent full cycles */\n" +
                    c_array(ctype, f"{vp}_age", ages))
    for key, what in (("i", "current"), ("t", "temperature"), ("dt", "dt"), ("v", "voltage"),
                      ("soc", "SOC")):
        if key in cat:
            body.append(f"/* {what} */\n" + c_array(ctype, f"{vp}_{key}", cat[key]))
    text = "\n".join(lines) + "\n" + "\n".join(body) + f"\n#endif /* {M}_VECTORS_H */\n"
    ctx = _context(spec)
    ctx["files"] = dict(file_names(spec.prefix, spec.numeric), **names)
    ctx["vp"] = vp
    ctx["fp_lines"] = c_statements(spec)
    env = _env()
    return {names["vectors"]: text, names["test"]: env.get_template("ecm_test.c.j2").render(ctx),
            names["pytest"]: env.get_template("test_equivalence.py.j2").render(ctx)}


def write_golden(spec: CSpec, out_dir, series=None, soc0: float = 1.0) -> list[Path]:
    """The vectors and the test program into ``out_dir``: the cycle ``series`` (a TimeSeries;
    None: :func:`drive_segment`) from ``soc0``, the edge-case set, then the probes of
    :mod:`ecmgen.c.probes`."""
    first = cycle_segment(spec, series, soc0) if series is not None else drive_segment(spec)
    segments = [first, edge_segment(spec)]
    if spec.age is not None:     # the cycle again, aged; the edge cases past the law's end
        from dataclasses import replace

        from .spec import aged_efc

        law = np.asarray(spec.age["grid"].x, dtype=np.float64) / (256.0 if spec.fixed else 1.0)
        segments = [first, replace(first, efc=aged_efc(law)),
                    replace(segments[1], efc=2.0 * float(law[-1]))]
    return write_texts(out_dir, render_vectors(spec, segments + probe_segments(spec)))


def write_texts(out_dir, texts: dict[str, str]) -> list[Path]:
    """{name: text} into ``out_dir``, leaving a file with the same text alone."""
    from ..files import write_atomic

    out = []
    for name, text in texts.items():
        path = Path(out_dir) / name
        if not (path.exists() and path.read_text() == text):
            write_atomic(path, text)
        out.append(path)
    return out
