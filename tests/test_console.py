"""The command line's console: progress on stderr (stages only in a log), notes counted
by kind, one line per validation cycle, the one-line summary."""

from __future__ import annotations

import io

from ecmgen.console import StderrProgress, cycle_table, detail_of, note_lines


def test_in_a_log_the_stages_are_lines_and_the_steps_are_left_out():
    buf = io.StringIO()
    p = StderrProgress(buf)
    p("fitting 4 pulse tests")
    detail_of(p)("[pulse test 1] GA fit")
    p.close()
    assert buf.getvalue() == "[ecmgen] fitting 4 pulse tests\n"
    said = []
    detail_of(said.append)("a step")         # a plain callable gets the steps too
    assert said == ["a step"]


def test_notes_are_counted_by_kind_and_warnings_kept_whole():
    notes = [f"[0.6 degC] pulse at t={t}.0 s (discharge 6C, soc 0.4) cut short after 1 s: "
             "left out" for t in range(5)]
    notes += ["us06.mat: the voltage lags the current by 1 sample (0.1 s)",
              "OCV: pulses, 57 rested voltages", "OCV check: 12 mV RMS; warning: the rests "
              "are the better source"]
    lines = note_lines(notes, "out/report.md")
    assert lines == [
        "warning: OCV check: 12 mV RMS; warning: the rests are the better source",
        "note: 5 pulses cut short (shorter than the others of their direction) and left out",
        "note: 1 cycles: the measured voltage lags the current (not corrected)",
        "note: 1 more note: see out/report.md"]


def test_one_line_per_cycle():
    rows = [("ga", "us06.mat", 37.8, 42.6, 503.0, 37.8, (25.6, 33.0)),
            ("curve", "us06.mat", 15.7, 23.4, 511.0, 15.7, (25.6, 33.0)),
            ("curve", "hwfet.mat", 10.6, 22.1, 377.0, 8.7, None)]
    text = cycle_table(rows, "curve").splitlines()
    assert "curve*" in text[0] and len(text) == 5
    assert text[2].split() == ["us06.mat", "25.6..33.0", "37.80", "15.70"]
    assert text[3].split() == ["hwfet.mat", "-", "-", "10.60"]


def test_build_quiet_prints_nothing_but_warnings(tmp_path):
    """`build -q` on success: no line on stdout; on stderr warnings only."""
    import subprocess
    import sys
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "examples" / "panasonic-25degC" / "config.toml"
    ecmgen = Path(sys.executable).with_name("ecmgen")
    res = subprocess.run([str(ecmgen), "build", str(example), "--out",
                          str(tmp_path / "out"), "-q", "--no-plots", "--no-c"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout == ""
    assert all(line.startswith("warning") for line in res.stderr.splitlines()), res.stderr


def test_the_command_line_runs_one_blas_thread_unless_told():
    """Set before numpy loads (ecmgen.parallel measured why); a caller's own setting stays."""
    import os
    import subprocess
    import sys

    probe = ("import sys, os; import ecmgen.parallel; assert 'numpy' not in sys.modules; "
             "import ecmgen.cli; print(os.environ['OPENBLAS_NUM_THREADS'], "
             "os.environ['OMP_NUM_THREADS'])")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    res = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["1", "1"]
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         env={**env, "OPENBLAS_NUM_THREADS": "3"})
    assert res.stdout.split() == ["3", "1"]


def test_the_library_holds_blas_to_one_thread_while_it_works():
    """A notebook loads numpy (with its BLAS threads) before ecmgen: the fits, the
    diagnosis and the filter hold BLAS to one thread while they run and give the caller's
    setting back after, also when they fail."""
    import json
    import os
    import subprocess
    import sys

    probe = """
import json, numpy, ecmgen
from threadpoolctl import threadpool_info, threadpool_limits
from ecmgen.parallel import one_blas_thread

def blas():
    return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})

seen = []
@one_blas_thread
def inner():
    seen.append(blas())
@one_blas_thread
def outer(fail):
    inner()
    seen.append(blas())
    if fail:
        raise ValueError
with threadpool_limits(2, user_api="blas"):
    outer(False)
    try:
        outer(True)
    except ValueError:
        pass
    seen.append(blas())
names = ("build", "fit_ga", "fit_lm", "fit_pulse_curves", "diagnose", "estimate_record",
         "run_filter")
print(json.dumps({"seen": seen,
                  "wrapped": all(hasattr(getattr(ecmgen, n), "__wrapped__") for n in names)}))
"""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    res = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout) == {"seen": [[1], [1], [1], [1], [2]], "wrapped": True}
