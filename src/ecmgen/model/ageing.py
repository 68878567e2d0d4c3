"""The ageing law of a model: how its resistances and capacity change with the cell's age.

model.json's optional ``ageing`` section (absent: a model of one age, as before)::

    "ageing": {"version": 1, "axis": "equivalent_full_cycles",
               "equivalent_full_cycles": [0.0, 200.0, 400.0],
               "resistance_scale": [1.0, 1.08, 1.19],
               "capacity_scale": [1.0, 0.962, 0.925],
               "source": "..."}

The axis is the cell's equivalent full cycles (EFC: the charge it has moved, in Ah, over
twice its rated capacity): what a BMS already counts, the same unit for a 2 Ah and a 200 Ah
cell, and what an ageing study logs at each check-up. At age ``a`` the model's tables are
those of the cell at the first breakpoint with every resistance (r0, r_fast, r_slow and
r_diff) times ``resistance_scale(a)`` and the capacity times ``capacity_scale(a)``; both
are linear between the breakpoints and held at the end values beyond them (clamped: no
extrapolation past the ages the law was measured at). Both scales are exactly 1 at the
first breakpoint, so the model at age 0 (or at the first breakpoint) is the model without
the law, bit for bit, in Python and in the C.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AGEING_VERSION = 1
AXIS = "equivalent_full_cycles"
KEYS = ("version", "axis", AXIS, "resistance_scale", "capacity_scale", "source")
MAX_BREAKPOINTS = 64          # small const tables in the C
SCALE_RANGE = (0.05, 20.0)    # a scale outside this is not an ageing law of one cell type
EFC_MAX = 1e6                 # the C's fixed-point age (Q8) holds up to 2^23


@dataclass(frozen=True)
class AgeingLaw:
    """Resistance and capacity scales over equivalent full cycles (see the module)."""

    equivalent_full_cycles: np.ndarray
    resistance_scale: np.ndarray
    capacity_scale: np.ndarray
    source: str = ""              # how the law was found (free text, e.g. the fleet)

    def __post_init__(self):
        for k in (AXIS, "resistance_scale", "capacity_scale"):
            object.__setattr__(self, k, np.asarray(getattr(self, k), dtype=np.float64))
        x = self.equivalent_full_cycles
        n = x.size
        if x.ndim != 1 or not 2 <= n <= MAX_BREAKPOINTS:
            raise ValueError(f"ageing.{AXIS} must list 2..{MAX_BREAKPOINTS} breakpoints")
        if not np.all(np.isfinite(x)) or x[0] < 0 or x[-1] > EFC_MAX or np.any(np.diff(x) <= 0):
            raise ValueError(f"ageing.{AXIS} must be strictly increasing within 0..{EFC_MAX:g}")
        lo, hi = SCALE_RANGE
        for k in ("resistance_scale", "capacity_scale"):
            v = getattr(self, k)
            if v.shape != (n,):
                raise ValueError(f"ageing.{k} must have one value per breakpoint ({n})")
            if not np.all(np.isfinite(v)) or np.any(v < lo) or np.any(v > hi):
                raise ValueError(f"ageing.{k} must be in {lo:g}..{hi:g}")
            if v[0] != 1.0:
                raise ValueError(f"ageing.{k} must be 1 at the first breakpoint (the model's "
                                 f"own tables), got {v[0]!r}")

    def at(self, equivalent_full_cycles) -> tuple[np.ndarray, np.ndarray]:
        """(resistance scale, capacity scale) at the age, linear, clamped to the ends."""
        a = np.asarray(equivalent_full_cycles, dtype=np.float64)
        x = self.equivalent_full_cycles
        return np.interp(a, x, self.resistance_scale), np.interp(a, x, self.capacity_scale)

    def to_json_dict(self) -> dict:
        def floats(a):
            return [float(v) for v in a]

        return {"version": AGEING_VERSION, "axis": AXIS, AXIS: floats(self.equivalent_full_cycles),
                "resistance_scale": floats(self.resistance_scale),
                "capacity_scale": floats(self.capacity_scale), "source": self.source}


def ageing_from_json(raw, fail) -> AgeingLaw:
    """The section as read from model.json; ``fail(message)`` raises the caller's error."""
    if not isinstance(raw, dict):
        fail("ageing must be a JSON object")
    for key in raw:
        if key not in KEYS:
            fail(f"unknown key ageing.{key!r}; known: {', '.join(KEYS)}")
    version = raw.get("version")
    if isinstance(version, bool) or version != AGEING_VERSION:
        fail(f"ageing.version {version!r} is not supported (this ecmgen reads {AGEING_VERSION})")
    if raw.get("axis") != AXIS:
        fail(f"ageing.axis must be {AXIS!r}, got {raw.get('axis')!r}")
    values = {}
    for key in (AXIS, "resistance_scale", "capacity_scale"):
        v = raw.get(key)
        if not isinstance(v, list) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            fail(f"ageing.{key} must be a list of numbers")
        values[key] = v
    source = raw.get("source", "")
    if not isinstance(source, str):
        fail("ageing.source must be a string")
    try:
        return AgeingLaw(source=source, **values)
    except ValueError as exc:
        fail(str(exc))
        raise
