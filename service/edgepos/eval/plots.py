"""PNG line plots for the evaluations. matplotlib is an optional extra (``edgepos[plots]``), imported
lazily with the non-interactive Agg backend so the evaluations run headless."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import ModuleType

import numpy as np


class PlotsUnavailable(RuntimeError):
    """matplotlib is not installed."""


def require_matplotlib() -> ModuleType:
    """matplotlib.pyplot on the Agg backend, or PlotsUnavailable naming the extra to install."""
    try:
        import matplotlib
    except ImportError as exc:
        raise PlotsUnavailable(
            "--plots needs matplotlib, which is not installed: pip install 'edgepos[plots]'"
        ) from exc
    matplotlib.use("Agg")
    from matplotlib import pyplot

    return pyplot


def line_plot(
    path: Path,
    t: np.ndarray,
    series: Mapping[str, np.ndarray],
    title: str,
    ylabel: str,
    ylim: tuple[float, float] | None = None,
) -> Path:
    """One figure of ``series`` (label -> values over ``t`` in seconds) written to ``path`` as PNG.

    ``ylim`` fixes the y axis, e.g. to clip a diverging curve so the others stay readable.
    """
    pyplot = require_matplotlib()
    figure, axes = pyplot.subplots(figsize=(9, 4.8), dpi=110)
    try:
        for label, values in series.items():
            axes.plot(t, values, label=label, linewidth=1.1)
        axes.set_title(title)
        axes.set_xlabel("t (s)")
        axes.set_ylabel(ylabel)
        axes.set_xlim(float(t[0]), float(t[-1]))
        if ylim is not None:
            axes.set_ylim(*ylim)
        axes.grid(True, alpha=0.3)
        axes.legend(loc="best", fontsize="small")
        figure.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(path)
    finally:
        pyplot.close(figure)
    return path


def readable_ylim(series: Mapping[str, np.ndarray], quantile: float = 0.98) -> tuple[float, float]:
    """A y range from 0 to a little above the median, over the series, of each one's ``quantile``: a
    diverging curve is clipped at the top instead of flattening the others."""
    top = float(np.median([np.quantile(values, quantile) for values in series.values()])) * 1.3
    return 0.0, top if top > 0 else 1.0
