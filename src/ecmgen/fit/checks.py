"""What a fit did not measure: time constants on a search bound or longer than the data
they were fitted on, and SOC levels left out. Each finding is a :class:`FitFlag`
(for ``--json``) and, summarised per method and kind, a note.

* point fits (GA, LM): the data is the pulse up to the last DC-IR time (10 s for the
  paper's five points); the search box is :func:`ecmgen.fit.points.default_bounds`.
* whole-test curve fit: one time constant per pair and test; the data for a slow one is
  the longest rest after a pulse (up to fit.relax_s); the box is the fit's
  ``tau_ranges``; SOC nodes outside the levels with a complete pulse are held flat
  (``left_out``; the fit's own note names them).

A time constant longer than the data window is not measured: the fit extrapolates
the curve's bend from the part it saw. One on its search bound was not resolved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .points import PointFit, default_bounds

TAU_FIELDS = ("tau_fast_s", "tau_slow_s")
BOUND_RTOL = 0.01


@dataclass(frozen=True)
class FitFlag:
    method: str
    kind: str          # "tau_on_bound" | "tau_beyond_data" | "left_out"
    direction: str
    soc: float
    param: str         # "tau_fast_s" | "tau_slow_s" | "" (left out)
    value: float       # the time constant, s (NaN when left out)
    limit: float       # the bound or the data window, s (NaN when left out)

    def as_dict(self) -> dict:
        return {"method": self.method, "kind": self.kind, "direction": self.direction,
                "soc": self.soc, "param": self.param, "value": self.value,
                "limit": self.limit}


def _tau_flags(method, soc, direction, taus: dict, boxes: dict, window) -> list[FitFlag]:
    out = []
    for k in range(len(soc)):
        for name in TAU_FIELDS:
            v = float(taus[name][k])
            if not np.isfinite(v):
                continue
            lo, hi = boxes[name]
            for b in (lo, hi):
                if np.isclose(v, b, rtol=BOUND_RTOL):
                    out.append(FitFlag(method, "tau_on_bound", str(direction[k]),
                                       float(soc[k]), name, v, float(b)))
            if name == "tau_slow_s" and v > window[k]:
                out.append(FitFlag(method, "tau_beyond_data", str(direction[k]), float(soc[k]),
                                   name, v, float(window[k])))
    return out


def point_fit_flags(method: str, fit: PointFit, rows) -> list[FitFlag]:
    """Flags of a GA/LM fit of the DC-IR rows ``rows`` (a DcirTable)."""
    b = default_bounds(rows.t_s, rows.r_ohm)
    boxes = {"tau_fast_s": b.tau_fast_s, "tau_slow_s": b.tau_slow_s}
    last = np.array([rows.t_s[np.flatnonzero(np.isfinite(r))[-1]] if np.isfinite(r).any()
                     else np.nan for r in rows.r_ohm])
    flags = _tau_flags(method, rows.soc, rows.direction,
                       {k: getattr(fit, k) for k in TAU_FIELDS}, boxes, last)
    left = ~np.isfinite(fit.tau_slow_s)
    flags += [FitFlag(method, "left_out", str(rows.direction[k]), float(rows.soc[k]), "",
                      float("nan"), float("nan")) for k in np.flatnonzero(left)]
    return flags


def curve_fit_flags(cf, relaxation_s: float | None = None) -> list[FitFlag]:
    """Flags of a whole-test curve fit (a CurveFit): its time constants (one per test) on
    a search bound or, for the slow and diffusion pairs, longer than ``relaxation_s`` (the
    longest rest after a pulse the test has, up to fit.relax_s); the SOC nodes held flat
    (``left_out``: outside the levels with a complete pulse)."""
    flags = []
    for kind, (lo, hi) in (cf.tau_ranges or {}).items():
        name = f"tau_{kind}_s"
        v = getattr(cf, name, None)
        if v is None:
            continue
        for d in cf.directions:
            for b in (lo, hi):
                if np.isclose(v, b, rtol=BOUND_RTOL):
                    flags.append(FitFlag("curve", "tau_on_bound", d, float("nan"), name, v,
                                         float(b)))
            if kind != "fast" and relaxation_s is not None and v > relaxation_s:
                flags.append(FitFlag("curve", "tau_beyond_data", d, float("nan"), name, v,
                                     float(relaxation_s)))
    for d in cf.directions:
        t = cf.table(d)
        flags += [FitFlag("curve", "left_out", d, float(s), "", float("nan"), float("nan"))
                  for s in cf.soc[~np.asarray(t.identified)]]
    return flags


def flag_notes(flags: list[FitFlag]) -> list[str]:
    """One note per method, kind and time constant."""
    notes = []
    groups: dict[tuple, list[FitFlag]] = {}
    for f in flags:
        groups.setdefault((f.method, f.kind, f.param), []).append(f)
    for (method, kind, param), fs in groups.items():
        if method == "curve" and kind in ("left_out", "tau_on_bound"):
            continue       # the curve fit's own notes name them
        where = ", ".join(f"{f.soc:.2f} ({f.direction})" if np.isfinite(f.soc) else
                          f"every SOC ({f.direction})" for f in fs[:6])
        more = f" and {len(fs) - 6} more" if len(fs) > 6 else ""
        name = param[:-2] if param.endswith("_s") else param
        if kind == "tau_on_bound":
            vals = sorted({round(f.limit, 3) for f in fs})
            notes.append(f"{method}: {name} on its search bound ({', '.join(f'{v:g}' for v in vals)}"
                         f" s) at SOC {where}{more}: not resolved by the data")
        elif kind == "tau_beyond_data":
            top = max(fs, key=lambda f: f.value / f.limit)
            notes.append(f"{method}: {name} longer than the data it was fitted on at "
                         f"{len(fs)} level{'s' if len(fs) > 1 else ''} (SOC {where}{more}; "
                         f"e.g. {top.value:.3g} s from {top.limit:.3g} s of data): extrapolated, "
                         "not measured")
        else:
            why = (f" ({name} on its search bound)" if param else " (no fit)")
            notes.append(f"{method}: SOC level{'s' if len(fs) > 1 else ''} {where}{more} "
                         f"left out{why}; the table interpolates across")
    return notes
