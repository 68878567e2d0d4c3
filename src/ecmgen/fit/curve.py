"""Whole-curve fit: every sample of each pulse AND its relaxation.

Five DC-IR points within 10 s cannot see time constants of minutes; the rest after a
pulse can. For each pulse the measured voltage from the rested sample before the edge
to the next pulse (at most ``relax_s`` after the edge) is compared with the same
discrete 2RC the simulator runs, driven by the measured current:

    v_k - v_rest = ocv(soc_k) - ocv(soc_rest) + r0*i_k + r_fast*x_fast_k + r_slow*x_slow_k
                   + u0 * (exp(-t_k/tau_slow) - 1)

where x_j is the unit-resistance response (x_k = a x_{k-1} + (1 - a) i_k, a = exp(-dt/tau)).
Given (tau_fast, tau_slow) the model is linear in the resistances, so they are solved
by bounded linear least squares, R >= 0 (variable projection); the two time constants are found
by a log grid and refined with scipy's least_squares. Pulses of one SOC level and
direction are fitted jointly. Each window also gets a free initial slow-state voltage
u0, since a cell is rarely fully relaxed at the rest sample (exact for a 2RC: an initial
state decays with the same time constant); v_rest is the mean of the last 10 s of rest.
Windows end at the next current flow, at ``relax_s``, or at a gap in the log.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from ..data.dcir import Pulse
from ..data.measure import TimeSeries
from ..data.ocv import OcvTable


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
            relax_s: float, ref_s: float = 10.0) -> _Window:
    t = series.time_s
    a = p.rest_index
    end = p.next_start
    b = int(np.searchsorted(t, t[a] + relax_s, side="right"))
    b = max(min(b, end, _first_gap(series, p.stop, b)), p.stop)
    tt = t[a:b] - t[a]
    dt = np.diff(tt, prepend=0.0)
    i = series.current_a[a:b] - series.current_a[a]
    q_ah = np.cumsum(i * dt) / 3600.0
    docv = ocv.ocv_at(p.soc + q_ah / capacity_ah) - ocv.ocv_at(p.soc)
    # reference: the mean rested voltage over the last ``ref_s`` before the edge (one
    # sample's noise would otherwise shift the whole window)
    pre = np.flatnonzero((t[:a + 1] >= t[a] - ref_s))
    rested = np.abs(series.current_a[pre] - series.current_a[a]) <= 1e-3 + 0.01 * abs(series.current_a[a])
    pre = pre[rested & (pre > _last_moving(series, a))]
    v_ref = float(np.mean(series.voltage_v[pre])) if pre.size else float(series.voltage_v[a])
    target = series.voltage_v[a:b] - v_ref - docv
    return _Window(dt, i, target, tt, docv)


def _last_moving(series: TimeSeries, a: int) -> int:
    """Index of the last sample before ``a`` whose current differs from the rest at a."""
    i = series.current_a[:a + 1]
    moving = np.flatnonzero(np.abs(i - i[-1]) > 1e-3 + 0.01 * abs(i[-1]))
    return int(moving[-1]) if moving.size else -1


def _first_gap(series: TimeSeries, start: int, stop: int) -> int:
    """First index in [start, stop) that follows an unlogged stretch: a time step far
    longer than the record's usual rest sampling, or one across which the logged Ah
    counter moved (current flowed that the file does not show)."""
    t = series.time_s[start - 1:stop]
    dt = np.diff(t)
    if dt.size == 0:
        return stop
    gap = dt > max(60.0, 20.0 * float(np.median(dt)))
    if series.charge_ah is not None:
        q = series.charge_ah[start - 1:stop]
        logged = np.diff(q)
        expected = series.current_a[start:stop] * dt / 3600.0
        gap |= np.abs(logged - expected) > 1e-3 * max(1.0, float(np.ptp(series.charge_ah)))
    hits = np.flatnonzero(gap)
    return int(start + hits[0]) if hits.size else stop


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


def _solve(wins, xf, xs, tau_slow_s: float):
    """Least squares for (r0, r_fast, r_slow) >= 0 given the unit responses, plus per
    window a free initial slow-state voltage u0 (the cell still relaxing from what came
    before the rest sample: it decays as u0 * (exp(-t/tau_slow) - 1) relative to v_rest).
    Returns (r, u0 per window, residual)."""
    n = len(wins)
    blocks = []
    for j, (w, f, s) in enumerate(zip(wins, xf, xs)):
        drift = np.zeros((w.t.size, n))
        drift[:, j] = np.expm1(-w.t / tau_slow_s)
        blocks.append(np.column_stack([w.i, f, s, drift]))
    A = np.vstack(blocks)
    y = np.concatenate([w.target for w in wins])
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    lo = np.concatenate([np.zeros(3), np.full(n, -np.inf)])
    sol = lsq_linear(A / scale, y, bounds=(lo, np.inf), method="bvls")
    x = sol.x / scale
    return x[:3], x[3:], A @ x - y


def fit_group(wins: list[_Window], *, tau_fast_range=(0.2, 60.0),
              tau_slow_range=(5.0, 3000.0), n_grid: int = 24):
    """Fit one group of windows. Returns (r0, r_fast, tau_fast, r_slow, tau_slow, rms, ok,
    unit responses, resistances, drift); ok is False when the refinement failed or a
    time constant ended on its search bound (not resolved by the data)."""
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
            _, _, res = _solve(wins, [x[:, m] for x in X], [x[:, n] for x in X], ts)
            cost = float(res @ res)
            if cost < best[0]:
                best = (cost, (tf, ts))
    if best[1] is None:
        raise ValueError("empty time-constant search range")

    def resid(z):
        tf, ts = np.exp(z)
        taus = np.array([tf, ts])
        xs = [_unit_responses(w, taus) for w in wins]
        _, _, res = _solve(wins, [x[:, 0] for x in xs], [x[:, 1] for x in xs], ts)
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
    r, u0, res = _solve(wins, [x[:, 0] for x in xs], [x[:, 1] for x in xs], ts)
    rms = float(np.sqrt(np.mean(res ** 2)))
    drift = [u * np.expm1(-w.t / ts) for u, w in zip(u0, wins)]
    # a time constant pinned at its search bound was not resolved by the data
    at_edge = (np.isclose(ts, tau_slow_range[1], rtol=0.01) or
               np.isclose(tf, tau_fast_range[0], rtol=0.01) and r[1] > 0.05 * r[0])
    ok = bool(sol.success) and not at_edge and np.all(np.isfinite(r))
    return r[0], r[1], tf, r[2], ts, rms, ok, xs, r, drift


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
        r0, rf, tf, rs, ts, rms, ok, xs, r, drift = fit_group(wins, **ranges)
        fitted = [w.i * r[0] + x[:, 0] * r[1] + x[:, 1] * r[2] + d
                  for w, x, d in zip(wins, xs, drift)]
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
