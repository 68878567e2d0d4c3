"""The README runs as written: its two first commands, its CSV and config (a build of a
synthetic cell), its Python snippet, its C snippet (compiled with -Wall -Wextra -Werror
and linked against generated C), its command list and its links; and the docs' generated
results table is made the way docs/make_docs.py makes it."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import textwrap
import tomllib

import numpy as np
import pytest

from conftest import REPO, make_pulse_test, synthetic_nca_model

README = (REPO / "README.md").read_text()
MODEL = REPO / "tests" / "data" / "panasonic-temperature-model.json"


def _blocks(lang: str) -> list[str]:
    return [textwrap.dedent(b) for b in re.findall(rf"```{lang}\n(.*?)```", README, re.S)]


def test_it_opens_with_make_demo_and_make_test():
    """The first lines a newcomer reads are the two commands (.ci/run runs `make test`)."""
    first = README.split("```")[1].splitlines()
    assert [line.split("#")[0].strip() for line in first[1:3]] == ["make demo", "make test"]
    assert "make test" in (REPO / ".ci" / "run").read_text()
    make = (REPO / "Makefile").read_text()
    assert re.search(r"^demo:", make, re.M) and re.search(r"^test:", make, re.M)


def test_it_stays_short():
    assert README.count("\n") <= 200 and len(README.encode()) <= 10_500


def test_its_links_and_pictures_exist():
    for target in re.findall(r"\]\(([^)#]+)\)", README):
        assert (REPO / target).exists(), target


def test_its_commands_are_commands():
    from ecmgen.cli import parser

    known = set(parser()._subparsers._group_actions[0].choices)
    text = next(b for b in _blocks("text") if b.startswith("ecmgen "))
    for line in text.splitlines():
        assert line.split()[1] in known, line


def test_the_python_snippet_runs(monkeypatch, capsys):
    code = _blocks("python")[0].replace("demo-out/model.json", str(MODEL))
    monkeypatch.chdir(REPO)
    exec(compile(code, "README.md", "exec"), {})
    mae = float(re.search(r"MAE ([0-9.]+) mV", capsys.readouterr().out).group(1))
    assert 0 < mae < 60


def test_your_own_cell_builds(tmp_path):
    """The CSV format and config of 'Your own cell in five minutes', on a synthetic cell."""
    from ecmgen.cli import main
    from ecmgen.data.measure import read_timeseries, write_timeseries_csv
    from ecmgen.model.simulate import simulate

    sample = _blocks("csv")[0]
    (tmp_path / "sample.csv").write_text(sample)
    assert read_timeseries(tmp_path / "sample.csv", capacity_ah=2.9).time_s.size == 4
    cfg = tomllib.loads(_blocks("toml")[0])
    m = synthetic_nca_model()
    series, _ = make_pulse_test(m, soc_levels=(0.9, 0.7, 0.5, 0.3), c_rates=(1.0, 2.0),
                                rest_s=600.0)
    write_timeseries_csv(series, tmp_path / cfg["data"]["pulses"])
    t = np.arange(0.0, 1800.0, 1.0)
    i = -2.9 * (0.5 + 0.5 * np.sin(t / 37.0)) * (t > 60)
    sim = simulate(m, t, i, 1.0)
    (tmp_path / cfg["data"]["cycle"]).write_text("time_s,current_a,voltage_v\n" + "".join(
        f"{a:.1f},{b:.4f},{c:.5f}\n" for a, b, c in zip(t, i, sim.voltage_v)))
    (tmp_path / "cell.toml").write_text(_blocks("toml")[0] + '[fit]\nmethods = ["lm"]\n')
    assert main(["build", str(tmp_path / "cell.toml"), "--out", str(tmp_path / "my-cell"),
                 "-q", "--no-c", "--no-plots"]) == 0
    assert (tmp_path / "my-cell" / "model.json").is_file()
    report = (tmp_path / "my-cell" / "report.md").read_text()
    assert "## Verdict" in report and "MAE <= 50 mV on every cycle" in report


@pytest.mark.skipif(shutil.which("cc") is None, reason="no host C compiler")
def test_the_c_snippet_compiles_and_links(tmp_path):
    from ecmgen.cli import main

    c = tmp_path / "c"
    assert main(["codegen", str(MODEL), "--out", str(c), "--prefix", "pan18650pf",
                 "--estimator", "ekf", "-q"]) == 0
    snippet = _blocks("c")[0]
    (tmp_path / "bms.c").write_text(snippet + textwrap.dedent("""
        #include <stdio.h>
        int main(void)
        {
            float soc = 0.0f;
            bms_init();
            for (int k = 0; k < 600; k++)
                soc = bms_sample(-2.9f, 25.0f, 1.0f, 3.9f);
            printf("%f\\n", (double)soc);
            return 0;
        }
        """))
    exe = tmp_path / "bms"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-I", str(c),
                    str(tmp_path / "bms.c"), str(c / "pan18650pf_ecm_f32.c"),
                    str(c / "pan18650pf_est_f32.c"), "-lm", "-o",
                    str(exe)], check=True, capture_output=True, text=True)
    soc = float(subprocess.run([str(exe)], check=True, capture_output=True,
                               text=True).stdout)
    assert 0.0 <= soc <= 1.0


def test_the_docs_results_table_is_made_from_build_json():
    sys.path.insert(0, str(REPO / "docs"))
    try:
        import make_docs
    finally:
        sys.path.pop(0)
    cyc = {"a.mat": {"mae_v": 0.0157, "rmse_v": 0.0234, "max_abs_v": 0.511,
                     "temperature_c": {"min": -10.2, "max": -2.4}}}
    doc = {"best": "curve", "validation": {"curve": {"cycles": cyc}, "ga": {"cycles": cyc}}}
    table = make_docs.results_table(doc)
    assert "| a.mat | -10.2..-2.4 | **15.7** / 23.4 / 511 | 15.7 / 23.4 / 511 |" in table
    assert "| x | 15.7 / 23.4 / 511 |" in make_docs.best_rows({"x": doc})
    page = (REPO / "docs" / "results.md").read_text()
    for name in make_docs.BLOCKS:
        assert make_docs.replace_block(page, name, table).count(table) == 1
    for name in make_docs.PICTURES:
        assert (REPO / "docs" / "img" / name).is_file()
