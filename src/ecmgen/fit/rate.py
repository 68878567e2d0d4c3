"""The pulse resistance's dependence on the current: Butler-Volmer's exchange current i0.

In the cold, R(1 s) of a pulse falls with its C-rate (charge transfer: the overpotential
grows like asinh(i / i0), not like i), while R(0.1 s) does not. Per SOC level l and pulse p
of current I_p the DC-IR table is fitted with

    R_p(t) = R0_l + r_l g(I_p / i0),    g(x) = asinh(x) / x                   (form B)

R0_l, the level's ohmic part, is the median first-sample resistance of its pulses of the
lower half of its C-rates (the first sample after a high-current edge catches the ramp);
r_l >= 0 is linear per level; i0 (one per test) minimises the relative residual
sum_p ((R_fit - R_p) / R_p)^2 by a 1-D search over ln i0. The fit uses complete rows with
0.3 < soc < 0.96 (away from the steep ends of the OCV), at ``t_s`` (default 1 s).

The result goes to the model's fast branch (r_fast g(i) i, :mod:`ecmgen.model.simulate`).
When the test cannot show the dependence -- fewer than two C-rates at a level, an i0 at
the top of the search range (g = 1 over the test's currents), or a fit that explains less
than ``min_gain`` of the residual of the current-independent fit -- ``i0_a`` is None: no
Butler-Volmer branch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .points import soc_levels

I0_RANGE_A = (0.01, 1000.0)


@dataclass(frozen=True)
class ExchangeCurrentFit:
    """i0_a: the exchange current (A), None when the test shows no current dependence.
    rms_rel / rms_rel_linear: relative RMS of form B / of the current-independent fit;
    n_rows: DC-IR rows used; notes: what was decided and why."""

    i0_a: float | None
    rms_rel: float
    rms_rel_linear: float
    n_rows: int
    notes: tuple[str, ...]


def butler_volmer_g(x) -> np.ndarray:
    """g(x) = asinh(x) / x (1 at x -> 0)."""
    x = np.maximum(np.abs(np.asarray(x, dtype=np.float64)), 1e-12)
    return np.arcsinh(x) / x


def fit_exchange_current(table, capacity_ah: float, *, t_s: float = 1.0,
                         soc_range: tuple[float, float] = (0.3, 0.96),
                         min_gain: float = 0.2) -> ExchangeCurrentFit:
    """i0 of one pulse test from its DC-IR table (module docstring)."""
    j = int(np.argmin(np.abs(table.t_s - t_s)))
    r = table.r_ohm[:, j]
    r_first = table.r_ohm[:, 0]
    ok = (np.isfinite(r) & np.isfinite(r_first) & (r > 0) & (table.soc > soc_range[0]) &
          (table.soc < soc_range[1]) & np.all(np.isfinite(table.r_ohm), axis=1))
    current = table.c_rate * capacity_ah
    levels, r0_level = [], []
    for g in soc_levels(table.soc, table.direction):
        g = g[ok[g]]
        if g.size < 2 or np.unique(table.c_rate[g]).size < 2:
            continue
        rates = table.c_rate[g]
        low = g[rates <= np.median(np.unique(rates))]
        levels.append(g)
        r0_level.append(float(np.median(r_first[low])))
    n = int(sum(g.size for g in levels))
    what = f"R({table.t_s[j]:g} s)"
    if not levels:
        return ExchangeCurrentFit(None, np.nan, np.nan, n, (
            f"Butler-Volmer: no SOC level in {soc_range[0]:g}..{soc_range[1]:g} has complete "
            "pulses at two C-rates: no current dependence fitted (i0 none)",))
    rows = np.concatenate(levels)
    lev = np.concatenate([np.full(g.size, k) for k, g in enumerate(levels)])
    r_row = r[rows]
    base = np.array(r0_level)[lev]
    cur = current[rows]

    def fit(i0):
        """Per-level r_l >= 0 in closed form; relative residuals."""
        gx = butler_volmer_g(cur / i0) if np.isfinite(i0) else np.ones_like(cur)
        a = gx / r_row
        b = (r_row - base) / r_row
        num = np.bincount(lev, a * b, len(levels))
        den = np.bincount(lev, a * a, len(levels))
        rl = np.maximum(num / np.maximum(den, 1e-300), 0.0)
        res = (base + rl[lev] * gx - r_row) / r_row
        return float(np.sqrt(np.mean(res ** 2)))

    grid = np.geomspace(*I0_RANGE_A, 161)
    cost = np.array([fit(v) for v in grid])
    k = int(np.argmin(cost))
    lo, hi = np.log(grid[max(k - 1, 0)]), np.log(grid[min(k + 1, grid.size - 1)])
    for _ in range(40):                      # golden section on ln i0 around the best
        a = hi - 0.618 * (hi - lo)
        b = lo + 0.618 * (hi - lo)
        if fit(np.exp(a)) < fit(np.exp(b)):
            hi = b
        else:
            lo = a
    i0 = float(np.exp(0.5 * (lo + hi)))
    rms, rms_lin = fit(i0), fit(np.inf)
    head = (f"Butler-Volmer: {what} over {n} complete pulses at {len(levels)} SOC levels "
            f"({np.unique(table.c_rate[rows]).size} C-rates): ")
    if k >= grid.size - 2:
        return ExchangeCurrentFit(None, rms, rms_lin, n, (
            head + f"no current dependence (i0 at the top of its range, relative RMS "
                   f"{rms_lin * 100:.1f} %): no Butler-Volmer branch",))
    if rms > (1.0 - min_gain) * rms_lin:
        return ExchangeCurrentFit(None, rms, rms_lin, n, (
            head + f"i0 {i0:.3g} A explains too little (relative RMS {rms * 100:.1f} % vs "
                   f"{rms_lin * 100:.1f} % without): no Butler-Volmer branch",))
    return ExchangeCurrentFit(i0, rms, rms_lin, n, (
        head + f"i0 {i0:.3g} A (relative RMS {rms * 100:.1f} %, {rms_lin * 100:.1f} % "
               "without current dependence) on the fast branch",))


# i0 / capacity searched by best_exchange_current: from a tenth of 1 C (strongly curved
# over a pulse test's currents) to 30 C (g = asinh(x)/x > 0.999 at 2 C: no dependence)
I0_SEARCH_C = (0.1, 30.0)


def best_exchange_current(rms_at, capacity_ah: float, *, grid: int = 6, refine: int = 5):
    """The i0 (A) of a current-dependent resistance that a whole-test fit supports best.

    ``rms_at(i0_a) -> (rms, result)`` refits the test with the resistance factor
    g = asinh(x) / x, x = |i| / i0 (r0 and r_fast) and returns its fit RMS. A log-spaced
    grid of ``grid`` points over I0_SEARCH_C x capacity, then a bounded scalar search
    (``refine`` evaluations) between the best point's neighbours. Returns
    (i0_a, rms, result) of the best evaluation."""
    from scipy.optimize import minimize_scalar

    seen: dict[float, tuple] = {}

    def at(ln_i0: float) -> float:
        key = round(float(ln_i0), 6)
        if key not in seen:
            seen[key] = rms_at(float(np.exp(key)))
        return float(seen[key][0])

    lo, hi = np.log(np.asarray(I0_SEARCH_C) * capacity_ah)
    pts = np.linspace(lo, hi, grid)
    k = int(np.argmin([at(p) for p in pts]))
    a, b = pts[max(k - 1, 0)], pts[min(k + 1, grid - 1)]
    if refine > 0 and b > a:
        minimize_scalar(at, bounds=(a, b), method="bounded",
                        options={"maxiter": refine, "xatol": 0.05})
    key = min(seen, key=lambda s: seen[s][0])
    return float(np.exp(key)), float(seen[key][0]), seen[key][1]
