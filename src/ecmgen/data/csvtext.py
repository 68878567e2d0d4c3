"""A CSV measurement file as text rows, read a block at a time.

A cycler export can hold millions of rows; read whole, as text and then as Python strings,
it took about 500 bytes a row (a 6 M-row file: 3 GB). Here the file is never in memory
whole: the csv module reads it line by line (any line end: LF, CRLF or a classic Mac CR),
and the caller turns each block of :data:`BLOCK_ROWS` rows into numbers before the next
one is read.
"""

from __future__ import annotations

import csv
import itertools
from pathlib import Path
from typing import Iterator

from ..errors import InputError

BLOCK_ROWS = 1 << 16
UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")    # Excel's "Unicode text" export
# bytes no text export holds (all control characters but tab, LF, VT, FF, CR)
_BINARY = bytes(range(0, 9)) + bytes(range(14, 32))


def csv_encoding(path: Path) -> str:
    """The encoding to try first: UTF-16 after its BOM, else UTF-8 (a BOM skipped); a
    file of control bytes is refused as binary."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    if head[:2] in UTF16_BOMS:
        return "utf-16"
    if head and sum(head.count(b) for b in _BINARY) > max(1, len(head) // 1000):
        raise InputError(path, "binary content (control bytes), not a CSV text file: "
                               "export the measurement as CSV or .mat")
    return "utf-8-sig"


class CsvRows:
    """The non-blank rows of a CSV file as (line number, cells), in blocks. The delimiter
    is the one of ``,`` ``;`` tab the first line holds most of."""

    def __init__(self, path: Path, encoding: str):
        self.path, self.encoding = path, encoding
        with open(path, newline="", encoding=encoding) as fh:
            first = fh.readline()
        self.delimiter = max((",", ";", "\t"), key=first.count)

    def __iter__(self) -> Iterator[tuple[int, list[str]]]:
        with open(self.path, newline="", encoding=self.encoding) as fh:
            reader = csv.reader(fh, delimiter=self.delimiter)
            for row in reader:
                if row and (len(row) > 1 or row[0].strip()):
                    yield reader.line_num, row


def blocks(rows, size: int = BLOCK_ROWS) -> Iterator[list]:
    """``rows`` in lists of at most ``size``."""
    rows = iter(rows)
    while block := list(itertools.islice(rows, size)):
        yield block
