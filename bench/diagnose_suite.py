"""Acceptance: `diagnose` on synthetic cells with known missing effects (truth kept apart).

For every cell folder (case.toml, pulses.csv, ocv.csv, cycle.csv, truth.json) it runs
`ecmgen diagnose` on the case's config as a user would (the base model from the config's
own settings), and scores the verdict against truth.json (``effect``: one name or
``none``, in ../shared/diagnose-suite; ``effects``: a list, in the cells of
bench/diagnose_cells.py). It prints one row per cell and the confusion matrix, truth x
verdict: the effects named, ``X|Y`` where diagnose says the data cannot tell X from Y,
``nothing`` (nothing missing) and ``unexpl.`` (nothing named, error left above 3x noise).

A cell is *right* when exactly its effects are named; a *wrong name* is any named effect
that is not in its truth, or an "X or Y" without the truth among them (a control with a
name is a false alarm); "X or Y" with the truth among them is neither.

    python bench/diagnose_suite.py [--suite DIR ...] [--jobs 2] [--json F] [--only a,b]

Targets: shared suite >= 11 of 12, no wrong name; on bench/diagnose_cells.py's
held-out half singles right >= 90 %, pairs both named >= 60 %, wrong names <= 2 % of
cells, no false alarm on the controls.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_SUITE = HERE.parent.parent / "shared" / "diagnose-suite"

SHORT = {"hysteresis": "hys", "extra_rc": "rc3", "current_dependent_resistance": "bv",
         "capacity_error": "cap", "temperature_dependence": "arr", "current_offset": "ioff",
         "current_gain": "igain", "voltage_lag": "vlag", "entropic_ocv": "ent",
         "diffusion": "diff", "ocv_error": "ocv"}


def truth_effects(truth: dict) -> tuple[str, ...]:
    if "effects" in truth:
        return tuple(truth["effects"])
    return () if truth["effect"] == "none" else (truth["effect"],)


def score(truth: tuple[str, ...], named: list[str], cannot_tell: list[list[str]]) -> dict:
    # a look-alike group without the truth in it misleads as a wrong name does
    wrong = [n for n in named if n not in truth] + \
        [g for g in cannot_tell if not set(g) & set(truth)]
    return {"right": sorted(named) == sorted(truth) and not cannot_tell,
            "wrong": bool(wrong), "false_alarm": not truth and bool(named),
            "partial": bool(truth) and not wrong and 0 < len(named) < len(truth)}


def verdict_label(named, cannot_tell, unexplained: bool) -> str:
    parts = [SHORT.get(n, n) for n in named]
    parts += ["|".join(SHORT.get(n, n) for n in g) for g in cannot_tell]
    if parts:
        return "+".join(parts)
    return "unexpl." if unexplained else "nothing"


def run_case(folder: str, progress=None) -> dict:
    """Diagnose one cell folder; returns its score row (truth read only to score)."""
    from ecmgen.config import load_config
    from ecmgen.fit.quality import model_quality
    from ecmgen.model import model_from_json_dict
    from ecmgen.pipeline import run_diagnose

    folder = Path(folder)
    truth = truth_effects(json.loads((folder / "truth.json").read_text()))
    cfg = load_config(folder / "case.toml")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result, _, _ = run_diagnose(cfg, Path(tmp) / "out", plots=False)
        base = json.loads((Path(tmp) / "out" / "model-base.json").read_text())
    q = model_quality(model_from_json_dict(base))
    named = list(result.effects)
    cannot = [list(g) for g in getattr(result, "cannot_tell", ())]
    drop = 1.0 - result.mae_after_v / result.mae_before_v if result.mae_before_v > 0 else 0.0
    row = {"case": folder.name, "truth": list(truth), "named": named, "cannot_tell": cannot,
           "mae_before_mv": 1e3 * result.mae_before_v, "mae_after_mv": 1e3 * result.mae_after_v,
           "noise_mv": 1e3 * result.noise_v, "drop": drop,
           "roughness": q.roughness, "non_positive": q.non_positive,
           "on_bound": list(q.on_bound), "unexplained": result.unexplained,
           "verdict": result.verdict, "seconds": time.perf_counter() - t0,
           "candidates": [(c.round, c.name, 1e3 * c.judge_mae_v, 1e3 * c.fit_mae_v, c.passed,
                           c.message) for c in result.candidates],
           "notes": list(result.notes)}
    row.update(score(truth, named, cannot))
    # the shared suite's rule: the first effect named is the truth
    row["ok"] = (not named) if not truth else bool(named) and named[0] == truth[0]
    row["label"] = verdict_label(named, cannot, result.unexplained)
    return row


def truth_label(truth) -> str:
    if not truth:
        return "none"
    return "+".join(SHORT.get(t, t) for t in truth)


def confusion(rows: list[dict]) -> str:
    """truth x verdict counts; pairs are one row each kind of pair."""
    cols = sorted({r["label"] for r in rows}, key=lambda c: (c in ("nothing", "unexpl."), c))
    truths = sorted({truth_label(r["truth"]) for r in rows},
                    key=lambda t: (t == "none", "+" in t, t))
    w = max(9, max(len(t) for t in truths) + 1)
    cw = [max(4, len(c)) for c in cols]
    out = [" " * w + " ".join(c.rjust(n) for c, n in zip(cols, cw))]
    for t in truths:
        cnt = Counter(r["label"] for r in rows if truth_label(r["truth"]) == t)
        out.append(t.ljust(w) + " ".join((str(cnt[c]) if cnt[c] else ".").rjust(n)
                                         for c, n in zip(cols, cw)))
    return "\n".join(out)


def summary(rows: list[dict]) -> str:
    singles = [r for r in rows if len(r["truth"]) == 1]
    pairs = [r for r in rows if len(r["truth"]) == 2]
    controls = [r for r in rows if not r["truth"]]

    def pct(k, n):
        return f"{k}/{n} ({100 * k / n:.0f} %)" if n else "-"

    return (f"singles named right {pct(sum(r['right'] for r in singles), len(singles))}, "
            f"pairs both named {pct(sum(r['right'] for r in pairs), len(pairs))} "
            f"(one of two {sum(r['partial'] for r in pairs)}), "
            f"wrong name {pct(sum(r['wrong'] for r in rows), len(rows))}, "
            f"control false alarms {sum(r['false_alarm'] or r['unexplained'] for r in controls)}"
            f"/{len(controls)}, 'cannot tell' {sum(bool(r['cannot_tell']) for r in rows)}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", action="append", help=f"cell folders' parent (default "
                    f"{DEFAULT_SUITE}); repeat for several")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", help="comma-separated cell folder names")
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    suites = args.suite or [str(DEFAULT_SUITE)]
    t0 = time.perf_counter()
    from ecmgen.parallel import Workers  # its workers use one BLAS thread each

    all_rows = []
    for suite in suites:
        cases = sorted(str(p.parent) for p in Path(suite).glob("*/truth.json"))
        if args.only:
            keep = set(args.only.split(","))
            cases = [c for c in cases if Path(c).name in keep]
        if not cases:
            print(f"no cells in {suite}", file=sys.stderr)
            return 2
        with Workers(args.jobs) as workers:
            rows = workers.map(run_case, [(c,) for c in cases])
        all_rows += rows
        print(f"\n== {suite}")
        print(f"{'cell':34s} {'truth':12s} {'verdict':16s} {'MAE mV':>14s} {'noise':>6s} "
              f"{'rough':>5s} {'s':>5s}")
        for r in rows:
            mark = "ok" if r["right"] else ("WRONG" if r["wrong"] else "miss")
            print(f"{r['case'][:34]:34s} {truth_label(r['truth'])[:12]:12s} "
                  f"{r['label'][:16]:16s} {r['mae_before_mv']:6.2f}->{r['mae_after_mv']:6.2f} "
                  f"{r['noise_mv']:6.2f} {r['roughness']:5.2f} {r['seconds']:5.0f} {mark}")
        print("\nconfusion (truth x verdict):")
        print(confusion(rows))
        print(summary(rows))
        if any("effect" in json.loads((Path(c) / "truth.json").read_text()) for c in cases):
            hits = sum(r["ok"] for r in rows)
            print(f"shared rule (first named = truth): {hits} of {len(rows)}")
    print(f"\n{len(all_rows)} cells, {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(all_rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
