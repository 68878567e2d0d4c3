"""PNG plots of a build: DC-IR points with fitted curves (paper Fig. 4), measured vs
simulated voltage with the error trace and the cell temperature (paper Figs. 5-6), and
each parameter over SOC with one line per temperature."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .style import (FLAGGED, MEASURED, METHOD_COLOURS, SOC_COLOUR, TEMPERATURE_COLOUR, _panels, _plt,
                       break_gaps, degrees, method_colour, save_png, temperature_colours)


def plot_dcir_fits(table, fits: dict, path: Path, at: str = "") -> Path:
    """One panel per SOC level x direction: R(t) points and each method's curve."""
    from ..fit.points import curve_r_ohm

    plt = _plt()
    n = len(table)
    fig, axes, cols = _panels(plt, n)
    t_fine = np.linspace(table.t_s[0], table.t_s[-1], 200)
    curves = {m: curve_r_ohm(f, t_fine) for m, f in fits.items()}
    for k, ax in enumerate(axes):
        for j, (m, c) in enumerate(curves.items()):
            ax.plot(t_fine, c[k] * 1e3, lw=1.2, color=method_colour(m, j), label=m.upper())
        ax.plot(table.t_s, table.r_ohm[k] * 1e3, "ko", ms=4, zorder=5, label="measured R(t)")
        ax.set_title(f"{table.direction[k]} SOC {table.soc[k] * 100:.0f} %", fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if k % cols == 0:
            ax.set_ylabel("R [mΩ]", fontsize=8)
        if k + cols >= n:
            ax.set_xlabel("time into the pulse [s]", fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle("DC-IR R(t) = ΔV/ΔI of the pulses and the fitted 2RC curves"
                 + (f" at {at}" if at else ""))
    _panel_layout(fig)
    save_png(fig, path)
    plt.close(fig)
    return path


def plot_curve_fits(curve_fit, path: Path, at: str = "") -> Path:
    """Whole-test fit: measured vs fitted voltage over each SOC level's pulses and rests."""
    plt = _plt()
    n = len(curve_fit.windows)
    fig, axes, cols = _panels(plt, n)
    for k, (ax, (soc, direction, rms, parts)) in enumerate(zip(axes, curve_fit.windows)):
        for j, (t, meas, fit) in enumerate(parts):
            ax.plot(t, fit, color=METHOD_COLOURS["curve"], lw=0.9,
                    label="fitted" if j == 0 else None)
            ax.plot(t, meas, label="measured" if j == 0 else None, **dict(MEASURED, lw=0.6))
        ax.set_xscale("symlog", linthresh=10)
        ax.set_title(f"{direction} SOC {soc * 100:.0f} %: RMS {rms * 1e3:.1f} mV", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_ylabel("voltage [V]", fontsize=7)
        if k + cols >= n:
            ax.set_xlabel("time from the level's first pulse [s]", fontsize=7)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle("Whole-test fit: measured and fitted voltage at each SOC level"
                 + (f", {at}" if at else "") + " (time axis linear to 10 s, log beyond)")
    _panel_layout(fig)
    save_png(fig, path)
    plt.close(fig)
    return path


def _panel_layout(fig) -> None:
    """Fixed margins for a grid of panels (_panels: 3.2 x 2.6 in each), much cheaper than
    tight_layout, which draws the figure once more to measure it."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.6 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.7 / h,
                        wspace=0.42, hspace=0.55)


def _stack_layout(fig, left_in: float, right_in: float, title_lines: int = 1,
                  hspace: float = 0.1) -> None:
    """Fixed margins (inches) for panels stacked over one x axis, as tight_layout sets
    them on the shared data, without its extra pass to measure the figure (a third of a
    validation plot's time)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left_in / w, right=1 - right_in / w, bottom=0.6 / h,
                        top=1 - (0.18 + 0.17 * title_lines) / h, hspace=hspace)


def _envelope(t: np.ndarray, y: np.ndarray, buckets: int = 1500):
    """A long trace as the min and max of each of ``buckets`` runs of samples (in time
    order), which draws the same picture at the plot's resolution, much faster."""
    n = t.size
    if n <= 4 * buckets:
        return t, y
    edges = np.linspace(0, n, buckets + 1).astype(int)
    lo = np.minimum.reduceat(y, edges[:-1])
    hi = np.maximum.reduceat(y, edges[:-1])
    mid = t[(edges[:-1] + edges[1:]) // 2]
    return np.repeat(mid, 2), np.column_stack([lo, hi]).ravel()


def plot_validation(val, path: Path, title: str = "") -> Path:
    """Measured vs simulated voltage, the error trace with the simulated SOC, and (when the
    record has one) the cell temperature the model ran on."""
    return plot_validations({"": val}, path, title)


def plot_validations(vals: dict, path, title: str = "", best: str = ""):
    """One cycle, several models (``{name: Validation}``, same record): measured (black,
    on top) and each simulated voltage, each error trace (clipped values at the edge,
    said), the simulated SOC and the cell temperature the models ran on (when the record
    has one). A long soak before the drive is not drawn, nor a line across a logging gap."""
    plt = _plt()
    first = next(iter(vals.values()))
    temp = getattr(first, "temperature_c", None)
    keep, skipped_s = _drive_window(first)
    t = first.sim.time_s[keep]
    n = 3 if temp is not None else 2
    fig, axes = plt.subplots(n, 1, figsize=(11, 6 + 1.6 * (n - 2)), sharex=True,
                             gridspec_kw={"height_ratios": [2, 1.2, 0.8][:n]})
    a1, a2 = axes[0], axes[1]
    a1.plot(*_trace(t, first.measured_v[keep]), label="measured", **MEASURED)
    order = sorted(vals, key=lambda m: m == best)        # the best one drawn last
    for k, m in enumerate(order):
        colour = method_colour(m, k)
        lab = "simulated" if not m else m.upper()
        a1.plot(*_trace(t, vals[m].sim.voltage_v[keep]), color=colour, lw=0.5, label=lab)
    a1.set_ylabel("voltage [V]")
    _thick(a1.legend(loc="upper right", fontsize=8))
    if not title and len(vals) == 1:
        title = (f"{first.source}: MAE {first.overall.mae_v * 1e3:.1f} mV, "
                 f"RMSE {first.overall.rmse_v * 1e3:.1f} mV, "
                 f"max {first.overall.max_abs_v * 1e3:.0f} mV")
    if skipped_s > 0:
        title += f"\n(the {skipped_s:.0f} s rest before the drive not drawn)"
    a1.set_title(title, fontsize=10)
    _error_panel(a2, t, keep, vals, order)
    b = a2.twinx()
    b.plot(*_trace(t, first.sim.soc[keep] * 100), color=SOC_COLOUR, lw=0.8)
    b.set_ylabel("simulated SOC [%]", color=SOC_COLOUR)
    if temp is not None:
        a3 = axes[2]
        a3.plot(*_trace(t, np.asarray(temp)[keep]), color=TEMPERATURE_COLOUR, lw=0.8)
        a3.set_ylabel("cell [°C]", color=TEMPERATURE_COLOUR)
        a3.grid(alpha=0.3)
    axes[-1].set_xlabel("time in the record [s]")
    # the two-line error label on the left, the SOC axis on the right
    _stack_layout(fig, 1.05, 0.72, title.count("\n") + 1)
    save_png(fig, path)
    plt.close(fig)
    return path


def _thick(legend) -> None:
    """Legend lines thick enough to tell their colours apart."""
    for line in legend.get_lines():
        line.set_linewidth(2.0)


def _trace(t: np.ndarray, y: np.ndarray):
    """A trace as drawn: no line across a logging gap, a long one as its envelope."""
    return _envelope(*break_gaps(t, y))


def _drive_window(val):
    """(the samples drawn, seconds left out): a rest before the drive longer than a fifth
    of the record is left out but for its last minute."""
    from ..model.simulate import DRIVE_CURRENT_A

    t = val.sim.time_s
    driven = np.flatnonzero(np.abs(val.sim.current_a) > DRIVE_CURRENT_A)
    if not driven.size or t[-1] <= t[0]:
        return slice(None), 0.0
    start = t[driven[0]] - 60.0
    if start - t[0] < 0.2 * (t[-1] - t[0]):
        return slice(None), 0.0
    k = int(np.searchsorted(t, start))
    return slice(k, None), float(t[k] - t[0])


def _error_panel(ax, t, keep, vals: dict, order) -> None:
    """Each method's simulated - measured voltage, with its MAE in the legend; values
    beyond the axis are drawn at its edge and said."""
    worst = max(float(np.percentile(np.abs(v.error_v[keep]), 99.5)) for v in vals.values())
    lim = max(20.0, worst * 1e3 * 1.2)
    beyond, peak = 0, 0.0
    for k, m in enumerate(order):
        err = vals[m].error_v[keep] * 1e3
        beyond += int(np.sum(np.abs(err) > lim))
        peak = max(peak, float(np.max(np.abs(err))))
        lab = (f"{m.upper() or 'simulated'}: MAE {vals[m].overall.mae_v * 1e3:.1f} mV")
        ax.plot(*_trace(t, np.clip(err, -lim, lim)), color=method_colour(m, k), lw=0.4,
                label=lab)
    ax.set_ylim(-lim * 1.05, lim * 1.05)
    ax.set_ylabel("simulated -\nmeasured [mV]")
    ax.grid(alpha=0.3)
    _thick(ax.legend(loc="lower left", fontsize=7, ncol=len(order)))
    if beyond:
        ax.text(0.99, 0.97, f"{beyond} samples beyond ±{lim:.0f} mV drawn at the edge "
                f"(largest {peak:.0f} mV)", transform=ax.transAxes, ha="right", va="top",
                fontsize=7, bbox=dict(fc="white", ec="0.7", alpha=0.9))


PARAMETER_PANELS = (("r0_ohm", "R0 [mΩ]", 1e3), ("r_fast_ohm", "R fast [mΩ]", 1e3),
                    ("tau_fast_s", "τ fast [s]", 1.0), ("r_slow_ohm", "R slow [mΩ]", 1e3),
                    ("tau_slow_s", "τ slow [s]", 1.0), ("r_diff_ohm", "R diff [mΩ]", 1e3),
                    ("tau_diff_s", "τ diff [s]", 1.0), ("i0_a", "i0 [A]", 1.0))


def plot_parameters(model, path, temperatures_c=None, derived_c=(), title: str = "",
                    flagged=()):
    """Each parameter of the discharge table over SOC, one line per temperature (the
    given ``temperatures_c``, default the table rows; ``derived_c`` dashed), and the OCV.
    ``flagged``: (parameter, temperature, SOC, why) of table values the quality checks
    flag, ringed in red."""
    plt = _plt()
    table = model.discharge
    keys = [(k, lab, sc) for k, lab, sc in PARAMETER_PANELS
            if k in RC_NAMES or getattr(table, k) is not None]
    temps = list(table.temperature_c if temperatures_c is None else temperatures_c)
    fig, axes, cols = _panels(plt, len(keys) + 1)
    soc = np.linspace(0.0, 1.0, 101)
    # nodes the fit measured (filled) or held / interpolated (open); values <= 0 red
    measured = np.asarray(table.converged).any(axis=0)
    lines = [*temps, *derived_c]
    for t, colour in zip(lines, temperature_colours(plt, lines)):
        tt = None if not np.isfinite(t) or not model.needs_temperature else float(t)
        style = "--" if t in derived_c else "-"
        label = "one temperature" if tt is None and not np.isfinite(t) else f"{t:.1f} °C" + (
            " (derived)" if t in derived_c else "")
        p = table.at(soc, tt)
        nodes = table.at(table.soc, tt)
        for ax, (k, _, sc) in zip(axes, keys):
            ax.plot(soc * 100, np.broadcast_to(p[k], soc.shape) * sc, style, color=colour,
                    lw=1.4, label=label)
            _mark_nodes(ax, table.soc, np.broadcast_to(nodes[k], table.soc.shape) * sc,
                        measured, colour)
        ocv_t = tt if model.ocv.n_temperatures > 1 else None
        axes[len(keys)].plot(soc * 100, model.ocv.ocv_at(soc, ocv_t), style, color=colour,
                             lw=1.4)
    _mark_flagged(axes, keys, table, flagged, model.needs_temperature)
    for ax, (_, lab, _) in zip(axes, [*keys, ("ocv", "OCV [V]", 1.0)]):
        ax.set_ylabel(lab, fontsize=8)
        ax.set_xlabel("SOC [%]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    _legend_beside(fig, axes[0], len(keys) + 1, flagged)
    what = (f"{model.method} model: discharge parameters over SOC at "
            + (", ".join(degrees(t) for t in temps) if model.needs_temperature
               else "one temperature")
            + (f", derived (dashed) at {', '.join(degrees(t) for t in derived_c)}"
               if derived_c else ""))
    fig.suptitle(title or what + "\n(filled: nodes the fit measured, open: held, "
                 "red x: <= 0, red ring: flagged by the table checks)", fontsize=10)
    _panel_layout(fig)
    save_png(fig, path)
    plt.close(fig)
    return path


def _legend_beside(fig, ax, n_panels: int, flagged) -> None:
    """The temperature legend in the first spare panel of the grid (off the data), else
    beside the figure's top right corner."""
    handles, labels = ax.get_legend_handles_labels()
    if flagged:
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], **FLAGGED))
        labels.append("flagged: " + "; ".join(sorted({f[3] for f in flagged})))
    spare = fig.axes[n_panels] if len(fig.axes) > n_panels else None
    if spare is not None:
        spare.legend(handles, labels, loc="center", fontsize=8, frameon=False)
    else:
        fig.legend(handles, labels, loc="upper right", fontsize=7)


def _mark_flagged(axes, keys, table, flagged, over_temperature: bool) -> None:
    """Ring each flagged table value (parameter, temperature, SOC, why) in red."""
    where = {k: ax for ax, (k, _, _) in zip(axes, keys)}
    scale = {k: sc for k, _, sc in keys}
    for name, t, s, _ in flagged:
        if name not in where or not np.isfinite(s):
            continue
        tt = float(t) if over_temperature and np.isfinite(t) else None
        v = float(np.broadcast_to(table.at(np.array([s]), tt)[name], (1,))[0])
        where[name].plot([s * 100], [v * scale[name]], **FLAGGED)


def _mark_nodes(ax, soc, values, measured, colour):
    """The table's SOC nodes on a parameter's line: filled where measured, open where
    held flat or interpolated, a red cross where the value is not positive."""
    x = soc * 100
    ax.plot(x[measured], values[measured], "o", ms=3, color=colour)
    ax.plot(x[~measured], values[~measured], "o", ms=3, mfc="none", color=colour)
    bad = values <= 0
    if bad.any():
        ax.plot(x[bad], values[bad], "x", ms=6, color="red")


def plot_ocv(inputs, path: Path, at: str = "") -> Path:
    """The chosen OCV, what each source was made of (low-rate branches, table points)
    and the pulse test's rested voltages; below, their difference from the OCV."""
    plt = _plt()
    report = inputs.ocv_report
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 7), sharex=True,
                                 gridspec_kw={"height_ratios": [3, 1]})
    ocv = inputs.ocv
    colour = 1
    for c in report.curves if report is not None else ():
        for label, soc, v in c.raw:
            if label == "rests":
                continue
            style = dict(ms=6, marker="s", ls="none") if np.size(soc) < 3 else dict(lw=0.8)
            a1.plot(soc * 100, v, color=f"C{colour}", alpha=0.8, label=f"{c.name}: {label}",
                    **style)
            a2.plot(soc * 100, (v - ocv.ocv_at(soc)) * 1e3, color=f"C{colour}",
                    **(dict(lw=0.6) if np.size(soc) >= 3 else style))
            colour += 1
    if report is not None and report.rests_soc is not None:
        a1.plot(report.rests_soc * 100, report.rests_v, "k.", ms=4,
                label="rested voltages of the pulse test")
        a2.plot(report.rests_soc * 100, (report.rests_v - ocv.ocv_at(report.rests_soc)) * 1e3,
                "k.", ms=4)
    a1.plot(ocv.soc * 100, ocv.ocv_v, "C0", lw=1.6, label="OCV (model)")
    _mark_held_flat(a1, a2, report)
    title = "OCV" + (f" at {at}" if at else "")
    title += (" from " + " + ".join("the pulse test's rests" if s == "pulses" else s
                                    for s in report.sources)) if report is not None else ""
    if report is not None and report.check is not None:
        title += f"  (vs pulse rests: {report.check.rms_v * 1e3:.1f} mV RMS)"
    a1.set_title(title, fontsize=10)
    a1.set_ylabel("voltage [V]")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=7, loc="lower right")
    a2.axhline(0.0, color="C0", lw=1)
    a2.set_ylabel("measured - OCV [mV]")
    a2.set_xlabel("SOC [%]")
    a2.set_ylim(-60, 60)
    a2.grid(alpha=0.3)
    _stack_layout(fig, 0.75, 0.15, hspace=0.07)
    save_png(fig, path)
    plt.close(fig)
    return path


def _mark_held_flat(a1, a2, report) -> None:
    """Shade the SOC beyond every source's measured span, where the OCV is held flat."""
    if report is None or not report.curves:
        return
    lo = min(c.span[0] for c in report.curves)
    hi = max(c.span[1] for c in report.curves)
    label = "held flat (not measured)"
    for a, b in ((0.0, lo), (hi, 1.0)):
        if b - a > 1e-3:
            a1.axvspan(a * 100, b * 100, color="0.88", zorder=0, label=label)
            a2.axvspan(a * 100, b * 100, color="0.88", zorder=0)
            label = None


RC_NAMES = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")


def _png(draw, *args, **kw) -> bytes:
    """What ``draw(..., path)`` writes, as PNG bytes (drawn where the data is: a worker
    process sends back bytes, not the data)."""
    import matplotlib

    buf = io.BytesIO()
    # each title at the top of its axes, where matplotlib's automatic placement leaves it
    # in these plots (no x tick labels on top, no y offset text under a title), without
    # measuring every axis for it at each draw: a fifth of a plot's time, same pixels
    with matplotlib.rc_context({"axes.titley": 1.0}):
        draw(*args, buf, **kw)
    return buf.getvalue()


def fit_pngs(raw: dict, suffix: str = "", progress=None, at: str = "") -> dict[str, bytes]:
    """The fit plots of one pulse test's raw fits: dcir-fit{suffix}.png (five-point fits)
    and curve-fit{suffix}.png (whole-curve fit)."""
    out = {}
    if raw.get("point_fits") and raw.get("point_table") is not None:
        out[f"dcir-fit{suffix}.png"] = _png(plot_dcir_fits, raw["point_table"],
                                            raw["point_fits"], at=at)
    if raw.get("curve_fit") is not None:
        out[f"curve-fit{suffix}.png"] = _png(plot_curve_fits, raw["curve_fit"], at=at)
    return out


def pulse_test_degrees(inputs) -> str:
    """The pulse test's median cell temperature for a title ('' when it has none)."""
    series = getattr(inputs, "pulses_series", None)
    temp = None if series is None else series.temperature_c
    return "" if temp is None or not np.size(temp) else degrees(float(np.nanmedian(temp)))


def ocv_png(inputs, progress=None, at: str = "") -> bytes:
    """ocv.png: the OCV of a build, its sources and the pulse test's rests."""
    return _png(plot_ocv, inputs, at=at)


def derived_rows(model, measured_c) -> tuple[float, ...]:
    """The temperature rows of ``model`` that were derived, not measured, as its notes
    say: the warm row above the measured temperatures ``measured_c`` and, for a model
    from one pulse test, the cold row below (the grid between rows is resampled, not
    derived)."""
    if not measured_c:
        return ()
    one = any("derived from one pulse test" in n for n in model.notes)
    warm = one or any("derived warm row" in n for n in model.notes)
    rows = np.asarray(model.discharge.temperature_c, dtype=float)
    cold = rows[rows < min(measured_c) - 0.5][:1] if one else ()
    hot = rows[rows > max(measured_c) + 0.5][-1:] if warm else ()
    return tuple(float(x) for x in (*cold, *hot))


def parameters_png(model, measured_c=None, progress=None) -> bytes:
    """parameters-<method>.png: the parameters over SOC at each measured temperature (the
    pulse tests'; default the table rows) and, dashed, the derived rows if any; the
    discharge values the table checks flag (roughest node of a rough row) ringed."""
    from ..fit.quality import ROUGHNESS_LIMIT, model_quality

    derived = derived_rows(model, measured_c)
    flagged = tuple((t.name, t.temperature_c, t.roughest_soc, f"rough > {ROUGHNESS_LIMIT:g}")
                    for t in model_quality(model, ()).tables
                    if t.direction == "discharge" and t.roughness > ROUGHNESS_LIMIT)
    return _png(plot_parameters, model, temperatures_c=measured_c, derived_c=derived,
                flagged=flagged)


def validation_png(vals: dict, label: str, best: str = "", progress=None) -> bytes:
    """validation-<cycle>.png: every method's model on one cycle."""
    tr = next(iter(vals.values())).temperature_range_c
    where = "" if tr is None else f", cell {tr[0]:.1f}..{tr[1]:.1f} °C over the drive"
    title = f"Validation on {label}{where}"
    if len(vals) == 1 and "" in vals:
        v = vals[""].overall
        title += (f": MAE {v.mae_v * 1e3:.1f} mV, RMSE {v.rmse_v * 1e3:.1f} mV, "
                  f"max {v.max_abs_v * 1e3:.0f} mV")
    return _png(plot_validations, vals, title=title, best=best)
