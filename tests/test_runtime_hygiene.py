"""What a reviewer checks in the C by hand, checked on every runtime header and on the
generated files of a model with every switch on: everything inside its include guard, no
#define or #undef inside a function body, function-like macros read only their parameters
(and other macros), and no model switch in the runtime (the generator chooses what a model
has: each runtime header compiles alone)."""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from ecmgen.c.cbuild import _harness_texts
from ecmgen.c.codegen import prepare, render
from ecmgen.c.estc import prepare_estimator
from ecmgen.c.estgolden import render_est_vectors
from ecmgen.c.golden import drive_segment, edge_segment, render_vectors
from ecmgen.c.cbuild import STRICT_CFLAGS, host_cc
from ecmgen.c.runtime import runtime_dir
from ecmgen.c.spec import SWITCHES
from ecmgen.config import EstimatorConfig
from test_estimate import ALL_EFFECTS, model_over_temperature

C_WORDS = {"sizeof", "int32_t", "int64_t", "uint32_t", "uint8_t", "unsigned", "float", "int",
           "const", "do", "while", "if", "else", "return", "defined", "char", "extern", "void"}


def _strip_comments(text: str) -> str:
    return re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)


def _problems(name: str, text: str) -> list[str]:
    out = []
    text = re.sub(r"#ifdef __cplusplus\n(extern \"C\" \{|\})\n#endif", "\n\n",
                  _strip_comments(text))             # the C++ linkage braces are no body
    lines = text.splitlines()
    code = [(n, ln) for n, ln in enumerate(lines, 1) if ln.strip()]
    if name.endswith(".h"):
        first, last = code[0][1].strip(), code[-1][1].strip()
        if not (first.startswith("#ifndef") and last.startswith("#endif")):
            out.append(f"{name}: not all inside its include guard ({first!r} ... {last!r})")
    depth = 0
    joined = "\n".join(lines).replace("\\\n", " ")
    for n, ln in enumerate(joined.splitlines(), 1):
        s = ln.strip()
        if depth > 0 and re.match(r"#\s*(define|undef)\b", s):
            out.append(f"{name}:{n}: #define/#undef inside a function body")
        m = re.match(r"#\s*define\s+(\w+)\(([^)]*)\)\s*(.*)", s)
        if m:
            params = {p.strip() for p in m.group(2).split(",")}
            body = re.sub(r"'[^']*'|\"[^\"]*\"", "", m.group(3))
            # identifiers after "->" or "." are fields; capitals are macros and constants
            free = {w for w in re.findall(r"(?<![.>\w])([a-z_]\w*)", body)
                    if w not in params and w not in C_WORDS and not w.startswith(("ecmrt_", "_"))}
            # functions, types and what the macro declares (extern char name[...])
            free = {w for w in free if not (w.endswith("_t") or re.search(rf"\b{w}\s*\(", body)
                                            or re.search(rf"\bchar\s+{w}\b", body))}
            if free:
                out.append(f"{name}:{n}: macro {m.group(1)} reads {sorted(free)}")
        if not s.startswith("#"):
            depth += s.count("{") - s.count("}")
    return out


def test_runtime_headers():
    problems = []
    for path in sorted(runtime_dir().glob("*.h")):
        problems += _problems(path.name, path.read_text())
    assert problems == []


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_generated_files(numeric):
    m = model_over_temperature(effects=ALL_EFFECTS)
    spec = prepare(m, numeric)
    est = prepare_estimator(m, spec, EstimatorConfig(offset_state=True)) \
        if numeric == "float" else None
    files = render(spec, None, est)
    files["ecmh_harness.h"], files["ecmh_harness.c"] = _harness_texts(spec, est)  # tests' too
    files.update(render_vectors(spec, [drive_segment(spec, 50), edge_segment(spec)]))
    if est is not None:
        seg = drive_segment(spec, 50)
        files.update(render_est_vectors(spec, est, seg, np.full(50, 3.7)))
    problems = []
    for name, text in files.items():
        if name.endswith((".h", ".c")):
            problems += _problems(name, text)
    assert problems == []


def test_the_runtime_has_no_model_switch(tmp_path):
    """What a model has is chosen when its C is generated (ecmgen.c.spec.SWITCHES): no runtime
    header tests a switch or reads a model's macro, so each compiles as it is, alone."""
    names = set(SWITCHES)
    assert len(names) >= 15 and "SURFACE" in names and "VARIABLE_DT" in names
    for path in runtime_dir().glob("*.h"):
        conds = re.findall(r"^\s*#\s*(?:if|ifdef|ifndef|elif)\b(.*)$", path.read_text(), re.M)
        tested = {w for c in conds for w in re.findall(r"\bECMRT_(\w+)", c)}
        assert not tested & names, (path.name, tested & names)
    for header, pre in (("ecmrt_f32.h", ""), ("ecmrt_q.h", ""),
                        ("ecmrt_est_f32.h", "#define ECMRT_EST_N 5u\n")):
        src = tmp_path / f"alone_{header}.c"
        src.write_text(f"{pre}#include \"{header}\"\nint ecmrt_alone(void);\n"
                       "int ecmrt_alone(void) { return 0; }\n")
        proc = subprocess.run([*host_cc(), *STRICT_CFLAGS, "-O2", "-I", str(runtime_dir()), "-c",
                               str(src), "-o", str(tmp_path / "alone.o")],
                              capture_output=True, text=True)
        assert proc.returncode == 0, (header, proc.stderr)
