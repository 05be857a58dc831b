"""The picture of one scan of the 16-to-64-beam evaluation: the input, some methods' outputs and
the full scan, from above and from the front."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .methods import INPUT, MIDPOINT, RANGE_IMAGE, NETWORK

#: Half width of the bird's-eye crop of the figure, metres (a 40 x 40 m square round the sensor).
FIGURE_HALF_WIDTH = 20.0
MAX_PLOTTED = 120_000


@dataclass(frozen=True)
class ScanOutputs:
    """One scan's clouds, kept for the figure: full (N, 3), its ground mask (N,), the 16-ring input
    (M, 3) and every method's output (Q, 3), all sensor frame, metres."""

    key: str
    full: np.ndarray
    full_ground: np.ndarray
    input: np.ndarray
    outputs: dict[str, np.ndarray]


def render_figure(clouds: ScanOutputs, path: Path, methods: tuple[str, ...] = (RANGE_IMAGE, MIDPOINT, NETWORK),
                  half_width: float = FIGURE_HALF_WIDTH) -> Path:
    """PNG of one scan: the 16-ring input, the outputs of `methods` and the full 64-ring scan.

    Top row: bird's-eye view of a 2 * half_width square round the sensor, coloured by height.
    Bottom row: front view (azimuth within +-45 degrees of straight ahead against elevation, left
    on the left), coloured by log range, which shows the rings each method adds.

    Returns:
        `path`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(INPUT, clouds.input)] + [(m, clouds.outputs[m]) for m in methods if m in clouds.outputs]
    panels.append(("full 64-ring scan", clouds.full))
    figure, axes = plt.subplots(2, len(panels), figsize=(5.2 * len(panels), 9.5), dpi=110, squeeze=False)
    for column, (label, cloud) in enumerate(panels):
        _bird_eye(axes[0, column], np.asarray(cloud, dtype=np.float64), half_width, f"{label}\n{len(cloud):,} points")
        _front_view(axes[1, column], np.asarray(cloud, dtype=np.float64))
    figure.suptitle(f"16-to-64-beam evaluation: {clouds.key}")
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path


def _subsample(cloud: np.ndarray) -> np.ndarray:
    if len(cloud) <= MAX_PLOTTED:
        return cloud
    return cloud[np.random.default_rng(0).choice(len(cloud), MAX_PLOTTED, replace=False)]


def _bird_eye(axis, cloud: np.ndarray, half_width: float, title: str) -> None:
    inside = (np.abs(cloud[:, 0]) < half_width) & (np.abs(cloud[:, 1]) < half_width)
    crop = _subsample(cloud[inside])
    axis.scatter(crop[:, 0], crop[:, 1], s=0.08, c=crop[:, 2], cmap="viridis", vmin=-2.0, vmax=2.0, linewidths=0)
    axis.set_xlim(-half_width, half_width)
    axis.set_ylim(-half_width, half_width)
    axis.set_aspect("equal")
    axis.set_title(title)
    axis.set_xlabel("x (m, forward)")
    axis.set_ylabel("y (m, left)")


def _front_view(axis, cloud: np.ndarray) -> None:
    distance = np.linalg.norm(cloud[:, :3], axis=1)
    azimuth = np.degrees(np.arctan2(cloud[:, 1], cloud[:, 0]))
    elevation = np.degrees(np.arcsin(np.clip(cloud[:, 2] / np.maximum(distance, 1e-9), -1.0, 1.0)))
    ahead = np.abs(azimuth) < 45.0
    points = _subsample(np.column_stack([-azimuth[ahead], elevation[ahead], distance[ahead]]))
    axis.scatter(points[:, 0], points[:, 1], s=0.3, c=np.log(np.maximum(points[:, 2], 1.0)), cmap="turbo",
                 vmin=np.log(2.0), vmax=np.log(60.0), linewidths=0)
    axis.set_xlim(-45.0, 45.0)
    axis.set_ylim(-26.0, 4.0)
    axis.set_xlabel("azimuth (deg, left is left)")
    axis.set_ylabel("elevation (deg)")
