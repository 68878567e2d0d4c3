"""One model over temperature from one-temperature models (one per pulse test).

:func:`assemble_over_temperature` joins the models that the per-test fits give (same
method, same capacity) into one :class:`EcmModel` whose RC tables run over (temperature,
SOC) and whose OCV has one row per pulse test:

- **breakpoints**: each test's temperature (the median cell temperature during its pulses,
  or the configured one), sorted; two tests closer than ``MIN_SPACING_K`` are refused;
- **interpolation over temperature**: Arrhenius, every resistance, time constant and the
  Butler-Volmer current i0 with ln(p) linear in 1/T (T in kelvin), per SOC node, between
  neighbouring breakpoints; a parameter that is 0 at either end is linear in 1/T instead;
- **derived warm row** (``warm_c``, default 45 degC, when above the warmest test): each
  resistance (and r_diff, 1/i0) of the warmest test scaled by exp(Ea/R (1/T - 1/T_warm))
  with ONE Ea/R per parameter, the median two-point slope between the two warmest tests
  over the SOC nodes both tests cover (never below 0); time constants and OCV those of
  the warmest test. The cells of a BMS run above the warmest pulse test, and a clamped
  table would hold them at its resistances;
- **grid**: the Arrhenius interpolation is resampled onto a uniform temperature grid
  (``step_c`` kelvin, multiples of it covering the breakpoints), which the model and the
  generated C interpolate bilinearly; ``step_c = 0`` keeps the measured rows (linear in T
  between them);
- **OCV**: each test's OCV as one row at its temperature (linear in T between rows), on a
  common SOC grid; tests that share one OCV give one row;
- everything is clamped beyond the table ends (the model does that).

The notes of the result name the measured breakpoints, the derived row and the grid.
:func:`derive_over_temperature` makes a model over temperature from ONE test and a given
Ea/R ([model] activation_k), through the same assembly. :func:`neighbour_time_constants`
gives a test between two others their time constants, interpolated to its temperature: the
curve fit takes them in place of its own where they predict a left-out level better.
Pure numpy on the given arrays: the same inputs give the same bytes in model.json.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from .model import BRANCH_FIELDS, DIRECTIONS, RC_FIELDS, EcmModel, OcvOverTemperature, RcTable

KELVIN = 273.15
MIN_SPACING_K = 0.5          # two pulse tests closer than this are one temperature
SOC_MERGE = 0.01             # SOC breakpoints of the tests closer than this become one
OCV_SOC_STEP = 0.01          # the common SOC grid of OCV rows from different tests
RESISTANCES = ("r0_ohm", "r_fast_ohm", "r_slow_ohm")
TIME_CONSTANTS = ("tau_fast_s", "tau_slow_s")


def inverse_kelvin(temperature_c) -> np.ndarray:
    return 1.0 / (np.asarray(temperature_c, dtype=np.float64) + KELVIN)


def arrhenius_interp(temperatures_c: np.ndarray, rows: np.ndarray, at_c) -> np.ndarray:
    """``rows`` (n_t, ...) given at the increasing ``temperatures_c``, evaluated at ``at_c``
    (scalar): ln(row) linear in 1/T_K between the two breakpoints around it (clamped
    beyond the ends); where either end is not positive, the row is linear in 1/T_K."""
    temps = np.asarray(temperatures_c, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    if temps.size == 1:
        return rows[0].copy()
    t = float(np.clip(at_c, temps[0], temps[-1]))
    k = int(np.clip(np.searchsorted(temps, t, side="right") - 1, 0, temps.size - 2))
    x, x0, x1 = inverse_kelvin([t, temps[k], temps[k + 1]])
    w = (x - x0) / (x1 - x0)
    a, b = rows[k], rows[k + 1]
    linear = a + (b - a) * w
    positive = (a > 0) & (b > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        geometric = np.exp(np.log(np.where(positive, a, 1.0)) * (1.0 - w) +
                           np.log(np.where(positive, b, 1.0)) * w)
    return np.where(positive, geometric, linear)


def neighbour_time_constants(temperatures_c, curve_fits) -> list[dict | None]:
    """Per test, the time constants of the tests on either side of it in temperature, ln
    tau linear in 1/T between them ({"fast": s, "slow": s[, "diff": s]}); None for the
    coldest and the warmest test, and where a neighbour has no curve fit (``curve_fits``:
    :class:`ecmgen.fit.curve.CurveFit` or None, in the order of ``temperatures_c``) or the
    two have different branches (one dropped its diffusion pair)."""
    temps = np.asarray(temperatures_c, dtype=np.float64)
    out: list[dict | None] = [None] * temps.size
    if temps.size < 3 or not np.all(np.isfinite(temps)):
        return out
    order = np.argsort(temps, kind="stable")

    def taus(f):
        t = {"fast": f.tau_fast_s, "slow": f.tau_slow_s, "diff": f.tau_diff_s}
        return {k: float(v) for k, v in t.items() if v is not None}

    for lo, k, hi in zip(order[:-2], order[1:-1], order[2:]):
        a, b = curve_fits[lo], curve_fits[hi]
        if a is None or b is None or set(taus(a)) != set(taus(b)) or \
                not temps[lo] + MIN_SPACING_K <= temps[k] <= temps[hi] - MIN_SPACING_K:
            continue
        ta, tb = taus(a), taus(b)
        x, x0, x1 = inverse_kelvin([temps[k], temps[lo], temps[hi]])
        w = (x - x0) / (x1 - x0)
        out[k] = {n: float(np.exp(np.log(ta[n]) * (1.0 - w) + np.log(tb[n]) * w)) for n in ta}
    return out


def activation_slope_k(t_warm_c: float, t_cold_c: float, warm: np.ndarray, cold: np.ndarray,
                       use: np.ndarray | None = None) -> float:
    """Ea/R in kelvin of a parameter that falls with temperature: the median over the
    (used, positive) nodes of ln(cold / warm) / (1/T_cold - 1/T_warm); 0 when it would be
    negative or no node qualifies."""
    warm, cold = np.atleast_1d(warm), np.atleast_1d(cold)
    ok = (warm > 0) & (cold > 0)
    if use is not None:
        ok &= use
    if not ok.any():
        return 0.0
    xw, xc = inverse_kelvin([t_warm_c, t_cold_c])
    slope = np.log(cold[ok] / warm[ok]) / (xc - xw)
    return max(float(np.median(slope)), 0.0)


def _soc_union(grids: Sequence[np.ndarray]) -> np.ndarray:
    """The union of SOC breakpoints, with runs closer than SOC_MERGE merged to their mean
    (one pulse level at slightly different SOCs in different tests)."""
    allx = np.unique(np.concatenate([np.asarray(g, dtype=np.float64) for g in grids]))
    groups: list[list[float]] = []
    for x in allx:
        if groups and x - groups[-1][0] < SOC_MERGE:
            groups[-1].append(float(x))
        else:
            groups.append([float(x)])
    out = np.array([np.mean(g) for g in groups])
    # the ends stay where a table has them (0 and 1 are breakpoints of many tables)
    out[0], out[-1] = allx[0], allx[-1]
    return out


def _converged(table: RcTable, soc: np.ndarray) -> np.ndarray:
    """``converged`` on ``soc``: where both neighbouring breakpoints converged (beyond the
    table's SOC span, where it holds its end value, as that end)."""
    return np.interp(soc, table.soc, table.converged[0].astype(np.float64)) >= 1.0


def _in_range(table: RcTable, soc: np.ndarray) -> np.ndarray:
    """Nodes of ``soc`` inside the SOC span the table was fitted on and converged there."""
    inside = (soc >= table.soc[0] - 1e-9) & (soc <= table.soc[-1] + 1e-9)
    return inside & _converged(table, soc)


def _measured_rows(tables: Sequence[RcTable], temps: np.ndarray, soc: np.ndarray
                   ) -> tuple[dict, list[str]]:
    """Every field of one-temperature tables as rows (n_tests, n_soc) on ``soc`` (branch
    fields (n_tests,)), the in-range masks, and notes on branch values filled in."""
    cols: dict = {k: np.vstack([np.interp(soc, t.soc, getattr(t, k)[0]) for t in tables])
                  for k in (*RC_FIELDS, "fit_error")}
    cols["converged"] = np.vstack([_converged(t, soc) for t in tables])
    cols["in_range"] = np.vstack([_in_range(t, soc) for t in tables])
    notes: list[str] = []
    for k in BRANCH_FIELDS:
        have = np.array([getattr(t, k) is not None for t in tables])
        values = np.array([getattr(t, k)[0] if h else np.nan for t, h in zip(tables, have)])
        if have.all() or not have.any():
            cols[k] = values if have.all() else None
            continue
        missing = ", ".join(f"{t:.1f}" for t in temps[~have])
        if k == "i0_a":
            # a test without a measurable current dependence: i0 from the others, ln(i0)
            # linear in 1/T (least squares; one other test: its value)
            x, y = inverse_kelvin(temps[have]), np.log(values[have])
            slope = float(np.polyfit(x, y, 1)[0]) if have.sum() > 1 else 0.0
            fill = np.exp(y.mean() + slope * (inverse_kelvin(temps[~have]) - x.mean()))
            notes.append(f"i0_a at {missing} degC (no current dependence found in that test) "
                         "from the other tests, ln(i0) linear in 1/T")
        elif k == "r_diff_ohm":
            fill = np.zeros((~have).sum())
            notes.append(f"no diffusion pair fitted at {missing} degC: r_diff_ohm = 0 there")
        else:   # tau_diff_s: the nearest test's (r_diff is 0 there anyway)
            near = [int(np.argmin(np.where(have, np.abs(temps - t), np.inf)))
                    for t in temps[~have]]
            fill = values[near]
        values[~have] = fill
        cols[k] = values
    return cols, notes


def _warm_row(temps: np.ndarray, cols: dict, warm_c: float) -> tuple[dict, dict[str, float]]:
    """The derived row at ``warm_c`` (above the warmest breakpoint) and the Ea/R used."""
    a, b = -1, -2          # the warmest and the next warmest breakpoint
    ta, tb = float(temps[a]), float(temps[b])
    use = cols["in_range"][a] & cols["in_range"][b]
    xa, xw = inverse_kelvin([ta, warm_c])
    row: dict = {}
    ea: dict[str, float] = {}
    for k in RESISTANCES:
        ea[k] = activation_slope_k(ta, tb, cols[k][a], cols[k][b], use)
        row[k] = cols[k][a] * np.exp(ea[k] * (xw - xa))
    for k in (*TIME_CONSTANTS, "fit_error", "converged", "in_range"):
        row[k] = cols[k][a].copy()
    if cols["r_diff_ohm"] is not None:
        k = "r_diff_ohm"
        ea[k] = activation_slope_k(ta, tb, cols[k][a], cols[k][b])
        row[k] = cols[k][a] * np.exp(ea[k] * (xw - xa))
        row["tau_diff_s"] = cols["tau_diff_s"][a]
    if cols["i0_a"] is not None:
        # i0 rises with temperature: 1/i0 extrapolates like a resistance
        inv = 1.0 / cols["i0_a"]
        ea["i0_a"] = activation_slope_k(ta, tb, inv[a], inv[b])
        row["i0_a"] = cols["i0_a"][a] / np.exp(ea["i0_a"] * (xw - xa))
    return row, ea


def temperature_grid(t_min_c: float, t_max_c: float, step_c: float) -> np.ndarray:
    """Multiples of ``step_c`` from the one at or below ``t_min_c`` to the one at or above
    ``t_max_c`` (rounded to 1e-9 K so that the grid is exact decimal text)."""
    lo = np.floor(t_min_c / step_c + 1e-9)
    hi = np.ceil(t_max_c / step_c - 1e-9)
    return np.round(np.arange(lo, hi + 1.0) * step_c, 9)


def _assemble_direction(tables: Sequence[RcTable], temps: np.ndarray, step_c: float,
                        warm_c: float | None
                        ) -> tuple[RcTable, dict[str, float] | None, list[str]]:
    soc = tables[0].soc if len(tables) == 1 else _soc_union([t.soc for t in tables])
    cols, fill_notes = _measured_rows(tables, temps, soc)
    ea = None
    row_temps = temps.copy()
    if warm_c is not None and temps.size >= 2 and warm_c > temps[-1] + MIN_SPACING_K:
        row, ea = _warm_row(temps, cols, warm_c)
        for k, v in row.items():
            if cols.get(k) is not None:
                cols[k] = np.concatenate([cols[k], np.atleast_1d(v)[None, :]
                                          if np.ndim(cols[k]) == 2 else np.atleast_1d(v)])
        row_temps = np.append(temps, warm_c)
    if step_c > 0 and row_temps.size >= 2:
        grid = temperature_grid(row_temps[0], row_temps[-1], step_c)
        out: dict = {}
        for k in (*RC_FIELDS, "fit_error"):
            out[k] = np.vstack([arrhenius_interp(row_temps, cols[k], t) for t in grid])
        # a grid cell is converged where both rows around it are
        conv = cols["converged"].astype(np.float64)
        out["converged"] = np.vstack([_both_neighbours(row_temps, conv, t) for t in grid])
        for k in BRANCH_FIELDS:
            if cols[k] is not None:
                out[k] = np.array([float(arrhenius_interp(row_temps, cols[k][:, None], t)[0])
                                   for t in grid])
        return RcTable(soc=soc, temperature_c=grid, **out), ea, fill_notes
    return RcTable(soc=soc, temperature_c=row_temps,
                   **{k: cols[k] for k in (*RC_FIELDS, "fit_error", "converged",
                                           *BRANCH_FIELDS)}), ea, fill_notes


def _both_neighbours(temps: np.ndarray, conv: np.ndarray, t: float) -> np.ndarray:
    t = float(np.clip(t, temps[0], temps[-1]))
    k = int(np.clip(np.searchsorted(temps, t, side="right") - 1, 0, temps.size - 2))
    if t == temps[k]:
        return conv[k] >= 1.0
    return (conv[k] >= 1.0) & (conv[k + 1] >= 1.0)


def _ocv_rows(models: Sequence[EcmModel], temps: np.ndarray) -> OcvOverTemperature:
    """One OCV row per test at its temperature; one row when every test has the same OCV."""
    ocvs = [m.ocv for m in models]
    for o in ocvs:
        if o.n_temperatures != 1:
            raise ValueError("assemble_over_temperature takes one-temperature models")
    first = ocvs[0]
    if all(np.array_equal(o.soc, first.soc) and np.array_equal(o.ocv_v, first.ocv_v)
           for o in ocvs):
        return first
    same_grid = all(np.array_equal(o.soc, first.soc) for o in ocvs)
    soc = first.soc if same_grid else np.round(np.arange(0.0, 1.0 + 1e-9, OCV_SOC_STEP), 9)
    rows = np.vstack([np.interp(soc, o.soc, o.ocv_v[0]) for o in ocvs])
    return OcvOverTemperature(temps, soc, rows)


def fill_ocv_rows(ocv: OcvOverTemperature, spans) -> tuple[OcvOverTemperature, list[str]]:
    """Each OCV row beyond the SOC span its own sources measured (``spans``: (lo, hi) per
    row), from the row nearest in temperature that measured there: its shape, shifted to
    meet this row where its span ends (then from the next nearest row that reaches further,
    and so on). A cold pulse test's rests stop where the voltage limit cuts its pulse sets
    (the Panasonic 18650PF: SOC 0.20 / 0.25 at -10 / -20 degC) and a test that opens with
    a charge from empty rests first well above empty (the Leaf at 25 degC): a row held
    flat there reads hundreds of mV high where a discharge runs into it, while the cell's
    OCV at another temperature differs by an entropic few mV. Beyond every row's span the
    row stays flat. Returns the OCV and notes."""
    rows = np.array(ocv.ocv_v, dtype=np.float64)
    soc, temps = ocv.soc, ocv.temperature_c
    spans = [(float(lo), float(hi)) for lo, hi in spans]
    if rows.shape[0] < 2 or len(spans) != rows.shape[0]:
        return ocv, []
    notes = []
    for k in range(len(spans)):
        nearest = sorted((j for j in range(len(spans)) if j != k),
                         key=lambda j: (abs(temps[j] - temps[k]), j))
        for below in (True, False):
            edge, pieces = spans[k][0] if below else spans[k][1], []
            while True:
                src = next((j for j in nearest
                            if (spans[j][0] < edge - 1e-9 if below else spans[j][1] > edge + 1e-9)),
                           None)
                if src is None:
                    break
                reach = spans[src][0] if below else spans[src][1]
                take = ((soc < edge - 1e-9) & (soc >= reach - 1e-9) if below else
                        (soc > edge + 1e-9) & (soc <= reach + 1e-9))
                shift = float(np.interp(edge, soc, rows[k]) - np.interp(edge, soc, rows[src]))
                rows[k, take] = rows[src, take] + shift
                pieces.append(f"SOC {reach:.2f}..{edge:.2f}" if below else
                              f"SOC {edge:.2f}..{reach:.2f}")
                pieces[-1] += (f" from the {_fmt_t(temps[src])} degC row, shifted by "
                               f"{shift * 1e3:+.1f} mV to meet it at SOC {edge:.2f}")
                edge = reach
            held = soc < edge - 1e-9 if below else soc > edge + 1e-9
            rows[k, held] = np.interp(edge, soc, rows[k])
            if pieces:
                notes.append(f"OCV [{_fmt_t(temps[k])} degC] beyond its own rests: "
                             + "; ".join(pieces))
        rows[k] = np.maximum.accumulate(rows[k])
    return OcvOverTemperature(temps, soc, rows), notes


def _fmt_t(t: float) -> str:
    return f"{t:.1f}"


def assemble_over_temperature(models: Sequence[EcmModel], temperatures_c, *,
                              step_c: float = 5.0, warm_c: float | None = 45.0,
                              labels: Sequence[str] | None = None,
                              ocv_spans: Sequence[tuple] | None = None) -> EcmModel:
    """One model over temperature from one-temperature ``models`` (one per pulse test, at
    ``temperatures_c``, any order; same method and capacity). See the module docstring.

    ``labels`` name the tests in the notes (e.g. their files); ``ocv_spans``, the SOC span
    each test's OCV sources measured, are filled beyond from the other tests' rows
    (:func:`fill_ocv_rows`). A single model comes back with its temperature on its rows
    (nothing to interpolate)."""
    temps = np.asarray(temperatures_c, dtype=np.float64)
    if temps.shape != (len(models),) or not len(models):
        raise ValueError("assemble_over_temperature: one temperature per model")
    if not np.all(np.isfinite(temps)):
        raise ValueError("assemble_over_temperature: temperatures must be finite")
    labels = list(labels) if labels is not None else [f"test {k + 1}" for k in range(len(models))]
    order = np.argsort(temps, kind="stable")
    temps, models = temps[order], [models[k] for k in order]
    labels = [labels[k] for k in order]
    spans = None if ocv_spans is None else [ocv_spans[k] for k in order]
    close = np.flatnonzero(np.diff(temps) < MIN_SPACING_K)
    if close.size:
        k = int(close[0])
        raise ValueError(f"{labels[k]} and {labels[k + 1]} are both at about "
                         f"{temps[k]:.1f} degC: one pulse test per temperature")
    base = models[0]
    for m in models[1:]:
        if m.method != base.method or m.capacity_ah != base.capacity_ah:
            raise ValueError("assemble_over_temperature: the models differ in method or "
                             "capacity")
    for m in models:
        if m.effects or m.needs_temperature:
            raise ValueError("assemble_over_temperature takes one-temperature models "
                             "without effects")

    tables, eas, fills = {}, {}, []
    for d in DIRECTIONS:
        tables[d], eas[d], filled = _assemble_direction([m.table(d) for m in models], temps,
                                                        step_c, warm_c)
        fills += [f"{d}: {n}" for n in filled]
    ocv = _ocv_rows(models, temps)
    if len(models) == 1:
        ocv = OcvOverTemperature(temps, ocv.soc, ocv.ocv_v)
    filled_ocv = []
    if spans is not None and ocv.n_temperatures > 1:
        ocv, filled_ocv = fill_ocv_rows(ocv, spans)

    notes = [f"[{_fmt_t(t)} degC] {n}" for t, m in zip(temps, models) for n in m.notes]
    notes += fills
    if len(models) > 1:
        notes.append("temperature breakpoints measured: " + ", ".join(
            f"{_fmt_t(t)} degC ({lab})" for t, lab in zip(temps, labels)))
        ea = eas["discharge"]
        if ea is not None:
            notes.append(
                f"derived warm row at {warm_c:g} degC (not measured): the {_fmt_t(temps[-1])} "
                f"degC row with each resistance x exp(Ea/R (1/T - 1/T_warm)), Ea/R from the "
                f"two warmest tests: " + ", ".join(f"{k} {v:.0f} K" for k, v in ea.items()) +
                "; time constants and OCV of the warmest test")
        grid = tables["discharge"].temperature_c
        if step_c > 0:
            notes.append(f"tables over temperature: Arrhenius (ln of every resistance, time "
                         f"constant and i0 linear in 1/T) between the breakpoints, resampled "
                         f"onto a uniform {step_c:g} K grid {grid[0]:g}..{grid[-1]:g} degC "
                         f"({grid.size} rows), bilinear between rows, clamped beyond")
        else:
            notes.append("tables over temperature: the measured breakpoints, linear in "
                         "temperature between them, clamped beyond")
        if ocv.n_temperatures > 1:
            notes.append("OCV: one row per pulse test at its temperature (from its own data), "
                         "linear in temperature between them, clamped beyond")
            notes += filled_ocv
    inputs = tuple(r for m in models for r in m.inputs)
    return replace(base, ocv=ocv, charge=tables["charge"], discharge=tables["discharge"],
                   inputs=inputs, notes=tuple(notes))


DERIVED_COLD_C = -30.0       # the cold row of a model derived from one test (clamped below)


def derive_over_temperature(model: EcmModel, test_c: float, activation_k: float, *,
                            step_c: float = 5.0, warm_c: float | None = 45.0,
                            label: str = "the pulse test") -> EcmModel:
    """A model over temperature from the one-temperature ``model`` of a pulse test at
    ``test_c``: a derived row at DERIVED_COLD_C (or a step below the test) with every
    resistance, r_diff too, x exp(activation_k (1/T - 1/T_test)), joined to it by
    :func:`assemble_over_temperature` (which also derives the warm row with that Ea/R);
    time constants, i0 and the OCV stay the test's."""
    cold_c = min(DERIVED_COLD_C, test_c - max(step_c, 5.0))
    f = float(np.exp(activation_k * (inverse_kelvin(cold_c) - inverse_kelvin(test_c))))

    def scaled(t: RcTable) -> RcTable:
        kw = {k: np.asarray(getattr(t, k)) * f for k in RESISTANCES}
        if t.r_diff_ohm is not None:
            kw["r_diff_ohm"] = np.asarray(t.r_diff_ohm) * f
        return replace(t, **kw)

    cold = replace(model, charge=scaled(model.charge), discharge=scaled(model.discharge),
                   notes=(), inputs=())
    out = assemble_over_temperature([cold, replace(model, notes=())], [cold_c, test_c],
                                    step_c=step_c, warm_c=warm_c, labels=["derived", label])
    grid = [n for n in out.notes if n.startswith("tables over temperature")]
    rows = f"{_fmt_t(cold_c)}" + (f" and {warm_c:g}" if warm_c is not None and warm_c > test_c
                                  else "")
    mine = (f"tables over temperature derived from one pulse test at {_fmt_t(test_c)} degC "
            f"({label}): rows at {rows} degC (not measured) with every resistance, r_diff "
            f"too, x exp({activation_k:g} K (1/T - 1/T_test)) ([model] activation_k); "
            "time constants, i0 and OCV of the test")
    return replace(out, notes=(*model.notes, *grid, mine))
