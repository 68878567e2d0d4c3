"""diagnose on synthetic cells with one hidden effect each (ecmgen.diagnosis.synthcell): the
Done-when statistics, 10 random cells per effect.

Each cell: pulse test + C/20 OCV test -> base model (10 s pulses with 30 s relaxation,
parameters averaged over C-rates; OCV = mean of the branches), then a ~3 h drive cycle
with rests and charges, 1 mV voltage noise, 5 mA current noise, logged temperature;
diagnose holds out the last 40 % of the cycle. For every effect it must be named first
in >= 9 of 10 cells with the held-out MAE down by >= 40 %; with no hidden effect,
nothing may be named in >= 9 of 10 cells. (Same cells as
bench/sweep_diagnose_synthetic.py, which prints the table.)"""

from __future__ import annotations

import pytest

from ecmgen.diagnosis.search import diagnose
from ecmgen.model.effects import EFFECT_NAMES
from ecmgen.diagnosis.synthcell import random_cell

pytestmark = pytest.mark.slow

CELLS = 10
FIRST_SEED = 1000


def _run(effect):
    out = []
    for k in range(CELLS):
        cell = random_cell(FIRST_SEED + k, effect)
        r = diagnose(cell.base_model(), cell.drive_cycle())
        out.append((r.effects, 1.0 - r.mae_after_v / r.mae_before_v))
    return out


@pytest.mark.parametrize("effect", EFFECT_NAMES)
def test_hidden_effect_is_named_first_and_the_error_falls(effect):
    runs = _run(effect)
    good = [named[:1] == (effect,) and drop >= 0.4 for named, drop in runs]
    assert sum(good) >= 9, runs


def test_no_hidden_effect_names_nothing():
    runs = _run(None)
    assert sum(named == () for named, _ in runs) >= 9, runs
