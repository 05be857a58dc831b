"""The embedded default: a synthetic KITTI raw drive, densified end to end like a real one."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .config import ConfigError, PipelineConfig
from .preflight import installed
from .synthetic_drive import write_synthetic_drive
from .info import parquet_files
from .preview import preview_frame
from .runner import run_pipeline
from .summary import FrameReport, RunSummary


def run_demo(out_dir: Path, config: PipelineConfig, n_frames: int = 3, seed: int = 0,
             progress: bool = True,
             on_report: Callable[[FrameReport], None] | None = None) -> tuple[RunSummary, list[Path]]:
    """Write a synthetic drive under `out_dir/kitti_raw`, run the pipeline on it through pykitti
    into `out_dir/output`, and render a before/after preview of the first frame.

    Args:
        out_dir: folder for the drive, the outputs, the summary and the previews.
        config: settings for everything but input and output locations (which the demo sets).
        n_frames: frames in the synthetic drive.
        seed: seed of the synthetic street and sensor noise.
        progress, on_report: as `pipeline.runner.run_pipeline`'s.

    Returns:
        The run's summary and the preview PNGs written.

    Raises:
        ConfigError: Open3D, which simulates the LiDAR, is not installed (nothing is written), or
            any of `run_pipeline`'s.
    """
    if not installed("open3d"):
        raise ConfigError('the demo simulates its LiDAR with Open3D, the optional open3d extra: '
                          'pip install "kitti-pu[open3d]"')
    out_dir = Path(out_dir)
    raw_base = out_dir / "kitti_raw"
    write_synthetic_drive(raw_base, n_frames=n_frames, seed=seed)
    demo_config = config.model_copy(
        update={
            "input": config.input.model_copy(update={"path": raw_base, "kind": "raw"}),
            "output": config.output.model_copy(update={"dir": out_dir / "output"}),
        }
    )
    summary = run_pipeline(demo_config, progress=progress, on_report=on_report)
    previews = []
    outputs = parquet_files(out_dir / "output")
    if outputs:
        previews.append(preview_frame(outputs[0], out_dir / "preview" / f"{outputs[0].stem}.png"))
    return summary, previews
