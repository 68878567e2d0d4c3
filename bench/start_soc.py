"""The start SOC of a drive record that opens anywhere: the shared Panasonic cycles cut at
openings of every kind, the start SOC ecmgen finds for each against the truth.

    python bench/start_soc.py [--model MODEL.json] [--windows 600,1200,1800]

Each of the eight shared cycles (25, 0, -10, -20 degC; US06 and HWFET) is taken whole
(it opens from a full cell, under load or after a soak) and cut at a fifth and at half of
its drive: under load (the next sample above 1 A), at the first sample of the next stop of
5 s or more, and 3 s into that stop (mid-relaxation). The truth is 1 + Ah / capacity at the
cut (the whole cycle starts full). For each opening: the start SOC of ``ecmgen validate``
(``start_estimate``: the voltage where the opening is settled, else the model over the
first window), its error and stated uncertainty, and the MAE of the cut record from that
start against the MAE from the true start; then the same from the voltage over each
window in ``--windows`` alone. Windows are chosen on the 25 and 0 degC cuts; the -10 and
-20 degC cuts are reported apart as the held-out half. The model: the demo's
(examples/panasonic-temperature), built here without C and plots unless given.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from ecmgen.parallel import ONE_BLAS_THREAD   # does not load numpy
import os

for _k, _v in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_k, _v)

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ECMGEN_SHARED_DATA") or REPO.parent / "shared" / "data")
CYCLES = [("25degC", "us06"), ("25degC", "hwfet-a"), ("0degC", "us06"), ("0degC", "hwfet"),
          ("n10degC", "us06"), ("n10degC", "hwfet"), ("n20degC", "us06"), ("n20degC", "hwfet")]


def openings(series):
    """(kind, index): the whole record, then under load, a stop, mid-relaxation at a
    fifth and half of the drive."""
    import numpy as np

    i, t = series.current_a, series.time_s
    drive = np.flatnonzero(np.abs(i) > 0.05)
    a, b = int(drive[0]), int(drive[-1])
    rest = np.abs(i) <= 0.05
    out = [("whole", 0)]
    for frac in (0.2, 0.5):
        k = a + int(frac * (b - a))
        out.append(("under load", k + int(np.flatnonzero(np.abs(i[k:]) > 1.0)[0])))
        for j in range(k, b):
            if rest[j] and not rest[j - 1]:
                e = j
                while e < b and rest[e]:
                    e += 1
                if t[e] - t[j] >= 5.0:
                    out += [("stop", j), ("mid-relaxation", j + int(np.searchsorted(t[j:], t[j] + 3.0)))]
                    break
    return out


def main(argv=None) -> int:
    import numpy as np

    from ecmgen.data.measure import read_timeseries
    from ecmgen.model.model import load_model
    from ecmgen.model.simulate import start_estimate, validate, window_start_soc

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model")
    ap.add_argument("--windows", default="600,1200,1800")
    args = ap.parse_args(argv)
    windows = [float(w) for w in args.windows.split(",") if w]
    if args.model:
        model = load_model(args.model)
    else:
        from ecmgen.config import load_config
        from ecmgen.pipeline import build
        cfg = load_config(REPO / "examples" / "panasonic-temperature" / "config.toml")
        with tempfile.TemporaryDirectory() as tmp:
            model = build(cfg, Path(tmp) / "out", plots=False, c_code=False).models[cfg.best]
    rows = []
    print(f"{'cycle':17s} {'opening':15s} {'truth':>6s} {'found':>6s} {'err %':>6s} {'sigma %':>7s} "
          f"{'MAE':>6s} {'true':>6s}  " + "  ".join(f"W{w:.0f}: err % / dMAE" for w in windows))
    for temp, name in CYCLES:
        series = read_timeseries(DATA / f"panasonic-18650pf-{temp}" / f"{name}.mat")
        q = series.coulomb_ah()
        for kind, k in openings(series):
            part = series.slice(k, len(series))
            truth = 1.0 + float(q[k]) / model.capacity_ah
            true_mae = validate(model, part, soc0=truth).overall.mae_v
            got = start_estimate(model, part)
            mae = validate(model, part, soc0=got.soc0).overall.mae_v
            per_w = []
            for w in windows:
                s = window_start_soc(model, part, w).soc0
                per_w.append((s - truth, validate(model, part, soc0=s).overall.mae_v - true_mae))
            rows.append((temp, kind, truth, got, mae - true_mae, per_w))
            print(f"{temp + '/' + name:17s} {kind:15s} {truth:6.3f} {got.soc0:6.3f} "
                  f"{100 * (got.soc0 - truth):+6.2f} {100 * got.sigma:7.2f} {1e3 * mae:6.1f} "
                  f"{1e3 * true_mae:6.1f}  " + "  ".join(
                      f"{100 * e:+6.2f} / {1e3 * d:+6.1f}" for e, d in per_w), flush=True)
    print()
    for label, held in (("25 and 0 degC (choice)", False), ("-10 and -20 degC (held out)", True)):
        sel = [r for r in rows if r[0].startswith("n") == held]
        err = np.array([r[3].soc0 - r[2] for r in sel])
        sig = np.array([r[3].sigma for r in sel])
        ok = np.sum((np.abs(err) <= 0.005) | (sig > 0.005))
        print(f"{label}: {len(sel)} openings; found within 0.5 % or said uncertain: {ok}; "
              f"|error| mean {100 * np.mean(np.abs(err)):.2f} %, within 2 sigma "
              f"{np.sum(np.abs(err) <= 2 * np.maximum(sig, 0.005))}; MAE against the true "
              f"start's {1e3 * np.mean([r[4] for r in sel]):+.2f} mV")
        for n, w in enumerate(windows):
            e = np.array([r[5][n][0] for r in sel])
            d = np.array([r[5][n][1] for r in sel])
            print(f"    window {w:.0f} s alone: |error| mean {100 * np.mean(np.abs(e)):.2f} %, "
                  f"within 0.5 %: {np.sum(np.abs(e) <= 0.005)}, MAE {1e3 * np.mean(d):+.2f} mV")
    return 0


if __name__ == "__main__":
    sys.exit(main())
