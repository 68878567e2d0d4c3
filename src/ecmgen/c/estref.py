"""Float32 reference of the generated SOC estimator (``c_runtime/ecmrt_est_f32.h`` around
the model's step of ``ecmrt_f32.h``), operation for operation: bit-identical to the C at
every step (tests/test_codegen_estimator.py, through cffi and under QEMU).

The model's step is mirrored here per sample (the filter changes the state between
steps, so :func:`ecmgen.c.cref.simulate_f32`, which runs a whole record at once, cannot
drive it); what does not depend on the state (the sanitised inputs, the direction, the
temperature row and weight, the per-temperature branch values, the Butler-Volmer factor,
the effects' factors and the hysteresis and extra RC coefficients) is computed for the
whole record at once, as cref does; with the offset state the current depends on the
state, and what depends on the current is computed per sample (``_current_terms``). With
the surface SOC the step's RC tables and the accessor's are read at the surface SOC from the
u_diff before the step (``_Tables.surface``), F gets its u_diff column. numpy float32 scalars round once
per operation, as the C built with -ffp-contract=off.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from . import cref
from .codegen import branch_rows, ocv_rows, surface_rows, table_rows
from ..estimate.ekf import HYSTERESIS_START_VAR
from .estc import EstSpec
from .qformat import DT_MAX_S, SOC_LIM
from .spec import CSpec

F32 = np.float32
ZERO, ONE, HALF = F32(0.0), F32(1.0), F32(0.5)
ITER, ITER_SOC, ITER_TOL = 5, F32("1.0e-3"), F32("1.0e-5")
V_MAX = F32(1000.0)          # ECMRT_EST_V_MAX: a reading beyond is no measurement


def _offsets(spec: CSpec) -> dict:
    """ECMRT_P_*: where each parameter's pair sits in a table row."""
    if spec.tau_t:
        return {"r0": 0, "rf": 2, "rs": 4, "ocv": 6}
    return {"r0": 0, "rf": 2, "tf": 4, "rs": 6, "ts": 8, "ocv": 10}


@dataclass(frozen=True)
class EstRef:
    """Per-sample outputs: the predicted voltage, the state after the update (n x N) and
    the covariance (n x N x N), float32."""

    v_pred: np.ndarray
    x: np.ndarray
    p: np.ndarray
    f: np.ndarray | None = None     # with jacobians=True: dstep/dx (n x N x N) and, before
    h: np.ndarray | None = None     # any iteration, dv/dx (n x N) of each sample

    @property
    def soc(self) -> np.ndarray:
        return self.x[:, 0]


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


def _locate_vec(g, v: np.ndarray):
    """ecmrt_f32_locate over an array (the temperature)."""
    x = g.x
    k = np.clip(np.searchsorted(x, v, side="right") - 1, 0, x.size - 2)
    with np.errstate(all="ignore"):
        w = ((v - x[k]) * g.inv_dx[k]).astype(F32)
    w = np.where(v >= x[-1], ONE, w)
    k = np.where(v >= x[-1], x.size - 2, k)
    below = ~(v >= x[0])
    return np.where(below, 0, k), np.where(below, ZERO, w).astype(F32)


class _Tables:
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


def _inputs(spec: CSpec, current_a, temperature_c, dt_s, chg=None):
    """The record's sanitised float32 inputs and what depends on them alone; ``chg``: the
    direction of every sample instead of the current's (the offset state's per-direction
    values)."""
    i = np.asarray(current_a, dtype=np.float64).astype(F32)
    imax = F32(spec.i_lim_a)
    i = np.where(np.isnan(i), ZERO, np.clip(i, -imax, imax)).astype(F32)
    dt = np.asarray(dt_s, dtype=np.float64).astype(F32)
    dt = np.where(dt > 0, np.minimum(dt, F32(DT_MAX_S)), ZERO).astype(F32)
    n = i.size
    temp = np.broadcast_to(np.asarray(temperature_c if temperature_c is not None else 0.0,
                                      dtype=np.float64), (n,)).astype(F32)
    chg = cref._direction(i, spec.deadband) if chg is None else chg
    if spec.temp:
        kt, wt = _locate_vec(spec.temp_grid, temp)
    else:
        kt, wt = np.zeros(n, dtype=np.int64), None
    branch = {}
    names = [k for k in ("r_diff", "k_diff", "i0") if getattr(spec.dirs[0], k) is not None]
    if names:
        for j, name in enumerate(names):
            per_dir = []
            for d in spec.dirs:
                b = branch_rows(spec, d)             # [row][pairs]
                y, dy = b[kt, 2 * j], b[kt, 2 * j + 1]
                per_dir.append(y + dy * wt if wt is not None else y)
            branch[name] = np.where(chg == 1, per_dir[1], per_dir[0]).astype(F32)
    ai = np.abs(i).astype(F32)
    out: dict = {"i": i, "dt": dt, "chg": chg, "kt": kt, "wt": wt,
                 "dsoc": ((i * dt) * F32(spec.k_soc)).astype(F32)}
    fx = spec.fx
    with np.errstate(all="ignore"):      # the effects' factors and coefficients, as the step's
        if fx.get("cdr"):
            out["g_cdr"] = cref.cdr_factor_f32(ai, fx["g_scale"], fx["g_inv_i0"])
        if fx.get("arr"):
            out["f_arr"] = cref.arrhenius_f32(temp, fx["a_k"], fx["a_inv_ref"])
        if fx.get("hyst"):
            out["c_h"] = cref.one_minus_exp_neg_f32((ai * dt) * F32(fx["h_k"]))
        if fx.get("xrc"):
            out["c_x"] = cref.one_minus_exp_neg_f32(dt / F32(fx["x_k"]))
    if "i0" in branch:
        out["i0"] = branch["i0"]
        with np.errstate(all="ignore"):
            a, x = cref.asinh_f32(ai / branch["i0"])
            out["g_bv"] = (a / x).astype(F32)
    tau_t = spec.tau_t
    if tau_t:                    # ecmrt_f32_coefs: 1/tau at the temperature, in the state
        from .codegen import tau_rows

        per = []
        for d in (spec.dirs[:1] * 2 if spec.tau_same else spec.dirs):
            tk = tau_rows(spec, d)
            tv = [tk[kt, j] + tk[kt, j + 1] * wt if wt is not None else tk[kt, j]
                  for j in (0, 2)]
            per.append([(ONE / v).astype(F32) for v in tv])
        out["kc_f"], out["kc_s"] = (np.where(chg == 1, per[1][j], per[0][j]).astype(F32)
                                    for j in (0, 1))
    if "r_diff" in branch:
        out["r_diff"] = branch["r_diff"]
        if tau_t:
            kd = branch["k_diff"]
            if spec.tau_same:    # kc[0]: the discharge direction's
                b = branch_rows(spec, spec.dirs[0])
                j = names.index("k_diff")
                kd = (b[kt, 2 * j] + b[kt, 2 * j + 1] * wt if wt is not None
                      else b[kt, 2 * j]).astype(F32)
            out["kc_d"] = (ONE / kd).astype(F32)
            out["c_diff"] = cref.one_minus_exp_neg_f32(dt * out["kc_d"])
        else:
            out["c_diff"] = cref.one_minus_exp_neg_f32(dt / branch["k_diff"])
    return out


def simulate_estimator_f32(spec: CSpec, est: EstSpec, current_a, dt_s, voltage_v,
                           soc0: float, temperature_c=None, jacobians: bool = False
                           ) -> EstRef:
    """The C estimator's float32 reference: ``<prefix>_est_init(soc0)``, then
    ``<prefix>_est_step(i[k], T[k], dt[k], v[k])`` for every sample (``current_a`` the
    current the filter sees, ``dt_s`` per sample, e.g. cref.dt_from_time). Overflow to inf
    and the like are IEEE results the C gets too, not errors. ``jacobians``: also the
    filter's F and H of every sample (tests/test_codegen_estimator_effects.py holds them
    against finite differences of the C step)."""
    if spec.fixed or not spec.variable_dt:
        raise ValueError("the estimator runs on the variable-dt float step")
    n = np.asarray(current_a).size
    dt_s = np.broadcast_to(np.asarray(dt_s, dtype=np.float64), (n,)).astype(F32)
    if n:
        dt_s[0] = ZERO           # est_step: init is the state at the first sample
    with np.errstate(all="ignore"):
        return _simulate(spec, est, current_a, dt_s, voltage_v, soc0, temperature_c,
                         jacobians)


def _simulate(spec, est, current_a, dt_s, voltage_v, soc0, temperature_c, jacobians
              ) -> EstRef:
    tab = _Tables(spec)
    off = est.offset
    if off:        # the current is the reading less the offset state: per sample, below
        n0 = np.asarray(current_a).size
        per = [_inputs(spec, np.zeros(n0), temperature_c, dt_s, np.full(n0, d, np.uint8))
               for d in (0, 1)]
        inp = per[0]
        seen = np.asarray(current_a, dtype=np.float64).astype(F32)
    else:
        inp = _inputs(spec, current_a, temperature_c, dt_s)
    vm_all = np.asarray(voltage_v, dtype=np.float64).astype(F32)
    n, N = inp["i"].size, est.n
    nz = {k: F32(v) for k, v in est.noise.items()}
    spread_k = nz.get("ocv_k", ZERO)             # ECMRT_EST_SPREAD 0: the tangent
    diff, bv = spec.diff, spec.has_bv
    surf = spec.surface is not None              # ECMRT_SURFACE (with the diffusion pair)
    # est_init: the model's init (SOC saturated to [-2, 2], NaN 0), then [0, 1]
    s0 = F32(soc0)
    s0 = ZERO if np.isnan(s0) else min(max(s0, F32(-SOC_LIM)), F32(SOC_LIM))
    soc = _clamp(F32(s0))
    u = [ZERO] * N                   # u[0] unused
    P = [[ZERO] * N for _ in range(N)]
    fx = spec.fx
    cdr, arr, hyst, xrc = (bool(fx.get(k)) for k in ("cdr", "arr", "hyst", "xrc"))
    ix = 3 + int(diff)                       # ECMRT_EST_IX, ECMRT_EST_IH
    ih = ix + int(xrc)
    P[0][0] = nz["p0_soc"]
    for r in range(1, N):
        P[r][r] = nz["p0_u"]
    if hyst:
        anywhere = nz["start_a"] != ZERO       # a start anywhere: the direction unknown
        P[ih][ih] = F32(HYSTERESIS_START_VAR) if anywhere else nz["p0_h"]
        u[ih] = ZERO if anywhere else F32(fx["h_init"])
        h_k, h_m, h_m0, h_ref = (F32(fx[k]) for k in ("h_k", "h_m", "h_m0", "h_ref"))
    if xrc:
        x_r = F32(fx["x_r"])
    ib = N - 1                               # ECMRT_EST_IB (with the offset state)
    if off:
        P[ib][ib] = nz["p0_b"]
        d_prev = 0
        imax, dband = F32(spec.i_lim_a), F32(spec.deadband)
    k_soc = F32(spec.k_soc)
    first = True
    held = ZERO                      # est_t's eta_v
    flat = not est.settings.resistance_slopes
    v_out = np.empty(n, dtype=F32)
    x_out = np.empty((n, N), dtype=F32)
    p_out = np.empty((n, N, N), dtype=F32)
    f_out = np.zeros((n, N, N), dtype=F32) if jacobians else None
    h_out = np.zeros((n, N), dtype=F32) if jacobians else None
    slo, shi = F32(-SOC_LIM), F32(SOC_LIM)
    i_a, dt_a, chg, kt_a, wt_a = inp["i"], inp["dt"], inp["chg"], inp["kt"], inp["wt"]
    fields_all = ("r0", "rf", "tf", "rs", "ts")
    tau_t = spec.tau_t
    for t in range(n):
        dt, kt = dt_a[t], int(kt_a[t])
        wt = None if wt_a is None else wt_a[t]
        if off:
            i = _sanitise(seen[t] - u[ib], imax)
            d = 1 if i > dband else (0 if i < -dband else d_prev)
            d_prev = d
            ai = -i if i < ZERO else i
            src, cur = per[d], _current_terms(spec, ai, dt, per[d], t)
            dsoc = (i * dt) * k_soc
        else:
            i, d = i_a[t], int(chg[t])
            ai = -i if i < ZERO else i
            src, cur = inp, {k: inp[k][t] for k in ("g_cdr", "g_bv", "c_h") if k in inp}
            dsoc = inp["dsoc"][t]
        # ---- the model's step (ecmrt_f32_step) ----
        u_prev = list(u)
        y = dsoc - ZERO                                    # soc_c is 0 after every est step
        sn = soc + y
        if sn < slo:
            sn = slo
        elif sn > shi:
            sn = shi
        soc = sn
        socr, sds, sdu = tab.surface(soc, u_prev[3], kt, wt) if surf else (soc, None, None)
        # the step's lookups (pv) and the accessor's (ecmrt_est_f32_params, pa) read the
        # same tables at the same SOC: one lookup gives both (the values are the same
        # operations; the accessor adds the slopes)
        pa = pv = tab.values(d, soc, kt, wt, fields_all, True, socr)
        r0, rf, rs, ocv = pv["r0"][0], pv["rf"][0], pv["rs"][0], pv["ocv"][0]
        gc = cur["g_cdr"] if cdr else ONE
        fa = inp["f_arr"][t] if arr else ONE
        if cdr:
            r0, rf = r0 * gc, rf * gc
        if arr:
            r0, rf, rs = r0 * fa, rf * fa, rs * fa
        if bv:
            rf = rf * cur["g_bv"]
        if flat:                     # ECMRT_EST_SLOPES 0: the RC tables flat in SOC
            pa = {k: (v[0], ZERO) if k != "ocv" else v for k, v in pa.items()}
        if tau_t:            # the state's coefficients kc = 1/tau(T), for step and filter
            cf, cs = omexp(dt * src["kc_f"][t]), omexp(dt * src["kc_s"][t])
            ja = (cf, cs)
        else:
            cf, cs = omexp(dt / pv["tf"][0]), omexp(dt / pv["ts"][0])
            ja = (omexp(dt / pa["tf"][0]), omexp(dt / pa["ts"][0]))
        uf = u[1] + cf * (rf * i - u[1])
        us = u[2] + cs * (rs * i - u[2])
        vp = ((ocv + r0 * i) + uf) + us
        u[1], u[2] = uf, us
        if diff:
            rd = src["r_diff"][t]
            ud = u[3] + src["c_diff"][t] * (rd * i - u[3])
            vp = vp + ud
            u[3] = ud
        if hyst:
            sg = ONE if d == 1 else F32(-1.0)
            ch = cur["c_h"]
            hh = u[ih] + ch * (sg - u[ih])
            u[ih] = hh
            vh = h_m * (hh - h_ref) + h_m0 * (sg - h_ref)
        if xrc:
            cx = inp["c_x"][t]
            ux = u[ix] + cx * (x_r * i - u[ix])
            u[ix] = ux
        if hyst and xrc:
            vp = vp + (vh + ux)
        elif hyst:
            vp = vp + vh
        elif xrc:
            vp = vp + ux
        # ---- the filter (ecmrt_est_f32_update) ----
        x0 = [soc] + u[1:]
        gf = cur["g_bv"] if bv else ONE
        a, f, q = [ONE] + [ZERO] * (N - 1), [ZERO] * N, [ZERO] * N
        (r0a, dr0a), (rf_, drf), (rs_, drs) = pa["r0"], pa["rf"], pa["rs"]
        if off:                               # before the current's factors
            rb0, rbf = (r0a * fa, rf_ * fa) if arr else (r0a, rf_)
            dg0 = (F32(fx["g_scale"]) / _s(cref.sqrt_f32(cur["xc"] * cur["xc"] + ONE))
                   if cdr else ONE)
            dgf = dg0
            if bv:
                xb = cur["xb"]
                dbv = ONE / _s(cref.sqrt_f32(xb * xb + ONE))
                dgf = (gc * dbv + gf * dg0) - gc * gf if cdr else dbv
            ds_di = dt * k_soc
            o = [ZERO] * N
            o[0] = -ds_di
        if cdr:                               # ecmrt_est_f32_fx
            r0a, dr0a, rf_, drf = r0a * gc, dr0a * gc, rf_ * gc, drf * gc
        if arr:
            r0a, dr0a, rf_, drf = r0a * fa, dr0a * fa, rf_ * fa, drf * fa
            rs_, drs = rs_ * fa, drs * fa
        one_a = ja[0]
        a[1] = ONE - one_a
        if tau_t:
            da = ZERO
        else:
            (tf_, dtf) = pa["tf"]
            da = ((a[1] * dt) / (tf_ * tf_)) * dtf
        f[1] = da * u_prev[1] + ((drf * one_a - rf_ * da) * gf) * i
        g = [ZERO] * N                        # F's u_diff column through the surface SOC
        if surf:
            g[1], f[1] = f[1] * sdu, f[1] * sds
        if off:
            o[1] = -((rbf * one_a) * dgf) - f[1] * ds_di
        ps = nz["pol_s2"] / (nz["pol_s2"] + P[0][0]) if nz["pol_s2"] > ZERO else ONE
        rg = rf_ * gf
        e = (nz["pol"] * rg) * i
        q[1] = ((e * e) * (ONE - a[1] * a[1])) * ps
        one_a = ja[1]
        a[2] = ONE - one_a
        if not tau_t:
            (ts_, dts) = pa["ts"]
            da = ((a[2] * dt) / (ts_ * ts_)) * dts
        f[2] = da * u_prev[2] + (drs * one_a - rs_ * da) * i
        if surf:
            g[2], f[2] = f[2] * sdu, f[2] * sds
        if off:
            o[2] = -(rs_ * one_a) - f[2] * ds_di
        e = (nz["pol"] * rs_) * i
        q[2] = ((e * e) * (ONE - a[2] * a[2])) * ps
        if diff:
            ad = ONE - src["c_diff"][t]
            a[3] = ad
            if off:
                o[3] = -(src["r_diff"][t] * src["c_diff"][t])
            e = (nz["pol"] * src["r_diff"][t]) * i
            q[3] = ((e * e) * (ONE - ad * ad)) * ps
        if xrc:
            a[ix] = ONE - cx
            if off:
                o[ix] = -(x_r * cx)
            e = (nz["pol"] * x_r) * i
            q[ix] = ((e * e) * (ONE - a[ix] * a[ix])) * ps
        if not off:                  # the resistance the current offset sees
            rdc = r0a + rg
            rdc = rdc + rs_
            if diff:
                rdc = rdc + src["r_diff"][t]
            if xrc:
                rdc = rdc + x_r
        if hyst:
            a[ih] = ONE - ch
            q[ih] = nz["p0_h"] * (ch * (F32(2.0) - ch))
        if off:
            if hyst:
                si = ONE if i > ZERO else (F32(-1.0) if i < ZERO else ZERO)
                o[ih] = (((u_prev[ih] - sg) * si) * (dt * h_k)) * a[ih]
            o[ib], a[ib], f[ib] = ZERO, ONE, ZERO
        if dt > ZERO:
            kk = dt * F32(spec.k_soc)
            if off:
                b = nz["gain"] * ai
                q[ib] = (nz["p0_b"] * dt) / nz["horizon_s"]
            else:
                b = nz["gain"] * ai + nz["offset_a"]
            e = b * F32(spec.k_soc)
            r = nz["noise_a"] * kk
            q[0] = (e * e) * (dt * nz["horizon_s"]) + r * r
        else:
            q = [ZERO] * N
        if first:                    # the RC voltages' start variance
            for s_, r_ in ((1, rg), (2, rs_), (3, src["r_diff"][t] if diff else None),
                           (ix, x_r if xrc else None)):
                if r_ is not None:
                    e = r_ * nz["start_a"]
                    q[s_] = q[s_] + e * e
        # (the loops over zipped rows: the same float32 operations in the same order as
        # indexed loops, at a third of the interpreter's cost)
        P0 = P[0]
        fp = [[ar * prc + fr * p0c for prc, p0c in zip(pr, P0)]
              for ar, fr, pr in zip(a, f, P)]
        if off:
            pb = P[ib]
            fp = [[v + orr * pbc for v, pbc in zip(row, pb)] for row, orr in zip(fp, o)]
        if surf:
            p3 = P[3]
            fp = [[v + gr * p3c for v, p3c in zip(row, p3)] for row, gr in zip(fp, g)]
        for r in range(N):
            fr_, fr0 = fp[r], fp[r][0]
            for c in range(r, N):
                val = a[c] * fr_[c] + f[c] * fr0
                if off:
                    val = val + o[c] * fr_[ib]
                if surf:
                    val = val + g[c] * fr_[3]
                if r == c:
                    val = val + q[r]
                P[r][c] = P[c][r] = val
        up = u_prev[3] if surf else None
        dv = _ocv_slope(tab, d, soc, P[0][0], spread_k, kt, wt, up, pa["ocv"][1])
        h = [dv + (dr0a * sds if surf else dr0a) * i] + [ONE] * (N - 1)
        if hyst:
            h[ih] = h_m
        if off:
            h[ib] = -(rb0 * dg0)
        if jacobians:
            f_out[t][np.diag_indices(N)] = a
            f_out[t, 1:, 0] = f[1:]
            if off:
                f_out[t, :ib, ib] = o[:ib]
            if surf:
                f_out[t, 1:3, 3] = g[1:3]
            h_out[t] = h
        e = _abs(vp - pa["ocv"][0])
        if nz["mem_k"] > ZERO:
            r = held - held * omexp(dt * nz["mem_k"])
            if r > e:
                e = r
            held = e
        e = nz["model_error"] * e
        R = nz["vn2"] + e * e
        if not off:
            e = nz["offset_a"] * rdc
            R = R + e * e
        if not (first and nz["start_a"] == ZERO) and dt < nz["corr_s"]:
            R = R * (nz["corr_s"] / dt) if dt > ZERO else ZERO
        first = False
        vm = vm_all[t]
        if not (vm >= -V_MAX and vm <= V_MAX):
            R = ZERO
        if R > ZERO:
            g = _gain(P, h, R, x0, vm - vp)
            ok = g is not None
            if ok:
                c, k, xu = g
            for _ in range(ITER):
                if not ok:
                    break
                xu[0] = _clamp(xu[0])
                if hyst:
                    xu[ih] = _clamp_h(xu[ih])
                if _abs(xu[0] - x0[0]) < ITER_SOC:
                    break
                socr, sds, _ = (tab.surface(xu[0], u_prev[3], kt, wt) if surf
                                else (xu[0], None, None))
                pi = tab.values(d, xu[0], kt, wt, ("r0",), True, socr)
                if flat:
                    pi["r0"] = (pi["r0"][0], ZERO)
                (r0i, dr0i) = pi["r0"]
                if off:
                    h[ib] = -((r0i * fa if arr else r0i) * dg0)
                if cdr:
                    r0i, dr0i = r0i * gc, dr0i * gc
                if arr:
                    r0i, dr0i = r0i * fa, dr0i * fa
                vi = ((pi["ocv"][0] + r0i * i) + xu[1]) + xu[2]
                if diff:
                    vi = vi + xu[3]
                if hyst:
                    vx = h_m * (xu[ih] - h_ref) + h_m0 * (sg - h_ref)
                    if xrc:
                        vx = vx + xu[ix]
                    vi = vi + vx
                elif xrc:
                    vi = vi + xu[ix]
                dv = _ocv_slope(tab, d, xu[0], P[0][0], spread_k, kt, wt, up, pi["ocv"][1])
                h[0] = dv + (dr0i * sds if surf else dr0i) * i
                e = vm - vi
                for j in range(N):
                    e = e - h[j] * (x0[j] - xu[j])
                g = _gain(P, h, R, x0, e)
                ok = g is not None
                if ok:
                    c, k, xn = g
                    dd = _abs(xn[0] - xu[0])
                    xu = xn
                    if dd < ITER_TOL:
                        break
            if ok:
                mm = [[prj - kr * cj for prj, cj in zip(pr, c)] for pr, kr in zip(P, k)]
                dv = [_dot(mr, h) for mr in mm]
                pn = [[(mrj - dvr * kj) + R * (kr * kj) for mrj, kj in zip(mr, k)]
                      for mr, dvr, kr in zip(mm, dv, k)]
                ok = _finite(xu) and all(_finite(row) for row in pn)
            if ok:
                for r in range(N):
                    for j in range(r, N):
                        P[r][j] = P[j][r] = HALF * (pn[r][j] + pn[j][r])
                u[1:] = xu[1:]
                if hyst:
                    u[ih] = _clamp_h(xu[ih])
                x0[0] = xu[0]
        soc = _clamp(x0[0])
        v_out[t] = vp
        x_out[t, 0] = soc
        x_out[t, 1:] = u[1:]
        p_out[t] = P
    return EstRef(v_out, x_out, p_out, f_out, h_out)


SPREAD_MIN, P_SOC_MIN = F32(1e-6), F32(1e-12)   # ECMRT_EST_SPREAD_MIN, ECMRT_EST_P_SOC_MIN


def _ocv_slope(tab, d, soc, p_soc, k, kt, wt, up, docv):
    """ecmrt_est_f32_ocv_slope: the tangent ``docv``, or (k > 0) the secant of the
    accessor's OCV over soc +- k sqrt(p_soc), clamped to [0, 1] (``up``: the u_diff the
    surface SOC reads, None without it)."""
    if not (k > ZERO and p_soc > P_SOC_MIN):
        return docv
    dd = k * _s(cref.sqrt_f32(p_soc))
    lo, hi = soc - dd, soc + dd
    lo = ZERO if lo < ZERO else lo
    hi = ONE if hi > ONE else hi
    if not hi - lo > SPREAD_MIN:
        return docv

    def ocv(x):
        socr = None if up is None else tab.surface(x, up, kt, wt)[0]
        return tab.values(d, x, kt, wt, ("r0",), False, socr)["ocv"][0]

    v_lo = ocv(lo)
    return (ocv(hi) - v_lo) / (hi - lo)


def _gain(P, h, R, x0, e):
    """ecmrt_est_f32_gain: (c, K, x) or None when h P h^T + R is not a positive number."""
    c = [_dot(pr, h) for pr in P]
    sm = _dot(h, c) + R
    if not (sm > ZERO and math.isfinite(sm)):
        return None
    k = [cr / sm for cr in c]
    return c, k, [xr + kr * e for xr, kr in zip(x0, k)]


_SERIES_X, _XMAX, _HALF_LN2 = cref.F_SERIES_X, cref.F_XMAX, cref.F_HALF_LN2
_INVLN2, _LN2_HI, _LN2_LO, _TAYLOR = cref.F_INVLN2, cref.F_LN2_HI, cref.F_LN2_LO, cref.F_TAYLOR


_SMALL = cref.F_SMALL                # the minimax polynomial below 1/4 (b4, b3, b2, b1)


def omexp(x):
    """cref.one_minus_exp_neg_f32 (ecmrt_f32_one_minus_exp_neg) for one float32 scalar, 30x
    faster than the array version (tests/test_codegen_estimator.py checks they agree)."""
    if not x > ZERO:
        return ZERO
    if x < _SERIES_X:
        b4, b3, b2, b1 = _SMALL
        q = x * b4 - b3
        q = x * q + b2
        q = x * q - b1
        q = x * q + ONE
        return x * q
    if not x < _XMAX:
        return ONE
    n = 0 if x < _HALF_LN2 else int(x * _INVLN2 + HALF)
    if n == 0:
        r = x
    else:
        fn = F32(n)
        r = (x - fn * _LN2_HI) - fn * _LN2_LO
    t = -r
    q = _TAYLOR[0]
    for c in _TAYLOR[1:]:
        q = c + t * q
    q = t * q
    sc = F32(2.0 ** -n)
    return (ONE - sc) - sc * q


def _dot(y, h):
    """ecmrt_est_f32_dot: y . h summed from the first entry on."""
    pairs = zip(y, h)
    a, b = next(pairs)
    sm = a * b
    for a, b in pairs:
        sm = sm + a * b
    return sm


def _finite(values) -> bool:
    """Every float32 of ``values`` finite (math.isfinite: np.all(np.isfinite(...)) costs
    ten times more per sample)."""
    return all(map(math.isfinite, values))


def _clamp(soc):
    if not soc >= ZERO:
        return ZERO
    return ONE if soc > ONE else soc


def _sanitise(i, imax):
    """ecmrt_est_f32_prior's current: NaN 0, saturated to +-imax."""
    if not i >= -imax:
        return -imax if i == i else ZERO
    return imax if i > imax else i


def _s(a):
    """A float32 scalar of a one-value array."""
    return F32(np.asarray(a).reshape(-1)[0])


def _current_terms(spec, ai, dt, src, t) -> dict:
    """What depends on the current (with the offset state, per sample): the step's
    current_dependent_resistance and Butler-Volmer factors (and their x), the hysteresis
    coefficient, as ``_inputs`` computes them for a whole record."""
    fx, out = spec.fx, {}
    if fx.get("cdr"):
        a, x = cref.asinh_f32(ai * F32(fx["g_inv_i0"]))
        out["xc"] = _s(x)
        out["g_cdr"] = (F32(fx["g_scale"]) * _s(a)) / out["xc"]
    if "i0" in src:
        a, x = cref.asinh_f32(ai / src["i0"][t])
        out["xb"] = _s(x)
        out["g_bv"] = _s(a) / out["xb"]
    if fx.get("hyst"):
        out["c_h"] = omexp((ai * dt) * F32(fx["h_k"]))
    return out


def _clamp_h(h):
    """ecmrt_est_f32_clamp_h: into [-1, 1] (NaN stays NaN)."""
    if h < F32(-1.0):
        return F32(-1.0)
    return ONE if h > ONE else h


def _abs(x):
    return -x if x < ZERO else x
