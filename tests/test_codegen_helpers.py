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

from conftest import PANASONIC, SHARED_DATA

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


# the issue-8 diffusion / Butler-Volmer values at the shared pulse tests' temperatures
BRANCH_T_C = np.array([-19.9, -9.9, 0.6, 25.8])
BRANCH_R_DIFF = np.array([0.117, 0.082, 0.059, 0.026])
BRANCH_TAU_DIFF = np.array([710.0, 540.0, 370.0, 450.0])
BRANCH_I0 = np.array([0.83, 1.21, 2.75, 17.5])
TEMPERATURE_MODEL = Path(__file__).resolve().parent / "data" / "panasonic-temperature-model.json"


def temperature_model(n_t: int = 4, n_rc: int = 20, seed: int = 3, branches: bool = False,
                      t_lo: float = -20.0, t_hi: float = 25.0, ocv_on_rc_grid: bool = False):
    """realistic_model over temperature: n_t rows from t_lo to t_hi degC, resistances and
    time constants scaled per row the way the shared cold pulse tests scale them (roughly
    Arrhenius, 3 to 4x from 25 to -20 degC), the OCV shifted by a few mV per row; with
    ``branches`` the diffusion pair and Butler-Volmer i0 of the issue, linear in T; with
    ``ocv_on_rc_grid`` the OCV sampled at the RC tables' SOC points (as a fitter that puts
    every table on one grid gives it) instead of its own 41 points."""
    from dataclasses import replace

    from ecmgen.model import EcmModel
    from ecmgen.model.model import RC_FIELDS, OcvOverTemperature, RcTable

    base = realistic_model(n_rc=n_rc, seed=seed)
    temps = np.linspace(t_lo, t_hi, n_t)
    rng = np.random.default_rng(seed + 100)
    f = np.exp(2600.0 * (1.0 / (temps + 273.15) - 1.0 / 298.15))     # 1 at 25, ~4 at -20

    def table(t: RcTable) -> RcTable:
        cols = {}
        for k in RC_FIELDS:
            v = getattr(t, k)[0]
            if k.startswith("r"):
                rows = [v * fk * (1.0 + 0.05 * rng.standard_normal(v.size)) for fk in f]
            else:
                rows = [v * (1.0 + 0.3 * (fk - 1.0) / 3.0) for fk in f]
            cols[k] = np.vstack(rows)
        extra = {}
        if branches:
            extra = {"r_diff_ohm": np.interp(temps, BRANCH_T_C, BRANCH_R_DIFF),
                     "tau_diff_s": np.interp(temps, BRANCH_T_C, BRANCH_TAU_DIFF),
                     "i0_a": np.interp(temps, BRANCH_T_C, BRANCH_I0)}
        n = (n_t, t.soc.size)
        return RcTable(soc=t.soc, temperature_c=temps, fit_error=np.zeros(n),
                       converged=np.ones(n, bool), **cols, **extra)

    ocv_soc = base.charge.soc if ocv_on_rc_grid else base.ocv.soc
    ocv0 = np.interp(ocv_soc, base.ocv.soc, base.ocv.ocv_v[0])
    ocv = OcvOverTemperature(temps, ocv_soc,
                             np.vstack([ocv0 + 2e-4 * (tc - 25.0) * (1.0 - ocv_soc)
                                        for tc in temps]))
    return replace(base, ocv=ocv, charge=table(base.charge), discharge=table(base.discharge))


def temperature_fitted_model():
    """The cached realistic model over temperature (tests/data/make_temperature_model.py:
    four one-temperature curve fits of the shared pulse tests, stacked, with diffusion and
    Butler-Volmer branches, on 14 x 21 points)."""
    from ecmgen.model import load_model

    return load_model(TEMPERATURE_MODEL)


# the shared pulse tests' cell temperatures: the OCV rows of a model built from them
PULSE_TEST_T_C = (-19.9, -9.9, 0.6, 25.8)


def fitter_layout_model(rows: slice | None = None, ocv_t_c=PULSE_TEST_T_C, branches: bool = False,
                        same_tau: bool = True):
    """The test model over temperature (temperature_fitted_model, 14 x 21) in the layout the
    current fitter gives (``ecmgen build`` with several pulse tests, method "curve"): RC
    tables on the uniform 21-point SOC grid and the 5 K temperature grid, each time constant
    constant along SOC (the curve fit's; here the row's value at 50 % SOC) and the same in
    both directions, the OCV on its own uniform 101-point SOC grid with one row per pulse test
    at its cell temperature (``ocv_t_c``). ``rows`` selects temperature rows of the RC tables
    (e.g. slice(4, 8): 0 .. 15 degC); without ``branches`` no diffusion / Butler-Volmer;
    without ``same_tau`` the charge direction's time constants 1.25 times the discharge's
    (ECMRT_TAU_T without ECMRT_TAU_SAME)."""
    from dataclasses import replace

    from ecmgen.model.model import BRANCH_FIELDS, RC_FIELDS, OcvOverTemperature

    m = temperature_fitted_model()
    rows = rows if rows is not None else slice(None)

    def table(t, ref, tau_scale=1.0):
        kw = {k: getattr(t, k)[rows] for k in (*RC_FIELDS, "fit_error", "converged")}
        for k in ("tau_fast_s", "tau_slow_s"):
            mid = tau_scale * getattr(ref, k)[rows][:, ref.soc.size // 2]
            kw[k] = np.repeat(mid[:, None], t.soc.size, axis=1)
        for k in BRANCH_FIELDS:
            v = getattr(t, k)
            kw[k] = v[rows] if branches and v is not None else None
        return replace(t, temperature_c=t.temperature_c[rows], **kw)

    soc = np.round(np.linspace(0.0, 1.0, 101), 9)
    temps = np.asarray(ocv_t_c, dtype=np.float64)
    ocv = OcvOverTemperature(temps, soc, np.vstack([m.ocv.ocv_at(soc, float(t)) for t in temps]))
    return replace(m, ocv=ocv, charge=table(m.charge, m.discharge, 1.0 if same_tau else 1.25),
                   discharge=table(m.discharge, m.discharge))


def load_cycle_t(folder: str, name: str):
    """A shared drive cycle with its cell temperature (Battery_Temp_degC)."""
    import scipy.io

    from conftest import SHARED_DATA
    from ecmgen.data.measure import TimeSeries

    path = SHARED_DATA / folder / name
    if not path.exists():
        pytest.skip(f"real data not found at {path} (expected ../shared/data beside the repo)")
    m = scipy.io.loadmat(str(path), squeeze_me=True, struct_as_record=False)["meas"]
    return TimeSeries(np.asarray(m.Time, float), np.asarray(m.Current, float),
                      np.asarray(m.Voltage, float), np.asarray(m.Battery_Temp_degC, float),
                      source=str(path))


def check_c_equivalence(res: dict, steps: int, tol: dict) -> None:
    """Print and check the c_equivalence block of a real cycle: bit-exact against the
    references, every step run, |dMAE| and max |dv| against float64 within tol[numeric]."""
    for numeric in ("float", "fixed"):
        r = res[numeric]
        print(f"  {numeric:5s} bit-exact {r['bit_exact_vs_reference']}; MAE {r['mae_v'] * 1e3:.3f} mV "
              f"(python {r['python_mae_v'] * 1e3:.3f}), |dMAE| {r['delta_mae_v'] * 1e3:.2e} mV, "
              f"max|dv| {r['max_abs_diff_vs_python_v'] * 1e3:.4f} mV")
        assert r["bit_exact_vs_reference"], numeric
        assert r["steps"] == steps
        assert r["delta_mae_v"] <= tol[numeric][0], numeric
        assert r["max_abs_diff_vs_python_v"] <= tol[numeric][1], numeric


def assert_fields_equal(got, ref, fields) -> None:
    """C run == reference on every step of every field, bit for bit (float32 by its bits)."""
    for f in fields:
        a, b = getattr(got, f), np.asarray(getattr(ref, f))
        if a.dtype == np.float32:
            a, b = a.view(np.uint32), b.astype(np.float32).view(np.uint32)
        else:
            a, b = a.astype(np.int64), b.astype(np.int64)
        bad = np.flatnonzero(a != b)
        assert bad.size == 0, f"{f} differs at {bad.size} steps, first {bad[:5]}"
