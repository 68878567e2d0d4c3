"""Helpers shared by the C code-generation and target tests (no tests of its own).

``realistic_model`` builds a Panasonic-18650PF-like 2RC model: the OCV comes from the real
C/20 test (mean of the charge and discharge branches) when the shared data is present, the
RC tables are irregular over SOC the way fitted tables are (seeded), charge != discharge.
Set ``ECMGEN_TEST_MODEL=/path/to/model.json`` to run the real-data tests on a fitted model
instead (the fitting pipeline's Panasonic 25 degC model).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from conftest import PANASONIC

CYCLES = ("us06.mat", "hwfet-a.mat")


def load_mat(path: Path):
    import scipy.io

    from ecmgen.data.measure import TimeSeries

    m = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)["meas"]
    return TimeSeries(np.asarray(m.Time, float), np.asarray(m.Current, float),
                      np.asarray(m.Voltage, float), source=str(path))


def _ocv_from_data(soc_grid: np.ndarray, capacity_ah: float):
    path = PANASONIC / "ocv-c20.mat"
    if not path.exists():
        return None
    import scipy.io

    m = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)["meas"]
    i, v, ah = (np.asarray(x, float) for x in (m.Current, m.Voltage, m.Ah))
    soc = 1.0 + (ah - ah.max()) / capacity_ah
    branches = []
    for sel in (i < -0.05, i > 0.05):
        s, vv = soc[sel], v[sel]
        order = np.argsort(s)
        branches.append(np.interp(soc_grid, s[order], vv[order]))
    ocv = 0.5 * (branches[0] + branches[1])
    # strictly increasing (the C/20 ends are flat or noisy)
    ocv = np.maximum.accumulate(ocv + 1e-4 * soc_grid)
    return np.maximum(ocv, 2.5) + 1e-6 * np.arange(ocv.size)


def realistic_model(n_rc: int = 15, seed: int = 1, n_ocv: int = 41, capacity_ah: float = 2.9):
    from ecmgen.model import EcmModel, OcvTable, RcTable

    rng = np.random.default_rng(seed)
    soc_ocv = np.linspace(0.0, 1.0, n_ocv)
    ocv = _ocv_from_data(soc_ocv, capacity_ah)
    if ocv is None:  # NCA-like shape without the data
        ocv = 3.0 + 1.05 * soc_ocv + 0.2 * (1 - np.exp(-12 * soc_ocv)) - 0.08 * np.sin(3 * soc_ocv)
    soc = np.sort(np.concatenate(([0.0, 1.0], rng.uniform(0.02, 0.98, n_rc - 2))))

    def table(scale):
        n = soc.size
        jit = lambda a: 1.0 + a * rng.standard_normal(n)  # noqa: E731 - fitted tables jump
        return RcTable(soc=soc,
                       r0_ohm=scale * (0.016 + 0.014 * (1 - soc) ** 3) * jit(0.05),
                       r_fast_ohm=scale * (0.006 + 0.010 * (1 - soc) ** 2) * jit(0.15),
                       tau_fast_s=np.clip(4.0 + 8.0 * rng.random(n) * (1.2 - soc), 1.0, 20.0),
                       r_slow_ohm=scale * (0.008 + 0.020 * (1 - soc) ** 4) * jit(0.2),
                       tau_slow_s=np.clip(60 + 600 * rng.random(n) ** 2, 30.0, 1000.0),
                       fit_error=np.zeros(n), converged=np.ones(n, bool))

    return EcmModel(capacity_ah=capacity_ah, ocv=OcvTable(soc_ocv, ocv), charge=table(0.85),
                    discharge=table(1.0), method="handmade", seed=seed,
                    direction_deadband_a=0.029)


def panasonic_model():
    """The fitted model from $ECMGEN_TEST_MODEL, else realistic_model()."""
    path = os.environ.get("ECMGEN_TEST_MODEL")
    if path:
        from ecmgen.model import load_model

        return load_model(path)
    return realistic_model()


def cycle(name: str):
    path = PANASONIC / name
    if not path.exists():
        pytest.skip(f"real data not found at {path} (expected ../shared/data beside the repo)")
    return load_mat(path)


def soc0_of(model, series) -> float:
    from ecmgen.model.simulate import initial_soc

    return float(initial_soc(model, series))
