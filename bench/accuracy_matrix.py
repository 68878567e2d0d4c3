"""The accuracy matrix: every configuration the shared data supports, each judged on every
shared record it may honestly be judged on, against a committed baseline.

    python bench/accuracy_matrix.py [--only NAME,...] [--workers N] [--json PATH]
                                    [--check BASELINE] [--update BASELINE] [--models DIR]

One table: a row per (configuration, record) with the MAE, the MAE above 10 % SOC (simulated)
and the max |error| in mV, and per configuration its build time (``ecmgen.pipeline.build``,
no C, no plots; wall seconds, so they depend on what else runs). ``--check`` exits 1 when a
gated cell is worse than the baseline's by more than max(5 %, 1 mV); ``--update`` writes
the baseline (bench/baseline/accuracy_matrix.json; docs/make_docs.py shows it in
docs/results.md). All three figures are gated: a build is deterministic, so each figure is
the same run to run (checked: the subset twice, and sequential against side by side).

Configurations (``[fit] methods = ["curve"]`` throughout; the demo's own three methods
give the same model.json):

- ``panT`` / ``panT+c20`` (T = 25, 0, n10, n20): the Panasonic 18650PF at one temperature
  from that temperature's hppc.mat alone (``pulses``, ``pulses_soc0 = 1``, OCV from its
  rests), and the same with the 25 degC C/20 test as OCV. Judged on that temperature's two
  drive cycles (US06 and HWFET; HWFET-a at 25 degC), from full (soc0 = 1).
- ``pan4`` (the four hppc.mat as [[data.pulse_tests]], ``soc0 = 1``, OCV from the rests,
  every other setting default: what a user with these files writes first), ``pan4+steps``
  (each with its SOC-steps file), ``pan4+c20`` (plain with the C/20 test as the one OCV)
  and ``demo`` (examples/panasonic-temperature/config.toml). Judged on all eight drive
  cycles, from full, each on its own measured cell temperature.
- ``leaf25``, ``leaf40``, ``leaf`` (tests/data/nissan-leaf/config.toml with one test, the
  other, both). The Leaf has no drive cycle; its records are the two HPPC files and the
  pseudo-OCV cycling file, none with a temperature column. Each HPPC file is judged whole,
  at its chamber temperature, from the start SOC the build itself takes for it (SOC 1.0 at
  the end of its opening CC-CV charge, counted back), so its opening charge from empty
  judges the OCV there: in-sample (``*``) for a model built from it; for the
  one-temperature model of the other test it is the other temperature, which that model
  does not follow. The cycling file, kept back from every model, is judged only on the
  5 min rest after its first full discharge (C/15 from 4.2 V to 3.0 V, simulated whole from
  full, soc0 = 1): the voltage at empty, which judges the OCV there and the capacity. Under
  current its voltage steps by 0.24 V within a sample as 2.2 A (1.8 A) start, 0.11 ohm
  where the HPPC files' 30 A pulses show 1.6 mohm: the set-up's, not the cell's, so its
  discharges and charges cannot judge a model. Its ambient is not recorded (10, 24 or
  40 degC, SOURCE.md): a one-temperature model holds its tables at any temperature; the
  model of both tests runs it at each test's temperature (``@25C``, ``@40C``), each that
  temperature's OCV.
- ``a123`` (examples/a123-dynamic/config.toml: OCV from the four OCV scripts, which the
  dynamic test's relaxed rests lead (``data.ocv_rests_first``), tables from the dynamic test
  s1) and ``a123+files`` (``ocv_rests_first = "never"``: the four files alone). Judged on
  s2 and s3, their start SOC from their opening rest, as the example's build does. s2
  opens nearly empty and holds 2.0 V for hours before its charge: its figures judge mostly
  the OCV at and below empty.

The shared data: ../shared/data beside the repository, or $ECMGEN_SHARED_DATA.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ecmgen.parallel import ONE_BLAS_THREAD   # does not load numpy

# one BLAS thread, before numpy loads, as the command line sets it: with BLAS threads
# spinning on the cores, one build here took 120 s against 13 s from the command line
for _name, _value in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_name, _value)

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ECMGEN_SHARED_DATA") or REPO.parent / "shared" / "data")
BASELINE = REPO / "bench" / "baseline" / "accuracy_matrix.json"
FIGURES = ("mae_mv", "mae_above_10_mv", "max_mv")
GATED = FIGURES
TOLERANCE, FLOOR_MV = 0.05, 1.0          # worse than baseline by more than max(5 %, 1 mV)
REBASELINE = "python bench/accuracy_matrix.py --update bench/baseline/accuracy_matrix.json"
PANASONIC_C = {"25": "25degC", "0": "0degC", "n10": "n10degC", "n20": "n20degC"}
LEAF = {"25": "NissanLeaf-cell-Low-Current-HPPC-25C-2.csv",
        "40": "NissanLeaf-cell-Low-Current-HPPC-40C-1.csv"}
LEAF_CYCLING = "NissanLeaf-cell-Cycling-10C-24C-40C.csv"


@dataclass(frozen=True)
class Record:
    """One record a configuration is judged on."""

    label: str
    path: Path
    soc0: float | str | None = 1.0      # None: from its opening rest; "cv": opening CV charge
    temperature_c: float | None = None   # for a record without a temperature column
    window: str = ""                     # "empty rest": the rest after its first discharge
    in_sample: bool = False


@dataclass(frozen=True)
class Configuration:
    name: str
    toml: str                            # the config, absolute paths
    records: tuple[Record, ...]


def panasonic(t: str, name: str = "") -> Path:
    return DATA / f"panasonic-18650pf-{PANASONIC_C[t]}" / name


def _cycles(t: str) -> tuple[Record, ...]:
    return tuple(Record(f"{PANASONIC_C[t]}/{Path(n).stem}", panasonic(t, n))
                 for n in ("us06.mat", "hwfet-a.mat" if t == "25" else "hwfet.mat"))


def _q(path: Path) -> str:
    return json.dumps(str(path))


CURVE = '[fit]\nmethods = ["curve"]\n'
PAN_CELL = "[cell]\ncapacity_ah = 2.9\n"
C20 = panasonic("25", "ocv-c20.mat")


def _one_temperature(t: str, c20: bool) -> Configuration:
    ocv = _q(C20) if c20 else '"pulses"'
    toml = (f"{PAN_CELL}[data]\npulses = {_q(panasonic(t, 'hppc.mat'))}\npulses_soc0 = 1.0\n"
            f"ocv = {ocv}\n{CURVE}")
    return Configuration(f"pan{t}" + ("+c20" if c20 else ""), toml, _cycles(t))


def _four_temperatures(name: str, steps: bool = False, c20: bool = False) -> Configuration:
    ocv = _q(C20) if c20 else '"pulses"'
    tests = "".join(f"[[data.pulse_tests]]\nfile = {_q(panasonic(t, 'hppc.mat'))}\nsoc0 = 1.0\n"
                    + (f"steps = {_q(panasonic(t, 'hppc-soc-steps.mat'))}\n" if steps else "")
                    for t in PANASONIC_C)
    toml = f"{PAN_CELL}[data]\nocv = {ocv}\n{tests}{CURVE}"
    return Configuration(name, toml, sum((_cycles(t) for t in PANASONIC_C), ()))


def _example(path: Path, replace: dict[str, str]) -> str:
    """An example's config with its relative paths made absolute (and lines replaced),
    without its validation cycles: the bench judges the model itself."""
    text = re.sub(r"^(cycle = .*|extra_cycles = \[[^]]*\])\n", "", path.read_text(),
                  flags=re.M)
    for old, new in replace.items():
        if old not in text:
            raise SystemExit(f"{path}: {old!r} not found")
        text = text.replace(old, new)
    return text


def _demo() -> Configuration:
    base = REPO / "examples" / "panasonic-temperature"
    rel = {f'"{d}/': f'"{base / d}/' for d in ("0degC", "n10degC", "n20degC")}
    rel['"../panasonic-25degC/'] = f'"{REPO / "examples" / "panasonic-25degC"}/'
    rel['methods = ["ga", "lm", "curve"]'] = 'methods = ["curve"]'
    return Configuration("demo", _example(base / "config.toml", rel),
                         sum((_cycles(t) for t in PANASONIC_C), ()))


def _leaf(temps: tuple[str, ...]) -> Configuration:
    tests = "".join(f"[[data.pulse_tests]]\nfile = {_q(DATA / 'nissan-leaf' / LEAF[t])}\n"
                    f"temperature_c = {t}\n" for t in temps)
    toml = f'[cell]\ncapacity_ah = 32.5\n[data]\nocv = "pulses"\n{tests}{CURVE}'
    records = tuple(Record(f"leaf/hppc-{t}C", DATA / "nissan-leaf" / LEAF[t], "cv", float(t),
                           in_sample=t in temps) for t in LEAF)
    rest = "leaf/cycling-empty-rest"
    cycling = tuple(Record(rest + (f"@{t}C" if len(temps) > 1 else ""),
                           DATA / "nissan-leaf" / LEAF_CYCLING, 1.0, float(t), "empty rest")
                    for t in temps)
    return Configuration("leaf" + ("" if len(temps) > 1 else temps[0]), toml,
                         records + cycling)


def _a123(files_alone: bool) -> Configuration:
    shared = str(DATA / "plett-a123-lfp")
    rel = {"../../../shared/data/plett-a123-lfp": shared}
    if files_alone:
        rel['ocv = ["'] = 'ocv_rests_first = "never"\nocv = ["'
    text = _example(REPO / "examples" / "a123-dynamic" / "config.toml", rel)
    dyn = DATA / "plett-a123-lfp" / "dyn_data"
    return Configuration("a123" + ("+files" if files_alone else ""), text,
                         tuple(Record(f"a123/{s}", dyn / f"A123_DYN_50_P25_{s}.csv", None)
                               for s in ("s2", "s3")))


def configurations() -> dict[str, Configuration]:
    out = [c for t in PANASONIC_C for c in (_one_temperature(t, False),
                                             _one_temperature(t, True))]
    out += [_four_temperatures("pan4"), _four_temperatures("pan4+steps", steps=True),
            _four_temperatures("pan4+c20", c20=True), _demo()]
    out += [_leaf(("25",)), _leaf(("40",)), _leaf(("25", "40"))]
    out += [_a123(False), _a123(True)]
    return {c.name: c for c in out}


def _first_discharge(series):
    """The record's first discharge and the rest after it (to the next charge), and which
    of its samples are that rest."""
    import numpy as np

    i = series.current_a
    start = int(np.flatnonzero(i < -0.5)[0])
    after = np.flatnonzero(i[start:] > 0.5)
    part = series.slice(start, start + int(after[0]) if after.size else len(series))
    moving = np.flatnonzero(np.abs(part.current_a) > 0.05)
    return part, np.arange(len(part)) > moving[-1]


def _mv(x: float) -> float | None:
    return None if not math.isfinite(x) else round(1e3 * x, 3)


def judge(model, cfg, rec: Record) -> dict:
    """The model on one record: its figures in mV."""
    from ecmgen.data.soc import opening_cv_charge
    from ecmgen.data.sources import read_series
    from ecmgen.model.simulate import Metrics, validate

    series = read_series(cfg, rec.path, "cycle")
    judged = None
    if rec.window == "empty rest":
        series, judged = _first_discharge(series)
    soc0 = rec.soc0
    if soc0 == "cv":            # as the build takes a pulse test's start (pulse_test_soc0)
        soc0 = opening_cv_charge(series, cfg.capacity_ah,
                                 max(0.02 * cfg.capacity_ah, 1e-3), after_discharge=True)[0]
    v = validate(model, series, soc0, temperature_c=rec.temperature_c)
    overall, above_10 = v.overall, v.soc_above_10
    if judged is not None:
        overall = Metrics.of(v.error_v[judged])
        above_10 = Metrics.of(v.error_v[judged & (v.sim.soc > 0.10)])
    return {"mae_mv": _mv(overall.mae_v), "mae_above_10_mv": _mv(above_10.mae_v),
            "max_mv": _mv(overall.max_abs_v), "in_sample": rec.in_sample,
            "soc0": round(float(v.soc0), 4)}


def run_configuration(name: str, build_workers: int = 2, models_dir: Path | None = None,
                      progress=None) -> dict:
    """Build one configuration (in a temporary folder) and judge it on its records;
    ``models_dir``: its model*.json copied to ``models_dir / name``."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    conf = configurations()[name]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{name.replace('+', '-')}.toml"
        path.write_text(conf.toml)
        cfg = load_config(path)
        t0 = time.perf_counter()
        result = build(cfg, Path(tmp) / "out", plots=False, c_code=False,
                       workers=build_workers)
        seconds = time.perf_counter() - t0
        model = result.models[result.best]
        records = {rec.label: judge(model, cfg, rec) for rec in conf.records}
        if models_dir is not None:
            keep = Path(models_dir) / name
            keep.mkdir(parents=True, exist_ok=True)
            for f in sorted((Path(tmp) / "out").glob("model*.json")):
                (keep / f.name).write_bytes(f.read_bytes())
    return {"build_s": round(seconds, 1), "records": records}


def run(names: list[str], workers: int = 1, progress=print,
        models_dir: Path | None = None) -> dict:
    """Every named configuration: side by side on ``workers`` processes (each build then
    on one), else one after the other (each build over temperature on two)."""
    from ecmgen.parallel import Workers

    out = {}
    with Workers(workers) as pool:
        build_workers = 1 if pool.parallel else 2
        tasks = {n: pool.submit(run_configuration, n, build_workers, models_dir)
                 for n in (names if pool.parallel else ())}
        for n in names:     # one after the other: each runs when submitted
            task = tasks[n] if pool.parallel else pool.submit(run_configuration, n, 2, models_dir)
            out[n] = task.result()
            progress(f"{n}: built in {out[n]['build_s']:.1f} s")
    return out


def table(results: dict) -> str:
    head = (f"| configuration | record | MAE mV | MAE above 10 % SOC mV | max mV | build s |\n"
            f"|---|---|---|---|---|---|\n")
    rows = []
    for name, res in results.items():
        for k, (label, f) in enumerate(res["records"].items()):
            cells = [("-" if f[x] is None else f"{f[x]:.1f}") for x in FIGURES]
            rows.append(f"| {name if k == 0 else ''} | {label}{' *' if f['in_sample'] else ''}"
                        f" | {' | '.join(cells)} | {res['build_s'] if k == 0 else ''} |")
    return (head + "\n".join(rows)
            + "\n\n(* in-sample: the record is one the model was built from)\n")


def worse(results: dict, baseline: dict) -> list[str]:
    """Every gated cell worse than the baseline's by more than max(5 %, 1 mV), every cell of
    the baseline missing from ``results`` (of the configurations run)."""
    out = []
    for name, res in results.items():
        base = baseline["configurations"].get(name)
        if base is None:
            out.append(f"{name}: not in the baseline")
            continue
        for label, b in base["records"].items():
            now = res["records"].get(label)
            for fig in GATED:
                old, new = b.get(fig), (now or {}).get(fig)
                if old is None:
                    continue
                bound = old + max(TOLERANCE * old, FLOOR_MV)
                if new is None or new > bound:
                    out.append(f"{name} {label} {fig}: {new} against baseline {old:.3f} "
                               f"(bound {bound:.3f})")
    return out


def better(results: dict, baseline: dict) -> list[str]:
    """Every gated cell better than the baseline's by more than max(5 %, 1 mV): the
    baseline should take it, in the same commit as the change, saying why."""
    out = []
    for name, res in results.items():
        base = baseline["configurations"].get(name, {"records": {}})
        for label, b in base["records"].items():
            for fig in GATED:
                old, new = b.get(fig), res["records"].get(label, {}).get(fig)
                if old is not None and new is not None and \
                        new < old - max(TOLERANCE * old, FLOOR_MV):
                    out.append(f"{name} {label} {fig}: {new} against baseline {old:.3f}")
    return out


def document(results: dict) -> dict:
    return {"note": "bench/accuracy_matrix.py; figures in mV, build_s wall seconds",
            "configurations": results}


def read_baseline(path: Path) -> dict | str:
    """The baseline at ``path``, or the one line that says why it cannot be read."""
    try:
        doc = json.loads(path.read_text())
        if isinstance(doc.get("configurations"), dict):
            return doc
        why = "no configurations"
    except (OSError, ValueError, AttributeError) as exc:
        why = str(exc) if isinstance(exc, ValueError) else type(exc).__name__
    return f"{path}: not an accuracy-matrix baseline ({why})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="NAME[,NAME...] (default: all): " + ", ".join(configurations()))
    ap.add_argument("--workers", type=int, default=1,
                    help="configurations side by side (each build on one process)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--check", type=Path, help="exit 1 on a cell worse than this baseline")
    ap.add_argument("--update", type=Path, help="write the results as this baseline")
    ap.add_argument("--models", type=Path, metavar="DIR",
                    help="keep each configuration's model*.json in DIR/NAME (to compare "
                         "two trees' tables)")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else list(configurations())
    unknown = [n for n in names if n not in configurations()]
    if unknown:
        print(f"accuracy_matrix: unknown configuration {', '.join(unknown)}", file=sys.stderr)
        return 2
    if not DATA.is_dir():
        print(f"accuracy_matrix: no shared data at {DATA} (set ECMGEN_SHARED_DATA)",
              file=sys.stderr)
        return 2
    baseline = read_baseline(args.check) if args.check is not None else None
    kept = read_baseline(args.update) if args.update is not None and args.only and \
        args.update.exists() else {"configurations": {}}      # --only keeps the other rows
    for doc in (baseline, kept):
        if isinstance(doc, str):
            print(doc, file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    results = run(names, args.workers, lambda m: print(m, file=sys.stderr, flush=True),
                  args.models)
    print(table(results))
    print(f"{len(names)} configurations in {time.perf_counter() - t0:.0f} s "
          f"({args.workers} side by side)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document(results), indent=1) + "\n")
    if args.update is not None:
        old = kept["configurations"]
        merged = {n: results.get(n, old.get(n)) for n in configurations()
                  if n in results or n in old}
        args.update.parent.mkdir(parents=True, exist_ok=True)
        args.update.write_text(json.dumps(document(merged), indent=1) + "\n")
    if args.check is not None:
        gained, bad = better(results, baseline), worse(results, baseline)
        if gained:
            print("better than the baseline by more than max(5 %, 1 mV) (re-baseline in the "
                  "same commit, saying why):\n  " + "\n  ".join(gained))
        if bad:
            print("worse than the baseline by more than max(5 %, 1 mV):\n  " + "\n  ".join(bad)
                  + f"\nif the change is meant, re-baseline in the same commit, saying why:\n"
                  f"  {REBASELINE}", file=sys.stderr)
            return 1
        print(f"no cell worse than {args.check} by more than max(5 %, 1 mV)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
