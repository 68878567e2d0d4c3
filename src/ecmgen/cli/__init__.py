"""`ecmgen` command line: a thin layer over the library (see ecmgen.pipeline).

:func:`main` is the entry point and the one boundary (bad input: one line, exit 2); the
parsers are in :mod:`ecmgen.cli.args`, the commands in :mod:`ecmgen.cli.commands`."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
import warnings

from ..parallel import ONE_BLAS_THREAD

# The command line owns its process: one BLAS thread unless the caller sets another,
# set before numpy loads (ecmgen.parallel says why).
for _name, _value in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_name, _value)

from ..errors import InputError, describe, user_file_of  # noqa: E402
from .args import parser  # noqa: E402

__all__ = ["main", "parser"]


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        with _no_stray_warnings(), _sigterm_unwinds():
            code = int(args.func(args) or 0)
            sys.stdout.flush()          # a full or closed stdout fails here, not at exit
            return code
    except InputError as exc:
        return _error(str(exc))
    except OSError as exc:
        if exc.filename is not None or exc.errno not in _STDOUT_ERRNOS:
            return _boundary(exc)
        _silence_stdout()               # else Python's own flush at exit fails again
        if exc.errno == errno.EPIPE:    # `ecmgen ... | head`: the reader left, not an error
            return 141
        return _error(f"standard output: cannot be written ({describe(exc)})")
    except KeyboardInterrupt:
        return 130
    except Terminated:
        return 143
    except Exception as exc:
        return _boundary(exc)


# errors of a write to a full, broken or closed standard output (a file name is not set)
_STDOUT_ERRNOS = {errno.ENOSPC, errno.EPIPE, errno.EIO, errno.EDQUOT, errno.EBADF, errno.EFBIG}


def _silence_stdout() -> None:
    with contextlib.suppress(OSError, ValueError, AttributeError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _boundary(exc: BaseException) -> int:
    """The one boundary: an exception raised while reading a user's file (marked by
    ecmgen.errors.reading), or the system refusing a path (an output folder under /proc, a
    full disk), is bad input or a bad place: one line, exit 2. Anything else is a fault of
    ecmgen and keeps its traceback (exit 1)."""
    where = user_file_of(exc)
    if where is None and isinstance(exc, OSError) and exc.filename is not None:
        where = exc.filename
    if where is None:
        raise exc
    return _error(f"{where}: {describe(exc)}")


def _error(message: str) -> int:
    print(f"ecmgen: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


class Terminated(BaseException):
    """SIGTERM, raised where the program is, like KeyboardInterrupt for SIGINT (not an
    Exception: no ``except Exception`` on the way may swallow it)."""


@contextlib.contextmanager
def _sigterm_unwinds():
    """SIGTERM (a CI timeout, ``kill``) unwinds the stack as Ctrl-C does, so that the
    staging folder and temporary files are removed on the way out (exit 143)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _no_stray_warnings():
    """Safety net: no Python warning reaches the user of the command line. What the user
    must know is said as a note or an error; the warnings numpy/scipy/matplotlib raise
    about intermediate values are fixed at their cause where found (and tested with
    ``-W error``), and anything left is not the user's to act on. A developer who asks
    for warnings (``python -W ...`` or PYTHONWARNINGS) still sees them."""
    if sys.warnoptions:
        yield
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield
