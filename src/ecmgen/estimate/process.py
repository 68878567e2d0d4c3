"""The model's discrete step in the filter's terms: state layout, process and measurement
functions, and their exact Jacobians.

The filter state after sample k is ``x = [soc, u_fast, u_slow, (u_diff), (u_extra), (h),
(offset_a)]`` (parenthesised entries only when the model has the diffusion pair, an
``extra_rc`` effect, a ``hysteresis`` effect, or when the current-offset state is asked
for). The inputs of sample k are dt_k, the current the filter sees i_seen_k and the cell
temperature T_k; the filter's current is i_k = i_seen_k - offset_a. With that current,
:meth:`StepModel.predict` is exactly the step of :mod:`ecmgen.model.simulate` (and of
:mod:`ecmgen.model.effects` for a model with effects), steps 1-4, and
:meth:`StepModel.measure` its step 5::

    soc_k  = soc + i_k dt_k / (3600 Q_eff)
    p      = table parameters of the direction at (soc_k, T_k), times the effects' factors
    u_j   <- a_j u_j + r_j (1 - a_j) i_k,   a_j = exp(-dt_k / tau_j)    (j = fast, slow, diff,
              extra; r_fast includes the Butler-Volmer g(i_k) = asinh(x)/x)
    h     <- a_h h + (1 - a_h) s_k,         a_h = exp(-|i_k| dt_k / (3600 decay_ah))
    v_k    = ocv(soc_k, T_k) + r0 i_k + u_fast + u_slow + u_diff + u_extra
             + m_v (h - h_table) + m0_v (s_k - h_table)

The Jacobians are analytic: d/dsoc through the piecewise-linear tables (the slope of the
segment the SOC is in, 0 where a table clamps; at a breakpoint the segment to its right;
with ``resistance_slopes`` False the RC tables' slopes are taken as 0, so that the SOC is
read from the OCV alone),
d/d(offset) through the current (d(i g(i))/di = 1/sqrt(1 + x^2) for the Butler-Volmer
branch) and through soc_k. The direction (deadband) is piecewise constant and has no
derivative. Everything is scalar arithmetic in a fixed order with exp, asinh and sqrt as
the only functions, so that a float32 C port follows it line by line.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..model.effects import (CapacityError, CurrentDependentResistance, ExtraRc, Hysteresis,
                             TemperatureDependence)
from ..model.model import EcmModel, RcTable, _grid_weights

KELVIN = 273.15
TABLE_FIELDS = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")
X_MIN = 1e-12            # as butler_volmer_factor: x = max(|i| / i0, 1e-12)


@dataclass(frozen=True)
class Layout:
    """Which state sits where. ``names`` in state order; an absent state has index -1."""

    names: tuple[str, ...]

    def index(self, name: str) -> int:
        return self.names.index(name) if name in self.names else -1

    @property
    def n(self) -> int:
        return len(self.names)


def state_layout(model: EcmModel, offset_state: bool = False) -> Layout:
    names = ["soc", "u_fast_v", "u_slow_v"]
    if model.discharge.has_diffusion:
        names.append("u_diff_v")
    if any(isinstance(e, ExtraRc) for e in model.effects):
        names.append("u_extra_v")
    if any(isinstance(e, Hysteresis) for e in model.effects):
        names.append("h")
    if offset_state:
        names.append("offset_a")
    return Layout(tuple(names))


class _Table:
    """One direction's table as plain lists: rows[t][j] = (r0, r_fast, tau_fast, r_slow,
    tau_slow) at temperature row t and SOC breakpoint j; per-temperature branch values."""

    def __init__(self, t: RcTable):
        self.soc = [float(s) for s in t.soc]
        cols = [np.asarray(getattr(t, k), dtype=np.float64) for k in TABLE_FIELDS]
        self.rows = [[tuple(float(c[r, j]) for c in cols) for j in range(t.soc.size)]
                     for r in range(t.n_temperatures)]
        self.r_diff = None if t.r_diff_ohm is None else [float(v) for v in t.r_diff_ohm]
        self.tau_diff = None if t.tau_diff_s is None else [float(v) for v in t.tau_diff_s]
        self.i0 = None if t.i0_a is None else [float(v) for v in t.i0_a]


def _segment(grid: list[float], x: float) -> tuple[int, float, float]:
    """Segment j, position t in [0, 1] and d t/dx of x on a piecewise-linear grid, as
    np.interp and interp_2d_soc_slope: clamped ends (slope 0 outside), a breakpoint
    belongs to the segment on its right."""
    n = len(grid)
    if n == 1:
        return 0, 0.0, 0.0
    if x < grid[0]:
        return 0, 0.0, 0.0
    if x > grid[-1]:
        return n - 2, 1.0, 0.0
    j = min(bisect_right(grid, x) - 1, n - 2)
    inv = 1.0 / (grid[j + 1] - grid[j])
    return j, (x - grid[j]) * inv, inv


def _row_value(row, j: int, t: float, inv: float, f: int) -> tuple[float, float]:
    y0 = row[j][f]
    if len(row) == 1:
        return y0, 0.0
    d = row[j + 1][f] - y0
    return y0 + d * t, d * inv


class StepAux(NamedTuple):
    """What one predict hands to the measurement and the process noise."""

    i: float                 # the filter's current (after the offset state), A
    charging: bool           # the direction of this sample
    g0: float                # resistance factor of r0 (current-dependent resistance)
    dg0: float               # d(i g0)/di
    rc: tuple                # (state index, a_j, r_j g_j) per RC branch
    u_prev: float = 0.0      # u_diff before the step (the surface SOC reads it)


@dataclass
class StepInputs:
    """Per-sample inputs prepared once for a whole record (vectorised): dt, the
    temperature row/weight of the RC tables, of the OCV, and the effects' factors."""

    dt: list
    i_seen: list
    t_rc: list          # per sample ((k, w) of the charge table, of the discharge table);
                        # (k, w) is None for a table without a temperature axis
    t_ocv: list
    temperature_factor: list   # temperature_dependence factor per sample (1.0 without)


class StepModel:
    """The model's step for a filter: :meth:`predict` (state and its Jacobian) and
    :meth:`measure` (terminal voltage and its gradient)."""

    def __init__(self, model: EcmModel, offset_state: bool = False,
                 resistance_slopes: bool = True):
        self.model = model
        self.slopes = resistance_slopes   # False: the Jacobians take the RC tables as flat in SOC
        # surface SOC (model.surface_soc_gain): lam / max(dOCV/dSOC, 0.3 V) on the OCV grid
        self.sv_rows = ([[float(v) for v in row] for row in model.surface_per_volt_rows()]
                        if model.surface_soc_gain else None)
        self.layout = state_layout(model, offset_state)
        lay = self.layout
        self.i_ud, self.i_ux = lay.index("u_diff_v"), lay.index("u_extra_v")
        self.i_h, self.i_b = lay.index("h"), lay.index("offset_a")
        self.n = lay.n
        self.tables = {True: _Table(model.charge), False: _Table(model.discharge)}
        self.ocv_soc = [float(s) for s in model.ocv.soc]
        self.ocv_rows = [[float(v) for v in row] for row in model.ocv.ocv_v]
        scale = 1.0
        self.cdr: list[tuple[float, float]] = []     # (scale_at_zero, i0_a)
        self.temp_dep: list[TemperatureDependence] = []
        self.hyst: Hysteresis | None = None
        self.extra: ExtraRc | None = None
        for e in model.effects:
            if isinstance(e, CapacityError):
                scale *= e.capacity_scale
            elif isinstance(e, CurrentDependentResistance):
                self.cdr.append((e.scale_at_zero, e.i0_a))
            elif isinstance(e, TemperatureDependence):
                self.temp_dep.append(e)
            elif isinstance(e, Hysteresis):
                if self.hyst is not None:
                    raise ValueError("the estimator takes at most one hysteresis effect")
                self.hyst = e
            elif isinstance(e, ExtraRc):
                if self.extra is not None:
                    raise ValueError("the estimator takes at most one extra_rc effect")
                self.extra = e
        self.soc_per_as = 1.0 / (3600.0 * model.capacity_ah * scale)
        self.deadband = float(model.direction_deadband_a)
        self._surface_last = self._r0_last = (None, None, None, None)

    # -- per-record inputs ------------------------------------------------------------
    def inputs(self, time_s, i_seen, temperature_c=None) -> StepInputs:
        time_s = np.asarray(time_s, dtype=np.float64)
        dt = np.diff(time_s, prepend=time_s[0])
        n = time_s.size

        def weights(grid, rows):
            if rows == 1 or temperature_c is None:
                return [None] * n
            k, w = _grid_weights(grid, temperature_c)
            return list(zip(np.broadcast_to(k, (n,)).tolist(),
                            np.broadcast_to(w, (n,)).tolist()))

        m = self.model
        tf = np.ones(n)
        if temperature_c is not None:
            for e in self.temp_dep:
                tf = tf * e.factor(temperature_c)
        return StepInputs(dt.tolist(), np.asarray(i_seen, dtype=np.float64).tolist(),
                          list(zip(weights(m.charge.temperature_c, m.charge.n_temperatures),
                                   weights(m.discharge.temperature_c,
                                           m.discharge.n_temperatures))),
                          weights(m.ocv.temperature_c, m.ocv.n_temperatures),
                          np.broadcast_to(tf, (n,)).tolist())

    # -- parameters ---------------------------------------------------------------------
    def params(self, charging: bool, soc: float, tw):
        """Table values and their d/dsoc at (soc, T): two lists of the five TABLE_FIELDS,
        and the per-temperature (r_diff, tau_diff, i0) (None where absent)."""
        tab = self.tables[charging]
        tw = tw[0] if charging else tw[1]
        j, t, inv = _segment(tab.soc, soc)
        # _row_value over the five fields, written out: the filter's innermost loop
        if tw is None:
            row = tab.rows[0]
            if len(row) == 1:
                vals, slopes = list(row[0]), [0.0] * 5
            else:
                a, b = row[j], row[j + 1]
                d = [b[f] - a[f] for f in range(5)]
                vals = [a[f] + d[f] * t for f in range(5)]
                slopes = [e * inv for e in d]
            branch = tuple(None if b is None else b[0]
                           for b in (tab.r_diff, tab.tau_diff, tab.i0))
            return vals, slopes, branch
        k, w = tw
        lo, hi = tab.rows[k], tab.rows[k + 1]
        if len(lo) == 1:
            v0, v1 = lo[0], hi[0]
            vals = [v0[f] + (v1[f] - v0[f]) * w for f in range(5)]
            slopes = [0.0 + (0.0 - 0.0) * w] * 5
        else:
            a0, b0, a1, b1 = lo[j], lo[j + 1], hi[j], hi[j + 1]
            vals, slopes = [], []
            for f in range(5):
                y0, y1 = a0[f], a1[f]
                d0, d1 = b0[f] - y0, b1[f] - y1
                v0, v1 = y0 + d0 * t, y1 + d1 * t
                s0, s1 = d0 * inv, d1 * inv
                vals.append(v0 + (v1 - v0) * w)
                slopes.append(s0 + (s1 - s0) * w)
        branch = tuple(None if b is None else b[k] + (b[k + 1] - b[k]) * w
                       for b in (tab.r_diff, tab.tau_diff, tab.i0))
        return vals, slopes, branch

    def _on_ocv_grid(self, rows, soc: float, tw) -> tuple[float, float]:
        """A table on the OCV's grid (the OCV, the surface SOC's) and its SOC slope at
        (soc, T), bilinear."""
        j, t, inv = _segment(self.ocv_soc, soc)
        if tw is None:
            return _ocv_row(rows[0], j, t, inv)
        k, w = tw
        v0, s0 = _ocv_row(rows[k], j, t, inv)
        v1, s1 = _ocv_row(rows[k + 1], j, t, inv)
        return v0 + (v1 - v0) * w, s0 + (s1 - s0) * w

    def ocv(self, soc: float, tw) -> tuple[float, float]:
        """OCV and dOCV/dsoc at (soc, T)."""
        return self._on_ocv_grid(self.ocv_rows, soc, tw)

    def surface_soc(self, soc: float, u_prev: float, tw_ocv) -> tuple[float, float, float]:
        """The SOC the RC tables are read at (ecmgen.model.simulate step 3') and its
        derivatives by soc and by u_prev: (soc, 1, 0) for a model without the surface SOC,
        (0 or 1, 0, 0) where it is clamped."""
        if self.sv_rows is None:
            return soc, 1.0, 0.0
        # a step reads it three times at the same values (predict, dc_resistance,
        # measure): the same objects give the last result
        last = self._surface_last
        if last[0] is soc and last[1] is u_prev and last[2] is tw_ocv:
            return last[3]
        sv, dsv = self._on_ocv_grid(self.sv_rows, soc, tw_ocv)
        r = soc + sv * u_prev
        if r < 0.0 or r > 1.0:
            out = min(max(r, 0.0), 1.0), 0.0, 0.0
        else:
            out = r, 1.0 + dsv * u_prev, sv
        self._surface_last = (soc, u_prev, tw_ocv, out)
        return out

    def direction(self, charging: bool, i: float) -> bool:
        if i > self.deadband:
            return True
        if i < -self.deadband:
            return False
        return charging

    def current_factors(self, i: float, i0):
        """Resistance factors of the current: (g_r0, g_fast) and d(i g)/di of each
        (the current-dependent-resistance effects on r0 and r_fast, the Butler-Volmer
        branch on r_fast only)."""
        g0, dg0 = 1.0, 1.0          # factor and d(i * factor)/di
        for scale, ci0 in self.cdr:
            g, d = _asinh_factor(i, ci0)
            # d(i g0 g)/di = g0 d + g dg0 - g0 g  (product rule on i g0 and i g over i)
            dg0 = scale * (g0 * d + g * dg0 - g0 * g)
            g0 = g0 * scale * g
        gf, dgf = g0, dg0
        if i0 is not None:
            g, d = _asinh_factor(i, i0)
            dgf = gf * d + g * dgf - gf * g
            gf = gf * g
        return g0, dg0, gf, dgf

    # -- the step ---------------------------------------------------------------------
    def predict(self, x: list[float], charging: bool, dt: float, i_seen: float, tw,
                tfac: float = 1.0, jacobian: bool = True, tw_ocv=None):
        """One process step from state ``x`` (after sample k-1) to sample k.

        Returns (x_k, charging_k, F, aux): F as a dense n x n list of rows (None when
        ``jacobian`` is False); aux carries what :meth:`measure` reuses (the current, the
        SOC-table lookup, the direction). ``tw_ocv``: the OCV's temperature row and weight
        (the surface SOC's table is on the OCV's grid)."""
        n = self.n
        i_b = self.i_b
        i = i_seen - x[i_b] if i_b >= 0 else i_seen
        charging = self.direction(charging, i)
        ds_di = dt * self.soc_per_as
        soc = x[0] + i * ds_di
        u_prev = x[self.i_ud] if self.sv_rows is not None else 0.0
        soc_t, dt_ds, dt_du = self.surface_soc(soc, u_prev, tw_ocv)
        vals, slopes, (r_diff, tau_diff, i0) = self.params(charging, soc_t, tw)
        if not self.slopes:
            slopes = [0.0] * 5
        _r0, r_fast, tau_fast, r_slow, tau_slow = vals
        g0, dg0, gf, dgf = self.current_factors(i, i0)
        xn = list(x)
        xn[0] = soc
        F = None
        if jacobian:
            F = [[0.0] * n for _ in range(n)]
            F[0][0] = 1.0
            if i_b >= 0:
                F[0][i_b] = -ds_di
                F[i_b][i_b] = 1.0
        # (state index, r, dr/dsoc, d(r i g)/di / r, g, tau, dtau/dsoc)
        branches = [(1, r_fast * tfac, slopes[1] * tfac, gf, dgf, tau_fast, slopes[2]),
                    (2, r_slow * tfac, slopes[3] * tfac, 1.0, 1.0, tau_slow, slopes[4])]
        if self.i_ud >= 0:
            branches.append((self.i_ud, r_diff, 0.0, 1.0, 1.0, tau_diff, 0.0))
        if self.i_ux >= 0:
            branches.append((self.i_ux, self.extra.r_ohm, 0.0, 1.0, 1.0, self.extra.tau_s, 0.0))
        rc = []
        for s, r, dr, g, dg, tau, dtau in branches:
            a = math.exp(-dt / tau)
            one_a = 1.0 - a
            rc.append((s, a, r * g))
            u = x[s]
            xn[s] = a * u + r * g * one_a * i
            if jacobian:
                da = a * dt / (tau * tau) * dtau          # da/dsoc of the tables
                dpar = da * u + (dr * one_a - r * da) * g * i   # by the tables' SOC
                dsoc = dpar * dt_ds                             # by soc_k
                F[s][s] = a
                F[s][0] = dsoc
                if dt_du and s != self.i_ud:                    # the surface SOC's u_diff
                    F[s][self.i_ud] = dpar * dt_du
                if i_b >= 0:
                    F[s][i_b] = -r * one_a * dg - dsoc * ds_di
        if self.i_h >= 0:
            e = self.hyst
            sign = 1.0 if charging else -1.0
            c = dt / (3600.0 * e.decay_ah)
            a = math.exp(-abs(i) * c)
            h = x[self.i_h]
            xn[self.i_h] = a * h + (1.0 - a) * sign
            if jacobian:
                F[self.i_h][self.i_h] = a
                if i_b >= 0:
                    # d a / d i = -sign(i) c a;  d/db = -d/di
                    si = 1.0 if i > 0 else (-1.0 if i < 0 else 0.0)
                    F[self.i_h][i_b] = (h - sign) * si * c * a
        aux = StepAux(i, charging, g0, dg0, tuple(rc), u_prev)
        return xn, charging, F, aux

    def r0(self, charging: bool, soc: float, tw) -> tuple[float, float]:
        """r0 and dr0/dsoc of the direction's table at (soc, T)."""
        last = self._r0_last        # dc_resistance and measure: the same values
        if last[0] is charging and last[1] is soc and last[2] is tw:
            return last[3]
        tab = self.tables[charging]
        tw_d = tw[0] if charging else tw[1]
        j, t, inv = _segment(tab.soc, soc)
        if tw_d is None:
            out = _row_value(tab.rows[0], j, t, inv, 0)
        else:
            k, w = tw_d
            v0, s0 = _row_value(tab.rows[k], j, t, inv, 0)
            v1, s1 = _row_value(tab.rows[k + 1], j, t, inv, 0)
            out = v0 + (v1 - v0) * w, s0 + (s1 - s0) * w
        self._r0_last = (charging, soc, tw, out)
        return out

    def dc_resistance(self, x: list[float], aux, tw, tw_ocv, tfac: float = 1.0) -> float:
        """r0 g0 + sum of r_j g_j at state ``x`` (sample k, ``aux`` from :meth:`predict`):
        the voltage per ampere of a steady error in the current the filter sees."""
        soc_t, _, _ = self.surface_soc(x[0], aux.u_prev, tw_ocv)
        r = self.r0(aux.charging, soc_t, tw)[0] * tfac * aux.g0
        for _s, _a, rg in aux.rc:
            r += rg
        return r

    def measure(self, x: list[float], aux, tw, tw_ocv, tfac: float = 1.0,
                jacobian: bool = True, ocv_slope: float | None = None):
        """Terminal voltage at state ``x`` (sample k, ``aux`` from :meth:`predict`), dv/dx
        (None without ``jacobian``) and the OCV, which the filter uses for the size of
        the model's error. ``ocv_slope``: the OCV's slope dv/dx takes (the EKF's secant,
        :func:`ecmgen.estimate.ekf.spread_slope`); None: the tangent at ``x``."""
        i, charging, g0, dg0 = aux.i, aux.charging, aux.g0, aux.dg0
        soc = x[0]
        soc_t, dt_ds, _ = self.surface_soc(soc, aux.u_prev, tw_ocv)
        r0, dr0 = self.r0(charging, soc_t, tw)
        r0, dr0 = r0 * tfac, (dr0 * tfac * dt_ds if self.slopes else 0.0)
        ocv, docv = self.ocv(soc, tw_ocv)
        v = ocv + r0 * g0 * i + x[1] + x[2]
        for s in (self.i_ud, self.i_ux):
            if s >= 0:
                v += x[s]
        if self.i_h >= 0:
            e = self.hyst
            sign = 1.0 if charging else -1.0
            v += e.m_v * (x[self.i_h] - e.ocv_table_state) + e.m0_v * (sign - e.ocv_table_state)
        H = None
        if jacobian:
            H = [0.0] * self.n
            H[0] = (docv if ocv_slope is None else ocv_slope) + dr0 * g0 * i
            H[1] = H[2] = 1.0
            for s in (self.i_ud, self.i_ux):
                if s >= 0:
                    H[s] = 1.0
            if self.i_h >= 0:
                H[self.i_h] = self.hyst.m_v
            if self.i_b >= 0:
                H[self.i_b] = -r0 * dg0
        return v, H, ocv


def _ocv_row(row, j, t, inv):
    y0 = row[j]
    if len(row) == 1:
        return y0, 0.0
    d = row[j + 1] - y0
    return y0 + d * t, d * inv


def _asinh_factor(i: float, i0: float) -> tuple[float, float]:
    """g = asinh(x)/x, x = max(|i|/i0, 1e-12), and d(i g)/di = 1/sqrt(1 + x^2)."""
    x = abs(i) / i0
    if x < X_MIN:
        x = X_MIN
    return math.asinh(x) / x, 1.0 / math.sqrt(1.0 + x * x)
