#!/usr/bin/env python3
"""How much of the generated C's tables `ecmgen verify` checks: corrupt one table entry at a
time in a copy of the C and count the copies verify fails.

For each model and numeric: `ecmgen codegen` writes the C and its golden vectors; N entries
are drawn at random (seeded) from every `static const` array of `<prefix>_ecm_<s>.c` (the
tables, grids and asinh(x)/x tables), each raised by --factor (an integer by at least one),
and `ecmgen verify --c COPY` run on each copy. Two figures per row: detected by the golden
vectors alone (a step differs: bit for bit in fixed point, beyond the tolerance in float)
and detected at all (vectors or the tables' fingerprint); for float, how many of the drawn
entries were a pair's difference (dy: the float tables hold each value with its float32
difference to the next row or point) and how many of those the vectors caught: +5 % of a
small difference (the OCV's few mV between temperature rows) can stay below the float
tolerance at every input. Then the two cases of the issue
(OCV at SOC 0.10 + 0.5 V, R0 at SOC 0.30 x 10, at the row nearest 25 degC) and the runs
that never ran (`--run true`, `--run echo`, an init that calls exit(0)).

Not drawn: entries the step never reads (a float table's last temperature row - or, without
a temperature axis, its last SOC point -, whose pairs the interpolation never reaches; the
asinh(x)/x nodes past the largest |i| / i0 of the current range) and entries +5 % leaves
unchanged (zeros); both are counted and printed.

    python bench/verify_coverage.py [--model A.json ...] [-n 60] [--seed 0] [--factor 1.05]
                                    [--dt-s DT]

Without --model: the demo (examples/panasonic-temperature) and the one-temperature example
(examples/panasonic-25degC), built once into bench/.cache/ (a few minutes).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / "bench" / ".cache" / "verify_coverage"
EXAMPLES = {"demo (4 temperatures)": REPO / "examples" / "panasonic-temperature" / "config.toml",
            "one temperature (25 degC)": REPO / "examples" / "panasonic-25degC" / "config.toml"}
ARRAY = re.compile(r"static const (float|int32_t) (\w+)\[(\d+)\] = \{(.*?)\};", re.S)


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ecmgen.cli", *map(str, args)],
                          capture_output=True, text=True)


def default_models() -> dict[str, Path]:
    out = {}
    for name, config in EXAMPLES.items():
        model = CACHE / config.parent.name / "model.json"
        if not model.is_file():
            print(f"building {config.parent.name} into {model.parent} ...", flush=True)
            res = cli("build", config, "--out", model.parent, "-q")
            if res.returncode != 0:
                sys.exit(f"build of {config} failed: {res.stderr.strip()}")
        out[name] = model
    return out


def arrays(src: str) -> list[dict]:
    out = []
    for m in ARRAY.finditer(src):
        toks = list(re.finditer(r"[^,\s]+", m.group(4)))
        out.append({"type": m.group(1), "name": m.group(2), "n": int(m.group(3)),
                    "start": m.start(4), "toks": toks})
    return out


def value(tok: str, fixed: bool):
    return int(tok) if fixed else float(tok.rstrip("f"))


def raised(tok: str, fixed: bool, factor: float) -> str | None:
    from ecmgen.c.codegen import c_float

    v = value(tok, fixed)
    if fixed:
        new = int(round(v * factor))
        if new == v:
            new = v + (1 if v >= 0 else -1) if v != 0 else v
        if new == v or not -2**31 <= new < 2**31:
            return None
        return str(new)
    if v == 0.0:
        return None
    new = c_float(np.float32(v) * np.float32(factor))
    return None if new == tok else new


def is_pair_table(spec, name: str) -> bool:
    """A float table of pairs (value, float32 difference to the next row or point)."""
    return not spec.fixed and re.match(r"(dis|chg)_(rows|tau|branch)|ocv_v|surface_per_volt|"
                                       r"age_scale", name) is not None


def dead(spec, name: str, n: int) -> set[int]:
    """Indices of the array ``name`` the step never reads (module doc)."""
    from ecmgen.c.qformat import cdr_nodes

    out: set[int] = set()
    n_t = spec.ocv.shape[0]
    if is_pair_table(spec, name):
        if name == "age_scale":
            rows = spec.age["grid"].n
        elif spec.temp:
            rows = n_t
        elif re.match(r"(dis|chg)_(tau|branch)", name):
            rows = 1                    # one row: read at weight 0, nothing dead
        else:                           # pairs along SOC: the last point's pair
            rows = (spec.ocv_grid.n if name in ("ocv_v", "surface_per_volt")
                    else spec.dirs[0 if name.startswith("dis") else 1].grid.n)
        if rows > 1:
            out |= set(range(n - n // rows, n))
    if name in ("bv_g", "cdr_g"):
        if name == "bv_g":
            i0 = min(float(np.min(d.i0)) for d in spec.dirs) / 2.0 ** spec.q["Q_I0"]
            x_max = spec.i_lim_a / i0
        else:
            x_max = spec.i_lim_a * spec.fx["g_k"] / 2.0 ** spec.fx["Q_GK"]
        x = cdr_nodes((n - 1) // 64 - 1)          # n = 64 (E + 1) + 1 nodes
        last = int(np.searchsorted(x, x_max)) + 1       # the node past the reach's segment
        out |= set(range(last, n))
    return out


def verdict(golden: Path, mine: Path, stem: str) -> tuple[bool, bool, str]:
    """(detected by the vectors, detected at all, verify's line)."""
    from ecmgen.c.verify import verify

    (v,) = [x for x in verify(golden, mine) if x.name == stem]
    if stem.endswith("_q"):             # fixed point: any differing step
        m = re.search(r"(\d+) differ", v.line)
    else:                               # float: beyond the tolerance
        m = re.search(r"(\d+) beyond the tolerance", v.line)
    return m is not None and int(m.group(1)) > 0, not v.passed, v.line


def one(model: Path, numeric: str, n: int, seed: int, factor: float, work: Path,
        dt_s: float | None = None) -> dict:
    from ecmgen.c.codegen import prepare
    from ecmgen.model import load_model

    golden = work / f"golden-{numeric}"
    dt = [] if dt_s is None else ["--dt-s", dt_s]
    res = cli("codegen", model, "--out", golden, "--numeric", numeric, "--prefix", "cell", "-q",
              *dt)
    if res.returncode != 0:
        sys.exit(res.stderr)
    spec = prepare(load_model(model), numeric=numeric, prefix="cell", dt_s=dt_s)
    fixed = numeric == "fixed"
    stem = "cell_ecm_q" if fixed else "cell_ecm_f32"
    src = (golden / f"{stem}.c").read_text()
    arrs = arrays(src)
    live, n_dead, n_zero = [], 0, 0
    for a in arrs:
        d = dead(spec, a["name"], a["n"])
        for k, tok in enumerate(a["toks"]):
            if k in d:
                n_dead += 1
            elif raised(tok.group(0), fixed, factor) is None:
                n_zero += 1
            else:
                live.append((a, k))
    rng = np.random.default_rng(seed)
    pick = [live[j] for j in sorted(rng.choice(len(live), size=min(n, len(live)), replace=False))]
    mine = work / f"mine-{numeric}"
    shutil.copytree(golden, mine)

    def run(a, k, new_tok):
        tok = a["toks"][k]
        at = a["start"] + tok.start()
        (mine / f"{stem}.c").write_text(src[:at] + new_tok + src[at + len(tok.group(0)):])
        return verdict(golden, mine, stem)

    by_vec = by_any = n_diff = diff_vec = 0
    misses = []
    for a, k in pick:
        tok = a["toks"][k].group(0)
        new = raised(tok, fixed, factor)
        v, anyhow, line = run(a, k, new)
        by_vec += v
        by_any += anyhow
        if is_pair_table(spec, a["name"]) and k % 2:
            n_diff += 1
            diff_vec += v
        if not v:
            misses.append(f"{a['name']}[{k}] {tok} -> {new}")
    cases = issue_cases(spec, arrs, run, fixed)
    (mine / f"{stem}.c").write_text(src)
    return {"n": len(pick), "vectors": by_vec, "any": by_any, "dead": n_dead, "zero": n_zero,
            "diff": n_diff, "diff_vectors": diff_vec,
            "live": len(live), "misses": misses, "cases": cases}


def issue_cases(spec, arrs, run, fixed: bool) -> list[str]:
    """OCV at SOC 0.10 + 0.5 V and R0 at SOC 0.30 x 10, at the row nearest 25 degC."""
    from ecmgen.c.codegen import c_float

    by = {a["name"]: a for a in arrs}
    row = 0
    if spec.temp:
        t = np.asarray(spec.temp_grid.x, dtype=np.float64) / (256.0 if fixed else 1.0)
        row = int(np.argmin(np.abs(t - 25.0)))
    width = 1 if fixed else 2
    out = []
    soc = lambda g: np.asarray(g.x, dtype=np.float64) / (2.0 ** 30 if fixed else 1.0)  # noqa: E731
    if "ocv_v" in by:
        k = int(np.argmin(np.abs(soc(spec.ocv_grid) - 0.10)))
        j = (row * spec.ocv_grid.n + k) * width
        tok = by["ocv_v"]["toks"][j].group(0)
        new = str(value(tok, True) + int(0.5 * 2 ** spec.q["Q_V"])) if fixed else \
            c_float(np.float32(value(tok, False) + 0.5))
        v, anyhow, line = run(by["ocv_v"], j, new)
        out.append(f"OCV at SOC 0.10 + 0.5 V: vectors {'FAIL' if v else 'pass'}, verify "
                   f"{'FAIL' if anyhow else 'PASS'}")
    d = spec.dirs[0]
    k = int(np.argmin(np.abs(soc(d.grid) - 0.30)))
    npar = (3 if spec.tau_t else 5) + (1 if spec.ocv_shared else 0)
    j = ((row * d.grid.n + k) * npar) * width
    tok = by["dis_rows"]["toks"][j].group(0)
    new = str(value(tok, True) * 10) if fixed else c_float(np.float32(value(tok, False) * 10))
    v, anyhow, line = run(by["dis_rows"], j, new)
    out.append(f"R0 at SOC 0.30 x 10: vectors {'FAIL' if v else 'pass'}, verify "
               f"{'FAIL' if anyhow else 'PASS'}")
    return out


def never_ran(model: Path, work: Path) -> list[str]:
    """--run true, --run echo and an init calling exit(0): each must fail."""
    golden = work / "golden-fixed"
    out = []
    for run in ("true", "echo"):
        res = cli("verify", golden, "--run", run)
        out.append(f"--run {run}: exit {res.returncode}")
    mine = work / "exit0"
    shutil.copytree(golden, mine)
    c = mine / "cell_ecm_q.c"
    src = c.read_text()
    src = src.replace("#include \"cell_ecm_q_config.h\"",
                      "#include \"cell_ecm_q_config.h\"\n#include <stdlib.h>", 1)
    src = re.sub(r"(void cell_init_q\([^)]*\)\n\{\n)", r"\1    exit(0);\n", src)
    c.write_text(src)
    res = cli("verify", golden, "--c", mine)
    out.append(f"init calls exit(0): exit {res.returncode}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, action="append", help="model.json (repeatable)")
    ap.add_argument("-n", type=int, default=60, help="entries drawn per model and numeric")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--factor", type=float, default=1.05)
    ap.add_argument("--dt-s", type=float, help="the fixed-dt C (default: variable dt)")
    args = ap.parse_args()
    models = {p.parent.name or str(p): p for p in args.model} if args.model else default_models()
    print(f"{'model':28} {'numeric':7} {'vectors':>9} {'verify':>9}   {'of them dy':>10}   "
          "live / never read / zero")
    extra = []
    for name, model in models.items():
        with tempfile.TemporaryDirectory(prefix="ecmgen-cov-") as tmp:
            for numeric in ("fixed", "float"):
                r = one(model, numeric, args.n, args.seed, args.factor, Path(tmp), args.dt_s)
                dy = f"{r['diff_vectors']} / {r['diff']}" if numeric == "float" else "-"
                print(f"{name:28} {numeric:7} {r['vectors']:>4} / {r['n']:<3} {r['any']:>4} / "
                      f"{r['n']:<3}  {dy:>10}   {r['live']} / {r['dead']} / {r['zero']}",
                      flush=True)
                if r["misses"]:
                    extra.append(f"{name} {numeric}: not moved by the vectors: "
                                 + ", ".join(r["misses"]))
                extra += [f"{name} {numeric}: {c}" for c in r["cases"]]
            extra += [f"{name}: {c}" for c in never_ran(model, Path(tmp))]
    print()
    print("\n".join(extra))


if __name__ == "__main__":
    main()
