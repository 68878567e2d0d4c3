"""`ecmgen fleet` on a synthetic ageing study (ecmgen.diagnosis.synthstudy): the trends
it recovers against the truth, a run killed and resumed, a rerun that builds nothing, a
row with a broken file that fails alone; and a bad manifest refused before any work."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from ecmgen.cli import main
from ecmgen.diagnosis.synthstudy import make_study, read_truth, write_study

pytest.importorskip("distributed")

BROKEN = ("cell03", "1")          # its pulse test is replaced by a broken file


def fleet(*args, timeout=240):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", "fleet", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO, timeout=timeout)


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """6 cells x 3 check-ups (the last cell an outlier that ages 3x faster); one row's
    pulse test broken."""
    folder = tmp_path_factory.mktemp("study")
    manifest = write_study(make_study(cells=6, checkups=3, seed=1), folder)
    (folder / BROKEN[0] / BROKEN[1] / "pulses.csv").write_text(
        "time_s,current_a,voltage_v\n0,0,3.9\n1,-3,three point eight\n")
    return manifest


def records(out: Path) -> list[Path]:
    return sorted(out.glob("*/*/fleet-row.json"))


def test_fleet_killed_resumed_and_the_trends_against_the_truth(study, tmp_path):
    out = tmp_path / "fleet"
    # 1. killed (SIGTERM) after a few rows: it unwinds (exit 143), each row is whole or
    # not there
    proc = subprocess.Popen([sys.executable, "-m", "ecmgen.cli", "fleet", str(study),
                             "--out", str(out), "--workers", "2", "-q"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 180
    while len(records(out)) < 4 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 143, proc.communicate()
    done_before = len(records(out))
    assert 4 <= done_before < 17
    for r in records(out):
        assert (r.parent / "model.json").is_file()
    assert not (out / "fleet.csv").exists()

    # 2. resumed: only the rows not done are built; the broken one fails alone (exit 1)
    res = fleet(study, "--out", out, "--workers", "2", "--json")
    assert res.returncode == 1, res.stderr
    doc = json.loads(res.stdout)
    assert (doc["rows"], doc["failed"]) == (18, 1)
    assert doc["unchanged"] == done_before and doc["built"] == 17 - done_before
    failures = read_csv(out / "failures.csv")
    assert [(f["cell"], f["checkup"], f["kind"]) for f in failures] == [BROKEN + ("input",)]
    assert "pulses.csv" in failures[0]["error"] and "\n" not in failures[0]["error"]
    assert not list(out.glob("*/.ecmgen-staging-*")), "a killed build's staging is left"

    # 3. nothing changed: nothing is built, the table comes out byte-identical
    table = (out / "fleet.csv").read_bytes()
    models = {p: p.stat().st_mtime_ns for p in out.glob("*/*/model.json")}
    res = fleet(study, "--out", out, "--workers", "1", "--json", "--no-plots")
    assert res.returncode == 1, res.stderr
    doc = json.loads(res.stdout)
    assert (doc["built"], doc["unchanged"], doc["failed"]) == (0, 17, 1)
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/*/model.json")} == models
    assert (out / "fleet.csv").read_bytes() == table

    check_table_against_truth(out, read_truth(study.parent / "truth.csv"))


def check_table_against_truth(out: Path, truth: list[dict]):
    import pyarrow.parquet as pq

    rows = read_csv(out / "fleet.csv")
    assert len(rows) == 17 and not any((r["cell"], r["checkup"]) == BROKEN for r in rows)
    assert pq.read_table(out / "fleet.parquet").num_rows == 17
    assert pq.read_table(out / "fleet.parquet").column_names == list(rows[0])
    assert (out / "trends-tests.png").stat().st_size > 10_000
    true = {(t["cell"], t["checkup"]): t for t in truth}
    for r in rows:
        t = true[(r["cell"], r["checkup"])]
        assert float(r["cycles"]) == t["cycles"]
        # capacity from the C/10 test: within 0.5 %; R0 at 50 % SOC within 6 %
        assert float(r["capacity_ah"]) == pytest.approx(t["capacity_ah"], rel=0.005)
        assert float(r["r0_ohm_soc50_25c"]) == pytest.approx(t["r0_soc50_ohm"], rel=0.06)
        assert r["validation_mae_mv"] != ""
    # the trends per cell: R0 growth first -> last check-up within 0.06 of the true ratio,
    # capacity fade within 0.005
    for cell in sorted({r["cell"] for r in rows} - {BROKEN[0]}):
        got = {r["checkup"]: r for r in rows if r["cell"] == cell}
        want = {k: true[(cell, k)] for k in got}
        for col, tcol, tol in (("r0_ohm_soc50_25c", "r0_soc50_ohm", 0.06),
                               ("capacity_ah", "capacity_ah", 0.005)):
            ratio = float(got["2"][col]) / float(got["0"][col])
            assert ratio == pytest.approx(want["2"][tcol] / want["0"][tcol], abs=tol), (cell, col)
    # ageing.csv: each cell's rates per cycle, relative to its first check-up (linear
    # truth: (last / first - 1) / cycles), R0 within 0.01 % per cycle (true 0.04..0.13),
    # the capacity within 0.002 % per cycle (true -0.016..-0.07)
    rates = {(a["cell"], a["quantity"]): a for a in read_csv(out / "ageing.csv")}
    for cell in sorted({r["cell"] for r in rows} - {BROKEN[0]}):
        for q, tq, tol in (("r0_ohm_soc50_25c", "r0_soc50_ohm", 1e-4),
                           ("capacity_ah", "capacity_ah", 2e-5)):
            a, t0, t2 = rates[(cell, q)], true[(cell, "0")], true[(cell, "2")]
            want = (t2[tq] / t0[tq] - 1.0) / t2["cycles"]
            assert a["axis"] == "equivalent full cycles" and a["checkups"] == "3"
            assert float(a["relative_slope"]) == pytest.approx(want, abs=tol), (cell, q)
            assert (a["outlier"] == "true") == bool(t0["outlier"])
    # the outlier cell (3x the ageing) is marked on capacity and R0 at the later check-ups,
    # no other cell is
    for r in rows:
        marks = set(r["outliers"].split(";")) & {"capacity_ah", "r0_ohm_soc50_25c"}
        outlier = bool(true[(r["cell"], r["checkup"])]["outlier"]) and r["checkup"] != "0"
        assert marks == ({"capacity_ah", "r0_ohm_soc50_25c"} if outlier else set()), r


def test_a_bad_manifest_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "a.toml").write_text("[cell]\ncapacity_ah = 3\n")
    out = tmp_path / "out"
    cases = {
        "cell,config\nc1,a.toml\n": "no column 'checkup'",
        "cell,checkup,config,cycle\nc1,0,a.toml,5\n": "unknown column 'cycle' (did you mean 'cycles'?)",
        "cell,checkup,config\nc1,0,a.toml\nc1,0,a.toml\n": "line 3: cell 'c1' check-up '0' is already on line 2",
        "cell,checkup,config\nc1,0,missing.toml\n": "line 2: config 'missing.toml': no such file",
        "cell,checkup,config\nc1,0,\n": "line 2: no config",
        "cell,checkup,config\n../c1,0,a.toml\n": "line 2: cell '../c1' is not a plain folder name",
        "cell,checkup,config,cycles\nc1,0,a.toml,-5\n": "line 2: cycles must be a number >= 0",
        "cell,checkup,config,date\nc1,0,a.toml,27.11.2026\n": "line 2: date must be YYYY-MM-DD",
        "cell,checkup,config\n": "has a header but no rows",
    }
    for text, message in cases.items():
        manifest = tmp_path / "manifest.csv"
        manifest.write_text(text)
        assert main(["fleet", str(manifest), "--out", str(out), "-q"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"ecmgen: error: {manifest}: ") and message in err, err
        assert err.count("\n") == 1
        assert not out.exists()
    assert main(["fleet", str(manifest), "--out", str(out), "--soc", "1.5"]) == 2
    assert "--soc must be a finite number in [0, 1]" in capsys.readouterr().err


def test_a_row_is_built_again_exactly_when_an_input_changes(tmp_path):
    """run_row on its own (no cluster): the row's hash covers the config and every file
    it names by content, not by where the study lies."""
    from ecmgen.fleet import Options, read_manifest, run_row

    study = tmp_path / "study"
    write_study(make_study(cells=1, checkups=1, seed=2), study, with_cycle=False)
    row = read_manifest(study / "manifest.csv")[0]
    out = tmp_path / "out"
    assert run_row(row, out, Options()).status == "built"
    assert run_row(row, out, Options()).status == "unchanged"
    assert run_row(row, out, Options(c_code=False)).status == "built"     # another option
    moved = tmp_path / "moved"
    study.rename(moved)
    row = read_manifest(moved / "manifest.csv")[0]
    assert run_row(row, out, Options(c_code=False)).status == "unchanged"
    config = moved / "cell01" / "0" / "cell.toml"
    config.write_text(config.read_text() + "\n[report]\nmax_mae_mv = 40\n")
    assert run_row(row, out, Options(c_code=False)).status == "built"
    (moved / "cell01" / "0" / "capacity.csv").write_text("time_s,current_a,voltage_v\n")
    failed = run_row(row, out, Options(c_code=False))
    assert (failed.status, failed.kind) == ("failed", "input")
    assert "capacity.csv" in failed.error
    assert not (out / "cell01" / "0" / "fleet-row.json").exists()
    assert np.isfinite(failed.seconds)


def test_a_running_cluster_by_its_address(tmp_path, monkeypatch, capsys):
    """--scheduler: the rows run on the cluster at that address; an address where no
    scheduler answers is one line, exit 2, nothing written."""
    import ecmgen.fleet.run as run
    from distributed import LocalCluster

    study = tmp_path / "study"
    manifest = write_study(make_study(cells=1, checkups=2, seed=3), study, with_cycle=False)
    with LocalCluster(n_workers=1, processes=False,
                      dashboard_address=run.LOCAL_HTTP) as cluster:
        assert main(["fleet", str(manifest), "--out", str(tmp_path / "out"), "-q",
                     "--scheduler", cluster.scheduler_address, "--no-plots"]) == 0
    assert "2 rows: 2 built, 0 unchanged, 0 failed" in capsys.readouterr().out
    assert len(read_csv(tmp_path / "out" / "fleet.csv")) == 2
    monkeypatch.setattr(run, "CONNECT_TIMEOUT_S", 0.5)
    assert main(["fleet", str(manifest), "--out", str(tmp_path / "none"), "-q",
                 "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ecmgen: error: --scheduler tcp://127.0.0.1:9: no Dask scheduler "
                          "answers there") and err.count("\n") == 1
    assert not (tmp_path / "none").exists()


def test_the_local_cluster_holds_no_fixed_port(recwarn):
    """The fleet's own cluster serves HTTP on an ephemeral port of this machine only: not
    Dask's default :8787 on every interface, which another cluster may hold (a warning)."""
    import socket

    import ecmgen.fleet.run as run

    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
    except OSError:
        holder.close()
        pytest.skip("port 8787 is taken on this machine already")
    holder.listen()
    try:
        with run._client(None, 1) as (client, _):
            server = client.cluster.scheduler.http_server      # tornado's HTTPServer
            host, port = next(iter(server._sockets.values())).getsockname()[:2]
    finally:
        holder.close()
    assert host == "127.0.0.1" and port != 8787
    assert not [w for w in recwarn if "8787" in str(w.message)]
