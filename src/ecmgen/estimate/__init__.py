"""Stage 4, estimation: a Kalman filter on the model's own discrete step.

The state, the process and measurement functions and their exact Jacobians are in
:mod:`.process`; the extended Kalman filter and the noise model in :mod:`.ekf`; the
sigma-point filter it is compared with in :mod:`.ukf`; running a filter over a record and
judging it against coulomb counting in :mod:`.run` (what ``ecmgen estimate`` does).
"""

from .run import Estimate, EstimateRun, SocMetrics, coulomb_count, estimate_record, run_filter

__all__ = ["Estimate", "EstimateRun", "SocMetrics", "coulomb_count", "estimate_record",
           "run_filter"]
