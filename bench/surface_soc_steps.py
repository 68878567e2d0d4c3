"""The surface SOC's gain judged on records that never chose it: the SOC-step discharges.

    python bench/surface_soc_steps.py [--config NAME] [--gains 0,0.3,0.5,0.7,1]

[model] surface_soc_gain (lambda) was chosen leaving one temperature out on the shared
Panasonic drive cycles (docs/results.md, "The surface SOC"), so those cycles cannot judge
it again. The SOC-step files can: each holds the 1C discharges that move a pulse test
from one SOC level to the next, which a model built from the pulse test alone (the
accuracy matrix's ``pan4``: no steps file) never saw. Each pulse test with its steps merged
in (ecmgen.data.steps.merge_soc_steps) is simulated whole from full at its measured cell
temperature, with each gain; the table gives the MAE over the step files' samples above
10 % SOC, in mV, per temperature.

The shared data: ../shared/data beside the repository, or $ECMGEN_SHARED_DATA.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

import accuracy_matrix as am


def step_errors(model, gains) -> dict:
    """{temperature: {gain: MAE in mV over the step samples above 10 % SOC}}."""
    from ecmgen.data.measure import read_timeseries
    from ecmgen.data.steps import merge_soc_steps
    from ecmgen.model.simulate import validate

    out = {}
    for t in am.PANASONIC_C:
        pulses = read_timeseries(am.panasonic(t, "hppc.mat"), None, capacity_ah=2.9)
        steps = read_timeseries(am.panasonic(t, "hppc-soc-steps.mat"), None, capacity_ah=2.9)
        merged, _ = merge_soc_steps(pulses, steps)
        logged = set(np.round(pulses.time_s, 3))
        from_steps = np.array([x not in logged for x in np.round(merged.time_s, 3)])
        out[am.PANASONIC_C[t]] = {}
        for g in gains:
            v = validate(replace(model, surface_soc_gain=g), merged, 1.0)
            k = from_steps & (v.sim.soc > 0.10)
            out[am.PANASONIC_C[t]][g] = 1e3 * float(np.mean(np.abs(v.error_v[k])))
    return out


def main(argv=None) -> int:
    from ecmgen.config import load_config
    from ecmgen.pipeline import build

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="pan4", help="an accuracy-matrix configuration "
                                                      "without steps files")
    ap.add_argument("--gains", default="0,0.3,0.5,0.7,1")
    args = ap.parse_args(argv)
    gains = [float(g) for g in args.gains.split(",")]
    conf = am.configurations()[args.config]
    if "steps" in conf.toml:
        raise SystemExit(f"{args.config}: its model saw the steps files; take one without")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.toml"
        path.write_text(conf.toml)
        result = build(load_config(path), Path(tmp) / "out", plots=False, c_code=False)
        model = result.models[result.best]
    if not model.discharge.has_diffusion:
        raise SystemExit(f"{args.config}: the model has no diffusion pair (no surface SOC)")
    table = step_errors(model, gains)
    print(f"{args.config}: MAE (mV) over the SOC-step samples above 10 % SOC, by "
          "surface_soc_gain\n")
    print("| temperature | " + " | ".join(f"{g:g}" for g in gains) + " |")
    print("|---|" + "---|" * len(gains))
    for t, row in table.items():
        print(f"| {t} | " + " | ".join(f"{row[g]:.1f}" for g in gains) + " |")
    total = {g: sum(row[g] for row in table.values()) for g in gains}
    print("| sum | " + " | ".join(f"{total[g]:.1f}" for g in gains) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
