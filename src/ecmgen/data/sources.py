"""Measurement files of a build config read as the config says: its column maps, its
temperatures (a number or a time-stamped log per file), its windows, and the OCV of its
file sources (tables or low-rate tests, consecutive low-rate parts joined)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import COLUMN_ROLE_FALLBACK, WINDOW_ROLES, BuildConfig
from ..errors import InputError
from ..files import short_names
from . import ocv as ocv_mod
from .measure import ColumnMap, TimeSeries, check_columns, read_timeseries

Progress = Callable[[str], None]


def read_series(cfg: BuildConfig, path: Path, role: str = "") -> TimeSeries:
    """Read a measurement file of the config. ``[data.columns]`` maps CSV columns from
    another cycler, for every CSV; ``[data.columns.<role>]`` extends it for one file role
    (``extra_cycles`` and ``judge`` fall back to ``cycle``'s); .mat files carry their own
    names. A validation file is cut to ``data.cycle_window_s`` when the config gives one."""
    series = read_timeseries(path, columns_for(cfg, path, role), capacity_ah=cfg.capacity_ah)
    temp = cfg.temperature_for(path) if series.temperature_c is None else None
    if isinstance(temp, Path):
        from .templog import with_temperature_log

        series = with_temperature_log(series, temp)
    elif temp is not None:
        series = replace(series, temperature_c=np.full(len(series), temp),
                         notes=series.notes + (f"no temperature column: the cell taken to "
                                               f"be at {temp:g} degC (the config's "
                                               f"temperature_c)",))
    window = cfg.window_for(path) if role in WINDOW_ROLES else None
    return series if window is None else series.window(*window)


def columns_for(cfg: BuildConfig, path: Path, role: str) -> ColumnMap | None:
    """The column map of one file of the config in ``role`` (None: known by its names)."""
    roles = (role, COLUMN_ROLE_FALLBACK[role]) if role in COLUMN_ROLE_FALLBACK else (role,)
    return ColumnMap.for_file(cfg.columns, roles, cfg.path, path,
                              cfg.file_columns.get(Path(path).resolve()))


def measurement_files(cfg: BuildConfig) -> list[tuple[Path, str]]:
    """Every measurement file the config names, with its role, once each in the order
    a build reads them (soc,ocv_v tables and DC-IR tables left out)."""
    files = [(p, "ocv") for p in cfg.ocv_sources if p != "pulses"]
    files += [(cfg.pulses, "pulses")] if cfg.pulses is not None else []
    for test in cfg.pulse_tests:
        files += [(p, "pulses") for p in (test.file, test.steps) if p is not None]
        files += [(test.ocv, "ocv")] if test.ocv is not None else []
    files += [(cfg.cycle, "cycle")] if cfg.cycle is not None else []
    files += [(p, "extra_cycles") for p in cfg.extra_cycles]
    diagnose = cfg.raw.get("diagnose") if isinstance(cfg.raw.get("diagnose"), dict) else {}
    for key, role in (("cycle", "cycle"), ("judge", "judge")):
        if isinstance(diagnose.get(key), str):
            files.append((cfg.path.resolve().parent / diagnose[key], role))
    seen, out = set(), []
    for p, role in files:
        p = Path(p).resolve()
        if (p, role) not in seen and p.is_file() and not ocv_mod.looks_like_ocv_table(p):
            seen.add((p, role))
            out.append((p, role))
    return out


def check_column_maps(cfg: BuildConfig) -> None:
    """Every measurement file's column map checked on the file's first lines, before any
    fitting: a wrong map is the same one line reading would give, seconds earlier."""
    for path, role in measurement_files(cfg):
        check_columns(path, columns_for(cfg, path, role), capacity_ah=cfg.capacity_ah)


def check_temperature_logs(cfg: BuildConfig) -> None:
    """Read every time-stamped temperature log the config names now, before any fit: a
    log without a time column is bad input at once, not after the fit of the pulses."""
    from .templog import read_temperature_log

    logs = cfg.temperature_c.values() if isinstance(cfg.temperature_c, dict) else ()
    for log in sorted({v for v in logs if isinstance(v, Path)}):
        read_temperature_log(log)


def ocv_file_curve(cfg: BuildConfig, path: Path, progress: Progress,
                    low: TimeSeries | None = None) -> ocv_mod.OcvCurve:
    """The OCV curve of one file source: a soc,ocv_v table or a low-rate test (``low``:
    that test, already read or joined from its parts)."""
    if low is None and ocv_mod.looks_like_ocv_table(path):
        return ocv_mod.curve_from_table(ocv_mod.read_ocv_table(path), path.name)
    if low is None:
        progress(f"reading low-rate OCV test {path.name}")
        low = read_series(cfg, path, "ocv")
    name = Path(low.source).name if low.source else path.name
    return ocv_mod.curve_from_low_rate(low, cfg.capacity_ah, name, soc0=cfg.ocv_soc0,
                                       branch=cfg.ocv_branch, cycle=cfg.ocv_cycle)


def ocv_file_curves(cfg: BuildConfig, sources, progress: Progress
                     ) -> tuple[list, dict, list[str]]:
    """The curves of data.ocv's file sources, in order: the sources left (a run of
    consecutive low-rate files, none a discharge + charge cycle alone, becomes its first
    file: their records joined end to end into one test), their curves, and notes."""
    from .lowrate import join_records, split_low_rate

    lows: dict = {}
    for src in sources:
        if src != "pulses" and not ocv_mod.looks_like_ocv_table(src):
            progress(f"reading low-rate OCV test {src.name}")
            low = read_series(cfg, src, "ocv")
            lows[src] = (low, not split_low_rate(low, cfg.capacity_ah).cycles)
    groups: list[tuple[list, bool]] = []      # ([sources], joinable), in order
    for src in sources:
        joinable = src in lows and lows[src][1]
        if joinable and groups and groups[-1][1]:
            groups[-1][0].append(src)
        else:
            groups.append(([src], joinable))
    kept, curves, notes = [], {}, []
    for group, _ in groups:
        first = group[0]
        kept.append(first)
        if len(group) > 1:
            joined, note = join_records([lows[p][0] for p in group])
            notes.append(note)
            curves[first] = ocv_file_curve(cfg, first, progress, joined)
        elif first in lows:
            curves[first] = ocv_file_curve(cfg, first, progress, lows[first][0])
        elif first != "pulses":
            curves[first] = ocv_file_curve(cfg, first, progress)
    return kept, curves, notes


# a pulse test's temperature_c and its own temperature column may differ by self-heating
# (the shared Panasonic tests: medians in the pulses within 0.9 K of the chamber's 25, 0,
# -10, -20 degC); more than this is another test's label
PULSE_LABEL_TOL_K = 5.0


def check_pulse_label(cfg: BuildConfig, test, measured: float | None) -> None:
    """InputError when a pulse test's temperature_c contradicts its own temperature column
    (``measured``: the median in its pulses; None: the file has none)."""
    temp = float(test.temperature_c)
    if measured is not None and abs(measured - temp) > PULSE_LABEL_TOL_K:
        raise InputError(cfg.path, f"the pulse test {test.file.name} is given temperature_c = "
                                   f"{temp:g} degC, but its own cell temperature column reads "
                                   f"{measured:.1f} degC in its pulses (median): labels "
                                   "swapped? (leave temperature_c out to take the file's)")


def pulse_test_records(cfg: BuildConfig, test, records) -> tuple:
    """A pulse test's input records with its files by the names the notes use (tests of
    one cell share file names): each record renamed only if it is that file's, so the
    other parts of a split data.ocv keep their own names (before: all named as the first)."""
    names = pulse_file_names(cfg)
    files = {"ocv": test.ocv, "pulses": test.file, "steps": test.steps}
    return tuple(replace(r, name=names.get(files[r.role], r.name))
                 if files.get(r.role) is not None and r.name == files[r.role].name else r
                 for r in records)


def pulse_file_names(cfg: BuildConfig) -> dict[Path, str]:
    """Short, distinct names for the files of the pulse tests (see short_names)."""
    files = list(dict.fromkeys(p for t in cfg.pulse_tests for p in (t.file, t.steps, t.ocv)
                               if p is not None))
    return dict(zip(files, short_names(files)))
