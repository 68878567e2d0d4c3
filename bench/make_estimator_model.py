"""The four-temperature Panasonic 18650PF test model of the estimator.

Built from one-temperature fits, the estimator is developed and tested on
this stand-in: one curve-fit model per shared pulse test (``ocv = "pulses"``, today's
pipeline), stacked over temperature with ``stack_rc_tables`` / ``OcvOverTemperature``, plus
the per-temperature diffusion RC pair and Butler-Volmer i0 measured in
/work/notes/temperature-findings.md (section 3). Breakpoints: the median cell temperature
during the pulses. Writes tests/data/panasonic-4t-model.json (deterministic):

    .venv/bin/python bench/make_estimator_model.py [--out PATH]
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from ecmgen.config import load_config
from ecmgen.model.model import EcmModel, OcvOverTemperature, stack_rc_tables
from ecmgen.pipeline import fit_models, prepare

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
OUT = REPO / "tests" / "data" / "panasonic-4t-model.json"

# folder, table temperature (degC), r_diff (ohm), tau_diff (s), i0 (A): findings section 3
ROWS = [("n20degC", -19.9, 0.117, 709.0, 0.83),
        ("n10degC", -9.9, 0.0819, 539.0, 1.21),
        ("0degC", 0.6, 0.0593, 372.0, 2.75),
        ("25degC", 25.8, 0.0262, 454.0, 17.5)]

CONFIG = """[cell]
capacity_ah = 2.9
[data]
pulses = "{pulses}"
pulses_soc0 = 1.0
ocv = "pulses"
[fit]
methods = ["curve"]
[c]
numeric = "float"
"""


def one_temperature(folder: str):
    pulses = DATA / f"panasonic-18650pf-{folder}" / "hppc.mat"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.toml"
        path.write_text(CONFIG.format(pulses=pulses))
        cfg = load_config(path)
        inputs = prepare(cfg)
        models, _ = fit_models(cfg, inputs)
    return models["curve"]


def build() -> EcmModel:
    models = [one_temperature(r[0]) for r in ROWS]
    temps = np.array([r[1] for r in ROWS])
    branch = {"r_diff_ohm": np.array([r[2] for r in ROWS]),
              "tau_diff_s": np.array([r[3] for r in ROWS]),
              "i0_a": np.array([r[4] for r in ROWS])}
    tables = {}
    for d in ("charge", "discharge"):
        stacked = stack_rc_tables([m.table(d) for m in models], temps)
        tables[d] = replace(stacked, **branch)
    soc = np.unique(np.concatenate([m.ocv.soc for m in models]))
    ocv = OcvOverTemperature(temps, soc, np.vstack([m.ocv.ocv_at(soc) for m in models]))
    notes = tuple(f"{r[0]}: {n}" for r, m in zip(ROWS, models) for n in m.notes) + (
        "test model of the estimator (bench/make_estimator_model.py): per-temperature curve "
        "fits stacked; r_diff, tau_diff, i0 from temperature-findings.md section 3",)
    return EcmModel(capacity_ah=2.9, ocv=ocv, charge=tables["charge"],
                    discharge=tables["discharge"], method="curve",
                    inputs=tuple(r for m in models for r in m.inputs), notes=notes,
                    direction_deadband_a=0.029)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args()
    model = build()
    model.save(Path(args.out))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
