"""The paper's five-point DC-IR curves: the pieces shared by the GA and the LM fit.

Aras & Yonel (2017) fit, for every table cell (SOC x direction x C-rate), the DC-IR
values R(t) = dV/dI measured at a few times into a pulse (0.1, 1, 3, 6, 10 s) with

    R(t) = R0 + R_fast (1 - exp(-t/tau_fast)) + R_slow (1 - exp(-t/tau_slow)).

R0 is not a free parameter: the curve is pinned to the first valid point t_0,

    R0 = R(t_0) - R_fast (1 - exp(-t_0/tau_fast)) - R_slow (1 - exp(-t_0/tau_slow)),

which is the paper's "R0 = R(0.1 s)" with four free parameters, while the model
still reproduces R(t_0) exactly. With d_k = R(t_k) - R(t_0) the fitted curve is

    d_k ~ R_fast phi(t_k; tau_fast) + R_slow phi(t_k; tau_slow),
    phi(t; tau) = exp(-t_0/tau) - exp(-t/tau),

and the paper's fitness (Eq. 5) is sum_k |d_k - fitted_k| over the valid points after
the first. Constraints everywhere: the bounds, tau_fast < tau_slow, and R0 >= 0.

This module holds what both fitters share: the result and bounds types
(:class:`PointFit`, :class:`Bounds`, :func:`default_bounds`), the fitted curve
(:func:`curve_r_ohm`), the data preparation and Eq. 5. The fitters:

:mod:`ecmgen.fit.ga`  ``fit_ga``: real-coded GA, vectorised over the population and all
         cells at once (arrays (n_cells, pop, 4)); minimises Eq. 5 (exactly-solved
         resistances for each individual's taus); MATLAB-``ga``-like stall rule.
:mod:`ecmgen.fit.lm`  ``fit_lm``: Levenberg-Marquardt (paper Eqs. 6-8,
         x <- x - (J'J + mu I)^-1 J'r) on the squared residuals with a casadi
         residual/Jacobian mapped over all cells; Nielsen's adaptive mu; scaled
         variables (log tau, branch amplitudes in units of the data); never worse than
         its x0 in Eq. 5.

Note on Table 1 of the paper: no curve of this form through the first point gets
within ~32 uOhm of all five points (whatever the parameters), so the fits there
differ from the data by 42 uOhm (LM) / 91 uOhm (GA's L1 optimum) at one point.

NaN entries of ``r_ohm`` (points a pulse did not reach) are masked out. A row with
fewer than 3 valid points after its first valid point gets NaN parameters and
``converged=False``.

``progress`` callbacks are called as ``progress(done, total)`` (generations or
iterations), like the other fitters of the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

Progress = Callable[[int, int], None]

MIN_POINTS = 3            # valid points after the first one needed for a fit
_LOG_GAP = 1e-6           # tau_slow >= tau_fast * exp(_LOG_GAP): strict ordering


# --------------------------------------------------------------------------------------
# public types
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Bounds:
    """Search box, as (lo, hi) pairs; the same for every cell of a table."""

    tau_fast_s: tuple[float, float]
    tau_slow_s: tuple[float, float]
    r_fast_ohm: tuple[float, float]
    r_slow_ohm: tuple[float, float]

    def __post_init__(self):
        for name in ("tau_fast_s", "tau_slow_s", "r_fast_ohm", "r_slow_ohm"):
            pair = getattr(self, name)
            if len(pair) != 2:
                raise ValueError(f"Bounds.{name} must be a (lo, hi) pair, got {pair!r}")
            lo, hi = float(pair[0]), float(pair[1])
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(f"Bounds.{name} needs finite lo < hi, got {pair!r}")
            if name.startswith("tau") and lo <= 0:
                raise ValueError(f"Bounds.{name} must be positive, got {pair!r}")
            object.__setattr__(self, name, (lo, hi))
        if self.tau_fast_s[0] * np.exp(2 * _LOG_GAP) >= self.tau_slow_s[1]:
            raise ValueError("Bounds leave no room for tau_fast < tau_slow: "
                             f"tau_fast_s {self.tau_fast_s}, tau_slow_s {self.tau_slow_s}")


@dataclass(frozen=True)
class PointFit:
    """One fit of a whole table; every array has shape (n_cells,)."""

    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    tau_fast_s: np.ndarray
    r_slow_ohm: np.ndarray
    tau_slow_s: np.ndarray
    fitness_ohm: np.ndarray    # Eq. 5: sum |R_meas - R_fit| over the points after the first
    converged: np.ndarray      # bool: stopping rule met (not just the iteration cap)
    iterations: np.ndarray     # generations (GA) / iterations (LM) per cell
    method: str                # "ga" | "lm"


def default_bounds(t_s: np.ndarray, r_ohm: np.ndarray) -> Bounds:
    """Search box derived from the sampling times and the data's magnitude.

    With t_0 the first time, t_end the last, span = t_end - t_0 and dt the smallest
    spacing:

    * tau_fast in [tau_lo, span], tau_slow in [tau_lo, 5 t_end], where
      tau_lo = max(dt / 10, t_0 / 5). Much faster dynamics than the sampling step or
      than t_0 (they are over before the pinned first point) are invisible.
      Beyond ~5 t_end the slow branch is a straight line over the window
      (1 - exp(-t/tau) ~ t/tau within 10 %), so only R_slow/tau_slow would be
      identifiable and R_slow would run away. Ordering tau_fast < tau_slow is a
      constraint, not part of the box.
    * R_fast, R_slow in [0, 10 rise], rise = largest R(t) - R(t_0) in the table
      (falls back to the largest |R| if the table never rises). A slow branch with
      tau = 5 t_end reaches 18 % of R_slow at t_end, i.e. needs R_slow ~ 5.5 rise;
      10 leaves margin for noise.
    """
    t = _check_t(t_s)
    r = _check_r(r_ohm, t.size)
    t0, t_end = float(t[0]), float(t[-1])
    span = t_end - t0
    dt = float(np.min(np.diff(t)))
    tau_lo = max(dt / 10.0, t0 / 5.0)
    valid = np.isfinite(r)
    rise = 0.0
    if valid.any():
        first = np.argmax(valid, axis=1)
        anchor = r[np.arange(r.shape[0]), first]
        rise = float(np.max(np.where(valid, r - anchor[:, None], -np.inf)))
        if not rise > 0:
            rise = float(np.max(np.abs(r[valid])))
    if not rise > 0:
        rise = 1e-3
    r_hi = 10.0 * rise
    return Bounds(tau_fast_s=(tau_lo, max(span, 2 * tau_lo)),
                  tau_slow_s=(tau_lo, max(5.0 * t_end, 4 * tau_lo)),
                  r_fast_ohm=(0.0, r_hi), r_slow_ohm=(0.0, r_hi))


def curve_r_ohm(fit: PointFit, t_s) -> np.ndarray:
    """The fitted model curve R(t), shape (n_cells, n_t)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))[None, :]
    col = lambda a: np.asarray(a, dtype=np.float64)[:, None]  # noqa: E731
    with np.errstate(invalid="ignore", divide="ignore"):
        return (col(fit.r0_ohm)
                - col(fit.r_fast_ohm) * np.expm1(-t / col(fit.tau_fast_s))
                - col(fit.r_slow_ohm) * np.expm1(-t / col(fit.tau_slow_s)))


# --------------------------------------------------------------------------------------
# shared data preparation and model pieces
# --------------------------------------------------------------------------------------
def _check_t(t_s) -> np.ndarray:
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"t_s must be a 1-D array of at least 2 times, got shape {t.shape}")
    if not np.all(np.isfinite(t)) or t[0] < 0 or np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be finite, >= 0 and strictly increasing")
    return t


def _check_r(r_ohm, n_t: int) -> np.ndarray:
    r = np.asarray(r_ohm, dtype=np.float64)
    if r.ndim == 1:
        r = r[None, :]
    if r.ndim != 2 or r.shape[1] != n_t:
        raise ValueError(f"r_ohm must have shape (n_cells, {n_t}), got {np.shape(r_ohm)}")
    if np.any(np.isinf(r)):
        raise ValueError("r_ohm has infinite values (use NaN for points not reached)")
    return r


@dataclass(frozen=True)
class _Data:
    t: np.ndarray        # (n_t,)
    r: np.ndarray        # (n_c, n_t) as given (NaN = missing)
    mask: np.ndarray     # (n_c, n_t) valid points after the first valid one
    ok: np.ndarray       # (n_c,) enough points to fit
    t0: np.ndarray       # (n_c,) time of the pinned first point (0 where none)
    ra: np.ndarray       # (n_c,) R at the pinned point (0 where none)
    d: np.ndarray        # (n_c, n_t) R - ra on the mask, 0 elsewhere
    tm: np.ndarray       # (n_c, n_t) t on the mask, t0 elsewhere (phi = 0 there)
    scale: np.ndarray    # (n_c,) magnitude of d, for scaling (> 0)


def _prepare(t_s, r_ohm) -> _Data:
    t = _check_t(t_s)
    r = _check_r(r_ohm, t.size)
    n_c, n_t = r.shape
    valid = np.isfinite(r)
    has = valid.any(axis=1)
    first = np.argmax(valid, axis=1)
    rows = np.arange(n_c)
    mask = valid & (np.arange(n_t)[None, :] > first[:, None])
    ok = has & (mask.sum(axis=1) >= MIN_POINTS)
    t0 = np.where(has, t[first], 0.0)
    ra = np.where(has, r[rows, first], 0.0)
    d = np.where(mask, r - ra[:, None], 0.0)
    tm = np.where(mask, t[None, :], t0[:, None])
    scale = np.max(np.abs(d), axis=1, initial=0.0)
    scale = np.where(scale > 0, scale, np.where(np.abs(ra) > 0, np.abs(ra), 1.0))
    return _Data(t, r, mask, ok, t0, ra, d, tm, scale)


def _phi(tm, t0, tau):
    """exp(-t0/tau) - exp(-t/tau), written to stay accurate for t close to t0."""
    return -np.exp(-t0 / tau) * np.expm1(-(tm - t0) / tau)


def _r0(ra, t0, tf, ts, rf, rs):
    return ra + rf * np.expm1(-t0 / tf) + rs * np.expm1(-t0 / ts)


def _eq5(data: _Data, tf, ts, rf, rs) -> np.ndarray:
    """Eq. 5 per cell for parameter arrays of shape (n_c,)."""
    col = lambda a: a[:, None]  # noqa: E731
    t0 = col(data.t0)
    fitted = col(rf) * _phi(data.tm, t0, col(tf)) + col(rs) * _phi(data.tm, t0, col(ts))
    return np.sum(np.where(data.mask, np.abs(data.d - fitted), 0.0), axis=1)


def _result(data: _Data, tf, ts, rf, rs, converged, iterations, method) -> PointFit:
    ok = data.ok
    nan = np.full(ok.shape, np.nan)
    tf, ts, rf, rs = (np.where(ok, a, nan) for a in (tf, ts, rf, rs))
    r0 = _r0(data.ra, data.t0, tf, ts, rf, rs)
    # rounding only: at an active constraint R0 = 0 comes out a few ulps of R(t_0) off,
    # of either sign; snap it to exactly 0. Above 0 only by ulps of R(t_0): a GA stall
    # at R0 ~ 1e-14 R(t_0) is a fitted value that the curve R(t_0) depends on.
    tiny = 1e-12 * np.maximum(np.abs(data.ra), data.scale)
    ulps = 4 * np.spacing(np.abs(data.ra))
    r0 = np.where((r0 > -tiny) & (r0 < ulps), 0.0, r0)
    fitness = np.where(ok, _eq5(data, tf, ts, rf, rs), np.nan)
    return PointFit(r0_ohm=r0, r_fast_ohm=rf, tau_fast_s=tf, r_slow_ohm=rs, tau_slow_s=ts,
                    fitness_ohm=fitness, converged=np.asarray(converged, bool) & ok,
                    iterations=np.asarray(iterations, dtype=np.int64), method=method)


def _clip_params(b: Bounds, tf, ts, rf, rs):
    """Params clipped to the box: removes exp(log(tau)) rounding at an active bound."""
    return (np.clip(tf, *b.tau_fast_s), np.clip(ts, *b.tau_slow_s),
            np.clip(rf, *b.r_fast_ohm), np.clip(rs, *b.r_slow_ohm))


def _bounds_for(data: _Data, bounds: Bounds | None) -> Bounds:
    if bounds is None:
        return default_bounds(data.t, data.r)
    if not isinstance(bounds, Bounds):
        raise TypeError(f"bounds must be a Bounds, got {type(bounds).__name__}")
    return bounds


# --------------------------------------------------------------------------------------
# which DC-IR rows the five-point fits take
# --------------------------------------------------------------------------------------
SOC_LEVEL_GAP = 0.025     # pulses closer than this in SOC belong to one pulse set (level)


def soc_levels(soc, direction, gap: float = SOC_LEVEL_GAP) -> list[np.ndarray]:
    """Row indices grouped into SOC levels (pulse sets), per direction (charge first), each
    direction by falling SOC: a level takes the rows within ``gap`` of its first row."""
    soc = np.asarray(soc, dtype=np.float64)
    direction = np.asarray(direction)
    groups: list[list[int]] = []
    for d in ("charge", "discharge"):
        ix = np.flatnonzero(direction == d)
        ix = ix[np.argsort(-soc[ix], kind="stable")]
        start = len(groups)
        for k in ix:
            if len(groups) > start and abs(soc[groups[-1][0]] - soc[k]) <= gap:
                groups[-1].append(int(k))
            else:
                groups.append([int(k)])
    return [np.array(g) for g in groups]


def _mean_of_finite(rows: np.ndarray) -> np.ndarray:
    """Column means over the finite values; NaN where a column has none (no warning)."""
    ok = np.isfinite(rows)
    n = ok.sum(axis=0)
    total = np.where(ok, rows, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _ranges(items: list[tuple[float, float]]) -> str:
    """'6C at SOC 1.00-0.20, 4C at 0.15' from (soc, rate) pairs in level order."""
    parts: list[list] = []
    for soc, rate in items:
        if parts and parts[-1][0] == rate:
            parts[-1][2] = soc
        else:
            parts.append([rate, soc, soc])
    return ", ".join(f"{r:g}C at SOC {a:.2f}" + (f"-{b:.2f}" if b != a else "")
                     for r, a, b in parts)


def five_point_rows(table, c_rate="max") -> tuple:
    """The DC-IR rows the five-point fits (GA, LM) use: one per SOC level and direction.

    A row is complete when it has R(t) at every time of the table (a pulse cut short by a
    voltage limit is not in the table at all, :func:`ecmgen.data.dcir.extract_dcir`).
    ``c_rate="max"``: at each level the highest C-rate whose pulses are complete (the
    paper's "highest C-rate" where the test has it); a number: the complete C-rate nearest
    to it; ``"all"``: R(t) averaged over every C-rate of the level. A level without a
    complete pulse is left out (the tables interpolate over it) and named in the notes.
    Returns (table of the chosen rows, notes)."""
    from ..data.dcir import DcirTable

    notes: list[str] = []
    soc, direction, rate, r = [], [], [], []
    complete = np.all(np.isfinite(table.r_ohm), axis=1)
    for d in ("charge", "discharge"):
        picked, missing = [], []
        for g in soc_levels(table.soc, table.direction):
            if table.direction[g[0]] != d:
                continue
            level = float(np.mean(table.soc[g]))
            if c_rate == "all":
                use = g
            else:
                ok = g[complete[g]]
                if ok.size == 0:
                    missing.append(level)
                    continue
                rates = table.c_rate[ok]
                pick = rates.max() if c_rate == "max" else \
                    rates[np.argmin(np.abs(rates - float(c_rate)))]
                use = ok[rates == pick]
                picked.append((level, float(pick)))
            soc.append(float(np.mean(table.soc[use])))
            direction.append(d)
            rate.append(float(np.mean(table.c_rate[use])))
            r.append(_mean_of_finite(table.r_ohm[use]))
        if picked:
            what = "the highest C-rate with complete pulses" if c_rate == "max" else \
                f"the complete C-rate nearest {float(c_rate):g}C"
            notes.append(f"five-point fits, {d}: {what} at each SOC level: {_ranges(picked)}")
        if missing:
            notes.append(f"five-point fits, {d}: no complete pulse at SOC "
                         f"{', '.join(f'{s:.3f}' for s in missing)}: those levels are left "
                         "out and interpolated from their neighbours")
    if c_rate == "all":
        notes.append("five-point fits use R(t) averaged over all C-rates of each SOC level")
    n_t = table.t_s.size
    out = DcirTable(np.array(soc), np.array(direction, dtype=str), np.array(rate),
                    table.t_s, np.array(r).reshape(len(r), n_t), table.notes)
    return out, notes
