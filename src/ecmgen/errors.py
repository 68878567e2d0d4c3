"""Bad input: one exception type, and the mark that says which user file was being read.

The command line prints an :class:`InputError` as one line and exits 2. Everything else
a reader of a user's file raises (a ``UnicodeDecodeError``, a ``csv.Error``, an
``OverflowError`` from a value no check foresaw) is marked by :func:`reading` with the
file's name, not converted: library callers still see the real exception, and the command
line (ecmgen.cli, the one boundary) turns a marked exception into the same one line. An
exception without the mark is a fault of ecmgen and keeps its traceback.
"""

from __future__ import annotations

import csv
from contextlib import contextmanager
from pathlib import Path

# the attribute :func:`reading` sets on an exception: the user's file being read
FILE_MARK = "ecmgen_user_file"


class InputError(Exception):
    """Bad user input. ``str()`` is one line: ``<file>: <what is wrong>``."""

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else str(path)
        self.message = " ".join(str(message).split())  # always one line
        super().__init__(self.message if self.path is None else f"{self.path}: {self.message}")


@contextmanager
def reading(path: str | Path):
    """Mark any exception raised inside as raised while reading the user's file ``path``
    (the innermost mark wins: the file actually being read)."""
    try:
        yield
    except InputError:
        raise
    except Exception as exc:
        if getattr(exc, FILE_MARK, None) is None:
            try:
                setattr(exc, FILE_MARK, str(path))
            except AttributeError:      # an exception type without a __dict__
                raise InputError(path, describe(exc)) from exc
        raise


def user_file_of(exc: BaseException) -> str | None:
    """The user's file an exception was raised while reading, if it was marked."""
    return getattr(exc, FILE_MARK, None)


def describe(exc: BaseException) -> str:
    """What went wrong, in one line, for an exception raised while reading a user's file."""
    if isinstance(exc, UnicodeDecodeError):
        return (f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
                "save it as UTF-8")
    if isinstance(exc, IsADirectoryError):
        return "is a folder, not a file"
    if isinstance(exc, FileNotFoundError):
        return "no such file or folder"
    if isinstance(exc, PermissionError):
        return "permission denied"
    if isinstance(exc, OSError):
        return exc.strerror or str(exc)
    if isinstance(exc, RecursionError):
        return "nested too deeply to read"
    if isinstance(exc, MemoryError):
        return "too large to read into memory"
    if isinstance(exc, csv.Error):
        return f"not a readable CSV file ({exc})"
    # an unforeseen problem: said with its kind, so that a report of it can be traced
    text = " ".join(str(exc).split())
    return f"cannot be read ({type(exc).__name__}{': ' + text if text else ''})"
