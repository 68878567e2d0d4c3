"""What a model.json may hold: every key with its JSON type, and the physical ranges of
its values; read before any table is built, so that anything else is one line naming the
file and the field.

Strict on purpose: JSON has numbers, so a string ("0.05") or a boolean where a number
belongs is a fault of whatever wrote the file, not a value to guess at. The ranges
(:data:`MODEL_RANGES`) are the ones the C code generator accepts
(ecmgen.c.spec.validate_for_c reads them from here), so that ``validate`` and ``codegen``
accept the same models; the C adds only limits of its own representation (at most 255
breakpoints, float32 underflow), which say nothing about the cell.
"""

from __future__ import annotations

import difflib
import math
from typing import Any

from ..errors import InputError

# value kind -> (lowest, highest, unit); the physical range of a cell's model
MODEL_RANGES = {
    "capacity_ah": (1e-3, 1e5, "Ah"),           # a coin cell .. a large stationary cell
    "direction_deadband_a": (0.0, 1e4, "A"),
    "surface_soc_gain": (0.0, 10.0, ""),
    "ocv_v": (1e-3, 100.0, "V"),
    "r_ohm": (0.0, 100.0, "ohm"),
    "tau_s": (1e-3, 1e6, "s"),
    "i0_a": (1e-6, 1e5, "A"),
    "temperature_c": (-100.0, 200.0, "degC"),
}

NUMBER, TEXT, INTEGER, OBJECT, LIST = "number", "string", "integer", "object", "list"
# top-level key -> (JSON kind, required)
TOP_LEVEL = {
    "schema": (TEXT, True), "schema_version": (INTEGER, True), "tool_version": (TEXT, False),
    "method": (TEXT, False), "seed": (INTEGER, False), "capacity_ah": (NUMBER, True),
    "direction_deadband_a": (NUMBER, False), "surface_soc_gain": (NUMBER, False),
    "ocv": (OBJECT, True), "rc": (OBJECT, True), "ageing": (OBJECT, False),
    "effects": (LIST, False),
    "inputs": (LIST, False), "notes": (LIST, False),
}
OCV_KEYS = ("temperature_c", "soc", "ocv_v")
TABLE_KEYS = ("temperature_c", "soc", "r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm",
              "tau_slow_s", "r_diff_ohm", "tau_diff_s", "i0_a", "fit_error", "converged")
INPUT_KEYS = ("role", "name", "sha256")


def _is(kind: str, v: Any) -> bool:
    if kind == NUMBER:
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    if kind == INTEGER:
        return isinstance(v, int) and not isinstance(v, bool)
    return isinstance(v, {TEXT: str, OBJECT: dict, LIST: list}[kind])


def _unknown(d: dict, known, where: str, path) -> None:
    for key in d:
        if key not in known:
            near = difflib.get_close_matches(str(key), list(known), n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise InputError(path, f"unknown key {where}{key!r}{hint}; known: "
                                   f"{', '.join(known)}")


def _numbers(v: Any, where: str, path, *, nulls: bool = False, bools: bool = False) -> None:
    """A number, or (nested) lists of numbers: no strings, no booleans (``bools``: only
    booleans), no NaN (JSON has none; Python's reader takes NaN/Infinity literally)."""
    if isinstance(v, list):
        for x in v:
            _numbers(x, where, path, nulls=nulls, bools=bools)
        return
    if v is None and nulls:
        return
    if bools:
        if not isinstance(v, bool):
            raise InputError(path, f"{where} must hold true/false values, got {v!r}")
        return
    if not _is(NUMBER, v):
        raise InputError(path, f"{where} must hold numbers, got {v!r}")
    if not math.isfinite(v):
        raise InputError(path, f"{where} has a non-finite value ({v!r})")


def check_model_json(raw: Any, path) -> None:
    """Types and keys of a parsed model.json (after its schema tag was checked)."""
    _unknown(raw, TOP_LEVEL, "", path)
    for key, (kind, required) in TOP_LEVEL.items():
        if key not in raw:
            if required:
                raise InputError(path, f"missing {key}")
            continue
        v = raw[key]
        if key == "seed" and v is None:
            continue
        if not _is(kind, v):
            raise InputError(path, f"{key} must be a JSON {kind}, got {v!r}"[:200])
        if kind == NUMBER and not math.isfinite(v):
            raise InputError(path, f"{key} must be finite, got {v!r}")
    for key in ("capacity_ah", "direction_deadband_a", "surface_soc_gain"):
        if key in raw:
            in_range(raw[key], key, key, path)
    if raw.get("seed") is not None and raw["seed"] < 0:
        raise InputError(path, f"seed must be a non-negative integer, got {raw['seed']!r}")
    _unknown(raw["ocv"], OCV_KEYS, "ocv.", path)
    for key in OCV_KEYS:
        if key in raw["ocv"]:
            _numbers(raw["ocv"][key], f"ocv.{key}", path, nulls=key == "temperature_c")
    _unknown(raw["rc"], ("charge", "discharge"), "rc.", path)
    for direction, table in raw["rc"].items():
        where = f"rc.{direction}."
        if not isinstance(table, dict):
            raise InputError(path, f"{where[:-1]} must be a JSON object")
        _unknown(table, TABLE_KEYS, where, path)
        for key, v in table.items():
            _numbers(v, where + key, path, nulls=key == "temperature_c",
                     bools=key == "converged")
    for n, e in enumerate(raw.get("effects", []), 1):
        if not isinstance(e, dict):
            raise InputError(path, f"effects[{n}] must be a JSON object, got {e!r}")
    for n, r in enumerate(raw.get("inputs", []), 1):
        if not isinstance(r, dict) or set(r) != set(INPUT_KEYS) or \
                not all(isinstance(r[k], str) for k in INPUT_KEYS):
            raise InputError(path, f"inputs[{n}] must be an object of the strings "
                                   f"{', '.join(INPUT_KEYS)}, got {r!r}"[:200])
    for n, note in enumerate(raw.get("notes", []), 1):
        if not isinstance(note, str):
            raise InputError(path, f"notes[{n}] must be a string, got {note!r}")


def in_range(values, kind: str, where: str, path) -> None:
    """InputError unless every finite value lies in MODEL_RANGES[kind]."""
    import numpy as np

    lo, hi, unit = MODEL_RANGES[kind]
    a = np.asarray(values, dtype=np.float64)
    bad = a[np.isfinite(a) & ((a < lo) | (a > hi))]
    if bad.size:
        raise InputError(path, f"{where} must be in the plausible range {lo:g}..{hi:g}"
                               f"{' ' + unit if unit else ''}, got {bad.flat[0]:g}")


def check_model_ranges(model, path) -> None:
    """Every table value of an EcmModel within MODEL_RANGES (one line naming the field)."""
    in_range(model.capacity_ah, "capacity_ah", "capacity_ah", path)
    in_range(model.direction_deadband_a, "direction_deadband_a", "direction_deadband_a", path)
    in_range(model.ocv.ocv_v, "ocv_v", "ocv.ocv_v", path)
    in_range(model.ocv.temperature_c, "temperature_c", "ocv.temperature_c", path)
    for d in ("charge", "discharge"):
        t = model.table(d)
        in_range(t.temperature_c, "temperature_c", f"rc.{d}.temperature_c", path)
        for k in TABLE_KEYS[2:-2]:          # the resistances, time constants and i0_a
            v = getattr(t, k, None)
            if v is not None:
                kind = "i0_a" if k == "i0_a" else "tau_s" if k.startswith("tau") else "r_ohm"
                in_range(v, kind, f"rc.{d}.{k}", path)
