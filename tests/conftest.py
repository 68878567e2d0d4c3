"""Shared test fixtures: where the real data lives, and a small synthetic model."""

from __future__ import annotations

import os

# One BLAS thread per process, set before numpy loads (and inherited by the xdist workers
# and the command lines the tests start): the fits gain nothing from BLAS threads, and
# their spinning on the cores the other worker needs makes the suite twice as long on
# 2 cores (18:52 against 8:48 min).
from ecmgen.parallel import ONE_BLAS_THREAD  # noqa: E402  (it does not load numpy)

for _name, _value in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_name, _value)

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
C_DIR = REPO / "tests" / "c"      # the tests' C programs (lintable C, not strings)
# ECMGEN_SHARED_DATA: the shared data elsewhere (a git worktree's checkout is not beside it)
SHARED_DATA = Path(os.environ.get("ECMGEN_SHARED_DATA", REPO.parent / "shared" / "data"))
PANASONIC = SHARED_DATA / "panasonic-18650pf-25degC"
CALCE = SHARED_DATA / "calce-a123-lfp"


def built_once(tmp_path_factory, name: str, build) -> Path:
    """A folder that ``build(folder)`` fills once per test run, whichever xdist worker asks
    first; the others wait for it and share it (a module fixture is otherwise built once
    per worker that runs a test of its module: 25-40 s each for the A123 build and the
    fleet study). Without xdist, once per session. Read it, never write into it."""
    import fcntl
    import shutil

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent                  # the run's, above each worker's own
    folder = root / f"built-once-{name}"
    with open(root / f"built-once-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)    # released when the file closes
        if not (folder / ".built").exists():
            shutil.rmtree(folder, ignore_errors=True)      # a build that failed half-way
            folder.mkdir()
            build(folder)
            (folder / ".built").touch()
    return folder


def a123_example(tmp_path_factory) -> Path:
    """examples/a123-dynamic built by ``ecmgen build --json -q`` once per test run
    (:func:`built_once`): the folder holds ``out/`` (the build) and ``build.json`` (what it
    printed). Skipped without the shared A123 data."""
    import subprocess
    import sys

    need(SHARED_DATA / "plett-a123-lfp")

    def build(folder):
        r = subprocess.run([sys.executable, "-m", "ecmgen.cli", "build",
                            str(REPO / "examples" / "a123-dynamic" / "config.toml"), "--out",
                            str(folder / "out"), "--json", "-q"], capture_output=True,
                           text=True, cwd=REPO)
        assert r.returncode == 0, r.stderr
        (folder / "build.json").write_text(r.stdout)

    return built_once(tmp_path_factory, "a123-example", build)


def need(path: Path) -> Path:
    """Skip (with the reason) when the shared real data is not beside the checkout."""
    if not path.exists():
        pytest.skip(f"real data not found at {path} (expected ../shared/data beside the repo)")
    return path


def diagnose_cells():
    """bench/diagnose_cells.py, the independent cell generator (numpy physics, no ecmgen
    import), loaded as a module: diagnose is scored on cells not made by its own equations."""
    import importlib.util
    import sys

    name = "diagnose_cells_bench"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "bench" / "diagnose_cells.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod        # its dataclasses look their module up
        spec.loader.exec_module(mod)
    return sys.modules[name]


def diagnose_generated(seed: int, effects: tuple[str, ...], folder: Path):
    """A quick cell of the independent generator (half the pulse levels and cycle) with
    ``effects`` missing, written into ``folder`` and diagnosed as a user would (its
    case.toml, no plots); returns the DiagnoseResult."""
    from ecmgen.config import load_config
    from ecmgen.pipeline import run_diagnose

    dc = diagnose_cells()
    case, extra = dc.make_case(seed, effects, quick=True)
    dc.write_case(case, extra, folder / "cell")
    result, _, _ = run_diagnose(load_config(folder / "cell" / "case.toml"), folder / "out",
                                plots=False)
    return result


@pytest.fixture
def synthetic_model():
    """A plausible NCA-like 2RC model with distinct charge/discharge tables."""
    return synthetic_nca_model()


def synthetic_nca_model(tau_fast_s=1.5, tau_slow_s=40.0):
    """A plausible NCA-like 2RC model with distinct charge/discharge tables."""
    from ecmgen.model import EcmModel, OcvTable, RcTable

    soc = np.linspace(0.0, 1.0, 11)
    ocv = OcvTable(soc, 3.0 + 1.2 * soc - 0.15 * np.sin(2.5 * soc))

    def table(scale):
        n = soc.size
        return RcTable(soc=soc,
                       r0_ohm=scale * (0.020 + 0.010 * (1 - soc) ** 2),
                       r_fast_ohm=scale * np.full(n, 0.008),
                       tau_fast_s=np.full(n, tau_fast_s),
                       r_slow_ohm=scale * (0.010 + 0.005 * (1 - soc)),
                       tau_slow_s=np.full(n, tau_slow_s),
                       fit_error=np.zeros(n), converged=np.ones(n, bool))

    return EcmModel(capacity_ah=2.9, ocv=ocv, charge=table(0.9), discharge=table(1.0),
                    method="synthetic", seed=0, direction_deadband_a=0.029)


def flat(model):
    """The model with RC parameters constant in SOC (their value at 50 %), so analytic
    responses apply exactly."""
    from dataclasses import replace

    def table(t):
        p = t.at(0.5)
        return replace(t, **{k: np.full(t.soc.size, float(v)) for k, v in p.items()})

    return replace(model, charge=table(model.charge), discharge=table(model.discharge))


def make_pulse_test(model, *, soc_levels=(0.9, 0.7, 0.5, 0.3, 0.15), c_rates=(1.0, 3.0),
                    pulse_s=10.0, rest_s=1200.0, noise_v=0.0, seed=0, direction=-1,
                    log_moves=False, rates_at=None):
    """A synthetic HPPC generated by ``model`` (exact ZOH simulation): at each SOC level
    a rest, then pulses of each C-rate (10 Hz) with rests (1 Hz) between, discharge
    (direction -1), charge (+1) or both ((-1, 1)); the SOC is
    moved between levels by a 1C discharge that the record leaves out (as the Panasonic
    file does), so the returned Ah column is what tells the SOC; ``log_moves=True`` keeps
    them in the record (1 Hz). ``rates_at(level)``, if given, is the C-rates run at that
    level instead of ``c_rates`` (e.g. fewer at a low level, as a voltage limit leaves).

    Returns (TimeSeries, soc0)."""
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate

    q = model.capacity_ah
    seg_t, seg_i = [np.array([0.0])], [np.array([0.0])]
    t_now = 0.0

    def add(duration, current, dt):
        nonlocal t_now
        n = int(round(duration / dt))
        seg_t.append(t_now + dt * np.arange(1, n + 1))
        seg_i.append(np.full(n, float(current)))
        t_now += n * dt

    soc_now = 1.0
    keep = [np.array([True])]
    for level in soc_levels:
        move_s = (soc_now - level) * q * 3600.0 / q  # at 1C
        if move_s > 0:
            add(move_s, -q, 1.0)
            keep.append(np.full(int(round(move_s)), bool(log_moves)))
        soc_now = level
        add(rest_s, 0.0, 1.0)
        keep.append(np.ones(int(round(rest_s)), bool))
        for c in (c_rates if rates_at is None else rates_at(level)):
            for d in np.atleast_1d(direction):
                add(pulse_s, d * c * q, 0.1)
                keep.append(np.ones(int(round(pulse_s / 0.1)), bool))
                add(rest_s, 0.0, 1.0)
                keep.append(np.ones(int(round(rest_s)), bool))
                soc_now += d * c * q * pulse_s / 3600.0 / q
    t = np.concatenate(seg_t)
    i = np.concatenate(seg_i)
    sim = simulate(model, t, i, 1.0)
    rng = np.random.default_rng(seed)
    v = sim.voltage_v + noise_v * rng.standard_normal(t.size)
    ah = (sim.soc - 1.0) * q
    k = np.concatenate(keep)
    return TimeSeries(t[k], i[k], v[k], None, ah[k], "synthetic-hppc"), 1.0


def make_usabc_hppc(model, *, levels=(0.9, 0.7, 0.5, 0.3), dis_s=30.0, chg_s=10.0,
                    dis_c=2.0, chg_c=1.5, gap_s=40.0, move_c=1 / 3, rest_s=1800.0,
                    noise_v=0.0005, seed=0):
    """A USABC/Leaf-shaped HPPC generated by ``model``: at each SOC level a rest, a
    ``dis_s`` discharge pulse, ``gap_s`` of rest, a ``chg_s`` regen pulse that runs
    straight into the constant-current (``move_c``) discharge to the next level; a final
    rest. 10 Hz around the pulses, 1 Hz elsewhere. Returns the TimeSeries (no Ah column:
    SOC by integrating the current from 1.0)."""
    from ecmgen.data.measure import TimeSeries
    from ecmgen.model.simulate import simulate

    q = model.capacity_ah
    ts, cur, now = [np.array([0.0])], [np.array([0.0])], [0.0]

    def seg(duration, amps, dt):
        n = int(round(duration / dt))
        ts.append(now[0] + dt * np.arange(1, n + 1))
        cur.append(np.full(n, float(amps)))
        now[0] += n * dt

    soc = 1.0
    for level in levels:
        if soc - level > 1e-9:
            seg((soc - level) * 3600.0 / move_c, -move_c * q, 1.0)
            soc = level
        seg(rest_s, 0.0, 1.0)
        seg(dis_s, -dis_c * q, 0.1)
        seg(gap_s, 0.0, 0.1)
        seg(chg_s, chg_c * q, 0.1)
        soc += (chg_c * chg_s - dis_c * dis_s) / 3600.0
    seg(rest_s, 0.0, 1.0)
    t, i = np.concatenate(ts), np.concatenate(cur)
    v = simulate(model, t, i, 1.0).voltage_v
    v = v + noise_v * np.random.default_rng(seed).standard_normal(t.size)
    return TimeSeries(t, i, v, None, None, "usabc-hppc.csv")


def write_synthetic_cell(folder, cycle_s: float):
    """A small synthetic cell into ``folder``: pulses.csv, ocv.csv and a discharge drive
    cycle.csv of ``cycle_s`` seconds (from SOC 0.8); returns its true model."""
    from ecmgen.data.measure import TimeSeries, write_timeseries_csv
    from ecmgen.model.simulate import simulate

    truth = synthetic_nca_model(tau_fast_s=2.0, tau_slow_s=60.0)
    series, _ = make_pulse_test(truth, soc_levels=(0.9, 0.6, 0.3), c_rates=(1.0, 3.0),
                                noise_v=0.0005, rest_s=900.0)
    write_timeseries_csv(series, folder / "pulses.csv")
    np.savetxt(folder / "ocv.csv", np.column_stack([truth.ocv.soc, truth.ocv.ocv_v[0]]),
               delimiter=",", header="soc,ocv_v", comments="")
    t = np.arange(0, cycle_s, 1.0)
    i = np.repeat(np.random.default_rng(0).uniform(-8, 0, t.size // 20), 20)  # the pulses too
    i[:60] = 0.0
    write_timeseries_csv(TimeSeries(t, i, simulate(truth, t, i, 0.8).voltage_v),
                         folder / "cycle.csv")
    return truth


@pytest.fixture(scope="module")
def cell_files(tmp_path_factory):
    """A small synthetic cell (pulse test, OCV table, a drive cycle) and its model."""
    folder = tmp_path_factory.mktemp("cell")
    write_synthetic_cell(folder, 1200.0).save(folder / "model.json")
    return folder
