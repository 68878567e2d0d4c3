"""Writing and hashing files: the lowest layer, shared by every stage that writes.

:func:`write_atomic` writes via a temporary file and a rename, so a failure never
leaves half a file; :func:`file_sha256` names an input file in a model's provenance;
:func:`short_names` and :func:`temperature_label` name the files a build reads and writes.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from pathlib import Path

from .errors import InputError


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write via a temporary file + rename, so a failure never leaves half a file. A
    folder the system refuses (under /proc, read-only, full) is an InputError naming
    ``path``, not the temporary file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise InputError(path, f"cannot be written ({exc.strerror or exc})") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(text.encode() if isinstance(text, str) else text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def json_safe(obj):
    """``obj`` with every non-finite float (NaN: a figure that has no value, e.g. the MAE
    above 10 % SOC of a cycle that never gets there) as None, so the JSON is valid: JSON
    has no NaN, and json.dumps would write a bare ``NaN`` that strict readers refuse; the
    others to 12 significant digits, as a person writes them, without the binary noise of
    a sum of time stamps."""
    if isinstance(obj, float):      # 12 digits: 23374, not 23374.000000000004
        return float(f"{obj:.12g}") if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "dtype") and getattr(obj, "shape", None) == ():   # numpy scalars
        return json_safe(obj.item())
    return obj


def json_text(obj, indent: int | None = None) -> str:
    """Valid JSON always: non-finite floats as null (json_safe), never NaN."""
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def short_names(paths) -> list[str]:
    """Names for files of the config: the file name, or as many of its last path parts as
    it takes to tell files of the same name apart (e.g. 0degC/us06.mat)."""
    paths = [Path(p) for p in paths]
    depth = 1
    while True:
        labels = ["/".join(p.parts[-depth:]) for p in paths]
        if len(set(labels)) == len(labels) or depth > max(len(p.parts) for p in paths):
            return labels
        depth += 1


def temperature_label(t: float) -> str:
    """25.8 -> "25.8degC", -9.9 -> "n9.9degC" (the shared data's folder style)."""
    if not math.isfinite(t):
        return "unknownT"
    return f"{'n' if t < 0 else ''}{abs(t):.1f}degC"
