"""Outputs never replace an input, never keep an earlier model's files beside a new one,
never stay half-written or staged; a C prefix is checked whole and against the runtime's
symbols, and a C that fails its compile check fails the build."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO
from ecmgen.cli import main
from ecmgen.outputs import MANIFEST, STAGING_PREFIX

CONFIG = ('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\nocv = "ocv.csv"\n'
          'cycle = "cycle.csv"\n[fit]\nmethods = ["lm"]\nrelax_s = 900\n')


@pytest.fixture
def project(tmp_path, cell_files):
    for f in cell_files.iterdir():
        shutil.copy(f, tmp_path / f.name)
    cfg = tmp_path / "cell.toml"
    cfg.write_text(CONFIG + '[c]\nnumeric = ["float"]\n')
    return tmp_path, cfg


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ecmgen: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in err, (w, err)
    return err


# --------------------------------------------------------------------------- inputs

@pytest.mark.parametrize("target", ["cell.toml", "cycle.csv", "ocv.csv"])
def test_dcir_config_out_refuses_every_file_the_config_names(project, capsys, target):
    """Before: `dcir --config cell.toml --out cell.toml` exited 0 and the config became a
    CSV; only the pulse file itself was checked."""
    folder, cfg = project
    before = snapshot(folder)
    assert main(["dcir", "--config", str(cfg), "--out", str(folder / target), "-q"]) == 2
    one_line_error(capsys, target, "input")
    assert snapshot(folder) == before


@pytest.mark.parametrize("argv", [
    ["validate", "model.json", "cycle.csv", "--plot", "cycle.csv"],
    ["validate", "model.json", "cycle.csv", "--config", "cell.toml", "--plot", "ocv.csv"],
    ["estimate", "model.json", "cycle.csv", "--config", "cell.toml", "--out", "pulses.csv"],
    ["fit", "cell.toml", "--out", "ocv.csv"],
    ["codegen", "model.json", "--out", "."],    # writes <prefix>_ecm.* only: allowed
])
def test_every_command_checks_its_output_against_its_inputs(project, capsys, monkeypatch, argv):
    folder, _ = project
    monkeypatch.chdir(folder)
    before = snapshot(folder)
    code = main(argv + ["--quiet"])
    if argv[0] == "codegen":
        assert code == 0
        assert {k: v for k, v in snapshot(folder).items() if k in before} == before
        return
    assert code == 2
    one_line_error(capsys, "input")
    assert snapshot(folder) == before


def test_out_an_existing_file_is_refused_before_the_fit(project, capsys, monkeypatch):
    """Before: a FileExistsError traceback after the whole fit."""
    import ecmgen.pipeline

    folder, cfg = project
    (folder / "afile").write_text("mine")

    def no_fit(*a, **k):
        raise AssertionError("the fit ran before the output was checked")

    monkeypatch.setattr(ecmgen.pipeline, "fit_all", no_fit)
    assert main(["build", str(cfg), "--out", str(folder / "afile"), "-q"]) == 2
    one_line_error(capsys, "afile", "existing file")
    assert (folder / "afile").read_text() == "mine"


def test_out_where_nothing_can_be_written_is_one_line(project, capsys):
    folder, cfg = project
    (folder / "plain").write_text("x")
    assert main(["fit", str(cfg), "--out", str(folder / "plain" / "m.json"), "-q"]) == 2
    one_line_error(capsys, "not a folder")


# --------------------------------------------------------------------------- reused --out

def test_reused_out_keeps_no_file_of_the_earlier_build(project, capsys):
    """Before: the second build left c/float beside a model.json with another hash."""
    folder, cfg = project
    out = folder / "out"
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots"]) == 0
    first = snapshot(out)
    assert any(k.startswith("c/float/") for k in first) and MANIFEST in first
    manifest = json.loads(first[MANIFEST])
    assert set(manifest["files"]) == set(first) - {MANIFEST}
    (out / "notes.txt").write_text("my own notes")          # not ecmgen's: stays
    (out / "c" / "float" / "ecm_ecm_f32_report.md").write_text("edited")   # changed: stays
    cfg.write_text(CONFIG.replace("relax_s = 900", "relax_s = 600") + '[c]\nnumeric = []\n')
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots"]) == 0
    second = snapshot(out)
    assert not [k for k in second if k.startswith("c/") and not k.endswith("report.md")]
    assert second["notes.txt"] == b"my own notes"
    assert second["c/float/ecm_ecm_f32_report.md"] == b"edited"
    manifest = json.loads(second[MANIFEST])
    assert manifest["kept_changed"] == ["c/float/ecm_ecm_f32_report.md"]
    assert set(manifest["files"]) == set(second) - {MANIFEST, "notes.txt",
                                                    "c/float/ecm_ecm_f32_report.md"}


def test_a_manifest_naming_paths_outside_out_removes_nothing_there(project):
    folder, cfg = project
    out = folder / "out"
    out.mkdir()
    victim = folder / "victim.txt"
    victim.write_text("keep")
    from ecmgen.files import file_sha256

    (out / MANIFEST).write_text(json.dumps({"files": {
        "../victim.txt": file_sha256(victim), str(victim): file_sha256(victim)}}))
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots", "--no-c"]) == 0
    assert victim.read_text() == "keep"


# --------------------------------------------------------------------------- staging

def staging_folders(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.startswith(STAGING_PREFIX))


def test_sigterm_during_the_write_leaves_no_staging_folder(project, monkeypatch):
    """Before: SIGTERM killed the build with its staging folder (up to 18 files) left
    beside --out; now it unwinds, removes it, and exits 143."""
    import ecmgen.report

    folder, cfg = project
    real = ecmgen.report.write_build_report

    def terminated(*a, **k):
        real(*a, **k)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(ecmgen.report, "write_build_report", terminated)
    assert main(["build", str(cfg), "--out", str(folder / "out"), "-q", "--no-plots"]) == 143
    assert staging_folders(folder) == [] and not (folder / "out").exists()
    assert signal.getsignal(signal.SIGTERM) is not None     # the handler was put back


def test_next_run_removes_staging_left_by_a_killed_process(project):
    folder, cfg = project
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    from ecmgen.outputs import _host

    left = folder / f"{STAGING_PREFIX}{dead}@{_host()}-abc"
    (left / "c").mkdir(parents=True)
    (left / "model.json").write_text("{}")
    alive = folder / f"{STAGING_PREFIX}{os.getppid()}@{_host()}-def"   # a running process's
    alive.mkdir()
    elsewhere = folder / f"{STAGING_PREFIX}{dead}@another.host-ghi"    # not ours to judge
    elsewhere.mkdir()
    assert main(["build", str(cfg), "--out", str(folder / "out"), "-q", "--no-plots",
                 "--no-c"]) == 0
    assert staging_folders(folder) == sorted([alive, elsewhere])   # by name, not pid


# --------------------------------------------------------------------------- C prefix

def runtime_symbols() -> set[str]:
    """The names the runtime headers define at file scope: macros (less those they
    #undef again), typedef names and functions (declared from column 0)."""
    names = set()
    for h in (REPO / "c_runtime").glob("*.h"):
        text = h.read_text()
        macros = set(re.findall(r"^#\s*define\s+(\w+)", text, re.M))
        macros -= set(re.findall(r"^#\s*undef\s+(\w+)", text, re.M))
        names |= macros
        names |= set(re.findall(r"^}\s*(\w+)\s*;", text, re.M))
        names |= set(re.findall(r"^(?:static\s+)?(?:inline\s+)?(?:const\s+)?\w+[\s*]+(\w+)\s*\(",
                                text, re.M))
    return names


def test_every_runtime_symbol_is_in_the_namespace_prefixes_may_not_use():
    """The prefix check refuses names beginning with "ecmrt"; that covers every runtime
    symbol only while each of them begins so."""
    from ecmgen.config import C_RUNTIME_NAMESPACE

    names = runtime_symbols()
    assert len(names) > 50 and "ecmrt_f32_count" in names and "ecmrt_q_grid_t" in names
    outside = sorted(n for n in names if not n.lower().startswith(C_RUNTIME_NAMESPACE))
    assert outside == []


@pytest.mark.parametrize("prefix", ["ecmrt_f32", "ecmrt_q", "ECMRT", "ecm\n", "ecm\n ",
                                    "a-b", "1ecm", "x" * 33, "int", ""])
def test_bad_prefixes_are_refused_by_config_and_codegen(project, capsys, prefix):
    """Before: "ecmrt_f32" built C that failed its own compile check (exit 0), and
    "ecm\\n" passed a `$`-anchored regex into file names."""
    folder, cfg = project
    cfg.write_text(CONFIG + f"[c]\nprefix = {json.dumps(prefix)}\n")
    assert main(["build", str(cfg), "--out", str(folder / "out"), "-q", "--no-plots"]) == 2
    one_line_error(capsys, "prefix")
    assert main(["codegen", str(folder / "model.json"), "--out", str(folder / "c"),
                 "--prefix", prefix, "-q"]) == 2
    one_line_error(capsys, "prefix")
    assert not (folder / "out").exists() and not (folder / "c").exists()


def test_a_failed_c_compile_check_fails_the_build(project, capsys, monkeypatch):
    """Before: the build exited 0 and only --json said "skipped": "compile failed"."""
    folder, cfg = project
    monkeypatch.setenv("CC", "false")          # a compiler that fails every file
    monkeypatch.setenv("ECMGEN_CACHE", str(folder / "cache"))
    assert main(["build", str(cfg), "--out", str(folder / "out"), "-q", "--no-plots"]) == 2
    one_line_error(capsys, "compile check")
    assert not (folder / "out").exists() and staging_folders(folder) == []


def test_no_compiler_still_skips_the_check(project, capsys, monkeypatch):
    folder, cfg = project
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("PATH", str(folder))               # no cc on the PATH either
    monkeypatch.setenv("ECMGEN_CACHE", str(folder / "cache"))
    assert main(["build", str(cfg), "--out", str(folder / "out"), "-q", "--no-plots",
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "no C compiler" in doc["c"]["float"]["skipped"]


def test_two_commits_into_one_folder_take_turns(tmp_path):
    """A second build committing into the same --out waits for the first: the files and
    the manifest of the two never interleave."""
    import fcntl
    import threading

    from ecmgen.outputs import staged

    out = tmp_path / "out"
    out.mkdir()
    order = []
    fd = os.open(out, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)          # a first build in the middle of its commit

    def second():
        with staged(out, set()) as (staging, files):
            (staging / "model.json").write_text("second")
        order.append("second")

    worker = threading.Thread(target=second)
    worker.start()
    worker.join(timeout=0.2)
    assert worker.is_alive() and order == []        # waiting for the lock
    order.append("first")
    os.close(fd)
    worker.join()
    assert order == ["first", "second"] and (out / "model.json").read_text() == "second"
