"""The candidate problems of ``diagnose``: each effect's free parameters and bounds, and
the casadi model of the discrete step with forward sensitivities that fits them.

:class:`_Problem` mirrors :mod:`ecmgen.model.simulate` + :mod:`ecmgen.model.effects`
exactly (the tests hold it to the simulator); :func:`_fit` is the bounded Gauss-Newton
(scipy TRF with the casadi Jacobian) that :mod:`ecmgen.diagnosis.search` calls for every
candidate. casadi and scipy are imported only when a problem is built or fitted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..data.measure import TimeSeries
from ..model import effects as fx
from ..model.effects import KELVIN
from ..errors import InputError
from ..model.model import BRANCH_FIELDS, RC_FIELDS, EcmModel
from ..model.simulate import step_inputs


# -- small numeric helpers ----------------------------------------------------------------

# -- parameter layout ---------------------------------------------------------------------

@dataclass(frozen=True)
class _Spec:
    lo: float
    hi: float
    log: bool
    # a fit that ends on this bound lies outside what the effect can be (a scale's both
    # ends; a magnitude's upper end: its lower end, 0, is the effect switched off)
    limit_lo: bool | None = None
    limit_hi: bool | None = None

    def ends_on_limit(self, v: float, rtol: float = 0.01) -> bool:
        lo = self.log if self.limit_lo is None else self.limit_lo
        hi = self.log if self.limit_hi is None else self.limit_hi
        if self.log:
            return (lo and v <= self.lo * (1 + rtol)) or (hi and v >= self.hi / (1 + rtol))
        span = rtol * (self.hi - self.lo)
        return (lo and v <= self.lo + span) or (hi and v >= self.hi - span)


def _specs(name: str, model: EcmModel, ctx: dict) -> dict[str, _Spec]:
    """Free parameters of an effect and their bounds (native units)."""
    q = model.capacity_ah
    if name == fx.Hysteresis.name:
        return {"m_v": _Spec(0.0, 0.3, False, limit_hi=True),
                "decay_ah": _Spec(0.002 * q, 0.5 * q, True),
                "m0_v": _Spec(0.0, 0.1, False, limit_hi=True),
                "ocv_table_state": _Spec(-1.0, 1.0, False),
                "initial_state": _Spec(-1.0, 1.0, False)}
    if name == fx.CurrentDependentResistance.name:
        return {"scale_at_zero": _Spec(0.2, 5.0, True), "i0_a": _Spec(0.02 * q, 50.0 * q, True)}
    if name == fx.ExtraRc.name:
        r_hi = max(0.5, 20.0 * ctx["r_total_ohm"])
        return {"r_ohm": _Spec(0.0, r_hi, False, limit_hi=True),
                "tau_s": _Spec(ctx["tau_min_s"], ctx["tau_max_s"], True)}
    if name == fx.CapacityError.name:
        return {"capacity_scale": _Spec(0.7, 1.4, False, limit_lo=True, limit_hi=True)}
    if name == fx.TemperatureDependence.name:
        return {"activation_k": _Spec(0.0, 15000.0, False, limit_hi=True)}
    raise ValueError(name)


def _fixed(name: str, ctx: dict) -> dict[str, float]:
    """Parameters that are set from the data, not fitted."""
    if name == fx.TemperatureDependence.name:
        return {"t_ref_c": ctx["t_ref_c"]}
    return {}


def _neutral(name: str, ctx: dict) -> dict[str, float]:
    """Parameter values at which the effect changes nothing (used as fallback start)."""
    return {
        fx.Hysteresis.name: {"m_v": 0.005, "decay_ah": 0.05 * ctx["capacity_ah"], "m0_v": 0.0,
                             "ocv_table_state": 0.0, "initial_state": 0.0},
        fx.CurrentDependentResistance.name: {"scale_at_zero": 1.0, "i0_a": ctx["capacity_ah"]},
        fx.ExtraRc.name: {"r_ohm": 0.0, "tau_s": 600.0},
        fx.CapacityError.name: {"capacity_scale": 1.0},
        fx.TemperatureDependence.name: {"activation_k": 0.0},
    }[name]


# -- the casadi model with forward sensitivities ---------------------------------------------

class _Problem:
    """Residual (simulated - measured) and its Jacobian for a set of effects whose
    parameters are partly free. Mirrors ecmgen.model.simulate + ecmgen.model.effects exactly,
    also for a base model over temperature (its tables read at the record's cell
    temperature) and with the diffusion pair and the Butler-Volmer fast branch."""

    def __init__(self, model: EcmModel, data: TimeSeries, soc0: float,
                 effects: list[tuple[str, dict[str, float], dict[str, _Spec]]]):
        import casadi as ca

        self.ca = ca
        self.model = model
        self.soc0 = float(soc0)
        self.t = data.time_s
        self.i = data.current_a
        self.v = data.voltage_v
        self.temp = data.temperature_c
        self.n = len(data)
        # effects: (name, values of all parameters, free parameter specs)
        self.effects = effects
        self.names = [e[0] for e in effects]
        self.free: list[tuple[int, str, _Spec]] = []
        self.const: list[tuple[int, str]] = []
        for k, (name, values, specs) in enumerate(effects):
            for pname in values:
                if pname in specs:
                    self.free.append((k, pname, specs[pname]))
                else:
                    self.const.append((k, pname))
        self.values = [dict(v) for _, v, _ in effects]
        # a model over temperature reads its tables at the record's cell temperature
        self.table_temp = self.temp if model.needs_temperature else None
        if model.needs_temperature and self.temp is None:
            raise InputError(data.source, "no cell temperature column: the model has tables "
                                          "over temperature")
        dt, soc, charging, _ = step_inputs(model, self.t, self.i, self.soc0, self.table_temp)
        # the optional branches of the base model (per temperature): a diffusion RC pair
        # and the Butler-Volmer factor of the fast branch
        self.branches = [k for k in BRANCH_FIELDS if getattr(model.discharge, k) is not None]
        self.dt = dt
        self.charging = charging
        self.s = np.where(charging, 1.0, -1.0)
        self.q_as = np.cumsum(self.i * dt)
        self.has_cap = fx.CapacityError.name in self.names
        self.has_temp = fx.TemperatureDependence.name in self.names and self.temp is not None
        self._build()

    # z <-> native ---------------------------------------------------------------------
    def z0(self) -> np.ndarray:
        out = []
        for k, pname, sp in self.free:
            v = min(max(self.values[k][pname], sp.lo), sp.hi)
            out.append(math.log(max(v, 1e-300)) if sp.log else v)
        return np.array(out, dtype=np.float64)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = [math.log(sp.lo) if sp.log else sp.lo for _, _, sp in self.free]
        hi = [math.log(sp.hi) if sp.log else sp.hi for _, _, sp in self.free]
        return np.array(lo), np.array(hi)

    def native(self, z, snap: bool = False) -> list[dict[str, float]]:
        """Parameter values of z; ``snap``: values within 1e-6 of the span of a bound are
        set to the bound (a term the fit switched off reads as exactly 0)."""
        vals = [dict(v) for v in self.values]
        for zk, (k, pname, sp) in zip(np.asarray(z, dtype=np.float64), self.free):
            x = float(math.exp(zk) if sp.log else zk)
            if snap:
                tol = 1e-6 * (sp.hi - sp.lo)
                x = sp.lo if x - sp.lo < tol else sp.hi if sp.hi - x < tol else x
            vals[k][pname] = x
        return vals

    def effects_of(self, z) -> list:
        return [fx.make_effect(name, **vals)
                for name, vals in zip(self.names, self.native(z, snap=True))]

    # casadi step ----------------------------------------------------------------------
    def _build(self) -> None:
        """The casadi step of the candidate's model and its forward sensitivities: F maps
        (state and sensitivities, inputs, free and constant parameters) to the next ones
        and (voltage, its sensitivities); Fm the same over the record."""
        ca = self.ca
        nf, nc = len(self.free), len(self.const)
        pf = ca.SX.sym("pf", nf)
        pc = ca.SX.sym("pc", nc)
        par = [dict() for _ in self.names]
        for j, (k, pname, _) in enumerate(self.free):
            par[k][pname] = pf[j]
        for j, (k, pname) in enumerate(self.const):
            par[k][pname] = pc[j]
        u, U, x, X = self._symbols()
        nxt, v = self._step(par, U, X, self._resistances(par, U))
        states = self.states
        xn = ca.vertcat(*[nxt[s_] for s_ in states])
        S = ca.SX.sym("S", len(states), nf)
        Sn = ca.jacobian(xn, x) @ S + ca.jacobian(xn, pf)
        dv = ca.jacobian(v, x) @ S + ca.jacobian(v, pf)
        xa = ca.vertcat(x, ca.vec(S))
        xan = ca.vertcat(xn, ca.vec(Sn))
        self.F = ca.Function("F", [xa, u, pf, pc], [xan, ca.vertcat(v, dv.T)])
        self.Fm = self.F.mapaccum("Fm", self.n)
        # initial state (h_{-1} = initial_state) and its sensitivity
        self._x0_index = {}
        for k, name in enumerate(self.names):
            if name == fx.Hysteresis.name:
                self._x0_index[k] = states.index(f"{name}#{k}")

    def _symbols(self):
        """The input row's symbols (``self.rows`` names them) and the state's
        (``self.states``), each as a vector and by name."""
        ca = self.ca
        rows = ["dt", "i", "s", "ocv"] + list(RC_FIELDS) + self.branches
        if self.has_cap:
            rows += ["q", "soc"] + ["d_ocv"] + ["d_" + k for k in RC_FIELDS]
        if self.has_temp:
            rows += ["temp"]
        self.rows = rows
        u = ca.SX.sym("u", len(rows))
        U = {r: u[j] for j, r in enumerate(rows)}
        states = ["u_fast", "u_slow"] + (["u_diff"] if "r_diff_ohm" in self.branches else [])
        for k, name in enumerate(self.names):
            if name in (fx.Hysteresis.name, fx.ExtraRc.name):
                states.append(f"{name}#{k}")
        self.states = states
        x = ca.SX.sym("x", len(states))
        X = {s: x[j] for j, s in enumerate(states)}
        return u, U, x, X

    def _resistances(self, par, U) -> dict:
        """The OCV (key ``"ocv"``) and the RC parameters of the step: at the SOC the
        capacity scale moves them to, then the parameter effects, then the Butler-Volmer
        branch (the simulator's order)."""
        ca = self.ca
        i = U["i"]
        ocv = U["ocv"]
        p = {k: U[k] for k in RC_FIELDS}
        if self.has_cap:
            scale = 1
            for k, name in enumerate(self.names):
                if name == fx.CapacityError.name:
                    scale = scale * par[k]["capacity_scale"]
            soc_sym = self.soc0 + U["q"] / (3600.0 * self.model.capacity_ah * scale)
            dsoc = soc_sym - U["soc"]
            ocv = ocv + U["d_ocv"] * dsoc
            p = {k: p[k] + U["d_" + k] * dsoc for k in RC_FIELDS}
        for k, name in enumerate(self.names):
            if name == fx.CurrentDependentResistance.name:
                xx = ca.fmax(ca.fabs(i) / par[k]["i0_a"], 1e-12)
                g = par[k]["scale_at_zero"] * ca.asinh(xx) / xx
                p["r0_ohm"] = p["r0_ohm"] * g
                p["r_fast_ohm"] = p["r_fast_ohm"] * g
            elif name == fx.TemperatureDependence.name and self.has_temp:
                f = ca.exp(par[k]["activation_k"] * (1.0 / (U["temp"] + KELVIN)
                                                    - 1.0 / (par[k]["t_ref_c"] + KELVIN)))
                for key in ("r0_ohm", "r_fast_ohm", "r_slow_ohm"):
                    p[key] = p[key] * f
        if "i0_a" in self.branches:       # after the effects, as the simulator
            xb = ca.fmax(ca.fabs(i) / U["i0_a"], 1e-12)
            p["r_fast_ohm"] = p["r_fast_ohm"] * (ca.asinh(xb) / xb)
        p["ocv"] = ocv
        return p

    def _step(self, par, U, X, p):
        """The next states (by name) and the voltage: the RC pairs, the diffusion pair,
        then each voltage effect in the candidate's order."""
        ca = self.ca
        dt, i, s = U["dt"], U["i"], U["s"]
        a_f = ca.exp(-dt / p["tau_fast_s"])
        a_s = ca.exp(-dt / p["tau_slow_s"])
        nxt = {"u_fast": a_f * X["u_fast"] + p["r_fast_ohm"] * (1 - a_f) * i,
               "u_slow": a_s * X["u_slow"] + p["r_slow_ohm"] * (1 - a_s) * i}
        v = p["ocv"] + p["r0_ohm"] * i + nxt["u_fast"] + nxt["u_slow"]
        if "u_diff" in X:
            a_d = ca.exp(-dt / U["tau_diff_s"])
            nxt["u_diff"] = a_d * X["u_diff"] + U["r_diff_ohm"] * (1 - a_d) * i
            v = v + nxt["u_diff"]
        for k, name in enumerate(self.names):
            key = f"{name}#{k}"
            if name == fx.Hysteresis.name:
                e = par[k]
                a_h = ca.exp(-ca.fabs(i) * dt / (3600.0 * e["decay_ah"]))
                nxt[key] = a_h * X[key] + (1 - a_h) * s
                v = v + e["m_v"] * (nxt[key] - e["ocv_table_state"]) \
                    + e["m0_v"] * (s - e["ocv_table_state"])
            elif name == fx.ExtraRc.name:
                a3 = ca.exp(-dt / par[k]["tau_s"])
                nxt[key] = a3 * X[key] + par[k]["r_ohm"] * (1 - a3) * i
                v = v + nxt[key]
        return nxt, v

    def _inputs(self, vals) -> np.ndarray:
        m = self.model
        i = self.i
        scale = 1.0
        for name, v in zip(self.names, vals):
            if name == fx.CapacityError.name:
                scale *= v["capacity_scale"]
        soc = self.soc0 + self.q_as / (3600.0 * m.capacity_ah * scale)
        ch = self.charging
        temp = self.table_temp
        pc_, pd_ = m.charge.at(soc, temp), m.discharge.at(soc, temp)
        cols = {"dt": self.dt, "i": i, "s": self.s, "ocv": m.ocv.ocv_at(soc, temp)}
        for k in (*RC_FIELDS, *self.branches):
            cols[k] = np.where(ch, pc_[k], pd_[k])
        if self.has_cap:
            cols["q"] = self.q_as
            cols["soc"] = soc
            cols["d_ocv"] = m.ocv.soc_slope(soc, temp)
            for k in RC_FIELDS:
                dc = m.charge.soc_slope(k, soc, temp)
                dd = m.discharge.soc_slope(k, soc, temp)
                cols["d_" + k] = np.where(ch, dc, dd)
        if self.has_temp:
            cols["temp"] = self.temp
        return np.vstack([cols[r] for r in self.rows])

    def simulate(self, z) -> tuple[np.ndarray, np.ndarray]:
        """Simulated voltage and its Jacobian with respect to z."""
        vals = self.native(z)
        nf = len(self.free)
        xa0 = np.zeros(len(self.states) * (1 + nf))
        for k, j in self._x0_index.items():
            xa0[j] = vals[k]["initial_state"]
            for col, (kk, pname, _) in enumerate(self.free):
                if kk == k and pname == "initial_state":
                    xa0[len(self.states) + col * len(self.states) + j] = 1.0
        pf = np.array([vals[k][p] for k, p, _ in self.free])
        pc = np.array([vals[k][p] for k, p in self.const])
        _, out = self.Fm(xa0, self._inputs(vals), pf, pc)
        out = np.asarray(out)
        v = out[0]
        jac = out[1:].T.copy() if nf else np.zeros((self.n, 0))
        for col, (k, pname, sp) in enumerate(self.free):
            if sp.log:
                jac[:, col] *= vals[k][pname]
        return v, jac


def _fit(problem: _Problem, rows: np.ndarray, starts: list[np.ndarray], max_nfev: int,
         f_scale: float) -> tuple[np.ndarray, float]:
    """Bounded Gauss-Newton (scipy TRF, casadi Jacobian) from the best of ``starts``."""
    from scipy.optimize import least_squares

    lo, hi = problem.bounds()
    span = np.maximum(hi - lo, 1e-12)
    cache: dict = {}

    def both(z):
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            v, jac = problem.simulate(z)
            r = (v - problem.v)[rows]
            jr = jac[rows]
            bad = ~np.isfinite(r)
            if bad.any():
                r = np.where(bad, 1.0, r)
                jr = np.where(bad[:, None], 0.0, jr)
            cache[key] = (r, np.nan_to_num(jr))
        return cache[key]

    def clip(z):
        return np.clip(z, lo + 1e-9 * span, hi - 1e-9 * span)

    best = None
    n_start_nfev = 6 if len(starts) > 1 else max_nfev
    for z in starts:
        sol = least_squares(lambda z: both(z)[0], clip(z), jac=lambda z: both(z)[1],
                            bounds=(lo, hi), method="trf", x_scale="jac", loss="soft_l1",
                            f_scale=f_scale, max_nfev=n_start_nfev, xtol=1e-6, ftol=1e-7)
        if best is None or sol.cost < best.cost:
            best = sol
    if len(starts) > 1:
        best = least_squares(lambda z: both(z)[0], clip(best.x), jac=lambda z: both(z)[1],
                             bounds=(lo, hi), method="trf", x_scale="jac", loss="soft_l1",
                             f_scale=f_scale, max_nfev=max_nfev, xtol=1e-6, ftol=1e-7)
    return best.x, float(best.cost)
