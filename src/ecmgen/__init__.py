"""ecmgen: cell test data -> 2RC equivalent-circuit model -> C code for BMS firmware.

The source follows the pipeline, one subpackage per stage; a stage imports only the
stages before it, never a later one (tests/test_layout.py checks this)::

    data/        measurement files -> TimeSeries (measure), pulse test -> DC-IR table
                 (dcir), OCV(SOC) (ocv)
    fit/         identification: the paper's five-point DC-IR curves (points, ga, lm)
                 and the whole-pulse-curve fit (curve)
    model/       EcmModel and the versioned model.json (model), the optional effects
                 (effects), discrete 2RC simulation and validation (simulate, rc)
    c/           model -> C: Q formats (qformat), generation (codegen), Python references
                 (cref), host build and equivalence (cbuild, check), Cortex-M (target)
    diagnosis/   `ecmgen diagnose`: signatures and greedy search (search), candidate fits
                 (problems), report and plots (output), synthetic cells (synthcell)
    estimate/    `ecmgen estimate`: the SOC filter on the model's step (process: state,
                 step and Jacobians; ekf, ukf), runs and SOC figures (run), noise
                 settings from the validation residual (residual)
    plots/, report    the PNG and text outputs of a build (plots.style: the house style)
    pipeline, cli    the chain behind `ecmgen build` / `ecmgen diagnose`, and the CLI
    fleet/       `ecmgen fleet`: the build of every row of a manifest on Dask, resumable
                 by the hash of each row's inputs; the fleet table and its trend plots
    config/, errors, files, _version    shared by all: the build config (loader,
                 schema), InputError, atomic writes and hashes, the version

The names a notebook needs are available from here (``ecmgen.build``,
``ecmgen.load_model``, ``ecmgen.simulate``, ...). They are imported on first use
(PEP 562), so ``import ecmgen`` stays light and no stage ever imports this facade.
"""

from ._version import __version__

# public name -> the module that defines it
_API = {
    "build": "ecmgen.pipeline",
    "load_config": "ecmgen.config",
    "InputError": "ecmgen.errors",
    "TimeSeries": "ecmgen.data.measure",
    "read_timeseries": "ecmgen.data.measure",
    "extract_dcir": "ecmgen.data.dcir",
    "find_pulses": "ecmgen.data.dcir",
    "fit_ga": "ecmgen.fit.ga",
    "fit_lm": "ecmgen.fit.lm",
    "fit_pulse_curves": "ecmgen.fit.curve",
    "CurveOptions": "ecmgen.fit.curve",
    "EcmModel": "ecmgen.model.model",
    "load_model": "ecmgen.model.model",
    "simulate": "ecmgen.model.simulate",
    "validate": "ecmgen.model.simulate",
    "generate_c": "ecmgen.c.codegen",
    "diagnose": "ecmgen.diagnosis.search",
    "estimate_record": "ecmgen.estimate.run",
    "run_filter": "ecmgen.estimate.run",
    "run_fleet": "ecmgen.fleet.run",
}

__all__ = ["__version__", *sorted(_API)]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'ecmgen' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))
