"""Where the templates and the hand-written C runtime are, and the runtime's switch list.

The compile-time switches (``ECMRT_<name>``, each 0 or 1) are listed once, in
``c_runtime/ecmrt_config.h``; :data:`SWITCHES` is read from there, so the generator, the
runtime headers and the tests' hand-written configurations cannot drift apart.
"""

from __future__ import annotations

import functools
import re
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


@functools.lru_cache(maxsize=None)
def switches() -> tuple[str, ...]:
    """The switch names (without ``ECMRT_``) in ecmrt_config.h's order: the ``defined()``
    checks after its "the switches" comment."""
    text = (runtime_dir() / "ecmrt_config.h").read_text()
    block = text[text.index("/* the switches"):]
    block = block[:block.index("#error")]
    return tuple(re.findall(r"defined\(ECMRT_(\w+)\)", block)) + optional_switches()


@functools.lru_cache(maxsize=None)
def optional_switches() -> tuple[str, ...]:
    """The switches ecmrt_config.h sets to 0 when a config leaves them out (the generator
    writes them only when 1): the ``defined()`` checks after its "the optional switches"
    comment."""
    text = (runtime_dir() / "ecmrt_config.h").read_text()
    block = text[text.index("/* the optional switches"):]
    return tuple(re.findall(r"!defined\(ECMRT_(\w+)\)", block))
