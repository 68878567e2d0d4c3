"""One fleet row on a worker: hash its inputs, build it unless its results are already
there under the same hash, and say how it went.

A row's outputs are the build's own (``DIR/<cell>/<checkup>/``: model.json, report.md,
...) plus ``fleet-row.json``, the row's record: the hash of its inputs (ecmgen.fleet.
manifest.row_key) and what the build measured that model.json does not hold (the
capacity the tests imply, the validation MAE per cycle, the table quality, the pulse
test's temperature). The record is written last, atomically, and removed before a build
starts, so a row is done exactly when its record is there with the current hash: a
killed run leaves the rows it finished and nothing else, and the next run builds the
rest.

Bad input of one row (its config, its measurement files) is that row's failure, with
the one line the command line would print; an error of ecmgen itself is too (kind
"internal", with its type), so one row never stops the fleet.
"""

from __future__ import annotations

import json
import math
import threading
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import InputError, describe, user_file_of
from ..files import json_text, write_atomic
from .manifest import Row, row_key

RECORD = "fleet-row.json"
RECORD_VERSION = 1
# one build at a time per worker process: a worker started with several threads would
# otherwise run builds side by side in one interpreter (matplotlib and the fits share state)
_ONE_BUILD = threading.Lock()


@dataclass(frozen=True)
class Options:
    """How every row is built (part of each row's hash)."""

    plots: bool = False         # the build's own PNGs per row
    c_code: bool = True         # the C, where the row's config asks for it ([c] numeric)

    def as_dict(self) -> dict:
        return {"plots": self.plots, "c_code": self.c_code}


@dataclass(frozen=True)
class Outcome:
    """What became of one row: status "built", "unchanged" or "failed" (then ``kind``
    "input" or "internal" and the one-line ``error``)."""

    cell: str
    checkup: str
    status: str
    seconds: float = 0.0
    cpu_seconds: float = 0.0        # of the worker process over the row
    error: str = ""
    kind: str = ""
    peak_rss_mb: float | None = None
    worker: str = ""


def row_folder(out: Path, row: Row) -> Path:
    return out / row.cell / row.checkup


def read_record(folder: Path) -> dict | None:
    """A row's record, or None when there is none (or it cannot be read: build again)."""
    try:
        doc = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("version") == RECORD_VERSION else None


def run_row(row: Row, out: Path, options: Options) -> Outcome:
    """Build one row unless it is done under its current hash (see the module doc)."""
    t0 = (time.perf_counter(), time.process_time())
    folder = row_folder(Path(out), row)
    try:
        with _ONE_BUILD, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            status = _build_if_changed(row, folder, options)
    except InputError as exc:
        return _failed(row, t0, str(exc), "input", folder)
    except Exception as exc:            # noqa: BLE001 - one row never stops the fleet
        where = user_file_of(exc)
        if where is None and isinstance(exc, OSError) and exc.filename is not None:
            where = exc.filename
        if where is not None:
            return _failed(row, t0, f"{where}: {describe(exc)}", "input", folder)
        last = traceback.extract_tb(exc.__traceback__)[-1]
        text = " ".join(str(exc).split())
        return _failed(row, t0, f"ecmgen fault: {type(exc).__name__}: {text} (at "
                                f"{Path(last.filename).name}:{last.lineno})", "internal", folder)
    return Outcome(row.cell, row.checkup, status, time.perf_counter() - t0[0],
                   time.process_time() - t0[1], peak_rss_mb=_peak_rss_mb(),
                   worker=_worker_name())


def _failed(row: Row, t0: tuple[float, float], error: str, kind: str,
            folder: Path | None = None) -> Outcome:
    if folder is not None and folder.is_dir():
        # the row's earlier results (built from other inputs) would pass for this one's
        from ..outputs import remove_outputs

        remove_outputs(folder, {Path(row.config).resolve()})
    return Outcome(row.cell, row.checkup, "failed", time.perf_counter() - t0[0],
                   time.process_time() - t0[1], error=" ".join(error.split()), kind=kind,
                   peak_rss_mb=_peak_rss_mb(), worker=_worker_name())


def _build_if_changed(row: Row, folder: Path, options: Options) -> str:
    from ..config import load_config
    from ..pipeline import build

    cfg = load_config(row.config)
    key = row_key(row.config, cfg.input_files(), options.as_dict())
    record = read_record(folder)
    if record is not None and record.get("key") == key and (folder / "model.json").is_file():
        return "unchanged"
    (folder / RECORD).unlink(missing_ok=True)
    result = build(cfg, folder, plots=options.plots, c_code=options.c_code, workers=1)
    write_atomic(folder / RECORD, json_text(_record(row, key, result), indent=1) + "\n")
    return "built"


def _record(row: Row, key: str, result) -> dict:
    """What the fleet table needs from a build beyond model.json."""
    from ..pipeline import pulses_temperature_c

    best = result.best
    quality = result.quality.get(best)
    capacity, source = capacity_from_tests(result)
    return {
        "version": RECORD_VERSION, "ecmgen": __version__, "key": key,
        "cell": row.cell, "checkup": row.checkup, "config": row.config.name,
        "best": best,
        "capacity_ah": capacity, "capacity_from": source,
        "pulses_temperature_c": pulses_temperature_c(result.inputs),
        "validation_mae_v": {name: v.overall.mae_v
                             for name, v in result.validations.get(best, {}).items()},
        "roughness": None if quality is None else float(quality.roughness),
        "quality_passes": None if quality is None else bool(quality.passes),
        "notes": len(result.models[best].notes) + len(result.notes),
    }


def capacity_from_tests(result) -> tuple[float | None, str | None]:
    """The capacity the row's tests measured: the discharge branch of a low-rate test
    among the OCV sources (from full to empty: the capacity test), else the capacity a
    pulse test's rests imply against the OCV (when the build fitted it), else None."""
    report = result.inputs.ocv_report
    for curve in (report.curves if report is not None else ()):
        q = dict(curve.capacity_ah or {}).get("discharge")
        if q is not None and math.isfinite(q) and q > 0:
            return float(q), f"low-rate discharge ({curve.name})"
    q = result.inputs.soc_capacity_ah
    rated = result.models[result.best].capacity_ah
    if q is not None and math.isfinite(q) and not np.isclose(q, rated, rtol=1e-9):
        return float(q), "pulse test rests against the OCV"
    return None, None


def _peak_rss_mb() -> float | None:
    try:
        import resource
    except ImportError:         # not on Windows
        return None
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return "local"
