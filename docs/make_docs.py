"""Regenerate what the docs show of the bundled examples: the tables between the
``<!-- generated: NAME -->`` and ``<!-- end: NAME -->`` lines of docs/results.md and the
pictures in docs/img/, each from a build of the example (or of a variant of its config).

    python docs/make_docs.py [--only NAME ...]

NAME: demo (the demo build, also the pictures), surface-off (the demo without the surface
SOC), one-temperature (the 25 degC example, with its OCV from the rests and from the C/20
test), estimator (the SOC filter on the demo's model), accuracy-matrix (the committed
baseline of bench/accuracy_matrix.py as it is: no build; its --update rewrites it), speed
(the committed baseline of bench/bench_speed.py, likewise). About a minute a build on 2
cores."""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"
RESULTS = REPO / "docs" / "results.md"
IMAGES = REPO / "docs" / "img"
# the demo's pictures the docs show, by the name the build gives them
PICTURES = ("validation-0degC-us06.png", "parameters-curve.png")
METHODS = (("curve", "whole-test fit (model.json)"), ("ga", "five-point GA"),
           ("lm", "five-point LM"))


def build_json(config: Path, out: Path, replace: dict[str, str] | None = None,
               plots: bool = False) -> dict:
    """`ecmgen build --json` of ``config`` into ``out``; with ``replace`` ({line pattern:
    new line}) of a variant written beside it (paths in a config are relative to it) and
    removed after."""
    if replace:
        text = config.read_text()
        for pattern, line in replace.items():
            text, n = re.subn(pattern, line, text, flags=re.M)
            if n != 1:
                raise SystemExit(f"{config}: {pattern!r} matched {n} lines")
        config = config.with_name(f".make-docs-{config.stem}.toml")
        config.write_text(text)
    try:
        cmd = [sys.executable, "-m", "ecmgen.cli", "build", str(config), "--out", str(out),
               "--json", "-q", "--no-c"] + ([] if plots else ["--no-plots"])
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    finally:
        if replace:
            config.unlink()
    return json.loads(res.stdout)


def figures(v: dict) -> str:
    return f"{v['mae_v'] * 1e3:.1f} / {v['rmse_v'] * 1e3:.1f} / {v['max_abs_v'] * 1e3:.0f}"


def results_table(doc: dict) -> str:
    """A build's validation as a Markdown table: one row per cycle, MAE / RMSE / max in
    mV per method, the best method's MAE in bold."""
    val = doc["validation"]
    methods = [(m, label) for m, label in METHODS if m in val]
    lines = ["| cycle | cell °C | " + " | ".join(label for _, label in methods) + " |",
             "|---|---|" + "---|" * len(methods)]
    for cycle, first in val[methods[0][0]]["cycles"].items():
        t = first.get("temperature_c")
        cells = [f"{t['min']:.1f}..{t['max']:.1f}" if t else "-"]
        for m, _ in methods:
            text = figures(val[m]["cycles"][cycle])
            mae, rest = text.split(" / ", 1)
            cells.append(f"**{mae}** / {rest}" if m == doc["best"] else text)
        lines.append(f"| {cycle} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def best_rows(rows: dict[str, dict]) -> str:
    """One row per build ({label: build JSON}), one column per cycle: model.json's
    MAE / RMSE / max in mV."""
    cycles = list(next(iter(rows.values()))["validation"][next(iter(rows.values()))["best"]]
                  ["cycles"])
    lines = ["| build | " + " | ".join(cycles) + " |", "|---|" + "---|" * len(cycles)]
    for label, doc in rows.items():
        cyc = doc["validation"][doc["best"]]["cycles"]
        lines.append(f"| {label} | " + " | ".join(figures(cyc[c]) for c in cycles) + " |")
    return "\n".join(lines) + "\n"


def replace_block(text: str, name: str, block: str) -> str:
    """``text`` with its generated block ``name`` set to ``block``."""
    start = text.index(f"<!-- generated: {name} ")
    start = text.index("\n", start) + 1
    end = text.index(f"<!-- end: {name} -->")
    return text[:start] + block + text[end:]


def demo(tmp: Path) -> str:
    out = tmp / "demo"
    doc = build_json(EXAMPLES / "panasonic-temperature" / "config.toml", out, plots=True)
    IMAGES.mkdir(exist_ok=True)
    for name in PICTURES:
        shutil.copyfile(out / name, IMAGES / name)
    return results_table(doc)


def surface_off(tmp: Path) -> str:
    doc = build_json(EXAMPLES / "panasonic-temperature" / "config.toml", tmp / "off",
                     {r"^surface_soc_gain = .*$": "surface_soc_gain = 0"})
    return best_rows({"surface SOC off (`surface_soc_gain = 0`)": doc})


def one_temperature(tmp: Path) -> str:
    config = EXAMPLES / "panasonic-25degC" / "config.toml"
    rests = build_json(config, tmp / "rests")
    c20 = build_json(config, tmp / "c20", {r'^ocv = "pulses"$': 'ocv = "ocv-c20.mat"'})
    ga = {"best": "ga", "validation": rests["validation"]}
    return best_rows({"whole-test fit, OCV from the rests (the config)": rests,
                      "five-point GA, the same": ga,
                      'whole-test fit, `ocv = "ocv-c20.mat"`': c20})


# the estimator's sensor-error scenario: told 0.8 for a full cell, 29 mA offset, 1 % gain
SCENARIO = ["--soc0", "1", "--soc0-guess", "0.8", "--current-offset-a", "0.029",
            "--current-gain", "1.01"]


def estimator(tmp: Path) -> str:
    """`ecmgen estimate` of the demo's model on each of its cycles in the sensor-error
    scenario: SOC RMSE and max error after 600 s, and coulomb counting's."""
    from ecmgen.config import load_config

    config = EXAMPLES / "panasonic-temperature" / "config.toml"
    model = tmp / "demo" / "model.json"
    if not model.is_file():
        build_json(config, tmp / "demo")
    cfg = load_config(config)
    lines = ["| cycle | SOC RMSE / max after 600 s, % | coulomb counting, % |", "|---|---|---|"]
    for cycle in [cfg.cycle, *cfg.extra_cycles]:
        res = subprocess.run([sys.executable, "-m", "ecmgen.cli", "estimate", str(model),
                              str(cycle), *SCENARIO, "--json"], capture_output=True, text=True,
                             check=True)
        doc = json.loads(res.stdout)
        cc = doc["coulomb_counting"]
        name = "/".join(Path(cycle).parts[-2:])
        lines.append(f"| {name} | {doc['soc_rmse'] * 100:.2f} / "
                     f"{doc['soc_max_abs_after_600s'] * 100:.2f} | {cc['soc_rmse'] * 100:.1f} / "
                     f"{cc['soc_max_abs_after_600s'] * 100:.1f} |")
    return "\n".join(lines) + "\n"


def _bench(name: str):
    """bench/NAME.py as a module."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
    bench = sys.modules[name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def accuracy_matrix(_tmp: Path) -> str:
    """The committed baseline of the accuracy matrix as its table."""
    bench = _bench("accuracy_matrix")
    return bench.table(json.loads(bench.BASELINE.read_text())["configurations"])


def speed(_tmp: Path) -> str:
    """The committed baseline of bench/bench_speed.py as its table."""
    bench = _bench("bench_speed")
    doc = json.loads(bench.BASELINE.read_text())
    return bench.table(doc["cases"], doc["ref"])


BLOCKS = {"demo": demo, "surface-off": surface_off, "one-temperature": one_temperature,
          "estimator": estimator, "accuracy-matrix": accuracy_matrix, "speed": speed}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", nargs="+", choices=sorted(BLOCKS), help="these blocks only")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only or BLOCKS:
            text = RESULTS.read_text()
            RESULTS.write_text(replace_block(text, name, BLOCKS[name](Path(tmp))))
            print(f"docs/results.md: {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
