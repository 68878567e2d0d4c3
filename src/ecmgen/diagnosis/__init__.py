"""Stage 4b, ``ecmgen diagnose``: find where the model and the measurement disagree,
name the missing effect, add it, and prove the gain on held-out data.

:mod:`.search` the signatures, the greedy search and the held-out judging
(:func:`diagnose`), :mod:`.problems` the candidate fits (casadi forward sensitivities of
the discrete step), :mod:`.corrections` the faults of the record (current sensor, OCV
table, a lagging voltage channel), :mod:`.lookalike` the block bootstrap and the look-alikes
the data cannot tell apart, :mod:`.prune` an effect named early judged again once later ones
joined, :mod:`.output` model.json, report.md, diagnose.json
and the plots, :mod:`.synthcell` synthetic cells with a hidden effect (for tests and
benches).
"""

from .output import report_text, write_diagnose_outputs
from .search import DiagnoseResult, diagnose, diagnose_options

__all__ = ["DiagnoseResult", "diagnose", "diagnose_options", "report_text",
           "write_diagnose_outputs"]
