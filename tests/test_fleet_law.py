"""`ecmgen age`: the ageing law of a synthetic study (ecmgen.diagnosis.synthstudy, known
truth) recovered from its fleet table within stated bounds, written into a model the C
takes; bad input is one line. The rows are built one after the other here (no Dask: the
fleet's own run is tested in test_fleet.py), and the table is written as `ecmgen fleet`
writes it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, built_once
from ecmgen.diagnosis.synthstudy import make_study, read_truth, write_study
from ecmgen.fleet import Options, read_manifest, run_row, write_fleet_table
from ecmgen.model import load_model

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """5 cells x 3 check-ups (200 cycles apart; the last cell ages 3x faster)."""
    def build(folder):
        manifest = write_study(make_study(cells=5, checkups=3, seed=2), folder,
                               with_cycle=False)
        rows = read_manifest(manifest)
        for row in rows:
            assert run_row(row, folder / "fleet",
                           Options(plots=False, c_code=False)).status == "built"
        write_fleet_table(rows, folder / "fleet", parquet=False, plots=False)

    folder = built_once(tmp_path_factory, "fleet-law-study", build)
    return folder / "fleet", read_truth(folder / "truth.csv")


def age(*args):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", "age", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO, timeout=120)


def test_the_law_against_the_truth(fleet, tmp_path):
    """Per check-up the median over the cells of each one's true ratio to its first
    check-up (a cell's resistances all scale alike): the resistance scale, a parameter of
    the model, within the spec's 5 % on known-truth data; the capacity scale, a ratio of two
    C/10 capacity tests sampled every 30 s, within one sample's charge on each count."""
    out, truth = fleet
    res = age(out, "--out", tmp_path / "aged.json")
    assert res.returncode == 0, res.stderr
    assert "cell01/0/model.json" in res.stdout and "wrote" in res.stdout, res.stdout
    model = load_model(tmp_path / "aged.json")
    base = load_model(out / "cell01" / "0" / "model.json")
    assert model.to_json().startswith(base.to_json()[:200])      # the base, with a law
    law = model.ageing
    assert list(law.equivalent_full_cycles) == [0.0, 200.0, 400.0]
    true = {(t["cell"], t["checkup"]): t for t in truth}
    cells = sorted({t["cell"] for t in truth})
    errors = []
    for k, r_got, q_got in zip("012", law.resistance_scale, law.capacity_scale):
        r_true = np.median([true[(c, k)]["r0_soc50_ohm"] / true[(c, "0")]["r0_soc50_ohm"]
                            for c in cells])
        q_true = np.median([true[(c, k)]["capacity_ah"] / true[(c, "0")]["capacity_ah"]
                            for c in cells])
        errors.append((k, r_got - r_true, q_got - q_true))
        assert r_got == pytest.approx(r_true, rel=0.05), errors
        assert q_got == pytest.approx(q_true, abs=2 * 0.1 * 30.0 / 3600.0), errors
    print("law - truth per check-up (resistance, capacity):", errors)


def test_a_given_base_and_bad_input(fleet, tmp_path):
    out, _ = fleet
    base = out / "cell02" / "1" / "model.json"
    res = age(out, "--out", tmp_path / "aged.json", "--base", base)
    assert res.returncode == 0, res.stderr
    assert load_model(tmp_path / "aged.json").capacity_ah == load_model(base).capacity_ah
    for args, words in (((tmp_path, "--out", tmp_path / "x.json"), "fleet.csv: no such file"),
                        ((out, "--out", tmp_path / "x.json", "--base", tmp_path / "none.json"),
                         "none.json")):
        bad = age(*args)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr
        assert "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
