"""Places no output can go are one line and exit 2, not a traceback: an --out (or --plot)
that is a symbolic link loop, a standard output that is full, a device or pipe given as an
output file (which the write's rename would replace)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO
from test_codegen_helpers import realistic_model


def _cli(*args, stdout=subprocess.PIPE, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          stdout=stdout, stderr=subprocess.PIPE, text=True, cwd=cwd,
                          timeout=300)


@pytest.fixture
def files(cell_files, tmp_path):
    for f in cell_files.iterdir():
        (tmp_path / f.name).write_bytes(f.read_bytes())
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\n'
                   'ocv = "ocv.csv"\ncycle = "cycle.csv"\n[fit]\nmethods = ["lm"]\n'
                   '[diagnose]\n')
    loop = tmp_path / "loop"
    os.symlink(loop, loop)
    return tmp_path, cfg, loop


def _one_line(res, *words):
    assert res.returncode == 2, (res.returncode, res.stderr)
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr, res.stderr
    for w in words:
        assert w in res.stderr, (w, res.stderr)


def test_a_symlink_loop_as_out_is_one_line(files):
    d, cfg, loop = files
    model, cycle = d / "model.json", d / "cycle.csv"
    for args in (["build", cfg, "--out", loop], ["fit", cfg, "--out", loop],
                 ["diagnose", cfg, "--out", loop], ["codegen", model, "--out", loop],
                 ["dcir", d / "pulses.csv", "--capacity-ah", "2.9", "--out", loop],
                 ["validate", model, cycle, "--plot", loop],
                 ["estimate", model, cycle, "--out", loop],
                 ["build", cfg, "--out", loop / "inside"]):
        _one_line(_cli(*args), "loop", "symbolic link")


def test_a_full_standard_output_is_one_line(files, tmp_path):
    """`config --explain > /dev/full` and the others: before, an OSError traceback."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    d, cfg, _ = files
    model = realistic_model(n_rc=6).save(tmp_path / "m.json")
    with open("/dev/full", "w") as full:
        for args in (["config", "--explain"], ["validate", d / "model.json", d / "cycle.csv",
                                               "--json"],
                     ["dcir", d / "pulses.csv", "--capacity-ah", "2.9"],
                     ["codegen", model, "--out", tmp_path / "c"]):
            _one_line(_cli(*args, stdout=full), "standard output", "No space left")


def test_a_pipe_given_as_an_output_file_is_refused(files):
    d, cfg, _ = files
    fifo = d / "fifo"
    os.mkfifo(fifo)
    res = _cli("dcir", d / "pulses.csv", "--capacity-ah", "2.9", "--out", fifo)
    _one_line(res, "not a regular file")
    assert fifo.exists() and not fifo.is_file()
