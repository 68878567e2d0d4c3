"""The ``[diagnose]`` section of a build config, checked and turned into the keyword
arguments of :func:`ecmgen.diagnosis.search.diagnose`."""

from __future__ import annotations

from ..errors import InputError
from ..model import effects as fx
from . import corrections as cx

# the effects of the model and the faults of the record (corrected in the data)
CANDIDATE_NAMES = fx.EFFECT_NAMES + cx.CORRECTION_NAMES


def diagnose_options(table, path=None) -> dict:
    """Check the optional ``[diagnose]`` table of a build config and turn it into keyword
    arguments of :func:`diagnose` (plus ``"cycle"`` and ``"judge"``: the file names as
    written, relative to the config, or None). Unknown keys or bad values raise
    InputError naming ``path``::

        [diagnose]
        cycle = "dyn.csv"         # the record to diagnose on (default: data.cycle)
        cycle_soc0 = 1.0          # its start SOC (default: data.soc0 for data.cycle, else
                                  # from its first rested voltage)
        judge = "hwfet-a.mat"     # a second cycle to judge on (default: the last part of
                                  # data.cycle, see split)
        judge_soc0 = 1.0          # its start SOC (default: from its first rested voltage)
        base = "out/model.json"   # the model to start from (default: the base fitted
                                  # from the config's data, the plain 2RC)
        split = 0.6               # fraction of data.cycle that is fitted without a judge
        effects = ["hysteresis", "extra_rc"]   # candidates (default: all)
        max_effects = 4
        min_rel_gain = 0.08       # held-out MAE must fall by at least this fraction
        confidence = 0.99         # of the block-bootstrap bound on the held-out gain
    """
    table = {} if table is None else table
    if not isinstance(table, dict):
        raise InputError(path, "[diagnose] must be a table")
    known = {"cycle", "cycle_soc0", "judge", "judge_soc0", "base", "split", "effects",
             "max_effects", "min_rel_gain", "confidence"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise InputError(path, f"unknown key(s) in [diagnose]: {', '.join(unknown)}; "
                               f"known: {', '.join(sorted(known))}")

    def number(key, lo, hi, integer=False):
        v = table[key]
        ok = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok or not (lo <= v <= hi):
            kind = "an integer" if integer else "a number"
            raise InputError(path, f"diagnose.{key} must be {kind} in [{lo}, {hi}], got {v!r}")
        return int(v) if integer else float(v)

    out: dict = {"judge": None, "cycle": None, "base": None}
    for key in ("cycle", "judge", "base"):
        if key in table:
            if not isinstance(table[key], str) or not table[key]:
                raise InputError(path, f"diagnose.{key} must be a file name")
            out[key] = table[key]
    if "cycle_soc0" in table:
        out["soc0"] = number("cycle_soc0", 0.0, 1.0)
    if "judge_soc0" in table:
        out["judge_soc0"] = number("judge_soc0", 0.0, 1.0)
    if "split" in table:
        out["split"] = number("split", 0.1, 0.9)
    if "effects" in table:
        eff = table["effects"]
        if not isinstance(eff, list) or not eff or any(e not in CANDIDATE_NAMES for e in eff):
            raise InputError(path, f"diagnose.effects must be a non-empty list from "
                                   f"{list(CANDIDATE_NAMES)}, got {eff!r}")
        out["candidates"] = tuple(eff)
    if "max_effects" in table:
        out["max_effects"] = number("max_effects", 1, len(CANDIDATE_NAMES), integer=True)
    if "min_rel_gain" in table:
        out["min_rel_gain"] = number("min_rel_gain", 0.0, 0.9)
    if "confidence" in table:
        out["confidence"] = number("confidence", 0.5, 0.9999)
    return out
