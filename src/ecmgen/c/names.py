"""The names of the generated C: one rule for files, functions, types and macros.

Float (IEEE binary32) and fixed point (int32 Q formats) of one model coexist in one
firmware image under one prefix, as CMSIS-DSP's ``arm_fir_f32`` / ``arm_fir_q31`` do:

==========  ======================================  ======================================
            float                                   fixed point
==========  ======================================  ======================================
files       ``<prefix>_ecm_f32.h`` / ``.c``         ``<prefix>_ecm_q.h`` / ``.c``
functions   ``<prefix>_init_f32``, ``_step_f32``,    ``<prefix>_init_q``, ``_step_q``,
            ``_run_f32``                             ``_run_q``
state type  ``<prefix>_state_f32_t``                ``<prefix>_state_q_t``
macros      ``<PREFIX>_ECM_F32_*``                  ``<PREFIX>_ECM_Q_*``
value types -                                       ``<prefix>_<quantity>_q<N>_t`` (the format
                                                    in the name, e.g. ``<prefix>_amp_q24_t``)
==========  ======================================  ======================================

The SOC estimator (float32): ``<prefix>_est_f32.h`` / ``.c``, ``<prefix>_est_f32_t``,
``<prefix>_est_init_f32`` / ``<prefix>_est_step_f32``, macros ``<PREFIX>_EST_F32_*``.
Internal to the generated C (not for the firmware's own code): ``<prefix>_ecm_<s>_config.h``
(the runtime configured for the model, included by the model's and the estimator's ``.c``)
and ``<prefix>_model_<s>``, the model's tables (``const``; the estimator reads them), of
the type ``<prefix>_model_<s>_t`` (its tables per direction ``<prefix>_dir_<s>_t``): one
model's layout, so two models' headers meet in one file without a clash. The
runtime headers (``ecmrt*.h``) have no external symbols (static inline only).
"""

from __future__ import annotations

SUFFIX = {"float": "f32", "fixed": "q"}


def c_names(prefix: str, numeric: str) -> dict[str, str]:
    """Every external name of the C of ``numeric`` ("float" / "fixed") under ``prefix``."""
    s = SUFFIX[numeric]
    P = prefix.upper()
    return {
        "suffix": s,
        "header": f"{prefix}_ecm_{s}.h", "source": f"{prefix}_ecm_{s}.c",
        "filelist": f"{prefix}_ecm_{s}_files.mk", "report": f"{prefix}_ecm_{s}_report.md",
        "config": f"{prefix}_ecm_{s}_config.h", "tables": f"{prefix}_model_{s}",
        "state": f"{prefix}_state_{s}_t", "init": f"{prefix}_init_{s}",
        "model_t": f"{prefix}_model_{s}_t", "dir_t": f"{prefix}_dir_{s}_t",
        "step": f"{prefix}_step_{s}", "run": f"{prefix}_run_{s}",
        "set_age": f"{prefix}_set_age_{s}",
        "M": f"{P}_ECM_{s.upper()}",
        "est_header": f"{prefix}_est_f32.h", "est_source": f"{prefix}_est_f32.c",
        "est_t": f"{prefix}_est_f32_t",
        "est_init": f"{prefix}_est_init_f32", "est_step": f"{prefix}_est_step_f32",
        "est_init_rested": f"{prefix}_est_init_rested_f32",
        "EM": f"{P}_EST_F32",
    }
