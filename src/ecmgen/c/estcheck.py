"""The generated SOC estimator against its references: the float32 reference
(:mod:`ecmgen.c.estref`, bit for bit) and the float64 Python filter
(:mod:`ecmgen.estimate`, within a small SOC tolerance). What ``ecmgen build --json``
reports for the estimator, and what the tests and bench/bench_estimator_c.py run."""

from __future__ import annotations

import numpy as np

from .names import c_names

from ..config import EstimatorConfig
from . import cref
from .estref import EstRef, simulate_estimator_f32


def run_estimator_c(cm, current_a, dt_s, voltage_v, soc0: float, temperature_c=None,
                    rested: bool = False) -> EstRef:
    """``<prefix>_est_init(soc0)`` (``rested``: ``<prefix>_est_init_rested``) and
    ``<prefix>_est_step`` over the record, in C (``cm`` a CModel compiled with an
    estimator): the predicted voltage, state and covariance per sample."""
    est = cm.estimator
    if est is None:
        raise ValueError("this CModel has no estimator")
    f32 = np.float32
    i = np.ascontiguousarray(np.asarray(current_a, dtype=np.float64).astype(f32))
    n = i.size
    dt = np.ascontiguousarray(np.asarray(dt_s, dtype=np.float64).astype(f32))
    v = np.ascontiguousarray(np.asarray(voltage_v, dtype=np.float64).astype(f32))
    temp = np.ascontiguousarray(np.broadcast_to(np.asarray(
        0.0 if temperature_c is None else temperature_c, dtype=np.float64), (n,)).astype(f32))
    if not (dt.size == v.size == n):
        raise ValueError("current, dt and voltage differ in length")
    nm = c_names(cm.spec.prefix, "float")
    e = cm.ffi.new(f"{nm['est_t']} *")
    getattr(cm.lib, nm["est_init_rested" if rested else "est_init"])(e, float(f32(soc0)))
    vp = np.empty(n, dtype=f32)
    x = np.empty((n, est.n), dtype=f32)
    pm = np.empty((n, est.n, est.n), dtype=f32)
    buf = lambda a: cm.ffi.from_buffer("float[]", a)  # noqa: E731
    cm.lib.ecmh_est_trace(e, buf(i), buf(temp), buf(dt), buf(v), buf(vp), buf(x), buf(pm), n)
    return EstRef(vp, x, pm)


def bits_equal(a: EstRef, b: EstRef) -> bool:
    return all(np.array_equal(np.asarray(getattr(a, f)).view(np.uint32),
                              np.asarray(getattr(b, f)).view(np.uint32))
               for f in ("v_pred", "x", "p"))


def python_filter_soc(model, time_s, current_a, voltage_v, soc0: float,
                      cfg: EstimatorConfig | None = None, temperature_c=None) -> np.ndarray:
    """The float64 EKF of ecmgen.estimate on the same record (the current it sees)."""
    from dataclasses import replace

    from ..estimate.run import run_filter

    cfg = replace(cfg or EstimatorConfig(), filter="ekf")
    return run_filter(model, time_s, current_a, voltage_v, soc0, cfg, temperature_c).soc


def estimator_equivalence(model, cm, time_s, current_a, voltage_v, soc0: float,
                          temperature_c=None) -> dict:
    """The C estimator over a record against its float32 reference (bit for bit: every
    predicted voltage, state and covariance entry) and its SOC against the float64 filter."""
    ref = reference_check(cm, time_s, current_a, voltage_v, soc0, temperature_c)
    soc64 = python_filter_soc(model, np.asarray(time_s, dtype=np.float64), current_a,
                              voltage_v, soc0, cm.estimator.settings, temperature_c)
    return equivalence_figures(ref, soc64)


def reference_check(cm, time_s, current_a, voltage_v, soc0: float, temperature_c=None) -> dict:
    """The C estimator over a record against its float32 reference: {"steps",
    "bit_exact_vs_reference", "soc" (the C filter's)}."""
    time_s = np.asarray(time_s, dtype=np.float64)
    dt = cref.dt_from_time(time_s)
    got = run_estimator_c(cm, current_a, dt, voltage_v, soc0, temperature_c)
    ref = simulate_estimator_f32(cm.spec, cm.estimator, current_a, dt, voltage_v, soc0,
                                 temperature_c)
    return {"steps": int(time_s.size), "bit_exact_vs_reference": bool(bits_equal(got, ref)),
            "soc": got.soc}


def equivalence_figures(reference: dict, soc64: np.ndarray) -> dict:
    """The estimator's figures from :func:`reference_check` and the float64 filter's SOC."""
    soc = reference["soc"]
    d = np.abs(soc.astype(np.float64) - soc64)
    return {"steps": reference["steps"],
            "bit_exact_vs_reference": reference["bit_exact_vs_reference"],
            "max_abs_soc_diff_vs_python": float(d.max()) if d.size else 0.0,
            "soc_end": float(soc[-1]) if d.size else None}
