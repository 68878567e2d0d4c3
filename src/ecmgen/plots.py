"""PNG plots of a build: DC-IR points with fitted curves (paper Fig. 4), measured vs
simulated voltage with the error trace and the cell temperature (paper Figs. 5-6), and
each parameter over SOC with one line per temperature."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .plotting import _panels, _plt


def plot_dcir_fits(table, fits: dict, path: Path) -> Path:
    """One panel per SOC level x direction: R(t) points and each method's curve."""
    from .fit.points import curve_r_ohm

    plt = _plt()
    n = len(table)
    fig, axes, cols = _panels(plt, n)
    t_fine = np.linspace(table.t_s[0], table.t_s[-1], 200)
    curves = {m: curve_r_ohm(f, t_fine) for m, f in fits.items()}
    for k, ax in enumerate(axes):
        ax.plot(table.t_s, table.r_ohm[k] * 1e3, "ko", ms=4, label="DC-IR")
        for m, c in curves.items():
            ax.plot(t_fine, c[k] * 1e3, lw=1.2, label=m.upper())
        ax.set_title(f"{table.direction[k]} SOC {table.soc[k] * 100:.0f} %", fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if k % cols == 0:
            ax.set_ylabel("R [mΩ]", fontsize=8)
        if k >= n - cols:
            ax.set_xlabel("t [s]", fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle("DC-IR points and fitted 2RC curves (Aras & Yonel Fig. 4)")
    _panel_layout(fig)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_curve_fits(curve_fit, path: Path) -> Path:
    """Whole-test fit: measured vs fitted voltage over each SOC level's pulses and rests."""
    plt = _plt()
    fig, axes, _ = _panels(plt, len(curve_fit.windows))
    for ax, (soc, direction, rms, parts) in zip(axes, curve_fit.windows):
        for t, meas, fit in parts:
            ax.plot(t, meas, "k", lw=0.6)
            ax.plot(t, fit, "r", lw=0.8)
        ax.set_xscale("symlog", linthresh=10)
        ax.set_title(f"{direction} SOC {soc * 100:.0f} % rms {rms * 1e3:.1f} mV", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("V")
    fig.suptitle("Whole-test fit: measured (black) vs fitted (red), each SOC level")
    _panel_layout(fig)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _panel_layout(fig) -> None:
    """Fixed margins for a grid of panels (_panels: 3.2 x 2.6 in each), much cheaper than
    tight_layout, which draws the figure once more to measure it."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.6 / w, right=1 - 0.15 / w, bottom=0.45 / h, top=1 - 0.5 / h,
                        wspace=0.42, hspace=0.55)


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
    """One cycle, several models (``{name: Validation}``, same record): measured and each
    simulated voltage, each error trace with the simulated SOC, and the cell temperature
    the models ran on (when the record has one)."""
    plt = _plt()
    first = next(iter(vals.values()))
    t = first.sim.time_s
    temp = getattr(first, "temperature_c", None)
    n = 3 if temp is not None else 2
    fig, axes = plt.subplots(n, 1, figsize=(11, 6 + 1.6 * (n - 2)), sharex=True,
                             gridspec_kw={"height_ratios": [2, 1, 0.8][:n]})
    a1, a2 = axes[0], axes[1]
    a1.plot(*_envelope(t, first.measured_v), "k", lw=0.4, label="measured")
    order = sorted(vals, key=lambda m: m == best)        # the best one on top
    for k, m in enumerate(order):
        val = vals[m]
        colour = "C1" if len(vals) == 1 else f"C{k + 1}"
        lab = "simulated" if not m else m.upper()
        a1.plot(*_envelope(t, val.sim.voltage_v), color=colour, lw=0.4, label=lab)
        a2.plot(*_envelope(t, val.error_v * 1e3), color=colour if len(vals) > 1 else "C3",
                lw=0.3)
    a1.set_ylabel("voltage [V]")
    a1.legend(loc="upper right")
    if not title and len(vals) == 1:
        title = (f"{first.source}: MAE {first.overall.mae_v * 1e3:.1f} mV, "
                 f"RMSE {first.overall.rmse_v * 1e3:.1f} mV, "
                 f"max {first.overall.max_abs_v * 1e3:.0f} mV")
    a1.set_title(title)
    a2.set_ylabel("sim - meas [mV]")
    worst = max(float(np.percentile(np.abs(v.error_v), 99.5)) for v in vals.values())
    lim = max(20.0, worst * 1e3 * 1.2)
    a2.set_ylim(-lim, lim)
    a2.grid(alpha=0.3)
    b = a2.twinx()
    b.plot(*_envelope(t, first.sim.soc * 100), "C0", lw=0.8)
    b.set_ylabel("SOC [%]", color="C0")
    if temp is not None:
        a3 = axes[2]
        a3.plot(*_envelope(t, temp), "C2", lw=0.8)
        a3.set_ylabel("cell [°C]")
        a3.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


PARAMETER_PANELS = (("r0_ohm", "R0 [mΩ]", 1e3), ("r_fast_ohm", "R fast [mΩ]", 1e3),
                    ("tau_fast_s", "τ fast [s]", 1.0), ("r_slow_ohm", "R slow [mΩ]", 1e3),
                    ("tau_slow_s", "τ slow [s]", 1.0), ("r_diff_ohm", "R diff [mΩ]", 1e3),
                    ("tau_diff_s", "τ diff [s]", 1.0), ("i0_a", "i0 [A]", 1.0))


def plot_parameters(model, path, temperatures_c=None, derived_c=(), title: str = ""):
    """Each parameter of the discharge table over SOC, one line per temperature (the
    given ``temperatures_c``, default the table rows; ``derived_c`` dashed), and the OCV."""
    plt = _plt()
    table = model.discharge
    keys = [(k, lab, sc) for k, lab, sc in PARAMETER_PANELS
            if k in RC_NAMES or getattr(table, k) is not None]
    temps = list(table.temperature_c if temperatures_c is None else temperatures_c)
    fig, axes, cols = _panels(plt, len(keys) + 1)
    soc = np.linspace(0.0, 1.0, 101)
    # nodes the fit measured (filled) or held / interpolated (open); values <= 0 red
    measured = np.asarray(table.converged).any(axis=0)
    cmap = plt.get_cmap("coolwarm")
    finite = [t for t in temps if np.isfinite(t)]
    lo, hi = (min(finite), max(finite)) if finite else (0.0, 1.0)
    for t in [*temps, *derived_c]:
        tt = None if not np.isfinite(t) or not model.needs_temperature else float(t)
        colour = cmap(0.5 if hi == lo or tt is None else (t - lo) / (hi - lo))
        style = "--" if t in derived_c else "-"
        label = "one temperature" if tt is None and not np.isfinite(t) else f"{t:.1f} °C" + (
            " (derived)" if t in derived_c else "")
        p = table.at(soc, tt)
        nodes = table.at(table.soc, tt)
        for ax, (k, _, sc) in zip(axes, keys):
            ax.plot(soc * 100, np.broadcast_to(p[k], soc.shape) * sc, style, color=colour,
                    lw=1.2, label=label)
            _mark_nodes(ax, table.soc, np.broadcast_to(nodes[k], table.soc.shape) * sc,
                        measured, colour)
        ocv_t = tt if model.ocv.n_temperatures > 1 else None
        axes[len(keys)].plot(soc * 100, model.ocv.ocv_at(soc, ocv_t), style, color=colour,
                             lw=1.2)
    for ax, (_, lab, _) in zip(axes, [*keys, ("ocv", "OCV [V]", 1.0)]):
        ax.set_ylabel(lab, fontsize=8)
        ax.set_xlabel("SOC [%]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title or f"{model.method} model: parameters over SOC per temperature "
                          "(discharge; filled: nodes the fit measured, open: held, red: <= 0)")
    _panel_layout(fig)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _mark_nodes(ax, soc, values, measured, colour):
    """The table's SOC nodes on a parameter's line: filled where measured, open where
    held flat or interpolated, a red cross where the value is not positive."""
    x = soc * 100
    ax.plot(x[measured], values[measured], "o", ms=3, color=colour)
    ax.plot(x[~measured], values[~measured], "o", ms=3, mfc="none", color=colour)
    bad = values <= 0
    if bad.any():
        ax.plot(x[bad], values[bad], "x", ms=6, color="red")


def plot_ocv(inputs, path: Path) -> Path:
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
    title = "OCV: " + " + ".join(report.sources) if report is not None else "OCV"
    if report is not None and report.check is not None:
        title += f"  (vs pulse rests: {report.check.rms_v * 1e3:.1f} mV RMS)"
    a1.set_title(title, fontsize=10)
    a1.set_ylabel("voltage [V]")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=7, loc="lower right")
    a2.axhline(0.0, color="C0", lw=1)
    a2.set_ylabel("minus OCV [mV]")
    a2.set_xlabel("SOC [%]")
    a2.set_ylim(-60, 60)
    a2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


RC_NAMES = ("r0_ohm", "r_fast_ohm", "tau_fast_s", "r_slow_ohm", "tau_slow_s")


def _png(draw, *args, **kw) -> bytes:
    """What ``draw(..., path)`` writes, as PNG bytes (drawn where the data is: a worker
    process sends back bytes, not the data)."""
    buf = io.BytesIO()
    draw(*args, buf, **kw)
    return buf.getvalue()


def fit_pngs(raw: dict, suffix: str = "", progress=None) -> dict[str, bytes]:
    """The fit plots of one pulse test's raw fits: dcir-fit{suffix}.png (five-point fits)
    and curve-fit{suffix}.png (whole-curve fit)."""
    out = {}
    if raw.get("point_fits") and raw.get("point_table") is not None:
        out[f"dcir-fit{suffix}.png"] = _png(plot_dcir_fits, raw["point_table"],
                                            raw["point_fits"])
    if raw.get("curve_fit") is not None:
        out[f"curve-fit{suffix}.png"] = _png(plot_curve_fits, raw["curve_fit"])
    return out


def ocv_png(inputs, progress=None) -> bytes:
    """ocv.png: the OCV of a build, its sources and the pulse test's rests."""
    return _png(plot_ocv, inputs)


def parameters_png(model, measured_c=None, progress=None) -> bytes:
    """parameters-<method>.png: the parameters over SOC at each measured temperature (the
    pulse tests'; default the table rows) and, dashed, the derived warm row if any."""
    derived: tuple = ()
    if measured_c and len(measured_c) > 1 and any("derived warm row" in n for n in model.notes):
        rows = model.discharge.temperature_c
        derived = tuple(float(x) for x in rows[rows > max(measured_c) + 0.5][-1:])
    return _png(plot_parameters, model, temperatures_c=measured_c, derived_c=derived)


def validation_png(vals: dict, label: str, best: str = "", progress=None) -> bytes:
    """validation-<cycle>.png: every method's model on one cycle."""
    title = f"{label}: MAE " + ", ".join(f"{m.upper()} {v.overall.mae_v * 1e3:.1f}"
                                         for m, v in vals.items()) + " mV"
    return _png(plot_validations, vals, title=title, best=best)
