"""RC tables from fits made per SOC level (the five-point GA / LM fits)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .model import RcTable


def level_tables(soc, direction, cols: dict[str, np.ndarray], fit_error, converged,
               source: Path | None = None) -> tuple[RcTable, RcTable, list[str]]:
    """Per-direction RcTables from per-level fits (rows of ``soc``, ``direction`` and the
    columns ``cols``); a direction without data takes the other's, with a note."""
    tables, notes = {}, []
    for d in ("charge", "discharge"):
        ix = np.flatnonzero((direction == d) & np.all(np.isfinite(np.vstack(list(cols.values()))), axis=0))
        if ix.size == 0:
            continue
        ix = ix[np.argsort(soc[ix])]
        s = np.clip(soc[ix], 0.0, 1.0)
        ok = np.concatenate(([True], np.diff(s) > 1e-6))
        ix = ix[ok]
        tables[d] = RcTable(soc=np.clip(soc[ix], 0, 1), fit_error=np.asarray(fit_error)[ix],
                            converged=np.asarray(converged)[ix],
                            **{k: np.asarray(v)[ix] for k, v in cols.items()})
    if not tables:
        raise InputError(source, "no table cell could be fitted: no SOC level has an R(t) "
                                 "value at every [dcir] times_s (pulses cut short, or too "
                                 "short or too slowly logged for those times? [dcir] "
                                 "c_rate = \"all\" uses every C-rate)")
    for d, other in (("charge", "discharge"), ("discharge", "charge")):
        if d not in tables:
            tables[d] = tables[other]
            notes.append(f"the test has {other} pulses only: the {d} parameters are the "
                         f"{other} parameters")
    return tables["charge"], tables["discharge"], notes


def copied_directions(notes: list[str]) -> set[str]:
    """Directions whose table level_tables copied from the other."""
    return {d for d in ("charge", "discharge") for n in notes if f"the {d} parameters are" in n}
