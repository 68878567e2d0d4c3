"""Synthetic cells with a hidden effect, for testing ``diagnose``.

A :class:`SyntheticCell` holds a hidden "true" model (a 2RC base plus at most one
effect from :mod:`ecmgen.model.effects`), a first-order thermal model and a noise model. It
produces the three records a cell test gives -- a pulse test, a low-rate OCV test and a
drive cycle with rests -- by simulating the hidden model (with
:func:`ecmgen.model.simulate.simulate`) and adding measurement noise. :meth:`base_model`
then builds the model the usual method would get from those records: OCV from the mean
of the low-rate branches, 2RC parameters per SOC level from 10 s pulses (plus a short
relaxation), and the nominal capacity. What the base model misses is the hidden effect.

    cell = random_cell(seed=3, effect="extra_rc")
    base = cell.base_model()
    cycle = cell.drive_cycle()
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..data.measure import TimeSeries
from ..data.ocv import OcvTable
from ..model import effects as fx
from ..model.model import EcmModel, RcTable
from ..model.rc import rc_recurrence
from ..model.simulate import simulate

SOC_GRID = np.linspace(0.0, 1.0, 101)


def nca_like_ocv(soc: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """A smooth NCA-like OCV curve (3.0 .. 4.2 V), strictly increasing."""
    s = np.asarray(soc, dtype=np.float64)
    return (3.25 + shift + 0.85 * s + 0.12 * (1 - np.exp(-12 * s)) - 0.05 * np.sin(math.pi * s)
            + 0.06 * s ** 6)


def lfp_like_ocv(soc: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """An LFP-like OCV curve (2.75 .. 3.55 V): steep knees below 5 % and above 97 % SOC,
    two flat plateaus (about 0.6 mV per % SOC) with a 50 mV step near 60 %."""
    s = np.asarray(soc, dtype=np.float64)
    return (3.22 + shift + 0.06 * s + 0.025 * np.tanh((s - 0.6) / 0.03)
            - 0.45 * np.exp(-s / 0.025) + 0.25 * np.exp(-(1.0 - s) / 0.02))


@dataclass(frozen=True)
class SyntheticCell:
    """A hidden cell model plus how it is measured.

    hidden        the true model, incl. its hidden effect (if any)
    effect        name of the hidden effect, or None
    ambient_c     chamber temperature, degC
    r_th_k_per_w, c_th_j_per_k   first-order thermal model (heat = i^2 * r_total)
    noise_v, noise_a, noise_c    Gaussian measurement noise (std)
    lsb_v         voltage quantisation, V
    seed          seed of the noise and of the drive profile
    """

    hidden: EcmModel
    effect: str | None
    ambient_c: float = 25.0
    r_th_k_per_w: float = 8.0
    c_th_j_per_k: float = 120.0
    noise_v: float = 1.0e-3
    noise_a: float = 5.0e-3
    noise_c: float = 0.05
    lsb_v: float = 1.0e-4
    seed: int = 0

    # -- helpers ---------------------------------------------------------------------------
    @property
    def capacity_ah(self) -> float:
        """Nominal capacity (what the base model is given)."""
        return self.hidden.capacity_ah

    @property
    def true_capacity_ah(self) -> float:
        return self.hidden.capacity_ah * fx.capacity_factor(self.hidden.effects)

    def _temperature(self, t: np.ndarray, i: np.ndarray, t0: float | None = None) -> np.ndarray:
        """Cell temperature from the first-order thermal model, exact ZOH per step."""
        dt = np.diff(t, prepend=t[0])
        tab = self.hidden.discharge
        r = float(np.mean(tab.r0_ohm + tab.r_fast_ohm + tab.r_slow_ohm))
        tau = self.r_th_k_per_w * self.c_th_j_per_k
        a = np.exp(-dt / tau)
        rise = rc_recurrence(a, (1 - a) * self.r_th_k_per_w * r * i * i,
                             0.0 if t0 is None else t0 - self.ambient_c)
        return self.ambient_c + rise

    def _measure(self, t, i, soc0, rng, name: str, with_temperature=True) -> TimeSeries:
        t = np.asarray(t, dtype=np.float64)
        i = np.asarray(i, dtype=np.float64)
        temp = self._temperature(t, i)
        sim = simulate(self.hidden, t, i, soc0, temp)
        v = sim.voltage_v + rng.normal(0.0, self.noise_v, t.size)
        v = np.round(v / self.lsb_v) * self.lsb_v
        i_meas = i + rng.normal(0.0, self.noise_a, t.size) * (np.abs(i) > 0)
        temp_meas = np.round((temp + rng.normal(0.0, self.noise_c, t.size)) * 10) / 10
        return TimeSeries(t, i_meas, v, temp_meas if with_temperature else None, None,
                          f"synthetic:{name}")

    # -- records -----------------------------------------------------------------------------
    def pulse_test(self, levels=(0.95, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1),
                   c_rates_discharge=(0.5, 1.0, 2.0, 4.0), c_rates_charge=(0.5, 1.0, 2.0),
                   pulse_s: float = 10.0, rest_s: float = 600.0, seed: int | None = None,
                   soc_start: float = 1.0) -> TimeSeries:
        """Discharge and charge pulses at each SOC level (true SOC) below ``soc_start``,
        starting rested at ``soc_start`` (default full); the SOC moves between levels by
        C/2 discharges followed by 30 min rests. 0.1 s sampling in pulses and the first
        30 s after them, 2 s in rests."""
        rng = np.random.default_rng(self.seed + 11 if seed is None else seed)
        q = self.true_capacity_ah
        qn = self.capacity_ah
        ts: list[np.ndarray] = [np.array([0.0])]
        cur: list[np.ndarray] = [np.array([0.0])]
        now = [0.0]

        def seg(duration, amps, dt):
            n = max(1, int(round(duration / dt)))
            ts.append(now[0] + dt * np.arange(1, n + 1))
            cur.append(np.full(n, float(amps)))
            now[0] += n * dt

        seg(1800.0, 0.0, 10.0)
        soc = soc_start
        for level in (x for x in levels if x <= soc_start + 1e-9):
            move = soc - level
            if move > 0:
                seg(move * q * 3600.0 / (0.5 * qn), -0.5 * qn, 5.0)
                seg(1800.0, 0.0, 10.0)
                soc = level
            for sign, rates in ((-1.0, c_rates_discharge), (1.0, c_rates_charge)):
                for c in rates:
                    seg(pulse_s, sign * c * qn, 0.1)
                    seg(30.0, 0.0, 0.1)
                    seg(rest_s - 30.0, 0.0, 2.0)
                    soc += sign * c * qn * pulse_s / 3600.0 / q
        t = np.concatenate(ts)
        i = np.concatenate(cur)
        return self._measure(t, i, soc_start, rng, "pulses")

    def ocv_test(self, c_rate: float = 0.05, dt: float = 10.0, seed: int | None = None
                 ) -> TimeSeries:
        """C/20 discharge from full to empty (true SOC), 1 h rest, C/20 charge to full."""
        rng = np.random.default_rng(self.seed + 13 if seed is None else seed)
        q = self.true_capacity_ah
        amps = c_rate * self.capacity_ah
        n = int(math.ceil(q * 3600.0 / amps / dt))
        last = q * 3600.0 / amps - (n - 1) * dt     # the last step ends exactly at SOC 0
        d = np.concatenate([np.full(n - 1, dt), [last]])
        t = np.concatenate([[0.0, 1800.0], 1800.0 + np.cumsum(d)])
        i = np.concatenate([[0.0, 0.0], np.full(n, -amps)])
        rest = t[-1] + dt * np.arange(1, 61)
        t = np.concatenate([t, rest, rest[-1] + np.cumsum(d)])
        i = np.concatenate([i, np.zeros(60), np.full(n, amps)])
        return self._measure(t, i, 1.0, rng, "ocv")

    def drive_cycle(self, soc_start: float = 0.95, soc_end: float = 0.12, seed: int | None = None,
                    dt: float = 1.0, with_temperature: bool = True, mean_c_rate: float = 0.8
                    ) -> TimeSeries:
        """A drive cycle with rests: 10 min rest, then until the SOC reaches ``soc_end``:
        drive segments of 8-20 min (random, mean about -``mean_c_rate`` C, peaks -4 C ..
        +1.5 C of regeneration), rests of 4-12 min, and every third segment a 0.5 C charge
        of 6-12 min; 15 min rest at the end. Starts rested at ``soc_start`` (true SOC)
        after a charge. About 3 h at the default rate."""
        rng = np.random.default_rng(self.seed + 17 if seed is None else seed)
        qn = self.capacity_ah
        q = self.true_capacity_ah
        cur = [np.zeros(int(600 / dt))]
        soc = soc_start
        k = 0
        while soc > soc_end + 0.03:
            k += 1
            n = int(rng.uniform(480, 1200) / dt)
            x = np.zeros(n)
            e = rng.normal(0, 1, n)
            phi = math.exp(-dt / 15.0)
            for j in range(1, n):
                x[j] = phi * x[j - 1] + math.sqrt(1 - phi * phi) * e[j]
            amps = qn * np.clip(-mean_c_rate + 1.1 * x, -4.0, 1.5)
            # hold each value 1..4 s like a speed trace at 1 Hz with gear changes
            hold = rng.integers(1, 5, n)
            idx = np.minimum(np.cumsum(hold) - hold, n - 1)
            amps = np.repeat(amps[idx], hold)[:n]
            # limit the segment to the SOC left
            used = -np.cumsum(amps) * dt / 3600.0 / q
            stop = int(np.searchsorted(used, soc - soc_end)) if used[-1] > soc - soc_end else n
            amps = amps[:max(stop, 1)]
            soc -= float(-np.sum(amps) * dt / 3600.0 / q)
            cur.append(amps)
            cur.append(np.zeros(int(rng.uniform(240, 720) / dt)))
            if k % 3 == 2 and soc < soc_start - 0.2:
                m = int(rng.uniform(360, 720) / dt)
                cur.append(np.full(m, 0.5 * qn))
                soc += 0.5 * qn * m * dt / 3600.0 / q
                cur.append(np.zeros(int(rng.uniform(240, 720) / dt)))
        cur.append(np.zeros(int(900 / dt)))
        i = np.concatenate(cur)
        t = dt * np.arange(i.size, dtype=np.float64)
        return self._measure(t, i, soc_start, rng, "drive", with_temperature)

    # -- the base model the 10 s-pulse method would fit ------------------------------------
    def base_model(self, pulses: TimeSeries | None = None, ocv: TimeSeries | None = None,
                   relax_s: float = 30.0) -> EcmModel:
        pulses = self.pulse_test() if pulses is None else pulses
        ocv = self.ocv_test() if ocv is None else ocv
        table = ocv_from_branches(ocv)
        ch, dis = fit_pulses(pulses, table, self.capacity_ah, relax_s=relax_s)
        return EcmModel(capacity_ah=self.capacity_ah, ocv=table, charge=ch, discharge=dis,
                        method="synthetic-pulses", seed=self.seed,
                        direction_deadband_a=0.01 * self.capacity_ah)


def ocv_from_branches(series: TimeSeries) -> OcvTable:
    """OCV = mean of the low-rate discharge and charge branches, SOC from the Ah of the
    discharge (its own capacity), on a 101-point grid."""
    t, i, v = series.time_s, series.current_a, series.voltage_v
    dt = np.diff(t, prepend=t[0])
    q = np.cumsum(i * dt) / 3600.0
    dis, chg = i < -1e-3, i > 1e-3
    cap = -q[dis].min()
    soc = 1.0 + q / cap
    sd, vd_raw = soc[dis][::-1], v[dis][::-1]
    sc = soc[chg] - soc[chg][0] + soc[dis][-1]
    vd = _smooth_on_grid(sd, vd_raw)
    vc = _smooth_on_grid(sc, v[chg])
    ocv = 0.5 * (vd + vc)
    for k in range(1, ocv.size):              # strictly increasing (noise at the ends)
        ocv[k] = max(ocv[k], ocv[k - 1] + 1e-6)
    return OcvTable(SOC_GRID.copy(), ocv)


def _smooth_on_grid(soc: np.ndarray, v: np.ndarray, half_width: float = 0.01) -> np.ndarray:
    """Local linear fit of v(soc) within +-half_width around each grid point."""
    out = np.empty(SOC_GRID.size)
    for k, g in enumerate(SOC_GRID):
        w = np.abs(soc - g) <= half_width
        if w.sum() >= 3:
            c = np.polyfit(soc[w] - g, v[w], 1)
            out[k] = c[1]
        else:
            out[k] = np.interp(g, soc, v)
    return out


def fit_pulses(series: TimeSeries, ocv: OcvTable, capacity_ah: float, relax_s: float = 30.0,
               min_a: float | None = None, soc0: float = 1.0) -> tuple[RcTable, RcTable]:
    """2RC tables from a pulse test, the common DC-IR practice: each pulse (with
    ``relax_s`` of relaxation) is fitted on its own, and the parameters of the pulses of
    one pulse set (same direction, consecutive, within 4 % SOC) are averaged over their
    C-rates. A direction without pulses gets the other direction's table. The test
    starts at ``soc0``; SOC from the logged Ah where the record has it."""
    t, i, v = series.time_s, series.current_a, series.voltage_v
    min_a = 0.1 * capacity_ah if min_a is None else min_a
    on = np.abs(i) > min_a
    edges = np.flatnonzero(on[1:] & ~on[:-1]) + 1
    soc_all = soc0 + series.coulomb_ah() / capacity_ah
    sets: list[tuple[str, float, list]] = []
    for e in edges:
        end = e
        while end < i.size and on[end]:
            end += 1
        if t[end - 1] - t[e] > 60.0:            # an SOC move, not a pulse
            continue
        stop = int(np.searchsorted(t, t[end - 1] + relax_s, side="right"))
        stop = min(stop, int(edges[edges > e][0]) if np.any(edges > e) else stop)
        a = e - 1
        w_dt = np.diff(t[a:stop] - t[a], prepend=0.0)
        w_i = np.where(np.abs(i[a:stop]) > min_a, i[a:stop], 0.0)
        soc = soc_all[a] + np.cumsum(w_i * w_dt) / 3600.0 / capacity_ah
        target = v[a:stop] - v[a] - (ocv.ocv_at(soc) - ocv.ocv_at(soc_all[a]))
        direction = "charge" if i[e] > 0 else "discharge"
        if not sets or sets[-1][0] != direction or abs(sets[-1][1] - soc_all[a]) > 0.04:
            sets.append((direction, float(soc_all[a]), []))
        sets[-1][2].append((float(soc_all[a]),) + _fit_pulse(w_dt, w_i, target))
    rows: dict[str, list] = {"charge": [], "discharge": []}
    for direction, _, f in sets:
        x = np.array([r[1] for r in f])
        rows[direction].append((float(np.mean([r[0] for r in f])), *np.mean(x, axis=0),
                                float(np.mean([r[2] for r in f])), all(r[3] for r in f)))
    tables = {}
    for d, r in rows.items():
        if not r:
            continue
        r.sort()
        a = np.array([x[:7] for x in r], dtype=np.float64)
        keep = np.concatenate([[True], np.diff(a[:, 0]) > 1e-6])
        a = a[keep]
        tables[d] = RcTable(soc=np.clip(a[:, 0], 0, 1), r0_ohm=a[:, 1], r_fast_ohm=a[:, 2],
                            tau_fast_s=a[:, 3], r_slow_ohm=a[:, 4], tau_slow_s=a[:, 5],
                            fit_error=a[:, 6], converged=np.array([x[7] for x in r])[keep])
    if not tables:
        raise ValueError(f"{series.source}: no pulses found")
    return tables.get("charge", tables.get("discharge")), \
        tables.get("discharge", tables.get("charge"))


def _fit_pulse(dt: np.ndarray, i: np.ndarray, target: np.ndarray):
    """(r0, r_fast, tau_fast, r_slow, tau_slow), rms error, success for one pulse window:
    variable projection (non-negative resistances by NNLS for given time constants; the
    two time constants from a log grid, refined by least squares)."""
    from scipy.optimize import least_squares, nnls

    def solve(x):
        tf, ts = np.exp(x)
        af, as_ = np.exp(-dt / tf), np.exp(-dt / ts)
        X = np.column_stack([i, rc_recurrence(af, (1 - af) * i), rc_recurrence(as_, (1 - as_) * i)])
        r, _ = nnls(X, target)
        return r, X @ r - target

    best = None
    for tf in np.geomspace(0.05, 5.0, 6):
        for ts in np.geomspace(2.0, 200.0, 6):
            if ts < 2 * tf:
                continue
            x = np.log([tf, ts])
            c = float(np.sum(solve(x)[1] ** 2))
            if best is None or c < best[0]:
                best = (c, x)
    lo, hi = np.log([0.02, 1.0]), np.log([10.0, 300.0])
    sol = least_squares(lambda x: solve(x)[1], np.clip(best[1], lo + 1e-9, hi - 1e-9),
                        bounds=(lo, hi), method="trf", max_nfev=40)
    r, res = solve(sol.x)
    tf, ts = np.exp(sol.x)
    if tf > ts:
        tf, ts, r = ts, tf, r[[0, 2, 1]]
    params = np.array([max(r[0], 1e-6), max(r[1], 1e-7), tf, max(r[2], 1e-7), ts])
    return params, math.sqrt(float(np.mean(res ** 2))), bool(sol.status > 0)


def random_base(rng: np.random.Generator, capacity_ah: float | None = None,
                chemistry: str = "nca") -> EcmModel:
    """A random, plausible 2RC model (no effects), with an NCA-like or (``chemistry`` =
    "lfp") an LFP-like OCV."""
    q = float(rng.uniform(2.4, 3.4)) if capacity_ah is None else capacity_ah
    soc = np.linspace(0.0, 1.0, 11)
    shape = {"nca": nca_like_ocv, "lfp": lfp_like_ocv}[chemistry]
    ocv = OcvTable(SOC_GRID.copy(), shape(SOC_GRID, float(rng.uniform(-0.05, 0.05))))
    scale = 2.9 / q
    r0 = scale * rng.uniform(0.015, 0.025) * (1 + 0.6 * (1 - soc) ** 3)
    rf = scale * rng.uniform(0.006, 0.012) * (1 + 0.5 * (1 - soc) ** 2)
    tf = np.full(soc.size, rng.uniform(0.6, 2.0))
    rs = scale * rng.uniform(0.006, 0.012) * (1 + 0.8 * (1 - soc) ** 2)
    ts = np.full(soc.size, rng.uniform(8.0, 20.0))

    def table(k):
        return RcTable(soc=soc, r0_ohm=k * r0, r_fast_ohm=k * rf, tau_fast_s=tf,
                       r_slow_ohm=k * rs, tau_slow_s=ts, fit_error=np.zeros(soc.size),
                       converged=np.ones(soc.size, bool))

    return EcmModel(capacity_ah=q, ocv=ocv, charge=table(0.92), discharge=table(1.0),
                    method="hidden", seed=None, direction_deadband_a=0.01 * q)


def random_effect(name: str, base: EcmModel, rng: np.random.Generator, ambient_c: float = 25.0):
    """A hidden effect of a clearly visible (but realistic) size."""
    q = base.capacity_ah
    r_tot = float(np.mean(base.discharge.r0_ohm + base.discharge.r_fast_ohm
                          + base.discharge.r_slow_ohm))
    if name == fx.Hysteresis.name:
        return fx.Hysteresis(m_v=float(rng.uniform(0.012, 0.025)),
                             decay_ah=float(rng.uniform(0.03, 0.08)) * q,
                             m0_v=float(rng.uniform(0.0, 0.004)), ocv_table_state=0.0,
                             initial_state=1.0)
    if name == fx.CurrentDependentResistance.name:
        return fx.CurrentDependentResistance(scale_at_zero=float(rng.uniform(1.1, 1.3)),
                                             i0_a=float(rng.uniform(0.6, 1.2)) * q)
    if name == fx.ExtraRc.name:
        return fx.ExtraRc(r_ohm=float(rng.uniform(0.5, 1.0)) * r_tot,
                          tau_s=float(rng.uniform(300.0, 1200.0)))
    if name == fx.CapacityError.name:
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        return fx.CapacityError(capacity_scale=1.0 + sign * float(rng.uniform(0.05, 0.09)))
    if name == fx.TemperatureDependence.name:
        return fx.TemperatureDependence(activation_k=float(rng.uniform(3500.0, 5500.0)),
                                        t_ref_c=ambient_c)
    raise ValueError(f"unknown effect {name!r}")


def random_cell(seed: int, effect: str | None = None, chemistry: str = "nca",
                effect_options: dict | None = None, **kw) -> SyntheticCell:
    """A random cell with at most one hidden effect (``effect`` = its name or None);
    ``effect_options`` replace fields of the drawn effect (e.g. the hysteresis's
    ``initial_state``)."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    base = random_base(rng, chemistry=chemistry)
    effects = () if effect is None else (random_effect(effect, base, rng),)
    if effect_options:
        effects = tuple(replace(e, **effect_options) for e in effects)
    return SyntheticCell(hidden=base.with_effects(effects), effect=effect, seed=seed, **kw)
