"""The tables' fingerprint: FNV-1a (32 bit) over every value of the model's ``const`` struct
(``<prefix>_model_<s>``: each table through its pointer, each grid and constant), as 32-bit
words, each word's bytes least significant first, in the struct's order.

The golden test program computes it from the tables it is linked with and compares it with
the value ecmgen computed here from what it generated: an entry changed anywhere - also
one the golden vectors do not move by a whole LSB, or one the step never reads - fails the
check. The order and the C expressions come from one list (:func:`fingerprint_items`), so
the program and this module cannot drift apart.
"""

from __future__ import annotations

import numpy as np

from .codegen import CSpec, _context

FNV_OFFSET = 0x811C9DC5
FNV_PRIME = 0x01000193


def _words(values, fixed: bool) -> np.ndarray:
    a = np.asarray(values)
    if fixed:
        return a.astype(np.int64).astype(np.uint32)         # two's complement, mod 2^32
    return a.astype(np.float32).view(np.uint32)


def _literal(text: str, fixed: bool):
    """A scalar as the generated C writes it (an int, or a float literal ending in f)."""
    return int(text) if fixed else np.float32(float(text.rstrip("f")))


def _grid(spec: CSpec, expr: str, g, fixed: bool, uniform: bool) -> list[tuple]:
    """(expr, kind, words) of a grid struct's members, in their declaration order."""
    if not uniform:
        return [(f"{expr}.x", "arr", _words(g.x, fixed)),
                (f"{expr}.inv_dx", "arr", _words(g.inv_dx, fixed)),
                (f"{expr}.n", "u8", np.array([g.n], dtype=np.uint32))]
    if fixed:
        um = (g.n - 1) << 30
        return [(f"{expr}.um", "i64", np.array([um & 0xFFFFFFFF, um >> 32], dtype=np.uint32)),
                (f"{expr}.x0", "val", _words([g.x0], True)),
                (f"{expr}.inv_h", "val", _words([g.inv_h], True)),
                (f"{expr}.n", "u8", np.array([g.n], dtype=np.uint32))]
    return [(f"{expr}.x0", "val", _words([g.x0], False)),
            (f"{expr}.inv_h", "val", _words([g.inv_h], False)),
            (f"{expr}.um", "val", _words([g.n - 1], False)),
            (f"{expr}.n", "u8", np.array([g.n], dtype=np.uint32))]


def fingerprint_items(spec: CSpec) -> list[tuple[str, str, np.ndarray]]:
    """(C expression on ``m->``, kind, expected words) for every member of the model's
    struct that holds a number, in the order of templates/ecm.c.j2."""
    fixed = spec.fixed
    ctx = _context(spec)
    vals = {a["name"]: a["values"] for a in ctx["arrays"]}
    items: list[tuple] = []
    if spec.temp:
        items += _grid(spec, "m->t", spec.temp_grid, fixed, False)
    if ctx["ocv_grid"] is not None:
        items += _grid(spec, "m->ocv_g", spec.ocv_grid, fixed, spec.ocv_uniform)
        items.append(("m->ocv", "arr", _words(vals[ctx["ocv"]], fixed)))
    for k, (d, cd) in enumerate(zip(spec.dirs, ctx["dirs"])):
        items += _grid(spec, f"m->dir[{k}].g", d.grid, fixed, spec.rc_uniform)
        for key in ("rows", "tk", "branch"):
            if cd[key] is not None:
                items.append((f"m->dir[{k}].{key}", "arr", _words(vals[cd[key]], fixed)))
    for name, text, _ in ctx["scalars"]:
        if name == "age":
            items += _grid(spec, "m->age", spec.age["grid"], fixed, False)
        elif text in vals:
            items.append((f"m->{name}", "arr", _words(vals[text], fixed)))
        else:
            items.append((f"m->{name}", "val", _words([_literal(text, fixed)], fixed)))
    return items


def fnv1a(words) -> int:
    h = FNV_OFFSET
    for w in np.asarray(words, dtype=np.uint32).tolist():
        for shift in (0, 8, 16, 24):
            h = ((h ^ ((w >> shift) & 0xFF)) * FNV_PRIME) & 0xFFFFFFFF
    return h


def fingerprint(spec: CSpec) -> int:
    """The value the golden test program computes from correct tables."""
    return fnv1a(np.concatenate([w for _, _, w in fingerprint_items(spec)]))


def c_statements(spec: CSpec) -> list[str]:
    """The test program's statements folding each member into ``h`` (``m`` points at the
    model's struct; ecmv_fp_* are the template's helpers)."""
    out = []
    for expr, kind, words in fingerprint_items(spec):
        if kind == "arr":
            fn = "ecmv_fp_i32s" if spec.fixed else "ecmv_fp_f32s"
            out.append(f"h = {fn}(h, {expr}, {words.size}u);")
        elif kind == "u8":
            out.append(f"h = ecmv_fp_word(h, (uint32_t){expr});")
        elif kind == "i64":
            out.append(f"h = ecmv_fp_word(h, (uint32_t)((uint64_t){expr} & 0xFFFFFFFFu));")
            out.append(f"h = ecmv_fp_word(h, (uint32_t)((uint64_t){expr} >> 32));")
        elif spec.fixed:
            out.append(f"h = ecmv_fp_word(h, (uint32_t){expr});")
        else:
            out.append(f"h = ecmv_fp_word(h, ecmv_bits({expr}));")
    return out
