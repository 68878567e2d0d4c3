"""Acceptance: `diagnose` on the synthetic cells of ../shared/diagnose-suite/ (truth kept apart).

For every cell folder (case.toml, pulses.csv, ocv.csv, cycle.csv, truth.json) it fits the base
model from the case's config as `ecmgen diagnose` does, runs diagnose on its cycle and scores
the first effect named against truth.json's ``effect`` (``none``: nothing may be named). It
also prints the base model's table quality (roughness, non-positive values, time constants on
a bound; ecmgen.fit.quality).

    python bench/diagnose_suite.py [--suite ../shared/diagnose-suite] [--jobs 2] [--json F]

Done-when: >= 11 of 12 named first, 0 false alarms, median held-out MAE drop >= 60 %.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_SUITE = HERE.parent.parent / "shared" / "diagnose-suite"


def run_case(folder: str, progress=None) -> dict:
    """Diagnose one cell folder; returns its score row (truth read only to score)."""
    from ecmgen.config import load_config
    from ecmgen.fit.quality import model_quality
    from ecmgen.pipeline import run_diagnose

    folder = Path(folder)
    truth = json.loads((folder / "truth.json").read_text())
    cfg = load_config(folder / "case.toml")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result, _, _ = run_diagnose(cfg, Path(tmp) / "out", plots=False)
        base = json.loads((Path(tmp) / "out" / "model-base.json").read_text())
    from ecmgen.model import model_from_json_dict
    q = model_quality(model_from_json_dict(base))
    effect = truth["effect"]
    named = list(result.effects)
    ok = (not named) if effect == "none" else bool(named) and named[0] == effect
    drop = 1.0 - result.mae_after_v / result.mae_before_v if result.mae_before_v > 0 else 0.0
    return {"case": folder.name, "truth": effect, "named": named, "ok": ok,
            "false_alarm": effect == "none" and bool(named),
            "mae_before_mv": 1e3 * result.mae_before_v, "mae_after_mv": 1e3 * result.mae_after_v,
            "noise_mv": 1e3 * result.noise_v, "drop": drop,
            "roughness": q.roughness, "non_positive": q.non_positive,
            "on_bound": list(q.on_bound), "unexplained": result.unexplained,
            "verdict": result.verdict,
            "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default=str(DEFAULT_SUITE))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    cases = sorted(str(p.parent) for p in Path(args.suite).glob("*/truth.json"))
    if not cases:
        print(f"no cells in {args.suite}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    from ecmgen.parallel import Workers     # its workers use one BLAS thread each

    with Workers(args.jobs) as workers:
        rows = workers.map(run_case, [(c,) for c in cases])
    print(f"{'cell':5s} {'truth':29s} {'named':40s} {'MAE mV':>14s} {'noise':>6s} {'drop':>5s} "
          f"{'rough':>6s} {'<=0':>4s} bound")
    for r in rows:
        print(f"{r['case']:5s} {r['truth']:29s} {','.join(r['named']) or '-':40s} "
              f"{r['mae_before_mv']:6.2f}->{r['mae_after_mv']:6.2f} {r['noise_mv']:6.2f} "
              f"{100 * r['drop']:4.0f}% {r['roughness']:6.2f} {r['non_positive']:4d} "
              f"{','.join(r['on_bound']) or '-'}  {'ok' if r['ok'] else 'MISS'}")
    effect_rows = [r for r in rows if r["truth"] != "none"]
    drops = sorted(r["drop"] for r in effect_rows)
    med = drops[len(drops) // 2] if drops else 0.0
    if len(drops) % 2 == 0 and drops:
        med = 0.5 * (drops[len(drops) // 2 - 1] + drops[len(drops) // 2])
    hits = sum(r["ok"] for r in rows)
    fa = sum(r["false_alarm"] for r in rows)
    print(f"named first {hits} of {len(rows)}, false alarms {fa}, median held-out drop "
          f"{100 * med:.0f} % (cells with an effect), max roughness "
          f"{max(r['roughness'] for r in rows):.2f}, non-positive "
          f"{sum(r['non_positive'] for r in rows)}; {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
