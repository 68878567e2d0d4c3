"""The source layout follows the pipeline: no import circles, no stage imports a later one,
no module over 800 lines, and the notebook API resolves from ``import ecmgen``. The C a
reviewer reads is capped as the Python is (every file of c_runtime/ and templates/), and
docs/layout.md names every module.

Every import statement of every module under src/ecmgen is read with ``ast`` (also the
ones inside functions, relative and absolute), so a lazy import counts like any other.
An edge X -> P for a package P means X imports P/__init__; ``from P import name`` is an
edge to the module P.name when that is a module, and importing a module of another
package is also an edge to that package (its __init__ runs first). The package facade
``ecmgen/__init__`` (lazy, PEP 562) is left out of the graph, and no module may import
it: the version comes from ``ecmgen._version``.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

import ecmgen

SRC = Path(ecmgen.__file__).resolve().parent
REPO = Path(__file__).resolve().parents[1]
# the brief's "no module over ~800 lines", for the Python and for the C files alike
MAX_LINES = 800
C_DIRS = ("c_runtime", "templates")
# the stages, lowest first; a unit may import only units of a lower level (and itself)
LEVELS = [
    {"base": ("ecmgen._version", "ecmgen.errors", "ecmgen.files", "ecmgen.config",
              "ecmgen.plots.style", "ecmgen.parallel", "ecmgen.outputs",
              "ecmgen.console")},
    {"data": ("ecmgen.data",)},
    {"fit": ("ecmgen.fit",)},
    {"model": ("ecmgen.model",)},
    # the C generates the estimator of the estimate stage (ecmgen.c.estc: its noise model,
    # compared with its float64 filter), so estimate sits below c
    {"estimate": ("ecmgen.estimate",)},
    {"c": ("ecmgen.c",), "diagnosis": ("ecmgen.diagnosis",)},
    {"plots": ("ecmgen.plots",), "report": ("ecmgen.report",)},
    {"pipeline": ("ecmgen.pipeline", "ecmgen.validation")},
    {"fleet": ("ecmgen.fleet",)},
    {"cli": ("ecmgen.cli",)},
]


def _modules() -> dict[str, Path]:
    """Dotted name -> file, for every module of the package (packages by their __init__)."""
    out = {}
    for path in sorted(SRC.rglob("*.py")):
        parts = ("ecmgen",) + path.relative_to(SRC).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _imports_nothing(path: Path) -> bool:
    return not any(isinstance(node, (ast.Import, ast.ImportFrom))
                   for node in ast.walk(ast.parse(path.read_text(), str(path))))


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules that ``name`` imports, anywhere in its file."""
    package = name if _is_package(path) else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.add(sub if sub in modules else target)
    # name and the packages it is part of, but not the facade: no module may import that
    own = {name.rsplit(".", k)[0] for k in range(name.count("."))}
    edges = set()
    for target in found:
        # `import a.b.c` names a, a.b and a.b.c: keep the deepest module of the package ...
        while target and target not in modules:
            target = target.rpartition(".")[0]
        if target and target not in own:
            edges.add(target)
        # ... and the packages on the way, whose __init__ runs first (not the facade, and
        # not a package that ``name`` itself is part of: that one is already running)
        target = target.rpartition(".")[0]
        while target and target != "ecmgen" and target not in own:
            if not _imports_nothing(modules[target]):   # an empty __init__ ties no stage
                edges.add(target)
            target = target.rpartition(".")[0]
    return edges


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _unit(module: str) -> tuple[int, str]:
    """The stage of the longest prefix that names ``module`` (ecmgen.plots.style is a base
    unit inside the plots package)."""
    found = [(len(p), level, unit) for level, units in enumerate(LEVELS)
             for unit, prefixes in units.items() for p in prefixes
             if module == p or module.startswith(p + ".")]
    if not found:
        raise AssertionError(f"{module} belongs to no stage of the layout; add it to LEVELS")
    return max(found)[1:]


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _check_the_graph_sees_lazy_and_relative_imports(g: dict[str, set[str]]) -> None:
    # lazy imports inside functions count (cli imports nearly everything that way)
    assert "ecmgen.pipeline" in g["ecmgen.cli.commands"]
    assert "ecmgen.model.effects" in g["ecmgen.model.model"]
    # `from . import cref` is an edge to the module, `from ..model import effects` too
    assert "ecmgen.c.cref" in g["ecmgen.c.target"]
    assert "ecmgen.model.effects" in g["ecmgen.diagnosis.search"]
    # a subpackage __init__ imports its own modules
    assert "ecmgen.c.codegen" in g["ecmgen.c"]


def _check_no_cycles_and_no_stage_imports_a_later_one(graph: dict[str, set[str]]) -> None:
    graph = dict(graph)
    facade = graph.pop("ecmgen")
    assert facade == {"ecmgen._version"}, "the facade imports its API lazily, by name"
    users = sorted(m for m, deps in graph.items() if "ecmgen" in deps)
    assert not users, f"modules import the package facade (use ecmgen._version): {users}"
    wrong = []
    for module, deps in sorted(graph.items()):
        level, unit = _unit(module)
        for dep in sorted(deps):
            dep_level, dep_unit = _unit(dep)
            if dep_unit != unit and dep_level >= level:
                wrong.append(f"{module} ({unit}) imports {dep} ({dep_unit})")
    assert not wrong, "\n".join(wrong)
    cycles = _cycles(graph)
    assert not cycles, "import circles: " + "; ".join(" <-> ".join(c) for c in cycles)


def _check_no_module_over_800_lines() -> None:
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def _check_the_notebook_api_resolves() -> None:
    from ecmgen.errors import InputError
    from ecmgen.model.model import EcmModel

    for name in ecmgen.__all__:
        assert getattr(ecmgen, name) is not None, name
    assert set(dir(ecmgen)) >= set(ecmgen.__all__)
    assert ecmgen.InputError is InputError and ecmgen.EcmModel is EcmModel
    for name in ("build", "load_config", "load_model", "read_timeseries", "simulate",
                 "validate", "diagnose", "generate_c", "extract_dcir", "find_pulses",
                 "fit_ga", "fit_lm", "fit_pulse_curves"):
        assert callable(getattr(ecmgen, name)), name
    # no API name is also a module of the package: importing that module would rebind
    # ecmgen.<name> to it (the reason the diagnose stage is the package `diagnosis`)
    top = {m.split(".")[1] for m in _modules() if m != "ecmgen"}
    assert not top & set(ecmgen.__all__), top & set(ecmgen.__all__)
    assert ecmgen.__version__ == importlib.import_module("ecmgen._version").__version__


def test_layout_follows_the_pipeline():
    graph = _graph()
    _check_the_graph_sees_lazy_and_relative_imports(graph)
    _check_no_cycles_and_no_stage_imports_a_later_one(graph)
    _check_no_module_over_800_lines()
    _check_the_notebook_api_resolves()


def _c_files() -> dict[str, int]:
    """Every file of c_runtime/ and templates/ (relative path) -> its lines."""
    return {f"{d}/{p.name}": len(p.read_text().splitlines())
            for d in C_DIRS for p in sorted((REPO / d).iterdir()) if p.is_file()}


def test_no_c_runtime_or_template_file_over_800_lines():
    files = _c_files()
    assert "c_runtime/ecmrt_f32.h" in files and "templates/ecm.c.j2" in files
    long = {name: n for name, n in files.items() if n > MAX_LINES}
    assert not long, long


def _c_function_body(text: str, name: str) -> str:
    """The body of the C function ``name`` (from its definition's opening brace to the
    matching close)."""
    start = re.search(r"\b" + name + r"\([^;{]*\)\s*\{", text)
    assert start, name
    depth, i = 0, start.end() - 1
    for j in range(i, len(text)):
        depth += {"{": 1, "}": -1}.get(text[j], 0)
        if depth == 0:
            return text[i:j + 1]
    raise AssertionError(name)


# the caps on the C a reviewer reads: preprocessor conditionals in c_runtime/ (include
# guards counted), lines of any C function of c_runtime/ or rendered by templates/ (signature
# to closing brace)
MAX_RUNTIME_CONDITIONALS = 60
MAX_C_FUNCTION_LINES = 80
_CONDITIONAL = re.compile(r"^\s*#\s*(?:if|ifdef|ifndef|elif)\b", re.M)


def _c_functions(text: str) -> dict[str, int]:
    """Every function defined in C text: name -> its lines, signature to closing brace
    (comments and preprocessor lines do not open or close anything)."""
    t = re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)
    t = "\n".join("" if ln.lstrip().startswith("#") else ln for ln in t.splitlines())
    out: dict[str, int] = {}
    depth, start = 0, 0          # start: where the current top-level declaration began
    for i, c in enumerate(t):
        if c == ";" and depth == 0:
            start = i + 1
        elif c == "{":
            head = t[start:i]
            m = re.search(r"(\w+)\s*\([^;{}]*\)\s*$", head)
            if depth == 0 and m and "=" not in head:
                body = _c_function_body(t[start:], m.group(1))
                out[m.group(1)] = head.lstrip().count("\n") + body.count("\n") + 1
            depth += 1
        elif c == "}":
            depth -= 1
            start = i + 1 if depth == 0 else start
    return out


def _rendered_c() -> dict[str, str]:
    """The C the templates render for models that have every feature between them: tables
    over temperature with both branches, every diagnose effect, an ageing law and (or) the
    surface SOC, searched and uniform grids; both numerics, both dt modes; the estimator with
    every option (the offset state, the OCV's secant, the error memory)."""
    from dataclasses import replace

    from ecmgen.c.codegen import prepare, render
    from ecmgen.c.estc import prepare_estimator
    from ecmgen.config import EstimatorConfig
    from ecmgen.model.ageing import AgeingLaw
    from test_codegen_helpers import temperature_model
    from test_estimate import ALL_EFFECTS, model_over_temperature

    law = AgeingLaw([0.0, 400.0], [1.0, 1.2], [1.0, 0.9], "a test law")
    models = {"effects_aged": replace(model_over_temperature(effects=ALL_EFFECTS), ageing=law),
              "effects_surface": replace(model_over_temperature(effects=ALL_EFFECTS),
                                         surface_soc_gain=0.5),
              "searched": replace(temperature_model(4, 10, seed=5, branches=True),
                                  ageing=law, surface_soc_gain=0.7).with_effects(ALL_EFFECTS)}
    out = {}
    for name, model in models.items():
        for numeric in ("float", "fixed"):
            for dt_s in (None, 0.1):
                spec = prepare(model, numeric=numeric, dt_s=dt_s, prefix=name)
                est = None
                if numeric == "float" and dt_s is None:
                    est = prepare_estimator(model, spec, EstimatorConfig(
                        offset_state=True, ocv_slope_spread=0.5, error_memory_s=60.0))
                for file, text in render(spec, None, est).items():
                    if file.endswith((".c", ".h")) and not file.startswith("ecmrt"):
                        out[f"{file} ({'vdt' if dt_s is None else 'dt'})"] = text
    return out


def test_c_runtime_conditionals_and_c_function_lengths_are_capped():
    """The features of a model are chosen when its C is generated, not by #if: c_runtime/
    holds at most 60 preprocessor conditionals (include guards and the compiler checks), and
    no C function, hand-written or rendered, is over 80 lines."""
    runtime = {p.name: p.read_text() for p in sorted((REPO / "c_runtime").glob("*.h"))}
    ifs = {name: len(_CONDITIONAL.findall(text)) for name, text in runtime.items()}
    assert sum(ifs.values()) <= MAX_RUNTIME_CONDITIONALS, ifs
    files = {**runtime, **_rendered_c()}
    functions = {f"{name}:{fn}": n for name, text in files.items()
                 for fn, n in _c_functions(text).items()}
    assert len(functions) > 100 and "ecmrt_est_f32_joseph" in " ".join(functions)
    long = {k: n for k, n in functions.items() if n > MAX_C_FUNCTION_LINES}
    assert not long, long


@pytest.mark.parametrize("numeric", ["float", "fixed"])
def test_the_step_calls_each_effect_as_a_unit(numeric):
    """Each effect is a unit of its own in the runtime, which the generated step of a model
    that has it calls (once), and that of a model without it does not name."""
    from ecmgen.c.codegen import prepare, render
    from test_estimate import ALL_EFFECTS, model_over_temperature

    s = "f32" if numeric == "float" else "q"
    runtime = (REPO / "c_runtime" / f"ecmrt_{s}_step.h").read_text()
    units = [f"ecmrt_{s}_fx_cdr", f"ecmrt_{s}_fx_arr", f"ecmrt_{s}_fx_hyst", f"ecmrt_{s}_bv"]
    for unit in units:
        assert re.search(rf"^static inline \w+ {unit}\(", runtime, re.M), unit
    with_fx = render(prepare(model_over_temperature(effects=ALL_EFFECTS), numeric=numeric))
    plain = render(prepare(model_over_temperature(diffusion=False, butler_volmer=False),
                           numeric=numeric))
    step = _c_function_body(with_fx[f"ecm_ecm_{s}.c"], f"ecm_step_{s}")
    assert all(step.count(f"{unit}(") == 1 for unit in units), step
    assert "s->u_x" in step and "s->u_diff" in step
    assert not any(unit in plain[f"ecm_ecm_{s}.c"] for unit in units)
    assert "u_x" not in plain[f"ecm_ecm_{s}.c"] and "u_diff" not in plain[f"ecm_ecm_{s}.c"]


def _layout_rows() -> dict[str, str]:
    """docs/layout.md's table of subpackages: package ("ecmgen" for the top level) -> the
    text of its row."""
    rows = {}
    for line in (REPO / "docs" / "layout.md").read_text().splitlines():
        m = re.match(r"\| (?:`(\w+)/`|top level) \|", line)
        if m:
            rows["ecmgen" + (f".{m.group(1)}" if m.group(1) else "")] = line
    return rows


def test_layout_md_names_every_module():
    """A subpackage has its row; a module is named (`name`) in its package's row."""
    rows = _layout_rows()
    assert {"ecmgen", "ecmgen.data", "ecmgen.c", "ecmgen.cli"} <= set(rows), sorted(rows)
    missing = []
    for name, path in _modules().items():
        if name == "ecmgen":
            continue
        package, _, leaf = name.rpartition(".")
        if _is_package(path):
            if name not in rows:
                missing.append(f"{name} (no row `{leaf}/`)")
        elif f"`{leaf}`" not in rows.get(package, ""):
            missing.append(name)
    assert not missing, "docs/layout.md does not name: " + ", ".join(missing)


def test_layout_md_says_which_code_mirrors_which():
    """The mirrors' table names files that exist (a renamed file shows here)."""
    text = (REPO / "docs" / "layout.md").read_text()
    table = text[text.index("## Which code mirrors which"):]
    named = set(re.findall(r"`((?:c_runtime|templates|tests|model|c|estimate)/[\w.]+)`", table))
    assert {"model/simulate.py", "c/cref.py", "c_runtime/ecmrt_f32.h",
            "c_runtime/ecmrt_f32_step.h", "c_runtime/ecmrt_q_step.h", "templates/ecm_step_f32.c.j2",
            "templates/ecm_step_q.c.j2", "estimate/process.py", "c/estref.py",
            "c_runtime/ecmrt_est_f32.h", "templates/est_model.c.j2"} <= named, named
    gone = [n for n in sorted(named)
            if not ((REPO / n).exists() or (SRC / n).exists())]
    assert not gone, gone


def test_the_top_level_holds_few_modules():
    """At most ten modules beside the subpackages (the stages live in subpackages; a
    module at the top is shared by all, or the build chain)."""
    top = sorted(p.stem for p in SRC.glob("*.py") if p.stem != "__init__")
    assert len(top) <= 10, top


def test_no_python_function_over_80_lines_without_a_reason():
    """A function over 80 lines says why in a docstring line that starts with "Long:"."""
    long = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                    node.end_lineno - node.lineno + 1 > 80:
                doc = ast.get_docstring(node) or ""
                if not any(line.strip().startswith("Long:") for line in doc.splitlines()):
                    long.append(f"{name}.{node.name} ({node.end_lineno - node.lineno + 1})")
    assert not long, long
