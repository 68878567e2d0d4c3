"""Where a model is used beyond what was measured: the SOC span of each RC table and
of the OCV against the SOC a validation cycle runs through. Outside its span a table
is held flat at its end value: a number the data never gave."""

from __future__ import annotations

import numpy as np

SPAN_MARGIN = 0.02      # SOC beyond a span by less than this is not worth a note
NARROW_SPAN = 0.1       # a table leaving more than this unmeasured at an end is noted


def table_spans(model) -> dict[str, list[float]]:
    """{"charge": [lo, hi], "discharge": [lo, hi]}: the SOC the RC tables were measured at."""
    return {d: [float(model.table(d).soc[0]), float(model.table(d).soc[-1])]
            for d in ("charge", "discharge")}


def model_span_notes(model, copied: set[str] = frozenset()) -> list[str]:
    """A note for each RC table measured over a narrow SOC span (``copied``: directions
    whose table is the other's, not noted twice)."""
    notes = []
    for d, (lo, hi) in table_spans(model).items():
        if d in copied:
            continue
        if lo > NARROW_SPAN or hi < 1.0 - NARROW_SPAN:
            notes.append(f"{model.method}: the {d} RC table is measured at SOC {lo:.2f}..{hi:.2f}"
                         " only; held flat at its end values outside that span")
    return notes


def _at_temperature(rows, temperature_c: np.ndarray, what: str
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per sample, the SOC span of ``what`` at its temperature: between two temperature
    rows the narrower of theirs (a value held flat in either row enters the blend), beyond
    them the nearest row's. ``rows``: [(temperature_c, {what: [lo, hi]})], sorted."""
    temps = np.array([t for t, _ in rows])
    lo = np.array([r[what][0] for _, r in rows])
    hi = np.array([r[what][1] for _, r in rows])
    k = np.clip(np.searchsorted(temps, temperature_c), 1, len(rows) - 1)
    below = np.clip(k - 1, 0, len(rows) - 1)
    lo_t = np.maximum(lo[below], lo[k])
    hi_t = np.minimum(hi[below], hi[k])
    outside = (temperature_c <= temps[0]) | (temperature_c >= temps[-1])
    nearest = np.where(temperature_c <= temps[0], 0, len(rows) - 1)
    return np.where(outside, lo[nearest], lo_t), np.where(outside, hi[nearest], hi_t)


def usage(model, validation, ocv_span=None, rows=None) -> dict:
    """The SOC range a validation ran through, and the share of its samples beyond each
    measured span (RC tables by the direction in use, the OCV). ``rows``: the spans of
    each temperature row of a model over temperature ([(temperature_c, {"ocv": [lo, hi],
    "charge": ..., "discharge": ...})]): each sample is then judged against the spans at
    its own temperature, not their union."""
    soc = np.clip(validation.sim.soc, 0.0, 1.0)
    out = {"soc_range": [float(soc.min()), float(soc.max())], "beyond_span": {}}
    spans = {**table_spans(model), **({"ocv": list(ocv_span)} if ocv_span else {})}
    temps = validation.temperature_c
    by_row = rows is not None and len(rows) > 1 and temps is not None
    if by_row:
        rows = sorted(rows, key=lambda r: r[0])
        out["row_spans"] = {f"{t:g}": r for t, r in rows}
    charging = validation.sim.charging
    for what in spans:
        lo, hi = _at_temperature(rows, np.asarray(temps, float), what) if by_row and \
            all(what in r for _, r in rows) else spans[what]
        beyond = (soc < np.asarray(lo) - SPAN_MARGIN) | (soc > np.asarray(hi) + SPAN_MARGIN)
        if what != "ocv":
            beyond &= charging if what == "charge" else ~charging
        out["beyond_span"][what] = float(beyond.mean())
    return out


NOTE_SHARE = 0.01       # a cycle using a table beyond its span for this share is noted


def usage_notes(model, name: str, use: dict, ocv_span=None) -> list[str]:
    """One note per cycle naming what it used beyond the measured spans (a table the
    other direction's copy is named once)."""
    lo, hi = use["soc_range"]
    spans = dict(table_spans(model))
    if ocv_span is not None:
        spans["ocv"] = list(ocv_span)
    parts = []
    rows = use.get("row_spans")
    for what, share in use["beyond_span"].items():
        if share < NOTE_SHARE or (what == "charge" and model.charge is model.discharge):
            continue
        label = "the OCV" if what == "ocv" else f"the {what} RC table"
        if rows and all(what in r for r in rows.values()):
            measured = ", ".join(f"{r[what][0]:.2f}..{r[what][1]:.2f} at {t} degC"
                                 for t, r in rows.items())
        else:
            a, b = spans[what]
            measured = f"{a:.2f}..{b:.2f}"
        parts.append(f"{label} (measured at SOC {measured}) on {share:.0%} of the samples")
    if not parts:
        return []
    return [f"{model.method} on {name} (SOC {lo:.2f}..{hi:.2f}) uses " + "; ".join(parts)
            + " beyond the measured span at its temperature, where it is held flat "
              "(warning)"]


# a cell warming this far from its one test's temperature is noted: the Panasonic cell's
# DC-IR falls by 12-25 % over 5 K at 0-25 degC (Ea/R 2100-3300 K between its tests), the
# Leaf's by 1-2 % (130-420 K between 25 and 40 degC): no one Ea/R stands for every cell
TEMPERATURE_NOTE_K = 5.0


def temperature_note(model, name: str, validation, test_c: float | None) -> str | None:
    """A warning when ``validation`` ran the cell more than TEMPERATURE_NOTE_K from the
    one temperature ``test_c`` its model was measured at, while the model's resistances
    do not follow the temperature (one row, no temperature_dependence effect)."""
    span = validation.temperature_range_c
    if (span is None or test_c is None or not np.isfinite(test_c) or model.needs_temperature
            or any(e.name == "temperature_dependence" for e in model.effects)):
        return None
    if max(abs(span[0] - test_c), abs(span[1] - test_c)) <= TEMPERATURE_NOTE_K:
        return None
    return (f"{name}: the cell runs at {span[0]:.1f}..{span[1]:.1f} degC, the model's "
            f"resistances stay its pulse test's at {test_c:.1f} degC ([model] activation_k, "
            "the cell's Ea/R, makes them follow; or pulse tests at more temperatures) (warning)")
