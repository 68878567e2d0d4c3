"""Benchmark: peak memory of ``ecmgen validate`` per CSV row.

A synthetic drive cycle (1 s samples, the canonical CSV header; about 35 bytes a row) of
ROWS rows is validated by a fresh process, which reports its own peak resident memory;
the same for a 10 000-row file gives the fixed part, and the difference divided by the
difference in rows is the memory per row. The bar: a 6 M-row CSV under 1 GB, i.e. well
under 160 bytes a row.

    python bench/bench_memory.py [--rows 2000000] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = """
import resource, sys
from ecmgen.cli import main
code = main(sys.argv[1:])
print("PEAK", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, file=sys.stderr)
sys.exit(code)
"""


def write_inputs(folder: Path, rows: int) -> tuple[Path, Path]:
    """model.json of a plausible 2RC cell, and a drive cycle of ``rows`` 1-s samples it
    generated (written in blocks: the writer itself stays small)."""
    import numpy as np

    from ecmgen.model import EcmModel, OcvTable, RcTable
    from ecmgen.model.simulate import simulate

    soc = np.linspace(0.0, 1.0, 11)
    ocv = OcvTable(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(2.5 * soc))
    n = soc.size
    table = RcTable(soc=soc, r0_ohm=0.02 + 0.01 * (1 - soc) ** 2, r_fast_ohm=np.full(n, 0.008),
                    tau_fast_s=np.full(n, 2.0), r_slow_ohm=0.01 + 0.005 * (1 - soc),
                    tau_slow_s=np.full(n, 60.0), fit_error=np.zeros(n),
                    converged=np.ones(n, bool))
    model = EcmModel(capacity_ah=2.9, ocv=ocv, charge=table, discharge=table,
                     method="synthetic", seed=0, direction_deadband_a=0.029)
    model_path = model.save(folder / "model.json")
    # a block of 2 h, repeated: a current of no net charge (40 whole sine periods), so
    # that every block starts from the same SOC
    t = np.arange(0, 7200.0)
    i = 2.0 * np.sin(2.0 * np.pi * 40.0 * t / 7200.0)
    v = simulate(model, t, i, 0.6).voltage_v
    block = [f"{a:.0f},{b:.6f},{c:.6f}\n" for a, b, c in zip(t, i, v)]
    path = folder / f"cycle-{rows}.csv"
    with open(path, "w") as fh:
        fh.write("time_s,current_a,voltage_v\n")
        done = 0
        while done < rows:
            k = min(rows - done, len(block))
            fh.writelines(f"{done + int(line.split(',', 1)[0])},{line.split(',', 1)[1]}"
                          for line in block[:k])     # the time axis runs on
            done += k
    return model_path, path


def peak_bytes(model: Path, cycle: Path) -> tuple[int, dict]:
    proc = subprocess.run([sys.executable, "-c", CHILD, "validate", str(model), str(cycle),
                           "--soc0", "0.6", "--json"], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(proc.stderr)
    peak = int(proc.stderr.rsplit("PEAK", 1)[1].split()[0])
    return peak, json.loads(proc.stdout)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--keep", help="write the files here (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        small_rows = 10_000
        model, small = write_inputs(folder, small_rows)
        _, big = write_inputs(folder, args.rows)
        base, _ = peak_bytes(model, small)
        peak, doc = peak_bytes(model, big)
        per_row = (peak - base) / (args.rows - small_rows)
        print(f"validate, {args.rows} rows ({big.stat().st_size / 1e6:.0f} MB CSV): peak "
              f"{peak / 1e6:.0f} MB, {small_rows} rows: {base / 1e6:.0f} MB -> "
              f"{per_row:.0f} bytes per row; 6 M rows would peak at about "
              f"{(base + per_row * 6e6) / 1e9:.2f} GB (MAE {doc['mae_v'] * 1e3:.2f} mV)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
