"""Is a fitted table physical? Smoothness, sign and support of every RC table of a model.

* roughness: per table row, the largest |ln p_k - ln p^_k| over the interior SOC nodes, with
  p^_k the linear interpolation of the neighbours' logarithms at node k (on a uniform grid
  ln p_k - (ln p_k-1 + ln p_k+1) / 2). A smooth table over SOC stays below about 0.3; a
  table that alternates between neighbouring nodes, or drops to zero, does not. Tables and
  rows with a non-positive value are counted apart (their logarithm does not exist). Only
  the nodes from the first to the last the fit marks converged count (for the whole-test
  fit, the nodes its levels pin down): beyond them a table holds its end value, and near
  empty, where resistances rise by a factor of 2-3 per 0.05 of SOC, the bend where that
  hold starts reads up to 0.6 whatever the fit (the Panasonic demo).
* non-positive: resistances and time constants <= 0 (a zero resistance is no measurement of
  one: a pulse at that SOC saw a voltage step).
* on bound: a time constant on its search bound (from the fit's flags) was not resolved.

:func:`model_quality` summarises a model; :func:`table_quality` gives the rows of a report.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RC_TABLES = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")
ROUGHNESS_LIMIT = 0.5      # above this a table row is reported as rough (real cells)


@dataclass(frozen=True)
class TableQuality:
    """One table row of one direction: where it is rough or non-positive."""

    direction: str
    name: str                  # r0_ohm, r_fast_ohm, ...
    temperature_c: float       # NaN for a one-temperature model
    roughness: float           # see the module docstring (0 for fewer than 3 nodes)
    roughest_soc: float        # the SOC node where it is largest (NaN when none)
    non_positive_soc: tuple    # SOC nodes with a value <= 0

    def as_dict(self) -> dict:
        return {"direction": self.direction, "table": self.name,
                "temperature_c": None if not np.isfinite(self.temperature_c)
                else float(self.temperature_c),
                "roughness": float(self.roughness),
                "roughest_soc": None if not np.isfinite(self.roughest_soc)
                else float(self.roughest_soc),
                "non_positive_soc": [float(s) for s in self.non_positive_soc]}


@dataclass(frozen=True)
class ModelQuality:
    """The model's worst table row and every row (``tables``)."""

    roughness: float
    non_positive: int
    on_bound: tuple = ()              # "tau_slow_s (500 s)" per time constant on a bound
    tables: tuple = field(default=(), repr=False)

    @property
    def passes(self) -> bool:
        return self.roughness <= ROUGHNESS_LIMIT and self.non_positive == 0

    def as_dict(self) -> dict:
        return {"roughness": float(self.roughness), "non_positive": int(self.non_positive),
                "on_bound": list(self.on_bound), "passes": self.passes,
                "roughness_limit": ROUGHNESS_LIMIT,
                "tables": [t.as_dict() for t in self.tables]}


def roughness(soc: np.ndarray, values: np.ndarray, fitted: np.ndarray | None = None
              ) -> tuple[float, float]:
    """(largest |ln p_k - interpolated neighbours|, the SOC where it is) over interior nodes
    with three positive neighbours; (0, NaN) when there are none. With ``fitted`` (bool per
    node) only the nodes from its first True to its last count: beyond them a table holds
    its end value, and a second difference across that end measures the hold, not the
    fit."""
    soc = np.asarray(soc, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if soc.size < 3:
        return 0.0, float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        lv = np.where(v > 0, np.log(np.where(v > 0, v, 1.0)), np.nan)
    if fitted is not None and np.any(fitted):
        on = np.flatnonzero(fitted)
        lv[:on[0]] = np.nan
        lv[on[-1] + 1:] = np.nan
    x0, x1, x2 = soc[:-2], soc[1:-1], soc[2:]
    w = (x1 - x0) / (x2 - x0)
    dev = np.abs(lv[1:-1] - ((1.0 - w) * lv[:-2] + w * lv[2:]))
    if not np.isfinite(dev).any():
        return 0.0, float("nan")
    k = int(np.nanargmax(dev))
    return float(dev[k]), float(x1[k])


def table_quality(model) -> list[TableQuality]:
    """Every RC table row of both directions of ``model`` (a direction copied from the other
    is the same object and listed once)."""
    out = []
    seen = []
    for d in ("discharge", "charge"):
        tab = getattr(model, d)
        if any(tab is s for s in seen):
            continue
        seen.append(tab)
        temps = np.atleast_1d(np.asarray(tab.temperature_c, dtype=np.float64))
        fitted = np.asarray(tab.converged, dtype=bool)
        for name in RC_TABLES:
            a = np.asarray(getattr(tab, name))
            for r in range(a.shape[0]):
                rough, at = roughness(tab.soc, a[r], fitted[r] if fitted.shape == a.shape
                                      else None)
                bad = tuple(float(s) for s in tab.soc[np.isfinite(a[r]) & (a[r] <= 0)])
                t = float(temps[r]) if temps.size == a.shape[0] else float("nan")
                out.append(TableQuality(d, name, t, rough, at, bad))
    return out


def model_quality(model, flags=()) -> ModelQuality:
    """Summary of :func:`table_quality`, with the time constants ``flags`` (FitFlags of
    :mod:`ecmgen.fit.checks`) found on a search bound."""
    rows = table_quality(model)
    rough = max((t.roughness for t in rows), default=0.0)
    bad = sum(len(t.non_positive_soc) for t in rows)
    bound = sorted({f"{f.param} ({f.value:.3g} s)" for f in flags if f.kind == "tau_on_bound"})
    return ModelQuality(rough, bad, tuple(bound), tuple(rows))


def quality_words(method: str, q: ModelQuality) -> str:
    """One line: why a model fails the table checks."""
    worst = max(q.tables, key=lambda t: t.roughness, default=None)
    parts = []
    if q.roughness > ROUGHNESS_LIMIT and worst is not None:
        where = "" if not np.isfinite(worst.temperature_c) else f" at {worst.temperature_c:g} degC"
        parts.append(f"{worst.direction} {worst.name} is rough over SOC (roughness "
                     f"{q.roughness:.2f} > {ROUGHNESS_LIMIT:g} at SOC {worst.roughest_soc:g}"
                     f"{where})")
    if q.non_positive:
        parts.append(f"{q.non_positive} table value(s) <= 0")
    return f"model {method!r} fails the table checks: " + "; ".join(parts)
