"""matplotlib helpers shared by every plot of the package (build plots in
:mod:`ecmgen.plots.figures`, diagnose plots in :mod:`ecmgen.diagnosis.output`): a headless
pyplot, imported only when a plot is drawn, and the panel grid.
"""

from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _panels(plt, n: int):
    """A grid of up to 5 columns for n panels; the spare axes are switched off.
    Returns (fig, axes of the n panels, number of columns)."""
    from matplotlib.ticker import MaxNLocator

    cols = min(5, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax in axes.flat[:n]:
        # at most 5 steps up a panel 2.6 in high (the default takes 7-9 there): each
        # tick is an artist to make and draw, a tenth of a grid plot's time
        ax.yaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))
    return fig, list(axes.flat[:n]), cols


def save_png(fig, path) -> None:
    """``fig`` at 90 dpi; a PNG (a file named .png or without a suffix, or a buffer) with
    zlib level 3: the lossless pixels in two thirds of the default level's time, files a
    few per cent larger."""
    from pathlib import Path

    png = not isinstance(path, (str, Path)) or Path(path).suffix.lower() in ("", ".png")
    fig.savefig(path, dpi=90, **({"pil_kwargs": {"compress_level": 3}} if png else {}))


# the one style of every plot: the measured trace black and on top of every model, each
# fit method its own colour, SOC and cell temperature colours no method uses
MEASURED = dict(color="black", lw=0.5, zorder=5)
METHOD_COLOURS = {"ga": "tab:orange", "lm": "tab:purple", "curve": "tab:red"}
SOC_COLOUR = "tab:blue"
TEMPERATURE_COLOUR = "tab:brown"
FLAGGED = dict(marker="o", ms=9, mfc="none", mec="red", mew=1.4, ls="none")


def method_colour(method: str, k: int = 0) -> str:
    """A fit method's colour (ga, lm, curve), else one of the colours no method uses."""
    return METHOD_COLOURS.get(method, ("tab:red", "tab:cyan", "tab:olive", "tab:pink")[k % 4])


def temperature_colours(plt, temps) -> list:
    """A colour per temperature, cold blue to warm red, none of them pale (the turbo map
    without its dark and light ends); one temperature gets plain blue."""
    finite = [t for t in temps if np.isfinite(t)]
    if len(set(finite)) < 2:
        return ["tab:blue"] * len(temps)
    lo, hi = min(finite), max(finite)
    cmap = plt.get_cmap("turbo")
    return [cmap(0.1 + 0.8 * (t - lo) / (hi - lo)) if np.isfinite(t) else "tab:blue"
            for t in temps]


def degrees(t) -> str:
    """A temperature for a title: '25.7 °C' (empty for none)."""
    return "" if t is None or not np.isfinite(t) else f"{t:.1f} °C"


def break_gaps(t: np.ndarray, *ys: np.ndarray, factor: float = 10.0, min_gap_s: float = 300.0):
    """``t`` and ``ys`` with a NaN after each logging gap (a step ``factor`` times the
    median step and at least ``min_gap_s``: not a rest logged slowly), so that a line is
    not drawn across it."""
    if t.size < 3:
        return (t, *ys)
    dt = np.diff(t)
    gaps = np.flatnonzero(dt > max(min_gap_s, factor * float(np.median(dt))))
    if not gaps.size:
        return (t, *ys)
    at = gaps + 1
    t2 = np.insert(t.astype(float), at, t[gaps] + 0.5 * dt[gaps])
    return (t2, *(np.insert(np.asarray(y, float), at, np.nan) for y in ys))
