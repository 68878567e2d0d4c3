"""The installed package (wheel, sdist), not only the editable checkout, generates C.

``templates/`` and ``c_runtime/`` sit at the top of the repository; pyproject.toml maps
them into the package as ``ecmgen/templates`` and ``ecmgen/c_runtime``. The slow test
builds the sdist and, from it, the wheel (``python -m build``, as a release would), installs
the wheel with its dependencies into a fresh virtual environment outside the source tree
and runs ``ecmgen build`` with C on a copy of the bundled example.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
import tomllib
import zipfile
from pathlib import Path

import pytest

from conftest import REPO
from ecmgen.c.codegen import file_names

EXAMPLE = REPO / "examples" / "panasonic-25degC"
# what a wheel is built from: everything else in the checkout (tests, examples, bench) is
# left behind, so nothing can be found in the source tree by accident
SOURCES = ("pyproject.toml", "README.md", "src", "templates", "c_runtime")
DATA_DIRS = ("templates", "c_runtime")


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_pyproject_lists_every_subpackage_and_data_dir():
    """The package list is explicit (it maps the two data folders), so a new subpackage
    must be added to it; and the package-data globs must cover every file of the folders."""
    st = _pyproject()["tool"]["setuptools"]
    src = REPO / "src"
    found = {".".join(p.parent.relative_to(src).parts) for p in src.rglob("__init__.py")}
    assert set(st["packages"]) == found | {f"ecmgen.{d}" for d in DATA_DIRS}
    for d in DATA_DIRS:
        assert st["package-dir"][f"ecmgen.{d}"] == d
        globs = st["package-data"][f"ecmgen.{d}"]
        files = [p for p in (REPO / d).iterdir() if p.is_file()]
        assert files
        assert all(any(p.match(g) for g in globs) for p in files), d


def test_codegen_finds_the_packaged_folders_first(tmp_path, monkeypatch):
    """In an installed package the folders sit inside ecmgen/ (the checkout's are not there)."""
    import ecmgen.c.runtime as codegen

    pkg = tmp_path / "site" / "ecmgen"
    for d in DATA_DIRS:
        (pkg / d).mkdir(parents=True)
    (pkg / "c").mkdir()
    monkeypatch.setattr(codegen, "__file__", str(pkg / "c" / "runtime.py"))
    assert codegen.templates_dir() == pkg / "templates"
    assert codegen.runtime_dir() == pkg / "c_runtime"
    shutil.rmtree(pkg / "templates")
    with pytest.raises(FileNotFoundError, match="templates"):
        codegen.templates_dir()


def _copy_sources(dest: Path) -> Path:
    dest.mkdir()
    skip = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.so", "*.pyc")
    for name in SOURCES:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=skip)
        else:
            shutil.copy2(src, dest / name)
    return dest


def _run(cmd, cwd, timeout=900) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONWARNINGS")}
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd}\nstdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-3000:]}"
    return r


@pytest.mark.slow
def test_wheel_in_a_fresh_venv_generates_c(tmp_path):
    src = _copy_sources(tmp_path / "checkout")
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "build", "--outdir", dist, src], tmp_path)
    sdist = next(dist.glob("ecmgen-*.tar.gz"))
    wheel = next(dist.glob("ecmgen-*.whl"))          # built from the sdist
    with tarfile.open(sdist) as tf:
        in_sdist = {Path(*Path(n).parts[1:]).as_posix() for n in tf.getnames()}
    in_wheel = set(zipfile.ZipFile(wheel).namelist())
    for d in DATA_DIRS:
        for f in (REPO / d).iterdir():
            if f.is_file():
                assert f"{d}/{f.name}" in in_sdist
                assert f"ecmgen/{d}/{f.name}" in in_wheel

    venv = tmp_path / "venv"
    try:
        _run([sys.executable, "-m", "venv", venv], tmp_path)
        py = venv / "bin" / "python"
        _run([py, "-m", "pip", "install", "--quiet", wheel], tmp_path)
        where = _run([py, "-c", "import ecmgen.c.codegen as c; "
                                "print(c.__file__); print(c.templates_dir()); "
                                "print(c.runtime_dir())"], tmp_path).stdout.split()
        assert all(Path(w).is_relative_to(venv) for w in where), where

        # the example, trimmed to one quick method (LM) and one cycle
        ex = tmp_path / "example"
        ex.mkdir()
        for name in ("hppc.mat", "us06.mat"):
            shutil.copy2(EXAMPLE / name, ex / name)
        cfg = (EXAMPLE / "config.toml").read_text()
        cfg = cfg.replace('extra_cycles = ["hwfet-a.mat"]', "")
        cfg = cfg.replace('methods = ["ga", "lm", "curve"]', 'methods = ["lm"]')
        cfg = cfg.replace('best = "curve"', 'best = "lm"')
        cfg = cfg[:cfg.index("[diagnose]")]
        assert 'methods = ["lm"]' in cfg and "hwfet" not in cfg
        (ex / "config.toml").write_text(cfg)
        r = _run([venv / "bin" / "ecmgen", "build", ex / "config.toml", "--out", tmp_path / "out",
                  "--json", "--quiet"], tmp_path)
        assert r.stderr == ""
        result = json.loads(r.stdout)
        for numeric in ("float", "fixed"):
            assert result["c"][numeric]["bit_exact_vs_reference"] is True
            src = file_names("pan18650pf", numeric)["source"]
            assert (tmp_path / "out" / "c" / numeric / src).is_file()
            # the generated equivalence test, with the wheel alone, outside the source tree
            test = tmp_path / "out" / "c" / numeric / f"test_{src[:-2]}_equivalence.py"
            r = _run([py, test], tmp_path)
            assert r.stdout.strip().endswith("equivalent to the golden vectors"), r.stdout
        r = _run([venv / "bin" / "ecmgen", "verify", tmp_path / "out"], tmp_path)
        assert r.stdout.splitlines()[-1] == "ecmgen verify: 2 of 2 passed", r.stdout
        assert (tmp_path / "out" / "c" / "float" / "ecmrt_f32.h").read_text() == \
            (REPO / "c_runtime" / "ecmrt_f32.h").read_text()
    finally:
        shutil.rmtree(venv, ignore_errors=True)     # about 600 MB of dependencies
