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


def usage(model, validation, ocv_span=None) -> dict:
    """The SOC range a validation ran through, and the share of its samples beyond each
    measured span (RC tables by the direction in use, the OCV)."""
    soc = np.clip(validation.sim.soc, 0.0, 1.0)
    out = {"soc_range": [float(soc.min()), float(soc.max())], "beyond_span": {}}
    spans = table_spans(model)
    charging = validation.sim.charging
    for d, (lo, hi) in spans.items():
        in_d = charging if d == "charge" else ~charging
        beyond = in_d & ((soc < lo - SPAN_MARGIN) | (soc > hi + SPAN_MARGIN))
        out["beyond_span"][d] = float(beyond.mean())
    if ocv_span is not None:
        lo, hi = ocv_span
        out["beyond_span"]["ocv"] = float(np.mean((soc < lo - SPAN_MARGIN) |
                                                  (soc > hi + SPAN_MARGIN)))
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
    for what, share in use["beyond_span"].items():
        if share < NOTE_SHARE or (what == "charge" and model.charge is model.discharge):
            continue
        a, b = spans[what]
        label = "the OCV" if what == "ocv" else f"the {what} RC table"
        parts.append(f"{label} (measured at SOC {a:.2f}..{b:.2f}) on {share:.0%} of the samples")
    if not parts:
        return []
    return [f"{model.method} on {name} (SOC {lo:.2f}..{hi:.2f}) uses " + "; ".join(parts)
            + " beyond the measured span, where it is held flat"]
