"""Cyclers' own files, read by their extension through well-kept readers: Neware
``.nda`` / ``.ndax`` (NewareNDA), BioLogic ``.mpr`` and Arbin ``.res`` (galvani). The
readers are the optional extra ``pip install 'ecmgen[cyclers]'``; without it such a file
is refused with that line.

A reader's table becomes named numeric columns and the column map that reads them (names,
units, current sign, the cycler's charge counters); :mod:`ecmgen.data.measure` then reads
them as it reads a .mat file's fields: units and sign, the counters joined over their
restarts (:mod:`ecmgen.data.counters`), the plausibility checks. A user's column table
for such a file extends :data:`NATIVE_COLUMNS` key by key (e.g. ``temperature = "T2"``).
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import tempfile
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError

INSTALL = "pip install 'ecmgen[cyclers]'"

# Per format: the columns every file of it has, in the reader's names, with their units
# and sign. Neware logs discharge negative (NewareNDA keeps the sign: its CC_DChg steps
# read negative), in mA and mAh, and splits its Ah counter into a charge and a discharge
# counter that both restart at every step. BioLogic's EC-Lab counts the working
# electrode's oxidation current positive, which on a cell wired positive-to-working is
# charge; (Q-Qo) is its cumulative charge. Arbin logs discharge negative, in A, V, s, Ah.
NATIVE_COLUMNS: dict[str, dict[str, Any]] = {
    ".nda": dict(time="Time", current="Current(mA)", voltage="Voltage", current_unit="mA",
                 charge="Charge_Capacity(mAh)", discharge="Discharge_Capacity(mAh)",
                 charge_unit="mAh"),
    ".mpr": dict(time="time/s", current="I/mA", voltage="Ewe/V", current_unit="mA"),
    ".res": dict(time="Test_Time", current="Current", voltage="Voltage",
                 charge="Charge_Capacity", discharge="Discharge_Capacity"),
}
NATIVE_COLUMNS[".ndax"] = NATIVE_COLUMNS[".nda"]
FORMATS = {".nda": ("a Neware", "NewareNDA"), ".ndax": ("a Neware", "NewareNDA"),
           ".mpr": ("a BioLogic", "galvani"), ".res": ("an Arbin", "galvani")}


@dataclass(frozen=True)
class NativeRecord:
    """A native file as named columns (float64, as the reader names them) and the
    column map keywords that read it (:data:`NATIVE_COLUMNS` and the optional columns this
    file has, e.g. its first temperature channel)."""

    fields: dict[str, np.ndarray]
    columns: dict[str, Any]
    what: str                          # "Neware .nda (NewareNDA 2026.6.11)"
    notes: tuple[str, ...] = ()


def is_native(path: str | Path) -> bool:
    """True for a file ecmgen reads through a cycler's reader (by its extension)."""
    return Path(path).suffix.lower() in FORMATS


def native_columns(path: str | Path) -> dict[str, Any] | None:
    """The column map keywords every file of this format has (None: not a native file)."""
    cols = NATIVE_COLUMNS.get(Path(path).suffix.lower())
    return None if cols is None else dict(cols)


def read_native(path: Path) -> NativeRecord:
    """Read a native cycler file; every problem (no reader installed, a version or a
    layout the reader cannot read) is an InputError naming the file."""
    suffix = path.suffix.lower()
    kind, package = FORMATS[suffix]
    reader: Callable[[Path], NativeRecord] = {".nda": _neware, ".ndax": _neware,
                                               ".mpr": _biologic, ".res": _arbin}[suffix]
    try:
        return reader(path)
    except ImportError:
        raise InputError(path, f"{kind} {suffix} file is read by {package}, which is not "
                               f"installed: {INSTALL}") from None


@contextmanager
def _quiet(logger_name: str):
    """A reader's own log lines and its dependencies' deprecation warnings are not the
    user's business: ecmgen says what went wrong in its one line."""
    logger = logging.getLogger(logger_name)
    was = logger.disabled
    logger.disabled = True
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.disabled = was


def _failed(path: Path, package: str, exc: Exception) -> InputError:
    why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return InputError(path, f"{package} cannot read it ({why[:200]})")


def _numeric(table: dict[str, Any]) -> dict[str, np.ndarray]:
    """The numeric columns of a reader's table as float64 vectors (text, categories and
    time stamps left out; a column that is NaN throughout, an unconnected channel, too)."""
    out = {}
    for name, values in table.items():
        arr = np.asarray(values)
        if arr.ndim != 1 or arr.dtype.kind not in "biuf":
            continue
        arr = arr.astype(np.float64)
        if arr.size and np.isnan(arr).all():
            continue
        out[str(name)] = arr
    return out


# --------------------------------------------------------------------------- Neware

def step_time_joined(time_s: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, int]:
    """A clock that restarts at every step made the test's clock: each step's times
    counted on from the previous step's last sample (a cycler logs a step's end, and the
    next step's clock starts there). Returns the times and how many restarts were joined;
    a clock that runs on over the test (newer Neware files) is returned as it is."""
    changes = np.flatnonzero(np.diff(step) != 0) + 1
    back = changes[time_s[changes] < time_s[changes - 1]]
    if back.size == 0:
        return time_s, 0
    out = time_s.copy()
    for k, start in enumerate(changes):
        stop = changes[k + 1] if k + 1 < changes.size else time_s.size
        out[start:stop] = out[start - 1] + time_s[start:stop]
    return out, int(back.size)


def _neware(path: Path) -> NativeRecord:
    import NewareNDA

    version = getattr(NewareNDA, "__version__", "")
    if path.suffix not in (".nda", ".ndax"):
        raise InputError(path, "NewareNDA reads .nda and .ndax files named in lower case: "
                               "rename the file")
    with _quiet("newarenda"):
        try:
            df = NewareNDA.read(str(path))
        except Exception as exc:       # the reader raises several types on what it cannot read
            raise _failed(path, "NewareNDA", exc) from None
    fields = _numeric({name: df[name].to_numpy() for name in df.columns})
    notes = []
    missing = [n for n in ("Time", "Current(mA)", "Voltage") if n not in fields]
    if missing or len(df) == 0:
        raise InputError(path, f"NewareNDA gives no {missing[0] if missing else 'records'} "
                               f"for it: no time, current and voltage to read")
    if "Step" in fields:
        fields["Time"], joined = step_time_joined(fields["Time"], fields["Step"])
        if joined:
            notes.append(f"its Time restarts at every step: joined into the test's clock "
                         f"over {joined} steps")
    _float32_note(np.asarray(df["Time"]), fields["Time"], notes)
    if "Timestamp" in df.columns:
        _pause_note(df["Timestamp"], fields["Time"], notes)
    columns = dict(NATIVE_COLUMNS[".nda"])
    temps = sorted((n for n in fields if n[:1] == "T" and n[1:].isdigit()),
                   key=lambda n: int(n[1:]))
    if temps:
        columns["temperature"] = temps[0]
        others = f" (also logged: {', '.join(temps[1:])}; map temperature to take one)" \
            if len(temps) > 1 else ""
        notes.append(f"cell temperature from the auxiliary channel {temps[0]}{others}")
    what = f"Neware {path.suffix} (NewareNDA {version})".replace(" )", ")")
    return NativeRecord(fields, columns, what, tuple(notes))


def _float32_note(stored: np.ndarray, time_s: np.ndarray, notes: list[str]) -> None:
    """NewareNDA stores times as float32: far into a long test that rounds the stamps.
    Said where the rounding at the record's end reaches a tenth of its usual interval."""
    if stored.dtype != np.float32 or time_s.size < 3:
        return
    resolution = float(np.spacing(np.float32(np.max(np.abs(time_s)))))
    usual = float(np.median(np.diff(time_s)))
    if usual > 0 and resolution > 0.1 * usual:
        notes.append(f"its reader stores time as float32: {resolution:.3g} s resolution at "
                     f"the record's end, against a usual interval of {usual:.3g} s")


def _pause_note(stamps, time_s: np.ndarray, notes: list[str]) -> None:
    """The test clock stands still while a test is paused; the wall-clock stamps do not.
    Said where they part by more than PAUSE_S (time stays the test clock: the cycler's
    counters and step times run on it, and nothing was logged in a pause)."""
    try:
        wall = (stamps - stamps.iloc[0]).dt.total_seconds().to_numpy(dtype=np.float64)
    except (AttributeError, TypeError, ValueError):   # not time stamps: nothing to say
        return
    extra = np.diff(wall) - np.diff(time_s)
    paused = extra[extra > PAUSE_S]
    if paused.size:
        notes.append(f"the test was paused {paused.size} time{'s' if paused.size > 1 else ''} "
                     f"(longest {paused.max() / 3600:.3g} h by its time stamps): time is the "
                     f"test clock, which stands still in a pause")


PAUSE_S = 60.0      # wall-clock time beyond the test clock's that is a pause, not jitter


# --------------------------------------------------------------------------- BioLogic

def _biologic(path: Path) -> NativeRecord:
    from galvani import BioLogic

    with _quiet("galvani"):
        try:
            mpr = BioLogic.MPRfile(str(path))
        except Exception as exc:
            raise _failed(path, "galvani", exc) from None
    data = mpr.data
    fields = _numeric({name: data[name] for name in data.dtype.names or ()})
    if "I/mA" not in fields and "<I>/mA" in fields:   # the averaged current, same units
        fields["I/mA"] = fields["<I>/mA"]
    columns = dict(NATIVE_COLUMNS[".mpr"])
    if "(Q-Qo)/mA.h" in fields:
        columns.update(charge="(Q-Qo)/mA.h", charge_unit="mAh")
    if "Temperature/°C" in fields:
        columns["temperature"] = "Temperature/°C"
    notes = ("the cell voltage read as Ewe/V (a two-electrode cell; map voltage to "
             "Ewe-Ece/V for a three-electrode one)",)
    return NativeRecord(fields, columns, "BioLogic .mpr (galvani)", notes)


# --------------------------------------------------------------------------- Arbin

def _arbin(path: Path) -> NativeRecord:
    from galvani import res2sqlite

    if shutil.which("mdb-export") is None:
        raise InputError(path, "an Arbin .res file is an Access database, which galvani "
                               "reads with mdbtools' mdb-export: install mdbtools (e.g. "
                               "apt-get install mdbtools) or export the file as CSV")
    with tempfile.TemporaryDirectory(prefix="ecmgen-res-") as tmp, _quiet("galvani"):
        db = Path(tmp) / "res.sqlite"
        try:
            res2sqlite.convert_arbin_to_sqlite(str(path), str(db))
        except Exception as exc:
            raise _failed(path, "galvani", exc) from None
        fields = arbin_table(db)
    if not fields:
        raise InputError(path, "galvani finds no rows in its Channel_Normal_Table")
    return NativeRecord(fields, dict(NATIVE_COLUMNS[".res"]), "Arbin .res (galvani)",
                        ("auxiliary channels (temperature) are not read from a .res "
                         "file",))


def arbin_table(db: Path) -> dict[str, np.ndarray]:
    """The numeric columns of an Arbin database's Channel_Normal_Table (as galvani
    converts it), in the order of its data points."""
    con = sqlite3.connect(db)
    try:
        cur = con.execute('SELECT * FROM "Channel_Normal_Table" ORDER BY "Data_Point"')
        names = [d[0] for d in cur.description]
        rows = cur.fetchall()
    finally:
        con.close()
    if not rows:
        return {}
    return _numeric({name: [row[k] for row in rows] for k, name in enumerate(names)})
