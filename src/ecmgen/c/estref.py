"""Float32 reference of the generated SOC estimator (``<prefix>_est_f32.c``: the model side
of ``templates/est_model.c.j2`` and ``est.c.j2`` with the units of ``c_runtime/ecmrt_est_f32*.h``,
around the model's step), operation for operation: bit-identical to the C at
every step (tests/test_codegen_estimator.py, through cffi and under QEMU).

Written as the C is: one function per generated function of the update (``<prefix>_est_update``
and the model's rows: ``_factors``, ``_rows_rc``, ``_rows_states``, ``_rows_soc``,
``_predict``, ``_measurement``, ``_relinearise``, ``_correct``) around ``_model_step``. The
model's step is mirrored here per sample (the filter changes the state between steps, so
:func:`ecmgen.c.cref.simulate_f32`, which runs a whole record at once, cannot drive it); what does not depend on the state (the sanitised inputs, the direction, the
temperature row and weight, the per-temperature branch values, the Butler-Volmer factor,
the effects' factors and the hysteresis and extra RC coefficients) is computed for the
whole record at once, as cref does; with the offset state the current depends on the
state, and what depends on the current is computed per sample (``_current_terms``). With
the surface SOC the step's RC tables and the accessor's are read at the surface SOC from the
u_diff before the step (``estref_tables.Tables.surface``), F gets its u_diff column. numpy float32 scalars round once
per operation, as the C built with -ffp-contract=off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import cref
from .codegen import branch_rows
from ..estimate.ekf import HYSTERESIS_START_VAR
from .estc import EstSpec
from .estref_tables import Tables, locate_vec
from .qformat import DT_MAX_S, SOC_LIM
from .spec import CSpec

F32 = np.float32
ZERO, ONE, HALF = F32(0.0), F32(1.0), F32(0.5)
ITER, ITER_SOC, ITER_TOL = 5, F32("1.0e-3"), F32("1.0e-5")
V_MAX = F32(1000.0)          # ECMRT_EST_V_MAX: a reading beyond is no measurement
SOC_LO, SOC_HI = F32(-SOC_LIM), F32(SOC_LIM)     # the step's SOC saturation


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
        kt, wt = locate_vec(spec.temp_grid, temp)
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


class _Run:
    """One run of the filter: its constants (the spec's, the noise's, the effects') and its
    state (the SOC, the RC voltages u, the covariance P, the start flags)."""

    def __init__(self, spec, est, current_a, dt_s, voltage_v, soc0, temperature_c):
        self.spec, self.tab, self.off = spec, Tables(spec), est.offset
        if self.off:     # the current is the reading less the offset state: per sample
            n0 = np.asarray(current_a).size
            self.per = [_inputs(spec, np.zeros(n0), temperature_c, dt_s,
                                np.full(n0, d, np.uint8)) for d in (0, 1)]
            self.inp = self.per[0]
            self.seen = np.asarray(current_a, dtype=np.float64).astype(F32)
            self.imax, self.dband = F32(spec.i_lim_a), F32(spec.deadband)
        else:
            self.inp = _inputs(spec, current_a, temperature_c, dt_s)
        self.vm_all = np.asarray(voltage_v, dtype=np.float64).astype(F32)
        self.n, self.N = self.inp["i"].size, est.n
        N = self.N
        nz = self.nz = {k: F32(v) for k, v in est.noise.items()}
        self.spread_k = nz.get("ocv_k", ZERO)      # no ocv_slope_spread: the tangent
        self.diff, self.bv, self.tau_t = spec.diff, spec.has_bv, spec.tau_t
        self.surf = spec.surface is not None        # the surface SOC (with the diffusion pair)
        self.flat = not est.settings.resistance_slopes
        fx = self.fx = spec.fx
        self.cdr, self.arr, self.hyst, self.xrc = (bool(fx.get(k))
                                                   for k in ("cdr", "arr", "hyst", "xrc"))
        self.ix = 3 + int(self.diff)                # u_x's, h's and the offset's indices
        self.ih = self.ix + int(self.xrc)
        self.ib = N - 1
        self.k_soc = F32(spec.k_soc)
        # est_init: the model's init (SOC saturated to [-2, 2], NaN 0), then [0, 1]
        s0 = F32(soc0)
        s0 = ZERO if np.isnan(s0) else min(max(s0, F32(-SOC_LIM)), F32(SOC_LIM))
        self.soc = _clamp(F32(s0))
        self.u = [ZERO] * N                          # u[0] unused
        P = self.P = [[ZERO] * N for _ in range(N)]
        P[0][0] = nz["p0_soc"]
        for r in range(1, N):
            P[r][r] = nz["p0_u"]
        if self.hyst:
            anywhere = nz["start_a"] != ZERO         # a start anywhere: the direction unknown
            P[self.ih][self.ih] = F32(HYSTERESIS_START_VAR) if anywhere else nz["p0_h"]
            self.u[self.ih] = ZERO if anywhere else F32(fx["h_init"])
            self.h_k, self.h_m, self.h_m0, self.h_ref = (F32(fx[k]) for k in
                                                        ("h_k", "h_m", "h_m0", "h_ref"))
        if self.xrc:
            self.x_r = F32(fx["x_r"])
        if self.off:
            P[self.ib][self.ib] = nz["p0_b"]
            self.d_prev = 0
        self.first, self.held = True, ZERO           # est_t's eta_v


class _Sample:
    """One sample's inputs, the step's values the filter reads, and the linearisation:
    F = diag(a) + f e_soc^T (+ o e_offset^T) (+ g e_u_diff^T), Q = diag(q), H = h, R."""

    __slots__ = ("t", "i", "d", "ai", "dt", "kt", "wt", "src", "cur", "u_prev", "vp", "pa",
                 "sds", "sdu", "ja", "gc", "fa", "gf", "sg", "ch", "cx", "r0a", "dr0a", "rf",
                 "drf", "rs", "drs", "rb0", "rbf", "dg0", "dgf", "ds_di", "rg", "ps",
                 "a", "f", "q", "o", "g", "h", "R")


def _sample_inputs(run: _Run, t: int) -> _Sample:
    """The sample's current (with the offset state: the reading less the offset, its
    direction and what depends on it), dt, temperature row and weight."""
    s, inp = _Sample(), run.inp
    s.t, s.dt, s.kt = t, inp["dt"][t], int(inp["kt"][t])
    s.wt = None if inp["wt"] is None else inp["wt"][t]
    if run.off:
        s.i = _sanitise(run.seen[t] - run.u[run.ib], run.imax)
        s.d = 1 if s.i > run.dband else (0 if s.i < -run.dband else run.d_prev)
        run.d_prev = s.d
        s.ai = -s.i if s.i < ZERO else s.i
        s.src = run.per[s.d]
        s.cur = _current_terms(run.spec, s.ai, s.dt, s.src, t)
    else:
        s.i, s.d = inp["i"][t], int(inp["chg"][t])
        s.ai = -s.i if s.i < ZERO else s.i
        s.src, s.cur = inp, {k: inp[k][t] for k in ("g_cdr", "g_bv", "c_h") if k in inp}
    return s


def _model_step(run: _Run, s: _Sample) -> None:
    """The model's step (<prefix>_step_f32) on the run's state: the SOC, the RC voltages, the predicted voltage
    s.vp; keeps what the filter reads (the tables at the new SOC with their slopes, the
    coefficients, the effects' factors)."""
    i, d, t, dt, kt, wt, src, u = s.i, s.d, s.t, s.dt, s.kt, s.wt, s.src, run.u
    dsoc = (i * dt) * run.k_soc if run.off else run.inp["dsoc"][t]
    s.u_prev = list(u)
    sn = run.soc + (dsoc - ZERO)                         # soc_c is 0 after every est step
    run.soc = SOC_LO if sn < SOC_LO else (SOC_HI if sn > SOC_HI else sn)
    socr, s.sds, s.sdu = (run.tab.surface(run.soc, s.u_prev[3], kt, wt) if run.surf
                          else (run.soc, None, None))
    # the step's lookups (pv) and the accessor's (ecmrt_est_f32_params, pa) read the same
    # tables at the same SOC: one lookup gives both (the accessor adds the slopes)
    pa = pv = run.tab.values(d, run.soc, kt, wt, ("r0", "rf", "tf", "rs", "ts"), True, socr)
    r0, rf, rs, ocv = pv["r0"][0], pv["rf"][0], pv["rs"][0], pv["ocv"][0]
    s.gc = s.cur["g_cdr"] if run.cdr else ONE
    s.fa = run.inp["f_arr"][t] if run.arr else ONE
    if run.cdr:
        r0, rf = r0 * s.gc, rf * s.gc
    if run.arr:
        r0, rf, rs = r0 * s.fa, rf * s.fa, rs * s.fa
    if run.bv:
        rf = rf * s.cur["g_bv"]
    if run.flat:                     # resistance_slopes false: the RC tables flat in SOC
        pa = {k: (v[0], ZERO) if k != "ocv" else v for k, v in pa.items()}
    s.pa = pa
    if run.tau_t:            # the state's coefficients kc = 1/tau(T), for step and filter
        cf, cs = omexp(dt * src["kc_f"][t]), omexp(dt * src["kc_s"][t])
        s.ja = (cf, cs)
    else:
        cf, cs = omexp(dt / pv["tf"][0]), omexp(dt / pv["ts"][0])
        s.ja = (omexp(dt / pa["tf"][0]), omexp(dt / pa["ts"][0]))
    u[1] = u[1] + cf * (rf * i - u[1])
    u[2] = u[2] + cs * (rs * i - u[2])
    vp = ((ocv + r0 * i) + u[1]) + u[2]
    if run.diff:
        u[3] = u[3] + src["c_diff"][t] * (src["r_diff"][t] * i - u[3])
        vp = vp + u[3]
    vh = vx = F32(-0.0)              # an effect that is off adds -0.0 (as the C step)
    if run.hyst:
        s.sg, s.ch = (ONE if d == 1 else F32(-1.0)), s.cur["c_h"]
        u[run.ih] = u[run.ih] + s.ch * (s.sg - u[run.ih])
        vh = run.h_m * (u[run.ih] - run.h_ref) + run.h_m0 * (s.sg - run.h_ref)
    if run.xrc:
        s.cx = run.inp["c_x"][t]
        u[run.ix] = u[run.ix] + s.cx * (run.x_r * i - u[run.ix])
        vx = u[run.ix]
    s.vp = vp + (vh + vx)


def _factors(run: _Run, s: _Sample) -> None:
    """ecmrt_est_f32_factors: the accessor's resistances (and slopes) times the effects'
    factors; with the offset state the resistances before them and d(i g)/di."""
    (r0a, dr0a), (rf, drf), (rs, drs) = s.pa["r0"], s.pa["rf"], s.pa["rs"]
    gc, fa = s.gc, s.fa
    s.gf = s.cur["g_bv"] if run.bv else ONE
    if run.off:                               # before the current's factors
        s.rb0, s.rbf = (r0a * fa, rf * fa) if run.arr else (r0a, rf)
        s.dg0 = (F32(run.fx["g_scale"]) / _s(cref.sqrt_f32(s.cur["xc"] * s.cur["xc"] + ONE))
                 if run.cdr else ONE)
        s.dgf = s.dg0
        if run.bv:
            xb = s.cur["xb"]
            dbv = ONE / _s(cref.sqrt_f32(xb * xb + ONE))
            s.dgf = (gc * dbv + s.gf * s.dg0) - gc * s.gf if run.cdr else dbv
        s.ds_di = s.dt * run.k_soc
    if run.cdr:                               # ecmrt_est_f32_fx
        r0a, dr0a, rf, drf = r0a * gc, dr0a * gc, rf * gc, drf * gc
    if run.arr:
        r0a, dr0a, rf, drf = r0a * fa, dr0a * fa, rf * fa, drf * fa
        rs, drs = rs * fa, drs * fa
    s.r0a, s.dr0a, s.rf, s.drf, s.rs, s.drs = r0a, dr0a, rf, drf, rs, drs


def _rows_rc(run: _Run, s: _Sample) -> None:
    """ecmrt_est_f32_rows_rc: the rows of u_fast and u_slow (SOC column through da/dsoc and
    dr/dsoc) and their noise."""
    nz, i, dt, a, f, q = run.nz, s.i, s.dt, s.a, s.f, s.q
    one_a = s.ja[0]
    a[1] = ONE - one_a
    if run.tau_t:
        da = ZERO
    else:
        (tf_, dtf) = s.pa["tf"]
        da = ((a[1] * dt) / (tf_ * tf_)) * dtf
    f[1] = da * s.u_prev[1] + ((s.drf * one_a - s.rf * da) * s.gf) * i
    if run.surf:
        s.g[1], f[1] = f[1] * s.sdu, f[1] * s.sds
    if run.off:
        s.o[1] = -((s.rbf * one_a) * s.dgf) - f[1] * s.ds_di
    s.rg = s.rf * s.gf
    e = (nz["pol"] * s.rg) * i
    q[1] = ((e * e) * (ONE - a[1] * a[1])) * s.ps
    one_a = s.ja[1]
    a[2] = ONE - one_a
    if not run.tau_t:
        (ts_, dts) = s.pa["ts"]
        da = ((a[2] * dt) / (ts_ * ts_)) * dts
    f[2] = da * s.u_prev[2] + (s.drs * one_a - s.rs * da) * i
    if run.surf:
        s.g[2], f[2] = f[2] * s.sdu, f[2] * s.sds
    if run.off:
        s.o[2] = -(s.rs * one_a) - f[2] * s.ds_di
    e = (nz["pol"] * s.rs) * i
    q[2] = ((e * e) * (ONE - a[2] * a[2])) * s.ps


def _rows_states(run: _Run, s: _Sample) -> None:
    """ecmrt_est_f32_row_diff, _row_xrc, _row_hyst: the rows of u_diff, u_x and h (no SOC
    column) and their noise."""
    nz, i, t, a, q = run.nz, s.i, s.t, s.a, s.q
    if run.diff:
        ad = ONE - s.src["c_diff"][t]
        a[3] = ad
        if run.off:
            s.o[3] = -(s.src["r_diff"][t] * s.src["c_diff"][t])
        e = (nz["pol"] * s.src["r_diff"][t]) * i
        q[3] = ((e * e) * (ONE - ad * ad)) * s.ps
    if run.xrc:
        ix = run.ix
        a[ix] = ONE - s.cx
        if run.off:
            s.o[ix] = -(run.x_r * s.cx)
        e = (nz["pol"] * run.x_r) * i
        q[ix] = ((e * e) * (ONE - a[ix] * a[ix])) * s.ps
    if run.hyst:
        ih = run.ih
        a[ih] = ONE - s.ch
        q[ih] = nz["p0_h"] * (s.ch * (F32(2.0) - s.ch))
        if run.off:
            si = ONE if i > ZERO else (F32(-1.0) if i < ZERO else ZERO)
            s.o[ih] = (((s.u_prev[ih] - s.sg) * si) * (s.dt * run.h_k)) * a[ih]


def _rows_soc(run: _Run, s: _Sample) -> None:
    """ecmrt_est_f32_rows_soc: the SOC's noise (the sensor's bias over the drift horizon and
    white noise; with the offset state its random walk instead), none for dt <= 0; then
    ecmrt_est_f32_start_noise at the first sample."""
    nz, dt = run.nz, s.dt
    if run.off:
        s.o[0] = -s.ds_di
        s.o[run.ib], s.a[run.ib], s.f[run.ib] = ZERO, ONE, ZERO
    if dt > ZERO:
        kk = dt * run.k_soc
        if run.off:
            b = nz["gain"] * s.ai
            s.q[run.ib] = (nz["p0_b"] * dt) / nz["horizon_s"]
        else:
            b = nz["gain"] * s.ai + nz["offset_a"]
        e = b * run.k_soc
        r = nz["noise_a"] * kk
        s.q[0] = (e * e) * (dt * nz["horizon_s"]) + r * r
    else:
        s.q = [ZERO] * run.N
    if run.first:                    # the RC voltages' start variance
        for j, r_ in ((1, s.rg), (2, s.rs),
                      (3, s.src["r_diff"][s.t] if run.diff else None),
                      (run.ix, run.x_r if run.xrc else None)):
            if r_ is not None:
                e = r_ * nz["start_a"]
                s.q[j] = s.q[j] + e * e


def _predict(run: _Run, s: _Sample) -> None:
    """ecmrt_est_f32_predict: P = F P F^T + Q, exactly symmetric (the loops over zipped
    rows: the same float32 operations in the same order as indexed loops, at a third of
    the interpreter's cost)."""
    P, N, a, f, q, o, g, ib = run.P, run.N, s.a, s.f, s.q, s.o, s.g, run.ib
    P0 = P[0]
    fp = [[ar * prc + fr * p0c for prc, p0c in zip(pr, P0)] for ar, fr, pr in zip(a, f, P)]
    if run.off:
        pb = P[ib]
        fp = [[v + orr * pbc for v, pbc in zip(row, pb)] for row, orr in zip(fp, o)]
    if run.surf:
        p3 = P[3]
        fp = [[v + gr * p3c for v, p3c in zip(row, p3)] for row, gr in zip(fp, g)]
    for r in range(N):
        fr_, fr0 = fp[r], fp[r][0]
        for c in range(r, N):
            val = a[c] * fr_[c] + f[c] * fr0
            if run.off:
                val = val + o[c] * fr_[ib]
            if run.surf:
                val = val + g[c] * fr_[3]
            if r == c:
                val = val + q[r]
            P[r][c] = P[c][r] = val


def _measurement(run: _Run, s: _Sample) -> None:
    """H (ecmrt_est_f32_h_soc at the predicted P) and R (ecmrt_est_f32_r)."""
    nz, i, dt = run.nz, s.i, s.dt
    up = s.u_prev[3] if run.surf else None
    dv = _ocv_slope(run.tab, s.d, run.soc, run.P[0][0], run.spread_k, s.kt, s.wt, up,
                    s.pa["ocv"][1])
    h = s.h = [dv + (s.dr0a * s.sds if run.surf else s.dr0a) * i] + [ONE] * (run.N - 1)
    if run.hyst:
        h[run.ih] = run.h_m
    if run.off:
        h[run.ib] = -(s.rb0 * s.dg0)
    e = _abs(s.vp - s.pa["ocv"][0])
    if nz["mem_k"] > ZERO:
        r = run.held - run.held * omexp(dt * nz["mem_k"])
        if r > e:
            e = r
        run.held = e
    e = nz["model_error"] * e
    R = nz["vn2"] + e * e
    if not run.off:                  # the offset through the resistances
        rdc = s.r0a + s.rg
        rdc = rdc + s.rs
        if run.diff:
            rdc = rdc + s.src["r_diff"][s.t]
        if run.xrc:
            rdc = rdc + run.x_r
        e = nz["offset_a"] * rdc
        R = R + e * e
    if not (run.first and nz["start_a"] == ZERO) and dt < nz["corr_s"]:
        R = R * (nz["corr_s"] / dt) if dt > ZERO else ZERO
    run.first = False
    vm = run.vm_all[s.t]
    s.R = R if vm >= -V_MAX and vm <= V_MAX else ZERO


def _relinearise(run: _Run, s: _Sample, xu: list, h: list):
    """At the updated state xu: H's SOC (and offset) entry and the model's voltage h(x)
    (ecmrt_est_f32_h_soc, ecmrt_est_f32_voltage)."""
    i, kt, wt = s.i, s.kt, s.wt
    socr, sds, _ = (run.tab.surface(xu[0], s.u_prev[3], kt, wt) if run.surf
                    else (xu[0], None, None))
    pi = run.tab.values(s.d, xu[0], kt, wt, ("r0",), True, socr)
    if run.flat:
        pi["r0"] = (pi["r0"][0], ZERO)
    (r0i, dr0i) = pi["r0"]
    if run.off:
        h[run.ib] = -((r0i * s.fa if run.arr else r0i) * s.dg0)
    if run.cdr:
        r0i, dr0i = r0i * s.gc, dr0i * s.gc
    if run.arr:
        r0i, dr0i = r0i * s.fa, dr0i * s.fa
    vi = ((pi["ocv"][0] + r0i * i) + xu[1]) + xu[2]
    if run.diff:
        vi = vi + xu[3]
    vh = vx = F32(-0.0)
    if run.hyst:
        vh = run.h_m * (xu[run.ih] - run.h_ref) + run.h_m0 * (s.sg - run.h_ref)
    if run.xrc:
        vx = xu[run.ix]
    up = s.u_prev[3] if run.surf else None
    dv = _ocv_slope(run.tab, s.d, xu[0], run.P[0][0], run.spread_k, kt, wt, up, pi["ocv"][1])
    h[0] = dv + (dr0i * sds if run.surf else dr0i) * i
    return vi + (vh + vx)


def _correct(run: _Run, s: _Sample, x0: list) -> None:
    """ecmrt_est_f32_correct: the update, iterated while it moves the SOC, then the Joseph
    form; the state and P written only when all of it is finite."""
    P, h, R, N, vm = run.P, s.h, s.R, run.N, run.vm_all[s.t]
    g = _gain(P, h, R, x0, vm - s.vp)
    ok = g is not None
    if ok:
        c, k, xu = g
    for _ in range(ITER):
        if not ok:
            break
        xu[0] = _clamp(xu[0])
        if run.hyst:
            xu[run.ih] = _clamp_h(xu[run.ih])
        if _abs(xu[0] - x0[0]) < ITER_SOC:
            break
        e = vm - _relinearise(run, s, xu, h)
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
        run.u[1:] = xu[1:]
        if run.hyst:
            run.u[run.ih] = _clamp_h(xu[run.ih])
        x0[0] = xu[0]


def _simulate(spec, est, current_a, dt_s, voltage_v, soc0, temperature_c, jacobians
              ) -> EstRef:
    run = _Run(spec, est, current_a, dt_s, voltage_v, soc0, temperature_c)
    n, N = run.n, run.N
    v_out = np.empty(n, dtype=F32)
    x_out = np.empty((n, N), dtype=F32)
    p_out = np.empty((n, N, N), dtype=F32)
    f_out = np.zeros((n, N, N), dtype=F32) if jacobians else None
    h_out = np.zeros((n, N), dtype=F32) if jacobians else None
    for t in range(n):
        s = _sample_inputs(run, t)
        _model_step(run, s)                      # <prefix>_step_f32
        x0 = [run.soc] + run.u[1:]               # ecmrt_est_f32_update from here
        _factors(run, s)
        s.a, s.f, s.q = [ONE] + [ZERO] * (N - 1), [ZERO] * N, [ZERO] * N
        s.g = [ZERO] * N                         # F's u_diff column through the surface SOC
        s.o = [ZERO] * N if run.off else None    # F's offset column
        s.ps = (run.nz["pol_s2"] / (run.nz["pol_s2"] + run.P[0][0])
                if run.nz["pol_s2"] > ZERO else ONE)
        _rows_rc(run, s)
        _rows_states(run, s)
        _rows_soc(run, s)
        _predict(run, s)
        _measurement(run, s)
        if jacobians:
            _keep_jacobians(run, s, f_out[t], h_out)
        if s.R > ZERO:
            _correct(run, s, x0)
        run.soc = _clamp(x0[0])
        v_out[t] = s.vp
        x_out[t, 0] = run.soc
        x_out[t, 1:] = run.u[1:]
        p_out[t] = run.P
    return EstRef(v_out, x_out, p_out, f_out, h_out)


def _keep_jacobians(run: _Run, s: _Sample, f_t: np.ndarray, h_out: np.ndarray) -> None:
    """F and H of the sample, before any iteration (jacobians=True)."""
    N, ib = run.N, run.ib
    f_t[np.diag_indices(N)] = s.a
    f_t[1:, 0] = s.f[1:]
    if run.off:
        f_t[:ib, ib] = s.o[:ib]
    if run.surf:
        f_t[1:3, 3] = s.g[1:3]
    h_out[s.t] = s.h


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
