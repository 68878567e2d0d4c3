"""matplotlib helpers shared by every plot of the package (build plots in
:mod:`ecmgen.plots`, diagnose plots in :mod:`ecmgen.diagnosis.output`): a headless
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
    cols = min(5, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, list(axes.flat[:n]), cols
