"""The fleet's manifest: one build per row, read and checked before any work.

``manifest.csv`` has a header line and the columns ``cell``, ``checkup`` and ``config``
(a build config, relative to the manifest), and optionally ``cycles`` (full equivalent
cycles at the check-up), ``throughput_ah`` (charge throughput) and ``date``
(YYYY-MM-DD). Anything wrong with the manifest itself -- a column missing or unknown,
an empty value, a cell or check-up name that is no plain folder name, a (cell, check-up)
twice, a config that does not exist -- is an :class:`InputError` naming the manifest
and its line: the fleet does not start. What is wrong inside a row's config or its
measurement files fails that row only (ecmgen.fleet.task).

:func:`row_key` is the hash a row's results are kept under: ecmgen's version, the
build options, the config's bytes and the bytes of every file it names (by their names
relative to the config), so a row is built again exactly when one of them changed.
"""

from __future__ import annotations

import csv
import datetime as dt
import difflib
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from .._version import __version__
from ..errors import InputError, reading
from ..files import file_sha256

REQUIRED = ("cell", "checkup", "config")
OPTIONAL = ("cycles", "throughput_ah", "date")
# a cell or check-up name becomes a folder: letters, digits, '-', '_', '.' (not first)
NAME = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}$")


@dataclass(frozen=True)
class Row:
    """One manifest row: a cell at one check-up and the config that builds it."""

    line: int                   # its line in the manifest (for messages)
    cell: str
    checkup: str
    config: Path                # resolved
    config_given: str = ""      # as the manifest names it (relative to the manifest)
    cycles: float | None = None
    throughput_ah: float | None = None
    date: str | None = None

    @property
    def label(self) -> str:
        return f"{self.cell}/{self.checkup}"


def read_manifest(path: str | Path) -> list[Row]:
    """The rows of a manifest, checked (InputError naming the manifest and the line)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file" if not path.exists() else "is not a file")
    with reading(path):
        text = path.read_text(encoding="utf-8-sig")
        lines = list(csv.reader(text.splitlines()))
    if not lines or not any(c.strip() for c in lines[0]):
        raise InputError(path, "is empty; expected a header line cell,checkup,config")
    header = [c.strip() for c in lines[0]]
    _check_header(path, header)
    rows, seen = [], {}
    for n, values in enumerate(lines[1:], start=2):
        if not any(v.strip() for v in values):
            continue
        if len(values) != len(header):
            raise InputError(path, f"line {n}: {len(values)} values for {len(header)} "
                                   f"columns ({','.join(header)})")
        row = _row(path, n, dict(zip(header, (v.strip() for v in values))))
        key = (row.cell, row.checkup)
        if key in seen:
            raise InputError(path, f"line {n}: cell {row.cell!r} check-up {row.checkup!r} "
                                   f"is already on line {seen[key]}")
        seen[key] = n
        rows.append(row)
    if not rows:
        raise InputError(path, "has a header but no rows")
    return rows


def _check_header(path: Path, header: list[str]) -> None:
    known = REQUIRED + OPTIONAL
    for name in header:
        if name not in known:
            near = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise InputError(path, f"unknown column {name!r}{hint}; known: "
                                   f"{', '.join(known)}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputError(path, f"no column {', '.join(map(repr, missing))}; the header must "
                               f"name cell, checkup and config (found: {','.join(header)})")
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:
        raise InputError(path, f"column {twice[0]!r} is named twice")


def _row(path: Path, n: int, v: dict[str, str]) -> Row:
    for name in REQUIRED:
        if not v[name]:
            raise InputError(path, f"line {n}: no {name}")
    for name in ("cell", "checkup"):
        if not NAME.match(v[name]) or v[name] in (".", ".."):
            raise InputError(path, f"line {n}: {name} {v[name]!r} is not a plain folder name "
                                   "(letters, digits, '-', '_', '.'; at most 100)")
    config = (path.parent / v["config"]).resolve()
    if not config.is_file():
        what = "no such file" if not config.exists() else "not a file"
        raise InputError(path, f"line {n}: config {v['config']!r}: {what}")
    return Row(line=n, cell=v["cell"], checkup=v["checkup"], config=config,
               config_given=v["config"],
               cycles=_number(path, n, "cycles", v.get("cycles")),
               throughput_ah=_number(path, n, "throughput_ah", v.get("throughput_ah")),
               date=_date(path, n, v.get("date")))


def _number(path: Path, n: int, name: str, text: str | None) -> float | None:
    if not text:
        return None
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x >= 0):
        raise InputError(path, f"line {n}: {name} must be a number >= 0, got {text!r}")
    return x


def _date(path: Path, n: int, text: str | None) -> str | None:
    if not text:
        return None
    try:
        return dt.date.fromisoformat(text).isoformat()
    except ValueError:
        raise InputError(path, f"line {n}: date must be YYYY-MM-DD, got {text!r}") from None


def row_key(config: Path, files, options: dict) -> str:
    """The hash of a row's inputs: ecmgen's version, ``options``, the config's bytes and
    every file it names (``files``, the config's input_files) by name relative to the
    config's folder and content."""
    base = config.parent
    named = {}
    for f in sorted(Path(p) for p in files):
        try:
            name = f.relative_to(base).as_posix()
        except ValueError:
            name = f.as_posix()
        named[name] = file_sha256(f)
    doc = {"ecmgen": __version__, "options": options, "files": named}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()
