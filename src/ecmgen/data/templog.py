"""A cell temperature logged apart from the cycler: a time-stamped CSV read onto a record's
clock (``data.temperature_c = {"hppc.csv" = "hppc-temperature.csv"}``).

The log needs a header line with a time column and a temperature column, recognised by
name (a name holding "time"; one holding "temp", or degC / °C), times in seconds on the
same clock as the record's own time column. Its values are interpolated linearly onto the
record's samples and held at its ends (said in a note) where the record runs beyond it.

Refused, one line each: a log that spans less than half the record's time (its end values
would stand for most of it), a log without a time column (a thermocouple logger's export of
values only, as the Leaf's: samples with no time stamps cannot be placed on the record,
and their rate is not known to be the cycler's), a log that does not overlap the record's
time at all (another clock: Unix time against time from the test's start), and a log of
fewer than two finite rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, reading
from .csvtext import CsvRows, csv_encoding
from .measure import TimeSeries


# a log must span at least half the record's time: the rest is held at the log's end
# values, which stand in for a temperature it never saw (a drive cycle warms the cell
# 5-7 K, the shared Panasonic records); past half, the held values are most of the record
MIN_COVER = 0.5


def _column(names: list[str], words: tuple[str, ...]) -> int | None:
    hits = [k for k, n in enumerate(names) if any(w in n.lower() for w in words)]
    return hits[0] if hits else None


def read_temperature_log(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, temperature_c) of a temperature log (module doc), sorted by time."""
    with reading(path):
        rows = iter(CsvRows(path, csv_encoding(path)))
        first = next(rows, None)
        if first is None:
            raise InputError(path, "empty file: not a temperature log")
        names = [c.strip() for c in first[1]]
        t_col = _column(names, ("time",))
        v_col = _column(names, ("temp", "degc", "°c"))
        if t_col is None:
            raise InputError(path, f"no time column (columns: {', '.join(names)[:120]}): a "
                                   "temperature log without time stamps cannot be placed on "
                                   "the record's clock; give the temperature as a number in "
                                   "data.temperature_c")
        if v_col is None or v_col == t_col:
            raise InputError(path, f"no temperature column (a name holding 'temp'; columns: "
                                   f"{', '.join(names)[:120]})")
        t, v = [], []
        for line, cells in rows:
            try:
                t.append(float(cells[t_col]))
                v.append(float(cells[v_col]))
            except (ValueError, IndexError):
                raise InputError(path, f"line {line}: not a number in the time or "
                                       "temperature column") from None
    t, v = np.array(t), np.array(v)
    ok = np.isfinite(t) & np.isfinite(v)
    if ok.sum() < 2:
        raise InputError(path, "fewer than two rows with a time and a temperature")
    order = np.argsort(t[ok], kind="stable")
    return t[ok][order], v[ok][order]


def with_temperature_log(series: TimeSeries, path: Path) -> TimeSeries:
    """``series`` with the cell temperature of the log at ``path`` on its samples."""
    from dataclasses import replace

    t_log, temp = read_temperature_log(path)
    t = series.time_s
    if t_log[-1] < t[0] or t_log[0] > t[-1]:
        raise InputError(path, f"its times ({t_log[0]:g} .. {t_log[-1]:g} s) do not overlap "
                               f"those of {Path(series.source).name} ({t[0]:g} .. {t[-1]:g} "
                               "s): not the same clock?")
    cover = (min(t_log[-1], t[-1]) - max(t_log[0], t[0])) / (t[-1] - t[0]) \
        if t[-1] > t[0] else 1.0
    if cover < MIN_COVER:
        raise InputError(path, f"its times ({t_log[0]:g} .. {t_log[-1]:g} s) cover "
                               f"{100.0 * cover:.1f} % of {Path(series.source).name} "
                               f"({t[0]:g} .. {t[-1]:g} s); its end values would stand for "
                               f"the cell's temperature over the rest (at least "
                               f"{100.0 * MIN_COVER:g} % needed): the log of another test?")
    note = f"cell temperature from {path.name} (a time-stamped log, interpolated)"
    outside = (t < t_log[0]) | (t > t_log[-1])
    if outside.any():
        note += (f"; {100.0 * outside.mean():.1f} % of the record lies beyond the log: held "
                 "at its end values there")
    return replace(series, temperature_c=np.interp(t, t_log, temp),
                   notes=series.notes + (note,))
