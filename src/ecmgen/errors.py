"""One exception type for bad input: the CLI prints it as one line and exits non-zero."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input. ``str()`` is one line: ``<file>: <what is wrong>``."""

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else str(path)
        self.message = " ".join(str(message).split())  # always one line
        super().__init__(self.message if self.path is None else f"{self.path}: {self.message}")
