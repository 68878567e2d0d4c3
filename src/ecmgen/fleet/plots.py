"""The fleet's trend plots: each figure of the fleet table against the check-up axis, one
line per cell, outliers circled red (the house style of ecmgen.plots.style).

``trends-<T>.png`` per temperature point: the capacity, each parameter at each SOC
point, the OCV at each SOC point and the validation MAE; ``trends-summary-<T>.png`` the
capacity, R0 at the middle SOC point and the MAE, for a page. Each figure says at which
temperature its values are: the temperature point, or for one-temperature models the
range of temperatures their pulse tests were measured at.
"""

from __future__ import annotations

import datetime as dt
import io
from pathlib import Path

import numpy as np

from ..files import write_atomic
from ..plots.style import FLAGGED, _panels, _plt
from .table import PARAMETERS, column, temperature_tag

LABELS = {"r0_ohm": ("R0", "mΩ", 1e3), "r_fast_ohm": ("R_fast", "mΩ", 1e3),
          "r_slow_ohm": ("R_slow", "mΩ", 1e3), "tau_fast_s": ("τ_fast", "s", 1.0),
          "tau_slow_s": ("τ_slow", "s", 1.0), "ocv_v": ("OCV", "V", 1.0)}


def checkup_axis(table: list[dict]) -> tuple[list[float], str]:
    """The x of each row and the axis label: the cycle count where every row has one,
    else the throughput, else days since the first date, else the check-up (its number
    where every check-up is a number, else its order of first appearance)."""
    for key, label in (("cycles", "equivalent full cycles"), ("throughput_ah",
                                                              "charge throughput [Ah]")):
        if table and all(d.get(key) is not None for d in table):
            return [float(d[key]) for d in table], label
    if table and all(d.get("date") for d in table):
        days = [dt.date.fromisoformat(d["date"]) for d in table]
        return [float((x - min(days)).days) for x in days], "days since the first check-up"
    try:
        return [float(d["checkup"]) for d in table], "check-up"
    except ValueError:
        order = list(dict.fromkeys(d["checkup"] for d in table))
        return [float(order.index(d["checkup"])) for d in table], "check-up (in order)"


def where_words(table: list[dict], temperature_c: float, over_temperature: bool) -> str:
    if over_temperature:
        return f"at {temperature_c:g} °C"
    temps = [d["pulses_temperature_c"] for d in table if d.get("pulses_temperature_c")
             is not None]
    if not temps:
        return "at the tests' temperature (not logged)"
    lo, hi = min(temps), max(temps)
    span = f"{lo:.1f} °C" if hi - lo < 0.05 else f"{lo:.1f}..{hi:.1f} °C"
    return f"at the tests' temperature ({span}; one-temperature models)"


def _panels_for(soc_points, temperature_c: float, summary: bool) -> list[tuple]:
    """(column, title, unit, scale) per panel."""
    out = [("capacity_ah", "capacity from the tests", "Ah", 1.0)]
    mid = soc_points[len(soc_points) // 2]
    params = ["r0_ohm"] if summary else list(PARAMETERS) + ["ocv_v"]
    points = [mid] if summary else list(soc_points)
    for p in params:
        name, unit, scale = LABELS[p]
        for s in points:
            out.append((column(p, s, temperature_c), f"{name} at SOC {100 * s:.0f} %",
                        unit, scale))
    out.append(("validation_mae_mv", "validation MAE (largest cycle)", "mV", 1.0))
    return out


def trend_png(table: list[dict], path: Path, soc_points, temperature_c: float,
              over_temperature: bool, summary: bool = False) -> Path | None:
    """One figure (see the module doc); None when the table is empty."""
    if not table:
        return None
    plt = _plt()
    x, xlabel = checkup_axis(table)
    panels = [p for p in _panels_for(soc_points, temperature_c, summary)
              if any(d.get(p[0]) is not None for d in table)]
    fig, axes, cols = _panels(plt, len(panels))
    cells = list(dict.fromkeys(d["cell"] for d in table))
    colours = _cell_colours(plt, len(cells))
    for k, (ax, (col, title, unit, scale)) in enumerate(zip(axes, panels)):
        for c, colour in zip(cells, colours):
            pts = sorted((xi, d[col] * scale, col in d["outliers"].split(";"))
                         for xi, d in zip(x, table) if d["cell"] == c and d.get(col) is not None)
            if not pts:
                continue
            xs, ys, flagged = (np.array(v) for v in zip(*pts))
            ax.plot(xs, ys, "o-", color=colour, lw=1.0, ms=3,
                    label=c if len(cells) <= 10 else None)
            if flagged.any():
                ax.plot(xs[flagged], ys[flagged], **FLAGGED)
        ax.set_title(title, fontsize=9)
        ax.set_ylabel(f"[{unit}]", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if k + cols >= len(panels):
            ax.set_xlabel(xlabel, fontsize=8)
    if len(cells) <= 10:
        axes[0].legend(fontsize=6, ncol=2)
    fig.suptitle(f"Fleet of {len(cells)} cells against the check-ups, "
                 f"{where_words(table, temperature_c, over_temperature)}\none line per "
                 "cell, discharge tables, red circles: outliers", fontsize=9)
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.6 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.7 / h,
                        wspace=0.42, hspace=0.55)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
    return path


def _cell_colours(plt, n: int) -> list:
    if n <= 10:
        return [f"C{k}" for k in range(n)]
    cmap = plt.get_cmap("viridis")
    return [cmap(k / max(n - 1, 1)) for k in range(n)]


def trend_pngs(table: list[dict], out: Path, soc_points, temperatures_c,
               over_temperature: bool) -> list[Path]:
    """Every trend figure into ``out`` (staged by the caller); returns the paths."""
    written = []
    for t in temperatures_c:
        tag = temperature_tag(t) if over_temperature else "tests"
        for summary, name in ((False, f"trends-{tag}.png"), (True, f"trends-summary-{tag}.png")):
            p = trend_png(table, out / name, soc_points, t, over_temperature, summary)
            if p is not None:
                written.append(p)
        if not over_temperature:
            break           # one-temperature models: the same figure at every point
    return written
