"""Where the commands write: never onto an input, never half, never beside stale files.

- :func:`refuse_inputs` / :func:`check_output_file` / :func:`check_output_folder`: an
  output is checked against every file the command reads, and its kind (file or folder)
  before any work, so a long fit never ends in "File exists".
- :func:`staged`: a build's or a diagnosis's files are written into a staging folder
  beside ``--out`` (``.ecmgen-staging-<pid>@<host>-*``) and moved into place only when
  all of them are there. The folder goes on any exception (the command line turns SIGTERM
  into one); a folder left by a killed process (SIGKILL, power loss) is found and removed
  by the next run that stages beside it, once its process is gone.
- A manifest (``ecmgen-manifest.json``) lists what ecmgen wrote into ``--out`` with each
  file's SHA-256. A later build into the same folder removes the files of the earlier one
  it does not write again (c/fixed, PNGs, per-method models), so that what is in the
  folder belongs to one model. A file changed since ecmgen wrote it is kept and named;
  one that a new run writes again is kept beside it as ``<name>.edited``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Iterable

from .errors import InputError
from .files import file_sha256, write_atomic

MANIFEST = "ecmgen-manifest.json"
STAGING_PREFIX = ".ecmgen-staging-"
# a staging folder without a process id of this machine in its name (written by an older
# ecmgen, or by another machine on a shared disk) is removed once nothing has touched it
# for this long: no build runs that long unnoticed
STALE_UNNAMED_S = 24 * 3600.0


def resolved(path: str | Path, option: str = "--out") -> Path:
    """``path`` resolved; a symbolic link loop on the way is bad input, not a traceback."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:      # RuntimeError: "Symlink loop" (3.11, 3.12)
        raise InputError(path, f"{option}: cannot be resolved ({exc}): a symbolic link "
                               "that leads back to itself? give another path") from None


def refuse_inputs(out: str | Path, inputs: Iterable[str | Path | None], option: str = "--out"
                  ) -> None:
    """InputError unless ``out`` is none of ``inputs`` (compared as resolved paths)."""
    target = resolved(out, option)
    for p in inputs:
        if p is not None and Path(p).resolve() == target:
            raise InputError(out, f"{option} would overwrite an input file of this command; "
                                  "choose another path")


def check_output_file(out: str | Path, inputs: Iterable, option: str = "--out") -> Path:
    """A file the command will write: not an input, not a folder, in a place that takes
    files."""
    out = Path(out)
    refuse_inputs(out, inputs, option)
    if out.is_dir():
        raise InputError(out, f"{option} is a directory; give a file name")
    if out.exists() and not out.is_file():
        # the write goes via a temporary file and a rename, which would replace the node
        raise InputError(out, f"{option} is not a regular file (a device or a pipe); "
                              "give a file name")
    _check_writable(out, option)
    return out


def _check_writable(out: Path, option: str, folder: Path | None = None) -> None:
    """Refuse now, not after the work, a place no file can be written: a temporary file
    is made (and removed at once) in the nearest folder that exists on the way to it."""
    folder = folder or resolved(out, option).parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(out, f"{option}: {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder, prefix=".ecmgen-probe-"):
            pass
    except OSError as exc:
        raise InputError(out, f"{option}: cannot write in {folder} "
                              f"({exc.strerror or exc})") from None


def check_output_folder(out: str | Path, inputs: Iterable, option: str = "--out") -> Path:
    """A folder the command will fill: not an existing file, no input inside it is one of
    the names it writes (checked again when the files move in)."""
    out = Path(out)
    refuse_inputs(out, inputs, option)
    if out.exists() and not out.is_dir():
        raise InputError(out, f"{option} is an existing file; give a folder")
    _check_writable(out, option, resolved(out, option))
    return out


# --------------------------------------------------------------------------- staging

def _host() -> str:
    """This machine's name as it goes into a staging folder's name (no '-' or '@')."""
    import socket

    return "".join(c for c in socket.gethostname() if c.isalnum() or c == ".") or "host"


def _staging_name() -> str:
    return f"{STAGING_PREFIX}{os.getpid()}@{_host()}-"


def _staging_pid(folder: Path) -> int | None:
    """The process id in a staging folder's name when that process ran on this machine
    (a folder on a shared disk may be another machine's, whose process ids say nothing
    here); None otherwise."""
    pid, _, host = folder.name[len(STAGING_PREFIX):].split("-", 1)[0].partition("@")
    return int(pid) if pid.isdigit() and host == _host() else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:         # someone else's process
        return True
    return True


def remove_stale_staging(parent: Path) -> list[Path]:
    """Remove the staging folders in ``parent`` whose process is gone; return them."""
    removed = []
    try:
        found = [p for p in parent.iterdir() if p.name.startswith(STAGING_PREFIX) and p.is_dir()]
    except OSError:
        return removed
    for p in found:
        pid = _staging_pid(p)
        if pid is None:
            try:
                stale = time.time() - p.stat().st_mtime > STALE_UNNAMED_S
            except OSError:
                continue
        else:
            stale = pid != os.getpid() and not _alive(pid)
        if stale:
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


@contextmanager
def staged(out_dir: Path, given: set[Path], remove_leftovers: bool = True):
    """Yield (staging folder, list of final paths); on success the staged files move into
    out_dir (the list is filled) and the earlier build's leftovers go; on any error or
    interruption nothing reaches out_dir (a commit that fails part-way puts back what it
    had replaced) and the staging folder is removed. ``remove_leftovers`` False: files of
    earlier runs stay (``ecmgen codegen``: models of other prefixes share a folder)."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(out_dir.parent)
    staging = Path(tempfile.mkdtemp(prefix=_staging_name(), dir=out_dir.parent))
    files: list[Path] = []
    try:
        yield staging, files
        files.extend(commit(staging, out_dir, given, remove_leftovers))
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def commit(staging: Path, out_dir: Path, given: set[Path], remove_leftovers: bool = True
           ) -> list[Path]:
    """Move the staged files into out_dir (refusing to replace any file the user gave),
    remove what the previous manifest lists and this build did not write, and write the
    new manifest. Returns the paths of the staged files in out_dir.

    All or nothing: a file it replaces is first moved aside (into the staging folder, on
    the same disk) and put back if a later move fails. A file it would replace that is
    not ecmgen's as the previous manifest recorded it (the user edited it, or wrote it) is
    kept beside, as ``<name>.edited`` (named in the manifest's ``kept_changed``)."""
    staged_files = [p for p in sorted(staging.rglob("*")) if p.is_file()]
    rel = [p.relative_to(staging).as_posix() for p in staged_files]
    targets = [out_dir / r for r in rel]
    for t in targets + [out_dir / MANIFEST]:
        if t.resolve() in given:
            raise InputError(t, "output would overwrite an input file; choose another --out")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "--out is an existing file; give a folder")
    for t in targets + [out_dir / MANIFEST]:
        if t.is_dir() and not t.is_symlink():
            raise InputError(t, "is a folder where ecmgen writes a file; move it away")
    hashes = {r: file_sha256(p) for r, p in zip(rel, staged_files)}
    out_dir.mkdir(parents=True, exist_ok=True)
    aside = Path(tempfile.mkdtemp(prefix=".replaced-", dir=staging))
    with _locked(out_dir):      # two builds into one folder: one after the other
        previous = read_manifest(out_dir)
        moved: list[Path] = []
        replaced: list[tuple[Path, Path]] = []
        edited: list[tuple[Path, Path]] = []
        try:
            for src, dst, r in zip(staged_files, targets, rel):
                if dst.is_file() and not dst.is_symlink():
                    sha = file_sha256(dst)
                    if sha == hashes[r]:
                        continue                    # the same bytes: left alone
                    keep = previous.get(r) != sha   # not as ecmgen wrote it: the user's
                    b = aside / r
                    b.parent.mkdir(parents=True, exist_ok=True)
                    shutil.move(str(dst), str(b))
                    replaced.append((b, dst))
                    if keep:
                        edited.append((b, dst))
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(src), str(dst))
                moved.append(dst)
            beside = [_free_name(dst) for _, dst in edited]
            kept = [p.relative_to(out_dir).as_posix() for p in beside]
            if remove_leftovers:
                kept += _remove_leftovers(out_dir, previous, hashes, given)
                files = hashes
            else:
                files = {**previous, **hashes}
            write_atomic(out_dir / MANIFEST, json.dumps(
                {"written_by": "ecmgen", "files": files, "kept_changed": kept}, indent=1) + "\n")
            for (b, _), name in zip(edited, beside):
                shutil.move(str(b), str(name))
        except BaseException:
            for dst in moved:
                dst.unlink(missing_ok=True)
            for b, dst in replaced:
                if b.exists():
                    shutil.move(str(b), str(dst))
            raise
    return targets


def _free_name(dst: Path) -> Path:
    """Where a user's file that ecmgen replaces is kept: ``<name>.edited`` beside it
    (``.edited-2`` ... when taken)."""
    name = dst.with_name(dst.name + ".edited")
    n = 2
    while name.exists() or name.is_symlink():
        name = dst.with_name(f"{dst.name}.edited-{n}")
        n += 1
    return name


@contextmanager
def _locked(folder: Path):
    """An exclusive lock on the folder itself (flock on its descriptor: no lock file to
    leave behind), so that the files and the manifest of two commits never interleave."""
    try:
        import fcntl
    except ImportError:         # not POSIX: no lock
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)            # closing releases the lock


def read_manifest(out_dir: Path) -> dict[str, str]:
    """{relative path: sha256} of ecmgen's earlier outputs in out_dir ({} without one, or
    when it is not ecmgen's: nothing is removed on the word of a file we cannot read)."""
    try:
        doc = json.loads((out_dir / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}
    files = doc.get("files") if isinstance(doc, dict) else None
    if not isinstance(files, dict):
        return {}
    return {k: v for k, v in files.items() if isinstance(k, str) and isinstance(v, str)}


def remove_outputs(out_dir: Path, given: set[Path] = frozenset()) -> list[str]:
    """Remove what the manifest in out_dir lists, unchanged since ecmgen wrote it, and the
    manifest (a run that failed leaves no earlier results that look like its own); return
    the changed files, which are kept (and listed in a manifest of no files)."""
    previous = read_manifest(out_dir)
    if not previous:
        return []
    with _locked(out_dir):
        kept = _remove_leftovers(out_dir, previous, {}, set(given))
        if kept:
            write_atomic(out_dir / MANIFEST, json.dumps(
                {"written_by": "ecmgen", "files": {}, "kept_changed": kept}, indent=1) + "\n")
        else:
            (out_dir / MANIFEST).unlink(missing_ok=True)
    return kept


def kept_beside(out_dir: Path) -> list[str]:
    """The files the last commit into out_dir kept as ``<name>.edited``: the user's
    versions of files it wrote again (from its manifest's kept_changed)."""
    try:
        kept = json.loads((out_dir / MANIFEST).read_text()).get("kept_changed", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [k for k in kept if isinstance(k, str) and re.search(r"\.edited(-\d+)?$", k)]


def _inside(out_dir: Path, rel: str) -> Path | None:
    """out_dir/rel when rel is a plain relative path that stays inside out_dir."""
    pure = PurePosixPath(rel)
    if pure.is_absolute() or ".." in pure.parts or not pure.parts:
        return None
    path = out_dir.joinpath(*pure.parts)
    return path if path.resolve().is_relative_to(out_dir.resolve()) else None


def _remove_leftovers(out_dir: Path, previous: dict[str, str], now: dict[str, str],
                      given: set[Path]) -> list[str]:
    """Remove the earlier outputs not written again, if unchanged since; return the
    changed ones, which are kept (the user edited them)."""
    kept = []
    for rel, sha in sorted(previous.items()):
        path = _inside(out_dir, rel)
        if rel in now or path is None or not path.is_file() or path.is_symlink() or \
                path.resolve() in given:
            continue
        if file_sha256(path) != sha:
            kept.append(rel)
            continue
        path.unlink()
        for folder in path.parents:         # folders it leaves empty (c/fixed, c)
            if folder == out_dir or not folder.is_relative_to(out_dir):
                break
            try:
                folder.rmdir()
            except OSError:
                break
    return kept
