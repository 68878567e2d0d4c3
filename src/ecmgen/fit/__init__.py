"""Stage 2, identification: 2RC parameters from the data of :mod:`ecmgen.data`.

:mod:`.points` the paper's five-point DC-IR curves (the pieces both fitters share),
:mod:`.ga` their genetic algorithm, :mod:`.lm` their casadi Levenberg-Marquardt fit, and
:mod:`.curve` the whole-pulse-curve fit (pulse + relaxation). casadi is imported only
when an LM fit runs.
"""

from .curve import CurveFit, fit_pulse_curves
from .ga import fit_ga
from .lm import fit_lm
from .points import Bounds, PointFit, curve_r_ohm, default_bounds

__all__ = ["Bounds", "CurveFit", "PointFit", "curve_r_ohm", "default_bounds", "fit_ga",
           "fit_lm", "fit_pulse_curves"]
