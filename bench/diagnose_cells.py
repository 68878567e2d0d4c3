"""Synthetic cells with known missing effects, for scoring ``ecmgen diagnose``.

This generator shares no code with ecmgen: its cell physics is written here, in numpy,
from the continuous-time equations, with its own discretisation (trapezoidal sub-steps for
the RC pairs, a modal sphere for solid diffusion, a quasi-static Butler-Volmer branch), so
that diagnose is not scored on the equations it fits.

Each cell folder holds what a user has -- ``pulses.csv`` (a lab pulse test, 90 -> 10 % SOC),
``ocv.csv`` (an OCV table, 101 points), ``cycle.csv`` (a drive record with rests and
charges, 3-6 h) and ``case.toml`` -- plus ``truth.json`` (the effects and every parameter;
read only to score). Kinds: one effect (``KINDS``), two effects (``PAIRS``), or none
(controls). Each effect changes the cycle voltage, against what a perfect model without
it predicts from the logged data, by at least max(4 mV, 4 noise sigmas) on average.

The physics (current positive on charge; i_k held over (t_{k-1}, t_k]):

    v = U(soc_surface, T) + h_term + R_ohm i + eta_ct(i) + u1 + u2 [+ u3] [+ v_diff]
    soc' = i / (3600 Q_true)
    u_j' = (R_j i - u_j) / tau_j                      (trapezoidal, 4 sub-steps a sample)
    hysteresis (Plett): h' = -|i| g / (3600 Q) (h - sgn i); h_term = M(soc) h + M0 s, s the
               sign of the last current above Q/100
    Butler-Volmer: eta_ct = 2 R_ct i0 asinh(i / (2 i0)) (linear R_ct i in other cells)
    diffusion: sphere modes x_k' = (i - x_k) / (tau_d / lambda_k^2), tan l = l, weights
               2/l^2 normalised; v_diff = R_d(soc) sum w_k x_k
    entropic: U += dU/dT(soc) (T - 25 degC); temperature: all R x exp(Ea/R (1/T - 1/T25))
    sensor faults on the cycle's logger: current offset b, gain g, a voltage channel that
    lags (first-order filter of 0.5-3 s, or a sample late); the OCV table off by an offset
    and an SOC scale (anchored at full); the capacity in case.toml off the true one.

    python bench/diagnose_cells.py OUT --half dev [--per-kind 4] [--kinds a,b]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

KINDS = ("hysteresis", "extra_rc", "current_dependent_resistance", "capacity_error",
         "temperature_dependence", "current_offset", "current_gain", "voltage_lag",
         "entropic_ocv", "diffusion", "ocv_error")
# pairs that a test bench shows together (one physics effect and one of the data or another)
PAIRS = (("hysteresis", "extra_rc"), ("extra_rc", "capacity_error"),
         ("hysteresis", "current_offset"), ("extra_rc", "voltage_lag"),
         ("capacity_error", "temperature_dependence"), ("diffusion", "current_gain"),
         ("current_dependent_resistance", "ocv_error"), ("entropic_ocv", "extra_rc"))
# the development half is generated from these seeds; the held-out half from HELD_SEED,
# which is not generated while diagnose is being developed
DEV_SEED = 1000
HELD_SEED = 5_000_000
T25 = 298.15
GAS = 8.314


def _sphere_roots(n: int = 30) -> np.ndarray:
    """The first n positive roots of tan(l) = l (bisection in ((k+1/2) pi - ..., (k+1/2) pi))."""
    out = []
    for k in range(1, n + 1):
        lo, hi = k * math.pi + 1e-9, k * math.pi + math.pi / 2 - 1e-9
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if math.tan(mid) - mid > 0:
                hi = mid
            else:
                lo = mid
        out.append(0.5 * (lo + hi))
    return np.array(out)


SPHERE_ROOTS = _sphere_roots()


# -- the cell ---------------------------------------------------------------------------

@dataclass
class Cell:
    chem: str
    q_true_ah: float
    q_nominal_ah: float
    ocv_coef: dict
    r: dict                      # r_ohm, r_ct, r1, r2 (ohm at 25 degC, SOC 0.5), tau1_s, tau2_s
    shape: dict                  # SOC shape per resistance: (a, k, b)
    asym: float                  # charge / discharge resistance asymmetry
    noise_v: float
    lsb_v: float
    noise_a: float
    effects: dict = field(default_factory=dict)     # name -> parameters

    # the OCV -----------------------------------------------------------------------------
    def ocv(self, soc) -> np.ndarray:
        s = np.clip(np.asarray(soc, dtype=np.float64), -0.05, 1.05)
        c = self.ocv_coef
        if self.chem == "lfp":
            v = (c["e0"] + c["slope"] * s + c["s1"] * np.tanh((s - c["m1"]) / 0.035)
                 + c["s2"] * np.tanh((s - c["m2"]) / 0.03)
                 - c["knee"] * np.exp(-s / 0.03) + c["top"] * np.exp(-(1 - s) / 0.02))
        else:
            v = (c["e0"] + c["slope"] * s + c["curv"] * s * s
                 + c["log"] * np.log((np.clip(s, -0.015, 1.015) + 0.02)
                                     / (1.02 - np.clip(s, -0.015, 1.015)))
                 + c["bump"] * np.tanh((s - c["m1"]) / 0.06)
                 - c["knee"] * np.exp(-s / 0.04))
        return v

    def ocv_given(self, soc) -> np.ndarray:
        """The OCV the user's table says (an ocv_error cell: offset and SOC scale)."""
        e = self.effects.get("ocv_error")
        s = np.asarray(soc, dtype=np.float64)
        if e is None:
            return self.ocv(s)
        return self.ocv(1.0 - (1.0 - s) * e["soc_scale"]) + e["offset_v"]

    def shaped(self, key: str, soc) -> np.ndarray:
        a, k, b = self.shape[key]
        s = np.clip(soc, 0.0, 1.0)
        return 1.0 + a * (np.exp(-s / k) - math.exp(-0.5 / k)) + b * (s - 0.5) ** 2


# -- one simulation ----------------------------------------------------------------------

def _rc(a: np.ndarray, b: np.ndarray, x0: float = 0.0) -> np.ndarray:
    out = np.empty(a.size)
    x = x0
    for k in range(a.size):
        x = a[k] * x + b[k]
        out[k] = x
    return out


def _trapezoid(dt: np.ndarray, tau: np.ndarray, sub: int = 4) -> np.ndarray:
    """Per-sample decay of an RC pair from ``sub`` trapezoidal sub-steps."""
    h = dt / sub
    alpha = (1.0 - h / (2.0 * tau)) / (1.0 + h / (2.0 * tau))
    return alpha ** sub


def simulate(cell: Cell, t, i, soc0: float, temp_c, *, off=(), h0: float = 0.0,
             q_ah: float | None = None, ocv=None) -> dict:
    """Noise-free voltage of ``cell`` driven by current ``i`` (A, + charge), with the
    physics effects in ``off`` left out; ``q_ah`` and ``ocv`` replace the true capacity and
    OCV (what a model would use)."""
    t = np.asarray(t, dtype=np.float64)
    i = np.asarray(i, dtype=np.float64)
    temp = np.asarray(temp_c, dtype=np.float64)
    dt = np.diff(t, prepend=t[0])
    eff = {k: v for k, v in cell.effects.items() if k not in off}
    q = cell.q_true_ah if q_ah is None else q_ah
    soc = soc0 + np.cumsum(i * dt) / (3600.0 * q)
    arr = np.ones_like(t)
    if "temperature_dependence" in eff:
        arr = np.exp(eff["temperature_dependence"]["ea_j_per_mol"] / GAS
                     * (1.0 / (temp + 273.15) - 1.0 / T25))
    side = np.where(i > 0, 1.0 + 0.5 * cell.asym, 1.0 - 0.5 * cell.asym)
    r_ohm = cell.r["r_ohm"] * cell.shaped("r0", soc) * side * arr
    r_ct = cell.r["r_ct"] * cell.shaped("r0", soc) * side * arr
    if "current_dependent_resistance" in eff:
        i0 = eff["current_dependent_resistance"]["i0_a"]
        eta = 2.0 * r_ct * i0 * np.arcsinh(i / (2.0 * i0))
    else:
        eta = r_ct * i
    v = (cell.ocv(soc) if ocv is None else ocv(soc)) + r_ohm * i + eta
    for j, key in ((1, "r1"), (2, "r2")):
        tau = cell.r[f"tau{j}_s"] * (1.0 + 0.3 * (0.5 - np.clip(soc, 0, 1))) * arr
        rj = cell.r[key] * cell.shaped(key, soc) * side * arr
        a = _trapezoid(dt, tau)
        v = v + _rc(a, (1.0 - a) * rj * i)
    if "extra_rc" in eff:
        e = eff["extra_rc"]
        a = _trapezoid(dt, np.full_like(t, e["tau_s"]) * arr)
        r3 = e["r_ohm"] * cell.shaped("r2", soc) * arr
        v = v + _rc(a, (1.0 - a) * r3 * i)
    if "diffusion" in eff:
        e = eff["diffusion"]
        lam = SPHERE_ROOTS
        w = 2.0 / lam ** 2
        w = w / w.sum()
        x = np.zeros(lam.size)
        tot = np.empty(t.size)
        a_all = np.exp(-dt[:, None] * lam[None, :] ** 2 / e["tau_d_s"])
        for k in range(t.size):
            x = a_all[k] * x + (1.0 - a_all[k]) * i[k]
            tot[k] = w @ x
        v = v + e["r_ohm"] * cell.shaped("r1", soc) * tot
    if "hysteresis" in eff:
        # Plett's ESC form: h moves with the previous sample's current; the instantaneous
        # term follows the sign of the last current above Q/100
        e = eff["hysteresis"]
        sgn = np.sign(i) * (np.abs(i) > 1e-9)
        a = np.exp(-np.abs(i) * e["gamma"] * dt / (3600.0 * cell.q_true_ah))
        h = np.concatenate([[h0], _rc(a, (1.0 - a) * sgn, h0)[:-1]])
        last = np.where(np.abs(i) > cell.q_true_ah / 100.0, sgn, np.nan)
        last[0] = h0 if np.isnan(last[0]) else last[0]
        idx = np.where(np.isnan(last), 0, np.arange(last.size))
        np.maximum.accumulate(idx, out=idx)
        v = v + e["m_v"] * (1.0 + e["m_slope"] * (0.5 - soc)) * h + e["m0_v"] * last[idx]
    if "entropic_ocv" in eff:
        e = eff["entropic_ocv"]
        dudt = (e["e0"] + e["e1"] * np.cos(math.pi * soc) + e["e2"] * np.sin(2 * math.pi * soc))
        v = v + 1e-3 * dudt * (temp - 25.0)
    return {"v": v, "soc": soc}


def voltage_channel(cell: Cell, t, v, off=()) -> np.ndarray:
    """What the cycle's logger records of the cell voltage (a lagging channel)."""
    e = cell.effects.get("voltage_lag")
    if e is None or "voltage_lag" in off:
        return v
    if e["mode"] == "late":
        k = int(e["samples"])
        return np.concatenate([np.full(k, v[0]), v[:-k]])
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / e["tau_s"])
    return _rc(a, (1.0 - a) * v, v[0])


def current_channel(cell: Cell, i, off=()) -> np.ndarray:
    """What the cycle's logger records of the current (offset, gain; noise added later)."""
    out = np.array(i, dtype=np.float64)
    if "current_gain" in cell.effects and "current_gain" not in off:
        out = out * (1.0 + cell.effects["current_gain"]["gain"])
    if "current_offset" in cell.effects and "current_offset" not in off:
        out = out + cell.effects["current_offset"]["offset_a"]
    return out


# -- the records ---------------------------------------------------------------------------

def pulse_profile(cell: Cell, rng, quick: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The lab pulse test: rested full (after a charge), to each level 90 .. 10 % (by the
    nominal capacity) at C/3 and a rest, then a discharge and a charge pulse at each C-rate
    with rests. 0.1 s sampling in pulses and the 30 s after them, 1 s for 90 s, 2 s else."""
    qn = cell.q_nominal_ah
    rates = sorted(rng.choice([0.2, 0.33, 0.5, 1.0, 1.5, 2.0], size=int(rng.integers(3, 5)),
                              replace=False))
    if quick:
        rates = rates[-2:]
    pulse_s = float(rng.choice([10.0, 10.0, 18.0, 30.0]))
    rest_s = float(rng.uniform(300.0, 900.0))
    level_rest_s = float(rng.uniform(1800.0, 3600.0))
    ts, cur = [np.array([0.0])], [np.array([0.0])]
    now = [0.0]

    def seg(duration, amps, dt):
        n = max(1, int(round(duration / dt)))
        ts.append(now[0] + dt * np.arange(1, n + 1))
        cur.append(np.full(n, float(amps)))
        now[0] += n * dt

    def rest(duration):
        seg(30.0, 0.0, 0.1)
        seg(min(90.0, duration - 30.0), 0.0, 1.0)
        if duration > 120.0:
            seg(duration - 120.0, 0.0, 2.0)

    rest(level_rest_s)
    soc = 1.0
    for level in np.arange(0.9, 0.05, -0.2 if quick else -0.1):
        # the cycler stops a cell whose true capacity is below the nominal at its cut-off
        if 1.0 - (1.0 - level) * qn / cell.q_true_ah < 0.04:
            break
        seg((soc - level) * qn * 3600.0 / (qn / 3.0), -qn / 3.0, 2.0)
        soc = level
        rest(level_rest_s)
        for c in rates:
            for sign in (-1.0, 1.0):
                seg(pulse_s, sign * c * qn, 0.1)
                rest(rest_s)
    return np.concatenate(ts), np.concatenate(cur)


def _drive_block(rng, n: int, qn: float, style: str) -> np.ndarray:
    """One drive block of n 1-s samples: accelerations draw, braking regenerates."""
    out = np.zeros(n)
    k = 0
    while k < n:
        if style == "city":
            stop, go = int(rng.uniform(5, 40)), int(rng.uniform(20, 90))
            peak = rng.uniform(0.8, 2.5)
        elif style == "highway":
            stop, go = 0, int(rng.uniform(60, 240))
            peak = rng.uniform(0.5, 1.2)
        else:
            stop, go = int(rng.uniform(2, 15)), int(rng.uniform(15, 60))
            peak = rng.uniform(2.0, 4.0)
        k += stop
        m = min(go, n - k)
        if m <= 0:
            break
        x = np.linspace(0.0, 1.0, m)
        shape = np.where(x < 0.3, -peak * (0.4 + 2.0 * x),
                         np.where(x < 0.8, -0.35 * peak * (1 + 0.4 * np.sin(9 * x)),
                                  0.5 * peak * (x - 0.8) / 0.2 * rng.uniform(0.2, 0.9)))
        shape = shape + rng.normal(0.0, 0.08 * peak, m)
        out[k:k + m] = np.clip(shape, -4.0, 1.5) * qn
        k += m
    hold = np.repeat(out[::2], 2)[:n]          # a 2 Hz .. 1 Hz set point
    return hold


def cycle_profile(cell: Cell, rng, soc0: float, quick: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The drive record (true current): rest, drive blocks of 8-25 min with rests of
    3-30 min, a CC charge every few blocks, a final rest; 3-6 h, while the true SOC stays
    above 15 %."""
    qn, q = cell.q_nominal_ah, cell.q_true_ah
    dt = float(rng.choice([1.0, 1.0, 1.0, 0.5, 2.0]))
    parts = [np.zeros(int(rng.uniform(300, 1200) / dt))]
    soc = soc0
    target = rng.uniform(3.0, 6.0) * 3600.0 * (0.5 if quick else 1.0)
    total = parts[0].size * dt
    k = 0
    while total < target:
        k += 1
        n = int(rng.uniform(480, 1500))
        style = str(rng.choice(["city", "highway", "aggressive"], p=[0.45, 0.35, 0.2]))
        block = _drive_block(rng, n, qn, style) * rng.uniform(0.6, 1.0)
        block = np.repeat(block, 1) if dt == 1.0 else (
            np.repeat(block, 2) if dt == 0.5 else block[::2])
        used = -np.cumsum(block) * dt / 3600.0 / q
        if soc - used.max() < 0.15:
            stop = int(np.searchsorted(used, soc - 0.2))
            block = block[:max(stop, 1)]
        soc += float(np.sum(block) * dt / 3600.0 / q)
        parts.append(block)
        parts.append(np.zeros(int(rng.uniform(180, 1800) / dt)))
        if soc < 0.45 or (k % 3 == 0 and soc < 0.8):
            m = int(rng.uniform(600, 2400) / dt)
            c = rng.uniform(0.3, 1.0) * qn
            m = min(m, int((0.95 - soc) * q * 3600.0 / c / dt))
            if m > 60:
                parts.append(np.full(m, c))
                soc += c * m * dt / 3600.0 / q
                parts.append(np.zeros(int(rng.uniform(600, 2400) / dt)))
        total = sum(p.size for p in parts) * dt
    parts.append(np.zeros(int(rng.uniform(900, 1800) / dt)))
    i = np.concatenate(parts)
    return dt * np.arange(i.size, dtype=np.float64), i


def temperature(cell: Cell, t, i, rng, kind: str) -> np.ndarray:
    """Cell temperature: the chamber (25 degC, or a ramp on the temperature and entropic
    cells) plus first-order self-heating."""
    dt = np.diff(t, prepend=t[0])
    chamber = np.full(t.size, 25.0)
    e = cell.effects
    if kind == "cycle" and ("temperature_dependence" in e or "entropic_ocv" in e):
        ramp = e.get("temperature_dependence", e.get("entropic_ocv"))
        tc = ramp["ramp_tau_s"]
        chamber = 25.0 + ramp["delta_t_c"] * (1.0 - np.exp(-(t - t[0]) / tc))
        r_th = ramp["r_th_k_per_w"]
    else:
        r_th = 0.5
    c_th = 15.0 * cell.q_true_ah              # J/K: about 45 J/K for an 18650
    r = cell.r["r_ohm"] + cell.r["r_ct"] + cell.r["r1"] + cell.r["r2"]
    a = np.exp(-dt / (r_th * c_th))
    rise = _rc(a, (1.0 - a) * r_th * r * i * i)
    return chamber + rise


# -- drawing a cell ---------------------------------------------------------------------------

def draw_cell(rng) -> Cell:
    chem = "lfp" if rng.uniform() < 0.3 else "nmc"
    q = float(math.exp(rng.uniform(math.log(2.0), math.log(60.0))))
    if chem == "lfp":
        coef = {"e0": rng.uniform(3.26, 3.30), "slope": rng.uniform(0.03, 0.07),
                "s1": rng.uniform(0.008, 0.02), "m1": rng.uniform(0.2, 0.4),
                "s2": rng.uniform(0.01, 0.025), "m2": rng.uniform(0.55, 0.7),
                "knee": rng.uniform(0.3, 0.5), "top": rng.uniform(0.08, 0.2)}
    else:
        coef = {"e0": rng.uniform(3.45, 3.6), "slope": rng.uniform(0.45, 0.6),
                "curv": rng.uniform(-0.05, 0.1), "log": rng.uniform(0.03, 0.06),
                "bump": rng.uniform(0.0, 0.03), "m1": rng.uniform(0.3, 0.7),
                "knee": rng.uniform(0.1, 0.3)}
    r0q = rng.uniform(0.03, 0.08)                  # ohm Ah
    r0 = r0q / q
    frac_ct = rng.uniform(0.2, 0.4)
    r = {"r_ohm": r0 * (1 - frac_ct), "r_ct": r0 * frac_ct,
         "r1": r0 * rng.uniform(0.3, 0.8), "tau1_s": rng.uniform(0.6, 5.0),
         "r2": r0 * rng.uniform(0.3, 1.0), "tau2_s": rng.uniform(15.0, 90.0)}
    shape = {key: (rng.uniform(0.3, 1.0), rng.uniform(0.08, 0.2), rng.uniform(0.05, 0.4))
             for key in ("r0", "r1", "r2")}
    noise = float(rng.uniform(0.3e-3, 1.5e-3))
    return Cell(chem=chem, q_true_ah=q, q_nominal_ah=q, ocv_coef=coef, r=r, shape=shape,
                asym=float(rng.uniform(-0.08, 0.08)), noise_v=noise, lsb_v=1e-4,
                noise_a=2e-4 * q)


def draw_effect(name: str, cell: Cell, rng) -> dict:
    """Parameters of one effect, at a realistic size (scaled up later where too small)."""
    r0 = cell.r["r_ohm"] + cell.r["r_ct"]
    q = cell.q_true_ah
    if name == "hysteresis":
        lfp = cell.chem == "lfp"
        return {"m_v": rng.uniform(0.01, 0.03) if lfp else rng.uniform(0.005, 0.02),
                "m_slope": rng.uniform(0.0, 0.8), "m0_v": rng.uniform(0.0, 0.004),
                "gamma": float(math.exp(rng.uniform(math.log(15), math.log(200))))}
    if name == "extra_rc":
        return {"r_ohm": r0 * rng.uniform(0.5, 1.5), "tau_s": rng.uniform(200.0, 1500.0)}
    if name == "current_dependent_resistance":
        cell.r["r_ct"] = r0 * rng.uniform(0.5, 0.8)
        cell.r["r_ohm"] = r0 - cell.r["r_ct"]
        return {"i0_a": q * rng.uniform(0.1, 0.6)}
    if name == "capacity_error":
        return {"q_true_over_nominal": 1.0 + rng.choice([-1, 1]) * rng.uniform(0.05, 0.15)}
    if name == "temperature_dependence":
        return {"ea_j_per_mol": rng.uniform(20e3, 50e3),
                "delta_t_c": rng.choice([-1, 1]) * rng.uniform(10.0, 22.0),
                "ramp_tau_s": rng.uniform(3000.0, 15000.0), "r_th_k_per_w": rng.uniform(1, 4)}
    if name == "entropic_ocv":
        return {"e0": rng.uniform(-0.3, 0.1), "e1": rng.uniform(-0.3, 0.3),
                "e2": rng.uniform(-0.2, 0.2), "delta_t_c": rng.choice([-1, 1])
                * rng.uniform(10.0, 20.0), "ramp_tau_s": rng.uniform(3000.0, 12000.0),
                "r_th_k_per_w": rng.uniform(2, 6)}
    if name == "diffusion":
        return {"r_ohm": r0 * rng.uniform(0.5, 1.5),
                "tau_d_s": float(math.exp(rng.uniform(math.log(1500), math.log(15000))))}
    if name == "current_offset":
        return {"offset_a": rng.choice([-1, 1]) * q * rng.uniform(0.004, 0.02)}
    if name == "current_gain":
        return {"gain": rng.choice([-1, 1]) * rng.uniform(0.02, 0.06)}
    if name == "voltage_lag":
        if rng.uniform() < 0.5:
            return {"mode": "lowpass", "tau_s": rng.uniform(0.5, 3.0)}
        return {"mode": "late", "samples": 1}
    if name == "ocv_error":
        which = rng.choice(["offset", "scale", "both"])
        return {"offset_v": (rng.choice([-1, 1]) * rng.uniform(0.003, 0.01)
                             if which != "scale" else 0.0),
                "soc_scale": (1.0 + rng.choice([-1, 1]) * rng.uniform(0.03, 0.1)
                              if which != "offset" else 1.0)}
    raise ValueError(name)


MAGNITUDE = {"hysteresis": ("m_v", 0.06), "extra_rc": ("r_ohm", None),
             "current_dependent_resistance": None, "capacity_error": None,
             "temperature_dependence": ("ea_j_per_mol", 65e3),
             "entropic_ocv": (("e0", "e1", "e2"), 3.0), "diffusion": ("r_ohm", None),
             "current_offset": ("offset_a", None), "current_gain": ("gain", 0.1),
             "voltage_lag": None, "ocv_error": None}


# -- one case -------------------------------------------------------------------------------

@dataclass
class Case:
    cell: Cell
    kind: str
    effects: tuple
    seed: int
    soc0: float
    h0_pulses: float
    h0_cycle: float


def _cycle_views(case: Case, t, i_true, temp):
    """The logged cycle voltage (noise-free) and, per effect, what a perfect model without
    that effect predicts from the logged data."""
    cell = case.cell
    i_log = current_channel(cell, i_true)
    truth = simulate(cell, t, i_true, case.soc0, temp, h0=case.h0_cycle)["v"]
    v_log = voltage_channel(cell, t, truth)
    views = {}
    for e in case.effects:
        i_drive = i_log if e in ("current_offset", "current_gain") else i_true
        if e in ("current_offset", "current_gain"):
            i_drive = current_channel(cell, i_true, off=tuple(x for x in case.effects
                                                              if x != e))
        kw = {}
        if e == "capacity_error":
            kw["q_ah"] = cell.q_nominal_ah
        if e == "ocv_error":
            kw["ocv"] = cell.ocv_given
        v = simulate(cell, t, i_drive, case.soc0, temp, off=(e,), h0=case.h0_cycle, **kw)["v"]
        views[e] = voltage_channel(cell, t, v, off=(e,))
    return v_log, i_log, views


def make_case(seed: int, effects: tuple[str, ...], max_draws: int = 40, quick: bool = False
              ) -> tuple[Case, dict]:
    """A cell with ``effects`` each at least max(4 mV, 4 sigma) on the cycle (mean |dv|):
    a drawn effect that is smaller is scaled up (within what is plausible), else redrawn.
    ``quick``: half the cycle, half the pulse levels and two C-rates (for tests)."""
    for draw in range(max_draws):
        rng = np.random.default_rng([seed, draw])
        cell = draw_cell(rng)
        for e in effects:
            cell.effects[e] = draw_effect(e, cell, rng)
        if "capacity_error" in effects:
            cell.q_nominal_ah = cell.q_true_ah / cell.effects["capacity_error"][
                "q_true_over_nominal"]
        soc0 = float(rng.uniform(0.7, 1.0))
        case = Case(cell, "+".join(effects) or "none", tuple(effects), seed, soc0,
                    h0_pulses=1.0, h0_cycle=float(rng.choice([-1.0, 1.0])))
        t, i = cycle_profile(cell, rng, soc0, quick)
        temp = temperature(cell, t, i, rng, "cycle")
        need = max(4e-3, 4.0 * cell.noise_v)
        for _ in range(5):
            v_log, _, views = _cycle_views(case, t, i, temp)
            sizes = {e: float(np.mean(np.abs(v_log - views[e]))) for e in effects}
            small = [e for e in effects if sizes[e] < need]
            if not small:
                return case, {"t": t, "i": i, "temp": temp, "sizes": sizes, "draws": draw + 1,
                              "quick": quick}
            if not _grow(cell, small, sizes, need):
                break
    raise RuntimeError(f"seed {seed}: no draw of {effects} reaches the size")


def _grow(cell: Cell, small, sizes, need) -> bool:
    """Scale up the effects that are too small; False where that leaves what is plausible."""
    r0 = cell.r["r_ohm"] + cell.r["r_ct"]
    for e in small:
        p = cell.effects[e]
        f = 1.25 * need / max(sizes[e], 1e-6)
        if e == "voltage_lag":
            if p["mode"] == "late":
                p["samples"] += 1
                if p["samples"] > 3:
                    return False
            else:
                p["tau_s"] *= f
                if p["tau_s"] > 5.0:
                    return False
            continue
        if e == "current_dependent_resistance":
            p["i0_a"] /= f
            if p["i0_a"] < 0.03 * cell.q_true_ah:
                return False
            continue
        spec = MAGNITUDE[e]
        if spec is None:
            return False
        keys, cap = spec
        keys = (keys,) if isinstance(keys, str) else keys
        for k in keys:
            p[k] *= f
        if cap is not None and max(abs(p[k]) for k in keys) > cap:
            return False
        if e in ("extra_rc", "diffusion") and p["r_ohm"] > 3.0 * r0:
            return False
        if e == "current_offset" and abs(p["offset_a"]) > 0.05 * cell.q_true_ah:
            return False
    return True


def write_case(case: Case, extra: dict, folder: Path) -> None:
    cell = case.cell
    rng = np.random.default_rng([case.seed, 7919])
    folder.mkdir(parents=True, exist_ok=True)
    # pulse test (lab channels: no logger fault)
    tp, ip = pulse_profile(cell, rng, extra.get("quick", False))
    temp_p = temperature(cell, tp, ip, rng, "pulses")
    vp = simulate(cell, tp, ip, 1.0, temp_p, h0=case.h0_pulses)["v"]
    _write_series(folder / "pulses.csv", tp, ip + _noise_a(cell, ip, rng),
                  _noise_v(cell, vp, rng), temp_p + rng.normal(0, 0.05, tp.size))
    # the OCV table the user has (the mean of the branches; off in an ocv_error cell)
    soc = np.linspace(0.0, 1.0, 101)
    ocv = cell.ocv_given(soc)
    (folder / "ocv.csv").write_text("soc,ocv_v\n" + "".join(
        f"{s:.2f},{v:.5f}\n" for s, v in zip(soc, ocv)))
    # the drive record
    t, i, temp = extra["t"], extra["i"], extra["temp"]
    v_log, i_log, _ = _cycle_views(case, t, i, temp)
    _write_series(folder / "cycle.csv", t, i_log + _noise_a(cell, i_log, rng),
                  _noise_v(cell, v_log, rng), temp + rng.normal(0, 0.05, t.size))
    (folder / "case.toml").write_text(
        f"[cell]\ncapacity_ah = {cell.q_nominal_ah:.4g}\n[data]\npulses = \"pulses.csv\"\n"
        f"ocv = \"ocv.csv\"\ncycle = \"cycle.csv\"\nsoc0 = {case.soc0:.3f}\n")
    truth = {"effects": list(case.effects), "kind": case.kind, "seed": case.seed,
             "params": {e: cell.effects[e] for e in case.effects},
             "mean_abs_effect_v": extra["sizes"], "noise_v": cell.noise_v,
             "chem": cell.chem, "q_true_ah": cell.q_true_ah,
             "q_nominal_ah": cell.q_nominal_ah, "r": cell.r, "soc0": case.soc0,
             "h0_pulses": case.h0_pulses, "h0_cycle": case.h0_cycle,
             "cycle_s": float(t[-1]), "cycle_dt_s": float(t[1] - t[0]),
             "draws": extra["draws"], "generator": "bench/diagnose_cells.py 1"}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1, default=float))


def _noise_v(cell: Cell, v, rng) -> np.ndarray:
    return np.round((v + rng.normal(0.0, cell.noise_v, v.size)) / cell.lsb_v) * cell.lsb_v


def _noise_a(cell: Cell, i, rng) -> np.ndarray:
    return rng.normal(0.0, cell.noise_a, np.size(i))


def _write_series(path: Path, t, i, v, temp) -> None:
    rows = "".join(f"{a:.1f},{b:.5g},{c:.4f},{d:.2f}\n" for a, b, c, d in zip(t, i, v, temp))
    path.write_text("time_s,current_a,voltage_v,temperature_c\n" + rows)


def plan(half: str, per_kind: int, kinds=None, pairs: int | None = None,
         controls: int | None = None, first_seed: int | None = None
         ) -> list[tuple[str, int, tuple]]:
    """(folder name, seed, effects) of every cell of a half (``first_seed``: another
    unseen set, from that seed on)."""
    first = first_seed if first_seed is not None else DEV_SEED if half == "dev" else HELD_SEED
    out = []
    n = 0
    for kind in kinds or KINDS:
        for k in range(per_kind):
            out.append((f"{kind}-{k}", first + n, (kind,)))
            n += 1
    if kinds is None:
        for k in range(per_kind if pairs is None else pairs):
            a, b = PAIRS[k % len(PAIRS)]
            out.append((f"pair-{k}-{a}+{b}", first + n, (a, b)))
            n += 1
        for k in range(per_kind if controls is None else controls):
            out.append((f"none-{k}", first + n, ()))
            n += 1
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--half", choices=("dev", "held"), required=True)
    ap.add_argument("--per-kind", type=int, default=4)
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--controls", type=int, default=6)
    ap.add_argument("--kinds", help="comma-separated subset of the single kinds (no pairs, "
                                    "no controls)")
    ap.add_argument("--only", help="comma-separated folder names to (re)write")
    ap.add_argument("--first-seed", type=int, help="the first seed (default: the half's): a "
                                                    "set no one has looked at yet")
    args = ap.parse_args(argv)
    kinds = args.kinds.split(",") if args.kinds else None
    out = Path(args.out)
    only = set(args.only.split(",")) if args.only else None
    for name, seed, effects in plan(args.half, args.per_kind, kinds, args.pairs, args.controls,
                                    args.first_seed):
        if only and name not in only:
            continue
        case, extra = make_case(seed, effects)
        write_case(case, extra, out / name)
        sizes = ", ".join(f"{e} {1e3 * s:.1f} mV" for e, s in extra["sizes"].items())
        print(f"{name:40s} seed {seed} {case.cell.chem} Q {case.cell.q_true_ah:5.1f} Ah "
              f"noise {1e3 * case.cell.noise_v:.2f} mV  {sizes}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
