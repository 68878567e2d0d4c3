"""The build configuration (one TOML file; paths are relative to it).

:mod:`ecmgen.config.schema` holds every section and key (type, unit, range, default,
meaning); :mod:`ecmgen.config.loader` checks a config against it, then what ties keys
together, and gives the typed :class:`BuildConfig` the stages read.
"""

from .loader import (C_ESTIMATORS, C_RUNTIME_NAMESPACE, COLUMN_ROLE_FALLBACK,
                     ESTIMATOR_FILTERS, START_ANYWHERE, SURFACE_SOC_GAIN_MAX,
                     SURFACE_SOC_GAIN_OVER_TEMPERATURE, WINDOW_ROLES,
                     BuildConfig, EstimatorConfig, PulseTest, c_prefix_problem,
                     estimator_config, load_config, start_settings)

__all__ = ["C_ESTIMATORS", "C_RUNTIME_NAMESPACE", "COLUMN_ROLE_FALLBACK", "ESTIMATOR_FILTERS",
           "START_ANYWHERE", "SURFACE_SOC_GAIN_MAX", "SURFACE_SOC_GAIN_OVER_TEMPERATURE",
           "WINDOW_ROLES", "BuildConfig", "EstimatorConfig", "PulseTest", "c_prefix_problem", "estimator_config",
           "load_config", "start_settings"]
