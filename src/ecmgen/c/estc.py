"""The SOC estimator in C (``[c] estimator = "ekf"``): its spec, its rendering beside the
model's C, and its cffi harness.

``<prefix>_est_f32.h`` declares ``<prefix>_est_f32_t`` (the model's state, the covariance, with
``error_memory_s`` the overpotential the model error holds, a first-sample flag) and
``<prefix>_est_init_f32`` / ``<prefix>_est_step_f32``, defined in ``<prefix>_est_f32.c``: it includes the model's ``<prefix>_ecm_f32_config.h`` (the runtime
as the model's ``.c`` configures it, and the declaration of the model's ``const`` tables,
which the filter's table accessor reads), predicts with ``<prefix>_step_f32`` and has the
filter itself in the hand-written ``c_runtime/ecmrt_est_f32.h``. The filter is the extended
Kalman filter of :mod:`ecmgen.estimate.ekf` (chosen over the sigma-point filter by
measurement), its noise settings (:class:`ecmgen.config.EstimatorConfig`) baked
in as float32 constants. A model's diagnose effects are taken: the hysteresis state and the
extra RC pair are states of the filter (the layout of :mod:`ecmgen.estimate.process`), the
parameter effects scale the resistances in its Jacobians; ``offset_state`` adds the current
sensor's offset as the last state (held in ``<prefix>_est_t.offset_a``); ``ocv_slope_spread``
above 0 generates the OCV's secant over the SOC's spread into H (two more
OCV lookups and a square root per update and per relinearisation).

Float32 only, by decision: the covariance spans 0.09 (the start SOC's variance) down to
~1e-9 (a settled SOC's, and the cross terms) and the Joseph update subtracts nearly equal
numbers; a fixed-point covariance would need block floating point (see docs/estimator.md, measured
figures in bench/bench_estimator_c.py). The model step under it is the float32 step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import EstimatorConfig
from ..errors import InputError
from ..estimate.ekf import HYSTERESIS_START_VAR, NoiseModel
from .names import c_names
from .spec import CSpec, state_bytes

ESTIMATORS = ("ekf",)
RUNTIME_FILES = ("ecmrt_est_f32_tables.h", "ecmrt_est_f32_rows.h", "ecmrt_est_f32.h")
# ecmrt_est_f32_noise_t, in order: field, comment
NOISE_FIELDS = (("p0_soc", "initial SOC variance, soc0_sigma^2"),
                ("p0_u", "initial RC voltage variance, u0_sigma_v^2, V^2"),
                ("offset_a", "current sensor offset, 1 sigma, A"),
                ("gain", "current sensor gain error, 1 sigma"),
                ("noise_a", "white current noise per sample, A"),
                ("horizon_s", "drift horizon of the sensor bias, s"),
                ("pol", "polarization_error (RC process noise)"),
                ("vn2", "voltage_noise_v^2, V^2"),
                ("model_error", "model voltage error / model overpotential"),
                ("corr_s", "error_correlation_s, s"),
                ("start_a", "the RC voltages' start sigma is r_j times this current, A"),
                ("mem_k", "1 / error_memory_s (0: the model error has no memory), 1/s"),
                ("pol_s2", "polarization_soc_sigma^2 (0: the RC noise is not scaled)"))
# with a hysteresis effect only; with the offset state only
HYST_FIELDS = (("p0_h", "hysteresis_sigma^2: h's initial variance and noise scale"),)
OFFSET_FIELDS = (("p0_b", "offset_a^2: the offset state's initial variance, A^2"),)
# with ocv_slope_spread > 0 only
SPREAD_FIELDS = (("ocv_k", "ocv_slope_spread: H's OCV slope is the secant over soc +- k sigma"),)
# where <prefix>_est_t holds each filter state (ecmgen.estimate.process.state_layout names)
STATE_FIELDS = {"soc": "m.soc", "u_fast_v": "m.u_fast", "u_slow_v": "m.u_slow",
                "u_diff_v": "m.u_diff", "u_extra_v": "m.u_x", "h": "m.h", "offset_a": "offset_a"}


@dataclass(frozen=True)
class EstSpec:
    """What the generated estimator holds: its kind, state names and float32 constants."""

    kind: str
    names: tuple[str, ...]
    noise: dict                 # NOISE_FIELDS name -> np.float32
    settings: EstimatorConfig   # what the constants were made from

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def offset(self) -> bool:
        """The current-offset state is the last state."""
        return self.names[-1] == "offset_a"

    @property
    def memory(self) -> bool:
        """<prefix>_est_t holds the overpotential the model error holds (eta_v)."""
        return self.settings.error_memory_s > 0

    @property
    def spread(self) -> bool:
        """H's OCV slope is the secant over the SOC's spread (generated only then)."""
        return self.settings.ocv_slope_spread > 0

    @property
    def fields(self) -> tuple[str, ...]:
        """Where <prefix>_est_t holds each filter state, in order (``m.soc``, ...)."""
        return tuple(STATE_FIELDS[k] for k in self.names)

    @property
    def noise_fields(self) -> tuple[tuple[str, str], ...]:
        """ecmrt_est_f32_noise_t's fields, in order: (name, comment)."""
        return (NOISE_FIELDS + (SPREAD_FIELDS if self.spread else ())
                + (HYST_FIELDS if "h" in self.names else ())
                + (OFFSET_FIELDS if self.offset else ()))


def prepare_estimator(model, spec: CSpec, cfg: EstimatorConfig | None = None,
                      kind: str = "ekf") -> EstSpec:
    """The estimator's spec for the float spec ``spec`` of ``model``; InputError when the C
    estimator cannot run on it."""
    cfg = cfg or EstimatorConfig()
    if kind not in ESTIMATORS:
        raise InputError(None, f"c.estimator must be one of {', '.join(ESTIMATORS)}, got {kind!r}")
    if spec.fixed:
        raise InputError(None, "the C estimator is float32 only: build it with numeric "
                               "\"float\"")
    if not spec.variable_dt:
        raise InputError(None, "the C estimator needs the variable-dt step: leave c.dt_s unset")
    nm = NoiseModel.from_config(cfg, model.capacity_ah)
    vals = {"p0_soc": nm.soc0_sigma ** 2, "p0_u": nm.u0_sigma_v ** 2,
            "offset_a": nm.offset_sigma_a, "gain": nm.gain_sigma,
            "noise_a": nm.current_noise_a, "horizon_s": nm.drift_horizon_s,
            "pol": nm.polarization_error, "vn2": nm.voltage_noise_v ** 2,
            "model_error": nm.model_error, "corr_s": nm.error_correlation_s,
            "start_a": nm.start_current_a,
            "mem_k": 1.0 / nm.error_memory_s if nm.error_memory_s > 0 else 0.0,
            "pol_s2": nm.polarization_soc_sigma ** 2, "ocv_k": nm.ocv_slope_spread,
            "p0_h": nm.hysteresis_sigma ** 2, "p0_b": nm.offset_sigma_a ** 2}
    # the states of ecmgen.estimate.process.state_layout, in its order
    names = (("soc", "u_fast_v", "u_slow_v") + (("u_diff_v",) if spec.diff else ())
             + (("u_extra_v",) if spec.fx.get("xrc") else ()) + (("h",) if spec.fx.get("hyst") else ())
             + (("offset_a",) if cfg.offset_state else ()))
    noise = {k: np.float32(vals[k]) for k, _ in EstSpec(kind, names, {}, cfg).noise_fields}
    for k, v in noise.items():
        if not np.isfinite(v):
            raise InputError(None, f"estimator setting {k} does not fit float32")
    return EstSpec(kind, names, noise, cfg)


def est_file_names(prefix: str) -> dict[str, str]:
    nm = c_names(prefix, "float")
    return {"est_header": nm["est_header"], "est_source": nm["est_source"],
            "est_runtime": list(RUNTIME_FILES)}


def render_estimator(env, ctx: dict, est: EstSpec, c_float) -> dict[str, str]:
    """{file name: text} of <prefix>_est_f32.h and .c; ``env`` and ``ctx`` the renderer's
    jinja2 environment and context, ``c_float`` its float literal."""
    # a start anywhere: the hysteresis state at 0, variance 1/3 (ecmgen.estimate.ekf)
    h_start = (c_float(np.float32(HYSTERESIS_START_VAR))
               if "h" in est.names and est.noise["start_a"] != 0.0 else None)
    ectx = dict(ctx, n=est.n, names=est.names, fields=est.fields, offset=est.offset, h_start=h_start,
                slopes=est.settings.resistance_slopes, spread=est.spread, memory=est.memory,
                noise=[(k, c_float(est.noise[k]), c) for k, c in est.noise_fields])
    files = ctx["files"]
    return {files["est_header"]: env.get_template("est.h.j2").render(ectx),
            files["est_source"]: env.get_template("est.c.j2").render(ectx)}


# --------------------------------------------------------------------------------------
# cffi declarations (the harness itself: templates/harness.c.j2)
# --------------------------------------------------------------------------------------

def est_trace_signature(spec: CSpec) -> str:
    """The prototype of the harness's estimator trace (templates/harness.c.j2)."""
    nm = c_names(spec.prefix, "float")
    return (f"void ecmh_est_trace({nm['est_t']} *e, const float *i, const float *temp, "
            "const float *dt, const float *v, float *vp, float *x, float *pm, size_t n)")


def cdef(spec: CSpec, est: EstSpec) -> str:
    nm = c_names(spec.prefix, "float")
    et = nm["est_t"]
    return "\n".join([
        f"typedef struct {{ {nm['state']} m; float p[{est.n * est.n}]; "
        + ("float offset_a; " if est.offset else "") + ("float eta_v; " if est.memory else "")
        + f"uint8_t first; }} {et};",
        f"void {nm['est_init']}({et} *e, float soc0);",
        f"void {nm['est_init_rested']}({et} *e, float soc0);",
        f"float {nm['est_step']}({et} *e, float i, float temperature, float dt, float v);",
        est_trace_signature(spec) + ";",
        "size_t ecmh_est_size(void);",
    ])


def est_state_bytes(spec: CSpec, est: EstSpec) -> int:
    """sizeof(<prefix>_est_t) on a 32-bit target: the model's state, the covariance, the
    offset, the held overpotential (error_memory_s), the flag, padded to 4."""
    return -(-(state_bytes(spec) + 4 * est.n * est.n + 4 * est.offset + 4 * est.memory + 1)
             // 4) * 4
