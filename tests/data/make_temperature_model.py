#!/usr/bin/env python3
"""Make tests/data/panasonic-temperature-model.json: a realistic model over temperature for
the C tests, from one-temperature fits.

How it is made (run from the repository root; needs ../shared/data, about 2 minutes):

1. one-temperature models with the existing pipeline, one per shared pulse test
   (panasonic-18650pf-{n20degC,n10degC,0degC,25degC}/hppc.mat; method "curve",
   ocv "pulses", pulses_soc0 = 1), at the pulse tests' cell temperatures
   -19.9 / -9.9 / 0.6 / 25.8 degC;
2. their RC tables stacked over temperature (ecmgen.model.model.stack_rc_tables), their
   OCVs as rows of an OcvOverTemperature;
3. a diffusion RC pair (r_diff 117 / 82 / 59 / 26 mOhm, tau_diff 710 / 540 / 370 / 450 s)
   and a Butler-Volmer fast branch (i0 0.83 / 1.21 / 2.75 / 17.5 A) at those temperatures,
   the same in both directions;
4. everything resampled onto the grid the temperature fitter will give: 14 rows at
   -20, -15, ..., 45 degC (5 K; clamped beyond 25.8 degC, as the model is) x 21 SOC points
   (0, 0.05, ..., 1) for the RC tables and the OCV, the values rounded to 6 significant
   digits (OCV 8): a small file; the tests compare the C with this model, not with the fits.

Usage: python tests/data/make_temperature_model.py [OUT.json]
       python tests/data/make_temperature_model.py --compact MODEL.json   (step 4's rounding)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
FOLDERS = (("panasonic-18650pf-n20degC", -19.9), ("panasonic-18650pf-n10degC", -9.9),
           ("panasonic-18650pf-0degC", 0.6), ("panasonic-18650pf-25degC", 25.8))
R_DIFF = (0.117, 0.082, 0.059, 0.026)
TAU_DIFF = (710.0, 540.0, 370.0, 450.0)
I0 = (0.83, 1.21, 2.75, 17.5)
T_GRID = np.arange(-20.0, 45.0 + 1e-9, 5.0)
SOC_GRID = np.round(np.linspace(0.0, 1.0, 21), 12)


def fit_one(folder: str, tmp: Path):
    from ecmgen.config import load_config
    from ecmgen.pipeline import fit_models, prepare

    cfg = tmp / f"{folder}.toml"
    cfg.write_text(f"""[cell]
capacity_ah = 2.9
[data]
pulses = "{DATA / folder / 'hppc.mat'}"
pulses_soc0 = 1.0
ocv = "pulses"
[fit]
methods = ["curve"]
""")
    c = load_config(cfg)
    inputs = prepare(c)
    models, _ = fit_models(c, inputs)
    return models["curve"]


def resample(models, temps):
    from dataclasses import replace

    from ecmgen.model.model import (BRANCH_FIELDS, RC_FIELDS, EcmModel, OcvOverTemperature,
                                    RcTable, stack_rc_tables)

    temps = np.asarray(temps, dtype=np.float64)
    branch = {"r_diff_ohm": np.array(R_DIFF), "tau_diff_s": np.array(TAU_DIFF),
              "i0_a": np.array(I0)}
    tables = {}
    for d in ("charge", "discharge"):
        st = stack_rc_tables([m.table(d) for m in models], temps)
        st = replace(st, **branch)
        cols = {k: np.vstack([st.at(SOC_GRID, t)[k] for t in T_GRID]) for k in RC_FIELDS}
        extra = {k: np.array([float(st.along_temperature(branch[k], t)) for t in T_GRID])
                 for k in BRANCH_FIELDS}
        n = (T_GRID.size, SOC_GRID.size)
        tables[d] = RcTable(soc=SOC_GRID, temperature_c=T_GRID, fit_error=np.zeros(n),
                            converged=np.ones(n, bool), **cols, **extra)
    ocv_rows = OcvOverTemperature(temps, SOC_GRID,
                                  np.vstack([m.ocv.ocv_at(SOC_GRID) for m in models]))
    ocv = OcvOverTemperature(T_GRID, SOC_GRID,
                             np.vstack([ocv_rows.ocv_at(SOC_GRID, t) for t in T_GRID]))
    m0 = models[-1]
    return EcmModel(capacity_ah=m0.capacity_ah, ocv=ocv, charge=tables["charge"],
                    discharge=tables["discharge"], method="curve", seed=0,
                    direction_deadband_a=m0.direction_deadband_a,
                    notes=("test model: four one-temperature curve fits (Panasonic 18650PF "
                           "at -19.9/-9.9/0.6/25.8 degC) stacked, with diffusion and "
                           "Butler-Volmer branches, resampled onto 5 K x 21 SOC points; "
                           "tests/data/make_temperature_model.py",))


def compact(model):
    """Every RC value rounded to 6 significant digits (the OCV to 8), fit_error set to 0."""
    from ecmgen.model.model import BRANCH_FIELDS, RC_FIELDS, OcvOverTemperature

    def r6(a, digits=6):
        return np.array([float(f"{v:.{digits}g}") for v in np.ravel(a)]).reshape(np.shape(a))

    def table(t):
        kw = {k: r6(getattr(t, k)) for k in RC_FIELDS}
        kw.update({k: r6(getattr(t, k)) for k in BRANCH_FIELDS if getattr(t, k) is not None})
        return replace(t, fit_error=np.zeros_like(t.fit_error), **kw)

    from dataclasses import replace
    ocv = np.maximum.accumulate(r6(model.ocv.ocv_v, 8), axis=1)     # 10 nV, still monotonic
    ocv = OcvOverTemperature(model.ocv.temperature_c, model.ocv.soc, ocv)
    return replace(model, ocv=ocv, charge=table(model.charge), discharge=table(model.discharge))


def main(argv) -> int:
    if len(argv) > 2 and argv[1] == "--compact":
        from ecmgen.model import load_model

        compact(load_model(argv[2])).save(argv[2])
        return 0
    out = Path(argv[1]) if len(argv) > 1 else Path(__file__).with_name(
        "panasonic-temperature-model.json")
    with tempfile.TemporaryDirectory() as tmp:
        models = []
        for folder, t in FOLDERS:
            print(f"fitting {folder} ({t} degC)", flush=True)
            models.append(fit_one(folder, Path(tmp)))
    model = compact(resample(models, [t for _, t in FOLDERS]))
    model.save(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
