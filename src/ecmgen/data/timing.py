"""The lag of a record's voltage column behind its current column, measured (never
corrected): a logger that samples them apart adds error on fast cycles."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import numpy as np


LAG_MARGIN = 0.1          # a lag > 0 is reported only where its correlation beats lag 0's by more
LAG_STEP_SHARE = 0.05     # a current step: a sample-to-sample change above this share of |i|max
LAG_MIN_STEPS = 20        # fewer steps on the regular grid: no verdict


@dataclass(frozen=True)
class VoltageLag:
    """How many samples the voltage column responds late to a step of the current column
    (a logger that samples them apart); measured, never corrected.

    samples      the lag reported, in samples (0: the steps line up)
    sample_s     the sampling interval it was measured on, s
    correlation  correlation of the current's and the voltage's sample-to-sample
                 differences with the voltage ``k`` samples later, k = 0 .. max_lag
    """

    samples: int
    sample_s: float
    correlation: tuple[float, ...]

    def note(self, source: str) -> str:
        """One line naming the file, e.g. for a validation's warnings."""
        where = Path(source).name if source else "record"
        c = self.correlation
        if self.samples == 0:
            return (f"{where}: voltage and current steps line up: correlation of their steps "
                    f"{c[0]:.2f} at lag 0")
        n = self.samples
        return (f"{where}: the voltage lags the current by {n} sample{'s' if n > 1 else ''} "
                f"({n * self.sample_s:.2g} s): correlation of their steps {c[n]:.2f} at lag "
                f"{n} vs {c[0]:.2f} at lag 0 (not corrected; it adds to the error on fast "
                f"cycles)")


def voltage_lag(series, max_lag: int = 2) -> VoltageLag | None:
    """The lag of the voltage behind the current, from the correlation of their
    sample-to-sample differences (``dv[k + lag]`` against ``di[k]``) at lags 0..max_lag.
    Only the regularly sampled part counts: intervals within 25 % of the interval at which
    the current steps (a record logged at 10 Hz around its pulses and 1 Hz between is
    judged at 10 Hz). A lag > 0 is reported where its correlation beats lag 0's by more
    than LAG_MARGIN. None where there are fewer than LAG_MIN_STEPS current steps."""
    t, i, v = (np.asarray(a, dtype=np.float64)
               for a in (series.time_s, series.current_a, series.voltage_v))
    if t.size < 3 or max_lag < 0:
        return None
    dt, di, dv = np.diff(t), np.diff(i), np.diff(v)
    step = np.abs(di) > LAG_STEP_SHARE * float(np.max(np.abs(i)))
    if np.count_nonzero(step) < LAG_MIN_STEPS:
        return None
    sample_s = float(np.median(dt[step]))
    regular = np.abs(dt - sample_s) <= 0.25 * sample_s
    if sample_s <= 0 or np.count_nonzero(step & regular) < LAG_MIN_STEPS:
        return None
    corr = []
    for lag in range(max_lag + 1):
        n = dt.size - lag
        ok = regular[:n].copy()
        for j in range(1, lag + 1):
            ok &= regular[j:j + n]
        if np.count_nonzero(ok) < LAG_MIN_STEPS:
            return None
        a, b = di[:n][ok], dv[lag:lag + n][ok]
        a, b = a - a.mean(), b - b.mean()
        norm = float(np.sqrt((a @ a) * (b @ b)))
        if not norm > 0:
            return None
        corr.append(float(a @ b) / norm)
    best = int(np.argmax(corr))
    samples = best if best > 0 and corr[best] > corr[0] + LAG_MARGIN else 0
    return VoltageLag(samples, sample_s, tuple(corr))
