"""Synthetic ageing studies: N cells x M check-ups with known trends, for the fleet's
tests and benchmarks.

A :class:`Study` is one cell type (a fresh 2RC model at the rated capacity, from
:func:`~ecmgen.diagnosis.synthcell.random_base`) and its cells, each with its own
:class:`CellAgeing`: a cell-to-cell spread of resistance and capacity when fresh, and
linear trends per check-up -- the resistances (R0, R_fast, R_slow alike; the time
constants unchanged) grow by ``r_growth`` of their fresh value, the capacity fades by
``fade`` of its fresh value. A cell may be an outlier (it ages ``outlier_factor`` times
faster). At each check-up the cell is measured as :class:`SyntheticCell` measures one
(thermal model, noise on voltage, current and temperature, a 0.1 mV voltage step):

- ``pulses.csv``: a short pulse test from full (rested), 10 s pulses at a few SOC levels;
- ``capacity.csv``: a C/10 discharge from full to empty and a C/10 charge back (the
  capacity test, also the OCV);
- ``drive.csv`` (``with_cycle``): a short drive cycle with rests, for the validation.

:func:`write_study` writes them under ``folder/<cell>/<checkup>/`` with a build config
(``cell.toml``, the fast five-point fits, no C) and ``manifest.csv``
(``cell,checkup,config,cycles,date``) plus ``truth.csv``: per row the true capacity and
the true parameters at the SOC points.

    study = make_study(cells=6, checkups=3, seed=1)
    manifest = write_study(study, "study")
"""

from __future__ import annotations

import csv
import datetime as dt
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..data.measure import TimeSeries
from ..files import write_atomic
from ..model import effects as fx
from ..model.model import EcmModel
from .synthcell import SyntheticCell, random_base

# the SOC points truth.csv gives the parameters at (and the fleet table by default)
TRUTH_SOC = (0.2, 0.5, 0.8)
PULSE_LEVELS = (0.9, 0.7, 0.5, 0.3, 0.15)
START_DATE = dt.date(2026, 1, 5)


@dataclass(frozen=True)
class CellAgeing:
    """One cell's truth: fresh resistance and capacity relative to the type's, and its
    linear trends per check-up (fractions of the fresh value)."""

    name: str
    seed: int
    r_scale: float          # fresh resistances / the type's
    q_scale: float          # fresh capacity / the rated one
    r_growth: float         # resistance growth per check-up
    fade: float             # capacity loss per check-up
    outlier: bool = False

    def resistance_factor(self, checkup: int) -> float:
        """The cell's resistances at check-up ``checkup`` / the type's fresh ones."""
        return self.r_scale * (1.0 + self.r_growth * checkup)

    def capacity_factor(self, checkup: int) -> float:
        """The cell's capacity at check-up ``checkup`` / the rated one."""
        return self.q_scale * (1.0 - self.fade * checkup)


@dataclass(frozen=True)
class Study:
    """A cell type, its cells and the check-up plan (``cycles_per_checkup`` full cycles
    between check-ups, ``days_per_checkup`` days)."""

    base: EcmModel
    cells: tuple[CellAgeing, ...]
    checkups: int
    cycles_per_checkup: int = 200
    days_per_checkup: int = 28
    seed: int = 0

    @property
    def rated_ah(self) -> float:
        return self.base.capacity_ah

    def hidden(self, cell: CellAgeing, checkup: int) -> EcmModel:
        """The cell's true model at a check-up: the type's tables scaled by its resistance
        factor; the capacity by a capacity_error effect (the C-rates stay the rated's)."""
        k = cell.resistance_factor(checkup)

        def scaled(t):
            return replace(t, r0_ohm=k * t.r0_ohm, r_fast_ohm=k * t.r_fast_ohm,
                           r_slow_ohm=k * t.r_slow_ohm)

        model = replace(self.base, charge=scaled(self.base.charge),
                        discharge=scaled(self.base.discharge))
        return model.with_effects((fx.CapacityError(cell.capacity_factor(checkup)),))

    def measured(self, cell: CellAgeing, checkup: int) -> SyntheticCell:
        return SyntheticCell(hidden=self.hidden(cell, checkup), effect=None,
                             seed=cell.seed * 1000 + checkup)

    def truth(self, cell: CellAgeing, checkup: int, soc=TRUTH_SOC) -> dict:
        """The true capacity and discharge parameters at the SOC points (column names
        as the fleet table's)."""
        row = {"cell": cell.name, "checkup": str(checkup), "cycles": self.cycles(checkup),
               "outlier": int(cell.outlier),
               "capacity_ah": self.rated_ah * cell.capacity_factor(checkup)}
        k = cell.resistance_factor(checkup)
        for s in soc:
            p = self.base.discharge.at(float(s))
            tag = f"soc{round(100 * s):02d}"
            for name in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
                row[f"{name.removesuffix('_ohm')}_{tag}_ohm"] = k * float(p[name])
            for name in ("tau_fast_s", "tau_slow_s"):
                row[f"{name.removesuffix('_s')}_{tag}_s"] = float(p[name])
        return row

    def cycles(self, checkup: int) -> int:
        return checkup * self.cycles_per_checkup

    def date(self, checkup: int) -> str:
        return (START_DATE + dt.timedelta(days=checkup * self.days_per_checkup)).isoformat()


def make_study(cells: int = 6, checkups: int = 3, seed: int = 0, *, r_growth: float = 0.10,
               fade: float = 0.04, spread: float = 0.05, outliers: int = 1,
               outlier_factor: float = 3.0, capacity_ah: float = 3.0) -> Study:
    """A study of ``cells`` cells of one random type: fresh resistance spread
    ``spread`` (relative, normal), capacity spread half that; per check-up the
    resistances grow by ``r_growth`` and the capacity fades by ``fade`` (each cell's
    rates drawn within +-20 % of them); the last ``outliers`` cells age
    ``outlier_factor`` times faster."""
    rng = np.random.default_rng(seed)
    base = random_base(rng, capacity_ah=capacity_ah)
    out = []
    for n in range(cells):
        outlier = n >= cells - outliers
        speed = outlier_factor if outlier else 1.0
        out.append(CellAgeing(
            name=f"cell{n + 1:02d}", seed=seed * 100 + n + 1,
            r_scale=float(1.0 + spread * rng.standard_normal()),
            q_scale=float(1.0 + 0.5 * spread * rng.standard_normal()),
            r_growth=speed * r_growth * float(rng.uniform(0.8, 1.2)),
            fade=speed * fade * float(rng.uniform(0.8, 1.2)), outlier=outlier))
    last = max(checkups - 1, 0)
    if any(c.capacity_factor(last) < 0.3 for c in out):
        raise ValueError("the study fades below 30 % of the capacity; less fade or fewer "
                         "check-ups")
    return Study(base=base, cells=tuple(out), checkups=checkups, seed=seed)


# --------------------------------------------------------------------------- writing

def _csv_text(series: TimeSeries) -> str:
    """The canonical CSV at a cycler's resolution (ms, 0.1 mA, 0.1 mV, 0.1 degC)."""
    cols = [series.time_s, series.current_a, series.voltage_v, series.temperature_c]
    lines = ["time_s,current_a,voltage_v,temperature_c"]
    lines += [f"{t:.3f},{i:.4f},{v:.4f},{c:.1f}" for t, i, v, c in zip(*cols)]
    return "\n".join(lines) + "\n"


CONFIG = """\
# a synthetic check-up (ecmgen.diagnosis.synthstudy): the fast five-point fits, no C
[cell]
capacity_ah = {rated:g}

[data]
pulses = "pulses.csv"
ocv = "capacity.csv"
ocv_branch = "both"
{cycle}
[fit]
methods = ["ga", "lm"]

[c]
numeric = []
"""


def write_checkup(study: Study, cell: CellAgeing, checkup: int, folder: Path,
                  with_cycle: bool = True) -> Path:
    """The records of one check-up and its config into ``folder``; returns the config."""
    folder.mkdir(parents=True, exist_ok=True)
    sc = study.measured(cell, checkup)
    pulses = sc.pulse_test(levels=PULSE_LEVELS, c_rates_discharge=(1.0, 2.0),
                           c_rates_charge=(1.0,), rest_s=300.0)
    write_atomic(folder / "pulses.csv", _csv_text(pulses))
    write_atomic(folder / "capacity.csv", _csv_text(sc.ocv_test(c_rate=0.1, dt=30.0)))
    cycle = ""
    if with_cycle:
        drive = sc.drive_cycle(soc_start=0.9, soc_end=0.6, mean_c_rate=1.0)
        write_atomic(folder / "drive.csv", _csv_text(drive))
        cycle = 'cycle = "drive.csv"\n'
    config = folder / "cell.toml"
    write_atomic(config, CONFIG.format(rated=study.rated_ah, cycle=cycle))
    return config


def write_study(study: Study, folder: str | Path, with_cycle: bool = True) -> Path:
    """Every check-up of every cell under ``folder/<cell>/<checkup>/``, ``manifest.csv``
    (cell, checkup, config, cycles, date) and ``truth.csv``; returns the manifest."""
    folder = Path(folder)
    rows, truth = [], []
    for cell in study.cells:
        for k in range(study.checkups):
            config = write_checkup(study, cell, k, folder / cell.name / str(k), with_cycle)
            rows.append([cell.name, str(k), config.relative_to(folder).as_posix(),
                         str(study.cycles(k)), study.date(k)])
            truth.append(study.truth(cell, k))
    manifest = folder / "manifest.csv"
    write_atomic(manifest, _table([["cell", "checkup", "config", "cycles", "date"]] + rows))
    names = list(truth[0])
    write_atomic(folder / "truth.csv",
                 _table([names] + [[_cell_text(r[n]) for n in names] for r in truth]))
    return manifest


def _cell_text(v) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _table(rows: list[list[str]]) -> str:
    import io

    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue()


def read_truth(path: str | Path) -> list[dict]:
    """truth.csv as dicts (numbers as floats, cell and checkup as text)."""
    with open(path, newline="") as f:
        return [{k: v if k in ("cell", "checkup") else float(v) for k, v in r.items()}
                for r in csv.DictReader(f)]
