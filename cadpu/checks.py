"""Checks of the arrays the model package's functions take, raising errors that name the caller."""

from __future__ import annotations

import numpy as np


def check_finite_points(caller: str, points: np.ndarray) -> None:
    """ValueError naming `caller` and how many points (rows along the last axis) hold a NaN or
    infinite coordinate, when any does.

    Args:
        caller: the function the error names. points: (..., 3) coordinates.
    """
    if np.isfinite(points).all():
        return
    bad = int((~np.isfinite(points)).any(axis=-1).sum())
    raise ValueError(f"{caller}: {bad} point{'s' if bad != 1 else ''} with NaN or infinite coordinates")
