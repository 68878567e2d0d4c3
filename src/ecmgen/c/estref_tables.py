"""The estimator reference's table accessor (the generated ``<prefix>_est_params`` with the
units of ``c_runtime/ecmrt_est_f32_tables.h``) in float32 scalars: a direction's parameters and their SOC
slopes at one SOC (and temperature row and weight), the surface SOC the step reads them at,
and the grids' segment search; used by :mod:`ecmgen.c.estref`."""

from __future__ import annotations

from bisect import bisect_right

import numpy as np

from .codegen import ocv_rows, surface_rows, table_rows
from .spec import CSpec

F32 = np.float32
ZERO, ONE = F32(0.0), F32(1.0)


def _offsets(spec: CSpec) -> dict:
    """Where each parameter's pair sits in a table row (codegen._layout's "p")."""
    if spec.tau_t:
        return {"r0": 0, "rf": 2, "rs": 4, "ocv": 6}
    return {"r0": 0, "rf": 2, "tf": 4, "rs": 6, "ts": 8, "ocv": 10}


class _Grid:
    def __init__(self, g, uniform: bool = False):
        self.n = g.n
        self.uniform = uniform
        if uniform:
            self.x0, self.inv_h, self.um = F32(g.x0), F32(g.inv_h), F32(g.n - 1)
            return
        self.x = [F32(v) for v in g.x]
        self.xf = [float(v) for v in g.x]
        self.inv = [F32(v) for v in g.inv_dx]

    def locate(self, v):
        """ecmrt_f32_locate / ecmrt_f32_ulocate: (k, w)."""
        last = self.n - 2
        if self.uniform:
            u = (v - self.x0) * self.inv_h
            if not u >= ZERO:
                return 0, ZERO
            if not u < self.um:
                return last, ONE
            k = int(u)
            return k, u - F32(k)
        if not v >= self.x[0]:
            return 0, ZERO
        if v >= self.x[-1]:
            return last, ONE
        k = min(bisect_right(self.xf, float(v)) - 1, last)
        return k, (v - self.x[k]) * self.inv[k]

    def inv_at(self, k, v):
        """ecmrt_est_f32_inv / _uinv: 1/spacing of segment k, 0 outside the grid."""
        if self.uniform:
            u = (v - self.x0) * self.inv_h
            return self.inv_h if (u >= ZERO and u <= self.um) else ZERO
        return self.inv[k] if (v >= self.x[0] and v <= self.x[-1]) else ZERO


def locate_vec(g, v: np.ndarray):
    """ecmrt_f32_locate over an array (the temperature)."""
    x = g.x
    k = np.clip(np.searchsorted(x, v, side="right") - 1, 0, x.size - 2)
    with np.errstate(all="ignore"):
        w = ((v - x[k]) * g.inv_dx[k]).astype(F32)
    w = np.where(v >= x[-1], ONE, w)
    k = np.where(v >= x[-1], x.size - 2, k)
    below = ~(v >= x[0])
    return np.where(below, 0, k), np.where(below, ZERO, w).astype(F32)


class Tables:
    """The spec's tables as the C holds them, as nested lists of float32 scalars."""

    def __init__(self, spec: CSpec):
        self.spec = spec
        self.off = _offsets(spec)
        rc_u = spec.rc_uniform
        self.grids = [_Grid(d.grid, rc_u) for d in spec.dirs]
        self.rows = [[[list(map(F32, pt)) for pt in row] for row in table_rows(spec, d)]
                     for d in spec.dirs]
        self.shared = spec.ocv_shared
        if not self.shared:
            self.ocv_grid = _Grid(spec.ocv_grid, spec.ocv_uniform)
            self.ocv = [[list(map(F32, pt)) for pt in row] for row in ocv_rows(spec)]
        self.sv = (None if spec.surface is None else
                   [[list(map(F32, pt)) for pt in row] for row in surface_rows(spec)])

    @staticmethod
    def _vs(rows, kt, k, j, w, wt, inv, slope: bool):
        """(value, SOC slope or None) of the pair at offset j of segment k."""
        r1 = rows[kt][k]
        if wt is None:                           # one row: pairs along SOC
            return r1[j] + r1[j + 1] * w, (r1[j + 1] * inv if slope else None)
        r2 = rows[kt][k + 1]                     # ecmrt_f32_segment, then along SOC
        a = r1[j] + r1[j + 1] * wt
        dd = (r2[j] + r2[j + 1] * wt) - a
        return a + dd * w, (dd * inv if slope else None)

    def surface(self, soc, up, kt, wt):
        """The surface SOC from u_diff ``up`` (the step's ecmrt_f32_surface, the accessor's
        reading of it) and its derivatives by soc and by up (0 where clamped): (soc_s, ds,
        du); (soc, None, None) without the surface SOC."""
        if self.sv is None:
            return soc, None, None
        g = self.ocv_grid
        k, w = g.locate(soc)
        inv = g.inv_at(k, soc)
        sv, dsv = self._vs(self.sv, kt, k, 0, w, wt, inv, True)
        r = soc + sv * up
        if not r >= ZERO:
            return ZERO, ZERO, ZERO
        if r > ONE:
            return ONE, ZERO, ZERO
        return r, ONE + dsv * up, sv

    def values(self, d, soc, kt, wt, fields, slope: bool, soc_rc=None):
        """{field: (value, slope)} of direction d at soc (the step's lookups; with slope:
        the accessor ecmrt_est_f32_params); fields of ("r0", "rf", "tf", "rs", "ts") at
        ``soc_rc`` (the surface SOC; None: soc), and "ocv" always at soc."""
        g = self.grids[d]
        soc_rc = soc if soc_rc is None else soc_rc
        k, w = g.locate(soc_rc)
        inv = g.inv_at(k, soc_rc) if slope else None
        off = self.off
        out = {f: self._vs(self.rows[d], kt, k, off[f], w, wt, inv, slope)
               for f in fields if f in off}
        if self.shared:
            out["ocv"] = self._vs(self.rows[d], kt, k, off["ocv"], w, wt, inv, slope)
        else:
            k, w = self.ocv_grid.locate(soc)
            inv = self.ocv_grid.inv_at(k, soc) if slope else None
            out["ocv"] = self._vs(self.ocv, kt, k, 0, w, wt, inv, slope)
        return out
