"""Reading a run's output folder back (kept for its importers; the code is in `pipeline.info`)."""

from __future__ import annotations

from pathlib import Path

from .info import folder_info, format_info, parquet_files

__all__ = ["describe_output", "parquet_files"]


def describe_output(out_dir: Path) -> str:
    """The text report of an output folder that `kitti-pu info` prints (`pipeline.info`).

    Raises ConfigError when `out_dir` holds no kitti-pu output.
    """
    return format_info(folder_info(out_dir))
