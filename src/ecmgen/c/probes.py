"""Probe vectors: golden-vector segments that read every table entry of the generated C.

A drive cycle stays in a narrow band of its tables (the demo's cycles reach SOC 0.5-0.9 at
one temperature), so a wrong entry elsewhere passed the golden check. These segments visit
every segment of every grid - SOC of each direction's RC table, SOC of the OCV, the
temperature rows, the age breakpoints and the fixed-point asinh(x)/x tables - 0.9 of the
way along it (and the first SOC segment also at 0.1: every node is read with weight 0.9
somewhere; a float table's pair (y, dy), the value and its difference to the next row or
point, with weights 1 and 0.9), and drive the step so that every parameter moves the
voltage:

``RC probes``  per temperature (in each temperature segment), direction and SOC
    segment: one step of +-i_cap from a state with every RC voltage 0 at the segment's
    middle, over dt = 2 tau_fast (r0, r_fast, tau_fast, the BV factor and, through
    dt / tau_slow, r_slow and tau_slow) and over dt = tau_slow (r_slow and tau_slow), and per
    temperature and direction one over tau_diff. Variable dt: the SOC is moved to the step's
    start by one step of current and the RC voltages reset by a rest of dt = 32767 s (at
    which 1 - exp(-dt/tau) is exactly 1 for tau < 1500 s), all in one segment; fixed dt:
    each probe is its own segment from init, a few steps long.
``OCV sweep``  per temperature, steps landing in every OCV segment; with the surface SOC
    instead, per OCV probe point, a step that builds the diffusion voltage so that the
    surface SOC sits where r0 is steepest, then a step of dt = 0 at i_cap (nothing moves
    but the voltage) reading the OCV and r0 at the surface SOC, which the per-volt table's
    entries move.
``age``        per ageing-law segment, one probe at its middle.
``g tables``   (fixed point) the asinh(x)/x tables of the Butler-Volmer branch and of
    current_dependent_resistance, swept at the middle of each of their segments.

Which entries a 5 % change of each is detected in is measured by ``bench/verify_coverage.py``
(through the C and ``ecmgen verify``); the runtime never reads a float table's last row or
point (interpolation stops at the pair before it) nor breakpoints past a table's reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .qformat import DT_MAX_S, Q30, cdr_nodes
from .spec import CSpec

I_CAP_FRACTION = 0.25       # probe current: a quarter of the C's current range (8 C at the
                            # default 32 C): large voltages, not saturated
MOVE_FRACTION = 0.25        # the steps that only move the SOC: a quarter of that (a contracted
                            # float build's rounding grows with the current)
SOC_REACH = 0.9             # largest SOC a probe step may move over (SOC stays inside +-2)
RESET_DT_S = DT_MAX_S       # the rest that sets every RC voltage to 0
NODE_WEIGHT = 0.9           # where in each SOC and temperature segment the probes run: a
                            # float table's pairs (y, dy) have dy read at this weight
FIXED_DT_STEPS = 8          # fixed dt: steps of one probe (its SOC moves by 8 i_cap dt k)


@dataclass(frozen=True)
class Segment:
    """SI inputs from one init: soc0, current (A), dt (s; None at fixed dt), temperature."""

    soc0: float
    current_a: np.ndarray
    dt_s: np.ndarray | None
    temperature_c: np.ndarray
    efc: float = 0.0          # the age set after init (a model with an ageing law), cycles


@dataclass
class _Seg:
    soc0: float
    temperature_c: float
    efc: float = 0.0
    i: list = field(default_factory=list)
    dt: list = field(default_factory=list)
    t: list = field(default_factory=list)
    soc: float = 0.0

    def __post_init__(self):
        self.soc = self.soc0

    def step(self, i: float, dt: float, k_soc: float, t: float | None = None) -> None:
        self.i.append(float(i))
        self.dt.append(float(dt))
        self.t.append(self.temperature_c if t is None else float(t))
        self.soc += float(i) * float(dt) * k_soc


@dataclass(frozen=True)
class _Si:
    """The spec's grids and time constants in SI units (approximate for fixed point: they
    only place the probes)."""

    k_soc: float                    # per A s (variable dt) or per A and step (fixed dt)
    i_cap: float
    temps: np.ndarray | None        # degC
    rc_soc: tuple                   # per direction
    ocv_soc: np.ndarray
    tau_fast: tuple                 # per direction (n_t, n_soc), s
    tau_slow: tuple
    tau_diff: tuple                 # per direction (n_t,) or None
    i0: tuple                       # per direction (n_t,) A or None
    r_diff: tuple
    r0: tuple                       # per direction (n_t, n_soc), ohm
    surface: np.ndarray | None      # (n_t, n_ocv) 1/V
    age: np.ndarray | None          # equivalent full cycles


def _si(spec: CSpec) -> _Si:
    q = spec.q
    fx = spec.fixed

    def soc(g):
        return np.ldexp(np.asarray(g.x, dtype=np.float64), -Q30) if fx else \
            np.asarray(g.x, dtype=np.float64)

    def tau(k, qd: str):
        k = np.asarray(k, dtype=np.float64)
        if spec.variable_dt:
            return np.ldexp(k, -q["Q_T"]) if fx else k
        d = np.ldexp(k, -q[qd]) if fx else k        # D = 1/(1 - exp(-dt/tau)) ~ tau/dt + 1/2
        return spec.dt_s * np.maximum(d - 0.5, 0.5)

    def opt(d, name, qf, conv):
        v = getattr(d, name)
        return None if v is None else conv(v, qf)

    def scale(v, qf):
        v = np.asarray(v, dtype=np.float64)
        return np.ldexp(v, -q[qf]) if fx else v

    k_soc = math.ldexp(float(spec.k_soc), -q["Q_K"]) if fx else float(spec.k_soc)
    temps = None
    if spec.temp:
        temps = np.asarray(spec.temp_grid.x, dtype=np.float64) / (256.0 if fx else 1.0)
    age = None
    if spec.age is not None:
        age = np.asarray(spec.age["grid"].x, dtype=np.float64) / (256.0 if fx else 1.0)
    return _Si(
        k_soc=k_soc, i_cap=I_CAP_FRACTION * spec.i_lim_a, temps=temps,
        rc_soc=tuple(soc(d.grid) for d in spec.dirs), ocv_soc=soc(spec.ocv_grid),
        tau_fast=tuple(tau(d.k_fast, "Q_DF") for d in spec.dirs),
        tau_slow=tuple(tau(d.k_slow, "Q_DS") for d in spec.dirs),
        tau_diff=tuple(opt(d, "k_diff", "Q_DD", lambda v, qf: tau(v, qf)) for d in spec.dirs),
        i0=tuple(opt(d, "i0", "Q_I0", scale) for d in spec.dirs),
        r_diff=tuple(opt(d, "r_diff", "Q_RD", scale) for d in spec.dirs),
        r0=tuple(scale(d.r0, "Q_R0") for d in spec.dirs),
        surface=None if spec.surface is None else scale(spec.surface, "Q_SV"), age=age)


def _mids(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return 0.5 * (x[1:] + x[:-1])


def _points(x: np.ndarray) -> np.ndarray:
    """SOC probe points of a grid: NODE_WEIGHT along each segment, and 1 - NODE_WEIGHT along
    the first: every node is read with weight NODE_WEIGHT (a float table's pair (y, dy)
    along SOC with weights 1 and NODE_WEIGHT)."""
    x = np.asarray(x, dtype=np.float64)
    dx = np.diff(x)
    return np.concatenate([[x[0] + (1.0 - NODE_WEIGHT) * dx[0]], x[:-1] + NODE_WEIGHT * dx])


def _temperature_points(si: _Si) -> list[tuple[float, int]]:
    """(temperature, row) of the probes: TEMP_WEIGHT along each temperature segment (row:
    the lower one), or 25 degC without a temperature axis."""
    if si.temps is None:
        return [(25.0, 0)]
    t = si.temps[:-1] + NODE_WEIGHT * np.diff(si.temps)
    return [(float(x), j) for j, x in enumerate(t)]


def _at(table: np.ndarray, row: int, grid: np.ndarray, s: float) -> float:
    """A (n_t, n_soc) table near (row .. row + 1, s): the mean of the four corners."""
    k = int(np.clip(np.searchsorted(grid, s) - 1, 0, grid.size - 2))
    rows = table[row:row + 2] if table.shape[0] > 1 else table[:1]
    return float(np.mean(rows[:, k:k + 2]))


def _row_mean(v, row: int) -> float:
    v = np.asarray(v, dtype=np.float64)
    return float(np.mean(v[row:row + 2]))


def _variable_dt_rc(spec: CSpec, si: _Si, t: float, row: int) -> _Seg:
    """Every RC probe at one temperature, in one segment: move, reset, probe."""
    seg = _Seg(0.5, t)

    def probe(sign: float, s: float, dt: float, cur: float) -> None:
        dt = float(min(max(dt, 1e-3), 0.5 * DT_MAX_S))
        cur = min(cur, SOC_REACH / (dt * si.k_soc))
        start = s - sign * cur * dt * si.k_soc
        move = start - seg.soc
        if abs(move) > 1e-9:
            i_move = MOVE_FRACTION * si.i_cap
            seg.step(math.copysign(i_move, move), abs(move) / (i_move * si.k_soc), si.k_soc)
        seg.step(0.0, RESET_DT_S, si.k_soc)
        seg.step(sign * cur, dt, si.k_soc)
        seg.soc = s                     # as landed (float rounding aside)

    for d, sign in ((0, -1.0), (1, 1.0)):
        grid = si.rc_soc[d]
        for s in _points(grid):
            tf = _at(si.tau_fast[d], row, grid, s)
            ts = _at(si.tau_slow[d], row, grid, s)
            probe(sign, s, 2.0 * tf, si.i_cap)
            probe(sign, s, ts, si.i_cap)
        if si.tau_diff[d] is not None:
            probe(sign, 0.5, _row_mean(si.tau_diff[d], row), si.i_cap)
    return seg


def _ocv_sweep(spec: CSpec, si: _Si, t: float, row: int) -> list[_Seg]:
    """Steps landing on every OCV probe point at one temperature, down from the top (one
    segment); fixed dt, which cannot move the SOC far in a step: one segment of one step
    per point."""
    cur = si.i_cap / 8.0
    points = _points(si.ocv_soc)[::-1]
    if not spec.variable_dt:
        out = []
        for s in points:
            seg = _Seg(float(s) + cur * si.k_soc, t)
            seg.step(-cur, 1.0, si.k_soc)
            out.append(seg)
        return out
    seg = _Seg(float(si.ocv_soc[-1]), t)
    for s in points:
        seg.step(-cur, abs(s - seg.soc) / (cur * si.k_soc), si.k_soc)
    return [seg]


def _r0_slopes(si: _Si, row: int) -> list:
    """Per direction (discharge, charge): the mid-SOC and |slope| of each segment of r0 at
    temperature row ``row``, the same for every probe point of the row."""
    out = []
    for d in (0, 1):
        x = si.rc_soc[d]
        r0 = np.mean(si.r0[d][row:row + 2], axis=0) if si.r0[d].shape[0] > 1 else si.r0[d][0]
        out.append((_mids(x), np.abs(np.diff(r0) / np.diff(x))))
    return out


def _surface_target(slopes: list, s: float) -> float:
    """The surface SOC to read the RC tables at from SOC ``s``: where r0's slope times the
    distance from s is largest (a per-volt entry moves the lookup by a fraction of that
    distance), on the discharge table below s, the charge table above it (``slopes``:
    :func:`_r0_slopes` of the row)."""
    best, where = -1.0, s
    for (mid, slope), side in zip(slopes, (-1.0, 1.0)):
        score = slope * np.abs(mid - s)
        score[side * (mid - s) <= 0] = -1.0
        k = int(np.argmax(score))
        if score[k] > best:
            best, where = float(score[k]), float(mid[k])
    return where


def _surface_probes(spec: CSpec, si: _Si, t: float, row: int) -> _Seg:
    """Variable dt with the surface SOC: per OCV probe point, a step over tau_diff builds the
    diffusion voltage that puts the surface SOC where r0 is steepest (_surface_target),
    landing on the point; then a step of dt = 0 at i_cap reads the OCV there and r0 at the
    surface SOC, which the per-volt entries move. Each from a reset, as the RC probes."""
    seg = _Seg(0.5, t)
    tau_d = _row_mean(si.tau_diff[0], row)
    rd = max(_row_mean(si.r_diff[0], row), 1e-9)
    slopes = _r0_slopes(si, row)
    for s in _points(si.ocv_soc):
        k = int(np.clip(np.searchsorted(si.ocv_soc, s) - 1, 0, si.ocv_soc.size - 2))
        sv = max(float(np.mean(si.surface[row:row + 2, k:k + 2])), 1e-9)
        u_d = (_surface_target(slopes, s) - s) / sv
        sign = -1.0 if u_d < 0 else 1.0
        cur = min(abs(u_d) / (rd * (1.0 - math.exp(-1.0))), si.i_cap,
                  SOC_REACH / (tau_d * si.k_soc))
        move = s - sign * cur * tau_d * si.k_soc - seg.soc
        if abs(move) > 1e-9:
            i_move = MOVE_FRACTION * si.i_cap
            seg.step(math.copysign(i_move, move), abs(move) / (i_move * si.k_soc), si.k_soc)
        seg.step(0.0, RESET_DT_S, si.k_soc)
        seg.step(sign * cur, tau_d, si.k_soc)
        seg.step(sign * si.i_cap, 0.0, si.k_soc)
        seg.soc = s
    return seg


def _fixed_dt_rc(spec: CSpec, si: _Si, t: float, row: int) -> list[_Seg]:
    """Fixed dt: each RC probe its own segment from init (no rest resets the RC voltages in
    a few steps): FIXED_DT_STEPS steps of +-i_cap through the SOC segment's middle."""
    out = []
    n = FIXED_DT_STEPS
    for d, sign in ((0, -1.0), (1, 1.0)):
        for s in _points(si.rc_soc[d]):
            seg = _Seg(s - sign * si.i_cap * si.k_soc * (n + 1) / 2.0, t)
            for _ in range(n):
                seg.step(sign * si.i_cap, 1.0, si.k_soc)
            out.append(seg)
    return out


def _age_probes(spec: CSpec, si: _Si) -> list[_Seg]:
    """One probe at the middle of each segment of the ageing law: r0 i and the SOC's rate."""
    out = []
    if si.age is None:
        return out
    t, row = _temperature_points(si)[0]
    for efc in _mids(si.age):
        seg = _Seg(0.5, t, efc=float(efc))
        tf = float(np.mean(si.tau_fast[0][row]))
        seg.step(-si.i_cap, 2.0 * tf if spec.variable_dt else 1.0, si.k_soc)
        out.append(seg)
    return out


def _g_sweep(spec: CSpec, si: _Si, e_bins: int, scale_i0, needs_dt: bool, t: float,
             row: int) -> _Seg:
    """Currents |i| = x i0 at the middle of every segment of an asinh(x)/x table (fixed
    point), alternating in sign so that the SOC stays put; ``needs_dt``: the factor acts on
    r_fast (Butler-Volmer), so each step lasts 2 tau_fast, else dt = 0 (r0 i at once)."""
    x = _mids(cdr_nodes(e_bins))
    cur = x * scale_i0
    seg = _Seg(0.5, t)
    tf = float(np.mean(si.tau_fast[0][row]))
    dt = (2.0 * tf if needs_dt else 0.0) if spec.variable_dt else 1.0
    for k, c in enumerate(cur[cur < spec.i_lim_a]):
        seg.step(c if k % 2 else -c, dt, si.k_soc)
    return seg


def _g_sweeps(spec: CSpec, si: _Si) -> list[_Seg]:
    out = []
    pts = _temperature_points(si)
    if spec.fixed and spec.has_bv:
        # the temperature of the smallest i0 reaches the largest x = |i| / i0
        i0 = np.minimum(*(np.asarray(v, dtype=np.float64) for v in si.i0))
        t, row = min(pts, key=lambda p: _row_mean(i0, p[1]))
        out.append(_g_sweep(spec, si, spec.bv["E"], _row_mean(i0, row), True, t, row))
    if spec.fixed and spec.fx.get("cdr"):
        i0 = 1.0 / math.ldexp(float(spec.fx["g_k"]), -spec.fx["Q_GK"])
        t, row = pts[0]
        out.append(_g_sweep(spec, si, spec.fx["CDR_E"], i0, False, t, row))
    return out


def probe_segments(spec: CSpec):
    """The probe segments of ``spec``."""
    si = _si(spec)
    segs: list[_Seg] = []
    for t, row in _temperature_points(si):
        if spec.variable_dt:
            segs.append(_variable_dt_rc(spec, si, t, row))
        else:
            segs += _fixed_dt_rc(spec, si, t, row)
        if spec.variable_dt and si.surface is not None and si.tau_diff[0] is not None:
            segs.append(_surface_probes(spec, si, t, row))
        else:
            segs += _ocv_sweep(spec, si, t, row)
    segs += _age_probes(spec, si)
    segs += _g_sweeps(spec, si)
    return [Segment(float(s.soc0), np.asarray(s.i, dtype=np.float64),
                    np.asarray(s.dt, dtype=np.float64) if spec.variable_dt else None,
                    np.asarray(s.t, dtype=np.float64), s.efc) for s in segs if s.i]
