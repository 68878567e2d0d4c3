"""No command loses a file it did not make, and none leaves results that are not its
own: an edited output written again is kept beside (``<name>.edited``), a commit that fails
part-way puts back what it replaced, the fleet and ``age`` never write onto what they read,
and a fleet row that fails leaves no earlier results behind. ``age`` takes each cell's
ratios over its own first check-up and refuses a resistance that is not positive."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO
from ecmgen.cli import main
from ecmgen.outputs import MANIFEST, staged
from test_codegen_helpers import realistic_model
from test_outputs import project, snapshot  # noqa: F401  (the fixture)


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO, timeout=timeout)


def test_a_rebuild_keeps_an_edited_report_and_model_beside(project, capsys):  # noqa: F811
    """Before: the second build replaced both and kept_changed stayed empty."""
    folder, cfg = project
    out = folder / "out"
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots"]) == 0
    (out / "report.md").write_text("my notes on this cell")
    (out / "model-lm.json").write_text('{"mine": true}')
    capsys.readouterr()
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots"]) == 0
    err = capsys.readouterr().err
    assert (out / "report.md.edited").read_text() == "my notes on this cell"
    assert (out / "model-lm.json.edited").read_text() == '{"mine": true}'
    assert (out / "report.md").read_text().startswith("#")          # the new report
    manifest = json.loads((out / MANIFEST).read_text())
    assert {"report.md.edited", "model-lm.json.edited"} <= set(manifest["kept_changed"])
    assert "report.md.edited" not in manifest["files"]
    assert "your version is kept as" in err and "report.md.edited" in err, err
    # a third build: ecmgen's own files replaced, the kept ones left alone
    assert main(["build", str(cfg), "--out", str(out), "-q", "--no-plots"]) == 0
    assert not (out / "report.md.edited-2").exists()
    assert (out / "report.md.edited").read_text() == "my notes on this cell"


def test_codegen_keeps_an_edited_c_and_other_prefixes(tmp_path):
    model = realistic_model(n_rc=8).save(tmp_path / "model.json")
    out = tmp_path / "c"
    assert _cli("codegen", model, "--out", out, "--prefix", "a", "-q").returncode == 0
    src = out / "a_ecm_f32.c"
    generated = src.read_text()
    src.write_text(generated + "/* my fix */\n")
    res = _cli("codegen", model, "--out", out, "--prefix", "a", "-q")
    assert res.returncode == 0, res.stderr
    assert src.read_text() == generated
    assert (out / "a_ecm_f32.c.edited").read_text().endswith("/* my fix */\n")
    assert "a_ecm_f32.c.edited" in res.stderr
    # a second model in the same folder: the first one's files stay
    assert _cli("codegen", model, "--out", out, "--prefix", "b", "-q").returncode == 0
    assert src.read_text() == generated and (out / "b_ecm_f32.c").is_file()


def test_a_commit_that_fails_part_way_puts_back_what_it_replaced(tmp_path, monkeypatch):
    """Before: the moves before the failing one stayed, new files beside the old ones."""
    import ecmgen.outputs as outputs

    out = tmp_path / "out"
    with staged(out, set()) as (staging, _):
        for name in ("model.json", "report.md", "z.png"):
            (staging / name).write_text(f"old {name}")
    before = snapshot(out)
    real = outputs.shutil.move

    def failing(src, dst):
        if Path(dst).name == "z.png" and Path(src).parent.name.startswith(".ecmgen-staging-"):
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(outputs.shutil, "move", failing)
    with pytest.raises(OSError):
        with staged(out, set()) as (staging, _):
            for name in ("model.json", "report.md", "z.png"):
                (staging / name).write_text(f"new {name}")
    assert snapshot(out) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".ecmgen-staging-")]


def test_fleet_refuses_to_write_onto_its_manifest(tmp_path):
    """`ecmgen fleet study/fleet.csv --out study` replaced the manifest with the table."""
    study = tmp_path / "study"
    study.mkdir()
    (study / "a.toml").write_text("[cell]\ncapacity_ah = 3\n")
    for name in ("fleet.csv", "failures.csv"):
        manifest = study / name
        manifest.write_text("cell,checkup,config\nc1,0,a.toml\n")
        res = _cli("fleet", manifest, "--out", study, "-q")
        assert res.returncode == 2, res.stderr
        assert res.stderr.count("\n") == 1 and "input" in res.stderr and name in res.stderr
        assert manifest.read_text() == "cell,checkup,config\nc1,0,a.toml\n"
        manifest.unlink()


# ------------------------------------------------------------------------------ age

def _fleet_dir(tmp_path, rows, write_models=True) -> Path:
    """A fleet folder as `ecmgen fleet` leaves it: fleet.csv and each row's model.json."""
    d = tmp_path / "fleet"
    d.mkdir()
    model = realistic_model(n_rc=8)
    cols = ["cell", "checkup", "cycles", "capacity_ah", "capacity_rel", "r0_ohm_soc50_25c",
            "outliers"]
    with open(d / "fleet.csv", "w", newline="") as f:
        w = csv.DictWriter(f, cols)
        w.writeheader()
        for r in rows:
            w.writerow({"outliers": "", **r})
            if write_models:
                model.save(d / r["cell"] / r["checkup"] / "model.json")
    return d


def _rows(cells, drop=()):
    """Cells ageing alike: R0 x1.1 and capacity x0.95 per 100 cycles; check-ups 0, 1, 2."""
    out = []
    for c in cells:
        for k in range(3):
            if (c, str(k)) in drop:
                continue
            out.append({"cell": c, "checkup": str(k), "cycles": 100 * k,
                        "capacity_ah": 3.0 * 0.95 ** k,
                        # capacity_rel as the table writes it: over the cell's first row
                        "capacity_rel": 0.95 ** (k - min(j for j in range(3)
                                                         if (c, str(j)) not in drop)),
                        "r0_ohm_soc50_25c": 0.02 * 1.1 ** k})
    return out


def test_age_leaves_out_cells_whose_first_checkup_failed(tmp_path):
    """Before: cells whose check-up 0 failed counted check-up 1 as their age 0 (x1.000,
    x1.000 there) and the base model was a 100-cycle one."""
    drop = {("c1", "0"), ("c2", "0"), ("c3", "0")}
    d = _fleet_dir(tmp_path, _rows(["c1", "c2", "c3", "c4", "c5"], drop))
    res = _cli("age", d, "--out", tmp_path / "aged.json")
    assert res.returncode == 0, res.stderr
    assert "c4/0/model.json" in res.stdout, res.stdout         # a fresh cell's model
    assert "c1, c2, c3" in res.stderr and "left out" in res.stderr, res.stderr
    from ecmgen.model import load_model

    law = load_model(tmp_path / "aged.json").ageing
    assert list(law.equivalent_full_cycles) == [0.0, 100.0, 200.0]
    assert law.resistance_scale[-1] == pytest.approx(1.21, rel=1e-9)
    assert law.capacity_scale[-1] == pytest.approx(0.9025, rel=1e-9)


def test_age_refuses_a_resistance_that_is_not_positive(tmp_path):
    rows = _rows(["c1", "c2"])
    rows[4]["r0_ohm_soc50_25c"] = -0.01
    d = _fleet_dir(tmp_path, rows)
    res = _cli("age", d, "--out", tmp_path / "aged.json")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "R0 must be positive" in res.stderr and "c2 check-up 1" in res.stderr
    assert not (tmp_path / "aged.json").exists()


def test_age_never_writes_onto_what_it_reads(tmp_path):
    """--out onto the fleet table, onto --base, onto the default base: one line, exit 2,
    nothing changed (before: each was overwritten, exit 0)."""
    d = _fleet_dir(tmp_path, _rows(["c1", "c2"]))
    other = tmp_path / "b.json"
    realistic_model(n_rc=8).save(other)
    before = {p: p.read_bytes() for p in [d / "fleet.csv", other, d / "c1" / "0" / "model.json"]}
    for args in (["--out", d / "fleet.csv"], ["--base", other, "--out", other],
                 ["--out", d / "c1" / "0" / "model.json"], ["--out", tmp_path]):
        res = _cli("age", d, *args)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr, res.stderr
        assert ".tmp" not in res.stderr, res.stderr      # not an internal temporary file
    assert {p: p.read_bytes() for p in before} == before


def test_age_on_a_binary_fleet_table_is_one_line(tmp_path):
    d = tmp_path / "fleet"
    d.mkdir()
    (d / "fleet.csv").write_bytes(bytes(range(256)) * 8)
    res = _cli("age", d, "--out", tmp_path / "aged.json")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "fleet.csv" in res.stderr and "Traceback" not in res.stderr


def test_a_fleet_row_that_fails_now_leaves_no_earlier_results(tmp_path):
    """Before: the row left the table, its old model.json, report.md and dcir.csv stayed
    in its folder as if they were its results."""
    from ecmgen.diagnosis.synthstudy import make_study, write_study
    from ecmgen.fleet import Options, read_manifest, run_row

    study = tmp_path / "study"
    write_study(make_study(cells=1, checkups=1, seed=2), study, with_cycle=False)
    row = read_manifest(study / "manifest.csv")[0]
    out = tmp_path / "out"
    options = Options(plots=False, c_code=False)
    assert run_row(row, out, options).status == "built"
    folder = out / row.cell / row.checkup
    assert (folder / "model.json").is_file() and (folder / "report.md").is_file()
    (folder / "notes.txt").write_text("mine")
    (study / row.cell / row.checkup / "capacity.csv").write_text("time_s,current_a,voltage_v\n")
    assert run_row(row, out, options).status == "failed"
    left = sorted(p.name for p in folder.iterdir())
    assert left == ["notes.txt"], left
