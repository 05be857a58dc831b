"""Plots of a training run's logs: loss terms per step (`plot_log`)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def plot_log(log_path: Path, png_path: Path) -> None:
    """Plot every loss column of a training log against the step (smoothed) into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(log_path.open()))
    if not rows:
        return
    steps = np.array([int(r["step"]) for r in rows])
    terms = ("emd", "regularizer", "adversarial", "discriminator")
    figure, axes = plt.subplots(1, len(terms), figsize=(4 * len(terms), 3))
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
