"""Where the templates and the hand-written C runtime are.

The runtime has no compile-time switches: what a model has is chosen when its C is
generated (:data:`ecmgen.c.spec.SWITCHES`), its tables' struct, state fields and unit calls
rendered by the templates.
"""

from __future__ import annotations

from pathlib import Path


def _find_dir(name: str) -> Path:
    """templates/ and c_runtime/: inside the installed package (a wheel or sdist carries
    them as ecmgen/templates and ecmgen/c_runtime, see pyproject.toml), else at the
    repository root (an editable install of a checkout, src/ecmgen -> ../../)."""
    here = Path(__file__).resolve().parents[1]    # the ecmgen package (this is ecmgen/c/)
    for cand in (here / name, here.parents[1] / name):
        if cand.is_dir():
            return cand
    raise FileNotFoundError(f"ecmgen: {name}/ not found (looked in {here} and "
                            f"{here.parents[1]}): a broken installation")


def templates_dir() -> Path:
    return _find_dir("templates")


def runtime_dir() -> Path:
    return _find_dir("c_runtime")
