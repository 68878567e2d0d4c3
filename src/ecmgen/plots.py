"""PNG plots of a build: DC-IR points with fitted curves (paper Fig. 4), and measured vs
simulated voltage with the error trace (paper Figs. 5-6)."""

from __future__ import annotations

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
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_curve_fits(curve_fit, path: Path) -> Path:
    """Whole-curve fit: measured vs fitted voltage change over each pulse + relaxation."""
    plt = _plt()
    fig, axes, _ = _panels(plt, len(curve_fit.soc))
    for k, ax in enumerate(axes):
        for t, meas, fit in curve_fit.windows[k]:
            ax.plot(t, meas * 1e3, "k", lw=0.6)
            ax.plot(t, fit * 1e3, "r", lw=0.8)
        ax.set_xscale("symlog", linthresh=10)
        ax.set_title(f"{curve_fit.direction[k]} SOC {curve_fit.soc[k] * 100:.0f} % "
                     f"rms {curve_fit.rms_error_v[k] * 1e3:.1f} mV", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("ΔV [mV]")
    fig.suptitle("Whole-curve fit: measured (black) vs fitted (red) pulse + relaxation")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_validation(val, path: Path, title: str = "") -> Path:
    """Measured vs simulated voltage, and the error trace with the simulated SOC."""
    plt = _plt()
    t = val.sim.time_s
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 6), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
    a1.plot(t, val.measured_v, "k", lw=0.4, label="measured")
    a1.plot(t, val.sim.voltage_v, "C1", lw=0.4, label="simulated")
    a1.set_ylabel("voltage [V]")
    a1.legend(loc="upper right")
    a1.set_title(title or f"{val.source}: MAE {val.overall.mae_v * 1e3:.1f} mV, "
                          f"RMSE {val.overall.rmse_v * 1e3:.1f} mV, "
                          f"max {val.overall.max_abs_v * 1e3:.0f} mV")
    a2.plot(t, val.error_v * 1e3, "C3", lw=0.3)
    a2.set_ylabel("sim - meas [mV]")
    a2.set_xlabel("time [s]")
    lim = max(20.0, float(np.percentile(np.abs(val.error_v), 99.5)) * 1e3 * 1.2)
    a2.set_ylim(-lim, lim)
    a2.grid(alpha=0.3)
    b = a2.twinx()
    b.plot(t, val.sim.soc * 100, "C0", lw=0.8)
    b.set_ylabel("SOC [%]", color="C0")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_build_plots(result, out_dir: Path) -> list[Path]:
    out = []
    if result.point_fits and result.point_table is not None:
        out.append(plot_dcir_fits(result.point_table, result.point_fits, out_dir / "dcir-fit.png"))
    if result.curve_fit is not None:
        out.append(plot_curve_fits(result.curve_fit, out_dir / "curve-fit.png"))
    for method, vals in result.validations.items():
        for name, val in vals.items():
            stem = Path(name).stem
            out.append(plot_validation(val, out_dir / f"validation-{method}-{stem}.png",
                                       f"{method.upper()} on {name}: MAE "
                                       f"{val.overall.mae_v * 1e3:.1f} mV, RMSE "
                                       f"{val.overall.rmse_v * 1e3:.1f} mV, max "
                                       f"{val.overall.max_abs_v * 1e3:.0f} mV"))
    return out
