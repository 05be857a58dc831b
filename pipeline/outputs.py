"""Reading a run's output folder back: what `kitti-pu info` prints."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.parquet as pq

from .config import ConfigError


def parquet_files(out_dir: Path) -> list[Path]:
    """Every frame's Parquet file under `out_dir`, sorted by path: as pyarrow and pandas read the
    Hive folder, names under `points/` starting with "." or "_" (temporaries, metadata) are not
    frames."""
    points = Path(out_dir) / "points"
    return sorted(path for path in points.glob("**/*.parquet")
                  if not any(part.startswith((".", "_")) for part in path.relative_to(points).parts))


def describe_output(out_dir: Path) -> str:
    """A text report of an output folder: per sequence, frames, points and generated points
    (from the Parquet footers, without reading the data), then the last run's summary line.

    Raises ConfigError when `out_dir` holds no kitti-pu output.
    """
    out_dir = Path(out_dir)
    files = parquet_files(out_dir)
    summary_path = out_dir / "summary.json"
    if not files and not summary_path.is_file():
        raise ConfigError(f"info: {out_dir} holds no kitti-pu output (no points/**/*.parquet, no summary.json)")
    per_sequence: dict[tuple[str, str], list[int]] = {}
    for path in files:
        footer = pq.read_metadata(path)
        meta = {k.decode(): v.decode() for k, v in (footer.metadata or {}).items() if not k.startswith(b"ARROW")}
        key = (meta.get("dataset", "?"), meta.get("sequence", "?"))
        counts = per_sequence.setdefault(key, [0, 0, 0])
        counts[0] += 1
        counts[1] += footer.num_rows
        counts[2] += int(meta.get("generated_points", 0))
    lines = [f"{'dataset':<10} {'sequence':<32} {'frames':>7} {'points':>12} {'generated':>12}"]
    for (dataset, sequence), (frames, points, generated) in sorted(per_sequence.items()):
        lines.append(f"{dataset:<10} {sequence:<32} {frames:>7} {points:>12} {generated:>12}")
    if summary_path.is_file():
        last = json.loads(summary_path.read_text())
        lines.append(
            f"last run: done {last['frames_done']}, skipped {last['frames_skipped']}, failed "
            f"{last['frames_failed']} of {last['frames_total']} frames in {last['wall_seconds']} s "
            f"(exit {last['exit_code']}, ratio {last['ratio']}, model {last['model_checksum'][:12]})"
        )
        for frame in last["frames"]:
            if frame["status"] == "failed":
                lines.append(f"  failed {frame['key']}: {frame['error']}")
    return "\n".join(lines)
