"""Stage 2, identification: 2RC parameters from the data of :mod:`ecmgen.data`.

:mod:`.points` the paper's five-point DC-IR curves (the pieces both fitters share, and
which DC-IR rows they take), :mod:`.ga` their genetic algorithm, :mod:`.lm` their casadi
Levenberg-Marquardt fit, :mod:`.rate` the Butler-Volmer exchange current from the C-rate
dependence, and :mod:`.curve` the whole-test fit of a pulse test (:mod:`.lsq` its
numerical pieces). casadi is imported only when an LM fit runs.
"""

from .curve import CurveFit, CurveOptions, fit_pulse_curves
from .ga import fit_ga
from .lm import fit_lm
from .points import Bounds, PointFit, curve_r_ohm, default_bounds, five_point_rows
from .rate import ExchangeCurrentFit, fit_exchange_current

__all__ = ["Bounds", "CurveFit", "CurveOptions", "ExchangeCurrentFit", "PointFit",
           "curve_r_ohm", "default_bounds", "fit_exchange_current", "fit_ga", "fit_lm",
           "fit_pulse_curves", "five_point_rows"]
