"""Acceptance: the table checks of every method's model on the synthetic cells.

Builds (no C, no plots) each cell of ../shared/diagnose-suite/ from its case.toml with the
methods GA, LM and curve, and prints per cell and method the table quality
(ecmgen.fit.quality: roughness, values <= 0, time constants on a bound) and the cycle's MAE.
The cells come from a generator that is not ours; truth.json is not read.

    python bench/synthetic_quality.py [--suite ../shared/diagnose-suite] [--jobs 2]

Done-when of the fit: roughness <= 0.35 on every synthetic cell, no value <= 0, every time
constant on a bound said.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_SUITE = HERE.parent.parent / "shared" / "diagnose-suite"
LIMIT = 0.35


def run_case(folder: str, progress=None) -> list[tuple]:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    folder = Path(folder)
    cfg = replace(load_config(folder / "case.toml"), methods=("ga", "lm", "curve"))
    with tempfile.TemporaryDirectory() as tmp:
        result = build(cfg, Path(tmp) / "out", plots=False, c_code=False, workers=1)
    rows = []
    for method, q in result.quality.items():
        maes = [1e3 * v.overall.mae_v for v in result.validations.get(method, {}).values()]
        rows.append((folder.name, method, q.roughness, q.non_positive, list(q.on_bound),
                     maes[0] if maes else float("nan")))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default=str(DEFAULT_SUITE))
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    folders = sorted(str(p) for p in Path(args.suite).iterdir() if (p / "case.toml").is_file())
    if not folders:
        print(f"{args.suite}: no cell folders", file=sys.stderr)
        return 2
    from ecmgen.parallel import Workers     # its workers use one BLAS thread each

    with Workers(args.jobs) as workers:
        results = [r for rows in workers.map(run_case, [(f,) for f in folders]) for r in rows]
    print(f"{'cell':5s} {'method':6s} {'rough':>6s} {'<=0':>4s} {'MAE mV':>7s}  on bound")
    for cell, method, rough, nonpos, bound, mae in results:
        print(f"{cell:5s} {method:6s} {rough:6.2f} {nonpos:4d} {mae:7.2f}  {', '.join(bound) or '-'}")
    print()
    for method in ("ga", "lm", "curve"):
        got = [r for r in results if r[1] == method]
        worst = max(r[2] for r in got)
        passing = sum(r[2] <= LIMIT and r[3] == 0 for r in got)
        print(f"{method:6s} max roughness {worst:.2f}, non-positive {sum(r[3] for r in got)}, "
              f"{passing} of {len(got)} cells within {LIMIT} with no value <= 0")
    return 0


if __name__ == "__main__":
    sys.exit(main())
