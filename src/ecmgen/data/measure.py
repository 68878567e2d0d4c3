"""Measurement files -> :class:`TimeSeries`.

Sign convention everywhere inside ecmgen: current is POSITIVE ON CHARGE, in amperes;
time in seconds, voltage in volts, temperature in degC, cumulative charge in Ah
(counts up on charge, i.e. the integral of the current).
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import InputError, reading
from ..files import write_atomic
from .counters import cumulative_charge, gap_note, integrate_current
from .csvtext import CsvRows, blocks, csv_encoding
from .native import read_native, is_native
from .columns import (  # noqa: F401 (re-exported)
    CANONICAL_HEADER, CHARGE_UNITS_AH, CSV_LAYOUTS, CURRENT_SIGNS, CURRENT_UNITS_A,
    MAT_LAYOUT, TIME_UNITS_S, VOLTAGE_UNITS_V, ColumnMap, _is_mat)
from .timing import LAG_MARGIN, VoltageLag, voltage_lag  # noqa: F401 (re-exported)
from .plausible import (MAX_C_RATE, MAX_CURRENT_A, TEMPERATURE_RANGE_C, VOLTAGE_RANGE_V,
                        check_current, check_temperature, check_voltage, implausible_ends)


@dataclass(frozen=True)
class TimeSeries:
    """One measured record, all arrays 1-D float64 of equal length.

    time_s        seconds, non-decreasing (repeated stamps at switching edges are allowed)
    current_a     amperes, positive = charge
    voltage_v     volts at the cell terminals
    temperature_c degC or None
    charge_ah     cumulative charge in Ah (positive = charged) or None; where a cycler
                  logs it, it is trusted over integrating current (files may omit segments);
                  a counter that restarts per step or cycle, or one split into charge and
                  discharge, is joined into this one on reading (ecmgen.data.counters)
    source        file the record came from (for error messages and provenance)
    """

    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    temperature_c: np.ndarray | None = None
    charge_ah: np.ndarray | None = None
    source: str = ""
    notes: tuple[str, ...] = field(default=())

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def slice(self, start: int, stop: int) -> "TimeSeries":
        """Rows [start, stop) as a new TimeSeries."""
        def cut(a):
            return None if a is None else a[start:stop]
        return TimeSeries(self.time_s[start:stop], self.current_a[start:stop],
                          self.voltage_v[start:stop], cut(self.temperature_c),
                          cut(self.charge_ah), self.source, self.notes)

    def window(self, t0_s: float, t1_s: float) -> "TimeSeries":
        """The rows with ``t0_s <= time_s <= t1_s`` (the record's own time axis, s), e.g.
        one cycle of a file that holds several. A reversed window, or one that leaves fewer
        than 2 samples, is an InputError naming the file."""
        where = self.source or None
        span = f"the record runs from {self.time_s[0]:g} to {self.time_s[-1]:g} s"
        if not t0_s < t1_s:
            raise InputError(where, f"time window [{t0_s:g}, {t1_s:g}] s: the start must "
                                    f"come before the end")
        if t1_s < self.time_s[0] or t0_s > self.time_s[-1]:
            raise InputError(where, f"time window [{t0_s:g}, {t1_s:g}] s lies outside the "
                                    f"record ({span})")
        ix = np.flatnonzero((self.time_s >= t0_s) & (self.time_s <= t1_s))
        if ix.size < 2:
            raise InputError(where, f"time window [{t0_s:g}, {t1_s:g}] s holds {ix.size} "
                                    f"sample{'s' if ix.size != 1 else ''} ({span})")
        cut = self.slice(int(ix[0]), int(ix[-1]) + 1)
        note = f"cut to the time window {t0_s:g} .. {t1_s:g} s ({ix.size} samples)"
        return TimeSeries(cut.time_s, cut.current_a, cut.voltage_v, cut.temperature_c,
                          cut.charge_ah, cut.source, cut.notes + (note,))

    def coulomb_ah(self) -> np.ndarray:
        """Cumulative charge in Ah from 0 at the first sample: the logged Ah column where
        the file has one (re-zeroed), else the integral of the current (the trapezoid,
        held over logging gaps: ecmgen.data.counters)."""
        if self.charge_ah is not None:
            return self.charge_ah - self.charge_ah[0]
        return integrate_current(self.time_s, self.current_a)


# --------------------------------------------------------------------------- reading

@dataclass
class _Raw:
    """Columns as found in the file, before conversion and checks."""

    kind: str                          # "column" (CSV) or "field" (.mat)
    names: dict[str, str]              # role -> how messages name it: "column 'I(A)'", "column 9"
    values: dict[str, np.ndarray]      # role -> raw float64 values
    where: Callable[[int], str]        # 0-based row -> "row 5 (line 6)"
    notes: list[str]


def read_timeseries(path: str | Path, columns: ColumnMap | None = None, *,
                    capacity_ah: float | None = None) -> TimeSeries:
    """Read a measurement file (CSV, or MATLAB v5 ``.mat``) into a checked TimeSeries.

    ``columns`` None: CSV must carry the canonical header
    ``time_s,current_a,voltage_v[,temperature_c][,charge_ah]`` or a recognised cycler
    layout (Arbin / CALCE); a .mat must hold a Panasonic-style ``meas`` struct (or the
    same fields at top level). ``capacity_ah`` (cell capacity) tightens the current check
    to 50 C. Every problem is an InputError ``<file>: <column>, <row>: <problem>``.
    """
    with reading(path):
        return _read_timeseries(path, columns, capacity_ah=capacity_ah)


def _read_timeseries(path: str | Path, columns: ColumnMap | None = None, *,
                     capacity_ah: float | None = None) -> TimeSeries:
    path = Path(path)
    if capacity_ah is not None and not (np.isfinite(capacity_ah) and capacity_ah > 0):
        raise ValueError(f"capacity_ah must be a positive number of Ah, got {capacity_ah!r}")
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a measurement file")
    if is_native(path):
        raw, colmap = _read_native(path, columns)
    elif _is_mat(path):
        raw, colmap = _read_mat(path, columns)
    else:
        raw, colmap = _read_csv(path, columns)
    return _finish(path, raw, colmap, capacity_ah)


def _choose_layout(path: Path, found: list[str], kind: str, layouts) -> tuple[ColumnMap, str]:
    for layout in layouts:
        colmap = layout.resolve(found)
        if colmap is not None:
            return colmap, layout.describe()
    listing = ", ".join(repr(n) for n in found) or "none"
    best = max(layouts, key=lambda lay: lay.present(found))
    if best.present(found) >= 2:
        # Nearly a known layout: name what is missing rather than refuse the whole file.
        missing = next(n for n in (best.columns.time, best.columns.current,
                                   best.columns.voltage) if n not in found)
        raise InputError(path, f"missing {kind} {missing!r} (the others of the "
                               f"{best.describe()} are there); {kind}s found: {listing}; "
                               f"otherwise map the {kind}s in [data.columns]")
    if kind == "field":
        expected = "a 'meas' struct with fields Time, Current, Voltage (Panasonic/Digatron)"
    else:
        expected = ("the header time_s,current_a,voltage_v[,temperature_c][,charge_ah] "
                    "or an Arbin/CALCE export")
    raise InputError(path, f"{kind}s not recognised (found: {listing}); expected {expected}, "
                           f"otherwise a [data.columns] mapping (time, current, voltage, "
                           f"units, current_sign) is needed")


def _label(kind: str, name: str | int) -> str:
    """How messages name a column: ``column 'Current(A)'``, or ``column 9`` by position."""
    return f"{kind} {name}" if isinstance(name, int) else f"{kind} {name!r}"


def _check_named(path: Path, colmap: ColumnMap, found: list[str], kind: str) -> None:
    listing = ", ".join(repr(n) for n in found) or "none"
    for role, name in colmap.names().items():
        if isinstance(name, int):
            if kind == "field":
                raise InputError(path, f"{role} = {name}: column positions apply to CSV "
                                       f"files; a .mat or a cycler's own file names its "
                                       f"fields")
            if name > len(found):
                raise InputError(path, f"{role} = {name} in [data.columns], but the file "
                                       f"has {len(found)} columns")
        elif name not in found:
            raise InputError(path, f"missing {kind} {name!r} (the {role} {kind} of "
                                   f"[data.columns]); {kind}s found: {listing}")


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _numbers_only(row: list[str]) -> bool:
    """A line of numbers (data), not of column names: every non-empty cell is a number."""
    cells = [c.strip() for c in row if c.strip()]
    return bool(cells) and all(_is_number(c) for c in cells)


def _mapped_cells(columns: ColumnMap, row: list[str]) -> list[str]:
    """The cells of ``row`` at the map's column positions (those the row reaches)."""
    return [row[k - 1] for k in columns.names().values()
            if isinstance(k, int) and k <= len(row)]


def _headerless(path: Path, row: list[str], line: int, text_columns: bool = False
                ) -> InputError:
    shown = ", ".join(c.strip() for c in row[:4]) + (", ..." if len(row) > 4 else "")
    what = "its mapped columns hold numbers" if text_columns else "holds numbers"
    return InputError(path, f"no header line: line {line} {what} ({shown}), not "
                            f"column names; for a file without a header set header = false "
                            f"in [data.columns] and give the columns by position, 1 = first "
                            f"(e.g. time = 1, current = 2, voltage = 3)")


HEAD_ROWS = 100     # the rows a column map is checked on before a file is read whole


def check_columns(path: str | Path, columns: ColumnMap | None, *,
                  capacity_ah: float | None = None) -> None:
    """The column map of a measurement file checked before a long run reads it whole
    (InputError as reading would raise it): a CSV on its header and first HEAD_ROWS rows
    (the names and positions, the header line or none, numbers in the mapped cells;
    voltage, current and temperature in a cell's range, else the file is read whole to
    tell a column or a unit mapped wrongly from a logger-off run the reading drops); a
    .mat or cycler file on its names, where a map is given for it."""
    with reading(path):
        path = Path(path)
        if is_native(path) or _is_mat(path):
            if columns is not None:
                (_read_native if is_native(path) else _read_mat)(path, columns)
            return
        raw, colmap = _read_csv(path, columns, max_rows=HEAD_ROWS)
        values = _in_units(raw.values, colmap, [])
        lo, hi = VOLTAGE_RANGE_V
        temps = values.get("temperature", np.zeros(1))
        peak = MAX_C_RATE * capacity_ah if capacity_ah is not None else MAX_CURRENT_A
        if np.any((values["voltage"] < lo) | (values["voltage"] > hi)) or \
                np.any(np.abs(values["current"]) > peak) or \
                np.any((temps < TEMPERATURE_RANGE_C[0]) | (temps > TEMPERATURE_RANGE_C[1])):
            _finish(path, *_read_csv(path, columns), capacity_ah)


def _read_csv(path: Path, columns: ColumnMap | None, max_rows: int | None = None
              ) -> tuple[_Raw, ColumnMap]:
    encoding = csv_encoding(path)
    try:
        return _read_csv_as(path, columns, encoding, max_rows)
    except UnicodeDecodeError:
        if encoding != "utf-8-sig":
            raise InputError(path, "starts as UTF-16 text (its BOM) but is not") from None
        return _read_csv_as(path, columns, "latin-1", max_rows)   # a Windows code page ("°C")


def _csv_header(path: Path, columns: ColumnMap | None, rows):
    """The CSV's header (names, or the positions 1..n of a headerless file), the words
    a width error names it by, and the data rows read to find it (to be read again)."""
    has_header = columns is None or columns.header
    pending: list[tuple[int, list[str]]] = []
    if has_header:
        line, row = next(rows, (0, None))
        if row is None:
            raise InputError(path, "empty file (no header line)")
        if _numbers_only(row):
            raise _headerless(path, row, line)
        if columns is not None and columns.by_position() and \
                _numbers_only(_mapped_cells(columns, row)):
            # read as a header, this line of data would be lost without a word
            raise _headerless(path, _mapped_cells(columns, row), line, text_columns=True)
        header = [name.strip() for name in row]
        against = "the header has"
    else:
        first = next(rows, None)
        if first is None:
            raise InputError(path, "empty file (no data lines)")
        line, row = first
        # a cycler's export holds text in columns of its own (Bitrode's "No", a mode
        # "CHRG"): only the mapped columns must hold numbers
        if not _numbers_only(_mapped_cells(columns, row)):
            text = [(role, k) for role, k in columns.names().items()
                    if k <= len(row) and row[k - 1].strip() and not _is_number(row[k - 1])]
            if 0 < len(text) < len(columns.names()):    # numbers elsewhere: a text column
                role, k = text[0]
                raise InputError(path, f"{role} = {k}: line {line} holds "
                                       f"{row[k - 1].strip()[:40]!r} in column {k}, not a "
                                       f"number (a text column?)")
            raise InputError(path, f"header = false in [data.columns], but line {line} "
                                   f"holds names ({', '.join(c.strip() for c in row[:4])}"
                                   f"{', ...' if len(row) > 4 else ''}): a header line?")
        header = [str(k) for k in range(1, len(row) + 1)]  # the positions
        against = f"line {line} has"
        pending = [first]
    return header, against, pending


def _read_csv_as(path: Path, columns: ColumnMap | None, encoding: str,
                 max_rows: int | None = None) -> tuple[_Raw, ColumnMap]:
    """The CSV's mapped columns as float64, converted a block of rows at a time (the
    text is never in memory whole: ecmgen.data.csvtext); its first ``max_rows`` only
    where given."""
    source = CsvRows(path, encoding)
    rows = iter(source)
    header, against, pending = _csv_header(path, columns, rows)

    notes = []
    if columns is None:
        colmap, layout = _choose_layout(path, header, "column", CSV_LAYOUTS)
        sign = "discharge" if colmap.current_sign == "discharge_positive" else "charge"
        notes.append(f"columns recognised by their names as {layout}; current taken as "
                     f"positive on {sign}")
    else:
        colmap = columns
        _check_named(path, colmap, header, "column")
    for role, name in colmap.names().items():
        if isinstance(name, str) and header.count(name) > 1:
            raise InputError(path, f"column {name!r} appears {header.count(name)} times "
                                   f"in the header")

    labels = {role: _label("column", name) for role, name in colmap.names().items()}
    position = {role: name - 1 if isinstance(name, int) else header.index(name)
                for role, name in colmap.names().items()}
    parts: dict[str, list[np.ndarray]] = {role: [] for role in position}
    line_parts: list[np.ndarray] = []
    done = 0
    data_rows = itertools.islice(itertools.chain(pending, rows), max_rows)
    for block in blocks(data_rows):
        lines = np.fromiter((ln for ln, _ in block), dtype=np.int64, count=len(block))
        cells_of = [r for _, r in block]
        _check_width(path, cells_of, lines, len(header), against, source.delimiter)

        def where(i: int, done=done, lines=lines) -> str:
            return f"row {done + i + 1} (line {lines[i]})"

        for role, j in position.items():
            parts[role].append(_column(path, labels[role], [r[j] for r in cells_of], where))
        line_parts.append(lines)
        done += len(block)
    values = {role: np.concatenate(p) if p else np.empty(0) for role, p in parts.items()}
    all_lines = np.concatenate(line_parts) if line_parts else np.empty(0, np.int64)

    def where(i: int) -> str:
        return f"row {i + 1} (line {all_lines[i]})"

    return _Raw("column", labels, values, where, notes), colmap


def _check_width(path: Path, rows: list[list[str]], lines, width: int, against: str,
                 delimiter: str) -> None:
    i = next((i for i, r in enumerate(rows) if len(r) != width), None)
    if i is not None:
        raise InputError(path, f"line {lines[i]} has {len(rows[i])} fields but {against} "
                               f"{width} (a truncated row or a stray {delimiter!r}?)")


def _column(path: Path, label: str, cells: list[str], where) -> np.ndarray:
    """One column of a block of rows as float64; a cell that is not a number is an
    InputError naming its row and line."""
    try:
        values = np.array(cells, dtype=np.float64)
    except ValueError:
        raise _non_numeric(path, label, cells, where) from None
    # Python's float() reads "1_0" as 10: a digit separator no cycler writes
    if "_" in "".join(cells):
        k = next(k for k, c in enumerate(cells) if "_" in c)
        raise InputError(path, f"{label}, {where(k)}: {cells[k].strip()!r} is not a number")
    return values


_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d+,\d+\s*$")


def _non_numeric(path: Path, label: str, cells: list[str], where) -> InputError:
    for i, cell in enumerate(cells):
        try:
            np.float64(cell)
            continue
        except ValueError:
            pass
        if not cell.strip():
            return InputError(path, f"{label}, {where(i)}: empty cell")
        hint = " (decimal comma? use '.')" if _DECIMAL_COMMA.match(cell) else ""
        return InputError(path, f"{label}, {where(i)}: {cell.strip()[:40]!r} "
                                f"is not a number{hint}")
    return InputError(path, f"{label}: holds values that are not numbers")


def _one_struct(value):
    """A 1x1 struct array -> the struct itself (loadmat keeps everything 2-D)."""
    if isinstance(value, np.ndarray) and value.dtype == object and value.size == 1 \
            and hasattr(value.flat[0], "_fieldnames"):
        return value.flat[0]
    return value


def _read_mat(path: Path, columns: ColumnMap | None) -> tuple[_Raw, ColumnMap]:
    import scipy.io

    try:
        # The 100k-row TimeStamp text is not needed: leaving chars unjoined and squeezing
        # only what is used below saves about half the load time.
        data = scipy.io.loadmat(path, squeeze_me=False, struct_as_record=False,
                                chars_as_strings=False)
    except NotImplementedError:
        raise InputError(path, "MATLAB v7.3 (HDF5) .mat files are not supported; "
                               "save with -v7") from None
    except Exception as exc:  # scipy raises several types for corrupt files
        raise InputError(path, f"not a readable MATLAB .mat file ({exc})") from None

    variables = {k: _one_struct(v) for k, v in data.items() if not k.startswith("__")}
    wanted = (columns or MAT_LAYOUT.columns).time
    container = None
    if "meas" in variables:
        container = variables["meas"]
    elif wanted not in variables:
        structs = [v for v in variables.values() if hasattr(v, "_fieldnames")]
        if len(structs) == 1:
            container = structs[0]
    if container is not None:
        if isinstance(container, np.ndarray) and container.dtype == object:
            raise InputError(path, f"'meas' is an array of {container.size} structs; "
                                   f"expected one struct")
        if not hasattr(container, "_fieldnames"):
            raise InputError(path, "'meas' is not a struct")
        found_fields = {n: _one_struct(getattr(container, n)) for n in container._fieldnames}
    else:
        found_fields = variables
    found = list(found_fields)

    notes = []
    if columns is None:
        colmap, layout = _choose_layout(path, found, "field", (MAT_LAYOUT,))
        notes.append(f"fields read as the {layout}")
    else:
        colmap = columns
        _check_named(path, colmap, found, "field")

    values = {}
    for role, name in colmap.names().items():
        arr = np.asarray(found_fields[name])
        if arr.ndim > 1 and sum(d > 1 for d in arr.shape) <= 1:
            arr = arr.reshape(-1)  # MATLAB stores vectors as n-by-1 or 1-by-n
        if arr.dtype.kind not in "biuf":
            held = "text" if arr.dtype.kind in "US" else "cells or structs"
            raise InputError(path, f"field {name!r} holds {held}, not numbers")
        if arr.ndim > 1:
            raise InputError(path, f"field {name!r} has shape {arr.shape}; expected a vector")
        values[role] = np.atleast_1d(arr).astype(np.float64)

    lengths = {role: v.size for role, v in values.items()}
    if len(set(lengths.values())) > 1:
        n_time = lengths["time"]
        role = next(r for r, n in lengths.items() if n != n_time)
        raise InputError(path, f"field {colmap.names()[role]!r} has {lengths[role]} rows "
                               f"but {colmap.time!r} has {n_time}")

    def where(i: int) -> str:
        return f"row {i + 1}"

    labels = {role: _label("field", name) for role, name in colmap.names().items()}
    return _Raw("field", labels, values, where, notes), colmap


def _read_native(path: Path, columns: ColumnMap | None) -> tuple[_Raw, ColumnMap]:
    """A cycler's own file through its reader (ecmgen.data.native): its named columns,
    read by the reader's column map, or by the user's with the optional columns it leaves
    unset (temperature, the charge counters) as the reader found them."""
    record = read_native(path)
    colmap = ColumnMap(**record.columns)
    if columns is not None:
        found = {k: v for k, v in record.columns.items()
                 if k in ("temperature",) and columns.temperature is None or
                 k in ("charge", "discharge", "charge_unit") and columns.charge is None}
        colmap = replace(columns, **found)
    _check_named(path, colmap, list(record.fields), "field")
    values = {role: record.fields[name] for role, name in colmap.names().items()}
    labels = {role: _label("field", name) for role, name in colmap.names().items()}
    notes = [f"read as {record.what}", *record.notes]
    return _Raw("field", labels, values, lambda i: f"row {i + 1}", notes), colmap


# --------------------------------------------------------------------------- checks

def _finish(path: Path, raw: _Raw, colmap: ColumnMap, capacity_ah: float | None) -> TimeSeries:
    values = dict(raw.values)
    notes = list(raw.notes)
    n = values["time"].size
    if n < 2:
        raise InputError(path, f"only {n} data row{'s' if n != 1 else ''}; "
                               f"a measurement needs at least 2")

    def loc(role: str, i: int) -> str:
        return f"{raw.names[role]}, {raw.where(i)}"

    # Units and sign first, so every check below works in A, V, s, Ah.
    values = _in_units(values, colmap, notes)

    first, stop = implausible_ends(values["voltage"])
    if (first, stop) != (0, n):
        for k in (*range(first), *range(stop, n)):
            notes.append(f"{loc('voltage', k)} dropped: voltage {raw.values['voltage'][k]:.6g} V "
                         f"at the record's {'start' if k < first else 'end'} is implausible "
                         f"for a cell (a logger switched off?)")
        values = {role: arr[first:stop] for role, arr in values.items()}
        n = stop - first

        def loc(role: str, i: int, first=first) -> str:
            return f"{raw.names[role]}, {raw.where(i + first)}"

    for role, arr in values.items():
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            logged = raw.values[role][i + first]  # as in the file, before sign/unit conversion
            what = "NaN" if np.isnan(logged) else ("+inf" if logged > 0 else "-inf")
            raise InputError(path, f"{loc(role, i)}: {what} (every value must be a finite "
                                   f"number)")

    time = values["time"]
    back = np.diff(time) < 0  # equal stamps at switching edges are real; only decreases are bad
    if back.any():
        i = int(np.argmax(back)) + 1
        hint = ""
        if str(colmap.time).startswith("Step_Time"):
            hint = " (Step_Time restarts at every step: use Test_Time or map [data.columns])"
        raise InputError(path, f"{loc('time', i)}: time goes backwards, {time[i]:.6g} s "
                               f"after {time[i - 1]:.6g} s{hint}")

    if time[-1] <= time[0]:
        raise InputError(path, f"time does not advance: all {time.size} rows at "
                               f"{time[0]:.6g} s")
    check_voltage(path, values["voltage"], colmap, loc)
    check_current(path, values["current"], colmap, capacity_ah, loc)
    if "temperature" in values:
        check_temperature(path, values["temperature"], loc)
    charge = _charge_count(path, values, colmap, raw.names, notes)
    gaps = gap_note(time, values["current"], charge is not None)
    if gaps:
        notes.append(gaps)

    return TimeSeries(time_s=time, current_a=values["current"], voltage_v=values["voltage"],
                      temperature_c=values.get("temperature"), charge_ah=charge,
                      source=str(path), notes=tuple(notes))


def _in_units(values: dict, colmap: ColumnMap, notes: list[str]) -> dict:
    """The columns in s, A, V, Ah, current positive on charge (said in ``notes``)."""
    scale = {"time": TIME_UNITS_S[colmap.time_unit],
             "current": CURRENT_UNITS_A[colmap.current_unit],
             "voltage": VOLTAGE_UNITS_V[colmap.voltage_unit],
             "charge": CHARGE_UNITS_AH[colmap.charge_unit],
             "discharge": CHARGE_UNITS_AH[colmap.charge_unit]}
    values = {role: arr * scale[role] if scale.get(role, 1.0) != 1.0 else arr
              for role, arr in values.items()}
    if colmap.current_sign == "discharge_positive":
        values["current"] = -values["current"]
        if "charge" in values and "discharge" not in values:   # split counters count up
            values["charge"] = -values["charge"]
        notes.append("current (and charge) negated: file logs discharge positive"
                     if "discharge" not in values else
                     "current negated: file logs discharge positive")
    for role, unit in (("time", colmap.time_unit), ("current", colmap.current_unit),
                       ("voltage", colmap.voltage_unit), ("charge", colmap.charge_unit)):
        if role in values and unit not in ("s", "A", "V", "Ah"):
            notes.append(f"{role} converted from {unit}")
    return values


def _charge_count(path: Path, values: dict, colmap: ColumnMap, names: dict,
                  notes: list[str]) -> np.ndarray | None:
    """The cumulative charge from the file's counter(s), joined over their restarts
    (ecmgen.data.counters; ecmgen's own charge_ah column is cumulative as written), its
    sign checked against the current; None without a counter."""
    if "charge" not in values:
        return None
    if colmap.charge == CANONICAL_HEADER[-1] and "discharge" not in values:
        charge = values["charge"]
        _check_charge_sign(path, values, names)
        return charge
    charge, restarts = cumulative_charge(values["time"], values["current"], values["charge"],
                                         values.get("discharge"))
    _check_charge_sign(path, dict(values, charge=charge), names)
    counted = names["charge"] + (f" - {names['discharge']}" if "discharge" in values else "")
    notes.append(f"charge counted by the cycler ({counted})" +
                 (f", joined over {restarts} restart{'s' if restarts > 1 else ''} of its "
                  f"counter" if restarts else ""))
    return charge


def _check_charge_sign(path, values, names) -> None:
    """The logged charge must move with the current; otherwise its sign (or the column)
    is wrong and SOC would run backwards."""
    d_charge = np.diff(values["charge"])
    mid_current = 0.5 * (values["current"][1:] + values["current"][:-1])
    moving = (d_charge != 0) & (mid_current != 0)
    if moving.sum() < 10:
        return
    agree = float(np.mean(np.sign(d_charge[moving]) == np.sign(mid_current[moving])))
    if agree < 0.2:
        raise InputError(path, f"{names['charge']}: cumulative charge falls while "
                               f"the current ({names['current']}) charges (agrees on only "
                               f"{agree:.0%} of samples): opposite sign conventions?")


# --------------------------------------------------------------------------- direction

def charging_direction(current_a: np.ndarray, deadband_a: float) -> np.ndarray:
    """Per sample, True where a model runs on its charge table: charge when the current
    exceeds +deadband, discharge below -deadband, the last decided direction in between
    (discharge before any). The simulator's rule (:mod:`ecmgen.model.simulate`, step 1),
    shared with the fit that must reproduce it."""
    current_a = np.asarray(current_a, dtype=np.float64)
    sign = np.where(current_a > deadband_a, 1.0, np.where(current_a < -deadband_a, -1.0, np.nan))
    if sign.size and np.isnan(sign[0]):
        sign[0] = -1.0
    idx = np.where(np.isnan(sign), 0, np.arange(sign.size))
    np.maximum.accumulate(idx, out=idx)
    return sign[idx] > 0


# --------------------------------------------------------------------------- writing

def write_timeseries_csv(series: TimeSeries, path: str | Path) -> Path:
    """Write the canonical CSV ``time_s,current_a,voltage_v[,temperature_c][,charge_ah]``
    (current positive on charge), floats as round-trip ``repr``; atomic."""
    present = [(name, getattr(series, name)) for name in CANONICAL_HEADER]
    header = [name for name, values in present if values is not None]
    cols = [values for _, values in present if values is not None]
    as_lists = [np.asarray(c, dtype=np.float64).tolist() for c in cols]  # Python floats
    lines = [",".join(header)]
    lines.extend(",".join(map(repr, row)) for row in zip(*as_lists))
    path = Path(path)
    write_atomic(path, "\n".join(lines) + "\n")
    return path
