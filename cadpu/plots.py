"""Plots of a training run's logs: loss terms per step (`plot_log`)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


#: The loss columns a training log may hold, in the order they are plotted.
LOSS_TERMS = ("emd", "snapped_chamfer", "regularizer", "adversarial", "discriminator")


def plotted_terms(rows: list[dict[str, str]]) -> list[str]:
    """The `LOSS_TERMS` a log's rows hold with at least one finite value (a run of the snapped
    objective logs no EMD; a log begun before a column existed lacks it)."""
    def finite(value: str | None) -> bool:
        try:
            return value is not None and np.isfinite(float(value))
        except ValueError:
            return False

    return [term for term in LOSS_TERMS if any(finite(row.get(term)) for row in rows)]


def plot_log(log_path: Path, png_path: Path) -> None:
    """Plot every loss column of a training log that holds values against the step (smoothed)
    into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(log_path.open()))
    terms = plotted_terms(rows)
    if not rows or not terms:
        return
    steps = np.array([int(r["step"]) for r in rows])
    figure, axes = plt.subplots(1, len(terms), figsize=(4 * len(terms), 3), squeeze=False)
    axes = axes[0]
    for axis, term in zip(axes, terms):
        values = np.array([float(r[term]) for r in rows])
        window = max(1, len(values) // 50)
        smooth = np.convolve(values, np.ones(window) / window, mode="valid")
        axis.plot(steps, values, alpha=0.25)
        axis.plot(steps[window - 1:], smooth)
        axis.set_title(term)
        axis.set_xlabel("step")
    figure.tight_layout()
    figure.savefig(png_path, dpi=80)
    plt.close(figure)
