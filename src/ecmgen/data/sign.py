"""Is the current's sign the file's own? A record logged with discharge positive and read as
charge positive (or the reverse) passes every range check and then fails somewhere far
from the cause: the pulse test's SOC runs out of 0..1 ("check data.pulses_soc0"), the
low-rate OCV comes out flat, a drive cycle's estimate drifts off. The voltage says which
way the current flows, whatever the model:

- at a current step the voltage moves with the current (the cell's ohmic resistance is
  positive: a discharge step pulls the voltage down): :func:`step_sign`;
- over a slow test the voltage rises with the charge put in (the OCV rises with SOC):
  :func:`trend_sign`.

Each returns the share of the evidence against ecmgen's convention (charge positive), and
:func:`check_sign` raises the one line that names the sign as the cause.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

STEP_SHARE = 0.2        # a step: |di| over this share of the record's largest |i|
MIN_STEPS = 5           # fewer steps than this say nothing
FLIPPED_SHARE = 0.8     # at least this share of the steps (or of the trend) against: flipped
MIN_TREND_V = 0.05      # a slow test whose voltage moves less than this says nothing

HINT = ("the current's sign looks flipped (ecmgen takes charge as positive): set "
        "current_sign = \"discharge_positive\" in the file's column map, or the reverse")


def step_sign(current_a, voltage_v) -> tuple[int, float]:
    """(steps, share of them where the voltage moved against the current)."""
    i = np.asarray(current_a, dtype=np.float64)
    v = np.asarray(voltage_v, dtype=np.float64)
    ok = np.isfinite(i) & np.isfinite(v)
    i, v = i[ok], v[ok]
    if i.size < 3:
        return 0, 0.0
    di, dv = np.diff(i), np.diff(v)
    big = np.abs(di) > STEP_SHARE * float(np.max(np.abs(i)))
    moved = big & (dv != 0)
    if not moved.any():
        return 0, 0.0
    return int(moved.sum()), float(np.mean(np.sign(dv[moved]) != np.sign(di[moved])))


def trend_sign(time_s, current_a, voltage_v) -> tuple[float, float]:
    """(voltage span, share of the voltage's movement against the charge put in): the
    voltage's rank correlation with the integrated current, mapped to [0, 1] (1: the
    voltage falls wherever charge goes in)."""
    t = np.asarray(time_s, dtype=np.float64)
    i = np.asarray(current_a, dtype=np.float64)
    v = np.asarray(voltage_v, dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(i) & np.isfinite(v)
    t, i, v = t[ok], i[ok], v[ok]
    if t.size < 10:
        return 0.0, 0.0
    q = np.concatenate([[0.0], np.cumsum(0.5 * (i[1:] + i[:-1]) * np.diff(t))])
    span = float(np.ptp(v))
    rq, rv = np.argsort(np.argsort(q)), np.argsort(np.argsort(v))
    if np.ptp(rq) == 0 or np.ptp(rv) == 0:
        return span, 0.0
    rho = float(np.corrcoef(rq, rv)[0, 1])
    return span, 0.5 * (1.0 - rho)


def check_sign(series, what: str = "record", slow: bool = False) -> None:
    """InputError naming the current's sign when the record's voltage says it is flipped
    (``slow``: a low-rate test, judged by its trend; else by its current steps)."""
    if series.voltage_v is None:
        return
    where = series.source or None
    if slow:
        span, against = trend_sign(series.time_s, series.current_a, series.voltage_v)
        if span >= MIN_TREND_V and against >= FLIPPED_SHARE:
            raise InputError(where, f"{what}: the voltage falls as charge goes in "
                                    f"({against:.0%} of its movement); {HINT}")
        return
    n, against = step_sign(series.current_a, series.voltage_v)
    if n >= MIN_STEPS and against >= FLIPPED_SHARE:
        raise InputError(where, f"{what}: at {against:.0%} of its {n} current steps the "
                                f"voltage moves against the current; {HINT}")
