"""``ecmgen fleet``: every manifest row one build task on Dask, then the fleet table.

:func:`run_fleet` reads and checks the manifest (ecmgen.fleet.manifest; anything wrong
with it stops here, before any work), starts a ``LocalCluster`` (one single-threaded
worker process per core, or ``workers``) or connects to a running scheduler
(``scheduler``: its address; its workers need this ecmgen installed and the manifest's
folder at the same path), submits one task per row (ecmgen.fleet.task.run_row: a row
whose results are there under the same input hash is left alone), shows the progress on
stderr, and writes into ``out``:

- ``<cell>/<checkup>/``: each row's build outputs and its record (``fleet-row.json``);
- ``failures.csv``: ``cell,checkup,config,kind,error``, one line per failed row (the
  header alone when none failed);
- ``fleet.csv`` and ``fleet.parquet`` (ecmgen.fleet.table), ``ageing.csv`` (each cell's
  rates, ecmgen.fleet.ageing) and the trend plots (ecmgen.fleet.plots) over every row
  that has results.

A row that fails (its config or files are bad, or ecmgen fails on them) is listed in
failures.csv; the others go on. Dask is an optional dependency (``pip install
'ecmgen[fleet]'``): the rest of ecmgen does not need it.
"""

from __future__ import annotations

import csv
import io
import logging
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..errors import InputError
from ..files import write_atomic
from ..outputs import check_output_folder, refuse_inputs, resolved
from .manifest import Row, read_manifest
from .task import Options, Outcome, run_row

DEFAULT_SOC = (0.2, 0.5, 0.8)
DEFAULT_TEMPERATURES_C = (25.0,)
CONNECT_TIMEOUT_S = 20.0
LOCAL_HTTP = "127.0.0.1:0"       # the local cluster's HTTP server (see _client)
INSTALL_HINT = "pip install 'ecmgen[fleet]' (dask.distributed and pyarrow)"
FLEET_FILES = ("failures.csv", "fleet.csv", "fleet.parquet", "ageing.csv")   # written into out


def _quiet(_msg: str) -> None:
    pass


@dataclass
class FleetResult:
    """What a fleet run did: every row's outcome (manifest order) and the files written."""

    rows: list[Row]
    outcomes: list[Outcome]
    out_dir: Path
    table: list[dict] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    workers: int = 0
    seconds: float = 0.0            # the whole run
    rows_seconds: float = 0.0       # from the first row submitted to the last one back

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def failed(self) -> list[Outcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def as_dict(self) -> dict:
        return {"rows": len(self.rows), "built": self.count("built"),
                "unchanged": self.count("unchanged"), "failed": self.count("failed"),
                "workers": self.workers, "seconds": self.seconds,
                "rows_seconds": self.rows_seconds,
                "out": str(self.out_dir), "files": [str(p) for p in self.files],
                "failures": [{"cell": o.cell, "checkup": o.checkup, "kind": o.kind,
                              "error": o.error} for o in self.failed]}


def run_fleet(manifest: str | Path, out: str | Path, *, scheduler: str | None = None,
              workers: int | None = None, soc_points=DEFAULT_SOC,
              temperatures_c=DEFAULT_TEMPERATURES_C, options: Options = Options(),
              parquet: bool = True, plots: bool = True,
              progress: Callable[[str], None] = _quiet) -> FleetResult:
    """Build every row of ``manifest`` into ``out`` (see the module doc)."""
    t0 = time.perf_counter()
    rows = read_manifest(manifest)
    out = resolved(out)
    inputs = {Path(manifest).resolve(), *(r.config for r in rows)}
    check_output_folder(out, inputs)
    for name in FLEET_FILES:        # e.g. the manifest given as study/fleet.csv, --out study
        refuse_inputs(out / name, inputs)
    _check_points(soc_points, temperatures_c, workers)
    if parquet:
        _need("pyarrow")
    _need("distributed")
    with _client(scheduler, workers) as (client, n_workers):
        out.mkdir(parents=True, exist_ok=True)
        progress(f"fleet: {len(rows)} rows on {n_workers} Dask worker"
                 f"{'s' if n_workers != 1 else ''}")
        t_rows = time.perf_counter()
        outcomes = _run_rows(client, rows, out, options, progress)
        rows_seconds = time.perf_counter() - t_rows
    result = FleetResult(rows=rows, outcomes=outcomes, out_dir=out, workers=n_workers,
                         rows_seconds=rows_seconds)
    result.files.append(write_failures(rows, outcomes, out / "failures.csv"))
    progress("fleet: the fleet table")
    result.table, files = write_fleet_table(rows, out, soc_points, temperatures_c,
                                            parquet=parquet, plots=plots)
    result.files += files
    result.seconds = time.perf_counter() - t0
    return result


def write_fleet_table(rows: list[Row], out: Path, soc_points=DEFAULT_SOC,
                      temperatures_c=DEFAULT_TEMPERATURES_C, *, parquet: bool = True,
                      plots: bool = True) -> tuple[list[dict], list[Path]]:
    """fleet.csv, fleet.parquet, ageing.csv and the trend plots from the rows' outputs in ``out``
    (also callable alone, e.g. at other SOC or temperature points)."""
    from .table import table_rows, write_table

    from .ageing import ageing_rows
    from .table import csv_text

    table = table_rows(rows, out, soc_points, temperatures_c)
    files = write_table(table, out, parquet=parquet)
    write_atomic(out / "ageing.csv", csv_text(ageing_rows(table)))
    files.append(out / "ageing.csv")
    if plots and table:
        from .plots import trend_pngs

        over_t = any(d["temperature_rows"] > 1 for d in table)
        files += trend_pngs(table, out, soc_points, temperatures_c, over_t)
    return table, files


def _check_points(soc_points, temperatures_c, workers) -> None:
    import math

    if not soc_points or any(not (math.isfinite(s) and 0.0 <= s <= 1.0) for s in soc_points):
        raise InputError(None, f"--soc must be SOC points in [0, 1], got {list(soc_points)}")
    if not temperatures_c or any(not (math.isfinite(t) and -60.0 <= t <= 100.0)
                                 for t in temperatures_c):
        raise InputError(None, "--temperature-c must be temperatures in -60..100 degC, got "
                               f"{list(temperatures_c)}")
    if workers is not None and not (isinstance(workers, int) and 1 <= workers <= 4096):
        raise InputError(None, f"--workers must be a whole number from 1, got {workers!r}")


def _need(module: str) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise InputError(None, f"ecmgen fleet needs {module}, which is not installed: "
                               f"{INSTALL_HINT}")


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # not on Linux
        return os.cpu_count() or 1


@contextmanager
def _client(scheduler: str | None, workers: int | None):
    """(a dask.distributed Client, its number of workers): a LocalCluster of ``workers``
    (default: one per core) single-threaded worker processes, or the scheduler at
    ``scheduler`` (waiting for ``workers`` workers when given)."""
    from distributed import Client, LocalCluster

    if scheduler is None:
        n = workers or cores()
        # the scheduler's HTTP server starts whatever the dashboard setting (None means
        # its default, :8787, on every interface, and a warning when another cluster holds
        # it): an ephemeral port on this machine only
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                          dashboard_address=LOCAL_HTTP, silence_logs=logging.ERROR) as cluster, \
                Client(cluster) as client:
            yield client, n
        return
    try:
        client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(None, f"--scheduler {scheduler}: no Dask scheduler answers there "
                               f"({' '.join(str(exc).split())})") from None
    try:
        if workers:
            client.wait_for_workers(workers, timeout=CONNECT_TIMEOUT_S * 3)
        yield client, len(client.nthreads())
    finally:
        client.close()


def _run_rows(client, rows: list[Row], out: Path, options: Options, progress) -> list[Outcome]:
    """Submit every row, follow them as they finish; the outcomes in manifest order."""
    from distributed import as_completed

    futures = {client.submit(run_row, r, out, options, pure=False,
                             key=f"ecmgen-fleet-{r.label}-{time.time_ns()}"): r for r in rows}
    bar = ProgressBar(len(rows), progress)
    done: dict[tuple[str, str], Outcome] = {}
    try:
        for fut in as_completed(futures):
            row = futures[fut]
            try:
                outcome = fut.result()
            except Exception as exc:    # noqa: BLE001 - the worker died or was lost
                outcome = Outcome(row.cell, row.checkup, "failed", kind="worker",
                                  error=f"the Dask worker running it was lost "
                                        f"({type(exc).__name__}: {' '.join(str(exc).split())})")
            done[(row.cell, row.checkup)] = outcome
            bar.update(outcome, row)
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        bar.close()
    return [done[(r.cell, r.checkup)] for r in rows]


class ProgressBar:
    """``[#####.....] 9/18 rows: 7 built, 1 unchanged, 1 failed, 0:21, ~0:20 left`` on
    stderr: on a terminal one line rewritten (through ``progress.detail``); in a log a
    line at every tenth of the rows and for each failed row."""

    def __init__(self, total: int, progress):
        self.total, self.progress = total, progress
        self.counts = {"built": 0, "unchanged": 0, "failed": 0}
        self.t0 = time.perf_counter()
        self.tty = bool(getattr(progress, "tty", False))
        self._next_log = 0.1

    def line(self) -> str:
        n = sum(self.counts.values())
        width = 20
        fill = int(round(width * n / max(self.total, 1)))
        spent = time.perf_counter() - self.t0
        left = spent / n * (self.total - n) if n else None
        eta = f", ~{_clock(left)} left" if left is not None and n < self.total else ""
        c = self.counts
        return (f"[{'#' * fill}{'.' * (width - fill)}] {n}/{self.total} rows: {c['built']} "
                f"built, {c['unchanged']} unchanged, {c['failed']} failed, "
                f"{_clock(spent)}{eta}")

    def update(self, outcome: Outcome, row: Row) -> None:
        self.counts[outcome.status] = self.counts.get(outcome.status, 0) + 1
        if outcome.status == "failed":
            self.progress(f"fleet: {row.label} failed: {outcome.error}")
        n = sum(self.counts.values())
        if self.tty:
            getattr(self.progress, "detail", self.progress)(f"fleet {self.line()}")
        elif n >= self._next_log * self.total or n == self.total:
            self.progress(f"fleet {self.line()}")
            while self._next_log * self.total <= n:
                self._next_log += 0.1

    def close(self) -> None:
        getattr(self.progress, "close", lambda: None)()


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def write_failures(rows: list[Row], outcomes: list[Outcome], path: Path) -> Path:
    """failures.csv: ``cell,checkup,config,kind,error`` per failed row (manifest order)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["cell", "checkup", "config", "kind", "error"])
    for r, o in zip(rows, outcomes):
        if o.status == "failed":
            w.writerow([r.cell, r.checkup, r.config_given, o.kind, o.error])
    write_atomic(path, buf.getvalue())
    return path
