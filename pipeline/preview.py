"""PNG previews of a frame before and after densification: bird's-eye and perspective views."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

from stages.temporaries import replace_atomically  # noqa: E402

MAX_PLOTTED = 150_000


def _subsample(points: np.ndarray, limit: int, seed: int = 0) -> np.ndarray:
    if points.shape[0] <= limit:
        return points
    keep = np.random.default_rng(seed).choice(points.shape[0], limit, replace=False)
    return points[np.sort(keep)]


def _crop(points: np.ndarray, half_width_m: float) -> np.ndarray:
    inside = (np.abs(points[:, 0]) < half_width_m) & (np.abs(points[:, 1]) < half_width_m)
    return points[inside]


def _perspective(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole projection from a virtual camera behind and above the sensor, looking forward."""
    eye = np.array([-8.0, 0.0, 6.0])
    pitch = np.deg2rad(20.0)
    rel = xyz - eye
    forward = rel[:, 0] * np.cos(pitch) - rel[:, 2] * np.sin(pitch)
    up = rel[:, 0] * np.sin(pitch) + rel[:, 2] * np.cos(pitch)
    visible = forward > 1.0
    u = -rel[visible, 1] / forward[visible]
    v = up[visible] / forward[visible]
    return u, v, forward[visible]


def render_preview(before: np.ndarray, after: np.ndarray, png_path: Path, title: str = "",
                   after_generated: np.ndarray | None = None, half_width_m: float = 30.0) -> Path:
    """Render a 2 x 2 figure: bird's-eye and perspective views of a scan before and after.

    Args:
        before: (N, 3+) input points, sensor frame, metres.
        after: (M, 3+) output points, sensor frame, metres.
        png_path: where to write the PNG.
        title: figure title (e.g. the frame key).
        after_generated: optional (M,) bool; generated points are drawn in a second colour.
        half_width_m: the bird's-eye views show |x|, |y| below this.

    Returns:
        `png_path`.
    """
    png_path = Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    flags = np.zeros(after.shape[0], bool) if after_generated is None else np.asarray(after_generated)
    after_with_flag = np.column_stack([after[:, :3], flags.astype(float)])
    panels = [
        ("before", _subsample(before[:, :3], MAX_PLOTTED)),
        ("after", _subsample(after_with_flag, MAX_PLOTTED)),
    ]
    figure, axes = plt.subplots(2, 2, figsize=(14, 11), dpi=110)
    for column, (label, points) in enumerate(panels):
        count = before.shape[0] if label == "before" else after.shape[0]
        bev = _crop(points, half_width_m)
        colour = bev[:, 2] if label == "before" or bev.shape[1] < 4 else np.where(bev[:, 3] > 0, 1.0, 0.0)
        axes[0, column].scatter(bev[:, 0], bev[:, 1], s=0.05, c=colour, cmap="viridis", linewidths=0)
        axes[0, column].set_aspect("equal")
        axes[0, column].set_title(f"{label}: bird's-eye, {count:,} points")
        axes[0, column].set_xlabel("x (m, forward)")
        axes[0, column].set_ylabel("y (m, left)")
        u, v, depth = _perspective(points[:, :3])
        axes[1, column].scatter(u, v, s=0.05, c=np.log(depth), cmap="magma_r", linewidths=0)
        axes[1, column].set_xlim(-1.5, 1.5)
        axes[1, column].set_ylim(-0.9, 0.6)
        axes[1, column].set_title(f"{label}: perspective")
        axes[1, column].set_xticks([])
        axes[1, column].set_yticks([])
    if after_generated is not None:
        axes[0, 1].set_title(axes[0, 1].get_title() + " (yellow: generated)")
    figure.suptitle(title)
    figure.tight_layout()
    try:
        replace_atomically(png_path, lambda temporary: figure.savefig(temporary, format="png"))
    finally:
        plt.close(figure)
    return png_path


def preview_parquet(parquet_path: Path, png_path: Path) -> Path:
    """Render the preview of one output frame from its Parquet file alone.

    The "before" cloud is the rows that are not generated (the input scan as read), the "after"
    cloud is every row.
    """
    table = pq.read_table(parquet_path, columns=["x", "y", "z", "generated"])
    xyz = np.column_stack([table.column(name).to_numpy() for name in ("x", "y", "z")])
    generated = table.column("generated").to_numpy(zero_copy_only=False)
    return render_preview(xyz[~generated], xyz, png_path, title=str(Path(parquet_path).name),
                          after_generated=generated)


def _is_points_folder(folder: Path) -> bool:
    """A kitti-pu output's `OUT/points`: named so, beside the run's summary or ply/ folder, or
    holding dataset folders (`stages.write`'s layout points/DATASET/SEQUENCE/N.parquet)."""
    if folder.name != "points":
        return False
    beside = (folder.parent / "summary.json").is_file() or (folder.parent / "ply").is_dir()
    return beside or any((folder / dataset).is_dir() for dataset in ("raw", "odometry", "bin"))


def hive_folder(path: Path) -> Path | None:
    """The data folder of a kitti-pu output (`OUT/points`) that the file `path` (existing or not)
    lies in, at any depth, or None: readers of `OUT/points` take every file there for data."""
    for folder in Path(path).resolve().parents:
        if _is_points_folder(folder):
            return folder
    return None


def default_png_path(parquet_path: Path) -> Path:
    """Where `kitti-pu preview` puts a frame's PNG: for `OUT/points/D/S/N.parquet`,
    `OUT/preview/D/S/N.png` (never inside the data folder, where readers would take it for data);
    for any other Parquet file, `N.png` in the current folder."""
    parquet_path = Path(parquet_path)
    sequence, dataset = parquet_path.parent, parquet_path.parent.parent
    if _is_points_folder(dataset.parent):
        return dataset.parent.parent / "preview" / dataset.name / sequence.name / f"{parquet_path.stem}.png"
    return Path(f"{parquet_path.stem}.png")
