"""Whole-curve fit: every sample of each pulse AND its relaxation.

Five DC-IR points within 10 s cannot see time constants of minutes; the rest after a
pulse can. For each pulse the measured voltage from the rested sample before the edge
to the next pulse (at most ``relax_s`` after the edge) is compared with the same
discrete 2RC the simulator runs, driven by the measured current:

    v_k - v_rest = ocv(soc_k) - ocv(soc_rest) + r0*i_k + r_fast*x_fast_k + r_slow*x_slow_k

where x_j is the unit-resistance response (x_k = a x_{k-1} + (1 - a) i_k, a = exp(-dt/tau)).
Given (tau_fast, tau_slow) the model is linear in the resistances, so they are solved
by non-negative least squares (variable projection); the two time constants are found
by a log grid and refined with scipy's least_squares. Pulses of one SOC level and
direction are fitted jointly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, nnls

from .dcir import Pulse
from .measure import TimeSeries
from .model import OcvTable


@dataclass(frozen=True)
class CurveFit:
    """One row per fitted group (SOC level x direction)."""

    soc: np.ndarray
    direction: np.ndarray
    r0_ohm: np.ndarray
    r_fast_ohm: np.ndarray
    tau_fast_s: np.ndarray
    r_slow_ohm: np.ndarray
    tau_slow_s: np.ndarray
    rms_error_v: np.ndarray
    converged: np.ndarray
    windows: tuple          # per group: list of (time_s, measured_dv, fitted_dv) for plots


@dataclass(frozen=True)
class _Window:
    dt: np.ndarray       # s, dt[0] = 0
    i: np.ndarray        # A, relative to the rest current
    target: np.ndarray   # v - v_rest - (ocv(soc) - ocv(soc_rest))  [V]
    t: np.ndarray        # s from the rest sample
    docv: np.ndarray


def _window(series: TimeSeries, p: Pulse, ocv: OcvTable, capacity_ah: float,
            relax_s: float) -> _Window:
    t = series.time_s
    a = p.rest_index
    end = p.next_start
    b = int(np.searchsorted(t, t[a] + relax_s, side="right"))
    b = max(min(b, end), p.stop)
    tt = t[a:b] - t[a]
    dt = np.diff(tt, prepend=0.0)
    i = series.current_a[a:b] - series.current_a[a]
    q_ah = np.cumsum(i * dt) / 3600.0
    docv = ocv.ocv_at(p.soc + q_ah / capacity_ah) - ocv.ocv_at(p.soc)
    target = series.voltage_v[a:b] - series.voltage_v[a] - docv
    return _Window(dt, i, target, tt, docv)


def _unit_responses(win: _Window, taus: np.ndarray) -> np.ndarray:
    """x[k, m]: response of a 1-ohm RC with time constant taus[m] to the window current."""
    a = np.exp(-win.dt[:, None] / taus[None, :])
    b = (1.0 - a) * win.i[:, None]
    x = np.empty_like(a)
    acc = np.zeros(taus.size)
    for k in range(a.shape[0]):
        acc = a[k] * acc + b[k]
        x[k] = acc
    return x


def _solve(wins, xf, xs):
    """NNLS for (r0, r_fast, r_slow) given the unit responses; returns (r, residual)."""
    A = np.vstack([np.column_stack([w.i, f, s]) for w, f, s in zip(wins, xf, xs)])
    y = np.concatenate([w.target for w in wins])
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    r, _ = nnls(A / scale, y)
    r = r / scale
    return r, A @ r - y


def fit_group(wins: list[_Window], *, tau_fast_range=(0.2, 60.0),
              tau_slow_range=(5.0, 3000.0), n_grid: int = 24):
    """Fit one group of windows. Returns (r0, r_fast, tau_fast, r_slow, tau_slow, rms, ok)."""
    lo = min(tau_fast_range[0], tau_slow_range[0])
    hi = max(tau_fast_range[1], tau_slow_range[1])
    grid = np.geomspace(lo, hi, n_grid)
    X = [_unit_responses(w, grid) for w in wins]
    best = (np.inf, None)
    for m, tf in enumerate(grid):
        if not tau_fast_range[0] <= tf <= tau_fast_range[1]:
            continue
        for n in range(m + 1, grid.size):
            ts = grid[n]
            if not tau_slow_range[0] <= ts <= tau_slow_range[1] or ts < 2.0 * tf:
                continue
            _, res = _solve(wins, [x[:, m] for x in X], [x[:, n] for x in X])
            cost = float(res @ res)
            if cost < best[0]:
                best = (cost, (tf, ts))
    if best[1] is None:
        raise ValueError("empty time-constant search range")

    def resid(z):
        tf, ts = np.exp(z)
        taus = np.array([tf, ts])
        xs = [_unit_responses(w, taus) for w in wins]
        _, res = _solve(wins, [x[:, 0] for x in xs], [x[:, 1] for x in xs])
        return res

    lb = np.log([tau_fast_range[0], tau_slow_range[0]])
    ub = np.log([tau_fast_range[1], tau_slow_range[1]])
    z0 = np.clip(np.log(best[1]), lb + 1e-9, ub - 1e-9)
    sol = least_squares(resid, z0, bounds=(lb, ub), x_scale=1.0, diff_step=1e-4,
                        xtol=1e-8, ftol=1e-10, max_nfev=200)
    tf, ts = np.exp(sol.x)
    if ts < tf:
        tf, ts = ts, tf
    taus = np.array([tf, ts])
    xs = [_unit_responses(w, taus) for w in wins]
    r, res = _solve(wins, [x[:, 0] for x in xs], [x[:, 1] for x in xs])
    rms = float(np.sqrt(np.mean(res ** 2)))
    return r[0], r[1], tf, r[2], ts, rms, bool(sol.success), xs, r


def fit_pulse_curves(series: TimeSeries, pulses: list[Pulse], ocv: OcvTable,
                     capacity_ah: float, *, relax_s: float = 1800.0,
                     soc_gap: float = 0.025, progress=None, **ranges) -> CurveFit:
    """Fit every SOC level x direction of a pulse test on the full voltage curves.

    Pulses closer than ``soc_gap`` in SOC (one pulse set) form one level; pulses
    flagged cut_short are left out."""
    use = [p for p in pulses if not p.cut_short]
    groups: list[list[Pulse]] = []
    for direction in ("charge", "discharge"):
        ps = sorted((p for p in use if p.direction == direction), key=lambda p: -p.soc)
        for p in ps:
            if groups and groups[-1][0].direction == direction and \
                    abs(groups[-1][0].soc - p.soc) <= soc_gap:
                groups[-1].append(p)
            else:
                groups.append([p])
    rows = []
    for g_ix, g in enumerate(groups):
        wins = [_window(series, p, ocv, capacity_ah, relax_s) for p in g]
        r0, rf, tf, rs, ts, rms, ok, xs, r = fit_group(wins, **ranges)
        fitted = [w.i * r[0] + x[:, 0] * r[1] + x[:, 1] * r[2] for w, x in zip(wins, xs)]
        # the SOC of a level: the charge-weighted mean over its pulses
        soc = float(np.mean([p.soc for p in g]))
        rows.append((soc, g[0].direction, r0, rf, tf, rs, ts, rms, ok,
                     [(w.t, w.target + w.docv, f + w.docv) for w, f in zip(wins, fitted)]))
        if progress:
            progress(g_ix + 1, len(groups))
    rows.sort(key=lambda r: (r[1], r[0]))
    col = lambda j: np.array([r[j] for r in rows])  # noqa: E731
    return CurveFit(col(0), col(1), col(2).astype(float), col(3).astype(float),
                    col(4).astype(float), col(5).astype(float), col(6).astype(float),
                    col(7).astype(float), col(8).astype(bool), tuple(r[9] for r in rows))
