"""``ecmgen verify``: the firmware team's copy of the generated C against the golden vectors.

The golden folder (a build's ``c/float`` or ``c/fixed``, or the build folder holding both)
has ``<prefix>_ecm_<s>_vectors.h`` and ``<prefix>_ecm_<s>_test.c`` (:mod:`ecmgen.c.golden`),
and with the estimator ``<prefix>_est_f32_vectors.h`` and its test (linked with the model's
``<prefix>_ecm_f32.c`` too; :mod:`ecmgen.c.estgolden`).
For each, the C as the user has it (``--c``: the folder of their ``<prefix>_ecm_<s>.c`` and
headers; default the golden folder itself) is compiled with their compiler and flags, the
test program is run (``--run``: e.g. a QEMU command for a cross compiler) and its one-line
verdict collected. Exit status 0: every model passes; 1: one fails (or does not compile);
2: bad input (no vectors, no sources, no compiler).
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

VECTORS_GLOB = "*_vectors.h"
EST_STEM = "_est_f32"           # <prefix>_est_f32_vectors.h: the estimator's (ecmgen.c.estgolden)
DEFAULT_CFLAGS = "-std=c99 -O2 -ffp-contract=off"


@dataclass
class Verdict:
    name: str            # the model's file stem, e.g. pan_ecm_q
    passed: bool
    line: str            # the test program's verdict, or why it did not run


def find_vectors(where: Path) -> list[Path]:
    """The vectors headers of a golden folder, of its c/<numeric>/ folders or of its
    <numeric>/ folders; ``where`` may be one vectors file."""
    if where.is_file():
        if not where.name.endswith("_vectors.h"):
            raise InputError(where, "not a golden vectors file (<prefix>_ecm_<s>_vectors.h)")
        return [where]
    if not where.is_dir():
        raise InputError(where, "no such file or folder")
    found = sorted(where.glob(VECTORS_GLOB)) or sorted(where.glob("*/" + VECTORS_GLOB)) or \
        sorted(where.glob("c/*/" + VECTORS_GLOB))
    if not found:
        raise InputError(where, "no golden vectors here (<prefix>_ecm_<s>_vectors.h, written "
                                "by ecmgen build into c/float and c/fixed)")
    return found


def _compile_and_run(vec: Path, csrc: Path | None, cc: list[str], cflags: list[str],
                     run: list[str], timeout: float) -> Verdict:
    stem = vec.name[:-len("_vectors.h")]
    test = vec.with_name(f"{stem}_test.c")
    src_dir = csrc if csrc is not None else vec.parent
    sources = [src_dir / f"{stem}.c"]
    if stem.endswith(EST_STEM):         # the estimator links the model's step and tables
        sources.append(src_dir / f"{stem[:-len(EST_STEM)]}_ecm_f32.c")
    for need in (test, *sources):
        if not need.is_file():
            raise InputError(need, "missing: the golden test program and the model's source "
                                   "are needed")
    with tempfile.TemporaryDirectory(prefix="ecmgen-verify-") as tmp:
        exe = Path(tmp) / f"{stem}_test"
        # the user's folder first: their headers (and runtime) are the ones under test
        args = [*cc, *cflags, "-I", str(src_dir), "-I", str(vec.parent), str(test),
                *map(str, sources), "-o", str(exe)]
        try:
            proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout)
        except OSError as exc:
            raise InputError(cc[0], f"compiler not found or not runnable ({exc.strerror}); "
                                    "give --cc") from None
        if proc.returncode != 0:
            err = next((ln for ln in proc.stderr.splitlines() if "error" in ln),
                       proc.stderr.strip().splitlines()[0] if proc.stderr.strip() else "")
            return Verdict(stem, False, f"{stem}: FAIL: does not compile: {err.strip()[:300]}")
        try:
            res = subprocess.run([*run, str(exe)], capture_output=True, text=True, timeout=timeout)
        except OSError as exc:
            raise InputError(run[0], f"--run command not found or not runnable "
                                     f"({exc.strerror})") from None
        except subprocess.TimeoutExpired:
            return Verdict(stem, False, f"{stem}: FAIL: did not finish within {timeout:g} s")
    return _judge(stem, _vector_steps(vec), res.returncode, res.stdout)


def _vector_steps(vec: Path) -> int | None:
    """The step count a vectors header declares (``#define <M>_VEC_STEPS 3064u``)."""
    m = re.search(r"^#define \w+_VEC_STEPS (\d+)u?\s*$", vec.read_text(errors="replace"), re.M)
    return None if m is None else int(m.group(1))


def _judge(stem: str, steps: int | None, status: int, stdout: str) -> Verdict:
    """A pass needs exit status 0 *and* the program's own PASS line with every step of the
    vectors run: a --run that never ran it (``true``, ``echo``) or a copy that exits early
    (an init calling exit(0)) prints no such line."""
    line = next((ln for ln in stdout.splitlines() if ln.startswith(f"{stem}: ")), None)
    if line is None:
        return Verdict(stem, False, f"{stem}: FAIL: no result line from the test program "
                                    f"(exit status {status}): it did not run, or stopped early")
    m = re.match(rf"{re.escape(stem)}: (PASS|FAIL): (\d+) steps", line)
    if m is None or steps is None or int(m.group(2)) != steps:
        ran = "no step count" if m is None else f"{m.group(2)} steps"
        return Verdict(stem, False, f"{line} [FAIL: {ran} where the vectors have {steps}]")
    if m.group(1) == "PASS" and status != 0:
        return Verdict(stem, False, f"{line} [FAIL: exit status {status}]")
    return Verdict(stem, m.group(1) == "PASS" and status == 0, line)


def _split(option: str, text: str) -> list[str]:
    """A command line as a shell would split it; unbalanced quotes are bad input."""
    try:
        return shlex.split(text)
    except ValueError as exc:
        raise InputError(option, f"cannot be split into words ({exc}): {text!r}") from None


def verify(where, csrc=None, cc: str | None = None, cflags: str | None = None,
           run: str | None = None, timeout: float = 300.0) -> list[Verdict]:
    """One verdict per golden vectors file found under ``where`` (see the module doc)."""
    where = Path(where)
    vectors = find_vectors(where)
    csrc_p = None if csrc is None else Path(csrc)
    if csrc_p is not None and not csrc_p.is_dir():
        raise InputError(csrc_p, "--c must be the folder of your copy of the generated C")
    if csrc_p is not None and len(vectors) > 1:
        # one folder of sources, several numerics: check those whose source is there
        vectors = [v for v in vectors if (csrc_p / f"{v.name[:-len('_vectors.h')]}.c").is_file()] \
            or vectors
    cc_cmd = _split("--cc", cc) if cc else [shutil.which("cc") or "cc"]
    flags = _split("--cflags", cflags if cflags is not None else DEFAULT_CFLAGS)
    run_cmd = _split("--run", run) if run else []
    if not cc_cmd:
        raise InputError("--cc", "is empty: give a compiler")
    return [_compile_and_run(v, csrc_p, cc_cmd, flags, run_cmd, timeout) for v in vectors]
